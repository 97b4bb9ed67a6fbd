"""The endpoint stays one thing (issue 50 item 1): the session, in one mode, its tick clock beside it
(``teleop.session.scheduler``).  Its class is at most 700 lines, none of its methods over 60, it
never reaches through its port into the node (``port.node.``), and it holds no scheduling state:
no queue of received datagrams, no tick policy, no grace."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

from teleop.session.endpoint import Endpoint

ROOT = Path(__file__).resolve().parent.parent
ENDPOINT = ROOT / "teleop" / "session" / "endpoint.py"
MAX_CLASS_LINES = 700
MAX_METHOD_LINES = 60
#: What the scheduler holds: none of it may come back into the endpoint.
SCHEDULING = ("_pending", "_policy", "_loop", "_early_at", "_grace", "grace", "_device", "_monitor")


def _shape(src: str, name: str) -> tuple[int, dict[str, int], set[str]]:
    """The class ``name`` in ``src``: its lines, each method's lines, the attributes set on self."""
    (cls,) = [n for n in ast.parse(src).body if isinstance(n, ast.ClassDef) and n.name == name]
    assert cls.end_lineno is not None
    methods = {
        f.name: f.end_lineno - f.lineno + 1
        for f in cls.body
        if isinstance(f, ast.FunctionDef) and f.end_lineno is not None
    }
    attrs = {
        t.attr
        for node in ast.walk(cls)
        if isinstance(node, ast.Assign | ast.AnnAssign | ast.AugAssign)
        for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
        for t in (t.elts if isinstance(t, ast.Tuple) else [t])
        if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id == "self"
    }
    return cls.end_lineno - cls.lineno + 1, methods, attrs


def _scheduling(attrs: set[str]) -> list[str]:
    return sorted(a for a in attrs if a in SCHEDULING or a.startswith("_grace"))


def test_the_endpoint_class_is_at_most_700_lines_and_no_method_over_60() -> None:
    lines, methods, _ = _shape(ENDPOINT.read_text(), "Endpoint")
    assert lines <= MAX_CLASS_LINES, lines
    assert len(methods) > 20, "the walk found the methods"
    long = {m: n for m, n in methods.items() if n > MAX_METHOD_LINES}
    assert not long, long


def test_the_endpoint_never_reaches_through_its_port_into_the_node() -> None:
    assert "port.node." not in ENDPOINT.read_text()


def test_the_endpoint_has_one_mode_and_no_scheduling_state() -> None:
    _, _, attrs = _shape(ENDPOINT.read_text(), "Endpoint")
    assert {"port", "params", "state", "k"} <= attrs, "the walk found its attributes"
    assert not _scheduling(attrs), _scheduling(attrs)
    params = inspect.signature(Endpoint.__init__).parameters
    assert not {"ticks", "monitor", "grace_us"} & params.keys(), sorted(params)


def test_the_shape_checks_can_fail() -> None:
    """A long class with a long method and a scheduling attribute is caught by the same walk."""
    body = "\n".join(f"        x{i} = {i}" for i in range(70))
    head = "class Endpoint:\n    def f(self):\n        self._pending = []\n        self.grace = {}\n"
    src = f"{head}{body}\n"
    lines, methods, attrs = _shape(src, "Endpoint")
    assert lines > MAX_METHOD_LINES and methods["f"] > MAX_METHOD_LINES
    assert _scheduling(attrs) == ["_pending", "grace"]
