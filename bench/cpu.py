"""CPU of the 1 kHz loop against the floor reference, in one invocation on one host (issue 22).

Runs, one after the other:

1. the floor reference (``bench.floor``: a pair of processes that sleep to 100 us before each
   deadline, spin the rest, seal a 40-byte body with keyed BLAKE2s, send it to the other over
   loopback UDP, drain and verify what arrived);
2. ``teleop run`` (``protocol`` scenario, UDP, authenticated, log on) for ``none``, ``eds:50`` and
   ``pdp:1`` at 2 and 6 DoF and ``none`` at 64 DoF, each with an empty reference loop
   (``bench.floor --empty``: the same scheduler with the former fixed 100 us spin and nothing to do) running
   alongside, so a stall of the shared host hits both;
3. the floor again: the figure each ratio divides by is the mean of the four floor processes.

Per process: CPU % (``loop.cpu_fraction`` of the report), its ratio to the floor, period-error
p99 and p99.9 and their ratio to the empty loop's, and the port's per-tick cost of that side
(``bench.tick.bench_port_sides``, no I/O).  Targets: CPU at most 1.5x the floor at 2 and 6 DoF and
2x at 64 DoF; the port's tick at most 15 us per side at 2 DoF with ``none``.

``--reference DIR`` (a checkout of another commit, such as ``git worktree add /tmp/ref <commit>``)
also runs every case from DIR, right before or after this tree's (alternated case by case), with
its own empty loop, and times its port the same way: each process then has its CPU and port tick
as a ratio to the reference's, measured minutes apart on the same host.  On a shared VM whose
noise moves the absolute figures by 10-20 % within an hour, that ratio is the figure that says
whether a change made the loop cheaper.

    python -m bench.cpu [--duration S] [--reference DIR] [--out FILE]
    python -m bench.cpu --out FILE --add-repeats MORE.json ...   (how often the targets held)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench import commit, write_result
from teleop.cli.args import float_range, int_range

CASES: tuple[tuple[str, int], ...] = (
    ("none", 2),
    ("eds:50", 2),
    ("pdp:1", 2),
    ("none", 6),
    ("eds:50", 6),
    ("pdp:1", 6),
    ("none", 64),
)
ROLES = ("operator", "teleoperator")
EMPTY_SPIN_US = 100  # the scheduler's spin before issue 22: the empty loop keeps it as the yardstick


def _case(text: str) -> tuple[str, int]:
    codec, _, dof = text.rpartition(":")
    if not codec or not dof.isdigit() or not 1 <= int(dof) <= 64:
        raise argparse.ArgumentTypeError(f"CODEC:DOF with DOF in 1..64, got {text!r}")
    return codec, int(dof)


def cpu_target(dof: int) -> float:
    return 2.0 if dof >= 64 else 1.5


SESSION_TARGET = 1.5  # a whole eds:50 session against the floor pair (issue 37)


def _session(figures: dict[str, Any], floor_pair: float) -> dict[str, Any]:
    """A session's CPU (SessionCpu.stop) and its ratio to the floor pair of the same run."""
    if "cpu_fraction_of_one_core" not in figures:
        return figures
    return {**figures, "x_floor_pair": figures["cpu_fraction_of_one_core"] / floor_pair}


def run_floor(duration: float, tmp: Path, name: str) -> dict[str, Any]:
    out = tmp / f"{name}.json"
    subprocess.run(
        [sys.executable, "-m", "bench.floor", "--duration", str(duration), "--out", str(out)], check=True
    )
    res: dict[str, Any] = json.loads(out.read_text())
    return res


def _tree_env(root: Path | None) -> tuple[Path | None, dict[str, str] | None]:
    """The working folder and environment that run ``-m`` modules from ``root`` (None: this tree)."""
    if root is None:
        return None, None
    return root, {**os.environ, "PYTHONPATH": str(root)}


