"""The real-time runner: one :class:`teleop.port.Port` between the ``Ticker`` and the transport.

Everything a side does with datagrams, the node, the shim, counters, link figures, recording and the
summary, lives in the sans-I/O port (``teleop.port``), and the handshake in the sans-I/O state
machines of ``teleop.protocol``; this module only owns the clock and the socket:

**Handshake.** ``OperatorHandshake``/``TeleoperatorHandshake`` are fed what the socket receives
(with its receive time) and say what to send and when to call again.  The operator estimates the
clock offset from NTP's four timestamps and sends the common start in the teleoperator's clock.
Tick ``k`` of both processes is then due at ``start + k dt`` in its own clock; the TO runs
``phase`` of a period (default 0.5) behind the operator, so a forward packet reaches the TO within
the same tick and a backward packet reaches the operator at the next tick, the order ``teleop sim``
uses.

**Loop.** Each tick: wait for the deadline (``transport.realtime``), drain the transport into the
port, poll a little for a payload that is due (grace), tick the port, send what it returns.

**End.** Both run the agreed number of ticks (a session of duration 0: until SIGINT/SIGTERM, or the
peer's ``bye``), linger briefly to count packets still in flight, say ``bye``, and finish
``<role>.mcap`` and write ``<role>.json`` (summary) in the log folder.  SIGINT/SIGTERM stop the loop at
the next tick; the logs are still written.

**Log.** The port hands its per-tick record to a sink a chunk (1000 ticks) at a time; here the sink is
``transport.mcaplog.McapLog``, which has a writer process write ``<role>.mcap`` as the session runs
(and, with ``live_view``, serve the same channels over the Foxglove WebSocket protocol), so memory
stays flat however long the session lasts and the loop never encodes or writes a message.
"""

from __future__ import annotations

import asyncio
import json
import os
import random
import secrets
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from teleop import auth, protocol
from teleop.devices import DeviceError
from teleop.port import Chunk, Port, PortKeys, make_node, make_shim
from teleop.protocol import PROTOCOL_VERSION, SessionParams

from .base import Addr, Transport
from .mcaplog import McapLog, spawn_writer, wall_clock_of
from .realtime import LoopStats, Ticker, setup_realtime
from .udp import UdpTransport, new_event_loop
from .zenoh import ZENOH_PEER, ZenohTransport, make_config

__all__ = [
    "PROTOCOL_VERSION",
    "EndpointOptions",
    "SessionError",
    "SessionParams",
    "ZenohOptions",
    "new_session_id",
    "run_endpoint",
]

# A real loop and transport deliver a payload a fraction of a tick late now and then (a stalled
# sender, the scheduler, Zenoh's threads): ``--playout auto`` keeps one tick of allowance for that.
REAL_PLAYOUT_FLOOR_TICKS = 1
REJOIN_OFFER_INTERVAL_NS = 250_000_000  # operator: how often to offer a rejoin while the link is lost
REJOIN_ANSWER_WAIT_NS = 600_000  # and how long to poll for the answer (the link is down anyway)
REJOIN_MAX_RTT_NS = 1_000_000  # a later answer still counts if its round trip fixes the offset to 0.5 ms


class SessionError(Exception):
    """The session could not start or run: printed as one clear line, non-zero exit."""


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
    psk: bytes | None = None  # the deployment's pre-shared key (teleop.auth); None: refuse to start
    insecure: bool = False  # --insecure: run with teleop.auth.INSECURE_KEY (integrity only), say so
    device: str | None = None  # --hsi/--robot spec (teleop.devices), local only; None: the scenario's
    live_view: int | None = None  # serve the Foxglove WebSocket live view on this port (0: any free)
    live_view_host: str = "127.0.0.1"


@dataclass
class ZenohOptions:
    """How a process joins Zenoh (see transport.zenoh.make_config and docs/guides/zenoh.md)."""

    mode: str = "peer"  # peer | client
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    prefix: str = "teleop/default"
    config_file: str | None = None


class _Discard:
    """The sink of a process that keeps no log and serves no live view: chunks are dropped."""

    def write(self, chunk: Chunk) -> None:
        pass


