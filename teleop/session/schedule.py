"""When a real-time endpoint ticks, and what its loop's timing was: sans-I/O, in the caller's time.

The policy that used to live in the real-time runner (``shell.runner``) is here, so that it
runs, and is tested, in virtual time: the scheduler's (``teleop.session.scheduler``) ``get_timer``
says each tick's deadline, its ``handle_timer`` runs the tick that is due (:class:`TickPolicy`), and
:class:`LoopFigures` counts how the deadlines were met.  Tick ``k`` of a session is due at
``t0 + k * period``; ``t0`` is the endpoint's and moves (the teleoperator's phase follows the
operator: ``teleop.session.link.phase``).

**Early work.** A precise runner sleeps until a spin before each deadline and spins the rest, and
that spin is CPU burnt for timing alone.  It may call ``handle_timer`` during the spin: the scheduler
then feeds what arrived (the *early drain*: each datagram only while its expected cost, a running
mean, still ends :data:`EARLY_MARGIN_NS` before the deadline) and, with ``early_tick``, runs the tick
itself and holds its datagrams until the deadline.  Why: on a host whose wake-ups are late by tens
of microseconds the spin is learned near its bound, about as long as a tick's own work, so doing
the work in it takes most of one off the other, and what the tick touches is warm in the cache
(``bench.phases``: a tick after a sleep costs 2-3x a hot one).  A tick's inputs are all there
early: its payload was filed under it, its device models run on the tick's time ``k dt``; a payload
that is due and missing is waited for at the deadline instead (grace).  What changes is that a
datagram arriving in the rest of the spin is filed under the next tick, as if it had arrived that
much later; the datagrams still leave on the deadline.

**Figures** (:class:`LoopFigures`): lateness is ``start - deadline`` of each tick (the deadline
instant, whether it ran early or not); period error is ``(start_k - start_{k-1}) - period``.  An
*overrun* is a tick started more than one period late.  More than ``max_catchup`` ticks late (a
stall: the VM's host stole the CPU), the missed ticks are *skipped* (counted) instead of run back to
back.  A device that paces the loop (a real arm) misses deadlines instead (*missed*, never run) or
comes over a tick early (*ahead*, held).  Departures (when each tick's datagrams left) are what the
peer sees of the loop's timing.
"""

from __future__ import annotations

from dataclasses import dataclass

from teleop.session.link.quantiles import Quantiles

__all__ = ["ADMIT_EVERY_NS", "EARLY_COST_START_NS", "EARLY_MARGIN_NS", "LoopFigures", "TickPolicy"]

#: The early drain stops this long before the deadline, and starts from this guess of a
#: datagram's cost to feed (then learns it from the times it is called at).
EARLY_MARGIN_NS = 10_000
EARLY_COST_START_NS = 30_000
#: How often, at most, the endpoint looks at its admission (a takeover becomes possible 50 ms after
#: the operator falls silent; a flood's sampling starts within this of the limiter's first drop).
ADMIT_EVERY_NS = 16_000_000
#: A device-paced session ends with a fault when its device has not ticked for this long.
DEVICE_SILENT_NS = 1_000_000_000
MAX_CATCHUP = 20


@dataclass(frozen=True)
class TickPolicy:
    """How a :class:`teleop.session.scheduler.Scheduler` runs an endpoint's ticks.  ``early_tick``:
    run a tick in the time before its deadline when ``handle_timer`` is called then (``--tick-at
    wake``), holding its datagrams until the deadline; else from the deadline (``--tick-at
    deadline``).  ``early_ns``: the earliest before a deadline that counts as the spin's time (the
    runner's spin bound).  ``grace_us``: how long past its deadline a tick waits for a payload that
    is due and missing (``--grace-us``; 0: never)."""

    early_tick: bool = True
    early_ns: int = 200_000
    max_catchup: int = MAX_CATCHUP
    grace_us: float = 400.0


def _q() -> Quantiles:
    return Quantiles(lo=1.0, hi=1e12)


class LoopFigures:
    """The timing of one session's ticks (module docstring), in streaming percentiles."""

    def __init__(self, period_ns: int, device_paced: bool = False) -> None:
        self.period_ns = period_ns
        self.device_paced = device_paced
        self.ticks = self.overruns = self.skipped = self.missed = self.ahead = 0
        self.lateness_q, self.period_error_q = _q(), _q()
        self.send_lateness_q, self.send_period_error_q = _q(), _q()
        self.last_lateness_ns = 0
        self._last_start = self._last_departure = 0

    def started(self, late_ns: int, now_ns: int) -> None:
        """A tick's deadline instant was met at ``now_ns``, ``late_ns`` after it."""
        self.last_lateness_ns = late_ns
        self.lateness_q.add(late_ns)
        if self.ticks:
            self.period_error_q.add(now_ns - self._last_start - self.period_ns)
        if late_ns > self.period_ns:
            self.overruns += 1
        self._last_start = now_ns
        self.ticks += 1

    def not_run(self) -> None:
        """The tick whose deadline :meth:`started` counted did not run (the session was stopped
        while it waited for its payload, a skew moved tick 0): ``ticks`` counts ticks run, as the
        log does (its lateness sample stays: the loop did wake for it)."""
        self.ticks -= 1

    def departed(self, now_ns: int, deadline_ns: int) -> None:
        """The datagrams of the tick due at ``deadline_ns`` left at ``now_ns``."""
        self.send_lateness_q.add(now_ns - deadline_ns)
        if self._last_departure:
            self.send_period_error_q.add(now_ns - self._last_departure - self.period_ns)
        self._last_departure = now_ns
