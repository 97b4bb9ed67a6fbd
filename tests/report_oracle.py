"""The report's whole-session figures by their definitions, over whole arrays (``read_log``): the
oracle the streamed fold (``teleop.offline.report``) is checked against.  This is how the report computed
them before it streamed; kept here, not in the package, since only tests should hold a session."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from shell.mcaplog import read_log
from teleop.control import metrics

Array = npt.NDArray[Any]


def true_margin(sender: dict[str, Array], receiver: dict[str, Array]) -> Array:
    """Per receiver tick: energy the sender had put into the packets accepted by then (looked up
    by seq in the sender's whole log), minus energy played since the receiver's last epoch (eq. 5);
    NaN outside the receiver's last epoch or where nothing compares."""
    played = receiver["energy_played_epoch"]
    sent_ticks = np.flatnonzero(sender["tx_seq"] >= 0)
    seqs, energy = sender["tx_seq"][sent_ticks], sender["energy_sent"][sent_ticks]
    rx = receiver["rx_seq"]
    idx = np.searchsorted(seqs, rx, side="left")
    found = (rx >= 0) & (idx < seqs.size) & (seqs[np.minimum(idx, max(seqs.size - 1, 0))] == rx)
    sent = np.where(found, energy[np.minimum(idx, max(energy.size - 1, 0))] if energy.size else 0.0, 0.0)
    last_epoch = receiver["peer_epoch"] == receiver["peer_epoch"].max()
    ok = last_epoch & ~np.isnan(played) & ((rx < 0) | found)
    return np.where(ok, sent - played, np.nan)


def _nanmin(x: Any) -> float | None:
    return float(np.nanmin(x)) if np.isfinite(x).any() else None


def figures(op_log: Path, to_log: Path, phases: list[tuple[str, float, float]], dt: float) -> dict[str, Any]:
    """Per-phase I and wire rates, each direction's minimum margin and the two-port's (eq. 4)."""
    _, a_op = read_log(op_log)
    _, a_to = read_log(to_log)
    n = min(len(a_op["v"]), len(a_to["v"]))
    a_op = {k: v if k == "lateness_ns" else v[:n] for k, v in a_op.items()}
    a_to = {k: v if k == "lateness_ns" else v[:n] for k, v in a_to.items()}
    valid = ~(np.isnan(a_op["v"]).any(axis=1) | np.isnan(a_to["v"]).any(axis=1))
    m_fwd, m_bwd = true_margin(a_op, a_to), true_margin(a_to, a_op)
    both = m_fwd + m_bwd
    with np.errstate(invalid="ignore"):
        return {
            "ticks": n,
            "I": metrics.transparency(
                a_op["v"][valid], a_to["v"][valid], a_op["f"][valid], a_to["f"][valid], dt
            ),
            "phases": metrics.phase_summary(
                a_op["v"],
                a_to["v"],
                a_op["f"],
                a_to["f"],
                dt,
                phases,
                {"forward": a_op["tx_wire"], "backward": a_to["tx_wire"]},
                valid,
            ),
            "min_margin": {
                "forward": float(np.nanmin(m_fwd)) if np.isfinite(m_fwd).any() else None,
                "backward": float(np.nanmin(m_bwd)) if np.isfinite(m_bwd).any() else None,
            },
            "two_port": float(np.nanmin(both)) if np.isfinite(both).any() else None,
            # Eq. (4) on the session clock, tick against tick (what teleop.offline.sim measures).
            "two_port_clock": _nanmin(
                (a_op["energy_sent"] - a_to["energy_played_epoch"])
                + (a_to["energy_sent"] - a_op["energy_played_epoch"])
            ),
            # The loop-timing histogram's ticks: those run, of the ticks both logs cover.
            "lateness_ticks": {
                "operator": int(np.count_nonzero(~np.isnan(a_op["play_time_s"]))),
                "teleoperator": int(np.count_nonzero(~np.isnan(a_to["play_time_s"]))),
            },
        }


def assert_fold_matches(fold: Any, want: dict[str, Any]) -> None:
    """The streamed fold's figures equal the oracle's (to rounding: sums taken a block at a time)."""
    import pytest

    assert fold.n == want["ticks"]
    got = fold.phase_summary()
    assert set(got) == set(want["phases"])
    for name, w in want["phases"].items():
        g = got[name]
        for key in ("start", "end", "ticks"):
            assert g[key] == w[key], (name, key)
        assert g["I"] == pytest.approx(w["I"], rel=1e-9, abs=1e-15), name
        assert g["I_dof"] == pytest.approx(w["I_dof"], rel=1e-9, abs=1e-15), name
        for d in ("forward", "backward"):
            for key in ("packets_per_s", "wire_bps"):
                if w[key][d] is None:
                    assert g[key][d] is None, (name, d, key)
                else:
                    assert g[key][d] == pytest.approx(w[key][d], rel=1e-12), (name, d, key)
    assert got["all"]["I"] == pytest.approx(want["I"], rel=1e-9, abs=1e-15)
    for d, m in (("forward", fold.fwd), ("backward", fold.bwd)):
        w = want["min_margin"][d]
        assert (w is None and np.isnan(m.minimum())) or m.minimum() == pytest.approx(
            w, rel=1e-12, abs=1e-15
        ), d
    two = fold.min_two_port()
    assert (two is None) == (want["two_port"] is None)
    if two is not None:
        assert two == pytest.approx(want["two_port"], rel=1e-12, abs=1e-15)
    clock = fold.min_two_port_clock()
    assert (clock is None) == (want["two_port_clock"] is None)
    if clock is not None:
        assert clock == pytest.approx(want["two_port_clock"], rel=1e-12, abs=1e-15)
    for role, late in fold.lateness.items():
        assert late.ticks == want["lateness_ticks"][role], role
