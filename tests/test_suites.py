"""The fast suite's guard (tests/conftest.py): every way a test can start a process is seen."""

from __future__ import annotations

import asyncio
import multiprocessing
import subprocess
import sys

import pytest

from tests import conftest


def _nothing() -> None:
    pass


@pytest.mark.integration  # it starts processes, three ways
def test_the_guard_sees_every_way_a_process_starts() -> None:
    seen = len(conftest._STARTED)
    subprocess.run([sys.executable, "-c", "pass"], check=True)

    async def child() -> int:
        p = await asyncio.create_subprocess_exec(sys.executable, "-c", "pass")
        return await p.wait()

    assert asyncio.run(child()) == 0
    # (spawn, not fork: a fork of this process, whose other threads may hold locks, is not a test's)
    p = multiprocessing.get_context("spawn").Process(target=_nothing)
    p.start()
    p.join(30)
    assert p.exitcode == 0
    started = conftest._STARTED[seen:]
    assert sum(sys.executable in s for s in started) >= 2  # subprocess.run, asyncio's exec
    assert sum(s.startswith("multiprocessing") for s in started) == 1


def test_a_test_without_a_process_starts_none() -> None:
    seen = len(conftest._STARTED)
    assert sum(range(10)) == 45
    assert conftest._STARTED[seen:] == []


@pytest.mark.integration
@pytest.mark.serial
def test_a_serial_test_runs_alone() -> None:
    """The README's last test command runs the serial tests without pytest-xdist: one at a time."""
    import os

    assert os.environ.get("PYTEST_XDIST_WORKER") is None


@pytest.mark.integration  # a pytest of its own, with two workers
def test_a_serial_test_under_two_workers_fails_saying_how_to_run_it() -> None:
    """A timing test run beside another would give a result not to trust: under -n 2 it fails,
    naming the command that runs it alone."""
    node = f"{__file__}::test_a_serial_test_runs_alone"
    r = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-n", "2", "-p", "no:cacheprovider", node],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert r.returncode == 1, r.stdout + r.stderr
    assert "a serial test under -n 2" in r.stdout and "(-m serial, no -n)" in r.stdout, r.stdout
