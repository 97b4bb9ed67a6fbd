"""Instructions per tick of the two ports, counted by Valgrind's cachegrind: a yardstick noise cannot move.

Why: on a shared VM the CPU figures of ``bench.cpu`` and the microseconds of ``bench.tick`` move by
10-20 % within minutes (the same unchanged side moved 38 -> 55 us between two runs of one hour), so a
change worth 5 % cannot be told from noise by timing it.  The instructions a tick executes do not
depend on the neighbours: cachegrind counts every one (``I refs``) on a simulated CPU, the same count
on every run of the same code and inputs (``PYTHONHASHSEED`` fixed): two runs of ``none`` at 2 DoF
gave 547 845.27 and 547 844.62 a tick.  They are not time (a cache miss after the loop's sleep
costs more than ten instructions; the retired ``bench.phases`` measured that), but a tick that
executes fewer instructions for the same bits did less work.

Each case runs ``bench.tick.port_side_ticks`` (both ports as their processes run them: receive what
arrived, tick, sent; the ``protocol`` scenario) under cachegrind twice, for ``--from`` and ``--to``
ticks; the difference over the ticks between is the ports' cost per tick, without the interpreter's
start, the imports and the ports' setup.  ``--reference DIR`` (a checkout of another commit, e.g.
``git worktree add /tmp/ref <commit>``) counts the same cases from it: the ratio is exact.  Needs
``valgrind`` (Debian's package ``valgrind``).  The two processes of a case run side by side (the
count does not depend on the host's load).

    python -m bench.instructions [--reference DIR] [--from K] [--to K] [--out FILE]
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from bench import commit, write_result
from bench.cpu import _case
from bench.tick import SIDE_CODECS, SIDE_DOFS

#: Per codec at 2, 6 and 64 DoF (issue 37), the hot port tick's grid (bench.tick's sides).
CASES: tuple[tuple[str, int], ...] = tuple((c, d) for d in SIDE_DOFS for c in SIDE_CODECS)

#: The default span: ticks 2000-7000 of the protocol task cross from free space into the foam (5 s).
FROM_TICKS, TO_TICKS = 2000, 7000
MAX_TICKS = 60_000  # 60 s of the task (its last push ends at 15 s); a 7000-tick count took ~50 s here
_CHILD = (
    "import sys; from bench.tick import _port_pair, port_side_ticks; "
    "n = int(sys.argv[3]); port_side_ticks(*_port_pair(sys.argv[1], int(sys.argv[2]), n + 10, 'protocol'), n)"
)
_IREFS = re.compile(r"I\s+refs:\s+([\d,]+)")


class BenchError(Exception):
    """A run could not be made or read: the message says which and why."""


def instructions(codec: str, dof: int, ticks: int, root: Path | None) -> int:
    """Instructions cachegrind counted in one process that builds the two ports and runs ``ticks``."""
    # OpenBLAS's idle worker thread polls, and cachegrind counts what it runs in proportion to the
    # run's emulated time, not its work (~8 k instructions a tick); one thread, none idle.  The dot
    # of a few elements runs on the calling thread either way (the same kernel, the same bits).
    env = {**os.environ, "PYTHONHASHSEED": "0", "OPENBLAS_NUM_THREADS": "1"}
    if root is not None:
        env["PYTHONPATH"] = str(root)
    cmd = ["valgrind", "--tool=cachegrind", "--cache-sim=no", "--cachegrind-out-file=/dev/null"]
    cmd += [sys.executable, "-c", _CHILD, codec, str(dof), str(ticks)]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=root, env=env)
    m = _IREFS.search(r.stderr)
    if r.returncode != 0 or m is None:
        tail = r.stderr.strip().splitlines()[-3:]
        raise BenchError(f"cachegrind of {codec} at {dof} DoF, {ticks} ticks failed: {' | '.join(tail)}")
    return int(m.group(1).replace(",", ""))


def per_tick(codec: str, dof: int, lo: int, hi: int, root: Path | None) -> dict[str, Any]:
    """Both ports' instructions per tick over ticks ``lo``..``hi`` (two cachegrind runs, side by side)."""
    with ThreadPoolExecutor(2) as pool:
        a, b = pool.map(lambda n: instructions(codec, dof, n, root), (lo, hi))
    return {"instructions": {str(lo): a, str(hi): b}, "per_tick": (b - a) / (hi - lo)}


def run(
    lo: int, hi: int, reference: Path | None, cases_run: Sequence[tuple[str, int]] = CASES
) -> dict[str, Any]:
    cases = []
    for codec, dof in cases_run:
        print(f"{codec} {dof} DoF ...", flush=True)
        case: dict[str, Any] = {"codec": codec, "dof": dof, "tree": per_tick(codec, dof, lo, hi, None)}
        if reference is not None:
            case["reference"] = per_tick(codec, dof, lo, hi, reference)
            case["ratio_to_reference"] = case["tree"]["per_tick"] / case["reference"]["per_tick"]
        cases.append(case)
    return {"cases": cases}


def _ticks(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number of ticks, got {text!r}") from None
    if not 0 <= n <= MAX_TICKS:
        raise argparse.ArgumentTypeError(f"must be in 0..{MAX_TICKS}, got {n}")
    return n


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--from", dest="lo", type=_ticks, default=FROM_TICKS, help="first tick counted")
    ap.add_argument("--to", dest="hi", type=_ticks, default=TO_TICKS, help="tick the count ends at")
    ap.add_argument("--reference", type=Path, help="a checkout of another commit, counted too")
    ap.add_argument("--out", default="bench/results/instructions.json")
    ap.add_argument(
        "--cases",
        nargs="+",
        type=_case,
        metavar="CODEC:DOF",
        help="count these cases only (default: " + " ".join(f"{c}:{d}" for c, d in CASES) + ")",
    )
    a = ap.parse_args(argv)
    if a.hi - a.lo < 100:
        ap.error(f"--to must be at least 100 ticks after --from, got {a.lo}..{a.hi}")
    if a.reference is not None and not (a.reference / "bench" / "tick.py").is_file():
        ap.error(f"--reference {a.reference}: not a checkout of this project (no bench/tick.py)")
    out = Path(a.out)
    if (out.exists() and not out.is_file()) or out.is_symlink():
        ap.error(f"--out {a.out}: not a regular file (a results file is written there)")
    if shutil.which("valgrind") is None:
        ap.error("needs valgrind on PATH (Debian: apt-get install valgrind)")
    t0 = time.monotonic()
    try:
        res = run(a.lo, a.hi, a.reference, a.cases or CASES)
    except BenchError as e:
        print(f"bench.instructions: {e}", file=sys.stderr)
        return 1
    doc = {
        "what": "instructions per tick of both ports (receive, tick, sent), cachegrind's I refs",
        "scenario": "protocol",
        "ticks": [a.lo, a.hi],
        "python": platform.python_version(),
        "machine": platform.machine(),
        "commit": commit(Path.cwd()),
        **({"reference": {"path": str(a.reference), "commit": commit(a.reference)}} if a.reference else {}),
        **res,
        "wall_s": time.monotonic() - t0,
    }
    out.parent.mkdir(parents=True, exist_ok=True)
    write_result(out, doc, indent=1)
    for c in doc["cases"]:
        ratio = f"  x{c['ratio_to_reference']:.3f} of the reference" if "reference" in c else ""
        print(f"{c['codec']:<7} {c['dof']:>2} DoF  {c['tree']['per_tick']:10.0f} instructions a tick{ratio}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
