"""The layers, checked on every module of every package: each imports only its own layer and those
below it, there is no import cycle, and ``transport/`` uses only the core's public names.

From the bottom: ``teleop``'s base modules (errors, files, limits), ``teleop.control`` (the
numerics), ``teleop.devices``, ``teleop.session`` (sans-I/O wire, handshake, node, port, endpoint),
``teleop.offline`` (sim, sweep, report), ``transport`` (the I/O shell), ``teleop.cli`` (the top: it
wires core and shells together).  Every import statement counts, at any depth (a function-local
import too: it hides a cycle, it does not break it), so a violation fails here rather than as a
cycle at run time.  A module no layer names fails too, so a new package must say where it stands.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: Package prefix -> rank; a module's layer is its longest matching prefix.
LAYERS = {
    "teleop": 0,
    "teleop.control": 1,
    "teleop.devices": 2,
    "teleop.session": 3,
    "teleop.offline": 4,
    "transport": 5,
    "teleop.cli": 6,
}


def _name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_name(p): p for folder in ("teleop", "transport") for p in sorted((ROOT / folder).rglob("*.py"))}


def _imports(path: Path) -> list[tuple[str, list[str], int]]:
    """(module, imported names, line) of every import in ``path``; relative ones resolved."""
    pkg = path.relative_to(ROOT).with_suffix("").parts[:-1]
    out: list[tuple[str, list[str], int]] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, [], node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = pkg[: len(pkg) - node.level + 1]
                base = ".".join([*parent, base] if base else parent)
            out.append((base, [a.name for a in node.names], node.lineno))
    return out


def _targets(path: Path) -> set[str]:
    """The project's modules ``path`` imports: ``from pkg import sub`` is the submodule ``pkg.sub``,
    ``from pkg import name`` the package ``pkg``."""
    out = set()
    for module, names, _ in _imports(path):
        for n in names or [""]:
            sub = f"{module}.{n}"
            out.add(sub if n and sub in MODULES else module)
    return (out & MODULES.keys()) - {_name(path)}


def _layer(module: str) -> str:
    return max((p for p in LAYERS if module == p or module.startswith(p + ".")), key=len, default="")


def test_the_walk_sees_imports() -> None:
    """The walker itself: it finds known imports, absolute and relative (so the checks can fail)."""
    found = _targets(ROOT / "transport" / "runner.py")
    assert "transport.realtime" in found
    assert "teleop.session.endpoint" in found
    assert _layer("teleop.session.link.netem") == "teleop.session"
    assert _layer("teleop.errors") == "teleop"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_every_module_imports_only_its_layer_and_below(module: str) -> None:
    layer = _layer(module)
    assert layer, f"{module} is in no layer: add its package to LAYERS"
    above = [(t, _layer(t)) for t in sorted(_targets(MODULES[module])) if LAYERS[_layer(t)] > LAYERS[layer]]
    assert not above, f"{module} ({layer}) imports a layer above its own: {above}"


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan): each is a cycle."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = [stack.pop()]
            while comp[-1] != v:
                comp.append(stack.pop())
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def test_no_import_cycle() -> None:
    assert not _cycles({m: _targets(p) for m, p in MODULES.items()})


def test_the_cycle_check_can_fail() -> None:
    """A cycle planted in a copy of the real graph, through a third module, is found."""
    graph = {m: set(_targets(p)) for m, p in MODULES.items()}
    graph["teleop.errors"].add("teleop.session.wire")  # wire -> limits and errors already
    assert ["teleop.errors", "teleop.session.wire"] in [
        [m for m in c if m in ("teleop.errors", "teleop.session.wire")] for c in _cycles(graph)
    ]


@pytest.mark.parametrize("path", [p for m, p in MODULES.items() if m.startswith("transport")], ids=str)
def test_transport_uses_only_public_core_names(path: Path) -> None:
    bad = []
    for module, names, line in _imports(path):
        if not module.startswith("teleop"):
            continue
        if any(part.startswith("_") for part in module.split(".")):
            bad.append((module, line))
        bad += [(f"{module}.{n}", line) for n in names if n.startswith("_")]
    assert not bad, f"{path.relative_to(ROOT)} imports private core names: {bad}"