_CLK_TCK = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float | None:
    """A process's CPU so far (user + system, its threads included), or None once it is gone."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / _CLK_TCK  # utime, stime (fields 14 and 15 of stat)


def _children(pid: int) -> set[int]:
    out: set[int] = set()
    try:
        for task in os.listdir(f"/proc/{pid}/task"):
            with open(f"/proc/{pid}/task/{task}/children") as f:
                out.update(int(c) for c in f.read().split())
    except OSError:
        pass
    return out


class SessionCpu:
    """The CPU of a whole session: every process below ``pid`` (``teleop run``'s two loops and
    their log writers; ``teleop run`` itself, which only waits, is left out), from the moment
    ``started()`` first holds (both logs exist: the session's first tick is due) to each process's
    exit, sampled every ``period`` s from /proc.  A process's CPU after its last sample is missed:
    at most ``period`` of it each."""

    def __init__(self, pid: int, started: Callable[[], bool], period: float = 0.02) -> None:
        self.pid, self.started, self.period = pid, started, period
        self.at_start: dict[int, float] = {}  # pid: CPU when the session started (0: born after)
        self.last: dict[int, float] = {}  # pid: CPU at its last sample
        self.t_start: float | None = None
        self.t_end: float | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            now = time.monotonic()
            todo, seen = list(_children(self.pid)), set()
            while todo:
                q = todo.pop()
                if q in seen:
                    continue
                seen.add(q)
                todo.extend(_children(q))
                cpu = _cpu_s(q)
                if cpu is not None:
                    self.last[q] = cpu
            if self.t_start is None and self.started():
                self.t_start = now
                self.at_start = dict(self.last)
            if self.t_start is not None and seen:
                self.t_end = now
            self._stop.wait(self.period)

    def stop(self) -> dict[str, Any]:
        self._stop.set()
        self._thread.join()
        if self.t_start is None or self.t_end is None or self.t_end <= self.t_start:
            return {"error": "the session never started (no two logs) or no process was seen after"}
        cpu = {q: c - self.at_start.get(q, 0.0) for q, c in self.last.items()}
        total = sum(cpu.values())
        wall = self.t_end - self.t_start
        return {
            "cpu_s": total,
            "wall_s": wall,
            "cpu_fraction_of_one_core": total / wall,
            "processes": len(cpu),
            "sample_period_s": self.period,
        }


def run_case(codec: str, dof: int, duration: float, tmp: Path, root: Path | None = None) -> dict[str, Any]:
    """One ``teleop run`` with an empty loop alongside; the two processes' loop figures and the empty's.
    ``root``: run ``teleop`` from that checkout instead of this tree (the empty loop is this tree's)."""
    name = f"{codec.replace(':', '')}-{dof}" + ("-ref" if root is not None else "")
    empty_json, run_dir = tmp / f"empty-{name}.json", tmp / f"run-{name}"
    cwd, env = _tree_env(root)
    # The session needs ~1 s to start; start the empty loop so the two overlap almost fully.
    ref = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "bench.floor",
            "--empty",
            str(empty_json),
            "--duration",
            str(duration),
            "--spin-us",
            str(EMPTY_SPIN_US),
            "--fixed-spin",
        ]
    )
    cmd = [sys.executable, "-m", "teleop.cli", "run", "--codec", codec, "--dof", str(dof)]
    cmd += ["--duration", str(duration), "--out", str(run_dir), "--no-plots", "--no-sim", "--no-live"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd, env=env)
    logs = run_dir / "logs"
    sampler = SessionCpu(proc.pid, lambda: len(list(logs.glob("*.mcap"))) >= 2)
    stdout, stderr = proc.communicate()
    session = sampler.stop()
    r = subprocess.CompletedProcess(cmd, proc.returncode, stdout, stderr)
    ref.wait(timeout=duration + 60)
    if r.returncode not in (0, 3):  # 3: a poor session (teleop.session.verdict): it ran, measured
        sys.exit(f"teleop run {codec} {dof} DoF failed{' (reference)' if root else ''}: {r.stderr}")
    rep = json.loads((run_dir / "report.json").read_text())
    if missing := [role for role in ROLES if not rep["processes"].get(role)]:
        # A process exited 0 and its log has no summary: a fault to find, not a case to skip.
        keep = Path(tempfile.mkdtemp(prefix=f"teleop-cpu-{name}-"))
        shutil.copytree(run_dir, keep, dirs_exist_ok=True)
        sys.exit(
            f"teleop run {codec} {dof} DoF{' (reference)' if root else ''}: the report has no figures of "
            f"the {' and the '.join(missing)} (its log has no summary); the run is kept in {keep}\n"
            f"its output: {r.stdout}\n{r.stderr}"
        )
    return {"empty": json.loads(empty_json.read_text()), "report": rep, "session": session}


