"""The docs against their sources: every figure of a generated benchmark table equals the JSON value it
came from, the generated experiment tables are what ``teleop experiment`` prints for the committed
JSON, the CLI reference covers every option, and the README stays short and quotes the two
quick-start commands exactly as ``.ci/run`` runs them."""

from __future__ import annotations

import dataclasses
import json
import math
import re
import statistics
from pathlib import Path
from typing import Any

import pytest

from bench import tables
from tools import docgen

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
CI = ROOT / ".ci" / "run"

# A number as printed in a cell: not part of a word (codec names such as eds:50 are labels).
NUMBER = re.compile(r"(?<!\w)(?<!\d\.)-?\d+(?:\.\d+)?(?:e[+-]?\d+)?")


def _lookup(doc: Any, path: str) -> Any:
    """The test's own reading of ``a.b[2].c`` (independent of bench.tables.resolve)."""
    node = doc
    for token in re.findall(r"[^.\[\]]+|\[\d+\]", path):
        node = node[int(token[1:-1])] if token.startswith("[") else node[token]
    return node


def _combine(op: str, values: list[float]) -> float:
    if op == "value":
        assert len(values) == 1
        return values[0]
    if op == "sum":
        return math.fsum(values)
    if op == "median":
        return float(statistics.median(values))
    if op == "min":
        return min(values)
    if op == "max":
        return max(values)
    raise AssertionError(f"unknown op {op!r}")


def _resolution(text: str) -> float:
    """Half a unit of the last digit printed in ``text``: what rounding may have cost."""
    mantissa, _, exp = text.lower().partition("e")
    decimals = len(mantissa.split(".")[1]) if "." in mantissa else 0
    return 0.5 * 10.0 ** (int(exp or 0) - decimals)


def _rows(markdown: str) -> list[list[str]]:
    lines = [ln for ln in markdown.splitlines() if ln.startswith("|")]
    return [[c.strip() for c in ln.strip("|").split("|")] for ln in lines[2:]]  # past header and rule


def _check(table: tables.Table, doc: Any) -> tuple[int, list[str]]:
    """Read ``table``'s markdown back; return how many figures it has and those that are not the
    JSON's value (recomputed here from the paths each figure names)."""
    printed = _rows(table.markdown())
    assert len(printed) == len(table.rows) and printed, table.name
    figures, wrong = 0, []
    for row_text, row in zip(printed, table.rows, strict=True):
        assert len(row_text) == len(row) == len(table.header)
        for cell_text, cell in zip(row_text, row, strict=True):
            if isinstance(cell, str):
                assert cell_text == cell
                continue
            _, figs = cell
            numbers = NUMBER.findall(cell_text)
            assert len(numbers) == len(figs), f"{table.name}: {cell_text!r}"
            for text, fig in zip(numbers, figs, strict=True):
                values = [float(_lookup(doc, p)) for p in fig.paths]
                expected = _combine(fig.op, values) * fig.scale
                figures += 1
                if not abs(float(text) - expected) <= _resolution(text) * (1 + 1e-9):
                    source = f"{fig.op}({', '.join(fig.paths)}) x {fig.scale}"
                    wrong.append(f"printed {text} for {source} = {expected}")
    return figures, wrong


@pytest.mark.parametrize("name", sorted(tables.TABLES))
def test_every_table_figure_is_its_json_value(name: str) -> None:
    table = tables.TABLES[name]()
    doc = json.loads((tables.RESULTS / table.source).read_text())
    figures, wrong = _check(table, doc)
    assert figures > 0
    assert not wrong, f"{name}: {wrong}"


def test_every_result_records_the_commit_it_measured() -> None:
    """Issue 38: a figure without the commit it measured cannot be compared with anything.  Every
    result file names it (``bench.write_result`` writes it; older files say what git knows), and
    every table's line shows it."""
    results = sorted(tables.RESULTS.rglob("*.json"))
    assert results
    for path in results:
        commit = json.loads(path.read_text()).get("commit")
        assert isinstance(commit, str) and commit.strip(), path
    for name, make in tables.TABLES.items():
        assert f"Measured at commit {tables.measured_commit(make().source)}." in make().markdown(), name


@pytest.mark.integration  # git rev-parse and git status: processes
def test_the_bench_writer_records_the_commit(tmp_path: Path) -> None:
    import bench

    out = tmp_path / "r.json"
    bench.write_result(out, {"what": "x"})
    doc = json.loads(out.read_text())
    assert list(doc) == ["commit", "what"] and doc["commit"] == bench.commit()
    bench.write_result(out, {"what": "x", "commit": "abc (another tree)"})  # a bench that measured another
    assert json.loads(out.read_text())["commit"] == "abc (another tree)"


