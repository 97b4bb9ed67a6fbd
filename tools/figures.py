"""The docs' committed figures, drawn again from the JSON beside them: each experiment's
``docs/experiment/*/fig15.png`` from its ``experiment.json``, and ``docs/results/fronts.png`` from
``bench/results/fronts/sweep.json``.  Run after a change to ``teleop.offline.plots``; the data is
never re-measured here, only drawn.

    python -m tools.figures          # rewrites the PNGs in place
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def redraw(root: Path = ROOT) -> list[Path]:
    """Every figure, drawn into a new file then moved over the old one; the paths written."""
    from teleop.offline import plots

    written = []
    for doc_path in sorted((root / "docs" / "experiment").glob("*/experiment.json")):
        doc = json.loads(doc_path.read_text())
        out = doc_path.with_name("fig15.png")
        new = out.with_name(".fig15.new.png")
        plots.experiment_bars(new, doc, plots.experiment_title(doc))
        new.replace(out)
        written.append(out)
    sweep = json.loads((root / "bench" / "results" / "fronts" / "sweep.json").read_text())
    out = root / "docs" / "results" / "fronts.png"
    new = out.with_name(".fronts.new.png")
    first = sweep["fronts"][0]
    title = f"teleop sweep: {first['scenario']} (commit {sweep['commit'][:7]})"
    plots.pareto_fronts(new, sweep["fronts"], title)
    new.replace(out)
    written.append(out)
    return written


if __name__ == "__main__":
    for p in redraw():
        print(f"wrote {p.relative_to(ROOT)}", file=sys.stderr)
