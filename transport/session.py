"""The real-time runner: a :class:`teleop.session.endpoint.Endpoint` between the ``Ticker`` and a transport.

The endpoint holds the whole session (handshake, start, rejoin, takeover, busy, bye, linger) and
the port every tick; it is sans-I/O and tested in virtual time.  This module only does I/O: wait
for the next tick's deadline or the endpoint's timer, drain the transport with receive times, feed
the endpoint, send what it returns, hand the record to the log, and turn the endpoint's events into
log messages, console lines and ``ROLE.json``.  Clocks are ``time.monotonic_ns``; tick ``k`` of a
session is due at ``t0 + k dt`` (the endpoint's ``SessionStarted`` says ``t0`` and the first tick).

The session's records (its MCAP log, live view and ``ROLE.json``) are ``transport.records``'s; the
process's options are ``transport.options``'.  SIGINT/SIGTERM stop the loop at the next tick; the
logs are still written.
"""

from __future__ import annotations

import asyncio
import os
import signal
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

from teleop.devices import DeviceError
from teleop.errors import TeleopError
from teleop.session import auth
from teleop.session.endpoint import (
    ClockShifted,
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
from teleop.session.port import Port, PortKeys
from teleop.session.protocol import PROTOCOL_VERSION, Pins, SessionParams
from teleop.session.summary import ProcessSummary, SessionSummary

from .base import Addr, Transport
from .mcaplog import LOG_CHUNK_TICKS, McapLog
from .options import EndpointOptions, ZenohOptions, new_session_id
from .realtime import LoopStats, Ticker, freeze_heap, setup_realtime
from .records import RecordError, Records
from .udp import UdpTransport, new_event_loop
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
#: Ticks between two looks at the endpoint's admission (a takeover becomes possible 50 ms after the
#: operator falls silent; a flood's sampling starts within this of the limiter's first drop).
ADMIT_EVERY = 16
#: The early drain (``_Runner.drain_early``) stops this long before the deadline, and starts from this
#: guess of a datagram's cost to feed (then learns it).
EARLY_MARGIN_NS = 10_000
EARLY_COST_START_NS = 30_000
#: With ``--tick-at wake``, ticks between two passes of the event loop (a signal waits at most this).
PASS_EVERY = 8
#: A device-paced session ends with a fault when its device has not ticked for this long.
DEVICE_SILENT_S = 1.0


class SessionError(TeleopError):
    """The session could not start or run: printed as one clear line, non-zero exit."""


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
        self,
        opts: EndpointOptions,
        tr: Transport,
        stop: _Stop,
        records: Records,
        build: Callable[[PortFactory], Endpoint],
    ) -> None:
        self.opts, self.tr, self.stop, self.records = opts, tr, stop, records
        self.clock = time.monotonic_ns
        self.log: McapLog | None = None  # the running session's (None: no log, no live view)
        self.watch = LogWatch()
        self.warnings: list[str] = []
        self.ticker: Ticker | None = None
        self._stats: LoopStats | None = None
        self._starts: dict[int, int] = {}  # session id -> its tick 0 on this clock
        self._created = self.clock()
        self._waited: dict[int, float] = {}  # session id -> s from this process's start to its start
        self.summary: SessionSummary | None = None
        self.ep = build(self._port)
        # The imports' objects frozen now (~17 ms), before the handshake: the freeze at each
        # session's start then collects only what came since (~0.1 ms), which matters for a late
        # joiner, whose first tick is 20 ticks after its start.
        freeze_heap()
        self._pending: list[tuple[bytes, Addr, int]] = []  # read by drain_early, not yet fed
        self._rx_cost_ns = EARLY_COST_START_NS  # a datagram's cost to feed, running mean
        self._rtt_ns: int | None = None  # operator: the handshake's round trip (the status line's floor)

    def _port(self, params: SessionParams, k0: int, keys: PortKeys, start_ns: int) -> Port:
        """The port factory, called by the endpoint when a session starts: its sink is the log."""
        sink = self.records.open(params.session, start_ns)
        o = self.opts
        port = session_port(
            o.role, params, k0, keys, header_bytes=self.tr.header_bytes, sink=sink, device=o.device
        )
        port.rec.defer = True  # a closed chunk of the record is sealed after the send (settle)
        port.rec.chunk_ticks = LOG_CHUNK_TICKS  # sealed 4 times a second: what a kill -9 loses
        return port

    # --- I/O ------------------------------------------------------------------------------------
    def drain(self) -> None:
        """Everything that arrived (what :meth:`drain_early` left first), into the endpoint."""
        self.feed_pending()
        for data, addr, t_rx in self.tr.drain():
            self.ep.receive_datagram(data, addr, t_rx)

    def feed_pending(self) -> None:
        """What :meth:`drain_early` read and left, into the endpoint, without reading the socket."""
        if self._pending:
            pending, self._pending = self._pending, []
            for data, addr, t_rx in pending:
                self.ep.receive_datagram(data, addr, t_rx)

    def drain_early(self, until_ns: int) -> None:
        """Read what arrived and feed the endpoint while each datagram's expected cost still ends
        before ``until_ns``; the rest waits in ``_pending`` for :meth:`drain`, in order.

        Why: the loop sleeps until ``spin`` before each deadline and spins the rest, and that spin
        is CPU burnt for timing alone.  A datagram that arrived before it is fed now, in the spin's
        time, exactly as it would be at the deadline (the endpoint files it under the coming tick,
        ``Endpoint._rx_k``, with its own receive time), and what the port touches is then warm in
        the cache when the tick runs (``bench.phases``: a tick after a sleep costs 2-3x a hot one)."""
        clock = self.clock
        got = self.tr.drain()
        for i, (data, addr, t_rx) in enumerate(got):
            t = clock()
            if t + self._rx_cost_ns > until_ns:
                self._pending.extend(got[i:])
                return
            self.ep.receive_datagram(data, addr, t_rx)
            self._rx_cost_ns += (clock() - t - self._rx_cost_ns) // 8  # a running mean

    def send(self) -> None:
        for data, addr in self.ep.datagrams_to_send(self.clock()):
            self.tr.send(data, addr)

    async def idle(self, until_ns: int | None = None) -> None:
        """Outside the ticks: sleep on the socket until a datagram, the endpoint's timer or
        ``until_ns``; feed, fire the timer, send, handle events."""
        timer = self.ep.get_timer()
        wake = min(t for t in (timer, until_ns, self.clock() + int(IDLE_WAIT_S * 1e9)) if t is not None)
        self.tr.admit(self.ep.admission(self.clock()))
        await self.tr.wait(max(0.0, (wake - self.clock()) / 1e9))
        self.drain()
        if (timer := self.ep.get_timer()) is not None and self.clock() >= timer:
            self.ep.handle_timer(self.clock())
        self.send()
        self.events()

    async def run(self) -> SessionSummary:
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
        session, wake = ep.params, o.tick_at == "wake"
        device = self._paced_device()
        if device is not None:
            try:
                await self.paced_ticks(ticker, device)
            finally:
                self._close_device(device)
            return
        while ep.running and not self.stop.requested and self.ticker is ticker:
            ticker.t0 = ep.t0_ns  # the endpoint's schedule: the phase it follows (teleop.session.link.phase)
            ticker.sleep()  # until the spin before the deadline; then, in the spin's time,
            self.drain_early(ticker.next_deadline - EARLY_MARGIN_NS)  # what arrived so far,
            early = self.tick_early(ticker, session) if wake else None  # and the tick itself
            k = ticker.spin_to_deadline()
            if early is not None:
                self.send()  # its datagrams leave at its deadline
                if early == k:  # (else a stall skipped the ticker past it: tick k's departure counts)
                    ticker.departed(self.clock())
            if early != k:  # not run early, or a stall of the host skipped the ticker past it
                # One event-loop pass (signals), not bounded, so after the deadline.
                await asyncio.sleep(0)
                self.drain()  # what arrived during the spin, and what the early drain left
                await self.grace(k, ticker)
                if not ep.running or ep.params is not session:  # a takeover replaced the session
                    self.send()  # the new operator's started
                    break
                ep.tick(k, self.clock())
                self.send()
                ticker.departed(self.clock())
                if ep.params is not session:  # ended without its peer (a ghost): waits again
                    self.events()
                    break
            else:
                # Run early, the tick is done: what arrives now counts for the next one, which the
                # next wake's early drain reads as well as a drain now would, for one read (a system
                # call, ~10 us of CPU on this VM) a tick fewer; only what the early drain read and
                # left is fed now, in order, without another read (that read found the socket empty
                # on most ticks, and a host that wakes late leaves something pending on most: 0.86
                # reads a tick, counted).  The event loop's pass (signals only: Zenoh's samples and
                # the log's writer do not need it) every PASS_EVERY ticks.
                self.feed_pending()
                if k % PASS_EVERY == 0:
                    await asyncio.sleep(0)
                if ep.params is not session:  # a takeover replaced the session
                    self.send()  # the new operator's started
                    break
            if k % ADMIT_EVERY == 0:  # the kernel's filter follows the endpoint (transport.sockfilter)
                self.tr.admit(ep.admission(self.clock()))
            assert ep.port is not None
            ep.port.settle()  # the tick's datagrams left: what could wait for it (the record's seal)
            ep.port.loop_timing(k, ticker.last_lateness_ns)
            if self.log is not None:
                self.watch.tick(
                    self.log, ep.port, k, ep.session_time(self.clock()), ticker.overruns, ticker.skipped
                )
            if o.live and k % 1000 == 999:
                print(
                    status_line(o.role, ep.port, k, ticker.overruns, o.insecure, self._rtt_ns),
                    file=sys.stderr,
                    flush=True,
                )
            self.events()
        if self.ticker is ticker:
            self._stats = ticker.stats()  # the ticking only, not the linger

    def _paced_device(self) -> Any:
        """This session's device if it paces the loop (``paced = True`` and ``wait(timeout_s)``)."""
        port = self.ep.port
        dev = getattr(port.node, "device", None) if port is not None else None
        if getattr(dev, "paced", False) is True and callable(getattr(dev, "wait", None)):
            return dev
        return None

    def _close_device(self, device: Any) -> None:
        """The session's ticks are over: the device ends its motion (a real arm stops without a
        reflex).  A device's close must be safe twice and after a fault."""
        close = getattr(device, "close", None)
        if callable(close):
            try:
                close()
            except DeviceError as e:
                self.warnings.append(f"device close: {e}")

    async def paced_ticks(self, ticker: Ticker, device: Any) -> None:
        """Tick on the device's clock: block in ``device.wait`` (a robot's next millisecond), then run
        the session tick the clock says (:meth:`Ticker.paced`: a tick the device skipped is a missed
        deadline, never run twice).  No grace and no early tick: the device waits for its command.
        A device fault (:class:`DeviceError` from ``wait``) ends the session with a bye saying why;
        nothing is ticked, so nothing is commanded, after it."""
        ep, o, session = self.ep, self.opts, self.ep.params
        ticker.device_paced = True
        timeout = max(0.01, 100 * ticker.period / 1e9)
        silent, n, next_status = 0.0, 0, ep.k0 - ep.k0 % 1000 + 999
        status = getattr(device, "status", None)
        hold = getattr(device, "hold", None)
        first = ticker.deadline(ep.k0) - ticker.period  # the device starts a tick before the first
        while ep.running and not self.stop.requested and self.ticker is ticker and self.clock() < first:
            await self.idle(first)
        while ep.running and not self.stop.requested and self.ticker is ticker:
            try:
                came = device.wait(timeout)
            except DeviceError as e:
                ep.fault(self.clock(), str(e))
                print(f"teleop {o.role}: device fault: {e}", file=sys.stderr, flush=True)
                self.send()
                self.events()
                break
            if not came:
                silent += timeout
                if silent >= DEVICE_SILENT_S:
                    ep.fault(self.clock(), f"the device did not tick for {silent:.1f} s")
                    self.send()
                    self.events()
                    break
                await asyncio.sleep(0)
                continue
            silent = 0.0
            now = self.clock()
            k = ticker.paced(now)
            if k is None:  # the device runs ahead of the session clock: it holds, no tick
                if callable(hold):
                    hold()
                continue
            self.drain()
            ep.tick(k, now)
            self.send()
            ticker.departed(self.clock())
            if ep.params is not session:  # a takeover replaced the session
                break
            n += 1
            if n % PASS_EVERY == 0:
                await asyncio.sleep(0)  # signals
            if n % ADMIT_EVERY == 0:
                self.tr.admit(ep.admission(self.clock()))
            assert ep.port is not None
            ep.port.settle()
            ep.port.loop_timing(k, ticker.last_lateness_ns)
            if self.log is not None:
                self.watch.tick(self.log, ep.port, k, ep.session_time(self.clock()), ticker.overruns)
            if o.live and k >= next_status:  # once a second of the session clock (k may jump)
                next_status = ((k - 999) // 1000 + 1) * 1000 + 999
                line = status_line(o.role, ep.port, k, ticker.overruns, o.insecure, self._rtt_ns)
                extra = f", missed deadlines {ticker.missed}" + (f", {status()}" if callable(status) else "")
                print(line + extra, file=sys.stderr, flush=True)
            self.events()
        if self.ticker is ticker:
            self._stats = ticker.stats()

    def tick_early(self, ticker: Ticker, session: SessionParams | None) -> int | None:
        """Run the coming tick now, in the time the spin before its deadline would burn; the caller
        sends its datagrams at the deadline.  Returns the tick run, or None: run it at the deadline.

        Why: the spin is CPU spent for timing alone, and on a host whose wake-ups are late by tens
        of microseconds it is learned near its 100 us bound, about as long as a tick's own work, so
        doing the work in it takes most of one off the other.  The tick's inputs are all here: its
        payload was filed under it by the early drain (one that is due and missing is waited for at
        the deadline instead, as before: grace), its device models run on the tick's time ``k dt``,
        not the clock.  What changes is that a datagram arriving in the rest of the spin is filed
        under the next tick rather than this one, as if it had arrived that much later; the
        datagrams still leave on the deadline, no later than after a tick run from it."""
        ep, now = self.ep, self.clock()
        k = ticker.k  # what spin_to_deadline returns next unless a stall skips ticks
        if not ep.running or ep.params is not session or now >= ticker.next_deadline:
            return None
        if self._pending:
            # What the early drain read and left (a host that wakes late leaves the drain no time
            # in its budget) arrived before this tick: fed now, each datagram is filed under it as
            # it would be at the deadline.  Left for after the tick, every payload would count a
            # tick late whenever the playout buffer held something releasable (the payload then is
            # not "due"), and auto playout would add that tick to every payload for good (measured:
            # most of a session one tick above its floor at each end).
            self.feed_pending()
            if not ep.running or ep.params is not session:  # what it fed started a takeover's session:
                return None  # tick k is the old session's number, not the new one's
            now = self.clock()
        if ep.grace_needed(k):
            return None
        ep.tick(k, now)
        return k

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
                self.log = self.records.logs.get(ev.params.session)
                self._starts[ev.params.session] = ev.start_ns
                self._rtt_ns = ev.rtt_ns or None
                self._waited[ev.params.session] = (self.clock() - self._created) / 1e9
                self.ticker = Ticker(period_ns=round(ev.params.dt * 1e9), spin_ns=o.spin_us * 1000)
                self.tr.max_datagram = ep.max_datagram_bytes  # refused by length in the transport
                self.warnings = setup_realtime(o.rt_priority) + self.tr.warnings
                freeze_heap()  # before the first tick: the GC walks only what the ticks make
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
            elif isinstance(ev, ClockShifted):
                msg = (
                    f"tick 0 moved {ev.ticks} ticks earlier at tick {ev.k}:"
                    " the peer's packets came before they left"
                )
                if not o.quiet:
                    print(f"teleop {o.role}: clock skew: {msg}", file=sys.stderr, flush=True)
                if self.log is not None:
                    self.log.event(ep.session_time(self.clock()), "clock_shifted", msg)
            elif isinstance(ev, SessionEnded):
                if ev.reason == EndReason.PEER_SILENT:
                    print(
                        f"teleop {o.role}: session {ev.summary.params.session} ended: not one packet from"
                        f" the operator since its start; waiting for an operator",
                        file=sys.stderr,
                        flush=True,
                    )
                self.ended(ev)

    def _failure(self, ev: Failed) -> str:
        o = self.opts
        if o.role == "teleoperator":
            return f"{ev.detail} on {_addr(self.tr.local_address)}"
        peer = _addr(o.peer) if o.peer is not None else "zenoh"
        hint = ""
        if ev.reason == Failure.NO_ANSWER:  # nothing came back: absent, unreachable, or silent
            hint = (
                f" (nothing came back: is `teleop teleoperator --listen {peer} --name {o.robot_name}`"
                " running and reachable? A robot of another name, or another key, stays silent too)"
            )
        elif ev.reason == Failure.THROTTLED:
            hint = " (it answered with retries only: it dropped our hellos with their cookie; flooded?)"
        elif ev.reason == Failure.UNVERIFIED:  # the one case that points at the key
            hint = (
                f" (answers came whose MAC did not verify: does the teleoperator hold the same key,"
                f" with --name {o.robot_name}?)"
            )
        return f"peer {peer} {ev.detail}{hint}"

    def ended(self, ev: SessionEnded) -> None:
        """One session is over: the process's figures join the endpoint's; ROLE.json and the log."""
        o, tr = self.opts, self.tr
        stats = self._stats or (self.ticker.stats() if self.ticker is not None else None)
        self._stats = None
        session = ev.summary.params.session
        s = SessionSummary(
            ev.summary,
            ProcessSummary(
                pid=os.getpid(),
                local=_addr(tr.local_address),
                transport=o.transport,
                robot=o.robot_name,
                auth="insecure" if o.insecure else "blake2s-128",
                key_id=auth.key_id(o.psk or b""),
                event_loop=type(asyncio.get_running_loop()).__module__.split(".")[0],
                stopped_by_signal=self.stop.signal,
                waited_for_session_s=self._waited.get(session),
                loop=stats.summary() if stats is not None else None,
                warnings=self.warnings,
                received=tr.report(),  # oversize: refused by length (Transport.max_datagram)
            ),
        )
        replaced = ev.reason == EndReason.REPLACED
        t_end = (self.clock() - self._starts.pop(session, self.ep.start_ns)) / 1e9
        why = {EndReason.PEER_BYE: "peer said bye", EndReason.STOPPED: f"signal {self.stop.signal}"}
        if ev.reason == EndReason.PEER_FAULT:
            print(
                f"teleop {o.role}: the peer's device ended the session: {ev.summary.fault}", file=sys.stderr
            )
        if self.log is self.records.logs.get(session):
            self.log = None
        self.records.end(s, session, t_end, why.get(ev.reason, ev.reason.value), replaced)
        if not replaced:
            self.ticker = None
        self.summary = s


# --------------------------------------------------------------------------------------------
# entry points
# --------------------------------------------------------------------------------------------
async def _open_transport(opts: EndpointOptions, key: bytes) -> Transport:
    if opts.transport == "udp":
        return await UdpTransport.bind(opts.listen, rcvbuf=opts.udp_rcvbuf)
    if opts.transport == "zenoh":
        z = opts.zenoh or ZenohOptions()
        try:
            config = make_config(z.mode, z.listen, z.connect, z.config_file)
        except ValueError as e:
            raise SessionError(str(e)) from None
        return await ZenohTransport.open(opts.role, z.prefix, config, key=key)
    raise SessionError(f"unknown transport {opts.transport!r}; accepted: udp, zenoh")


async def _endpoint(opts: EndpointOptions, params: SessionParams | None, pins: Pins | None) -> SessionSummary:
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
    tr = await _open_transport(opts, key)
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
        return Endpoint.teleoperator(pins or Pins(), make_port, local_limits=opts.local_limits, **kw)

    records = Records(opts.role, opts.log_dir, opts.live_view, opts.live_view_host)
    try:
        summary = await _Runner(opts, tr, stop, records, build).run()
        await asyncio.to_thread(records.wait_finished)
        return summary
    except RecordError as e:
        raise SessionError(str(e)) from None
    finally:
        tr.close()
        records.close()


def run_endpoint(opts: EndpointOptions, params: SessionParams | None = None, pins: Pins | None = None) -> int:
    """Run one process's side of a session; returns the exit status (0 ok, 1 error, 130 interrupted)."""
    loop, loop_name = new_event_loop(opts.use_uvloop)
    try:
        summary = loop.run_until_complete(_endpoint(opts, params, pins))
    except (SessionError, DeviceError) as e:  # DeviceError: this side's device cannot run the session
        print(f"teleop {opts.role}: error: {e}", file=sys.stderr)
        return 1
    except OSError as e:
        print(f"teleop {opts.role}: error: {e.strerror or e}", file=sys.stderr)
        return 1
    finally:
        loop.close()
    proc = summary.process
    assert proc is not None
    if not opts.quiet and proc.loop:
        lp, port = proc.loop, summary.endpoint.port
        pe = lp["period_error_us"]
        print(
            f"teleop {opts.role} [{loop_name}]: {lp['ticks']} ticks, overruns {lp['overruns']}, "
            f"period error p50/p99/max {pe['p50']:.1f}/{pe['p99']:.1f}/{pe['max']:.0f} us, "
            f"CPU {100 * lp['cpu_fraction']:.0f}%, sent {port['sent']['packets']} packets, "
            f"received {port['received']['packets']}",
            file=sys.stderr,
        )
    if summary.endpoint.fault:  # a device ended the session (this side's or the peer's): said above
        return 1
    if proc.stopped_by_signal is not None and not summary.endpoint.params.until_stopped:
        return 128 + proc.stopped_by_signal
    return 0  # a session without a fixed end stopped by a signal ended as it should
