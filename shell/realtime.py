"""A 1 kHz scheduler on absolute deadlines of the monotonic clock.

Why not asyncio timers: libuv (uvloop) timers have millisecond resolution and Linux's default
timer slack is 50 us, so a loop on ``call_later`` or relative sleeps drifts and jitters.  Here tick
``k`` is due at ``t0 + k * period`` exactly; the loop sleeps (``time.sleep``, which uses
``clock_nanosleep`` on Linux) until ``spin`` before the deadline, then spins on the clock for the
last stretch.  Deadlines never accumulate error, because they are computed, not chained.

**The spin is learned.**  Spinning covers ``time.sleep``'s wake-up latency, which is a property of
the host (timer slack, C-states, a VM's scheduler): a few microseconds on a quiet kernel, tens on a
shared VM.  A fixed 100 us spin burns 10% of a core when the host wakes in 20 us, and that CPU is
what the robot's own controller does not get.  So the ticker measures every wake-up (how long after
the asked time ``sleep`` returned) and spins only that host's high percentile plus a margin
(:class:`SpinLearner`), within ``[min_spin, spin]``.  The 99.9th percentile, not the 99th: a
tick that starts late makes two period errors (late, then early), so the 99th percentile of the
period error stays where a fixed spin would put it only if well under 0.5% of wake-ups overrun.
It starts at ``spin`` and adapts once a second, so a host that gets noisier widens the spin within
a second.

Lateness is ``start - deadline`` of each tick; period error is ``(start_k - start_{k-1}) - period``.
An *overrun* is a tick started more than one period late.  When the loop falls more than
``max_catchup`` ticks behind (a stall: the VM's host stole the CPU), the missed ticks are *skipped*
(counted) instead of run back to back, so the session clock stays true.

**Device-paced.**  A device with its own clock (a real arm: libfranka's read returns once per
robot millisecond) may pace the loop instead of the timer: the runner blocks in the device's
``wait`` and then asks :meth:`Ticker.paced` which session tick to run.  Tick numbers still follow
``t0 + k * period``; a tick of the clock the device skipped is a *missed deadline* (counted, never
run), and no tick runs twice.

**When the datagrams leave.**  The endpoint may run a tick before its deadline, in the time the
spin would burn, and send its datagrams at the deadline (``teleop.session.schedule``, ``--tick-at
wake``), or run it from the deadline (``--tick-at deadline``).  The real-time runner
(``shell.runner``) sleeps with :class:`PreciseSleep` and takes its figures from the endpoint
(``teleop.session.schedule.LoopFigures``, the same accounting as here: :meth:`LoopStats.of`).
The figures above are of the deadline instant either way; :meth:`Ticker.departed` adds the
instant each tick's datagrams left (``send_lateness_us``, ``send_period_error_us``), which is what
the peer sees of the loop's timing in both modes.

Real-time priority (SCHED_FIFO) and 1 ns timer slack are requested where permitted, and the
process's memory is locked (:func:`lock_memory`); where not, they return warnings and the run goes
on.  Under SCHED_FIFO a thread that never sleeps is throttled by the kernel, which is another
reason to sleep most of the period.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import importlib
import os
import resource
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from teleop.session.link.quantiles import Quantiles
from teleop.session.schedule import LoopFigures

PR_SET_TIMERSLACK = 29


def _libc() -> ctypes.CDLL:
    """The C library, with ``errno`` kept for :func:`ctypes.get_errno` (raises OSError if absent)."""
    return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)


def setup_realtime(priority: int | None = 10, timer_slack_ns: int = 1) -> list[str]:
    """Ask for SCHED_FIFO at ``priority`` (None: leave the policy) and a tight timer slack.

    Returns human-readable warnings for what was not permitted; never raises.
    """
    warnings: list[str] = []
    try:
        if _libc().prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(timer_slack_ns), 0, 0, 0) != 0:
            warnings.append(
                f"timer slack not set (errno {ctypes.get_errno()}); sleeps may wake up to 50 us late"
            )
    except (OSError, AttributeError) as e:
        warnings.append(f"timer slack not set ({e}); sleeps may wake up to 50 us late")
    if priority is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except (PermissionError, OSError, AttributeError) as e:
            warnings.append(f"SCHED_FIFO priority {priority} not permitted ({e}); running at normal priority")
    return warnings


MCL_CURRENT, MCL_FUTURE = 1, 2  # <sys/mman.h> on Linux


def lock_memory() -> list[str]:
    """``mlockall(MCL_CURRENT | MCL_FUTURE)``: every page this process maps now or later stays in RAM.

    Why: a page the kernel reclaims is read back from disk the next time the loop touches it (a
    major fault), and no scheduling priority shortens that read.  On this project's test VM the
    kernel's DAMON pages out what went unused for a minute; code a session runs for the first time
    (a link lost, a takeover) may be such a page.  Locking is what real-time Linux guides and
    cyclictest do.  Costs: the libraries' pages read in now (~115 ms, ~260 MB resident for a
    process with numpy, Zenoh and uvloop, measured) and each new thread's stack touched at once
    (~3 ms).  Needs CAP_IPC_LOCK or a large enough ``ulimit -l``; else a warning, nothing locked."""
    try:
        if _libc().mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
            err = ctypes.get_errno()
            limit = resource.getrlimit(resource.RLIMIT_MEMLOCK)[0]
            allowed = "unlimited" if limit == resource.RLIM_INFINITY else f"{limit // 1024} KiB"
            return [
                f"memory not locked (mlockall: {os.strerror(err)}; ulimit -l is {allowed}): a page the "
                "kernel reclaims costs a tick a read from disk"
            ]
    except (OSError, AttributeError) as e:
        return [f"memory not locked ({e}): a page the kernel reclaims costs a tick a read from disk"]
    return []


def major_faults() -> int:
    """Page faults of this process so far that read from disk (a tick that took one waited for it)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_majflt


