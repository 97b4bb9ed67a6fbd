"""Functions that fit on a screen (issue 50 item 5: 18 were over 80 lines): at most five in the
project's packages, each named here with the one-line reason it stays whole."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("teleop", "transport", "shell", "conformance")
LIMIT = 80  # lines, signature and docstring included

#: The long functions kept long, and why; a new one must be split or argued for here (at most five).
ALLOWED = {
    "teleop/control/codecs/reflective.py:encode": "one tick's encoder state machine in the paper's order; "
    "split, its dozen state fields would travel as arguments on the hot path",
    "teleop/files.py:open_dir": "the safe-open walk is one audit read top to bottom: each refusal sits "
    "beside the syscall whose result it checks",
    "teleop/offline/logfile.py:iter_ticks": "a hostile file's reader: every bound is checked where the "
    "value it bounds is read, in the order of the file",
    "conformance/checker.py:_energy_checks": "the energy rules of PROTOCOL.md 3.4 and 3.6 share one "
    "pass over the recorded packets and one tally",
}


def long_functions() -> dict[str, int]:
    out = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    n = (node.end_lineno or node.lineno) - node.lineno + 1
                    if n > LIMIT:
                        out[f"{path.relative_to(ROOT)}:{node.name}"] = n
    return out


def test_at_most_five_functions_are_over_80_lines_each_with_its_reason() -> None:
    assert len(ALLOWED) <= 5 and all(len(why) > 20 for why in ALLOWED.values())
    found = long_functions()
    assert "teleop/files.py:open_dir" in found  # the walk sees a long one (so the check can fail)
    unexplained = {k: n for k, n in found.items() if k not in ALLOWED}
    assert not unexplained, f"over {LIMIT} lines, split them or say why here: {unexplained}"
    stale = set(ALLOWED) - set(found)
    assert not stale, f"no longer over {LIMIT} lines: take them off the list: {stale}"
