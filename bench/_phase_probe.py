"""Per-phase CPU of a real ``teleop`` process's 1 kHz loop, for ``bench.phases``.

Installed at interpreter start (``bench.phases`` puts a ``sitecustomize`` on ``PYTHONPATH`` that
calls :func:`install` when ``TELEOP_PHASES`` names a folder): it wraps the runner's and the
transport's per-tick methods with this thread's CPU clock (``time.thread_time_ns``) and at exit
writes what each took, in total, to ``TELEOP_PHASES/phases-PID.json``.  Nothing in ``teleop`` or
``transport`` knows about it.  Each wrapped call costs two clock reads; the file says how long one
read took here (``clock_read_ns``) and how many calls were wrapped, so a reader can take it off.
"""

from __future__ import annotations

import atexit
import functools
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

_acc: dict[str, int] = {}
_calls: dict[str, int] = {}
_clock = time.thread_time_ns
_ticking = [False]  # inside the runner's ticks: only then is a phase counted


def _wrap(cls: Any, name: str, key: str) -> None:
    f: Callable[..., Any] = getattr(cls, name)

    @functools.wraps(f)
    def timed(*a: Any, **k: Any) -> Any:
        if not _ticking[0]:  # the handshake's, the session start's (its GC freeze), the linger's
            return f(*a, **k)
        t = _clock()
        try:
            return f(*a, **k)
        finally:
            _count(key, _clock() - t)

    setattr(cls, name, timed)


def _count(key: str, ns: int) -> None:
    _acc[key] = _acc.get(key, 0) + ns
    _calls[key] = _calls.get(key, 0) + 1


def _awrap(cls: Any, name: str, key: str) -> None:
    """As :func:`_wrap` for a coroutine; also the process's CPU (every thread) over the same span."""
    f: Callable[..., Any] = getattr(cls, name)

    @functools.wraps(f)
    async def timed(*a: Any, **k: Any) -> Any:
        t, p = _clock(), time.process_time_ns()
        _ticking[0] = True
        try:
            return await f(*a, **k)
        finally:
            _ticking[0] = False
            _count(key, _clock() - t)
            _acc[key + "_process"] = _acc.get(key + "_process", 0) + time.process_time_ns() - p

    setattr(cls, name, timed)


def _clock_read_ns(n: int = 20_000) -> float:
    t = _clock()
    for _ in range(n):
        _clock()
    return (_clock() - t) / n


#: (module, class, method, phase, async).  ``ticks`` is the whole ticking (its CPU minus the phases is
#: the event loop's pass, a grace wait's sleeps and the loop's own lines); ``sleep`` is the sleep's CPU
#: (the system call), ``spin`` the spin's.  Every phase is counted inside the ticks only (the
#: handshake's reads, the session start's events and the linger's are not the loop's).
PHASES = (
    ("transport.session", "_Runner", "ticks", "ticks", True),
    ("transport.realtime", "Ticker", "sleep", "sleep", False),
    ("transport.realtime", "Ticker", "spin_to_deadline", "spin", False),
    ("transport.udp", "UdpTransport", "drain", "socket_read", False),
    ("teleop.session.endpoint", "Endpoint", "receive_datagram", "endpoint_receive", False),
    ("teleop.session.endpoint", "Endpoint", "tick", "endpoint_tick", False),
    ("teleop.session.port", "Port", "tick", "port_tick", False),
    ("teleop.session.endpoint", "Endpoint", "datagrams_to_send", "endpoint_send", False),
    ("transport.udp", "UdpTransport", "send", "socket_send", False),
    ("teleop.session.port", "Port", "loop_timing", "loop_timing", False),
    ("transport.watch", "LogWatch", "tick", "log_watch", False),
    ("transport.session", "_Runner", "events", "events", False),
)


def install(folder: str) -> None:
    import importlib

    role = next((a for a in sys.argv if a in ("operator", "teleoperator")), "other")
    for module, cls, method, key, is_async in PHASES:
        c = getattr(importlib.import_module(module), cls)
        (_awrap if is_async else _wrap)(c, method, key)

    def dump() -> None:
        doc = {
            "role": role,
            "pid": os.getpid(),
            "cpu_ns": _acc,
            "calls": _calls,
            "clock_read_ns": _clock_read_ns(),
        }
        Path(folder, f"phases-{os.getpid()}.json").write_text(json.dumps(doc))

    atexit.register(dump)
