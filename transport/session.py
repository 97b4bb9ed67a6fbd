"""The real-time runner: a :class:`teleop.endpoint.Endpoint` between the ``Ticker`` and a transport.

The endpoint holds the whole session (handshake, start, rejoin, takeover, busy, bye, linger) and
the port every tick; it is sans-I/O and tested in virtual time.  This module only does I/O: wait
for the next tick's deadline or the endpoint's timer, drain the transport with receive times, feed
the endpoint, send what it returns, hand the record to the log, and turn the endpoint's events into
log messages, console lines and ``ROLE.json``.  Clocks are ``time.monotonic_ns``; tick ``k`` of a
session is due at ``t0 + k dt`` (the endpoint's ``SessionStarted`` says ``t0`` and the first tick).

**Log.** The port hands its per-tick record to a sink a chunk (1000 ticks) at a time; here the sink
is ``transport.mcaplog.McapLog``, whose writer process writes ``ROLE.mcap`` as the session runs (and,
with ``live_view``, serves the same channels over the Foxglove WebSocket protocol), so memory stays
flat however long the session lasts and the loop never encodes or writes a message.  SIGINT/SIGTERM
stop the loop at the next tick; the logs are still written.
"""

from __future__ import annotations

import asyncio
import os
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from teleop import auth
from teleop.devices import DeviceError
from teleop.endpoint import (
    Endpoint,
    EndReason,
    Failed,
    Failure,
    HelloRejected,
    LinkLost,
    LinkRestored,
    PeerRestarted,
    PortFactory,
    Replaced,
    SessionEnded,
    SessionStarted,
    State,
    session_port,
)
from teleop.errors import TeleopError
from teleop.port import Chunk, Port, PortKeys
from teleop.protocol import PROTOCOL_VERSION, LocalLimits, SessionParams

from . import logdir
from .base import Addr, Transport
from .mcaplog import McapLog, spawn_writer, wall_clock_of
from .realtime import LoopStats, Ticker, setup_realtime
from .udp import DEFAULT_RCVBUF_BYTES, UdpTransport, new_event_loop
from .watch import LogWatch, status_line
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

IDLE_WAIT_S = 0.01  # the longest the runner sleeps on the socket outside the ticks


class SessionError(TeleopError):
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
    robot_name: str = auth.DEFAULT_ROBOT_NAME  # the robot this operator names / this robot is
    local_limits: LocalLimits = field(default_factory=LocalLimits)  # teleoperator: what it affords
    udp_rcvbuf: int = DEFAULT_RCVBUF_BYTES  # the UDP socket's receive buffer asked for (transport.udp)


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


