"""How long ``teleop export --to lerobot`` takes against the session it exports (issue 46: at most
1/50 of its duration): each log folder given is exported ``--repeats`` times into a fresh folder,
the whole command timed from outside (Python's start and its imports included) beside the time it
prints (reading, parsing, writing, pyarrow's import) and the CPU it prints (every thread).
Medians and ranges, the host's load before and after: a shared 2-core machine's figure says so.

    python -m bench.export LOGDIR [LOGDIR ...] [--repeats 5] [--out bench/results/export.json]
"""

from __future__ import annotations

import argparse
import compileall
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench import ROOT, write_result

PRINTED = re.compile(r", ([\d.]+) s of session\).* in ([\d.]+) s \(CPU ([\d.]+) s\)")


def _one(logs: Path, out: Path) -> dict[str, float]:
    teleop = str(Path(sys.executable).with_name("teleop"))
    t = time.perf_counter()
    r = subprocess.run([teleop, "export", str(logs), "--to", "lerobot", "--out", str(out)],
                       capture_output=True, text=True, timeout=600)  # fmt: skip
    wall = time.perf_counter() - t
    m = PRINTED.search(r.stdout)
    if r.returncode != 0 or m is None:
        said = (r.stderr or r.stdout).strip()[-500:]
        raise SystemExit(f"teleop export {logs} failed ({r.returncode}): {said}")
    return {"session_s": float(m[1]), "printed_s": float(m[2]), "cpu_s": float(m[3]), "command_s": wall}


def _summary(runs: list[dict[str, float]]) -> dict[str, Any]:
    out: dict[str, Any] = {"session_s": runs[0]["session_s"], "runs": runs}
    for k in ("printed_s", "cpu_s", "command_s"):
        xs = [r[k] for r in runs]
        out[k] = {"median": statistics.median(xs), "min": min(xs), "max": max(xs)}
    s = out["session_s"]
    out["fraction_printed"] = out["printed_s"]["median"] / s  # the target: at most 1/50
    out["fraction_command"] = out["command_s"]["median"] / s
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.export", description=__doc__.split("\n\n")[0])
    ap.add_argument("logs", nargs="+", type=Path, help="log folders of sessions (one episode each)")
    ap.add_argument("--label", action="append", help="a name per log folder, in order")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "export.json")
    args = ap.parse_args(argv)
    labels = args.label or [p.name for p in args.logs]
    if len(labels) != len(args.logs):
        raise SystemExit("give one --label per log folder")
    # Compiled first, as an install that may write its caches is after its first run: with
    # PYTHONDONTWRITEBYTECODE set (this project's machines) every command would compile the
    # modules it imports anew, and the figure would be that, not the export.
    for package in ("teleop", "shell", "transport", "conformance"):
        compileall.compile_dir(ROOT / package, quiet=2)
    load_before = os.getloadavg()
    sessions: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for label, logs in zip(labels, args.logs, strict=True):
            runs = []
            for i in range(args.repeats):
                out = Path(tmp) / f"{label}-{i}"
                runs.append(_one(logs, out))
                shutil.rmtree(out)
            sessions[label] = _summary(runs)
            sizes = sum(f.stat().st_size for f in logs.glob("*.mcap"))
            sessions[label]["logs_mb"] = sizes / 1e6
            print(json.dumps({label: {k: v for k, v in sessions[label].items() if k != "runs"}}), flush=True)
    write_result(args.out, {
        "host": {"cpus": os.cpu_count(), "load_before": load_before, "load_after": os.getloadavg()},
        "repeats": args.repeats, "sessions": sessions,
    })  # fmt: skip
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
