"""Micro-benchmark: the cost of one tick of the MuJoCo robot (``--robot mujoco``), in microseconds.

One tick is ``affine(now)`` (collision pass, forward dynamics at a zero command and one probe per
DoF) plus ``advance(now, v, f)`` (forward dynamics at the command, one integration step).  The
robot is driven open-loop with the commanded velocities of a ``teleop sim --scenario protocol
--robot mujoco`` run, so it passes through the same states: free space (0-5 s), foam (5-10 s),
foam and wall (10-15 s).  Each tick is timed alone (``perf_counter_ns``); the figures are the
median, p99 and max per phase, against the 1 ms period (target: under 5%, 50 us).  The built-in
``protocol`` environment is timed the same way for scale.

    python -m bench.mujoco_step [--out FILE] [--repeats R] [--dof N]

This machine is shared (other jobs, a VM that steals CPU in bursts): p99 and max are noisy.
"""

from __future__ import annotations

import argparse
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench import write_result
from teleop.devices import make
from teleop.devices.models import Array
from teleop.offline.sim import SimConfig, run_case

DT = 1e-3
PHASES = {"free space 0-5 s": (0.0, 5.0), "foam 5-10 s": (5.0, 10.0), "foam and wall 10-15 s": (10.0, 15.0)}


def time_ticks(robot: str, v_cmd: Array, dof: int) -> Array:
    """Microseconds of each tick of a fresh ``robot`` commanded ``v_cmd`` (ticks, dof)."""
    dev = make("robot", robot, dof, DT)
    out = np.empty(len(v_cmd))
    clock = time.perf_counter_ns
    for n, v in enumerate(v_cmd):
        now = n * DT
        t0 = clock()
        f0, z = dev.affine(now)
        dev.advance(now, v, f0 + z * v)
        out[n] = (clock() - t0) / 1e3
    return out


def stats(us: Array) -> dict[str, float]:
    return {
        "median_us": float(np.median(us)),
        "p99_us": float(np.percentile(us, 99)),
        "max_us": float(us.max()),
        "median_fraction_of_period": float(np.median(us)) * 1e-6 / DT,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="bench/results/mujoco_step.json")
    ap.add_argument("--repeats", type=int, default=2, help="runs of the 15 s profile per robot (default 2)")
    ap.add_argument("--dof", type=int, default=2)
    args = ap.parse_args(argv)
    case = run_case(SimConfig(scenario="protocol", robot="mujoco", dof=args.dof))
    v_cmd = case.trace.v_to
    t = case.trace.t
    results: dict[str, Any] = {}
    for robot in ("mujoco", "protocol"):
        runs = np.concatenate([time_ticks(robot, v_cmd, args.dof) for _ in range(args.repeats)])
        tt = np.tile(t, args.repeats)
        results[robot] = {
            "all": stats(runs),
            **{name: stats(runs[(tt >= a) & (tt < b)]) for name, (a, b) in PHASES.items()},
        }
        a = results[robot]["all"]
        print(
            f"{robot:>9}: median {a['median_us']:.1f} us, p99 {a['p99_us']:.1f} us, max {a['max_us']:.0f} us"
        )
    import mujoco

    doc = {
        "what": "one robot tick (affine + advance), 1 kHz, Section VI profile, open-loop replay",
        "dof": args.dof,
        "repeats": args.repeats,
        "ticks": len(v_cmd) * args.repeats,
        "target_us": 50.0,
        "mujoco": mujoco.__version__,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "note": "shared 2-core VM with other jobs running: p99 and max are noisy",
        "robots": results,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_result(out, doc)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
