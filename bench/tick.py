"""Micro-benchmark: microseconds per 1 kHz tick of the control core, at 2 and 6 DoF; and the hot
port tick per side, per codec at 2, 6 and 64 DoF (issue 37).

Measures, per codec: the wave transform alone, encode+decode alone, a full operator tick plus
teleoperator tick including wire encoding and parsing, and the same through the two sans-I/O ports
(``teleop.session.port``: adds the wire counters, the link observer and the per-tick recorder, which is
what one loop iteration of each process costs apart from I/O, added together).  Medians over
repeats; writes JSON (default ``bench/results/tick.json``).

The hot port tick per side (``sides`` in the JSON) is each side's port as its process runs it
(receive what arrived, tick, sent; the ``protocol`` task), back to back: the caches stay warm, so it
is the floor of what a tick costs in the loop, where a tick after the sleep is colder.

    python -m bench.tick [--out FILE] [--ticks N] [--repeats R] [--sides-only]
"""

from __future__ import annotations

import argparse
import platform
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bench import write_result
from teleop.control.codecs import make_codec
from teleop.control.wave import WaveImpedance
from teleop.devices.models import LtiEnvironment, StepHuman
from teleop.session import wire
from teleop.session.endpoint import REAL_PLAYOUT_FLOOR_TICKS
from teleop.session.node import OperatorNode, PortOptions, TeleoperatorNode
from teleop.session.port import Port, make_node
from teleop.session.settings import Envelope, Passivity

CODECS = ("none", "ids:50", "eds:50", "cq:8")
TDPA_CODECS = ("none", "eds:50", "pdp:1")  # the port's hot path under TDPA (issue 23)
SIDE_CODECS = ("none", "eds:50", "pdp:1")  # the hot port tick per side (issue 37)
SIDE_DOFS = (2, 6, 64)
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


def _port_pair(
    spec: str, dof: int, ticks: int, scenario: str = "step", passivity: Passivity = Passivity.WAVE
) -> tuple[Port, Port]:
    """The two ports as the real runner makes them: playout ``auto`` at the runner's floor."""
    opts = PortOptions(playout="auto", passivity=passivity)
    op, to = (
        Port(
            make_node(
                role,
                scenario=scenario,
                dof=dof,
                dt=DT,
                b=1.0,
                codec=spec,
                full_scale=2.0,
                session=1,
                options=opts,
            ),
            ticks=ticks,
            playout_floor=REAL_PLAYOUT_FLOOR_TICKS,
        )
        for role in ("operator", "teleoperator")
    )
    to.node.confine(Envelope())  # the robot runs inside its envelope, as the endpoint starts it
    return op, to


def bench_ports(
    spec: str, dof: int, ticks: int, repeats: int, passivity: Passivity = Passivity.WAVE
) -> list[float]:
    """Both ports per tick: node, wire encode and parse, counters, link observer, playout buffer
    (``auto`` with the real runner's floor), recorder; ``passivity`` ``tdpa``: power
    variables, the energy reports and both dampers instead of the wave transform."""
    out = []
    for _ in range(repeats):
        op, to = _port_pair(spec, dof, ticks, passivity=passivity)
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


def port_side_ticks(
    op: Port, to: Port, ticks: int, wait: Callable[[], object] | None = None
) -> tuple[list[int], list[int]]:
    """Each side's port, per tick (ns), as its process runs it: receive what arrived, tick, sent;
    ``wait`` (if given) is called before each tick (the retired ``bench.phases`` paced it at 1 kHz)."""
    clock = time.perf_counter_ns
    t_op: list[int] = []
    t_to: list[int] = []
    backward: list[bytes] = []
    for k in range(ticks):
        now = k * DT
        if wait is not None:
            wait()
        t0 = clock()
        for d in backward:
            op.receive(d, now, k)
        forward = op.tick(k, now)
        op.sent(k, now)
        t1 = clock()
        for d in forward:
            to.receive(d, now, k)
        backward = to.tick(k, now)
        to.sent(k, now)
        t_op.append(t1 - t0)
        t_to.append(clock() - t1)
    return t_op, t_to


def bench_port_sides(
    spec: str, dof: int, ticks: int, repeats: int, scenario: str = "step"
) -> tuple[list[float], list[float]]:
    """Each side's port per tick (:func:`port_side_ticks`), the mean of each repeat, in µs; a clock
    read around each side's share (~0.1 us each)."""
    ops, tos = [], []
    for _ in range(repeats):
        t_op, t_to = port_side_ticks(*_port_pair(spec, dof, ticks, scenario), ticks)
        ops.append(sum(t_op) / ticks / 1e3)
        tos.append(sum(t_to) / ticks / 1e3)
    return ops, tos


def bench_sides(
    ticks: int, repeats: int, codecs: Sequence[str] = SIDE_CODECS, dofs: Sequence[int] = SIDE_DOFS
) -> list[dict[str, Any]]:
    """The hot port tick per side: per codec and DoF, each side's median over ``repeats`` (us)."""
    out = []
    for dof in dofs:
        for spec in codecs:
            op, to = bench_port_sides(spec, dof, ticks, repeats, scenario="protocol")
            out.append(
                {
                    "codec": spec,
                    "dof": dof,
                    "operator_us": statistics.median(op),
                    "teleoperator_us": statistics.median(to),
                    "operator_runs_us": op,
                    "teleoperator_runs_us": to,
                }
            )
            print(
                f"dof {dof:>2}  {spec:<7} hot port tick: operator {statistics.median(op):7.2f} us  "
                f"teleoperator {statistics.median(to):7.2f} us"
            )
    return out


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="bench/results/tick.json")
    ap.add_argument("--ticks", type=int, default=5000)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--sides-only", action="store_true", help="only the hot port tick per side")
    a = ap.parse_args(argv)
    res: dict[str, Any] = {
        "what": "microseconds per tick, median over repeats",
        "ticks": a.ticks,
        "repeats": a.repeats,
        "python": platform.python_version(),
        "machine": platform.machine(),
        "sides": bench_sides(a.ticks, a.repeats),
        "results": [],
    }
    for dof in () if a.sides_only else (2, 6):
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
        for spec in TDPA_CODECS:
            mt = statistics.median(bench_ports(spec, dof, a.ticks, a.repeats, passivity=Passivity.TDPA))
            res["results"].append(
                {
                    "dof": dof,
                    "part": "both port ticks, --passivity tdpa (power variables, energy reports, dampers)",
                    "codec": spec,
                    "us": mt,
                    "fraction_of_period": mt / 1000.0,
                }
            )
            print(f"dof {dof}  {spec:<7} tdpa: both ports {mt:7.2f} us ({mt / 10:.1f}%)")
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_result(out, res)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
