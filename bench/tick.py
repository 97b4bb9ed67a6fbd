"""Micro-benchmark: microseconds per 1 kHz tick of the control core, at 2 and 6 DoF.

Measures, per codec: the wave transform alone, encode+decode alone, a full operator tick plus
teleoperator tick including wire encoding and parsing, and the same through the two sans-I/O ports
(``teleop.port``: adds the wire counters, the link observer and the per-tick recorder, which is
what one loop iteration of each process costs apart from I/O, added together).  Medians over
repeats; writes JSON (default ``bench/results/tick.json``).

    python -m bench.tick [--out FILE] [--ticks N] [--repeats R]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from teleop import wire
from teleop.codecs import make_codec
from teleop.models import LtiEnvironment, StepHuman
from teleop.node import OperatorNode, PortOptions, TeleoperatorNode
from teleop.port import Port, make_node
from teleop.wave import WaveImpedance

CODECS = ("none", "ids:50", "eds:50", "cq:8")
DT = 1e-3


def _time_per_call(fn: Callable[[int], None], ticks: int, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter_ns()
        fn(ticks)
        out.append((time.perf_counter_ns() - t0) / ticks / 1e3)
    return out


def bench_transform(dof: int, ticks: int, repeats: int) -> list[float]:
    w = WaveImpedance.of(1.0, dof)
    v, f = np.linspace(-1, 1, dof), np.linspace(1, -1, dof)

    def run(n: int) -> None:
        for _ in range(n):
            g, h = w.to_waves(v, f)
            w.from_waves(g, h)

    return _time_per_call(run, ticks, repeats)


def bench_codec(spec: str, dof: int, ticks: int, repeats: int) -> list[float]:
    c = make_codec(spec, dof, 2.0)
    enc, dec = c.encoder(), c.decoder()
    x = np.sin(np.arange(ticks)[:, None] * 0.01 + np.arange(dof)[None, :])

    def run(n: int) -> None:
        for k in range(n):
            p = enc.encode(x[k])
            if p is not None:
                dec.push(p)
            dec.next()

    return _time_per_call(run, ticks, repeats)


def bench_nodes(spec: str, dof: int, ticks: int, repeats: int) -> list[float]:
    w = WaveImpedance.of(1.0, dof)
    c = make_codec(spec, dof, 2.0)
    op = OperatorNode(human=StepHuman(dof, DT, t_step=0.0), wave=w, tx=c, rx=c, session=1, dt=DT)
    to = TeleoperatorNode(environment=LtiEnvironment(dof, DT), wave=w, tx=c, rx=c, session=1, dt=DT)
    clock = [0]

    def run(n: int) -> None:
        for _ in range(n):
            now = clock[0] * DT
            clock[0] += 1
            p = op.tick(now)
            if p is not None:
                to.receive(wire.encode(p))
            q = to.tick(now)
            if q is not None:
                op.receive(wire.encode(q))

    return _time_per_call(run, ticks, repeats)


def bench_ports(spec: str, dof: int, ticks: int, repeats: int) -> list[float]:
    """Both ports per tick: node, wire encode and parse, counters, link observer, playout buffer
    (``auto`` with the real runner's one-tick floor), recorder."""
    opts = PortOptions(playout="auto")
    out = []
    for _ in range(repeats):
        ports = [
            Port(
                make_node(
                    role,
                    scenario="step",
                    dof=dof,
                    dt=DT,
                    b=1.0,
                    codec=spec,
                    full_scale=2.0,
                    session=1,
                    options=opts,
                ),
                ticks=ticks,
                playout_floor=1,
            )
            for role in ("operator", "teleoperator")
        ]
        op, to = ports
        t0 = time.perf_counter_ns()
        for k in range(ticks):
            now = k * DT
            for d in op.tick(k, now):
                to.receive(d, now, k)
            op.sent(k, now)
            for d in to.tick(k, now):
                op.receive(d, now, k)
            to.sent(k, now)
        out.append((time.perf_counter_ns() - t0) / ticks / 1e3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="bench/results/tick.json")
    ap.add_argument("--ticks", type=int, default=5000)
    ap.add_argument("--repeats", type=int, default=7)
    a = ap.parse_args()
    res: dict[str, Any] = {
        "what": "microseconds per tick, median over repeats",
        "ticks": a.ticks,
        "repeats": a.repeats,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "results": [],
    }
    for dof in (2, 6):
        med = statistics.median(bench_transform(dof, a.ticks, a.repeats))
        res["results"].append({"dof": dof, "part": "wave transform + inverse", "codec": None, "us": med})
        print(f"dof {dof}  wave transform+inverse          {med:7.2f} us")
        for spec in CODECS:
            mc = statistics.median(bench_codec(spec, dof, a.ticks, a.repeats))
            mn = statistics.median(bench_nodes(spec, dof, a.ticks, a.repeats))
            mp = statistics.median(bench_ports(spec, dof, a.ticks, a.repeats))
            res["results"].append({"dof": dof, "part": "encode + decode", "codec": spec, "us": mc})
            res["results"].append(
                {
                    "dof": dof,
                    "part": "operator tick + teleoperator tick + wire",
                    "codec": spec,
                    "us": mn,
                    "fraction_of_period": mn / 1000.0,
                }
            )
            res["results"].append(
                {
                    "dof": dof,
                    "part": "operator port tick + teleoperator port tick (counters, observer, recorder)",
                    "codec": spec,
                    "us": mp,
                    "fraction_of_period": mp / 1000.0,
                }
            )
            print(
                f"dof {dof}  {spec:<7} codec {mc:7.2f} us   both nodes + wire {mn:7.2f} us "
                f"({mn / 10:.1f}% of 1 ms)   both ports {mp:7.2f} us ({mp / 10:.1f}%)"
            )
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=2) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
