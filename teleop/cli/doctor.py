"""``teleop doctor``: is this machine ready for a 1 kHz session?

Each check ends in ``ok`` or ``warn`` and one line saying what to do.  The checks are what decides
whether a session's loop keeps its millisecond: the kernel's preemption model, the rights the
runner asks for (SCHED_FIFO, locked memory, a 1 ns timer slack), the CPU frequency governor, and
an idle loop run for ``--duration`` seconds exactly as a session's scheduler runs it
(``shell.realtime.Ticker``, SCHED_FIFO where permitted), counting its late wake-ups beside
the CPU time the hypervisor stole meanwhile (``/proc/stat``).  Nothing is changed on the machine;
the process's own priority and timer slack are restored before it exits.  Exit status 0 when
every check is ok, 1 when one warns (a script can gate a session on it).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import glob
import os
import resource
import time
from dataclasses import dataclass

from teleop.cli.args import Subcommands, float_range

#: A wake-up this late (us) misses the tick it was for: what the report counts as a stall.
STALL_US = 900.0
#: Locked memory a session needs (MiB): a process with numpy, Zenoh and uvloop resident, measured.
MEMLOCK_MIB = 512
PR_GET_TIMERSLACK, PR_SET_TIMERSLACK = 30, 29


@dataclass(frozen=True)
class Finding:
    name: str
    ok: bool
    said: str  # what was found, and what to do where it is not ok

    def line(self) -> str:
        return f"  {'ok  ' if self.ok else 'warn'}  {self.name:<14} {self.said}"


def _read(path: str) -> str | None:
    try:
        with open(path, encoding="ascii", errors="replace") as f:
            return f.read(4096).strip()
    except OSError:
        return None


def check_kernel() -> Finding:
    version = os.uname().version
    rt = "PREEMPT_RT" in version or _read("/sys/kernel/realtime") == "1"
    if rt:
        return Finding("kernel", True, f"PREEMPT_RT ({os.uname().release})")
    model = next((m for m in ("PREEMPT_DYNAMIC", "PREEMPT") if m in version), "none")
    return Finding(
        "kernel",
        False,
        f"{os.uname().release} is not PREEMPT_RT (preemption: {model}): wake-ups may come milliseconds "
        "late under load; install a real-time kernel (Debian: linux-image-rt-amd64)",
    )


def check_fifo() -> Finding:
    try:
        before = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))
        os.sched_setscheduler(0, before[0], before[1])
    except (PermissionError, OSError, AttributeError) as e:
        soft = resource.getrlimit(resource.RLIMIT_RTPRIO)[0]
        return Finding(
            "SCHED_FIFO",
            False,
            f"not permitted ({e.__class__.__name__}; ulimit -r is {soft}): the loop runs at normal "
            "priority; run as root, or give the user an rtprio limit (limits.conf: @realtime - rtprio 98)",
        )
    return Finding("SCHED_FIFO", True, "permitted (the runner asks for priority 10)")


def check_memlock() -> Finding:
    soft = resource.getrlimit(resource.RLIMIT_MEMLOCK)[0]
    if os.geteuid() == 0 or soft == resource.RLIM_INFINITY or soft >= MEMLOCK_MIB << 20:
        said = "unlimited" if soft == resource.RLIM_INFINITY or os.geteuid() == 0 else f"{soft >> 20} MiB"
        return Finding("memory lock", True, f"{said}: the runner locks its pages (no tick waits on the disk)")
    return Finding(
        "memory lock",
        False,
        f"ulimit -l is {soft >> 10} KiB, under the {MEMLOCK_MIB} MiB a session locks: a page the kernel "
        "reclaims costs a tick a read from disk; raise it (limits.conf: @realtime - memlock unlimited)",
    )


def check_timer_slack() -> Finding:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        before = libc.prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0)
        ok = libc.prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(1), 0, 0, 0) == 0
        now = libc.prctl(PR_GET_TIMERSLACK, 0, 0, 0, 0)
        libc.prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(max(before, 1)), 0, 0, 0)
    except (OSError, AttributeError) as e:
        return Finding("timer slack", False, f"cannot be read ({e}): sleeps may wake up to 50 us late")
    if ok and now == 1:
        said = f"settable to 1 ns (default here {before} ns; the runner sets it)"
        return Finding("timer slack", True, said)
    return Finding(
        "timer slack", False, f"stays {now} ns: sleeps may wake up that late; check prctl's rights"
    )


def check_governor() -> Finding:
    paths = glob.glob("/sys/devices/system/cpu/cpu[0-9]*/cpufreq/scaling_governor")
    found = {g for p in paths if (g := _read(p))}
    if not found:
        return Finding(
            "CPU governor",
            False,
            "no cpufreq here (a VM: its host sets the frequency): nothing to set in this machine; on "
            "bare metal, use the performance governor",
        )
    if found == {"performance"}:
        return Finding("CPU governor", True, "performance on every CPU")
    return Finding(
        "CPU governor",
        False,
        f"{', '.join(sorted(found))}: a CPU clocked down wakes slower; "
        "set it: cpupower frequency-set -g performance",
    )


def check_idle_loop(duration: float) -> Finding:
    """The session's scheduler with nothing to do: how often it woke a tick late."""
    from shell.realtime import HostMarks, Ticker

    try:
        policy = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(10))  # as the runner asks
        fifo = True
    except OSError:
        fifo = False
    n = max(1, round(duration * 1000))
    ticker = Ticker(capacity=n + 16)
    host0 = HostMarks.now()
    ticker.start(time.monotonic_ns() + 20_000_000)
    try:
        while ticker.k < n:
            ticker.wait()
    finally:
        if fifo:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, policy[0], policy[1])
    host = HostMarks.now() - host0
    stats = ticker.stats()
    late = stats.lateness_ns[: stats.ticks]
    stalls = int((late > STALL_US * 1e3).sum())
    worst = float(late.max(initial=0)) / 1e3
    steal = "unknown" if host.steal_ms is None else f"{host.steal_ms:.0f} ms"
    said = (
        f"{stalls} of {stats.ticks} wake-ups over {STALL_US:.0f} us late in {duration:g} s "
        f"(worst {worst:.0f} us, {'SCHED_FIFO' if fifo else 'normal priority'}), host steal {steal}"
    )
    if stalls == 0 and not host.steal_ms:
        return Finding("idle loop", True, said)
    cause = (
        "the hypervisor took the CPU (steal): ask for dedicated vCPUs"
        if host.steal_ms
        else "the kernel woke it late: a real-time kernel, isolated CPUs (isolcpus) or a quieter machine"
    )
    return Finding("idle loop", False, f"{said}: each is a tick missed; {cause}")


