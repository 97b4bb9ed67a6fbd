"""The cyclic GC's collections while a real ``teleop`` process ticks, for ``bench.stalls``.

Installed at interpreter start (``bench.stalls`` puts a ``sitecustomize`` on ``PYTHONPATH`` that
calls :func:`install` when ``TELEOP_GC_PROBE`` names a folder): a ``gc.callbacks`` hook times every
collection, and a wrapper of the runner's ``ticks`` marks when the process ticks; at exit it writes
``TELEOP_GC_PROBE/gc-PID.json``, the collections made while ticking as ``[generation, us]``.
Nothing in ``teleop`` or ``transport`` knows about it.
"""

from __future__ import annotations

import atexit
import functools
import gc
import json
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

_ticking = [False]
_started = [0]
_collections: list[tuple[int, float]] = []


def _hook(phase: str, info: dict[str, Any]) -> None:
    if phase == "start":
        _started[0] = time.perf_counter_ns()
    elif _ticking[0]:
        _collections.append((int(info["generation"]), (time.perf_counter_ns() - _started[0]) / 1e3))


def install(folder: str) -> None:
    """Hook the GC and the runner, in an operator or teleoperator process only (not the log's
    writer, nor ``teleop run``'s parent)."""
    if not any(a in ("operator", "teleoperator") for a in sys.argv):
        return
    from transport.session import _Runner

    ticks: Callable[..., Any] = _Runner.ticks

    @functools.wraps(ticks)
    async def marked(*a: Any, **k: Any) -> Any:
        _ticking[0] = True
        try:
            return await ticks(*a, **k)
        finally:
            _ticking[0] = False

    _Runner.ticks = marked  # type: ignore[method-assign]
    gc.callbacks.append(_hook)

    def dump() -> None:
        Path(folder, f"gc-{os.getpid()}.json").write_text(json.dumps(_collections))

    atexit.register(dump)