def host_steal_ms(path: str = "/proc/stat") -> float | None:
    """CPU time the hypervisor gave to other guests so far, summed over this machine's CPUs (ms),
    from ``/proc/stat``'s ``steal`` column; None where there is none (not Linux, not a VM's kernel,
    unreadable).  A vCPU with work that the host does not run stalls every thread on it,
    SCHED_FIFO or not, and that shows here; a timer the host delivers late to an idle vCPU (a loop
    asleep until its tick) stalls it as much and does not (traced on this project's VM: most of
    its millisecond stalls are that kind).  The file is the kernel's, read before and after the
    ticks, never in one; its first line is still checked, as any file's."""
    try:
        with open(path, "rb") as f:
            head = f.readline(4096).split()
        # cpu user nice system idle iowait irq softirq steal ...
        steal = int(head[8]) if head[:1] == [b"cpu"] else -1
        hz = os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None
    return steal * 1e3 / hz if steal >= 0 and hz > 0 else None


@dataclass(frozen=True)
class HostMarks:
    """What the host did so far that no priority of ours prevents (:func:`major_faults`,
    :func:`host_steal_ms`); two marks' difference is what it did to a session."""

    major_faults: int
    steal_ms: float | None

    @classmethod
    def now(cls) -> HostMarks:
        return cls(major_faults(), host_steal_ms())

    def __sub__(self, before: HostMarks) -> HostMarks:
        steal = None if self.steal_ms is None or before.steal_ms is None else self.steal_ms - before.steal_ms
        return HostMarks(self.major_faults - before.major_faults, steal)


#: Modules numpy imports only on first use, which a tick would pay for: ``np.quantile`` (the phase
#: estimator, ``teleop.session.link.phase``, every 100 ticks) calls ``np.unique``, whose first call
#: imports ``numpy.ma``: 11-19 ms of one early tick on both sides (measured), a stall that made the
#: auto playout add 8-13 ms to every payload for the next 2 s.
LAZY_MODULES = ("numpy.ma",)


def freeze_heap() -> None:
    """Import :data:`LAZY_MODULES`, collect, then move every object into the cyclic GC's permanent
    generation (``gc.freeze``).

    Why: a full collection during the ticks would walk the ~30 000 objects of the imports and the
    session's setup (measured 10 ms in-process, a skipped tick); frozen, it walks only what the
    ticks made (0.6 us).  Collected first, because a frozen cycle is never freed, and an earlier
    session's port is one (its counters call back into its recorder): each takeover would leak one.
    Costs a full collection of what is not frozen yet: ~17 ms the first time (the imports), ~0.1 ms
    at a session's start after that, so the runner calls it once before the handshake too."""
    for name in LAZY_MODULES:
        importlib.import_module(name)
    gc.collect()
    gc.freeze()


def percentiles_us(samples_ns: npt.NDArray[np.int64]) -> dict[str, float]:
    """p50, p99, p99.9 and max of absolute values, in microseconds."""
    if samples_ns.size == 0:
        return {"p50": 0.0, "p99": 0.0, "p999": 0.0, "max": 0.0}
    a = np.abs(samples_ns.astype(np.float64)) / 1e3
    p50, p99, p999 = np.percentile(a, [50, 99, 99.9])
    return {"p50": float(p50), "p99": float(p99), "p999": float(p999), "max": float(a.max())}


