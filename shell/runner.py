"""The real-time runner: an endpoint and its scheduler between the clock and a transport.

The endpoint (``teleop.session.endpoint``) holds the whole session (handshake, start, rejoin,
takeover, busy, bye, linger) and each tick; its scheduler (``teleop.session.scheduler``) when each
tick is due (its timers: early drain, early tick, grace, skips); both are sans-I/O and tested in
virtual time.  This module only does I/O: it waits (on the socket, or a sleep then a spin:
``shell.realtime.PreciseSleep``), reads, feeds the scheduler, fires its timer, sends, and turns
its events into log messages, console lines (``shell.console``) and ``ROLE.json``
(``shell.records``).  Clocks are ``time.monotonic_ns``.  A stop (SIGINT/SIGTERM) ends the
session, which lingers; the logs are still written.
"""

from __future__ import annotations

import asyncio
import os
import sys
import time
from collections.abc import Callable
from dataclasses import asdict
from typing import Any

from teleop.devices import DeviceError
from teleop.errors import TeleopError
from teleop.session.endpoint import Endpoint, PortFactory, session_port
from teleop.session.events import (
    AdmissionChanged,
    ClockShifted,
    EndReason,
    Failed,
    SessionEnded,
    SessionStarted,
    TicksEnded,
)
from teleop.session.port import Port, PortKeys
from teleop.session.protocol import SessionParams
from teleop.session.schedule import EARLY_MARGIN_NS, TickPolicy
from teleop.session.scheduler import Scheduler
from teleop.session.summary import SessionSummary
from transport.base import Transport

from . import console
from .mcaplog import LOG_CHUNK_TICKS, McapLog
from .options import EndpointOptions, Interrupted
from .realtime import HostMarks, LoopStats, PreciseSleep, freeze_heap, lock_memory, setup_realtime
from .records import Records
from .watch import Watch

__all__ = ["Runner", "SessionError", "Stop"]

IDLE_WAIT_NS = 10_000_000  # the longest the runner waits on the socket outside the ticks
FIRST_TICK_LEAD_NS = 2_000_000  # the socket is served until this long before the first tick
PASS_EVERY = 8  # device-paced: ticks between two passes of the event loop (signals)
#: An event-loop pass (signals only: Zenoh's samples and the log's writer do not need it) at least
#: this often during the ticks; a signal waits at most this.
PASS_NS = 8_000_000
GRACE_POLL_S = 20e-6  # grace: a short sleep rather than a spin (under SCHED_FIFO a spin would
# starve the threads that deliver the packet: Zenoh's runtime runs at normal priority)


class SessionError(TeleopError):
    """The session could not start or run: printed as one clear line, non-zero exit."""


class Stop:
    def __init__(self) -> None:
        self.requested = False
        self.signal: int | None = None

    def __call__(self, signum: int) -> None:
        self.requested = True
        self.signal = signum