def cmd_doctor(args: argparse.Namespace) -> int:
    print(f"teleop doctor: this machine for a 1 kHz session ({os.cpu_count()} CPUs)", flush=True)
    checks = [check_kernel(), check_fifo(), check_memlock(), check_timer_slack(), check_governor()]
    for c in checks:
        print(c.line(), flush=True)
    print(f"  ....  idle loop      ticking for {args.duration:g} s ...", flush=True)
    checks.append(check_idle_loop(args.duration))
    print(checks[-1].line())
    warn = [c.name for c in checks if not c.ok]
    verdict = "ready" if not warn else f"{len(warn)} warning(s): {', '.join(warn)}"
    print(f"teleop doctor: {len(checks) - len(warn)} ok, {verdict}")
    return 0 if not warn else 1


def add_parser(sub: Subcommands) -> None:
    d = sub.add_parser(
        "doctor",
        help="check this machine for a 1 kHz session (kernel, rights, governor, an idle loop)",
        description="Check this machine for a 1 kHz session: the kernel (PREEMPT_RT or not), the "
        "SCHED_FIFO, memory lock and timer slack rights the runner asks for, the CPU governor, and "
        "an idle loop run as a session's scheduler runs it, counting late wake-ups and the "
        "hypervisor's steal. Each check says ok or warn and what to do. Exit status 1 if one warns.",
    )
    d.add_argument(
        "--duration",
        type=float_range("duration", 0.1, 60.0, "s"),
        default=5.0,
        metavar="S",
        help="seconds of the idle loop (default 5)",
    )
    d.set_defaults(func=cmd_doctor)