def test_a_figure_that_is_not_the_json_value_is_caught() -> None:
    """The check fails on a table whose figure does not match its JSON path."""
    table = tables.sweep()
    doc = json.loads((tables.RESULTS / table.source).read_text())
    first = table.rows[0]
    cell = first[1]
    assert not isinstance(cell, str)
    template, figs = cell
    off = dataclasses.replace(figs[0], value=figs[0].value * 1.01)
    tampered_row = (first[0], (template, (off, *figs[1:])), *first[2:])
    tampered = dataclasses.replace(table, rows=(tampered_row, *table.rows[1:]))
    _, wrong = _check(tampered, doc)
    assert len(wrong) == 1


def test_the_sweep_table_has_every_case() -> None:
    doc = json.loads((tables.RESULTS / "sweep" / "sweep.json").read_text())
    rows = _rows(tables.sweep().markdown())
    assert sorted(r[0].strip("`") for r in rows) == sorted(c["codec"] for c in doc["cases"])


def test_experiment_tables_are_what_teleop_experiment_prints() -> None:
    from teleop.offline.experiment import format_paired, format_table

    for folder in docgen.EXPERIMENTS:
        doc = json.loads((ROOT / "docs" / "experiment" / folder / "experiment.json").read_text())
        snippet = docgen.experiment_snippet(folder)
        assert format_table(doc) in snippet
        assert format_paired(doc) in snippet


def test_cli_reference_lists_every_command_and_option() -> None:
    import argparse

    from teleop.cli.parser import build_parser

    text = docgen.cli_reference()
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    for name, parser in sub.choices.items():
        assert f"## `teleop {name}`" in text
        for action in parser._actions:
            if action.help != argparse.SUPPRESS:
                for opt in action.option_strings:
                    assert f"`{opt}`" in text, f"teleop {name} {opt}"


def test_the_cli_reference_in_the_repository_is_the_parsers(tmp_path: Path) -> None:
    """docs/reference/cli.md is the whole reference, readable without building the site (it was
    one include line): it must be what the parsers say now."""
    assert docgen.CLI_PAGE.read_text() == docgen.cli_page(), (
        "docs/reference/cli.md is stale: run .venv/bin/python -m tools.docgen --cli"
    )


def test_generated_snippets_cover_every_include(tmp_path: Path) -> None:
    """Every ``--8<-- "NAME"`` in a page is a file the generator writes (or PROTOCOL.md), or a
    section of a file (``FILE:SECTION``) whose markers are there."""
    written = {p.name for p in docgen.write_all(tmp_path)}
    for page in (ROOT / "docs").rglob("*.md"):
        if "_generated" in page.parts:
            continue
        for name in re.findall(r'^--8<-- "([^"]+)"', page.read_text(), flags=re.M):
            file, _, section = name.partition(":")
            if section:
                assert f"--8<-- [start:{section}]" in (ROOT / file).read_text(), f"{page}: {name}"
                continue
            assert name in written or (ROOT / name).is_file(), f"{page}: {name}"


def _quick_start_commands(text: str) -> list[str]:
    return [ln.strip() for ln in text.splitlines() if ln.strip().startswith("python3 -m venv .venv")]


def test_readme_is_short_and_quotes_ci_commands() -> None:
    readme = README.read_text()
    assert len(readme.splitlines()) <= 200
    ci = _quick_start_commands(CI.read_text())
    ours = _quick_start_commands(readme)
    assert ci, ".ci/run lost its copy of the README's test command"
    assert len(ours) == 2
    # The first runs the main job, the second the tests; .ci/run runs the second verbatim.
    assert ours[1] in ci
    assert ours[0].endswith(".venv/bin/teleop run")
    assert ours[0].split(" && ")[:2] == ours[1].split(" && ")[:2]  # the same set-up (venv, pip)


def test_readme_links_resolve() -> None:
    readme = README.read_text()
    for target in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", readme):
        if "://" in target:
            continue
        assert (ROOT / target).exists(), target


