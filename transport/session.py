"""The operator and teleoperator processes: handshake, the 1 kHz loop, logs.

**Handshake** (msgpack maps; data packets are msgpack arrays, so the two never mix up):

1. operator -> TO ``hello``: session id, codec, DoF, b, range, scenario, duration, and the operator's
   monotonic clock ``t_ns``; resent every 100 ms until answered or ``--connect-timeout``.
2. TO -> operator ``welcome`` (echoes ``t_ns``, adds its own clock ``peer_ns``) or ``reject`` with
   the reason.  From the quickest of a few exchanges the operator estimates the clock offset
   (NTP style: ``offset = peer_ns - (t_ns + rtt/2)``).
3. operator -> TO ``start`` with the common start time in the TO's clock; TO -> operator
   ``started``.  Tick ``k`` of both processes is then due at ``start + k * dt`` in its own clock,
   so both logs align by tick.  The TO runs ``phase`` of a period (default 0.5) behind the
   operator: a forward packet reaches the TO within the same tick and a backward packet reaches
   the operator at the next tick, exactly the order ``teleop sim`` uses.

**Loop.** Each tick: wait for the deadline (``transport.realtime``), let the event loop deliver
datagrams (one ``await asyncio.sleep(0)``), hand them to the node, tick the node at session time
``now = k dt``, send its packet.  Bytes are counted at the socket (``transport.counters``).

**End.** Both run the agreed number of ticks, linger briefly to count packets still in flight,
say ``bye``, and write ``<role>.json`` (summary) and ``<role>.npz`` (per-tick signals) to the log
folder.  SIGINT/SIGTERM stop the loop at the next tick; the logs are still written.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
import os
import random
import signal
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from teleop import scenarios, wire
from teleop.codecs import CodecError, make_codec
from teleop.node import OperatorNode, PortOptions, TeleoperatorNode
from teleop.wave import WaveImpedance

from .base import Addr, Transport
from .counters import DirectionCounters
from .linkstats import LinkObserver
from .netem import Link, make_link
from .realtime import Ticker, setup_realtime
from .udp import UdpTransport, new_event_loop
from .zenoh import ZENOH_PEER, ZenohTransport, make_config

PROTOCOL_VERSION = 1
ROLES = ("operator", "teleoperator")


class SessionError(Exception):
    """The session could not start or run: printed as one clear line, non-zero exit."""


@dataclass(frozen=True)
class SessionParams:
    """What the handshake agrees on."""

    session: int
    codec: str
    scenario: str
    dof: int
    b: float
    full_scale: float
    duration: float
    dt: float = 0.001
    phase: float = 0.5
    netem_forward: str = ""  # impairment of operator -> TO, applied by the operator's shim
    netem_backward: str = ""  # impairment of TO -> operator, applied by the TO's shim
    seed: int = 0
    on_loss: str = "zero"  # reconstruction when nothing is queued (teleop.node.PortOptions)
    controller: bool = True  # passivity controller
    link_timeout: float = 0.05  # s of silence before a side goes to its safe state

    def validate(self) -> SessionParams:
        """Raise ValueError/CodecError saying what is wrong; returns self with the codec canonical."""
        scenarios.get(self.scenario)
        if not 1 <= self.dof <= 64:
            raise ValueError(f"dof must be 1..64, got {self.dof}")
        if not self.duration > 0 or not self.dt > 0:
            raise ValueError(f"duration and dt must be > 0, got {self.duration}, {self.dt}")
        if not 0.0 <= self.phase < 1.0:
            raise ValueError(f"phase must be in [0, 1) periods, got {self.phase}")
        WaveImpedance.of(self.b, self.dof)
        for text in (self.netem_forward, self.netem_backward):
            if text:
                make_link(text, self.seed)  # NetemError (a ValueError) names the bad token
        self.port_options()  # ValueError for a bad on_loss or timeout
        spec = make_codec(self.codec, self.dof, self.full_scale).spec
        return SessionParams(**{**asdict(self), "codec": spec})

    def port_options(self) -> PortOptions:
        return PortOptions(on_loss=self.on_loss, controller=self.controller, link_timeout=self.link_timeout)

    @property
    def ticks(self) -> int:
        return round(self.duration / self.dt)

    @classmethod
    def from_msg(cls, m: dict[str, Any]) -> SessionParams:
        try:
            p = cls(
                session=int(m["session"]),
                codec=str(m["codec"]),
                scenario=str(m["scenario"]),
                dof=int(m["dof"]),
                b=float(m["b"]),
                full_scale=float(m["range"]),
                duration=float(m["duration"]),
                dt=float(m["dt"]),
                phase=float(m["phase"]),
                netem_forward=str(m.get("netem_forward", "")),
                netem_backward=str(m.get("netem_backward", "")),
                seed=int(m.get("seed", 0)),
                on_loss=str(m.get("on_loss", "zero")),
                controller=bool(m.get("controller", True)),
                link_timeout=float(m.get("link_timeout", 0.05)),
            )
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"bad hello: {type(e).__name__}: {e}") from None
        return p.validate()

    def to_msg(self) -> dict[str, Any]:
        return {
            "session": self.session,
            "codec": self.codec,
            "scenario": self.scenario,
            "dof": self.dof,
            "b": self.b,
            "range": self.full_scale,
            "duration": self.duration,
            "dt": self.dt,
            "phase": self.phase,
            "netem_forward": self.netem_forward,
            "netem_backward": self.netem_backward,
            "seed": self.seed,
            "on_loss": self.on_loss,
            "controller": self.controller,
            "link_timeout": self.link_timeout,
        }


@dataclass
class EndpointOptions:
    role: str
    listen: Addr
    peer: Addr | None = None
    log_dir: Path | None = None
    connect_timeout: float = 10.0
    rt_priority: int | None = 10
    use_uvloop: bool = True
    spin_us: int = 100
    linger: float = 0.2
    grace_us: float = 400.0
    quiet: bool = False
    live: bool = False  # a status line every second: traffic, link, watchdog
    transport: str = "udp"  # "udp" or "zenoh"
    zenoh: ZenohOptions | None = None


@dataclass
class ZenohOptions:
    """How a process joins Zenoh (see transport.zenoh.make_config and README, Zenoh)."""

    mode: str = "peer"  # peer | client
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    prefix: str = "teleop/default"
    config_file: str | None = None


def _control(kind: str, **fields: Any) -> bytes:
    out: bytes = msgpack.packb({"t": kind, "v": PROTOCOL_VERSION, **fields}, use_bin_type=True)
    return out


def _parse_control(data: bytes) -> dict[str, Any] | None:
    """A control map, or None if ``data`` is not one (data packets are arrays)."""
    if not data or (data[0] & 0xF0 != 0x80 and data[0] not in (0xDE, 0xDF)):
        return None
    try:
        m = msgpack.unpackb(data, raw=False)
    except Exception:
        return None
    return m if isinstance(m, dict) and isinstance(m.get("t"), str) else None


class _Stop:
    def __init__(self) -> None:
        self.requested = False
        self.signal: int | None = None

    def __call__(self, signum: int) -> None:
        self.requested = True
        self.signal = signum


# --------------------------------------------------------------------------------------------
# handshake
# --------------------------------------------------------------------------------------------
async def _operator_handshake(
    tr: Transport, peer: Addr, params: SessionParams, timeout: float, stop: _Stop
) -> tuple[int, int, int]:
    """Returns (offset_ns, rtt_ns, start_ns in the operator's clock).

    Clock offset from NTP's four timestamps of the quickest of several exchanges: hello sent at t1,
    received by the TO at t2, welcome sent at t3, received here at t4;
    ``offset = ((t2 - t1) + (t3 - t4)) / 2``, ``rtt = (t4 - t1) - (t3 - t2)``.
    """
    clock = time.monotonic_ns
    give_up = clock() + int(timeout * 1e9)
    best: tuple[int, int] | None = None  # (rtt, offset)
    answers = 0
    hello = params.to_msg()
    while answers < 8:
        if stop.requested:
            raise SessionError("interrupted during the handshake")
        if clock() > give_up:
            if best is not None:
                break
            raise SessionError(
                f"peer {peer[0]}:{peer[1]} never answered within {timeout:g} s "
                f"(is `teleop teleoperator --listen {peer[0]}:{peer[1]}` running?)"
            )
        t1 = clock()
        tr.send(_control("hello", t_ns=t1, **hello), peer)
        wait_until = t1 + 100_000_000
        answered = False
        while not answered and clock() < wait_until:
            await tr.wait((wait_until - clock()) / 1e9)
            for data, addr, t4 in tr.drain():
                m = _parse_control(data)
                if m is None or addr != peer or m.get("session") != params.session:
                    continue
                if m["t"] == "reject":
                    raise SessionError(f"peer {peer[0]}:{peer[1]} rejected the session: {m.get('why')}")
                if m["t"] == "welcome" and m.get("t_ns") == t1:
                    t2, t3 = int(m["t2"]), int(m["t3"])
                    rtt = (t4 - t1) - (t3 - t2)
                    offset = ((t2 - t1) + (t3 - t4)) // 2
                    if best is None or rtt < best[0]:
                        best = (rtt, offset)
                    answers += 1
                    answered = True
    assert best is not None
    rtt, offset = best
    start = clock() + 300_000_000
    while clock() < start - 50_000_000:
        tr.send(_control("start", session=params.session, start_ns=start + offset), peer)
        t_wait = clock() + 20_000_000
        while clock() < t_wait:
            await tr.wait((t_wait - clock()) / 1e9)
            for data, addr, _ in tr.drain():
                m = _parse_control(data)
                if m and addr == peer and m["t"] == "started" and m.get("session") == params.session:
                    return offset, rtt, start
    raise SessionError(f"peer {peer[0]}:{peer[1]} did not confirm the start")


async def _teleoperator_handshake(
    tr: Transport, timeout: float, expect: dict[str, Any], stop: _Stop
) -> tuple[SessionParams, Addr, int, bool]:
    """Wait for an operator; returns (params, operator address, start_ns in this clock, rejoin).

    ``rejoin`` is set when the operator's session was already running (this process replaces a
    teleoperator that went away): ``start_ns`` is then in the past and the loop joins late."""
    clock = time.monotonic_ns
    give_up = clock() + int(timeout * 1e9)
    params: SessionParams | None = None
    peer: Addr | None = None
    while True:
        if stop.requested:
            raise SessionError("interrupted during the handshake")
        if clock() > give_up:
            what = "no operator said hello" if params is None else "the operator never sent start"
            raise SessionError(f"{what} within {timeout:g} s on {tr.local_address[0]}:{tr.local_address[1]}")
        await tr.wait(min(0.1, (give_up - clock()) / 1e9))
        for data, addr, t2 in tr.drain():
            m = _parse_control(data)
            if m is None:
                continue
            if m["t"] == "hello":
                if params is not None and (addr != peer or m.get("session") != params.session):
                    # Over Zenoh every operator has the same pseudo-address: the session id tells them apart.
                    tr.send(
                        _control("reject", session=m.get("session"), why="busy with another operator"), addr
                    )
                    continue
                try:
                    p = SessionParams.from_msg(m)
                    for k, v in expect.items():
                        if v is not None and getattr(p, k) != v:
                            raise ValueError(f"{k} {getattr(p, k)!r} differs from this teleoperator's {v!r}")
                except (ValueError, CodecError) as e:
                    tr.send(_control("reject", session=m.get("session"), why=str(e)), addr)
                    raise SessionError(f"rejected the operator at {addr[0]}:{addr[1]}: {e}") from None
                params, peer = p, addr
                tr.send(
                    _control("welcome", session=p.session, t_ns=m.get("t_ns", 0), t2=t2, t3=clock()), addr
                )
            elif (
                m["t"] == "start"
                and params is not None
                and addr == peer
                and m.get("session") == params.session
            ):
                tr.send(_control("started", session=params.session), addr)
                assert peer is not None
                return params, peer, int(m["start_ns"]), bool(m.get("rejoin", False))


# --------------------------------------------------------------------------------------------
# the loop
# --------------------------------------------------------------------------------------------
def _flush(link: Link, now: float, send: Any, peer: Addr, tx: DirectionCounters, k: int) -> None:
    """Send what the shim says is due, counting it at the socket."""
    for data in link.due(now):
        send(data, peer)
        try:
            payload_len: int | None = len(wire.decode(data).payload)
        except wire.WireError:  # corrupted by the shim on purpose
            payload_len = None
        tx.packet(k, len(data), payload_len)


class _Inbound:
    """Sorts what the socket received: data packets to the node, control messages, strangers.

    Every data packet from the peer is also shown to a :class:`LinkObserver` (arrival time on the
    common session clock), which measures the link from the receiver's side.
    """

    def __init__(
        self,
        tr: Transport,
        peer: Addr,
        node: OperatorNode | TeleoperatorNode,
        rx: DirectionCounters,
        session: int,
        t_common_ns: int,
        observer: LinkObserver,
    ) -> None:
        self.tr = tr
        self.peer = peer
        self.node = node
        self.rx = rx
        self.session = session
        self.t_common = t_common_ns
        self.observer = observer
        self.foreign = 0
        self.peer_bye: dict[str, Any] | None = None
        self.welcome: tuple[dict[str, Any], int] | None = None
        self.new_session_hello = False

    def _other_hello(self, m: dict[str, Any], addr: Addr) -> None:
        """Another operator.  If ours has gone silent it was probably restarted: end this session
        and serve the new one (teleoperator only); otherwise we are busy."""
        if m.get("session") == self.session:
            return  # our own operator's rejoin offer: only a restarted teleoperator answers it
        if self.node.link_lost and self.node.tx_direction == wire.BACKWARD:
            self.new_session_hello = True
        else:
            self.tr.send(_control("reject", session=m.get("session"), why="busy with another operator"), addr)

    def handle(self, k: int, play: bool = True) -> None:
        """Drain the inbox during tick ``k``; with ``play`` False only count (after the loop)."""
        rx, node = self.rx, self.node
        for data, addr, t_rx in self.tr.drain():
            if addr != self.peer:
                m = _parse_control(data)
                if m is not None and m["t"] == "hello":
                    self._other_hello(m, addr)  # a restarted operator comes from a new port
                else:
                    self.foreign += 1
                continue
            if data[:1] == b"\x9a":  # a 10-element msgpack array: a data packet
                try:
                    pkt = wire.decode(data)
                except wire.WireError as e:
                    rx.packet(k, len(data), None)
                    node.malformed(str(e))
                    continue
                rx.packet(k, len(data), len(pkt.payload))
                self.observer.observe((t_rx - self.t_common) / 1e9, pkt.seq, pkt.t_us / 1e6, len(data))
                if play:
                    node.receive_packet(pkt)
                continue
            m = _parse_control(data)
            if m is None:
                rx.packet(k, len(data), None)
                node.malformed("neither a data packet nor a control message")
            elif m["t"] == "start":
                self.tr.send(_control("started", session=self.session), self.peer)
            elif m["t"] == "bye":
                self.peer_bye = m
            elif m["t"] == "hello" and m.get("session") != self.session:
                self._other_hello(m, addr)
            elif m["t"] == "welcome" and m.get("session") == self.session:
                self.welcome = (m, t_rx)  # a restarted teleoperator answering our rejoin hello


async def _run_loop(
    opts: EndpointOptions,
    tr: Transport,
    peer: Addr,
    params: SessionParams,
    node: OperatorNode | TeleoperatorNode,
    t0_ns: int,
    t_common_ns: int,
    stop: _Stop,
    k0: int = 0,
) -> dict[str, Any]:
    """Tick from ``k0`` to the session's end; tick ``k`` is due at ``t0_ns + k dt``, and
    ``t_common_ns`` is the session's tick 0 on this clock."""
    n = params.ticks
    dt = params.dt
    dof = params.dof
    tx_dir = node.tx_direction
    tx = DirectionCounters(n, tr.header_bytes)
    rx = DirectionCounters(n, tr.header_bytes)
    raw_payload = bytes(make_codec("none", dof, params.full_scale).raw_bytes_per_tick)
    rec = {name: np.full((n, dof), np.nan) for name in ("v", "f", "wave_out", "wave_in")}
    e_sent = np.full(n, np.nan)
    e_played = np.full(n, np.nan)
    e_margin = np.full(n, np.nan)  # the watchdog's view: reported in-band minus played
    e_epoch = np.full(n, np.nan)  # played since the last energy epoch (a peer restart)
    # s on the common session clock: when each tick played its received sample, and when it sent
    t_play = np.full(n, np.nan)
    t_sent = np.full(n, np.nan)
    spec_tx = params.netem_forward if tx_dir == wire.FORWARD else params.netem_backward
    spec_rx = params.netem_backward if tx_dir == wire.FORWARD else params.netem_forward
    # The impairment shim sits between the node and the socket: what it drops never reaches the
    # socket (and is not counted as sent); what it duplicates is sent and counted twice.
    link: Link | None = make_link(spec_tx, 2 * params.seed + tx_dir) if spec_tx else None  # as teleop sim
    inbound = _Inbound(
        tr, peer, node, rx, params.session, t_common_ns, LinkObserver(spec_rx, joined_late=k0 > 0)
    )
    grace_ns = round(opts.grace_us * 1000)
    grace_waits = grace_missed = grace_ns_total = grace_streak = grace_resume = 0
    clock = time.monotonic_ns
    period_ns = round(dt * 1e9)
    ticker = Ticker(period_ns=period_ns, spin_ns=opts.spin_us * 1000, capacity=n + 16)
    ticker.start(t0_ns, k0)
    rejoin_offers = rejoins = 0
    last_offer = 0
    send = tr.send
    encode = wire.encode
    k = 0
    while not stop.requested and ticker.k < n:
        k = ticker.wait()
        if k >= n:  # a stall skipped past the end
            break
        await asyncio.sleep(0)  # one event-loop pass: datagrams received since the last tick
        inbound.handle(k)
        if grace_ns and node.decoder.queued == 0 and node.counters.accepted and k >= grace_resume:
            # A payload is due and not here yet: poll for it a little rather than play a gap.
            limit = ticker.deadline(k) + grace_ns
            grace_waits += 1
            t_wait = clock()
            while node.decoder.queued == 0 and clock() < limit:
                await asyncio.sleep(0)
                inbound.handle(k)
                if node.decoder.queued == 0:
                    # Sleep a little rather than spin: under SCHED_FIFO a spinning loop would starve
                    # the threads that deliver the packet (Zenoh's runtime runs at normal priority).
                    time.sleep(20e-6)
            grace_ns_total += clock() - t_wait
            if node.decoder.queued == 0:
                grace_missed += 1
                grace_streak += 1
                if grace_streak >= 3:  # a delayed or jittery link: packets are ms late, not us; rest
                    grace_resume = k + 200
                    grace_streak = 0
            else:
                grace_streak = 0
        if inbound.new_session_hello:
            break  # teleoperator: a new operator session replaces the silent one
        if opts.role == "operator" and node.link_lost and clock() - last_offer > 250_000_000:
            # The teleoperator went away: offer a rejoin to whoever restarts there.  Poll for the
            # answer right away (the link is down anyway) so that its receive time, and with it the
            # clock offset (NTP's four timestamps), is exact to a few microseconds.
            t1 = last_offer = clock()
            send(_control("hello", t_ns=t1, rejoin=True, **params.to_msg()), peer)
            rejoin_offers += 1
            inbound.welcome = None
            while inbound.welcome is None and clock() - t1 < 600_000:
                await asyncio.sleep(0)
                inbound.handle(k)
                time.sleep(10e-6)  # let the transport's threads run (see the grace wait)
            if inbound.welcome is not None and int(inbound.welcome[0].get("t_ns", -1)) == t1:
                m, t4 = inbound.welcome
                offset = ((int(m["t2"]) - t1) + (int(m["t3"]) - t4)) // 2
                node.peer_restarted()
                inbound.observer = LinkObserver(spec_rx)  # the link figures cover the current peer
                send(
                    _control("start", session=params.session, start_ns=t_common_ns + offset, rejoin=True),
                    peer,
                )
                rejoins += 1
            inbound.welcome = None
        now = k * dt
        t_play[k] = (clock() - t_common_ns) / 1e9
        pkt = node.tick(now)
        t_us = int(now * 1e6)
        if pkt is not None:
            data = encode(pkt)
            if link is None:
                send(data, peer)
                tx.packet(k, len(data), len(pkt.payload))
            else:
                link.send((clock() - t_common_ns) / 1e9, data)
        if link is not None:
            _flush(link, (clock() - t_common_ns) / 1e9, send, peer, tx, k)
        t_sent[k] = (clock() - t_common_ns) / 1e9
        base = encode(wire.Packet(params.session, tx_dir, k, k, t_us, 0, raw_payload, node.energy_sent))
        tx.baseline(k, len(base), len(raw_payload))
        rec["v"][k] = node.v
        rec["f"][k] = node.f
        rec["wave_out"][k] = node.wave_out
        rec["wave_in"][k] = node.wave_in
        e_sent[k] = node.energy_sent
        e_played[k] = node.energy_played
        e_margin[k] = node.guard.margin
        e_epoch[k] = node.guard.played_in_epoch
        if opts.live and k % 1000 == 999:
            pv = node.passivity
            print(
                f"  [{opts.role} {(k + 1) * dt:5.1f} s] sent {tx.packets} recv {rx.packets}  "
                f"{'LINK LOST' if node.link_lost else 'link ok'}  watchdog: violations {pv.violations}, "
                f"controller {pv.controller_active_ticks} ticks, margin {node.guard.margin:.3e} J, "
                f"overruns {ticker.overruns}",
                file=sys.stderr,
                flush=True,
            )
    stats = ticker.stats()
    completed = not stop.requested and ticker.k >= n and not inbound.new_session_hello
    # Linger: deliver what the shim still holds and count what is in flight, so that sender and
    # receiver counts can be compared; the bye tells the receiver how many packets there were.
    t_end = clock() + int(opts.linger * 1e9)
    while link is not None and (due := link.next_due()) is not None and clock() < t_end + 2_000_000_000:
        await asyncio.sleep(max(0.0, min(0.005, due - (clock() - t_common_ns) / 1e9)))
        _flush(link, (clock() - t_common_ns) / 1e9, send, peer, tx, n - 1)
        inbound.handle(n - 1, play=False)
    shim = dataclasses.asdict(link.stats) if link is not None else None
    for _ in range(3):
        send(
            _control(
                "bye",
                session=params.session,
                produced=node.seq,
                dropped_by_limit=shim["dropped_by_limit"] if shim else 0,
            ),
            peer,
        )
    while clock() < t_end:
        await asyncio.sleep(0.005)
        inbound.handle(n - 1, play=False)
    bye = inbound.peer_bye or {}
    link_rx = inbound.observer.summary(
        sent=bye.get("produced"), dropped_by_limit=bye.get("dropped_by_limit", 0)
    )
    direction = wire.DIRECTIONS[tx_dir]
    other = wire.DIRECTIONS[1 - tx_dir]
    window = max(1, round(0.1 / dt))
    summary: dict[str, Any] = {
        "role": opts.role,
        "pid": os.getpid(),
        "local": f"{tr.local_address[0]}:{tr.local_address[1]}",
        "peer": f"{peer[0]}:{peer[1]}",
        "transport": opts.transport,
        "completed": completed,
        "stopped_by_signal": stop.signal,
        "peer_said_bye": inbound.peer_bye is not None,
        "first_tick": k0,
        "replaced_by_new_session": inbound.new_session_hello,
        "rejoin": {"offers": rejoin_offers, "rejoins": rejoins},
        "link_received": link_rx,
        "shim": {"spec": spec_tx, **shim} if shim else None,
        "grace": {
            "limit_us": opts.grace_us,
            "waits": grace_waits,
            "missed": grace_missed,
            "waited_us_total": grace_ns_total / 1e3,
        },
        "params": asdict(params),
        "loop": stats.summary(),
        "sent": {"direction": direction, **tx.summary(window)},
        "received": {
            "direction": other,
            **rx.summary(window),
            "foreign": inbound.foreign,
            "inbox_overflow": tr.inbox_overflow,
            "socket_errors": tr.socket_errors,
        },
        "node": {
            **node.counters.as_dict(),
            "last_error": node.last_error,
            "decoder_underruns": node.decoder.underruns,
            "decoder_dropped_samples": node.decoder.dropped_samples,
        },
        "passivity": {"direction": other, **node.passivity.as_dict()},
        "energy": {
            "sent": node.energy_sent,
            "played": node.energy_played,
            "peer_reported_sent": node.peer_energy_sent,
        },
    }
    arrays: dict[str, Any] = {
        **rec,
        "energy_sent": e_sent,
        "energy_played": e_played,
        "energy_margin_observed": e_margin,
        "energy_played_epoch": e_epoch,
        "play_time_s": t_play,
        "send_time_s": t_sent,
        "lateness_ns": stats.lateness_ns,
        **tx.arrays("tx"),
        **rx.arrays("rx"),
    }
    if opts.log_dir is not None:
        opts.log_dir.mkdir(parents=True, exist_ok=True)
        (opts.log_dir / f"{opts.role}.json").write_text(json.dumps(summary, indent=2) + "\n")
        np.savez_compressed(opts.log_dir / f"{opts.role}.npz", **arrays)
    return summary


