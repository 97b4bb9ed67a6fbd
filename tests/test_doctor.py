"""``teleop doctor`` (issue 48): each check says ok or warn and what to do, in one line."""

from __future__ import annotations

import os
import resource
from typing import Any

import pytest

from teleop.cli import doctor
from teleop.cli.parser import main


def test_a_kernel_that_is_not_preempt_rt_is_a_warning_naming_the_fix(monkeypatch: pytest.MonkeyPatch) -> None:
    u = os.uname()
    fake = type(u)((u.sysname, u.nodename, u.release, "#1 SMP PREEMPT_DYNAMIC", u.machine))
    monkeypatch.setattr(os, "uname", lambda: fake)
    monkeypatch.setattr(doctor, "_read", lambda path: None)
    c = doctor.check_kernel()
    assert not c.ok and "PREEMPT_DYNAMIC" in c.said and "linux-image-rt" in c.said
    rt = type(u)((u.sysname, u.nodename, u.release, "#1 SMP PREEMPT_RT", u.machine))
    monkeypatch.setattr(os, "uname", lambda: rt)
    assert doctor.check_kernel().ok


def test_no_cpufreq_and_a_powersave_governor_are_warnings(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("glob.glob", lambda pattern: [])
    assert not doctor.check_governor().ok
    monkeypatch.setattr("glob.glob", lambda pattern: ["a", "b"])
    monkeypatch.setattr(doctor, "_read", lambda path: "powersave" if path == "a" else "performance")
    c = doctor.check_governor()
    assert not c.ok and "cpupower frequency-set -g performance" in c.said
    monkeypatch.setattr(doctor, "_read", lambda path: "performance")
    assert doctor.check_governor().ok


def test_a_small_memlock_limit_is_a_warning(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    monkeypatch.setattr(resource, "getrlimit", lambda what: (64 << 10, 64 << 10))
    c = doctor.check_memlock()
    assert not c.ok and "64 KiB" in c.said and "memlock" in c.said


def test_the_idle_loop_counts_its_late_wake_ups_and_restores_the_policy() -> None:
    before = os.sched_getscheduler(0)
    c = doctor.check_idle_loop(0.2)
    assert os.sched_getscheduler(0) == before
    assert c.name == "idle loop" and "wake-ups over 900 us late in 0.2 s" in c.said
    assert c.ok == (c.said.startswith("0 of") and ("steal 0 ms" in c.said or "steal unknown" in c.said))
    assert "\n" not in c.line()


def test_every_line_ends_in_a_verdict(capsys: Any) -> None:
    rc = main(["doctor", "--duration", "0.1"])
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("teleop doctor: this machine") and out[-1].startswith("teleop doctor: ")
    checks = [line for line in out[1:-1] if not line.strip().startswith("....")]
    assert len(checks) == 6 and all(line.split()[0] in ("ok", "warn") for line in checks)
    assert rc == (0 if all(line.split()[0] == "ok" for line in checks) else 1)


@pytest.mark.parametrize("bad", ["0", "nan", "61", "x"])
def test_a_bad_duration_is_one_line(bad: str, capsys: Any) -> None:
    with pytest.raises(SystemExit) as e:
        main(["doctor", "--duration", bad])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "duration must be" in err
