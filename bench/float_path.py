"""What numpy's per-call cost is of the operator's tick at 2 DoF: the premise of a plain-float path.

A design measurement for issue 22, not a part of the stack.  ``none`` at 2 and 6 DoF stays at about
2x the floor's CPU (``bench.cpu``), and no one piece of the tick is large: at 2 DoF the operator's
node tick is some 25 numpy calls on two-element arrays, each costing about as much as ten Python
operations after the loop's sleep.  This times, in one process, the operator node's tick (the real
code: decoder, energy guard, the protocol human's third-order admittance, the HSI's closed-form
solve, the wave out, its energy, the 16-bit codes, the packet) against the same arithmetic on plain
Python floats, one DoF at a time, run in lockstep on the same inputs (a sine of received waves):

- paced: one tick a millisecond on the real scheduler (``transport.realtime.Ticker``), the two
  alternating which runs first after the sleep (the first pays the cold caches); medians of the
  ticks each ran first;
- back to back, as ``bench.tick`` times;
- and whether the float rendering computes the same bits: velocity, force, wave out, energy and the
  payload's bytes, every tick.  It keeps the two dot products in numpy, on a two-element scratch
  array (``x.dot(x)`` is OpenBLAS's ``ddot``, which fuses a multiply-add: ``x0*x0 + x1*x1`` in
  floats differs in about one case in six), and ``math.sin`` where the human uses ``np.sin`` on
  one lateral DoF.

    python -m bench.float_path [--ticks N] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import struct
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.tick import DT, _port_pair
from teleop.devices.models import ProtocolHuman
from teleop.session import wire
from transport.realtime import Ticker


class FloatOperator:
    """The operator node's tick at 2 DoF in plain floats (coupling 1, the guard never acting)."""

    def __init__(self, node: Any) -> None:
        w, hum = node.wave, node.human
        assert isinstance(hum, ProtocolHuman) and w.dof == 2
        lti = hum.admittance
        self.human = hum
        self.b = [float(x) for x in w.b]
        self.s2b = [float(x) for x in w.sqrt2b]
        y = [float(x) for x in hum._y]
        self.ys = [y[i] * self.s2b[i] for i in range(2)]  # the node's _gains, element by element
        self.den = [1.0 + y[i] * self.b[i] for i in range(2)]
        self.bz, self.az, self.n = [float(x) for x in lti.b], [float(x) for x in lti.a], lti.order
        self.z = [[0.0, 0.0] for _ in range(self.n)]
        self.lateral_w = float(hum._lateral_w[0])
        self.lateral_amp = hum.plan.lateral_amp
        raw = node.encoder.raw
        self.inv, self.max_code, self.step = raw._inv_step, raw._max_code_f, raw._step
        self.half_dt = node.half_dt
        self.session, self.codec_id = node.session, node.tx_codec.codec_id
        self.energy_sent = self.played = 0.0
        self.seq = 0
        self._dot = np.zeros(2)  # the dot products stay numpy's (OpenBLAS fuses a multiply-add)
        self._pack = struct.Struct("<2h")

    def _dot2(self, a: float, b: float) -> float:
        d = self._dot
        d[0], d[1] = a, b
        return float(d.dot(d))

    def tick(self, now: float, payload: bytes) -> tuple[list[float], list[float], list[float], wire.Packet]:
        q = self._pack.unpack(payload)
        h = [q[0] * self.step, q[1] * self.step]
        self.played += self.half_dt * self._dot2(h[0], h[1])
        ref = (self.human.push_profile(now), self.lateral_amp * math.sin(self.lateral_w * now))
        z, bz, az, n = self.z, self.bz, self.az, self.n
        v, f, g = [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]
        for i in range(2):
            vi = ((ref[i] - z[0][i]) + self.ys[i] * h[i]) / self.den[i]
            fi = self.b[i] * vi - self.s2b[i] * h[i]
            yo = bz[0] * fi + z[0][i]
            for j in range(n - 1):
                z[j][i] = (bz[j + 1] * fi - az[j + 1] * yo) + z[j + 1][i]
            z[n - 1][i] = bz[n] * fi - az[n] * yo
            v[i], f[i], g[i] = vi, fi, self.s2b[i] * vi - h[i]
        self.energy_sent += self.half_dt * self._dot2(g[0], g[1])
        m = self.max_code
        codes = [int(min(max(x * self.inv, -m), m)) for x in g]
        pkt = wire.Packet(
            self.session, wire.FORWARD, self.seq, int(now / DT + 0.5), round(now * 1e6), self.codec_id,
            self._pack.pack(*codes), self.energy_sent,
        )  # fmt: skip
        self.seq += 1
        return v, f, g, pkt


