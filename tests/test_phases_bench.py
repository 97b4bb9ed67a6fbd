"""bench.phases' arithmetic on a probe file, without running a process (the runs are the bench's)."""

from __future__ import annotations

from bench import phases
from bench._phase_probe import PHASES


def test_phases_take_the_probes_reads_off_and_nest_the_port_in_the_endpoint() -> None:
    ticks = 1000
    calls = {k: ticks for _, _, _, k, _ in PHASES}
    calls["ticks"] = 1
    us = 1000  # ns per µs
    cpu = {"ticks": 300 * us * ticks, "ticks_process": 310 * us * ticks, "spin": 100 * us * ticks}
    cpu |= {"endpoint_tick": 80 * us * ticks, "port_tick": 70 * us * ticks, "socket_read": 20 * us * ticks}
    f = phases.figures({"cpu_ns": cpu, "calls": calls, "clock_read_ns": 500.0}, ticks)
    assert f["spin"] == 99.0  # two reads of 0.5 µs a call taken off
    assert f["port_tick"] == 69.0 and f["endpoint_tick"] == 78.0  # and the nested port's two
    assert f["process"] == 310.0 and f["threads"] == 10.0
    wrapped = sum(calls.values()) - 1
    ticking = (300 * us * ticks - 2 * 500.0 * (1 + wrapped)) / ticks / us
    top = sum(v for k, v in f.items() if k in calls and k not in ("ticks", "port_tick"))
    assert abs(f["ticking"] - ticking) < 0.01 and abs(f["other"] - (ticking - top)) < 0.02
