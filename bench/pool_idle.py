"""Is there a reserve to pool?  At each budget send of one direction of a ``pdr`` run (``teleop sim
--scenario protocol``, 0 ms), the budget the same side holds for the other direction's wave, less
what that wave plays before its sender's next send refreshes it: the part a grant (``pdr``'s POOL)
could lend without costing the other direction a send, in ticks of the power of the wave that needs
it (issue 23 item 6; the codec guide's "Two-port accounting").

    python -m bench.pool_idle [--codec pdr:0.8:100:1:128:86] [--duration 15]

Virtual time only.  Measured on the default: forward median 0.5 ticks (90 %: 16.5), backward short
(negative) at 94 % of its budget sends: both budgets run out together.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from teleop.offline.sim import SimConfig, run_case
from teleop.session import node


def measure(codec: str, duration: float) -> dict[str, dict[str, float]]:
    """Per direction: budget sends and the quantiles of the other direction's idle budget."""
    logs: list[tuple[Any, list[tuple[float, float, float, str]]]] = []
    init, transmit = node._Port.__init__, node._Port._transmit

    def _init(self: node._Port, *a: Any, **k: Any) -> None:
        init(self, *a, **k)
        logs.append((self, []))

    def _transmit(self: node._Port, now: float, x: np.ndarray) -> Any:
        before = dict(self.encoder.sends)  # type: ignore[attr-defined]
        pkt = transmit(self, now, x)
        after = self.encoder.sends  # type: ignore[attr-defined]
        why = next((r for r in after if after[r] != before[r]), "")
        w = self.wave_in
        log = next(entry for port, entry in logs if port is self)
        log.append((self.guard.margin, self.half_dt * float(w.dot(w)), self.half_dt * float(x.dot(x)), why))
        return pkt

    node._Port.__init__ = _init  # type: ignore[method-assign]
    node._Port._transmit = _transmit  # type: ignore[method-assign]
    try:
        run_case(SimConfig(codec=codec, scenario="protocol", duration=duration))
    finally:
        node._Port.__init__ = init  # type: ignore[method-assign]
        node._Port._transmit = transmit  # type: ignore[method-assign]
    (_, op), (_, to) = logs[-2:]
    out = {}
    for name, mine, other in (("forward", op, to), ("backward", to, op)):
        margin, p_in, p_out = (np.array([r[i] for r in mine]) for i in range(3))
        why = np.array([r[3] for r in mine])
        other_sends = np.flatnonzero(np.array([r[3] for r in other]) != "")
        c_in = np.concatenate([[0.0], np.cumsum(p_in)])
        idle = []
        for t in np.flatnonzero(why == "budget"):
            j = np.searchsorted(other_sends, t + 1)
            t_o = other_sends[j] if j < len(other_sends) else len(margin)
            spare = margin[t] - (c_in[min(t_o + 1, len(margin))] - c_in[t + 1])
            idle.append(spare / max(p_out[t], 1e-15))
        a = np.array(idle)
        q = np.quantile(a, [0.5, 0.9]) if a.size else np.zeros(2)
        out[name] = {
            "budget_sends": float(a.size),
            "share_idle": float(np.mean(a > 0)) if a.size else 0.0,
            "median": float(q[0]),
            "p90": float(q[1]),
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--codec", default="pdr:0.8:100:1:128:86")
    ap.add_argument("--duration", type=float, default=15.0)
    a = ap.parse_args()
    for d, r in measure(a.codec, a.duration).items():
        print(
            f"{d}: {r['budget_sends']:.0f} budget sends; the other direction's idle budget > 0 at "
            f"{r['share_idle']:.0%}, median {r['median']:.1f} ticks of this power, 90 % {r['p90']:.1f}"
        )


if __name__ == "__main__":
    main()