@dataclass
class LoopStats:
    """What the scheduler saw; ``lateness_ns[i]`` is tick i's start minus its deadline (kept only by
    a ticker with a ``capacity``; a session's loop streams it to its log instead, and its
    percentiles come from ``lateness_q`` and ``period_error_q``)."""

    period_ns: int
    ticks: int
    overruns: int
    skipped: int
    lateness_ns: npt.NDArray[np.int64]
    period_error_ns: npt.NDArray[np.int64]
    cpu_s: float
    wall_s: float
    lateness_q: Quantiles | None = None
    period_error_q: Quantiles | None = None
    spin_ns: int = 0  # the spin in use at the end (learned, see SpinLearner)
    send_lateness_q: Quantiles | None = None  # when each tick's datagrams left (Ticker.departed)
    send_period_error_q: Quantiles | None = None
    missed_deadlines: int = 0  # device-paced: session ticks the device's clock skipped
    device_ahead: int = 0  # device-paced: device ticks over a tick ahead of the clock (held, no tick)
    device_paced: bool = False
    major_faults: int | None = None  # page faults that read from disk, the session's start to its end
    host_steal_ms: float | None = None  # the machine's CPU time stolen by its hypervisor, likewise

    def summary(self) -> dict[str, object]:
        unkept = np.zeros(0, dtype=np.int64)  # departures are kept as percentiles only
        return {
            "ticks": self.ticks,
            "overruns": self.overruns,
            "skipped": self.skipped,
            "period_us": self.period_ns / 1e3,
            "period_error_us": _percentiles(self.period_error_q, self.period_error_ns),
            "lateness_us": _percentiles(self.lateness_q, self.lateness_ns),
            "cpu_s": self.cpu_s,
            "wall_s": self.wall_s,
            "cpu_fraction": self.cpu_s / self.wall_s if self.wall_s > 0 else 0.0,
            "spin_us": self.spin_ns / 1e3,
            **({} if self.major_faults is None else {"major_faults": self.major_faults}),
            **({} if self.host_steal_ms is None else {"host_steal_ms": self.host_steal_ms}),
            "send_lateness_us": _percentiles(self.send_lateness_q, unkept),
            "send_period_error_us": _percentiles(self.send_period_error_q, unkept),
            **(
                {
                    "device_paced": True,
                    "missed_deadlines": self.missed_deadlines,
                    "device_ahead": self.device_ahead,
                }
                if self.device_paced
                else {}
            ),
        }

    @classmethod
    def of(
        cls, loop: LoopFigures, cpu_s: float, wall_s: float, spin_ns: int, host: HostMarks | None = None
    ) -> LoopStats:
        """A session's figures: its endpoint's ticks (``teleop.session.schedule``) and this host's
        (``host``: what it did over the session, :class:`HostMarks`)."""
        none = np.zeros(0, dtype=np.int64)
        return cls(
            period_ns=loop.period_ns,
            ticks=loop.ticks,
            overruns=loop.overruns,
            skipped=loop.skipped,
            lateness_ns=none,
            period_error_ns=none,
            cpu_s=cpu_s,
            wall_s=wall_s,
            lateness_q=loop.lateness_q,
            period_error_q=loop.period_error_q,
            spin_ns=spin_ns,
            send_lateness_q=loop.send_lateness_q,
            send_period_error_q=loop.send_period_error_q,
            missed_deadlines=loop.missed,
            device_ahead=loop.ahead,
            device_paced=loop.device_paced,
            major_faults=None if host is None else host.major_faults,
            host_steal_ms=None if host is None else host.steal_ms,
        )


def _percentiles(q: Quantiles | None, samples_ns: npt.NDArray[np.int64]) -> dict[str, float]:
    if q is None or samples_ns.size:
        return percentiles_us(samples_ns)
    p50, p99, p999 = q.percentiles([50, 99, 99.9], absolute=True)
    return {"p50": p50 / 1e3, "p99": p99 / 1e3, "p999": p999 / 1e3, "max": q.max_abs / 1e3}


