"""The real-time runner stays a thin shell around the endpoint (issue 38 item 2): it waits, reads,
sends and prints, in at most 300 lines, through at most 8 of the endpoint's names and never its
port; the scheduling policy is the endpoint's (``teleop.session.schedule``), tested in virtual time.
And nothing outside the tests builds or patches a private class."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RUNNER = ROOT / "shell" / "runner.py"


def _endpoint_names(tree: ast.AST) -> set[str]:
    """Attributes read on the endpoint: ``self.ep.x``, or ``x`` of a local bound to ``self.ep``."""
    locals_: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign | ast.AnnAssign):
            value = node.value
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            pairs: list[tuple[ast.expr, ast.expr | None]]
            if isinstance(value, ast.Tuple):
                pairs = [
                    (t, v)
                    for tt in targets
                    if isinstance(tt, ast.Tuple)
                    for t, v in zip(tt.elts, value.elts, strict=False)
                ]
            else:
                pairs = [(t, value) for t in targets]
            for t, v in pairs:
                if isinstance(t, ast.Name) and isinstance(v, ast.Attribute) and v.attr == "ep":
                    locals_.add(t.id)
    names = set()
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute):
            continue
        v = node.value
        if (isinstance(v, ast.Attribute) and v.attr == "ep" and isinstance(v.value, ast.Name)) or (
            isinstance(v, ast.Name) and v.id in locals_
        ):
            names.add(node.attr)
    return names


def test_the_runner_is_at_most_300_lines_and_uses_at_most_8_endpoint_names() -> None:
    text = RUNNER.read_text()
    assert len(text.splitlines()) <= 300
    names = _endpoint_names(ast.parse(text))
    assert names, "the walk found none: it would pass whatever the runner did"
    assert len(names) <= 8, sorted(names)
    assert "port" not in names
    assert names <= {
        "receive_datagram",
        "datagrams_to_send",
        "get_timer",
        "handle_timer",
        "next_event",
        "stop",
        "fault",
        "awaiting_payload",
    }, sorted(names)


def test_the_walk_sees_a_local_alias_of_the_endpoint() -> None:
    src = "def f(self):\n    ep, clock = self.ep, self.clock\n    ep.port.settle()\n    self.ep.tick(1, 2)\n"
    assert _endpoint_names(ast.parse(src)) == {"port", "tick"}


def test_nothing_outside_the_tests_builds_or_imports_a_private_class() -> None:
    found = []
    for top in ("teleop", "transport", "shell", "conformance", "bench", "tools"):
        for path in (ROOT / top).rglob("*.py"):
            tree = ast.parse(path.read_text())
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom):
                    found += [
                        f"{path}: {a.name}"
                        for a in node.names
                        if a.name.startswith("_") and a.name[1:2].isupper()
                    ]
                elif isinstance(node, ast.Call) and ast.unparse(node.func) == "object.__new__":
                    found.append(f"{path}:{node.lineno}: object.__new__")
    assert not found, found
