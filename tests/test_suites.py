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