class SpinLearner:
    """How long to spin before a deadline: the ``quantile`` of recent wake-up latencies plus ``margin``.

    Latencies go in 1 us bins (a list of ints: a tick adds one to a bin, nothing more).  Every
    ``every`` samples the spin is recomputed and the counts are halved, so the estimate follows
    the host over a few seconds while one stalled second is not forgotten at once.  A latency
    beyond ``hi`` lands in the last bin, which asks for the full ``hi`` spin.
    """

    def __init__(
        self, lo_ns: int, hi_ns: int, quantile: float = 0.999, margin_ns: int = 10_000, every: int = 1000
    ) -> None:
        self.lo, self.hi = lo_ns, hi_ns
        self.quantile, self.margin, self.every = quantile, margin_ns, every
        self.bins = [0.0] * (hi_ns // 1000 + 1)  # weights: halved every ``every`` samples
        self.total = 0.0  # weight in the bins (halved with them)
        self._n = 0
        self.spin_ns = hi_ns  # until the first estimate: the bound

    def add(self, latency_ns: int) -> int:
        """One wake-up's latency; returns the spin to use from now on."""
        bins = self.bins
        i = latency_ns // 1000
        bins[i if 0 <= i < len(bins) else (0 if i < 0 else len(bins) - 1)] += 1
        self._n += 1
        if self._n >= self.every:
            self._update()
        return self.spin_ns

    def _update(self) -> None:
        self.total = self.total / 2 + self._n
        self._n = 0
        need, acc, top = self.quantile * self.total, 0.0, len(self.bins) - 1
        for i, c in enumerate(self.bins):
            acc += c
            if acc >= need:
                top = i
                break
        latency = (top + 1) * 1000  # the bin's upper edge
        self.spin_ns = min(self.hi, max(self.lo, latency + self.margin))
        self.bins = [c / 2 for c in self.bins]


class PreciseSleep:
    """Sleep until a spin before a time (``clock_nanosleep``), learning this host's wake-up latency
    (:class:`SpinLearner`); the caller spins the rest, doing in it what may run early."""

    def __init__(
        self, spin_ns: int = 150_000, min_spin_ns: int = 10_000, clock: Callable[[], int] = time.monotonic_ns
    ) -> None:
        self.spin = spin_ns
        self.learner = SpinLearner(min(min_spin_ns, spin_ns), spin_ns) if min_spin_ns < spin_ns else None
        self.clock = clock

    def sleep(self, t_ns: int) -> None:
        remaining = t_ns - self.clock()
        if remaining > self.spin:
            wake = t_ns - self.spin
            time.sleep((remaining - self.spin) / 1e9)
            if self.learner is not None:
                self.spin = self.learner.add(self.clock() - wake)


class Ticker:
    """Blocking absolute-deadline ticker: ``start(t0_ns)``, then ``wait() -> k`` for each tick.

    ``capacity`` > 0 keeps every tick's lateness and period error in arrays (benchmarks); 0 keeps
    only streaming percentiles, so a loop of any length runs in fixed memory (``last_lateness_ns``
    says how late the latest tick started, for the caller's own record).  ``spin_ns`` bounds the
    learned spin (:class:`SpinLearner`) from above and ``min_spin_ns`` from below; equal, the spin
    is fixed."""

    def __init__(
        self,
        period_ns: int = 1_000_000,
        spin_ns: int = 150_000,
        max_catchup: int = 20,
        capacity: int = 0,
        clock: Callable[[], int] = time.monotonic_ns,
        min_spin_ns: int = 10_000,
    ) -> None:
        if period_ns <= 0 or spin_ns < 0 or max_catchup < 1:
            raise ValueError("period must be > 0, spin >= 0, max_catchup >= 1")
        self.period = period_ns
        self.spin = spin_ns  # the spin in use (learned, within [min_spin_ns, spin_ns])
        self.learner = SpinLearner(min(min_spin_ns, spin_ns), spin_ns) if min_spin_ns < spin_ns else None
        self.max_catchup = max_catchup
        self.clock = clock
        self.k = 0
        self.t0 = 0
        self.overruns = 0
        self.skipped = 0
        self.missed = 0  # device-paced: ticks of the session clock the device did not come for
        self.ahead = 0  # device-paced: device ticks that came over a tick before the session clock
        self.device_paced = False
        self._keep = capacity > 0
        self._lateness = np.zeros(max(capacity, 1024) if self._keep else 0, dtype=np.int64)
        self._perr = np.zeros_like(self._lateness)
        self._late_q = Quantiles(lo=1.0, hi=1e12)
        self._perr_q = Quantiles(lo=1.0, hi=1e12)
        self.last_lateness_ns = 0
        self._send_late_q = Quantiles(lo=1.0, hi=1e12)
        self._send_perr_q = Quantiles(lo=1.0, hi=1e12)
        self._last_departure = 0
        self._n = 0
        self._last_start = 0
        self._cpu0 = 0.0
        self._wall0 = 0

    def start(self, t0_ns: int, k0: int = 0) -> None:
        """Tick ``k`` is due at ``t0_ns + k * period``; the first tick run is ``k0`` (a late joiner)."""
        self.t0 = t0_ns
        self.k = k0
        self._cpu0 = time.process_time()
        self._wall0 = t0_ns + k0 * self.period  # wall time and CPU cover the ticking, not the wait

    def deadline(self, k: int) -> int:
        return self.t0 + k * self.period

    def wait(self) -> int:
        """Block until tick ``k``'s deadline; returns ``k`` (which may jump after a skip)."""
        self.sleep()
        return self.spin_to_deadline()

    @property
    def next_deadline(self) -> int:
        """The deadline of the tick :meth:`wait` (or :meth:`spin_to_deadline`) returns next."""
        return self.t0 + self.k * self.period

    def sleep(self) -> None:
        """The first half of :meth:`wait`: sleep until ``spin`` before the next deadline.  A caller
        may then do work that need not wait for the deadline (``shell.process`` reads what
        arrived), in time the spin would otherwise burn, before :meth:`spin_to_deadline`."""
        clock = self.clock
        deadline = self.t0 + self.k * self.period
        remaining = deadline - clock()
        if remaining > self.spin:
            wake = deadline - self.spin
            time.sleep((remaining - self.spin) / 1e9)
            if self.learner is not None:
                self.spin = self.learner.add(clock() - wake)

    def spin_to_deadline(self) -> int:
        """The second half of :meth:`wait`: spin until the deadline; returns the tick."""
        clock = self.clock
        deadline = self.t0 + self.k * self.period
        while clock() < deadline:
            pass
        now = clock()
        late = now - deadline
        if late > self.max_catchup * self.period:
            jump = late // self.period
            self.skipped += int(jump)
            self.k += int(jump)
            late -= jump * self.period
        if late > self.period:
            self.overruns += 1
        self._record(late, now)
        k = self.k
        self.k += 1
        return k

    def paced(self, now: int) -> int | None:
        """Device-paced mode: a device's servo tick (libfranka's ``readOnce``) came at ``now``; returns
        the session tick to run.  The tick number still follows the session clock: the tick due
        nearest ``now``, or the next one if that already ran (never a tick twice); ticks of the clock
        the device did not come for are *missed deadlines*, counted (``missed``), never run.  None:
        the device is more than a tick ahead of the clock (counted, ``ahead``): no tick now."""
        due = (now - self.t0 + self.period // 2) // self.period
        k = self.k
        if k > due + 1:
            self.ahead += 1
            return None
        if due > k:
            self.missed += int(due - k)
            k = int(due)
        late = now - (self.t0 + k * self.period)
        if late > self.period:
            self.overruns += 1
        self._record(late, now)
        self.k = k + 1
        return k

    def departed(self, now: int) -> None:
        """The datagrams of the tick :meth:`spin_to_deadline` last returned left at ``now``."""
        self._send_late_q.add(now - self.deadline(self.k - 1))
        if self._last_departure:
            self._send_perr_q.add(now - self._last_departure - self.period)
        self._last_departure = now

    def _record(self, late: int, now: int) -> None:
        self.last_lateness_ns = late
        self._late_q.add(late)
        if self._n:
            self._perr_q.add(now - self._last_start - self.period)
        if self._keep:
            if self._n == self._lateness.size:
                self._lateness = np.concatenate([self._lateness, np.zeros_like(self._lateness)])
                self._perr = np.concatenate([self._perr, np.zeros_like(self._perr)])
            self._lateness[self._n] = late
            self._perr[self._n] = (now - self._last_start - self.period) if self._n else 0
        self._last_start = now
        self._n += 1

    def stats(self) -> LoopStats:
        n = self._n
        return LoopStats(
            period_ns=self.period,
            ticks=n,
            overruns=self.overruns,
            skipped=self.skipped,
            lateness_ns=self._lateness[:n].copy() if self._keep else self._lateness[:0],
            period_error_ns=self._perr[1:n].copy() if self._keep else self._perr[:0],
            cpu_s=time.process_time() - self._cpu0,
            wall_s=(self.clock() - self._wall0) / 1e9,
            lateness_q=self._late_q,
            period_error_q=self._perr_q,
            spin_ns=self.spin,
            send_lateness_q=self._send_late_q,
            send_period_error_q=self._send_perr_q,
            missed_deadlines=self.missed,
            device_ahead=self.ahead,
            device_paced=self.device_paced,
        )
