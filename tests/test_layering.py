"""The layers, checked on every module of every package: each imports only its own layer and those
below it, there is no import cycle, and the shells use only the core's public names.

From the bottom: ``teleop``'s base modules (errors, files, limits), ``teleop.control`` (the
numerics), ``teleop.devices``, ``teleop.session`` (sans-I/O wire, handshake, node, port, endpoint),
``teleop.offline`` (sim, sweep, report), ``transport`` (the carriers: UDP, Zenoh, the socket
filter), ``shell`` (the process around an endpoint: the 1 kHz loop, console, logs), ``conformance``
(the checker, a driver of its own over the transports), ``teleop.cli`` (the top: it wires core and
shells together).  Every import statement counts, at any depth (a function-local
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
    "shell": 6,
    "conformance": 7,
    "teleop.cli": 8,
}


#: Every package of the project's code (tests, bench and tools stand outside the layers).
PACKAGES = ("teleop", "transport", "shell", "conformance")


def _name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_name(p): p for folder in PACKAGES for p in sorted((ROOT / folder).rglob("*.py"))}


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
    found = _targets(ROOT / "shell" / "runner.py")
    assert "shell.realtime" in found
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


@pytest.mark.parametrize("path", [p for m, p in MODULES.items() if not m.startswith("teleop")], ids=str)
def test_shells_use_only_public_core_names(path: Path) -> None:
    bad = []
    for module, names, line in _imports(path):
        if not module.startswith("teleop"):
            continue
        if any(part.startswith("_") for part in module.split(".")):
            bad.append((module, line))
        bad += [(f"{module}.{n}", line) for n in names if n.startswith("_")]
    assert not bad, f"{path.relative_to(ROOT)} imports private core names: {bad}"


def _classes() -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for module, path in MODULES.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef):
                out.setdefault(node.name, []).append(module)
    return out


def test_one_name_per_idea_no_two_classes_share_a_name() -> None:
    """Two ``Port`` classes and two ``Monitor`` classes once meant two ideas under one name (issue 50):
    every class of every package has a name of its own."""
    classes = _classes()
    assert "Port" in classes and "Endpoint" in classes  # the walk sees classes
    assert not {n: m for n, m in classes.items() if len(m) > 1}


def test_no_module_is_named_like_a_package() -> None:
    """``transport/session.py`` beside ``teleop/session/`` read as one idea: a module's last name is
    never the name of a package elsewhere in the project.  The CLI's modules are named for their
    commands (``teleop conformance`` is ``teleop.cli.conformance``), so they stand outside the rule."""
    packages = {m.rsplit(".", 1)[-1] for m, p in MODULES.items() if p.name == "__init__.py"}
    modules = [m for m, p in MODULES.items() if p.name != "__init__.py" and not m.startswith("teleop.cli.")]
    clash = [m for m in modules if m.rsplit(".", 1)[-1] in packages]
    assert not clash, clash