class _Stop:
    def __init__(self) -> None:
        self.requested = False
        self.signal: int | None = None

    def __call__(self, signum: int) -> None:
        self.requested = True
        self.signal = signum


def _addr(a: Addr) -> str:
    return f"{a[0]}:{a[1]}"


# --------------------------------------------------------------------------------------------
# handshake: the state machines of teleop.protocol, fed by the socket
# --------------------------------------------------------------------------------------------
async def _operator_handshake(
    tr: Transport, peer: Addr, params: SessionParams, timeout: float, stop: _Stop, psk: bytes
) -> tuple[int, int, int, PortKeys]:
    """Returns (offset_ns, rtt_ns, start_ns in the operator's clock, the port's keys)."""
    clock = time.monotonic_ns
    nonce = secrets.token_bytes(auth.NONCE_BYTES)
    hs = protocol.OperatorHandshake(params, now_ns=clock(), timeout_s=timeout, psk=psk, nonce=nonce)
    while True:
        if stop.requested:
            raise SessionError("interrupted during the handshake")
        for data in hs.poll(clock()):
            tr.send(data, peer)
        if hs.error is not None:
            hint = ""
            if "answer" in hs.error:  # a teleoperator with another key stays silent, by design
                hint = f" (is `teleop teleoperator --listen {_addr(peer)}` running, with the same key?)"
            raise SessionError(f"peer {_addr(peer)} {hs.error}{hint}")
        if hs.done:
            assert hs.tx_sealer is not None and hs.rx_opener is not None
            keys = PortKeys(hs.tx_sealer, hs.rx_opener, hs.hs_sealer, hs.hs_opener, psk, nonce)
            return hs.offset_ns, hs.rtt_ns, hs.start_ns, keys
        await tr.wait(max(0.0, (hs.next_timer() - clock()) / 1e9))
        for data, addr, t_rx in tr.drain():
            if addr == peer:
                hs.receive(data, t_rx)


@dataclass
class _Handover:
    """A teleoperator handshake that completed: what the session runs with."""

    params: SessionParams
    peer: Addr
    start_ns: int  # on this clock
    rejoin: bool
    keys: PortKeys

    @classmethod
    def of(cls, hs: protocol.TeleoperatorHandshake) -> _Handover:
        assert hs.done and hs.params is not None and hs.peer is not None
        assert hs.tx_sealer is not None and hs.rx_opener is not None
        keys = PortKeys(hs.tx_sealer, hs.rx_opener, hs.hs_sealer, hs.hs_opener, hs.psk, hs.nonce)
        return cls(hs.params, hs.peer, hs.start_ns, hs.rejoin, keys)


async def _teleoperator_handshake(
    tr: Transport, timeout: float, expect: dict[str, Any], stop: _Stop, psk: bytes
) -> _Handover:
    """Wait for an operator; returns (params, operator address, start_ns in this clock, rejoin).

    A hello that is malformed or does not match this teleoperator's settings is answered with a
    reject and counted; the teleoperator keeps waiting for a good one.  ``rejoin`` is set when the
    operator's session was already running (this process replaces a teleoperator that went away):
    ``start_ns`` is then in the past and the loop joins late."""
    clock = time.monotonic_ns
    nonce = secrets.token_bytes(auth.NONCE_BYTES)
    hs = protocol.TeleoperatorHandshake(expect, now_ns=clock(), timeout_s=timeout, psk=psk, nonce=nonce)
    shown = 0
    while True:
        if stop.requested:
            raise SessionError("interrupted during the handshake")
        hs.poll(clock())
        if hs.error is not None:
            raise SessionError(f"{hs.error} on {_addr(tr.local_address)}")
        await tr.wait(0.1)
        for data, addr, t_rx in tr.drain():
            for reply, dest in hs.receive(data, addr, t_rx, reply_clock=clock):
                tr.send(reply, dest)
        new = hs.rejected - shown
        if new:  # say why, but never let a flood of bad hellos flood the terminal
            reasons = list(hs.rejections)[-min(new, 3) :]
            for why in reasons:
                print(f"teleop teleoperator: rejected the operator: {why}", file=sys.stderr, flush=True)
            if new > len(reasons):
                print(f"teleop teleoperator: ... and {new - len(reasons)} more", file=sys.stderr, flush=True)
        shown = hs.rejected
        if hs.done:
            return _Handover.of(hs)