_PORT_SIDES = (
    "import json, statistics, sys; from bench.tick import bench_port_sides; "
    "o, t = bench_port_sides(sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), "
    "scenario='protocol'); print(json.dumps([statistics.median(o), statistics.median(t)]))"
)


def port_tick(
    codec: str, dof: int, ticks: int, repeats: int, root: Path | None = None
) -> tuple[float, float]:
    """Each side's port tick (median of ``repeats``, us), in a fresh interpreter of ``root``'s tree
    (None: this one), so two trees' figures come from equal processes."""
    cwd, env = _tree_env(root)
    args = [codec, str(dof), str(ticks), str(repeats)]
    cmd = [sys.executable, "-c", _PORT_SIDES, *args]
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, env=env, check=True).stdout
    op, to = json.loads(out)
    return float(op), float(to)


def _vs_reference(r: dict[str, Any]) -> str:
    return f"  x reference: CPU {r['cpu_ratio']:.2f}, port tick {r['port_tick_ratio']:.2f}"


def add_repeats(out: Path, others: list[Path]) -> None:
    """Record in ``out`` (a bench.cpu result) how the targets fared in ``others`` (more runs of
    it, made right after from the same tree): the ``repeats`` block its table's note reads."""
    runs = []
    for p in [out, *others]:
        if not p.is_file():  # a FIFO would block the read, a directory fail it
            sys.exit(f"{p}: not a regular file (a bench.cpu result is a JSON file)")
        try:
            r = json.loads(p.read_text())
        except (OSError, ValueError) as e:
            sys.exit(f"{p}: cannot read it as JSON ({e})")
        if not isinstance(r, dict) or "cases" not in r or "targets" not in r:
            sys.exit(f"{p}: not a bench.cpu result")
        runs.append(r)
    doc = runs[0]
    doc["repeats"] = {
        "what": f"bench.cpu run {len(others)} more times right after this file's run, without"
        " --reference; this file is the first; targets met in each",
        "cpu_met": [r["targets"]["cpu"]["met"] for r in runs],
        "port_tick_met": [r["targets"]["port_tick_15us_none_2dof"]["met"] for r in runs],
        "floor_cpu_fraction": [r["floor"]["cpu_fraction"] for r in runs],
        "cpu_ratio_to_floor": [
            {
                f"{c['codec']} {c['dof']} {role}": round(c[role]["cpu_ratio_to_floor"], 3)
                for c in r["cases"]
                for role in ROLES
            }
            for r in runs
        ],
    }
    out.write_text(json.dumps(doc, indent=2) + "\n")  # the runs' file, its commit as measured
    print(f"{out}: CPU targets met {doc['repeats']['cpu_met']}, port tick {doc['repeats']['port_tick_met']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    # Checked here, in one line, not minutes later by a child's traceback (nan reached bench.floor).
    ap.add_argument(
        "--duration",
        type=float_range("--duration", 1.0, 600.0, "s"),
        default=10.0,
        help="seconds per session (default 10)",
    )
    ap.add_argument(
        "--tick-ticks",
        type=int_range("--tick-ticks", 100, 1_000_000),
        default=3000,
        help="ticks per repeat of the port timing",
    )
    ap.add_argument("--tick-repeats", type=int_range("--tick-repeats", 1, 1000), default=5)
    ap.add_argument("--reference", type=Path, help="a checkout of another commit: every case run from it too")
    ap.add_argument(
        "--cases",
        nargs="+",
        type=_case,
        metavar="CODEC:DOF",
        help="run these cases only (default: " + " ".join(f"{c}:{d}" for c, d in CASES) + ")",
    )
    ap.add_argument("--out", default="bench/results/cpu.json")
    ap.add_argument(
        "--add-repeats",
        nargs="+",
        type=Path,
        metavar="FILE",
        help="run nothing: record in --out how the targets fared in these further runs' files",
    )
    a = ap.parse_args()
    if a.add_repeats:
        add_repeats(Path(a.out), a.add_repeats)
        return
    root: Path | None = a.reference.resolve() if a.reference is not None else None
    if root is not None and not (root / "teleop" / "cli").is_dir():
        sys.exit(f"--reference {a.reference}: not a checkout of this project (no teleop/cli in it)")
    started = time.time()
    refs: dict[tuple[str, int], dict[str, Any]] = {}
    with tempfile.TemporaryDirectory() as tmpdir:
        tmp = Path(tmpdir)
        floors = [run_floor(a.duration, tmp, "floor-before")]
        runs = []
        for i, (codec, dof) in enumerate(a.cases or CASES):
            print(f"teleop run {codec} {dof} DoF ...", flush=True)
            if root is not None and i % 2 == 1:  # alternated: the reference first every other case
                refs[codec, dof] = run_case(codec, dof, a.duration, tmp, root)
            runs.append((codec, dof, run_case(codec, dof, a.duration, tmp)))
            if root is not None and i % 2 == 0:
                refs[codec, dof] = run_case(codec, dof, a.duration, tmp, root)
        floors.append(run_floor(a.duration, tmp, "floor-after"))
    floor_cpu = statistics.fmean(s["cpu_fraction"] for f in floors for s in f["sides"])
    # The floor pair, both processes, as a fraction of one core: what a whole session is held to.
    floor_pair = statistics.fmean(sum(s["cpu_fraction"] for s in f["sides"]) for f in floors)
    cases = []
    for codec, dof, r in runs:
        empty = r["empty"]
        pe_empty = empty["period_error_us"]
        ticks = port_tick(codec, dof, a.tick_ticks, a.tick_repeats)
        tick_us = dict(zip(ROLES, ticks, strict=True))
        ref_tick_us: dict[str, float] = {}
        if root is not None:
            ref_ticks = port_tick(codec, dof, a.tick_ticks, a.tick_repeats, root)
            ref_tick_us = dict(zip(ROLES, ref_ticks, strict=True))
        case: dict[str, Any] = {
            "codec": codec,
            "dof": dof,
            "empty": {"period_error_us": pe_empty, "cpu_fraction": empty["cpu_fraction"]},
            "cpu_target_ratio": cpu_target(dof),
            "session": _session(r["session"], floor_pair),
        }
        if root is not None:
            case["session"]["reference"] = _session(refs[codec, dof]["session"], floor_pair)
        for role in ROLES:
            loop = r["report"]["processes"][role]["loop"]
            pe = loop["period_error_us"]
            ratio = loop["cpu_fraction"] / floor_cpu
            case[role] = {
                "cpu_fraction": loop["cpu_fraction"],
                "cpu_ratio_to_floor": ratio,
                "period_error_us": {"p99": pe["p99"], "p999": pe["p999"], "max": pe["max"]},
                "p99_ratio_to_empty": pe["p99"] / pe_empty["p99"] if pe_empty["p99"] > 0 else None,
                "p999_ratio_to_empty": pe["p999"] / pe_empty["p999"] if pe_empty["p999"] > 0 else None,
                "overruns": loop["overruns"],
                "spin_us": loop.get("spin_us"),
                # When the datagrams left (absent before --tick-at: a reference may lack it).
                "send_period_error_us": loop.get("send_period_error_us"),
                "send_lateness_us": loop.get("send_lateness_us"),
                "skipped": loop["skipped"],
                "port_tick_us": tick_us[role],
                "cpu_target_met": ratio <= cpu_target(dof),
            }
            if root is not None:
                ref_loop = refs[codec, dof]["report"]["processes"][role]["loop"]
                ref_cpu = ref_loop["cpu_fraction"]
                case[role]["reference"] = {
                    "cpu_fraction": ref_cpu,
                    "period_error_us": ref_loop["period_error_us"],
                    "spin_us": ref_loop.get("spin_us"),
                    "cpu_ratio": loop["cpu_fraction"] / ref_cpu,
                    "port_tick_us": ref_tick_us[role],
                    "port_tick_ratio": tick_us[role] / ref_tick_us[role],
                }
        cases.append(case)
    tick_2 = [
        c[role]["port_tick_us"] for c in cases if c["codec"] == "none" and c["dof"] == 2 for role in ROLES
    ]
    eds = [c["session"] for c in cases if c["codec"] == "eds:50" and "x_floor_pair" in c["session"]]
    targets = {
        # Issue 37: a whole eds:50 session (both loops and their log writers) at most 1.5x the
        # floor pair of the same run.
        "session_eds50_within_1.5x_floor_pair": {
            "met": sum(s["x_floor_pair"] <= SESSION_TARGET for s in eds),
            "of": len(eds),
        },
        "cpu": {"met": sum(c[role]["cpu_target_met"] for c in cases for role in ROLES), "of": 2 * len(cases)},
        "port_tick_15us_none_2dof": {"met": sum(t <= 15.0 for t in tick_2), "of": len(tick_2)},
    }
    res: dict[str, Any] = {
        "what": "CPU per process of teleop run against the floor reference, same invocation, same host",
        "commit": commit(),  # the tree measured
        # Some hosts pin OpenBLAS's kernels (OPENBLAS_CORETYPE, OPENBLAS_L2_SIZE): they change the
        # numpy calls' cost, so a run says which it had.
        "openblas_env": {k: v for k, v in sorted(os.environ.items()) if k.startswith("OPENBLAS_")},
        "duration_s": a.duration,
        "scenario": "protocol",
        "python": platform.python_version(),
        "machine": platform.machine(),
        "empty_loop_spin_us": EMPTY_SPIN_US,
        "floor": {"cpu_fraction": floor_cpu, "pair_cpu_fraction": floor_pair, "runs": floors},
        "cases": cases,
        "targets": targets,
        "wall_s": time.time() - started,
    }
    if root is not None:
        res["reference"] = {
            "commit": commit(root),
            "what": "every case also run from this commit, alternated case by case; per process its"
            " CPU and port tick, and this tree's as a ratio to them",
        }
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_result(out, res)
    print(f"floor: CPU {100 * floor_cpu:.1f}% per process, {100 * floor_pair:.1f}% the pair")
    for c in cases:
        se = c["session"]
        if "x_floor_pair" in se:
            print(
                f"{c['codec']:<7} {c['dof']:>2} DoF session (both loops and writers) CPU "
                f"{100 * se['cpu_fraction_of_one_core']:5.1f}% of a core, "
                f"{se['x_floor_pair']:.2f}x the floor pair"
            )
        else:
            print(f"{c['codec']:<7} {c['dof']:>2} DoF session: {se['error']}")
        for role in ROLES:
            x, pe_empty = c[role], c["empty"]["period_error_us"]
            print(
                f"{c['codec']:<7} {c['dof']:>2} DoF {role:<12} CPU {100 * x['cpu_fraction']:5.1f}% "
                f"({x['cpu_ratio_to_floor']:.2f}x floor, target {c['cpu_target_ratio']:g}x)  "
                f"p99 {x['period_error_us']['p99']:7.1f} us (empty {pe_empty['p99']:6.1f})  "
                f"p99.9 {x['period_error_us']['p999']:7.1f} us  port tick {x['port_tick_us']:6.1f} us"
                + (_vs_reference(x["reference"]) if "reference" in x else "")
            )
    print(
        f"targets: CPU {targets['cpu']['met']}/{targets['cpu']['of']}, port tick "
        f"{targets['port_tick_15us_none_2dof']['met']}/{targets['port_tick_15us_none_2dof']['of']}, eds:50 "
        f"session {targets['session_eds50_within_1.5x_floor_pair']['met']}/"
        f"{targets['session_eds50_within_1.5x_floor_pair']['of']}; wrote {out}"
    )


if __name__ == "__main__":
    main()