class _Runner:
    """One process: the clock, the socket, the log and the console around an endpoint."""

    def __init__(
        self, opts: EndpointOptions, tr: Transport, stop: _Stop, build: Callable[[PortFactory], Endpoint]
    ) -> None:
        self.opts, self.tr, self.stop = opts, tr, stop
        self.clock = time.monotonic_ns
        self.log: McapLog | None = None
        self._logs: dict[int, McapLog | None] = {}  # session id -> its log (a takeover opens the next)
        self._writer: subprocess.Popen[bytes] | None = None
        self.watch = LogWatch()
        self.warnings: list[str] = []
        self.ticker: Ticker | None = None
        self._stats: LoopStats | None = None
        self._finishing: list[threading.Thread] = []  # replaced sessions' logs being finished
        self._starts: dict[int, int] = {}  # session id -> its tick 0 on this clock
        self._created = self.clock()
        self._waited: dict[int, float] = {}  # session id -> s from this process's start to its start
        self.summary: dict[str, Any] | None = None
        self.ep = build(self._port)

    # --- the port factory (called by the endpoint when a session starts) ----------------------
    def _port(self, params: SessionParams, k0: int, keys: PortKeys, start_ns: int) -> Port:
        log = self._open_log(params.session, start_ns)
        self._logs[params.session] = log
        sink = log if log is not None else _Discard()
        return session_port(
            self.opts.role,
            params,
            k0,
            keys,
            header_bytes=self.tr.header_bytes,
            sink=sink,
            device=self.opts.device,
        )

    def _open_log(self, session: int, t_common_ns: int) -> McapLog | None:
        """A new MCAP file in the log folder (``transport.logdir.reserve``: ``ROLE.mcap`` or, if an
        earlier run or session holds it, ``ROLE-SESSION[-N].mcap``; nothing is renamed or
        overwritten) and/or the live view, or None (neither)."""
        o = self.opts
        if o.log_dir is None and o.live_view is None:
            return None
        writer, self._writer = self._writer, None
        try:
            files = logdir.reserve(o.log_dir, o.role, session) if o.log_dir is not None else None
            return McapLog(
                files.mcap if files is not None else None,
                o.role,
                wall_clock_of(t_common_ns),
                live_port=o.live_view,
                live_host=o.live_view_host,
                process=writer,
                file_id=(files.dev, files.ino) if files is not None else None,
            )
        except (OSError, RuntimeError, ValueError) as e:  # a folder others can write, the port is taken
            raise SessionError(f"cannot open the log or the live view: {e}") from None

    # --- I/O ------------------------------------------------------------------------------------
    def drain(self) -> None:
        for data, addr, t_rx in self.tr.drain():
            self.ep.receive_datagram(data, addr, t_rx)

    def send(self) -> None:
        for data, addr in self.ep.datagrams_to_send(self.clock()):
            self.tr.send(data, addr)

    async def idle(self, until_ns: int | None = None) -> None:
        """Outside the ticks: sleep on the socket until a datagram, the endpoint's timer or
        ``until_ns``; feed, fire the timer, send, handle events."""
        timer = self.ep.get_timer()
        wake = min(t for t in (timer, until_ns, self.clock() + int(IDLE_WAIT_S * 1e9)) if t is not None)
        await self.tr.wait(max(0.0, (wake - self.clock()) / 1e9))
        self.drain()
        if (timer := self.ep.get_timer()) is not None and self.clock() >= timer:
            self.ep.handle_timer(self.clock())
        self.send()
        self.events()

    async def run(self) -> dict[str, Any]:
        """Until the endpoint is finished: handshake, each session (a takeover starts the next)."""
        self.send()
        while not self.ep.finished:
            if self.stop.requested and self.ep.state == State.HANDSHAKE:
                raise SessionError("interrupted during the handshake")
            if self.stop.requested:
                self.ep.stop(self.clock())
            if self.ep.running and self.ticker is not None:
                await self.ticks()
            else:
                await self.idle()
        self.events()
        assert self.summary is not None
        return self.summary

    async def ticks(self) -> None:
        """Serve the socket until just before the first tick, then tick until the session ends."""
        ep, ticker, o = self.ep, self.ticker, self.opts
        assert ticker is not None
        while ep.state == State.STARTING and not self.stop.requested:
            left = ticker.deadline(ep.k0) - 2_000_000 - self.clock()
            if left <= 0:
                break
            await self.idle(self.clock() + left)
        if self.ticker is not ticker:  # replaced while waiting
            return
        ticker.start(ep.t0_ns, ep.k0)
        session = ep.params
        while ep.running and not self.stop.requested and self.ticker is ticker:
            k = ticker.wait()
            await asyncio.sleep(0)  # one event-loop pass: datagrams received since the last tick
            self.drain()
            await self.grace(k, ticker)
            if not ep.running or ep.params is not session:  # a takeover replaced the session
                self.send()  # the new operator's started
                break
            ep.tick(k, self.clock())
            self.send()
            assert ep.port is not None
            ep.port.loop_timing(k, ticker.last_lateness_ns)
            if self.log is not None:
                self.watch.tick(self.log, ep.port, k, ep.session_time(self.clock()), ticker.overruns)
            if o.live and k % 1000 == 999:
                print(
                    status_line(o.role, ep.port, k, ticker.overruns, o.insecure), file=sys.stderr, flush=True
                )
            self.events()
        if self.ticker is ticker:
            self._stats = ticker.stats()  # the ticking only, not the linger

    async def grace(self, k: int, ticker: Ticker) -> None:
        """A payload is due and not here yet: poll for it until the endpoint's limit."""
        limit = self.ep.grace_until(k, ticker.deadline(k))
        if limit is None:
            return
        t_wait = self.clock()
        while not self.ep.payload_ready(k) and self.clock() < limit:
            await asyncio.sleep(0)
            self.drain()
            if not self.ep.payload_ready(k):
                # Sleep a little rather than spin: under SCHED_FIFO a spinning loop would starve
                # the threads that deliver the packet (Zenoh's runtime runs at normal priority).
                time.sleep(20e-6)
        self.ep.grace_result(k, self.clock() - t_wait)

    # --- events ---------------------------------------------------------------------------------
    def events(self) -> None:
        ep, o = self.ep, self.opts
        while (ev := ep.next_event()) is not None:
            if isinstance(ev, SessionStarted):
                self.log = self._logs.get(ev.params.session)
                self._starts[ev.params.session] = ev.start_ns
                self._waited[ev.params.session] = (self.clock() - self._created) / 1e9
                self.ticker = Ticker(period_ns=round(ev.params.dt * 1e9), spin_ns=o.spin_us * 1000)
                self.tr.max_datagram = ep.max_datagram_bytes  # refused by length in the transport
                self.warnings = setup_realtime(o.rt_priority) + self.tr.warnings
                for w in self.warnings:
                    print(f"teleop {o.role}: warning: {w}", file=sys.stderr)
                if self.log is not None:
                    info = {"role": o.role, "pid": os.getpid(), "params": asdict(ev.params)}
                    self.log.status("session", 0.0, info)
                    self.log.event(0.0, "session_start", f"session {ev.params.session}, first tick {ev.k0}")
            elif isinstance(ev, Failed):
                raise SessionError(self._failure(ev))
            elif isinstance(ev, HelloRejected):
                print(f"teleop {o.role}: rejected the operator: {ev.why}", file=sys.stderr, flush=True)
            elif isinstance(ev, Replaced) and not o.quiet:
                print(
                    f"teleop {o.role}: session {ev.old_session} replaced by a new operator", file=sys.stderr
                )
            elif isinstance(ev, PeerRestarted | LinkLost | LinkRestored) and self.log is not None:
                name = {PeerRestarted: "peer_rejoined", LinkLost: "link_lost", LinkRestored: "link_restored"}
                self.log.event(ep.session_time(self.clock()), name[type(ev)], f"tick {ev.k}")
            elif isinstance(ev, SessionEnded):
                self.ended(ev)

    def _failure(self, ev: Failed) -> str:
        o = self.opts
        if o.role == "teleoperator":
            return f"{ev.detail} on {_addr(self.tr.local_address)}"
        peer = _addr(o.peer) if o.peer is not None else "zenoh"
        hint = ""
        if ev.reason == Failure.NO_ANSWER:  # a teleoperator with another key or name stays silent
            hint = (
                f" (is `teleop teleoperator --listen {peer} --name {o.robot_name}` running, with the"
                " same key? A robot of another name, or another key, never answers)"
            )
        return f"peer {peer} {ev.detail}{hint}"

    def ended(self, ev: SessionEnded) -> None:
        """One session is over: the process's figures join the endpoint's; ROLE.json and the log."""
        o, s = self.opts, dict(ev.summary)
        stats = self._stats or (self.ticker.stats() if self.ticker is not None else None)
        self._stats = None
        s["received"].update(self.tr.report())  # oversize: refused by length (Transport.max_datagram)
        s.update(
            pid=os.getpid(),
            local=_addr(self.tr.local_address),
            transport=o.transport,
            stopped_by_signal=self.stop.signal,
            robot=o.robot_name,
            waited_for_session_s=self._waited.get(s["params"]["session"]),
            loop=stats.summary() if stats is not None else None,
            warnings=self.warnings,
            event_loop=type(asyncio.get_running_loop()).__module__.split(".")[0],
        )
        s["security"].update(
            auth="insecure" if o.insecure else "blake2s-128", key_id=auth.key_id(o.psk or b"")
        )
        session = s["params"]["session"]
        log = self._logs.pop(session, None)
        replaced = ev.reason == EndReason.REPLACED
        t_end = (self.clock() - self._starts.pop(session, self.ep.start_ns)) / 1e9
        if log is not None:
            why = {EndReason.PEER_BYE: "peer said bye", EndReason.STOPPED: f"signal {self.stop.signal}"}
            log.event(t_end, "session_end", why.get(ev.reason, ev.reason.value))
        name = f"{o.role}-{session}" if replaced else o.role
        if replaced:  # the next session already runs: finish this one's files beside it, not in its way
            done = threading.Thread(target=self._finish, args=(s, log, name, t_end), name="finish-log")
            done.start()
            self._finishing.append(done)
        else:
            self._finish(s, log, name, t_end)
            self.ticker = None
        if self.log is log:
            self.log = None
        self.summary = s

    def _finish(self, s: dict[str, Any], log: McapLog | None, name: str, t_end: float) -> None:
        """Close the session's log (it waits for the writer) and write its JSON summary beside it
        (``transport.logdir.save_summary``: the MCAP file's stem, never over a file; a full disk
        is one line)."""
        o = self.opts
        if log is not None:
            log.close({**s, "end_t": t_end})
            s["log"] = {
                "mcap": log.path.name if log.path is not None else None,
                "messages": log.messages,
                "dropped_chunks": log.dropped_chunks,
                "live_view_port": log.live_port,
                "error": log.error,
            }
        if o.log_dir is not None:
            logdir.save_summary(o.log_dir, o.role, s)