# --------------------------------------------------------------------------------------------
# entry points
# --------------------------------------------------------------------------------------------
async def _open_transport(opts: EndpointOptions) -> Transport:
    if opts.transport == "udp":
        return await UdpTransport.bind(opts.listen)
    if opts.transport == "zenoh":
        z = opts.zenoh or ZenohOptions()
        try:
            config = make_config(z.mode, z.listen, z.connect, z.config_file)
        except ValueError as e:
            raise SessionError(str(e)) from None
        return await ZenohTransport.open(opts.role, z.prefix, config)
    raise SessionError(f"unknown transport {opts.transport!r}; accepted: udp, zenoh")


async def _endpoint(
    opts: EndpointOptions, params: SessionParams | None, expect: dict[str, Any]
) -> dict[str, Any]:
    loop = asyncio.get_running_loop()
    stop = _Stop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop, sig)
    tr = await _open_transport(opts)
    try:
        while True:
            summary = await _session(opts, tr, params, expect, stop)
            summary.update(event_loop=type(loop).__module__.split(".")[0])
            if opts.log_dir is not None:
                (opts.log_dir / f"{opts.role}.json").write_text(json.dumps(summary, indent=2) + "\n")
            if not summary.get("replaced_by_new_session"):
                return summary
            # The teleoperator's operator was replaced mid-session (restarted): keep the old
            # session's logs under its id and serve the new operator.
            if opts.log_dir is not None:
                old = summary["params"]["session"]
                for ext in ("json", "npz"):
                    (opts.log_dir / f"{opts.role}.{ext}").replace(opts.log_dir / f"{opts.role}-{old}.{ext}")
            if not opts.quiet:
                print(
                    f"teleop {opts.role}: session {summary['params']['session']} replaced by a new operator",
                    file=sys.stderr,
                )
    finally:
        tr.close()


