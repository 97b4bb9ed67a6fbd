"""Waiting for what a test needs, never for a fixed time.

A test that sleeps a fixed time either waits longer than it needs on a quiet host or fails on a
loaded one (issue 38: a restart test failed under load for that).  These poll a condition until it
holds or a deadline passes; the deadline is generous because reaching it is a failure, not the
normal path, so it costs nothing when the condition comes true early.
"""

from __future__ import annotations

import asyncio
import subprocess
import time
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import TypeVar

from tests.ran import RAN

T = TypeVar("T")

#: Between two polls: short against every deadline here, long enough not to load the host.
POLL_S = 0.01


def wait_for(predicate: Callable[[], T], timeout: float = 10.0, what: str = "", poll: float = POLL_S) -> T:
    """Poll ``predicate`` until it returns something true, and return that; fail the test after
    ``timeout`` seconds, naming ``what`` it waited for."""
    deadline = time.monotonic() + timeout
    while True:
        got = predicate()
        if got:
            return got
        if time.monotonic() > deadline:
            raise AssertionError(f"waited {timeout:g} s for {what or predicate!r} in vain")
        time.sleep(poll)  # the poll interval, not a fixed wait: see the module's docstring


def exited_ok(proc: subprocess.Popen[str], timeout: float = 30.0) -> None:
    """Wait for ``proc`` to exit and fail the test with its stderr unless it ran its session (0, or 3:
    a poor session, see tests/ran.py): a bare ``returncode == 0`` assertion hides why a process
    failed, and a flaky failure is then a guess."""
    code = proc.wait(timeout=timeout)
    if code not in RAN:
        err = proc.stderr.read() if proc.stderr is not None else ""
        raise AssertionError(f"{proc.args!r} exited {code}; its stderr:\n{err[-4000:]}")


async def await_for(
    predicate: Callable[[], T | Awaitable[T]], timeout: float = 10.0, what: str = "", poll: float = POLL_S
) -> T:
    """:func:`wait_for` in a coroutine: the event loop runs between polls; ``predicate`` may be a
    coroutine function."""
    deadline = time.monotonic() + timeout
    while True:
        got = predicate()
        if isinstance(got, Awaitable):
            got = await got
        if got:
            return got
        if time.monotonic() > deadline:
            raise AssertionError(f"waited {timeout:g} s for {what or predicate!r} in vain")
        await asyncio.sleep(poll)  # the poll interval, not a fixed wait: see the module's docstring


async def pace(period: float) -> None:
    """The pace of a sender that must not flood (Zenoh drops under congestion; a live view takes
    what it is fed at its rate): one period between two sends.  Not a wait for anything: nothing is
    asserted on what happens during it."""
    await asyncio.sleep(period)  # a sender's pace, not a fixed wait


def _hex_address(host: str, port: int) -> str:
    return f"{''.join(reversed([f'{int(b):02X}' for b in host.split('.')]))}:{port:04X}"


def _sockets(table: str) -> list[list[str]]:
    with open(f"/proc/net/{table}") as f:
        next(f)
        return [line.split() for line in f]


def udp_bound(port: int, host: str = "127.0.0.1") -> bool:
    """Whether a socket of this host is bound to UDP ``host:port`` (read from /proc, so that the
    check never takes the port itself: a test's own bind would make the process it waits for fail)."""
    want = _hex_address(host, port)
    return any(row[1] == want for row in _sockets("udp"))


def udp_queued(port: int, host: str = "127.0.0.1") -> int:
    """The bytes the kernel holds for the socket bound to UDP ``host:port`` (its receive queue as
    /proc counts it: each datagram's whole buffer, the same for datagrams of one size)."""
    want = _hex_address(host, port)
    return sum(int(row[4].split(":")[1], 16) for row in _sockets("udp") if row[1] == want)


def tcp_listening(port: int, host: str = "127.0.0.1") -> bool:
    """Whether a socket of this host listens on TCP ``host:port`` (a Zenoh router or peer is up)."""
    want = _hex_address(host, port)
    return any(row[1] == want and row[3] == "0A" for row in _sockets("tcp"))


def tcp_clients(port: int, host: str = "127.0.0.1") -> int:
    """How many established TCP connections of this host lead to ``host:port`` (the clients a
    Zenoh router on it has: a client that has joined it)."""
    want = _hex_address(host, port)
    return sum(1 for row in _sockets("tcp") if row[2] == want and row[3] == "01")


def ticks_logged(path: Path) -> int:
    """How many ticks a session's log holds so far: a live log, whose writer is still writing it,
    is read up to its last whole chunk (0 while it does not exist or holds none)."""
    from teleop.offline.logfile import LogError, iter_ticks

    n = 0
    try:
        for k0, arrays in iter_ticks(path, ("signals",)):
            n = k0 + len(arrays["ran"])
    except (LogError, FileNotFoundError):
        pass
    return n