# --------------------------------------------------------------------------------------------
# the loop
# --------------------------------------------------------------------------------------------
class _Runner:
    """One session of one process: the clock, the socket and the session control around a port."""

    def __init__(
        self,
        opts: EndpointOptions,
        tr: Transport,
        peer: Addr,
        params: SessionParams,
        port: Port,
        t_common_ns: int,
        stop: _Stop,
        expect: dict[str, Any] | None = None,
        log: McapLog | None = None,
    ) -> None:
        self.opts, self.tr, self.peer, self.params, self.port = opts, tr, peer, params, port
        self.expect = expect or {}
        self.log = log
        self._watched: tuple[int, ...] = ()  # what the events channel last saw (teleop.port state)
        # Teleoperator, link lost: the handshake of whoever may replace the silent operator, and
        # its result once a start proved it (a hello alone may be a recording: teleop.protocol).
        self.takeover: protocol.TeleoperatorHandshake | None = None
        self.handover: _Handover | None = None
        self.node = port.node
        self.t_common = t_common_ns
        self.stop = stop
        self.foreign = 0
        self.peer_bye: protocol.Bye | None = None
        self._offer_t1 = -1  # t_ns of the last rejoin offer not yet answered
        self.replaced = False  # teleoperator: a new operator session replaces the silent one
        self.rejoin_offers = self.rejoins = 0
        self.own_hellos_ignored = 0  # teleoperator: our own operator's rejoin offers (see _own_hello)
        self._local_netem = protocol.configured_netem(self.expect)
        self._last_offer = 0
        self.grace = {"limit_us": opts.grace_us, "waits": 0, "missed": 0, "waited_us_total": 0.0}
        self._grace_streak = self._grace_resume = 0

    def now(self) -> float:
        """Seconds on the common session clock (tick 0 of the session is 0)."""
        return (time.monotonic_ns() - self.t_common) / 1e9

    def send(self, msg: protocol.Message) -> None:
        self.tr.send(self.port.seal(msg), self.peer)

    # --- inbound ---------------------------------------------------------------------------
    def drain(self, k: int, play: bool = True) -> None:
        """Everything the transport received, into the port; control messages to the session logic."""
        for data, addr, t_rx in self.tr.drain():
            if self._to_takeover(data, addr, t_rx):
                continue
            t = (t_rx - self.t_common) / 1e9
            if addr != self.peer:
                msg = self.port.receive(data, t, k, play, from_peer=False)
                if isinstance(msg, protocol.Hello):
                    self._other_hello(msg, addr)  # a restarted operator comes from a new port
                else:
                    self.foreign += 1
                continue
            msg = self.port.receive(data, t, k, play)
            if msg is not None:
                self._control(msg, addr, t_rx)

    def _control(self, msg: protocol.Message, addr: Addr, t_rx: int) -> None:
        ours = getattr(msg, "session", None) == self.params.session
        if isinstance(msg, protocol.Start) and ours:
            self.send(protocol.Started(self.params.session))
        elif isinstance(msg, protocol.Bye) and ours:
            self.peer_bye = msg
        elif isinstance(msg, protocol.Hello):
            self._other_hello(msg, addr)
        elif isinstance(msg, protocol.Welcome) and ours and msg.t_ns == self._offer_t1:
            self._rejoin(msg, t_rx)  # a restarted teleoperator answering our rejoin offer

    def _other_hello(self, msg: protocol.Hello, addr: Addr) -> None:
        """Another operator while ours is alive: we are busy.  (Our own operator's rejoin offer is
        only for a restarted teleoperator; with the link lost, hellos go to the takeover.)"""
        if msg.params.session != self.params.session:
            reject = protocol.Reject(msg.params.session, protocol.BUSY, msg.t_ns)
            self.tr.send(self.port.seal(reject), addr)

    def _to_takeover(self, data: bytes, addr: Addr, t_rx: int) -> bool:
        """Teleoperator whose operator went silent (probably restarted): handshake datagrams, and
        session datagrams that are not our peer's, go to a handshake of their own; the session is
        replaced only when that handshake completes, i.e. when a start proved the key and our fresh
        nonce.  Returns whether the datagram was taken."""
        if self.opts.role != "teleoperator" or not self.node.link_lost or self.handover is not None:
            self.takeover = None
            return False
        hdr = auth.peek(data)
        if hdr is None or (hdr[0] == auth.SESSION and self.port.verifies(data)):
            return False
        if hdr[0] == auth.HANDSHAKE and addr == self.peer and self._own_hello(data):
            self.own_hellos_ignored += 1
            return True
        hs = self.takeover
        if hs is not None:
            hs.poll(t_rx)
        if hs is None or hs.error is not None:
            if hdr[0] != auth.HANDSHAKE:
                return False
            nonce = secrets.token_bytes(auth.NONCE_BYTES)
            timeout = self.opts.connect_timeout
            hs = self.takeover = protocol.TeleoperatorHandshake(
                self.expect, now_ns=t_rx, timeout_s=timeout, psk=self.port.keys.psk, nonce=nonce
            )
        for reply, dest in hs.receive(data, addr, t_rx, reply_clock=time.monotonic_ns):
            self.tr.send(reply, dest)
        if hs.done:
            self.handover, self.replaced = _Handover.of(hs), True
        return True

    def _own_hello(self, data: bytes) -> bool:
        """Whether ``data`` is an authentic hello of this very session: our own operator offering a
        rejoin (meant for a restarted teleoperator) across an outage that both sides saw.  This
        process did not restart, so it must not answer as one: taken as a takeover, the offer split
        the session in two (a "replaced" log and a late-joined one) although nobody was replaced.
        Dropped, the session simply goes on when the link comes back."""
        try:
            body = self.port.keys.hs_rx.verify(data)[1]
            msg = protocol.parse(body, local_netem=self._local_netem)
        except (auth.AuthError, protocol.ProtocolError):
            return False
        return isinstance(msg, protocol.Hello) and msg.params.session == self.params.session

    # --- per tick --------------------------------------------------------------------------
    async def wait_for_payload(self, ticker: Ticker, k: int) -> None:
        """Grace: a payload is due and not here yet; poll for it a little rather than play a gap."""
        node, g, port = self.node, self.grace, self.port
        if not (g["limit_us"] and not port.payload_ready(k) and node.counters.accepted):
            return
        if k < self._grace_resume:
            return
        clock = time.monotonic_ns
        limit = ticker.deadline(k) + round(g["limit_us"] * 1000)
        g["waits"] += 1
        t_wait = clock()
        while not port.payload_ready(k) and clock() < limit:
            await asyncio.sleep(0)
            self.drain(k)
            if not port.payload_ready(k):
                # Sleep a little rather than spin: under SCHED_FIFO a spinning loop would starve
                # the threads that deliver the packet (Zenoh's runtime runs at normal priority).
                time.sleep(20e-6)
        g["waited_us_total"] += (clock() - t_wait) / 1e3
        if port.payload_ready(k):
            self._grace_streak = 0
            return
        g["missed"] += 1
        self._grace_streak += 1
        if self._grace_streak >= 3:  # a delayed or jittery link: packets are ms late, not us; rest
            self._grace_resume = k + 200
            self._grace_streak = 0

    async def offer_rejoin(self, k: int) -> None:
        """Operator, link lost: offer a rejoin to whoever restarts at the teleoperator's address.

        Poll for the answer right away (the link is down anyway) so that its receive time, and
        with it the clock offset (NTP's four timestamps), is exact to a few microseconds.  A
        welcome that comes later is still taken (:meth:`_rejoin`) if its round trip is short
        enough to place the start within half a tick."""
        clock = time.monotonic_ns
        if clock() - self._last_offer < REJOIN_OFFER_INTERVAL_NS:
            return
        t1 = self._offer_t1 = self._last_offer = clock()
        self.send(protocol.Hello(self.params, t_ns=t1, rejoin=True, nonce=self.port.keys.nonce))
        self.rejoin_offers += 1
        rejoins = self.rejoins
        while self.rejoins == rejoins and clock() - t1 < REJOIN_ANSWER_WAIT_NS:
            await asyncio.sleep(0)
            self.drain(k)
            time.sleep(10e-6)  # let the transport's threads run (see the grace wait)

    def _rejoin(self, m: protocol.Welcome, t4: int) -> None:
        """A restarted teleoperator welcomed our rejoin offer: re-key with its nonce, send the start."""
        t1 = self._offer_t1
        offset, rtt = protocol.ntp_offset(t1, m.t2, m.t3, t4)
        if rtt > REJOIN_MAX_RTT_NS:  # too slow to place the start precisely: wait for the next offer
            return
        self._offer_t1 = -1  # one start per offer
        self.port.peer_restarted(m.nonce)  # its new nonce keys the rest of the session
        self.send(protocol.Start(self.params.session, start_ns=self.t_common + offset, rejoin=True))
        self.rejoins += 1

    def status(self, k: int, ticker: Ticker) -> None:
        pv, port = self.node.passivity, self.port
        print(
            f"  [{self.opts.role} {(k + 1) * self.params.dt:5.1f} s] sent {port.tx.packets} "
            f"recv {port.rx.packets}  {'LINK LOST' if self.node.link_lost else 'link ok'}  watchdog: "
            f"violations {pv.violations}, controller {pv.controller_active_ticks} ticks, "
            f"margin {self.node.guard.margin:.3e} J, overruns {ticker.overruns}"
            f"{'  INSECURE (no key)' if self.opts.insecure else ''}",
            file=sys.stderr,
            flush=True,
        )

    async def until(self, t_ns: int, k0: int) -> None:
        """Before tick 0: keep serving the socket, so a start resent because our started was lost
        is answered (the operator gives up 50 ms before tick 0), and nothing piles up unread."""
        while not self.stop.requested and (left := t_ns - time.monotonic_ns()) > 0:
            await self.tr.wait(min(left / 1e9, 0.01))
            self.drain(k0, play=False)

    async def run(self, ticker: Ticker) -> None:
        """Tick until the session's end, a signal, or (teleoperator) a new operator's session."""
        n, port, opts = self.params.ticks, self.port, self.opts
        open_ended = self.params.until_stopped
        while not self.stop.requested and ticker.k < n:
            if open_ended and self.peer_bye is not None:  # the peer was stopped: so is the session
                break
            k = ticker.wait()
            if k >= n:  # a stall skipped past the end
                break
            await asyncio.sleep(0)  # one event-loop pass: datagrams received since the last tick
            self.drain(k)
            await self.wait_for_payload(ticker, k)
            if self.replaced:
                break
            if opts.role == "operator" and self.node.link_lost:
                await self.offer_rejoin(k)
            datagrams = port.tick(k, self.now())
            # Stamped once the sample exists and before it leaves: the peer cannot play it earlier,
            # so the true margin (teleop.report) never counts a sample as played before it was sent.
            port.sent(k, self.now())
            for data in datagrams:
                self.tr.send(data, self.peer)
            port.loop_timing(k, ticker.last_lateness_ns)
            if self.log is not None:
                self.observe(k, ticker)
            if opts.live and k % 1000 == 999:
                self.status(k, ticker)

    def observe(self, k: int, ticker: Ticker) -> None:
        """The log's low-rate channels: events as they happen, the live view's decimated ticks, and
        the link figures once a second.  A few integer comparisons a tick; messages are queued."""
        log, node, port = self.log, self.node, self.port
        assert log is not None
        sec = port.security
        watched = (int(node.link_lost), node.peer_restarts, sec.rejected, sec.replayed, ticker.overruns)
        if watched != self._watched:
            t = self.now()
            if self._watched:
                old = self._watched
                if watched[0] != old[0]:
                    log.event(t, "link_lost" if watched[0] else "link_restored", f"tick {k}")
                if watched[1] != old[1]:
                    log.event(t, "peer_restarted", f"energy epoch {watched[1]}")
                if watched[2] != old[2]:
                    log.event(t, "auth_rejected", f"{watched[2]} so far: {sec.last_rejection}")
                if watched[3] != old[3]:
                    log.event(t, "replayed", f"{watched[3]} so far")
                if watched[4] != old[4]:
                    log.event(t, "overrun", f"tick {k}: {ticker.overruns} so far")
            self._watched = watched
        if k % log.live_every == 0:
            log.live(k, self.now(), self._live_messages(k))
        if k % 1000 == 999:
            pv = node.passivity
            log.status(
                "link",
                self.now(),
                {
                    "t": self.now(),
                    "link": port.observer.quick(),
                    "sent": port.tx.summary(),
                    "received": port.rx.summary(),
                    "watchdog": {
                        "violations": pv.violations,
                        "controller_active_ticks": pv.controller_active_ticks,
                        "energy_dissipated": pv.energy_dissipated,
                        "margin": node.guard.margin,
                        "link_lost": node.link_lost,
                    },
                },
            )

    def _live_messages(self, k: int) -> dict[str, dict[str, Any]]:
        """This tick's per-tick messages, built from the node (the record's chunk is not sealed yet)."""
        node, t = self.node, self.now()
        return {
            "signals": {"k": k, "t": t, "v": node.v.tolist(), "f": node.f.tolist()},
            "waves": {"k": k, "t": t, "wave_out": node.wave_out.tolist(), "wave_in": node.wave_in.tolist()},
            "energy": {
                "k": k,
                "t": t,
                "sent": node.energy_sent,
                "played": node.energy_played,
                "margin_observed": node.guard.margin,
                "played_epoch": node.guard.played_in_epoch,
                "peer_epoch": node.peer_restarts,
            },
        }

    async def linger(self) -> None:
        """Deliver what the shim still holds, say bye, and count what is still in flight, so that
        sender and receiver counts can be compared; the bye tells the receiver how many packets
        there were."""
        port, last = self.port, max(self.port.rec.last, 0)
        clock = time.monotonic_ns
        t_end = clock() + int(self.opts.linger * 1e9)
        while (due := port.next_due()) is not None and clock() < t_end + 2_000_000_000:
            await asyncio.sleep(max(0.0, min(0.005, due - self.now())))
            for data in port.flush(self.now(), last):
                self.tr.send(data, self.peer)
            self.drain(last, play=False)
        shim = port.shim_stats()
        bye = protocol.Bye(self.params.session, port.produced(), shim["dropped_by_limit"] if shim else 0)
        for _ in range(3):
            self.send(bye)
        while clock() < t_end:
            await asyncio.sleep(0.005)
            self.drain(last, play=False)

    def summary(self, stats: LoopStats, completed: bool, k0: int) -> dict[str, Any]:
        bye = self.peer_bye
        s = self.port.summary(
            peer_produced=bye.produced if bye else None,
            peer_dropped_by_limit=bye.dropped_by_limit if bye else 0,
        )
        s["received"].update(
            foreign=self.foreign, inbox_overflow=self.tr.inbox_overflow, socket_errors=self.tr.socket_errors
        )
        shim = self.port.shim_stats()
        spec_tx = self.params.netem_forward if self.opts.role == "operator" else self.params.netem_backward
        return {
            "role": self.opts.role,
            "pid": os.getpid(),
            "local": _addr(self.tr.local_address),
            "peer": _addr(self.peer),
            "transport": self.opts.transport,
            "completed": completed,
            "stopped_by_signal": self.stop.signal,
            "peer_said_bye": bye is not None,
            "first_tick": k0,
            "replaced_by_new_session": self.replaced,
            "rejoin": {
                "offers": self.rejoin_offers,
                "rejoins": self.rejoins,
                "own_offers_ignored": self.own_hellos_ignored,
            },
            "shim": {"spec": spec_tx, **shim} if shim else None,
            "grace": self.grace,
            "params": asdict(self.params),
            "loop": stats.summary(),
            **s,
        }