async def _session(
    opts: EndpointOptions, tr: Transport, params: SessionParams | None, expect: dict[str, Any], stop: _Stop
) -> dict[str, Any]:
    """Handshake, build the node, run the loop: one session of this process."""
    if opts.role == "operator":
        assert params is not None
        peer = ZENOH_PEER if opts.transport == "zenoh" else opts.peer
        assert peer is not None
        offset, rtt, start = await _operator_handshake(tr, peer, params, opts.connect_timeout, stop)
        t0 = start
        k0 = 0
        extra: dict[str, Any] = {"clock_offset_ns": offset, "handshake_rtt_us": rtt / 1e3}
    else:
        params, peer, start, rejoin = await _teleoperator_handshake(tr, opts.connect_timeout, expect, stop)
        t0 = start + round(params.phase * params.dt * 1e9)
        period = round(params.dt * 1e9)
        # Joining a running session: start at a tick a little in the future, on the session's clock.
        k0 = max(0, -(-(time.monotonic_ns() - t0) // period) + 20) if rejoin else 0
        extra = {"joined_late": rejoin}
    warnings = setup_realtime(opts.rt_priority)
    for w in warnings:
        print(f"teleop {opts.role}: warning: {w}", file=sys.stderr)
    human, env = scenarios.get(params.scenario).make(params.dof, params.dt)
    wave = WaveImpedance.of(params.b, params.dof)
    codec = make_codec(params.codec, params.dof, params.full_scale)
    node: OperatorNode | TeleoperatorNode
    if opts.role == "operator":
        node = OperatorNode(
            human=human,
            wave=wave,
            tx=codec,
            rx=codec,
            session=params.session,
            dt=params.dt,
            options=params.port_options(),
        )
    else:
        node = TeleoperatorNode(
            environment=env,
            wave=wave,
            tx=codec,
            rx=codec,
            session=params.session,
            dt=params.dt,
            options=params.port_options(),
        )
    if k0:
        node.joined_late()
    summary = await _run_loop(opts, tr, peer, params, node, t0, start, stop, k0)
    summary.update(extra, warnings=warnings)
    return summary


def run_endpoint(
    opts: EndpointOptions, params: SessionParams | None = None, expect: dict[str, Any] | None = None
) -> int:
    """Run one process's side of a session; returns the exit status (0 ok, 1 error, 130 interrupted)."""
    loop, loop_name = new_event_loop(opts.use_uvloop)
    try:
        summary = loop.run_until_complete(_endpoint(opts, params, expect or {}))
    except SessionError as e:
        print(f"teleop {opts.role}: error: {e}", file=sys.stderr)
        return 1
    except OSError as e:
        print(f"teleop {opts.role}: error: {e.strerror or e}", file=sys.stderr)
        return 1
    finally:
        loop.close()
    if not opts.quiet:
        lp = summary["loop"]
        pe = lp["period_error_us"]
        print(
            f"teleop {opts.role} [{loop_name}]: {lp['ticks']} ticks, overruns {lp['overruns']}, "
            f"period error p50/p99/max {pe['p50']:.1f}/{pe['p99']:.1f}/{pe['max']:.0f} us, "
            f"CPU {100 * lp['cpu_fraction']:.0f}%, sent {summary['sent']['packets']} packets, "
            f"received {summary['received']['packets']}",
            file=sys.stderr,
        )
    if summary["stopped_by_signal"] is not None:
        return 128 + int(summary["stopped_by_signal"])
    return 0


def new_session_id() -> int:
    return random.SystemRandom().randrange(1, 2**32)
