"""Shared by every test: Hypothesis without a per-example deadline (a timed test fails on a loaded
machine, not on a defect: speed is measured in bench/, never asserted in tests), the ``key``
fixture (a pre-shared key file), and the guard that keeps the fast suite fast: a test that starts
an OS process (subprocess, asyncio's subprocesses, multiprocessing, a fork) and is not marked
``integration`` fails, naming what it started, so ``pytest -m "not integration"`` never starts one.
A run's summary ends with the two suites' counts and times (a run of both, as the README's command
is, shows what the fast suite alone costs).
"""

from __future__ import annotations

import compileall
import contextlib
import multiprocessing.process
import os
import platform
import subprocess
import time
from collections.abc import Callable, Generator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import settings

settings.register_profile("teleop", deadline=None)
settings.load_profile("teleop")


@pytest.fixture
def key(tmp_path: Path) -> str:
    """A deployment's pre-shared key, as `teleop keygen` writes it."""
    from teleop.session import auth

    path = tmp_path / "teleop.key"
    auth.write_key_file(path, auth.generate_key())
    return str(path)


# --- processes only in integration tests -----------------------------------------------------

_STARTED: list[str] = []  # what each process start was, in order, for the whole session


def _recording(what: Callable[..., str], original: Callable[..., Any]) -> Callable[..., Any]:
    def start(*args: Any, **kwargs: Any) -> Any:
        _STARTED.append(what(*args, **kwargs))
        return original(*args, **kwargs)

    return start


def _argv(_self: Any, args: Any, *_rest: Any, **_kw: Any) -> str:
    return " ".join(map(str, args)) if isinstance(args, list | tuple) else str(args)


def pytest_configure(config: pytest.Config) -> None:
    # Every way the stack and the tests start a process ends in one of these three: subprocess.run,
    # Popen and asyncio.create_subprocess_* in Popen._execute_child; multiprocessing (any start
    # method) in BaseProcess.start; a bare fork in os.fork.
    # The stdlib's one cached process: platform.processor() runs `uname -p` once per interpreter
    # (benches record the host); run it before the guard, so no test is charged with it.
    platform.processor()
    popen: Any = subprocess.Popen
    popen._execute_child = _recording(_argv, popen._execute_child)
    base: Any = multiprocessing.process.BaseProcess
    base.start = _recording(lambda self: f"multiprocessing {self.name}", base.start)
    os.fork = _recording(lambda: "os.fork()", os.fork)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Generator[None, None, None]:
    item.stash[_FIRST] = len(_STARTED)
    yield


_FIRST = pytest.StashKey[int]()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Generator[None, Any, None]:
    outcome = yield
    report: pytest.TestReport = outcome.get_result()
    if report.when != "teardown" or item.get_closest_marker("integration") is not None:
        return
    started = _STARTED[item.stash.get(_FIRST, len(_STARTED)) :]
    if started:
        report.outcome = "failed"
        report.longrepr = (
            f"{item.nodeid} started {len(started)} process(es) (first: {started[0][:200]}) "
            "but is not marked integration (pytest.mark.integration): the fast suite, "
            '`pytest -m "not integration"`, starts none'
        )


# --- the two suites in the summary -------------------------------------------------------------

_SUITES: dict[str, list[float]] = {"fast": [], "integration": []}  # per test: seconds, all phases
_IN_SUITE: dict[str, str] = {}  # by node id, where this process collected (not under xdist)
_WALL: list[float] = []  # when the run began (time.monotonic)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        _IN_SUITE[item.nodeid] = "integration" if item.get_closest_marker("integration") else "fast"
    _serial_alone(config, items)


def _serial_alone(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Only a process-starting test can be serial (it measures time or load, or holds a host-wide
    resource: it never runs beside another; see :func:`pytest_runtest_setup`)."""
    serial = [i for i in items if i.get_closest_marker("serial")]
    wrong = [i.nodeid for i in serial if not i.get_closest_marker("integration")]
    if wrong:
        raise pytest.UsageError(f"marked serial but not integration: {', '.join(wrong[:5])}")


def pytest_runtest_setup(item: pytest.Item) -> None:
    """A serial test under pytest-xdist with two workers or more fails, saying how to run it: a
    timing result taken beside another test is not one to trust (each worker collects, so this is
    where the worker count is known)."""
    workers = int(getattr(item.config, "workerinput", {}).get("workercount", 1))
    if workers > 1 and item.get_closest_marker("serial"):
        pytest.fail(
            f"a serial test under -n {workers}: it measures time or load, or holds the host; run it "
            "alone (-m serial, no -n) and the others with -m 'not serial'",
            pytrace=False,
        )


def pytest_sessionstart(session: pytest.Session) -> None:
    _WALL.append(time.monotonic())
    _compile_the_project()
    _font_cache()
    _mujoco()


def _mujoco() -> None:
    """MuJoCo imported before any test: its import loads glfw, whose version probe is a child
    process, and the fast suite's guard then failed whichever test checked ``--robot mujoco``
    first (``test_devices``, ``test_config``)."""
    with contextlib.suppress(ImportError):  # an install without the extra: its tests skip
        import mujoco  # noqa: F401


def _font_cache() -> None:
    """matplotlib's font list, built before any test.  Why: on a machine where it was never built
    (a fresh one, as CI's may be) the first plot runs ``fc-list`` to build it, and the fast suite's
    guard then fails whichever test drew first for starting a process."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.font_manager  # builds the cache, or loads it


#: The project's packages, which every process a test starts imports (an editable install: pip
#: compiled none of them).
_PACKAGES = ("teleop", "transport", "shell", "conformance", "tests", "bench")


def _compile_the_project() -> None:
    """Each package's modules compiled into ``__pycache__`` once, before any test.  Why: with
    ``PYTHONDONTWRITEBYTECODE`` set, as on this project's machines, no process caches what it
    compiles, so each of the ~500 processes the integration tests start compiled the project anew:
    ~0.1 s more of a process's start (0.21 against 0.32 s to import the CLI, the runner and the log
    writer, measured).  Up-to-date files are skipped; under xdist each worker checks the same."""
    root = Path(__file__).resolve().parents[1]
    for name in _PACKAGES:
        compileall.compile_dir(root / name, quiet=2, workers=1)


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    # Under pytest-xdist (`-n 2`) the workers collect and this hook runs in the controller: there
    # the report's keywords (its markers among them) tell.
    suite = _IN_SUITE.get(report.nodeid) or ("integration" if "integration" in report.keywords else "fast")
    if report.when == "setup":
        _SUITES[suite].append(0.0)
    if _SUITES[suite]:
        _SUITES[suite][-1] += report.duration


def pytest_terminal_summary(terminalreporter: Any) -> None:
    parts = [
        f"{name} {len(times)} tests in {sum(times):.1f} s"
        for name, times in (
            ("fast suite (-m 'not integration'):", _SUITES["fast"]),
            ("integration:", _SUITES["integration"]),
        )
        if times
    ]
    if parts:
        wall = f"; the run's wall time {time.monotonic() - _WALL[0]:.1f} s" if _WALL else ""
        line = "suites (setup + call + teardown of each test): " + "; ".join(parts) + wall
        terminalreporter.write_line(line)