class Runner:
    """One process: the clock, the socket, the log and the console around an endpoint."""

    def __init__(
        self,
        opts: EndpointOptions,
        tr: Transport,
        stop: Stop,
        records: Records,
        build: Callable[[PortFactory], Endpoint],
    ) -> None:
        self.opts, self.tr, self.stop, self.records = opts, tr, stop, records
        self.clock = time.monotonic_ns
        self.log: McapLog | None = None  # the running session's (None: no log)
        self.watch = Watch(opts.role, opts.live, opts.insecure, opts.wide)
        self.warnings: list[str] = []
        self.sleeper = PreciseSleep(spin_ns=opts.spin_us * 1000)
        self.session = 0
        self.in_session = False  # a session started and did not end listening again
        self.ticking = False  # its ticks run (SessionStarted .. TicksEnded)
        self.device: Any = None  # it paces them
        self._period = 1_000_000
        self._first = 0  # its first tick's deadline (paced: the device's first tick)
        self._ticks0: tuple[float, int] | None = None  # the CPU and the clock when the ticks began
        self._host0 = HostMarks(0, None)  # the host's page faults and steal when the session started
        self._stats: LoopStats | None = None
        self._starts: dict[int, int] = {}  # session id -> its tick 0 on this clock
        self._created = self.clock()
        self._waited: dict[int, float] = {}  # session id -> s from this process's start to its start
        self.summary: SessionSummary | None = None
        early = opts.spin_us * 1000 + EARLY_MARGIN_NS
        policy = TickPolicy(early_tick=opts.tick_at == "wake", early_ns=early, grace_us=opts.grace_us)
        self.ep = Scheduler(build(self._port), policy, self.watch)
        # The imports' objects frozen now (~17 ms), before the handshake: the freeze at each
        # session's start then collects only what came since (~0.1 ms), which matters for a late
        # joiner, whose first tick is 20 ticks after its start.
        freeze_heap()
        self._lock_warnings = lock_memory() if opts.rt_priority is not None else []  # ~115 ms, no tick's

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
    def feed(self) -> None:
        """Everything that arrived, into the endpoint, with its receive time."""
        for data, addr, t_rx in self.tr.drain():
            self.ep.receive_datagram(data, addr, t_rx)

    def send(self) -> None:
        for data, addr in self.ep.datagrams_to_send(self.clock()):
            self.tr.send(data, addr)

    def fire(self) -> None:
        """The endpoint's timer if due, then send; once more if that made it due at once (a tick's
        datagrams left: it settles them now, and counts their departure)."""
        for _ in range(2):
            due = (t := self.ep.get_timer()) is not None and (now := self.clock()) >= t
            if due:
                self.ep.handle_timer(now)
            self.send()
            if not due:
                return

    async def run(self) -> SessionSummary:
        """Until the endpoint is finished (no timer): wait, read, fire its timer, send, events."""
        ep, clock = self.ep, self.clock
        self.send()
        last_pass = clock()
        try:
            while (t := ep.get_timer()) is not None:
                if self.stop.requested:
                    if not self.in_session:
                        raise Interrupted.of(self.opts.role)
                    ep.stop(clock())
                if self.device is not None and clock() >= self._first and not self.stop.requested:
                    await self.paced()
                    continue
                if t > clock():
                    await self.wait(t)
                self.fire()
                if not self.ticking or clock() - last_pass > PASS_NS:
                    await asyncio.sleep(0)
                    last_pass = clock()
                self.events()
        finally:
            self.close_device()
        self.events()
        assert self.summary is not None
        return self.summary

    async def wait(self, t: int) -> None:
        """Until ``t`` (the endpoint's timer) or a datagram: on the socket outside the ticks and
        until just before the first; during them a short sleep if a tick awaits its payload (grace),
        else precisely: a sleep until the spin before ``t``, one read, and the spin, in which the
        endpoint works (it feeds what came and may run the tick early: ``teleop.session.schedule``)."""
        now, clock = self.clock(), self.clock
        if self.device is not None:  # paced, before its first tick (then the device's clock)
            t = min(t, self._first)
        elif self.ticking and (self._ticks0 is not None or t - now <= FIRST_TICK_LEAD_NS):
            if self.ep.awaiting_payload:
                time.sleep(GRACE_POLL_S)
                self.feed()
                return
            if self._ticks0 is None:
                self._ticks0 = (time.process_time(), t)
            self.sleeper.sleep(t)
            self.feed()
            while (now := clock()) < t:
                self.ep.handle_timer(now)
            self.ep.handle_timer(now)  # due: the instant the spin ended is the deadline's figure
            self.send()
            return
        elif self.ticking:
            t -= FIRST_TICK_LEAD_NS
        await self.tr.wait(min(t - now, IDLE_WAIT_NS) / 1e9)
        self.feed()

    async def paced(self) -> None:
        """Tick on the device's clock: block in ``device.wait`` (a robot's next millisecond), then
        the endpoint runs the session tick that clock says.  No grace and no early tick: the device
        waits for its command.  A device fault (:class:`DeviceError` from ``wait``) ends the session
        with a bye saying why; nothing is ticked, so nothing is commanded, after it."""
        ep, device, clock = self.ep, self.device, self.clock
        timeout = max(0.01, 100 * self._period / 1e9)
        self._ticks0, n = (time.process_time(), self._first + self._period), 0
        while self.device is device and not self.stop.requested:
            try:
                came = device.wait(timeout)
            except DeviceError as e:
                ep.fault(clock(), str(e))
                print(f"teleop {self.opts.role}: device fault: {e}", file=sys.stderr, flush=True)
                self.send()
                self.events()
                return
            if came:  # its tick: the session's tick the clock says
                self.feed()
                ep.handle_timer(clock())
                self.send()
            self.fire()  # its datagrams left (settle), or the device fell silent (a fault)
            n += 1
            if not came or n % PASS_EVERY == 0:
                await asyncio.sleep(0)  # signals
            self.events()

    def close_device(self) -> None:
        """The session's ticks are over: the device ends its motion (a real arm stops without a
        reflex).  A device's close must be safe twice and after a fault."""
        device, self.device = self.device, None
        close = getattr(device, "close", None)
        if callable(close):
            try:
                close()
            except DeviceError as e:
                self.warnings.append(f"device close: {e}")

    # --- events ---------------------------------------------------------------------------------
    def events(self) -> None:
        o = self.opts
        while (ev := self.ep.next_event()) is not None:
            console.say(o, ev)
            if isinstance(ev, SessionStarted):
                self.started(ev)
            elif isinstance(ev, TicksEnded) and ev.loop is not None:  # (a scheduler's: always)
                spin = 0 if ev.loop.device_paced else self.sleeper.spin
                cpu0, wall0 = self._ticks0 or (time.process_time(), self.clock())
                cpu, wall, host = time.process_time() - cpu0, (self.clock() - wall0) / 1e9, HostMarks.now()
                self._stats = LoopStats.of(ev.loop, cpu, wall, spin, host - self._host0)
                self.ticking, self._ticks0 = False, None
                self.close_device()
            elif isinstance(ev, AdmissionChanged):  # the kernel's filter follows the endpoint
                self.tr.admit(ev.admission)
                self.tr.max_datagram = ev.admission.max_bytes  # refused by length in the transport
            elif isinstance(ev, Failed):
                raise SessionError(console.failure(o, self.tr, ev))
            elif (line := console.log_line(ev)) is not None:
                if isinstance(ev, ClockShifted):  # the session clock moved: so does its tick 0 here
                    self._starts[self.session] -= ev.ticks * self._period
                if self.log is not None:
                    self.log.event((self.clock() - self._starts[self.session]) / 1e9, *line)
            elif isinstance(ev, SessionEnded):
                self.ended(ev)

    def started(self, ev: SessionStarted) -> None:
        o, session = self.opts, ev.params.session
        self.session, self.in_session, self.ticking, self.device = session, True, True, ev.device
        self._period, self._ticks0, self._stats = round(ev.params.dt * 1e9), None, None
        self._first = ev.t0_ns + (ev.k0 - (1 if ev.device else 0)) * self._period  # a device: a tick before
        self.log = self.records.logs.get(session)
        self._starts[session] = ev.start_ns
        self._waited[session] = (self.clock() - self._created) / 1e9
        self.watch.start(self.log, ev.k0, ev.rtt_ns or None, ev.device)
        self.warnings = setup_realtime(o.rt_priority) + self._lock_warnings + self.tr.warnings
        self._host0 = HostMarks.now()
        freeze_heap()  # before the first tick: the GC walks only what the ticks make
        for w in self.warnings:
            print(f"teleop {o.role}: warning: {w}", file=sys.stderr)
        if self.log is not None:
            self.log.status("session", 0.0, {"role": o.role, "pid": os.getpid(), "params": asdict(ev.params)})
            self.log.event(0.0, "session_start", f"session {session}, first tick {ev.k0}")

    def ended(self, ev: SessionEnded) -> None:
        """One session is over: the process's figures join the endpoint's; ROLE.json and the log."""
        session, stats = ev.summary.params.session, self._stats
        self._stats = None
        loop = stats.summary() if stats is not None else None
        proc = console.process_summary(
            self.opts, self.tr, self.stop.signal, self._waited.get(session), loop, self.warnings
        )
        s = SessionSummary(ev.summary, proc)
        replaced = ev.reason == EndReason.REPLACED
        t_end = (self.clock() - self._starts.pop(session, self.clock())) / 1e9
        why = {EndReason.PEER_BYE: "peer said bye", EndReason.STOPPED: f"signal {self.stop.signal}"}
        if self.log is self.records.logs.get(session):
            self.log = self.watch.log = None
        self.records.end(s, session, t_end, why.get(ev.reason, ev.reason.value), replaced)
        self.in_session = ev.reason != EndReason.PEER_SILENT  # (else it listens for an operator)
        self.summary = s