async def _run_loop(
    opts: EndpointOptions,
    tr: Transport,
    peer: Addr,
    params: SessionParams,
    port: Port,
    t0_ns: int,
    t_common_ns: int,
    stop: _Stop,
    k0: int = 0,
    expect: dict[str, Any] | None = None,
    log: McapLog | None = None,
) -> tuple[dict[str, Any], _Handover | None]:
    """Tick from ``k0`` to the session's end; tick ``k`` is due at ``t0_ns + k dt``, and
    ``t_common_ns`` is the session's tick 0 on this clock.  Returns the summary and, when a new
    operator replaced a silent one, its completed handshake."""
    runner = _Runner(opts, tr, peer, params, port, t_common_ns, stop, expect, log)
    if log is not None:
        log.status("session", 0.0, {"role": opts.role, "pid": os.getpid(), "params": asdict(params)})
        log.event(0.0, "session_start", f"session {params.session}, first tick {k0}")
    await runner.until(t0_ns + k0 * round(params.dt * 1e9) - 2_000_000, k0)
    # No per-tick arrays in the ticker: the loop's timing goes to the port's record, a chunk at a time.
    ticker = Ticker(period_ns=round(params.dt * 1e9), spin_ns=opts.spin_us * 1000)
    ticker.start(t0_ns, k0)
    await runner.run(ticker)
    stats = ticker.stats()  # the ticking only, not the linger
    ended = ticker.k >= params.ticks or (
        params.until_stopped and (stop.requested or runner.peer_bye is not None)
    )
    completed = ended and not runner.replaced and (params.until_stopped or not stop.requested)
    if not runner.replaced:  # a replaced session's operator is gone: nothing is in flight to count
        await runner.linger()
    summary = runner.summary(stats, completed, k0)
    if log is not None:  # the file is finished by _session, once the summary is complete
        why = f"signal {stop.signal}" if stop.requested else ("peer said bye" if runner.peer_bye else "end")
        log.event(runner.now(), "session_end", f"{why}; {stats.ticks} ticks run")
    if opts.log_dir is not None:
        (opts.log_dir / f"{opts.role}.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary, runner.handover


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
    handover: _Handover | None = None
    writer = None
    try:
        while True:
            # The log's writer process starts now, so that it has imported before the loop starts.
            wants_log = opts.log_dir is not None or opts.live_view is not None
            writer = spawn_writer() if wants_log else None
            summary, handover = await _session(opts, tr, params, expect, stop, handover, writer)
            writer = None  # the session's log owns it now
            if opts.log_dir is not None:
                (opts.log_dir / f"{opts.role}.json").write_text(json.dumps(summary, indent=2) + "\n")
            if not summary.get("replaced_by_new_session"):
                return summary
            # The teleoperator's operator was replaced mid-session (restarted): keep the old
            # session's logs under its id and serve the new operator.
            if opts.log_dir is not None:
                old = summary["params"]["session"]
                for ext in ("json", "mcap"):
                    (opts.log_dir / f"{opts.role}.{ext}").replace(opts.log_dir / f"{opts.role}-{old}.{ext}")
            if not opts.quiet:
                print(
                    f"teleop {opts.role}: session {summary['params']['session']} replaced by a new operator",
                    file=sys.stderr,
                )
    finally:
        tr.close()
        if writer is not None and writer.poll() is None:  # unused (no session): it exits at end of input
            try:
                writer.communicate(timeout=10)
            except subprocess.TimeoutExpired:
                writer.kill()
                writer.wait()


async def _session(
    opts: EndpointOptions,
    tr: Transport,
    params: SessionParams | None,
    expect: dict[str, Any],
    stop: _Stop,
    handover: _Handover | None = None,
    writer: subprocess.Popen[bytes] | None = None,
) -> tuple[dict[str, Any], _Handover | None]:
    """Handshake (unless a running session's takeover already completed one), build the port, run
    the loop: one session of this process."""
    psk = opts.psk
    if psk is None:
        raise SessionError("no key: give the pre-shared key (teleop keygen) or choose insecure")
    if opts.role == "operator":
        assert params is not None
        peer = ZENOH_PEER if opts.transport == "zenoh" else opts.peer
        assert peer is not None
        offset, rtt, start, keys = await _operator_handshake(
            tr, peer, params, opts.connect_timeout, stop, psk
        )
        t0 = start
        k0 = 0
        extra: dict[str, Any] = {"clock_offset_ns": offset, "handshake_rtt_us": rtt / 1e3}
    else:
        h = handover or await _teleoperator_handshake(tr, opts.connect_timeout, expect, stop, psk)
        params, peer, start, rejoin, keys = h.params, h.peer, h.start_ns, h.rejoin, h.keys
        t0 = start + round(params.phase * params.dt * 1e9)
        # A takeover's start may have passed while the replaced session wrote its logs: join late.
        rejoin = rejoin or time.monotonic_ns() > t0 - 2_000_000
        period = round(params.dt * 1e9)
        # Joining a running session: start at a tick a little in the future, on the session's clock.
        k0 = max(0, -(-(time.monotonic_ns() - t0) // period) + 20) if rejoin else 0
        extra = {"joined_late": rejoin}
    warnings = setup_realtime(opts.rt_priority)
    for w in warnings:
        print(f"teleop {opts.role}: warning: {w}", file=sys.stderr)
    log = _open_log(opts, start, writer)
    port = _make_port(opts, tr, params, k0, keys, log)
    try:
        summary, replaced_by = await _run_loop(opts, tr, peer, params, port, t0, start, stop, k0, expect, log)
    except BaseException:
        if log is not None:
            log.close()
        raise
    summary.update(
        extra, warnings=warnings, event_loop=type(asyncio.get_running_loop()).__module__.split(".")[0]
    )
    summary["security"].update(auth=_auth_name(opts), key_id=auth.key_id(psk))
    if log is not None:  # the complete summary goes into the file: teleop report reads it there
        log.close({**summary, "end_t": (time.monotonic_ns() - start) / 1e9})
        summary["log"] = {
            "mcap": f"{opts.role}.mcap" if opts.log_dir is not None else None,
            "messages": log.messages,
            "dropped_chunks": log.dropped_chunks,
            "live_view_port": log.live_port,
            "error": log.error,
        }
    return summary, replaced_by


def _auth_name(opts: EndpointOptions) -> str:
    """What protects the datagrams: a keyed MAC, or the insecure key (integrity against accidents only)."""
    return "insecure" if opts.insecure else "blake2s-128"


def _open_log(
    opts: EndpointOptions, t_common_ns: int, writer: subprocess.Popen[bytes] | None
) -> McapLog | None:
    """``ROLE.mcap`` in the log folder and/or the live view, or None (no log, no view)."""
    if opts.log_dir is None and opts.live_view is None:
        return None
    path = None
    if opts.log_dir is not None:
        opts.log_dir.mkdir(parents=True, exist_ok=True)
        path = opts.log_dir / f"{opts.role}.mcap"
    try:
        return McapLog(
            path,
            opts.role,
            wall_clock_of(t_common_ns),
            live_port=opts.live_view,
            live_host=opts.live_view_host,
            process=writer,
        )
    except (OSError, RuntimeError) as e:  # the file cannot be made, the port is taken
        raise SessionError(f"cannot open the log or the live view: {e}") from None


def _make_port(
    opts: EndpointOptions, tr: Transport, params: SessionParams, k0: int, keys: PortKeys, log: McapLog | None
) -> Port:
    """This side's port: its node, its outgoing shim (seeded as in ``teleop sim``), counters."""
    node = make_node(
        opts.role,
        scenario=params.scenario,
        dof=params.dof,
        dt=params.dt,
        b=params.b,
        codec=params.codec,
        full_scale=params.full_scale,
        session=params.session,
        options=params.port_options(),
        device=opts.device,
        seed=params.seed,
        variation=params.variation,
    )
    if k0:
        node.joined_late()
    fwd, bwd = params.netem_forward, params.netem_backward
    spec_tx, spec_rx = (fwd, bwd) if opts.role == "operator" else (bwd, fwd)
    shim = make_shim(spec_tx, params.seed, node.tx_direction)
    return Port(
        node,
        ticks=params.ticks,
        shim=shim,
        peer_spec=spec_rx,
        header_bytes=tr.header_bytes,
        first_tick=k0,
        keys=keys,
        playout_floor=REAL_PLAYOUT_FLOOR_TICKS,
        sink=log if log is not None else _Discard(),
        window_ticks=max(1, round(0.1 / params.dt)),
    )


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
    except DeviceError as e:  # this side's device cannot run the agreed session (more DoF than it drives)
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
    if summary["stopped_by_signal"] is not None and summary["params"]["duration"] != 0:
        return 128 + int(summary["stopped_by_signal"])
    return 0  # a session without a fixed end stopped by a signal ended as it should


def new_session_id() -> int:
    return random.SystemRandom().randrange(1, 2**32)
