"""Evaluation criteria of Section III: transparency (7) and compression c:1.

Compression is counted from bytes actually produced (payloads, or datagrams on the wire), never
from a codec's nominal figure: ``c = baseline bytes / sent bytes``, the baseline being every tick's
raw 16-bit sample.  The minimum instantaneous compression is the same ratio over a sliding window
(default 100 ms): what bounds the peak data rate.
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]


def transparency(v_hsi: Array, v_to: Array, f_hsi: Array, f_to: Array, dt: float) -> float:
    """I of eq. (7), summed over DoF: ``sum((v_hsi - v_to)**2 + (F_to - F_hsi)**2) dt``."""
    dv = np.asarray(v_hsi) - np.asarray(v_to)
    df = np.asarray(f_to) - np.asarray(f_hsi)
    return float((np.sum(dv * dv) + np.sum(df * df)) * dt)


def compression(baseline_bytes: float, sent_bytes: float) -> float:
    """Average c of c:1; ``inf`` when nothing was sent."""
    return float(baseline_bytes / sent_bytes) if sent_bytes > 0 else float("inf")


def min_instant_compression(baseline_per_tick: Array, sent_per_tick: Array, window: int) -> float:
    """Minimum over every full window of ``window`` ticks of baseline / sent bytes (Section III)."""
    b = np.asarray(baseline_per_tick, dtype=np.float64)
    s = np.asarray(sent_per_tick, dtype=np.float64)
    if window < 1:
        raise ValueError(f"window must be >= 1 tick, got {window}")
    if b.size < window:
        return compression(float(b.sum()), float(s.sum()))
    cb = np.concatenate(([0.0], np.cumsum(b)))
    cs = np.concatenate(([0.0], np.cumsum(s)))
    wb = cb[window:] - cb[:-window]
    ws = cs[window:] - cs[:-window]
    with np.errstate(divide="ignore"):
        ratios = np.where(ws > 0, wb / np.where(ws > 0, ws, 1.0), np.inf)
    return float(ratios.min())
