"""``teleop run`` with a probe loaded in its processes, for ``bench.phases`` and ``bench.stalls``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any


def probed_run(
    root: Path, site: Path, probe_env: dict[str, str], codec: str, dof: int, duration: float, out: Path
) -> dict[str, Any]:
    """``teleop run`` (UDP, log on; no plots, sim or status lines) from ``root``'s tree, with ``site``
    (a folder whose ``sitecustomize`` loads a probe) first on ``PYTHONPATH`` and ``probe_env`` set;
    its report.  Exits saying why if the run fails."""
    env = {
        **os.environ,
        **probe_env,
        "PYTHONPATH": os.pathsep.join([str(site), str(root), os.environ.get("PYTHONPATH", "")]),
    }
    cmd = [sys.executable, "-m", "teleop.cli", "run", "--codec", codec, "--dof", str(dof)]
    cmd += ["--duration", str(duration), "--out", str(out), "--no-plots", "--no-sim", "--no-live"]
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=root)
    if r.returncode != 0:
        sys.exit(f"teleop run {codec} from {root} failed: {r.stderr}")
    report: dict[str, Any] = json.loads((out / "report.json").read_text())
    return report