def run(ticks: int) -> dict[str, Any]:
    op, _ = _port_pair("none", 2, ticks + 10, "protocol")
    node = op.node
    node.guard.sent(1e9, 0.0)  # a budget the guard never reaches: it plays what arrives, as the floats
    fl = FloatOperator(node)
    pack = struct.Struct("<2h").pack
    payloads = [
        pack(round(9000 * math.sin(0.01 * k)), round(-7000 * math.cos(0.013 * k))) for k in range(ticks)
    ]
    ticker = Ticker(period_ns=1_000_000, spin_ns=100_000, min_spin_ns=100_000)
    ticker.start(time.monotonic_ns() + 1_000_000)
    clock = time.perf_counter_ns
    cold: dict[str, list[int]] = {"numpy": [], "floats": []}
    same = {"v": 0, "f": 0, "wave_out": 0, "energy": 0, "payload": 0}
    for k in range(ticks):
        now = k * DT
        node.decoder.push(payloads[k])
        ticker.wait()
        first = "numpy" if k % 2 == 0 else "floats"
        for which in (first, "floats" if first == "numpy" else "numpy"):
            t0 = clock()
            if which == "numpy":
                pkt = node.tick(now)
            else:
                v, f, g, fpkt = fl.tick(now, payloads[k])
            if which == first:
                cold[which].append(clock() - t0)
        assert pkt is not None
        same["v"] += v == node.v.tolist()
        same["f"] += f == node.f.tolist()
        same["wave_out"] += g == node.wave_out.tolist()
        same["energy"] += fl.energy_sent == node.energy_sent and fl.played == node.guard.played
        same["payload"] += fpkt.payload == pkt.payload
    hot: dict[str, float] = {}
    op2, _ = _port_pair("none", 2, ticks + 10, "protocol")
    node2 = op2.node
    node2.guard.sent(1e9, 0.0)
    fl2 = FloatOperator(node2)
    t0 = clock()
    for k in range(ticks):
        node2.decoder.push(payloads[k])
        node2.tick(k * DT)
    t1 = clock()
    for k in range(ticks):
        fl2.tick(k * DT, payloads[k])
    hot = {"numpy": (t1 - t0) / ticks / 1e3, "floats": (clock() - t1) / ticks / 1e3}
    return {
        "paced_us": {k: statistics.median(v[50:]) / 1e3 for k, v in cold.items()},
        "hot_us": hot,
        "ticks": ticks,
        "bit_identical_ticks": same,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.float_path", description=__doc__.split("\n\n")[0])
    ap.add_argument("--ticks", type=int, default=6000, help="ticks (default 6000: 6 s paced)")
    ap.add_argument("--out", default="bench/results/float_path.json")
    a = ap.parse_args(argv)
    if not 200 <= a.ticks <= 600_000:
        ap.error("--ticks must be an integer from 200 to 600000 (at most 10 minutes paced)")
    res = run(a.ticks)
    doc = {
        "what": "the operator node's tick at 2 DoF (numpy) against the same arithmetic in plain floats",
        "python": platform.python_version(),
        "numpy": np.__version__,
        **res,
    }
    Path(a.out).parent.mkdir(parents=True, exist_ok=True)
    Path(a.out).write_text(json.dumps(doc, indent=2) + "\n")
    p, h, s = res["paced_us"], res["hot_us"], res["bit_identical_ticks"]
    print(f"paced: numpy {p['numpy']:.1f} us, floats {p['floats']:.1f} us", end="; ")
    print(f"back to back: numpy {h['numpy']:.1f} us, floats {h['floats']:.1f} us")
    print(f"bit-identical ticks of {res['ticks']}: " + ", ".join(f"{k} {v}" for k, v in s.items()))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
