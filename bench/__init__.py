"""Benchmarks: ``python -m bench.NAME`` writes ``bench/results/NAME.json`` through
:func:`write_result`, which records the commit measured; ``bench/tables.py`` turns the results into
the docs' tables."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent


def commit(root: Path = ROOT) -> str:
    """The commit checked out at ``root`` (or why it is not known), and whether tracked files
    differ from it: a figure measured on uncommitted changes says so.  ``bench/results`` is left
    out: benches run one after another write there, and their output is not the code measured."""
    r = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True)
    if r.returncode != 0:
        return f"unknown ({r.stderr.strip()})"
    status = ["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"]
    status += ["--", ".", ":!bench/results"]
    st = subprocess.run(status, capture_output=True, text=True)
    return r.stdout.strip() + (" with uncommitted changes" if st.stdout.strip() else "")


def write_result(path: Path | str, doc: dict[str, Any], indent: int = 2, root: Path = ROOT) -> None:
    """Write a bench's result: ``doc`` with the commit it measured first (``doc``'s own ``commit``,
    if it names one, wins: a bench that measured another tree says which)."""
    out = {"commit": commit(root), **doc}
    Path(path).write_text(json.dumps(out, indent=indent, default=str) + "\n")
