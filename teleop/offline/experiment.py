"""Section VI's experiment: every codec over the same N seeded humans, per phase mean and spread.

The paper performs its protocol (free space, foam, wall) ten times per method and reports
transparency per phase as mean and standard deviation, the no-LDR case as the reference (Fig. 15).
Here run ``i`` of every codec uses the seed ``seed0 + i``, so every codec meets the same N
performances of the human (``teleop.devices.models.ProtocolPlan``): the spread is the human's, not the
codec's luck.  ``std`` is the sample standard deviation (``ddof = 1``; 0 for a single run).

This module aggregates runs, whoever ran them: :func:`sim_run` in virtual time, or the CLI's real
two-process sessions (their ``report.json``).  Both give the same per-phase block
(``teleop.control.metrics.phase_summary``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from teleop.offline.sim import ENERGY_TOLERANCE, SimConfig, run_case

PHASE_ORDER = ("free", "foam", "wall", "all")
REFERENCE = "none"  # the no-LDR case


@dataclass
class RunResult:
    """One run of one codec (:func:`aggregate` holds the runs by codec): passivity and the per-phase
    block; ``error`` when it did not complete."""

    seed: int
    passive: bool
    phases: dict[str, dict[str, Any]] = field(default_factory=dict)
    error: str | None = None
    # Real runs: what the host did to the loops (a stalled tick conceals a late packet, raising I).
    host: dict[str, int] | None = None


def sim_run(base: SimConfig, codec: str, seed: int) -> RunResult:
    """Run ``codec`` in virtual time with the human of ``seed`` (the rest of ``base`` unchanged)."""
    r = run_case(replace(base, codec=codec, seed=seed))
    return RunResult(seed, bool(r.summary["passive"]), r.summary["phases"])


def real_passive(report: dict[str, Any]) -> bool:
    """A real session's passivity, as ``teleop sim`` judges it: every per-tick energy margin >= 0
    (eq. 5, per direction, from both logs), within float rounding; no margin at all is a failure."""
    margins = [report["energy"][d]["min_margin"] for d in ("forward", "backward")]
    return all(m is not None and m >= -ENERGY_TOLERANCE for m in margins)


#: A real run whose two logs overlap on fewer of its ticks than this is left out (``error``).
MIN_TICKS_COMPARED = 0.9


def incomplete(report: dict[str, Any]) -> str | None:
    """Why a real run cannot be compared, or None.  Host stalls skip a few ticks (a few %); a
    process that joined the session late (seen on a loaded host) leaves most of it unrecorded."""
    ticks = round(report["duration_s"] * 1000)  # every session runs at 1 kHz (teleop run)
    got = int(report["transparency"]["ticks_compared"])
    if got >= MIN_TICKS_COMPARED * ticks:
        return None
    per = {role: p["loop"]["ticks"] for role, p in report["processes"].items()}
    return f"only {got} of {ticks} ticks recorded by both processes (ticks run: {per})"


def host_figures(report: dict[str, Any]) -> dict[str, int]:
    """Both processes' loop overruns and late packets missed, and the watchdogs' violations."""
    procs = report["processes"].values()
    return {
        "overruns": sum(int(p["loop"]["overruns"]) for p in procs),
        "late_packets_missed": sum(int(p["grace"]["missed"]) for p in procs),
        "watchdog_violations": sum(int(v["violations"]) for v in report["passivity"].values()),
    }


def stats(values: Sequence[float]) -> dict[str, float | None]:
    """mean, sample std, min and max (``None`` for no values)."""
    a = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    if a.size == 0:
        return {"mean": None, "std": None, "min": None, "max": None}
    return {
        "mean": float(a.mean()),
        "std": float(a.std(ddof=1)) if a.size > 1 else 0.0,
        "min": float(a.min()),
        "max": float(a.max()),
    }


def _mean(values: Sequence[float | None]) -> float | None:
    a = [v for v in values if v is not None]
    return float(np.mean(a)) if a else None


def _ratios(done: Sequence[RunResult], ref: dict[int, dict[str, Any]], name: str) -> list[float]:
    """Per seed run by both: this codec's I over the reference's in phase ``name``."""
    out = []
    for r in done:
        i_ref = ref.get(r.seed, {}).get(name, {}).get("I")
        if i_ref and name in r.phases:
            out.append(r.phases[name]["I"] / i_ref)
    return out


def _phase_names(runs: Sequence[RunResult]) -> list[str]:
    names = {n for r in runs for n in r.phases}
    return [n for n in PHASE_ORDER if n in names] + sorted(names - set(PHASE_ORDER))


#: s: a phase a run spent less time in than this is left out of the experiment's figures (its I
#: over a few ticks of a phase's start is no measure of the phase); the whole run always counts.
MIN_PHASE_S = 1.0


def _reached(block: Mapping[str, Any], name: str) -> bool:
    if not block.get("ticks"):
        return False
    return name == "all" or float(block.get("end", 0.0)) - float(block.get("start", 0.0)) >= MIN_PHASE_S


def aggregate(
    runs: Mapping[str, Sequence[RunResult]], n_runs: int, real: bool, settings: dict[str, Any]
) -> dict[str, Any]:
    """The ``experiment.json`` document from the runs of each codec: per codec (in ``runs``' order),
    per phase, I's mean, spread, min and max over the completed runs, I per DoF, the mean packet and
    wire rates, and (with the reference among the runs) ``I_over_reference``: I over the
    reference's, seed by seed."""
    cases = []
    ref = {r.seed: r.phases for r in runs.get(REFERENCE, ()) if r.error is None}
    for spec, mine in runs.items():
        done = [r for r in mine if r.error is None]
        phases: dict[str, Any] = {}
        for name in _phase_names(done):
            # A phase the run never reached (a short --duration) has no ticks: no figure, not 0;
            # nor has one it barely entered (a 5 s run's foam: 3.5e-7 from a few ticks, drawn once).
            blocks = [r.phases[name] for r in done if _reached(r.phases.get(name, {}), name)]
            if not blocks:
                continue
            n_dof = max((len(b["I_dof"]) for b in blocks), default=0)
            phases[name] = {
                "I": stats([b["I"] for b in blocks]),
                "I_dof": [stats([b["I_dof"][j] for b in blocks]) for j in range(n_dof)],
                "start": stats([b["start"] for b in blocks]),
                "end": stats([b["end"] for b in blocks]),
                "packets_per_s": {
                    d: _mean([b["packets_per_s"][d] for b in blocks]) for d in ("forward", "backward")
                },
                "wire_bps": {d: _mean([b["wire_bps"][d] for b in blocks]) for d in ("forward", "backward")},
            }
            if spec != REFERENCE and ref:
                # Paired by seed: the same human with and without LDR, so the human's spread cancels.
                phases[name]["I_over_reference"] = stats(_ratios(done, ref, name))
        cases.append(
            {
                "codec": spec,
                "reference": spec == REFERENCE,
                # Shown passive only if every run completed: an incomplete run's margins cover part of it.
                "passive": bool(mine) and all(r.passive and r.error is None for r in mine),
                "completed": len(done),
                "phases": phases,
                "per_run": [
                    {
                        "seed": r.seed,
                        "passive": r.passive,
                        "error": r.error,
                        "I": {n: b["I"] for n, b in r.phases.items()},
                        **({"host": r.host} if r.host is not None else {}),
                    }
                    for r in mine
                ],
            }
        )
    return {"runs": n_runs, "real": real, **settings, "cases": cases}


def format_table(doc: dict[str, Any]) -> str:
    """Per codec and phase: I mean +- std over the runs, and whether every run stayed passive."""
    names = [n for n in PHASE_ORDER if any(n in c["phases"] for c in doc["cases"])]
    w = max([10, *(len(c["codec"]) for c in doc["cases"])])  # pdr's self-credit specs are longer
    head = f"{'codec':<{w}} " + " ".join(f"{'I ' + n + ' (mean +- std)':>24}" for n in names) + "  passive"
    lines = [head, "-" * len(head)]
    for c in doc["cases"]:
        cells = []
        for n in names:
            s = c["phases"].get(n, {}).get("I", {})
            cells.append(
                f"{s['mean']:>11.3e} +- {s['std']:<9.2e}" if s.get("mean") is not None else f"{'-':>24}"
            )
        ok = "yes" if all(r["passive"] for r in c["per_run"]) else "NO"
        runs = f"{c['completed']}/{doc['runs']} runs complete"
        lines.append(f"{c['codec']:<{w}} " + " ".join(cells) + f"  {ok} ({runs})")
    return "\n".join(lines)


def format_paired(doc: dict[str, Any]) -> str:
    """Per codec and phase: I over the reference's, seed by seed: mean (min..max)."""
    names = [n for n in PHASE_ORDER if any(n in c["phases"] for c in doc["cases"])]
    rows = [c for c in doc["cases"] if any("I_over_reference" in b for b in c["phases"].values())]
    if not rows:
        return ""
    head = f"{'I / ' + REFERENCE + ', same seed':<20} " + " ".join(f"{n:>30}" for n in names)
    lines = [head, "-" * len(head)]
    for c in rows:
        cells = []
        for n in names:
            s = c["phases"].get(n, {}).get("I_over_reference", {})
            text = f"{s['mean']:.3g} ({s['min']:.3g}..{s['max']:.3g})" if s.get("mean") is not None else "-"
            cells.append(f"{text:>30}")
        lines.append(f"{c['codec']:<20} " + " ".join(cells))
    return "\n".join(lines)
