"""The tick clock beside the endpoint: when each tick of a session runs, sans I/O, in the caller's time.

A :class:`Scheduler` wraps an :class:`teleop.session.endpoint.Endpoint` as aioquic's
``H3Connection`` wraps its ``QuicConnection``: it owns it, consumes its events and forwards them,
and has the same surface, so the real-time runner (``shell.runner``) drives it and nothing else::

    sched.receive_datagram(data, addr, now_ns)   # queued while the ticks run: fed before a tick
    for data, addr in sched.datagrams_to_send(now_ns): sock.sendto(data, addr)
    sched.get_timer()  /  sched.handle_timer(now_ns)
    sched.next_event()                           # the endpoint's, and TicksEnded, AdmissionChanged

The 1 kHz ticks are its timers: ``get_timer`` says each tick's deadline (or its grace limit, or a
paced device's silence limit) and ``handle_timer`` runs the tick that is due, early in the spin
before its deadline if called then.  It holds the policy of ``teleop.session.schedule`` (the early
drain, the early tick, grace, skips, device pacing, the loop's figures); the endpoint holds the
session and runs a tick when told (:meth:`Endpoint.tick`).  The endpoint never queues what it
receives: what arrives while the ticks run waits here, the one queue before the playout buffer, and
is fed before the tick it belongs to, so a takeover's new session starts between two ticks, never
in the middle of one.  Like the endpoint it never reads a clock, and it runs in virtual time in the
tests (``tests/vnet.py``, ``tests/test_schedule.py``).
"""

from __future__ import annotations

import dataclasses
from collections import deque
from collections.abc import Callable
from typing import Any, TypeAlias

from teleop.session.admission import Admission
from teleop.session.endpoint import EVENTS_KEPT, Endpoint
from teleop.session.events import AdmissionChanged, Event, SessionEnded, SessionStarted, TicksEnded
from teleop.session.link import Addr
from teleop.session.port import Port
from teleop.session.schedule import (
    ADMIT_EVERY_NS,
    DEVICE_SILENT_NS,
    EARLY_COST_START_NS,
    EARLY_MARGIN_NS,
    LoopFigures,
    TickPolicy,
)

__all__ = ["GRACE_RESUME_TICKS", "GRACE_STREAK", "Monitor", "Scheduler"]

GRACE_STREAK = 3  # grace waits missed in a row before grace rests
GRACE_RESUME_TICKS = 200  # ... for this many ticks (the link is late by ms, not us)

#: Called after each tick's datagrams left: (port, tick, session time, the loop's figures).  The
#: shell's live view and status line; the port is the one the endpoint's factory made.
Monitor: TypeAlias = Callable[[Port, int, float, LoopFigures], None]
#: A tick whose datagrams are about to leave, or left: (k, deadline, its session's port and figures).
_Departure: TypeAlias = tuple[int, int, Port, LoopFigures]


def _no_grace(limit_us: float) -> dict[str, Any]:
    return {"limit_us": limit_us, "waits": 0, "missed": 0, "waited_us_total": 0.0}


