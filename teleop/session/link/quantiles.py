"""Percentiles of a stream in bounded memory: loop timing and one-way delay of a session of any length.

A session without a fixed end cannot keep every sample (8 bytes a tick is 29 MB an hour).
:class:`Quantiles` keeps the first ``exact`` samples as they are, so short sessions (every test, most
runs) report exact percentiles; past that it moves to a histogram of log-spaced bins of ``|x|`` per
sign, whose relative resolution is ``rel`` (0.1 %: a p99 of 123.4 us reads as 123.4 +- 0.06 us).
Memory is then fixed (about 2 x 23k counters), whatever the session's length.
"""

from __future__ import annotations

import math
from array import array

import numpy as np
import numpy.typing as npt

__all__ = ["Quantiles", "linear_quantile"]

Array = npt.NDArray[np.float64]
#: Kept samples binned with each sample added once binning started (``Quantiles._start_binning``):
#: ~50 us of numpy each, so 65 536 of them move over 64 samples (a 1 kHz loop's 64 ticks).
MOVE_PER_ADD = 1024


def linear_quantile(x: Array, q: float) -> float:
    """``np.quantile(x, q)`` (its default, linear method), bit for bit, for a 1-d array of finite
    floats: one ``np.partition`` and numpy's own interpolation (``_lerp``) in Python floats.

    Why: ``np.quantile`` is some twenty Python-level numpy calls; run in a tick every 100 ticks by
    the phase estimator it took ~270 us cold (measured), which delayed that tick's send."""
    n = x.size
    v = (n - 1) * q
    if v >= n - 1:
        return float(x.max())
    if v < 0:
        return float(x.min())
    i = math.floor(v)
    g = v - i
    part = np.partition(x, (i, i + 1))
    a, b = float(part[i]), float(part[i + 1])
    d = b - a
    return b - d * (1 - g) if g >= 0.5 else a + d * g


class Quantiles:
    """Streaming percentiles: exact up to ``exact`` samples, then binned (``lo`` .. ``hi`` in |x|)."""

    __slots__ = (
        "_bins",
        "_exact",
        "_inv_log",
        "_lo",
        "_moved",
        "_neg",
        "_pos",
        "_samples",
        "_to_move",
        "count",
        "max_abs",
        "total",
    )

    def __init__(self, exact: int = 1 << 16, lo: float = 1e-9, hi: float = 1e3, rel: float = 1e-3) -> None:
        if not 0 < lo < hi or rel <= 0 or exact < 0:
            raise ValueError("need 0 < lo < hi, rel > 0 and exact >= 0")
        self._exact = exact
        self._lo = lo
        self._inv_log = 1.0 / math.log1p(rel)
        self._bins = math.ceil(math.log(hi / lo) * self._inv_log) + 2  # 0: below lo; last: above hi
        self._samples: array[float] | None = array("d")  # 8 bytes a sample until binned
        self._pos: Array | None = None
        self._neg: Array | None = None
        self._to_move: Array | None = None  # the exact samples still to bin, once binning started
        self._moved = 0
        self.count = 0
        self.total = 0.0
        self.max_abs = 0.0

    def add(self, x: float) -> None:
        """One sample (O(1), no allocation once binned)."""
        self.count += 1
        self.total += x
        a = abs(x)
        if a > self.max_abs:
            self.max_abs = a
        s = self._samples
        if s is not None:
            s.append(x)
            if len(s) > self._exact:
                self._start_binning()
            return
        self._bin(x)
        if self._to_move is not None:
            self._move(MOVE_PER_ADD)

    def _bin(self, x: float) -> None:
        a = abs(x)
        i = 0 if a < self._lo else min(self._bins - 1, 1 + int(math.log(a / self._lo) * self._inv_log))
        h = self._pos if x >= 0 else self._neg
        assert h is not None
        h[i] += 1

    def _start_binning(self) -> None:
        """The exact samples ran out: bins from now on.  The kept samples move into them
        MOVE_PER_ADD at a time with each later sample (all at once if percentiles are asked first):
        moved in one go, 65 536 of them stalled the caller ~41 ms in Python and ~3 ms in numpy,
        and the loop's ticker holds four of these that fill on the same tick (65.5 s into a
        session), a link observer one."""
        s, self._samples = self._samples or array("d"), None
        self._pos = np.zeros(self._bins)
        self._neg = np.zeros(self._bins)
        self._to_move, self._moved = np.frombuffer(s, dtype=np.float64), 0

    def _move(self, n: int) -> None:
        """Bin the next ``n`` kept samples, :meth:`_bin`'s rule in numpy over the slice."""
        assert self._to_move is not None and self._pos is not None and self._neg is not None
        x = self._to_move[self._moved : self._moved + n]
        self._moved += len(x)
        if self._moved >= len(self._to_move):
            self._to_move = None
        a = np.abs(x)
        with np.errstate(divide="ignore"):  # log(0): the bin below lo, picked by the where
            above = np.minimum(self._bins - 1, 1 + np.floor(np.log(a / self._lo) * self._inv_log))
        i = np.where(a < self._lo, 0, above).astype(np.intp)
        np.add.at(self._pos, i[x >= 0], 1.0)
        np.add.at(self._neg, i[x < 0], 1.0)

    def _centers(self) -> Array:
        """A value for each bin: 0 below ``lo``, else the bin's geometric middle."""
        i = np.arange(self._bins, dtype=np.float64)
        c = self._lo * np.exp((i - 0.5) / self._inv_log)
        c[0] = 0.0
        return c

    def percentiles(self, qs: list[float], absolute: bool = False) -> list[float]:
        """The ``qs`` percentiles (0..100) of the samples (of their absolute values with ``absolute``);
        exact while unbinned (numpy's linear interpolation), else the bin's value (nearest rank)."""
        if self.count == 0:
            return [0.0] * len(qs)
        if self._samples is not None:
            a = np.asarray(self._samples, dtype=np.float64)
            return [float(v) for v in np.percentile(np.abs(a) if absolute else a, qs)]
        if self._to_move is not None:
            self._move(len(self._to_move))
        assert self._pos is not None and self._neg is not None
        c = self._centers()
        if absolute:
            values, counts = c, self._pos + self._neg
        else:
            values = np.concatenate([-c[::-1], c])
            counts = np.concatenate([self._neg[::-1], self._pos])
        cum = np.cumsum(counts)
        out = []
        for q in qs:
            rank = q / 100.0 * (self.count - 1)
            i = int(np.searchsorted(cum, rank, side="right"))
            out.append(float(values[min(i, len(values) - 1)]))
        return out
