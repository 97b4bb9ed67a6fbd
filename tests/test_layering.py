"""The core does not import the shell: ``teleop/`` (less ``teleop/cli``) never imports ``transport``,
and ``transport/`` imports only the core's public names (no ``_private`` ones).

Walks every import statement of every module (``ast``), at any depth (function-local imports too),
so a violation anywhere fails here rather than as a cycle at run time.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


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


def _modules(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def test_the_walk_sees_imports() -> None:
    """The walker itself: it finds a known import, relative ones resolved (so the checks can fail)."""
    found = _imports(ROOT / "transport" / "session.py")
    assert any(m == "transport.realtime" for m, _, _ in found)
    assert any(m.startswith("teleop") for m, _, _ in found)


@pytest.mark.parametrize("path", _modules("teleop"), ids=lambda p: str(p.relative_to(ROOT)))
def test_core_never_imports_transport(path: Path) -> None:
    if "cli" in path.relative_to(ROOT).parts:
        pytest.skip("teleop/cli wires core and shells together")
    bad = [(m, line) for m, _, line in _imports(path) if m == "transport" or m.startswith("transport.")]
    assert not bad, f"{path.relative_to(ROOT)} imports the shell: {bad}"


@pytest.mark.parametrize("path", _modules("transport"), ids=lambda p: str(p.relative_to(ROOT)))
def test_transport_uses_only_public_core_names(path: Path) -> None:
    bad = []
    for module, names, line in _imports(path):
        if not module.startswith("teleop"):
            continue
        if any(part.startswith("_") for part in module.split(".")):
            bad.append((module, line))
        bad += [(f"{module}.{n}", line) for n in names if n.startswith("_")]
    assert not bad, f"{path.relative_to(ROOT)} imports private core names: {bad}"