class Scheduler:
    """Runs an endpoint's ticks as timers (the module docstring); ``monitor`` is told of each."""

    def __init__(
        self, endpoint: Endpoint, policy: TickPolicy | None = None, monitor: Monitor | None = None
    ) -> None:
        self.endpoint = endpoint
        self.policy = policy = policy or TickPolicy()
        self.grace_limit_ns = round(policy.grace_us * 1e3)
        self._monitor = monitor
        self._events: deque[Event] = deque(maxlen=EVENTS_KEPT)
        self._sessions = 0  # sessions started: one more once a takeover's new session began
        self._now = 0  # the latest time handle_timer was given: "at once"
        self._next_k = 0  # the tick due next
        self._loop: LoopFigures | None = None
        self._pending: deque[tuple[bytes, Addr, int]] = deque()  # received, fed before the next tick
        self._cost = EARLY_COST_START_NS  # a datagram's cost to feed, running mean (the early drain)
        self._fed_at: int | None = None
        self._early_at: tuple[int, int] | None = None  # the tick run early and its deadline, not yet met
        self._hold_until = 0  # an early tick's datagrams (and what follows them) leave at its deadline
        self._quiet_until = 0  # handle_timer has nothing to do before this (the spin's early work done)
        self._grace_until: int | None = None
        self._grace_t0 = 0
        self.grace = _no_grace(policy.grace_us)
        self._grace_streak = self._grace_resume = 0
        self._out_tick: _Departure | None = None  # a tick's datagrams about to leave
        self._departed: _Departure | None = None  # ... and left (settle them)
        self._device: Any = None  # paces the ticks (a real arm)
        self._device_last = 0
        self._admit_next = 0
        self._admitted: Admission | None = None
        self._pump()

    # --- the surface ------------------------------------------------------------------------
    def next_event(self) -> Event | None:
        return self._events.popleft() if self._events else None

    @property
    def awaiting_payload(self) -> bool:
        """A tick is waiting for its payload (grace): a datagram that comes before :meth:`get_timer`
        may let it run, so a caller should wait on its socket rather than sleep."""
        return self._grace_until is not None

    def receive_datagram(self, data: bytes, addr: Addr, now_ns: int) -> None:
        """A datagram received at ``now_ns``.  While the ticks run (and no device paces them) it is
        only queued, for :meth:`handle_timer`: the early drain decides when each is worth its cost."""
        if self._device is None and self.endpoint.running:
            self._pending.append((data, addr, now_ns))
            self._quiet_until = 0
            return
        self.endpoint.receive_datagram(data, addr, now_ns)
        self._pump()

    def datagrams_to_send(self, now_ns: int) -> list[tuple[bytes, Addr]]:
        """The endpoint's datagrams; an early tick's, and what came after them, wait for its deadline."""
        if now_ns >= self._admit_next:
            self._admit(now_ns)
        if now_ns < self._hold_until:
            return []
        if self._out_tick is not None:
            self._departed, self._out_tick = self._out_tick, None
        out = self.endpoint.datagrams_to_send(now_ns)
        self._pump()
        return out

    def get_timer(self) -> int | None:
        """When :meth:`handle_timer` must be called next (ns on the caller's clock); None: finished.
        While the ticks run: the next tick's deadline, its grace limit, or a paced device's silence
        limit; else the endpoint's own timer."""
        if self._departed is not None:
            return self._now  # a tick's datagrams left: settle them
        running = self.endpoint.running
        if running and self._device is None:
            if self._grace_until is not None:  # what came may be the payload
                ready = self._pending or self._payload_ready(self._next_k)
                return self._now if ready else self._grace_until
            d = self._early_at[1] if self._early_at is not None else self._deadline(self._next_k)
            # What came is fed at once, but in the spin only as the early drain allows.
            return self._now if self._pending and self._now < d - self.policy.early_ns else d
        if running:
            return self._device_last + DEVICE_SILENT_NS
        if self._hold_until > self._now:
            return self._hold_until
        if self._pending:
            return self._now
        return self.endpoint.get_timer()

    def handle_timer(self, now_ns: int) -> None:
        """The timer is due.  It may also be called before a tick's deadline, in the time a precise
        caller spins before it: then it feeds what arrived and may run the tick early
        (``teleop.session.schedule``); with a paced device, each call after the device ticked runs
        the session's tick its clock says."""
        if now_ns < self._quiet_until:
            return  # in a spin, with nothing to do before the deadline (called on every turn of it)
        self._now = now_ns
        if self._departed is not None:
            self._settle(now_ns)
            return
        if self.endpoint.running:
            self._tick(now_ns)
            return
        if self._early_at is not None and now_ns >= self._early_at[1]:
            self._met_early(now_ns)
        while self._pending:  # what came before the ticks ended
            self.endpoint.receive_datagram(*self._pending.popleft())
            self._pump()
        self.endpoint.handle_timer(now_ns)
        self._pump()

    def stop(self, now_ns: int) -> None:
        """Stop locally (a signal): the session lingers and ends."""
        self.endpoint.stop(now_ns)
        self._pump()

    def fault(self, now_ns: int, why: str) -> None:
        """This side's device ended the session (:meth:`Endpoint.fault`): nothing is ticked after it."""
        self.endpoint.fault(now_ns, why)
        self._pump()

    # --- the endpoint's events ------------------------------------------------------------------
    def _pump(self) -> None:
        """The endpoint's events, in order, into ours: a session's start sets its ticks up, the end
        of its ticks gives their figures, its summary gets the grace figures."""
        while (ev := self.endpoint.next_event()) is not None:
            if isinstance(ev, SessionStarted):
                ev = self._started(ev)
            elif isinstance(ev, TicksEnded):
                ev = self._ticks_ended(ev)
            elif isinstance(ev, SessionEnded):
                ev = dataclasses.replace(ev, summary=dataclasses.replace(ev.summary, grace=dict(self.grace)))
            self._events.append(ev)

    def _started(self, ev: SessionStarted) -> SessionStarted:
        port = self.endpoint.port
        assert port is not None
        period = round(ev.params.dt * 1e9)
        device = port.paced_device()
        self._sessions += 1
        self._device, self._device_last = device, ev.t0_ns + (ev.k0 - 1) * period
        self._loop = LoopFigures(period, device_paced=device is not None)
        self._next_k, self._early_at, self._grace_until, self._hold_until = ev.k0, None, None, 0
        self._quiet_until = self._admit_next = 0
        self.grace = _no_grace(self.policy.grace_us)
        self._grace_streak = self._grace_resume = 0
        return dataclasses.replace(ev, device=device)

    def _ticks_ended(self, ev: TicksEnded) -> TicksEnded:
        loop = self._loop
        assert loop is not None
        if self._grace_until is not None:  # its deadline was counted; waiting, it never runs
            loop.not_run()
        # (an early tick's deadline is still met: handle_timer then)
        self._device, self._grace_until, self._admit_next = None, None, 0
        return TicksEnded(ev.k, loop)

    def _admit(self, now_ns: int) -> None:
        self._admit_next = now_ns + ADMIT_EVERY_NS
        a = self.endpoint.admission(now_ns)
        if a != self._admitted:
            self._admitted = a
            self._events.append(AdmissionChanged(a))

    # --- the ticks --------------------------------------------------------------------------
    def _deadline(self, k: int) -> int:
        ep = self.endpoint
        assert ep.params is not None
        return ep.t0_ns + k * round(ep.params.dt * 1e9)

    def _feed(self, limit: int | None = None) -> bool:
        """Feed the queued datagrams (at most ``limit``); False if the session they fed to ended or
        was replaced on the way (a takeover's start): the tick they came before is not run."""
        sessions, n = self._sessions, 0
        while self._pending and (limit is None or n < limit):
            self.endpoint.receive_datagram(*self._pending.popleft())
            self._pump()
            n += 1
            if self._sessions != sessions or not self.endpoint.running:
                return False
        return True

    def _run(self, k: int, deadline: int, now: int, loop: LoopFigures) -> bool:
        """Run tick ``k`` (due at ``deadline``) now; its datagrams leave with the next send."""
        port = self.endpoint.port
        assert port is not None
        ran = self.endpoint.tick(k, now)
        self._pump()
        if ran:
            self._out_tick = (k, deadline, port, loop)
        return ran

    def _tick(self, now: int) -> None:
        if self._device is not None:
            self._paced_tick(now)
            return
        policy, k = self.policy, self._next_k
        # An early tick's deadline stays its own (its tick may have moved t0: the phase, a skew).
        deadline = self._early_at[1] if self._early_at is not None else self._deadline(k)
        if now < deadline:
            if now >= deadline - policy.early_ns:
                self._early(k, deadline, now)
            else:
                self._fed_at = None
                self._feed()
            return
        self._fed_at = None  # (the spin is over: the next call's time says nothing of a feed's cost)
        if self._early_at is not None:  # run early: its deadline is met now, its datagrams leave
            self._met_early(now)
            self._next_k = k + 1
            self._feed()
            return
        if not self._feed():
            return
        loop, params = self._loop, self.endpoint.params
        assert loop is not None and params is not None
        if self._grace_until is None:
            period = round(params.dt * 1e9)
            late = now - deadline
            if late > policy.max_catchup * period:  # a stall: skip, counted, rather than catch up
                # ... the session's ticks only: a stall past its end skips to the end (the loop's
                # ticks and skipped ticks add up to the session's, a report's invariant).
                jump = min(late // period, max(params.ticks - k, 0))
                loop.skipped += jump
                k += jump
                late -= jump * period
                deadline += jump * period
                self._next_k = k
            loop.started(late, now)
            if self._grace_needed(k):
                self.grace["waits"] += 1
                self._grace_until, self._grace_t0 = deadline + self.grace_limit_ns, now
                return
        else:
            if not self._payload_ready(k) and now < self._grace_until:
                return
            self._grace_until = None
            self._grace_result(k, now - self._grace_t0)
        self._next_k = k + 1
        if not self._run(k, deadline, now, loop):  # not run (stopped during its grace, a skew)
            loop.not_run()

    def _met_early(self, now: int) -> None:
        """The deadline of the tick run early is met (also once that tick ended the session)."""
        assert self._early_at is not None and self._loop is not None
        deadline, self._early_at = self._early_at[1], None
        self._loop.started(now - deadline, now)

    def _early(self, k: int, deadline: int, now: int) -> None:
        """Before the deadline, in the spin's time: the early drain, then maybe the early tick."""
        policy = self.policy
        if self._fed_at is not None:  # the datagram fed at the last call (in this spin) cost this
            self._cost += (min(now - self._fed_at, policy.early_ns) - self._cost) // 8
            self._fed_at = None
        if self._early_at is not None:
            return
        if not policy.early_tick:
            if self._pending and now + self._cost <= deadline - EARLY_MARGIN_NS:
                self._fed_at = now
                self._feed(1)
            else:
                self._quiet_until = deadline  # nothing more before it: the caller's spin stays tight
            return
        # What arrived before this tick is its (left for after the tick, every payload would count
        # a tick late whenever the playout buffer held something releasable, and auto playout would
        # add that tick for good: measured, most of a session one tick above its floor).
        if not self._feed():
            return  # a takeover's new session
        self._quiet_until = deadline
        params, loop = self.endpoint.params, self._loop
        assert params is not None and loop is not None
        if self._grace_needed(k) or k + 1 >= params.ticks:
            return  # a payload to wait for, or the last tick: at the deadline
        self._hold_until = deadline
        self._early_at = (k, deadline)
        if not self._run(k, deadline, now, loop):  # not run (a skew moved tick 0): no loop tick
            self._early_at, self._hold_until = None, 0

    def _paced_tick(self, now: int) -> None:
        """A device that paces the session ticked at ``now``: the session tick the clock says (the
        tick due nearest ``now``, or the next if that one ran: never twice; ticks it skipped are
        missed deadlines, counted; over a tick ahead of the clock, it holds, counted).  Silent for
        :data:`DEVICE_SILENT_NS`, it ends the session with a fault."""
        ep, loop = self.endpoint, self._loop
        assert ep.params is not None and loop is not None
        if now >= self._device_last + DEVICE_SILENT_NS:
            self.fault(now, f"the device did not tick for {(now - self._device_last) / 1e9:.1f} s")
            return
        self._device_last = now
        period, k = round(ep.params.dt * 1e9), self._next_k
        due = (now - ep.t0_ns + period // 2) // period
        if k > due + 1:
            loop.ahead += 1
            hold = getattr(self._device, "hold", None)
            if callable(hold):
                hold()
            return
        if due > k:
            loop.missed += due - k
            k = due
        deadline = self._deadline(k)
        loop.started(now - deadline, now)
        self._next_k = k + 1
        if not self._run(k, deadline, now, loop):
            loop.not_run()

    def _settle(self, now: int) -> None:
        """A tick's datagrams left: what could wait for them (the record's seal, the live view)."""
        assert self._departed is not None
        k, deadline, port, loop = self._departed  # (its own session's, if another began since)
        self._departed = None
        loop.departed(now, deadline)
        port.settle()
        port.loop_timing(k, loop.last_lateness_ns)
        if self._monitor is not None:
            self._monitor(port, k, self.endpoint.session_time(now), loop)

    # --- grace ------------------------------------------------------------------------------
    def _grace_needed(self, k: int) -> bool:
        """Whether tick ``k`` waits for its payload: due, not here, and the peer heard from."""
        port = self.endpoint.port
        if port is None or not self.grace_limit_ns or k < self._grace_resume:
            return False
        return not port.payload_ready(k) and port.heard_from_peer

    def _payload_ready(self, k: int) -> bool:
        port = self.endpoint.port
        return port is not None and port.payload_ready(k)

    def _grace_result(self, k: int, waited_ns: int) -> None:
        self.grace["waited_us_total"] += waited_ns / 1e3
        if self._payload_ready(k):
            self._grace_streak = 0
            return
        self.grace["missed"] += 1
        self._grace_streak += 1
        if self._grace_streak >= GRACE_STREAK:  # a delayed or jittery link: packets are ms late; rest
            self._grace_resume = k + GRACE_RESUME_TICKS
            self._grace_streak = 0
