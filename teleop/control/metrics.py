"""Evaluation criteria of Section III: transparency (7) and compression c:1.

Compression is counted from bytes actually produced (payloads, or datagrams on the wire), never
from a codec's nominal figure: ``c = baseline bytes / sent bytes``, the baseline being every tick's
raw 16-bit sample.  The minimum instantaneous compression is the same ratio over a sliding window
(default 100 ms): what bounds the peak data rate.

Per phase (Section VI, Fig. 15): the same I and rates over each phase of a scenario, the phases
given as ``(name, start s, end s)`` by the scenario (``teleop.devices.scenarios.Scenario.phases``); tick
``n`` (time ``n dt``) belongs to the phase with ``start <= n dt < end``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

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


Phases = Sequence[tuple[str, float, float]]


def first_tick(t: float, dt: float) -> int:
    """The first tick at or after ``t`` s (a phase's bound in ticks; 1e-6 tick of float slack)."""
    return max(0, math.ceil(t / dt - 1e-6))


def phase_ticks(n_ticks: int, dt: float, phases: Phases) -> dict[str, slice]:
    """Each phase's ticks, plus ``all``: every tick of the run."""
    out = {}
    for name, t0, t1 in phases:
        a, b = (min(n_ticks, first_tick(t, dt)) for t in (t0, t1))
        out[name] = slice(a, max(a, b))
    out["all"] = slice(0, n_ticks)
    return out


def phase_transparency(
    v_hsi: Array,
    v_to: Array,
    f_hsi: Array,
    f_to: Array,
    dt: float,
    phases: Phases,
    valid: npt.ArrayLike | None = None,
) -> dict[str, dict[str, Any]]:
    """I of eq. (7) per phase and per DoF: ``{phase: {"I", "I_dof": [...], "start", "end", "ticks"}}``.

    Signals are (ticks, dof); ``valid`` (bool per tick) leaves out ticks one side did not record (a
    real run's rows of NaN).  ``all`` is the whole run, so its ``I`` is :func:`transparency`'s."""
    dv = np.asarray(v_hsi, dtype=np.float64) - np.asarray(v_to, dtype=np.float64)
    df = np.asarray(f_to, dtype=np.float64) - np.asarray(f_hsi, dtype=np.float64)
    dv, df = dv.reshape(dv.shape[0], -1), df.reshape(df.shape[0], -1)
    per_tick = dv * dv + df * df
    if valid is not None:
        per_tick = np.where(np.asarray(valid, dtype=bool)[:, None], per_tick, 0.0)
    n = per_tick.shape[0]
    out: dict[str, dict[str, Any]] = {}
    for name, sl in phase_ticks(n, dt, phases).items():
        i_dof = per_tick[sl].sum(axis=0) * dt
        counted = sl.stop - sl.start if valid is None else int(np.count_nonzero(np.asarray(valid)[sl]))
        out[name] = {
            "I": float(i_dof.sum()),
            "I_dof": [float(x) for x in i_dof],
            "start": round(sl.start * dt, 9),
            "end": round(sl.stop * dt, 9),
            "ticks": int(counted),
        }
    return out


def phase_rates(sent_bytes: Array, dt: float, phases: Phases) -> dict[str, dict[str, float | None]]:
    """Per phase: packets per second (ticks that sent bytes) and bits per second of ``sent_bytes``.

    ``sent_bytes`` is one direction's bytes sent per tick (payload, packet or wire bytes); a phase
    of no ticks has ``None``."""
    b = np.nan_to_num(np.asarray(sent_bytes, dtype=np.float64))
    out: dict[str, dict[str, float | None]] = {}
    for name, sl in phase_ticks(b.size, dt, phases).items():
        span = (sl.stop - sl.start) * dt
        seg = b[sl]
        out[name] = {
            "packets_per_s": float(np.count_nonzero(seg)) / span if span > 0 else None,
            "bps": 8.0 * float(seg.sum()) / span if span > 0 else None,
        }
    return out


def phase_summary(
    v_hsi: Array,
    v_to: Array,
    f_hsi: Array,
    f_to: Array,
    dt: float,
    phases: Phases,
    wire_bytes: dict[str, Array],
    valid: npt.ArrayLike | None = None,
) -> dict[str, dict[str, Any]]:
    """Per phase: :func:`phase_transparency`'s figures plus, per direction of ``wire_bytes`` (bytes
    on the wire per tick), ``packets_per_s`` and ``wire_bps`` (:func:`phase_rates`)."""
    out = phase_transparency(v_hsi, v_to, f_hsi, f_to, dt, phases, valid)
    rates = {d: phase_rates(b, dt, phases) for d, b in wire_bytes.items()}
    for name, block in out.items():
        block["packets_per_s"] = {d: r[name]["packets_per_s"] for d, r in rates.items()}
        block["wire_bps"] = {d: r[name]["bps"] for d, r in rates.items()}
    return out


def _shifted(a: Array, b: Array, shift: int) -> tuple[Array, Array]:
    """``a`` ``shift`` ticks earlier against ``b``: ``(a[:n - shift], b[shift:])``."""
    shift = max(0, min(int(shift), a.shape[0]))
    return a[: a.shape[0] - shift], b[shift:]


def delay_compensated(
    v_hsi: Array, v_to: Array, f_hsi: Array, f_to: Array, dt: float, shift_fwd: int, shift_bwd: int
) -> float:
    """Eq. (7) with each side's signal against the other's as it left ``shift`` ticks earlier::

        I_dc = sum (v_hsi(t - T_f) - v_to(t))^2 + (F_to(t - T_b) - F_hsi(t))^2 dt

    ``T_f``, ``T_b`` the one-way delays in ticks: what remains is distortion (codec, reconstruction,
    passivity controller, reflections), not the delay itself, which (7) counts as error."""
    a, b = _shifted(np.asarray(v_hsi, dtype=np.float64), np.asarray(v_to, dtype=np.float64), shift_fwd)
    c, d = _shifted(np.asarray(f_to, dtype=np.float64), np.asarray(f_hsi, dtype=np.float64), shift_bwd)
    dv, df = a - b, c - d
    return float((np.sum(dv * dv) + np.sum(df * df)) * dt)


def one_way_ticks(playout: Mapping[str, Any], link: Mapping[str, Any], dt: float) -> int:
    """The one-way delay a direction's samples saw, in ticks: the playout buffer's median release
    delay when it holds them, else the link's measured mean delay (None: nothing arrived, 0)."""
    ms = playout["delay_ms"]["p50"] if playout["delay_ms"]["p50"] is not None else link["delay_ms"]["mean"]
    return 0 if ms is None else round(ms / 1e3 / dt)


class DelayDistortionFold:
    """:func:`delay_compensated` and :func:`position_drift` folded a block of ticks at a time (the
    report streams hour-long logs).  Rows with a NaN (a tick one process did not run) count as no
    motion in the positions and are left out of ``I_dc``'s sum; without NaN the figures equal the
    whole-array functions' (a test holds them so)."""

    def __init__(self, dof: int, dt: float, shift_fwd: int, shift_bwd: int) -> None:
        self.dt, self.sf, self.sb = dt, max(0, int(shift_fwd)), max(0, int(shift_bwd))
        self._v_hsi = np.zeros((0, dof))  # the last ``sf`` rows: what the next block's first rows pair with
        self._f_to = np.zeros((0, dof))
        self._x_hsi_tail = np.zeros((0, dof))
        self._x_hsi, self._x_to = np.zeros(dof), np.zeros(dof)
        self._sum = 0.0
        self.drift_max = self.drift_final = 0.0
        self._pairs = 0

    @staticmethod
    def _pair(tail: Array, block: Array, other: Array, shift: int) -> tuple[Array, Array, Array]:
        """(``block`` shifted by ``shift`` rows against ``other``, those rows of ``other``, new tail)."""
        full = np.concatenate([tail, block])
        m = max(0, full.shape[0] - shift)  # rows of ``full`` that have a partner ``shift`` rows on
        new_tail = full[max(0, full.shape[0] - shift) :] if shift else full[:0]
        return full[:m], other[other.shape[0] - m :], new_tail

    def add(self, v_hsi: Array, v_to: Array, f_hsi: Array, f_to: Array) -> None:
        a, b, self._v_hsi = self._pair(self._v_hsi, v_hsi, v_to, self.sf)
        c, d, self._f_to = self._pair(self._f_to, f_to, f_hsi, self.sb)
        dv, df = a - b, c - d
        self._sum += float(np.nansum(dv * dv) + np.nansum(df * df))
        # Positions from rest, integrated across blocks (a NaN row: no motion).
        x_hsi = self._x_hsi + np.cumsum(np.nan_to_num(v_hsi), axis=0) * self.dt
        x_to = self._x_to + np.cumsum(np.nan_to_num(v_to), axis=0) * self.dt
        if x_hsi.shape[0]:
            self._x_hsi, self._x_to = x_hsi[-1].copy(), x_to[-1].copy()
        xa, xb, self._x_hsi_tail = self._pair(self._x_hsi_tail, x_hsi, x_to, self.sf)
        if xa.shape[0]:
            e = np.sqrt(np.sum((xa - xb) ** 2, axis=1))
            self.drift_max = max(self.drift_max, float(e.max()))
            self.drift_final = float(e[-1])
            self._pairs += xa.shape[0]

    @property
    def i_dc(self) -> float:
        return self._sum * self.dt

    def drift(self) -> dict[str, float]:
        return {"max": self.drift_max, "final": self.drift_final}


def position_drift(v_hsi: Array, v_to: Array, dt: float, shift_fwd: int) -> dict[str, float]:
    """The position mismatch ``|x_hsi(t - T_f) - x_to(t)|`` (norm over DoF, m), positions integrated
    from the velocities from rest at 0: its maximum and its value at the end.  Wave variables and TDPA
    both let it grow (a series damper's velocity never comes back); the delay itself is taken out."""
    x_hsi = np.cumsum(np.asarray(v_hsi, dtype=np.float64), axis=0) * dt
    x_to = np.cumsum(np.asarray(v_to, dtype=np.float64), axis=0) * dt
    a, b = _shifted(x_hsi.reshape(x_hsi.shape[0], -1), x_to.reshape(x_to.shape[0], -1), shift_fwd)
    if a.shape[0] == 0:
        return {"max": 0.0, "final": 0.0}
    e = np.sqrt(np.sum((a - b) ** 2, axis=1))
    return {"max": float(e.max()), "final": float(e[-1])}