# --------------------------------------------------------------------------------------------
# entry points
# --------------------------------------------------------------------------------------------
async def _open_transport(opts: EndpointOptions) -> Transport:
    if opts.transport == "udp":
        return await UdpTransport.bind(opts.listen, rcvbuf=opts.udp_rcvbuf)
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
    if opts.psk is None:
        raise SessionError("no key: give the pre-shared key (teleop keygen) or choose insecure")
    try:
        key = auth.robot_key(opts.psk, opts.robot_name)
    except ValueError as e:
        raise SessionError(str(e)) from None
    loop = asyncio.get_running_loop()
    stop = _Stop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop, sig)
    tr = await _open_transport(opts)
    kw: dict[str, Any] = {
        "now_ns": time.monotonic_ns(),
        "psk": key,
        "connect_timeout_s": opts.connect_timeout,
        "linger_s": opts.linger,
        "grace_us": opts.grace_us,
    }

    def build(make_port: PortFactory) -> Endpoint:
        if opts.role == "operator":
            peer = ZENOH_PEER if opts.transport == "zenoh" else opts.peer
            assert params is not None and peer is not None
            return Endpoint.operator(params, peer, make_port, **kw)
        return Endpoint.teleoperator(expect, make_port, local_limits=opts.local_limits, **kw)

    runner: _Runner | None = None
    try:
        runner = _Runner(opts, tr, stop, build)
        # The log's writer process starts now, so that it has imported before the loop starts.
        if opts.log_dir is not None or opts.live_view is not None:
            runner._writer = spawn_writer()
        summary = await runner.run()
        for t in runner._finishing:
            await asyncio.to_thread(t.join)
        return summary
    finally:
        tr.close()
        writer = runner._writer if runner is not None else None
        if writer is not None and writer.poll() is None:  # unused (no session): it exits at end of input
            try:
                writer.communicate(timeout=10)
            except subprocess.TimeoutExpired:
                writer.kill()
                writer.wait()
        for log in runner._logs.values() if runner is not None else ():
            if log is not None:
                log.close()


def run_endpoint(
    opts: EndpointOptions, params: SessionParams | None = None, expect: dict[str, Any] | None = None
) -> int:
    """Run one process's side of a session; returns the exit status (0 ok, 1 error, 130 interrupted)."""
    loop, loop_name = new_event_loop(opts.use_uvloop)
    try:
        summary = loop.run_until_complete(_endpoint(opts, params, expect or {}))
    except (SessionError, DeviceError) as e:  # DeviceError: this side's device cannot run the session
        print(f"teleop {opts.role}: error: {e}", file=sys.stderr)
        return 1
    except OSError as e:
        print(f"teleop {opts.role}: error: {e.strerror or e}", file=sys.stderr)
        return 1
    finally:
        loop.close()
    if not opts.quiet and summary.get("loop"):
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
