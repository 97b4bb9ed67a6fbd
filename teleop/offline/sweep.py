"""``teleop sweep``: the packet-rate / transparency trade-off over a grid of codecs, in simulation.

Each case is one deterministic ``teleop sim`` run (``teleop.offline.sim.run_case``) with the same scenario,
impairment and passivity settings; cases are independent, so they run in parallel processes.  The
Pareto front is over transparency I (eq. 7, lower is better) and the total wire rate of both
directions (lower is better): a case is on it when no other case is at least as good in both and
better in one.  The paper's Section III frames LDR design exactly so, as a multi-objective problem.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from typing import Any

from teleop.offline.sim import SECTION_V_CODECS, SimConfig, run_case

#: Every family, the paper's set first: rates from 1000/s down to 10/s per direction, and every point
#: of the measured front (a test checks it against bench/results).
DEFAULT_GRID: tuple[str, ...] = (
    *SECTION_V_CODECS,
    "cq:6",
    "ids:5",
    "ids:10",
    "ids:20",
    "eds:5",
    "eds:10",
    "eds:20",
    "dct:10:2",
    "dct:20:2",
    "dct:50:5",
    "dct:50:2",
    "pd:0.5",
    "pd:1",
    "pd:2",
    "pd:5",
    "pdp:0.25",
    "pdp:0.5",
    "pdp:1",
    "pdp:2",
    "pdp:5",
    "pdr:0.8",
    "pdr:2",
    # The reflective deadband's measured front (bench/results/frontier0*.json): per-direction
    # reserve, and self-credit; c0.5 has the lowest busier direction at ids:2's I (preset low-rate).
    "pdr:0.8:100:1:128:86",
    "pdr:0.6:100:0.6:30:30:c1",
    "pdr:0.8:100:0.8:30:30:c1",
    "pdr:0.8:100:0.8:30:30:c0.5",
)


def case_row(summary: dict[str, Any], duration: float) -> dict[str, Any]:
    """One ``sweep.json`` case from a ``teleop sim`` case summary."""
    dirs = ("forward", "backward")
    return {
        "codec": summary["codec"],
        "class": summary["class"],
        "I": summary["I"],
        "packets_per_s": {d: summary["wire"][d]["packets"] / duration for d in dirs},
        "wire_bps": {d: 8.0 * summary["wire"][d]["wire_bytes"] / duration for d in dirs},
        "compression": summary["compression"],
        "min_instant_compression": summary["min_instant_compression"],
        "passive": summary["passive"],
        "min_energy_margin": summary["min_energy_margin"],
        "rate_cap": summary.get("rate_cap"),
        # Delay against distortion (issue 23): eq. (7) with the one-way delays taken out, drift, PC energy.
        "I_dc": summary["I_dc"],
        "drift_m": summary["drift_m"],
        "energy_dissipated": summary["energy_dissipated"]["total"],
    }


def pareto_flags(points: Sequence[tuple[float, float]]) -> list[bool]:
    """For each (cost_a, cost_b), whether no other point is <= in both and < in one."""
    out = []
    for i, (a, b) in enumerate(points):
        dominated = any(
            (a2 <= a and b2 <= b and (a2 < a or b2 < b)) for j, (a2, b2) in enumerate(points) if j != i
        )
        out.append(not dominated)
    return out


def _run_one(cfg: SimConfig) -> dict[str, Any]:
    assert cfg.duration is not None
    return case_row(run_case(cfg).summary, cfg.duration)


def run_sweep(
    codecs: Iterable[str],
    base: SimConfig,
    workers: int = 1,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict[str, Any]:
    """Run every codec with ``base``'s settings; returns the ``sweep.json`` document."""
    base = base.resolved()
    assert base.duration is not None
    specs = list(dict.fromkeys(codecs))  # in order, each once
    cfgs = [replace(base, codec=s) for s in specs]
    rows: list[dict[str, Any]] = []

    def results() -> Iterator[dict[str, Any]]:
        if workers <= 1 or len(cfgs) <= 1:
            yield from map(_run_one, cfgs)
            return
        with ProcessPoolExecutor(max_workers=workers) as ex:
            yield from ex.map(_run_one, cfgs)

    for i, row in enumerate(results()):
        rows.append(row)
        if progress is not None:
            progress(i + 1, len(cfgs), row["codec"])
    flags = pareto_flags([(r["I"], sum(r["wire_bps"].values())) for r in rows])
    for r, f in zip(rows, flags, strict=True):
        r["pareto"] = f
    return {
        "scenario": base.scenario,
        "duration": base.duration,
        "dof": base.dof,
        "netem": {"forward": base.netem_forward, "backward": base.netem_backward},
        "seed": base.seed,
        "rate_cap": base.rate_cap,
        "passivity": base.passivity,
        "cases": rows,
    }


def format_table(doc: dict[str, Any]) -> str:
    w = max([10, *(len(c["codec"]) for c in doc["cases"])])  # pdr's self-credit specs are long
    head = (
        f"{'codec':<{w}} {'I':>11} {'pkt/s fwd':>9} {'pkt/s bwd':>9} {'kbit/s':>8} {'c:1':>7} "
        f"{'min c:1':>8} {'passive':>7} {'pareto':>6}"
    )
    lines = [head, "-" * len(head)]
    for c in sorted(doc["cases"], key=lambda c: sum(c["wire_bps"].values())):
        pps, bps = c["packets_per_s"], sum(c["wire_bps"].values())
        lines.append(
            f"{c['codec']:<{w}} {c['I']:>11.4e} {pps['forward']:>9.1f} {pps['backward']:>9.1f} "
            f"{bps / 1e3:>8.1f} {c['compression']:>7.2f} {c['min_instant_compression']:>8.2f} "
            f"{'yes' if c['passive'] else 'NO':>7} {'*' if c['pareto'] else '':>6}"
        )
    return "\n".join(lines)