def test_nothing_in_the_repository_points_at_a_file_outside_it() -> None:
    """The design notes the project was built from are not in this repository: code and docs
    name what is here (issue 50 counted 10 such pointers)."""
    outside = re.compile(r"DESIGN\.md|DEVELOPERS\.md|\.\./shared")
    found = []
    subs = ("teleop", "transport", "shell", "conformance", "bench", "tests", "tools", "docs", "deploy", ".ci")
    for sub in subs:
        for path in (ROOT / sub).rglob("*"):
            if path.is_file() and path.suffix in (".py", ".md", ".toml", ".yml", ".json5", ".sh", ""):
                if path.name == "test_docs.py" or "_generated" in path.parts:
                    continue
                text = path.read_text(errors="replace")
                found += [f"{path.relative_to(ROOT)}: {m.group(0)}" for m in outside.finditer(text)]
    for name in ("README.md", "PROTOCOL.md", "pyproject.toml", "mkdocs.yml"):
        found += [f"{name}: {m.group(0)}" for m in outside.finditer((ROOT / name).read_text())]
    assert not found, found


def _layout() -> str:
    text = (ROOT / "docs" / "reference" / "development.md").read_text()
    block = text.split("## Layout", 1)[1]
    return block.split("```text\n", 1)[1].split("```", 1)[0]


def _unnamed(layout: str) -> list[str]:
    """The project's modules the layout does not name as a word (bench's and tools' modules are
    listed by their folder: ``python -m bench.NAME``)."""
    words = set(re.findall(r"[A-Za-z_][A-Za-z0-9_]*", layout))
    missing = []
    for pkg in ("teleop", "transport", "shell", "conformance", "bench", "tools"):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            if pkg in ("bench", "tools") and path.stem != "__init__":
                continue
            name = path.stem if path.stem not in ("__init__", "__main__") else path.parent.name
            if name not in words:
                missing.append(str(path.relative_to(ROOT)))
    return missing


def test_the_development_layout_names_every_module_and_only_folders_that_exist() -> None:
    """The layout in the development docs against the tree (issue 50: it once called a moved module
    the runner and missed seven): every module of every package is named there as a word, and every
    top-level ``folder/`` it lists is in the repository."""
    layout = _layout()
    assert not _unnamed(layout), f"modules the layout does not name: {_unnamed(layout)}"
    tops = re.findall(r"^([a-z_]+)/", layout, re.M)
    assert {"teleop", "transport", "shell", "conformance", "docs"} <= set(tops)
    assert all((ROOT / t).is_dir() for t in tops), [t for t in tops if not (ROOT / t).is_dir()]


def test_the_layout_check_can_fail() -> None:
    """A module the layout stops naming is reported."""
    assert _unnamed(_layout().replace("sockfilter", "")) == ["transport/sockfilter.py"]


def _nav_pages() -> list[str]:
    """The site's pages in mkdocs.yml's nav order: the one list of pages."""
    nav = (ROOT / "mkdocs.yml").read_text().split("\nnav:\n", 1)[1]
    return re.findall(r":\s*([\w/.-]+\.md)\s*$", nav, re.M)


def test_the_page_list_lives_in_mkdocs_nav_and_the_readme_and_index_follow_it() -> None:
    """The page list was kept three times and drifted (issue 50: the index lacked four pages): the
    nav is the list, and the README's table and the site's index name the same pages in its order."""
    pages = _nav_pages()
    assert len(pages) >= 20 and pages[0] == "index.md", pages
    # (the README links the protocol's own file, which the site's reference/protocol.md includes)
    rows = re.findall(r"^\|[^|]*\| \[[^]]+\]\(([\w/.-]+\.md)\)", README.read_text(), re.M)
    readme = ["reference/protocol.md" if r == "PROTOCOL.md" else r.removeprefix("docs/") for r in rows]
    assert readme == pages[1:]
    index = (ROOT / "docs" / "index.md").read_text().split("## Guides", 1)[1]
    assert re.findall(r"^- \[[^]]+\]\(([\w/.-]+\.md)\)", index, re.M) == pages[1:]
    assert all((ROOT / "docs" / p).is_file() for p in pages)


def test_the_sample_output_is_held_once_in_the_readme_and_included_by_the_first_session() -> None:
    """The README's sample output was copied into first-session.md (34 lines) and could drift: the
    guide includes the README's block; ``python -m tools.docgen --sample`` rewrites it from a run."""
    block = docgen.SAMPLE.search(README.read_text())
    assert block is not None and block.group(2).startswith("teleop run: ")
    guide = (ROOT / "docs" / "guides" / "first-session.md").read_text()
    assert '--8<-- "README.md:sample"' in guide
    assert block.group(2).splitlines()[-1] not in guide  # included, not copied
