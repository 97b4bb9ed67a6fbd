"""The ticker's learned spin (issue 22): it spins as long as the host's wake-ups need, bounded."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from shell.realtime import HostMarks, LoopStats, SpinLearner, Ticker, host_steal_ms
from teleop.session.schedule import LoopFigures


def test_the_spin_follows_the_hosts_wake_up_latency_within_bounds() -> None:
    s = SpinLearner(10_000, 100_000)
    assert s.spin_ns == 100_000  # nothing learned yet: the bound
    for i in range(1000):
        s.add(20_000 + (i % 5) * 1000)  # wake-ups 20-24 us late
    assert s.spin_ns == 25_000 + 10_000  # the bin's upper edge plus the margin
    for _ in range(10_000):
        s.add(3_000)  # a quiet host: the spin shrinks (the old seconds fade by half each), to the floor
    assert s.spin_ns == 14_000
    s.add(5_000_000)  # a stall beyond the bound counts in the last bin
    for i in range(999):
        s.add(-1 if i == 0 else 3_000)
    assert s.spin_ns == 14_000  # 1 in ~2000 is below the 0.1% the quantile leaves out
    for _ in range(2):
        for _ in range(20):
            s.add(500_000)
        for _ in range(980):
            s.add(3_000)
    assert s.spin_ns == 100_000  # a host stalling 2% of its wake-ups gets the whole bound


def test_a_ticker_with_equal_bounds_keeps_its_spin() -> None:
    t = Ticker(spin_ns=100_000, min_spin_ns=100_000)
    assert t.learner is None and t.spin == 100_000
    t.start(0)
    assert Ticker(spin_ns=100_000).learner is not None


def test_departures_are_timed_against_the_deadline_of_the_tick_they_belong_to() -> None:
    """Ticker.departed: when each tick's datagrams left, minus its deadline, and the period error
    between departures (the report's send_lateness_us and send_period_error_us)."""
    now = [0]
    t = Ticker(period_ns=1_000_000, spin_ns=0, min_spin_ns=0, clock=lambda: now[0])
    t.start(0)
    for k, leave in enumerate((30_000, 50_000, 20_000)):
        now[0] = k * 1_000_000
        assert t.spin_to_deadline() == k
        now[0] += leave
        t.departed(now[0])
    s: dict[str, Any] = t.stats().summary()
    late = s["send_lateness_us"]
    assert late == {"p50": 30.0, "p99": pytest.approx(49.6), "p999": pytest.approx(49.96), "max": 50.0}
    assert s["send_period_error_us"]["max"] == 30.0  # 50 - 20: the third left 30 us less than a period after
    assert s["period_error_us"]["max"] == 0.0  # every deadline was met on the dot


_FREEZE_SCRIPT = """
import gc, weakref
from teleop.session.node import PortOptions
from teleop.session.port import Port, make_node
from shell.realtime import freeze_heap

def port():
    node = make_node("operator", scenario="protocol", dof=2, dt=1e-3, b=20.0, codec="none",
                     full_scale=2.0, session=7, options=PortOptions())
    return Port(node)

old = weakref.ref(port().rec)  # a session's port is a cycle: only the cyclic GC frees it
assert old() is not None
freeze_heap()
assert old() is None, "the earlier session's port was frozen, not freed"
assert gc.get_freeze_count() > 1000  # the imports' objects
live = weakref.ref(port().rec)  # made after the freeze: still the GC's to free
gc.collect()
assert live() is None
print("ok")
"""


@pytest.mark.integration  # a child python
def test_freeze_heap_frees_an_earlier_sessions_port_then_freezes_the_rest() -> None:
    """The runner freezes the heap at each session's start (a full collection during the ticks would
    walk the imports' objects); a cycle frozen would never be freed, and a port is one, so it
    collects first.  In a child process: freezing is process-wide."""
    r = subprocess.run([sys.executable, "-c", _FREEZE_SCRIPT], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == "ok", r.stderr


_NO_IMPORT_SCRIPT = """
import sys
from shell.realtime import freeze_heap
from tests.vnet import VirtualNet, params

net = VirtualNet(0.1)
to = net.teleoperator()
op = net.operator(params(codec="none", duration=2.0, netem_forward="delay 1ms 1ms"))
net.seconds(30.0, stop=lambda: bool(op.started) and bool(to.started))
assert op.started and to.started
freeze_heap()  # what the runner does when a session starts, before its first tick
before = set(sys.modules)
net.seconds(30.0, stop=lambda: op.ep.finished and to.ep.finished)
assert op.ep.finished and to.ep.finished
print(sorted(set(sys.modules) - before))
"""


@pytest.mark.integration  # a child python: what a fresh process imports is process-wide
def test_a_sessions_ticks_import_nothing() -> None:
    """An import during the ticks stalls one: numpy imports ``numpy.ma`` on the first ``np.unique``,
    which the phase estimator's ``np.quantile`` calls 100 ticks in (11-19 ms, measured on both
    sides).  The runner's :func:`freeze_heap` imports such modules first; a whole session (jittered,
    so the playout and the phase estimator work) then imports nothing."""
    r = subprocess.run([sys.executable, "-c", _NO_IMPORT_SCRIPT], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", r.stdout


_LOCK_SCRIPT = """
import json, os, resource, sys
from shell.realtime import lock_memory
if sys.argv[1] == "refused":  # no CAP_IPC_LOCK (not root any more) and a 64 KiB ulimit -l
    resource.setrlimit(resource.RLIMIT_MEMLOCK, (65536, 65536))
    os.setgid(65534)
    os.setuid(65534)
warnings = lock_memory()
locked = [ln for ln in open("/proc/self/status") if ln.startswith("VmLck:")][0].split()[1]
print(json.dumps([int(locked), warnings]))
"""


def _locked(case: str) -> tuple[int, list[str]]:
    r = subprocess.run(
        [sys.executable, "-c", _LOCK_SCRIPT, case], capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stderr
    kib, warnings = json.loads(r.stdout)
    return int(kib), list(warnings)


@pytest.mark.integration  # a child python: a memory lock is process-wide
def test_lock_memory_locks_the_process_or_says_why_not() -> None:
    """The runner locks its memory before the handshake, so that no tick waits for a page read back
    from disk (the test VM's kernel pages out what went unused for a minute).  Permitted (root):
    the libraries' pages are locked, no warning.  As another user under a 64 KiB ``ulimit -l``:
    nothing locked, and a warning naming the limit."""
    if os.geteuid() != 0:
        pytest.skip("needs root: to lock ~260 MB, and to become another user for the refused case")
    kib, warnings = _locked("permitted")
    assert warnings == [] and kib > 50_000, (kib, warnings)  # (about 260 MB: numpy, uvloop, Zenoh)
    kib, warnings = _locked("refused")
    assert kib == 0 and len(warnings) == 1, (kib, warnings)
    assert "memory not locked" in warnings[0] and "ulimit -l is 64 KiB" in warnings[0], warnings


def test_the_loop_summary_says_what_the_host_did_when_counted() -> None:
    loop = LoopFigures(1_000_000)
    summary = LoopStats.of(loop, 0.1, 1.0, 0, HostMarks(5, 130.0) - HostMarks(2, 100.0)).summary()
    assert summary["major_faults"] == 3 and summary["host_steal_ms"] == 30.0
    unknown = LoopStats.of(loop, 0.1, 1.0, 0, HostMarks(5, 1.0) - HostMarks(2, None)).summary()
    assert unknown["major_faults"] == 3 and "host_steal_ms" not in unknown  # no steal column: not 0
    assert not {"major_faults", "host_steal_ms"} & set(LoopStats.of(loop, 0.1, 1.0, 0).summary())


def test_host_steal_is_read_from_the_kernels_cpu_line_and_a_bad_file_is_unknown(tmp_path: Path) -> None:
    """/proc/stat's first line, ``steal`` its 8th number, in USER_HZ ticks; anything else: None."""
    hz = os.sysconf("SC_CLK_TCK")
    f = tmp_path / "stat"
    f.write_text("cpu  10 0 5 900 1 0 2 37 0 0\ncpu0 5 0 2 450 0 0 1 20 0 0\n")
    assert host_steal_ms(str(f)) == 37 * 1e3 / hz
    bad_lines = (
        "cpu 1 2 3 4\n",  # no steal column (an old kernel)
        "cpu0 1 2 3 4 5 6 7 8\n",  # not the machine's line
        "cpu 1 2 3 4 5 6 7 x\n",
        "cpu 1 2 3 4 5 6 7 -8\n",
        "",
    )
    for bad in bad_lines:
        f.write_text(bad)
        assert host_steal_ms(str(f)) is None, bad
    assert host_steal_ms(str(tmp_path / "absent")) is None
    here = host_steal_ms()  # this machine's, if it has the column: a count, never negative
    assert here is None or here >= 0.0


def test_a_logs_host_steal_is_printed_only_when_it_is_a_plausible_duration() -> None:
    """The report's process line reads ``host_steal_ms`` from a log, a file: a string, a bool, NaN,
    inf, a negative or an absurd number is left out of the line, never printed or raised."""
    from teleop.offline.report import _plausible_ms

    assert _plausible_ms(0) and _plausible_ms(20.0) and _plausible_ms(2350.0)
    for bad in ("x", True, None, [1], float("nan"), float("inf"), -5.0, 1e308):
        assert not _plausible_ms(bad), bad
