"""``teleop sim``: a deterministic virtual-time run of the two nodes joined by a channel.

The runner owns the clock.  Tick ``n`` is ``now = n dt``; within it the operator ticks first, its
packet enters the forward link, then the teleoperator ticks with whatever is due, and its packet
enters the backward link.  With delay ``T`` per direction a forward packet is played at tick
``n + T/dt`` and a backward one at tick ``n + T/dt + 1``: closing the loop through two nodes that
each tick once costs one tick, the floor of any causal implementation (two real processes cannot
do better).  The paper's ``I_ref = 0`` assumes the loop solved algebraically across the channel;
here ``none`` at ``T = 0`` shows the small residual of that one-tick floor and of 16-bit
quantisation, and the report says so.

Packets cross the links as wire bytes (``teleop.wire``), so the sim exercises the same parsing as
the real processes, and payload and packet sizes are counted, not estimated.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from . import metrics, scenarios, wire
from .codecs import make_codec
from .node import OperatorNode, TeleoperatorNode
from .wave import WaveImpedance

Array = npt.NDArray[np.float64]

#: The paper's Section V set.
SECTION_V_CODECS = ("none", "ids:2", "ids:50", "eds:2", "eds:50", "cq:8")
ENERGY_TOLERANCE = 1e-9  # J: float rounding in cumulative sums, far below any real violation


class ConstantDelayLink:
    """A lossless link with constant delay: ``send(now, data)``, ``due(now) -> [data]``.

    Same interface as the netem shim's link model, so the runner does not care which it has.
    """

    def __init__(self, delay: float) -> None:
        if delay < 0:
            raise ValueError(f"delay must be >= 0 s, got {delay}")
        self.delay = delay
        self._heap: list[tuple[float, int, bytes]] = []
        self._n = 0

    def send(self, now: float, data: bytes) -> None:
        heapq.heappush(self._heap, (now + self.delay, self._n, data))
        self._n += 1

    def due(self, now: float) -> list[bytes]:
        out = []
        limit = now + 1e-9
        while self._heap and self._heap[0][0] <= limit:
            out.append(heapq.heappop(self._heap)[2])
        return out


@dataclass
class SimConfig:
    """One run.  ``None`` means the scenario's default (``teleop.scenarios``)."""

    codec: str = "none"
    delay_ms: float = 0.0
    duration: float | None = None
    dt: float = 0.001
    dof: int | None = None
    b: float | None = None
    full_scale: float | None = None
    scenario: str = "step"
    window_ms: float = 100.0
    session: int = 1

    def resolved(self) -> SimConfig:
        """A copy with every default filled in and every value checked (ValueError says what is wrong)."""
        sc = scenarios.get(self.scenario)
        c = replace(
            self,
            duration=sc.duration if self.duration is None else self.duration,
            dof=sc.dof if self.dof is None else self.dof,
            b=sc.b if self.b is None else self.b,
            full_scale=sc.full_scale if self.full_scale is None else self.full_scale,
        )
        if not c.dt > 0:
            raise ValueError(f"dt must be > 0 s, got {c.dt}")
        if not c.duration or not c.duration > 0:
            raise ValueError(f"duration must be > 0 s, got {c.duration}")
        if not c.delay_ms >= 0:
            raise ValueError(f"delay must be >= 0 ms, got {c.delay_ms}")
        if not c.dof or c.dof < 1:
            raise ValueError(f"dof must be >= 1, got {c.dof}")
        if not c.window_ms >= c.dt * 1e3:
            raise ValueError(f"window must be at least one tick ({c.dt * 1e3} ms), got {c.window_ms}")
        return c


@dataclass
class Trace:
    """Per-tick signals, shape (ticks, dof), and per-tick byte counts per direction."""

    t: Array
    v_hsi: Array
    f_hsi: Array
    v_to: Array
    f_to: Array
    margin_fwd: Array  # J, energy sent minus played, forward (eq. 5, first integral)
    margin_bwd: Array
    payload_bytes: dict[str, Array] = field(default_factory=dict)
    packet_bytes: dict[str, Array] = field(default_factory=dict)


@dataclass
class CaseResult:
    codec: str
    summary: dict[str, Any]
    trace: Trace


def run_case(cfg: SimConfig) -> CaseResult:
    """One deterministic run; same config, same bits out."""
    cfg = cfg.resolved()
    assert (
        cfg.dof is not None and cfg.duration is not None and cfg.b is not None and cfg.full_scale is not None
    )
    dof, dt = cfg.dof, cfg.dt
    n_ticks = round(cfg.duration / dt)
    wave = WaveImpedance.of(cfg.b, dof)
    codec = make_codec(cfg.codec, dof, cfg.full_scale)
    human, env = scenarios.get(cfg.scenario).make(dof, dt)
    op = OperatorNode(human=human, wave=wave, tx=codec, rx=codec, session=cfg.session, dt=dt)
    to = TeleoperatorNode(environment=env, wave=wave, tx=codec, rx=codec, session=cfg.session, dt=dt)
    delay = cfg.delay_ms / 1e3
    fwd, bwd = ConstantDelayLink(delay), ConstantDelayLink(delay)

    shape = (n_ticks, dof)
    tr = Trace(
        t=np.arange(n_ticks, dtype=np.float64) * dt,
        v_hsi=np.empty(shape),
        f_hsi=np.empty(shape),
        v_to=np.empty(shape),
        f_to=np.empty(shape),
        margin_fwd=np.empty(n_ticks),
        margin_bwd=np.empty(n_ticks),
    )
    pay = {d: np.zeros(n_ticks) for d in wire.DIRECTIONS}
    pkt_bytes = {d: np.zeros(n_ticks) for d in wire.DIRECTIONS}
    for n in range(n_ticks):
        now = n * dt
        for data in bwd.due(now):
            op.receive(data)
        p = op.tick(now)
        if p is not None:
            data = wire.encode(p)
            pay["forward"][n] = len(p.payload)
            pkt_bytes["forward"][n] = len(data)
            fwd.send(now, data)
        for data in fwd.due(now):
            to.receive(data)
        p = to.tick(now)
        if p is not None:
            data = wire.encode(p)
            pay["backward"][n] = len(p.payload)
            pkt_bytes["backward"][n] = len(data)
            bwd.send(now, data)
        tr.v_hsi[n], tr.f_hsi[n], tr.v_to[n], tr.f_to[n] = op.v, op.f, to.v, to.f
        tr.margin_fwd[n] = op.energy_sent - to.energy_played
        tr.margin_bwd[n] = to.energy_sent - op.energy_played
    tr.payload_bytes, tr.packet_bytes = pay, pkt_bytes

    window = max(1, round(cfg.window_ms / 1e3 / dt))
    raw_per_tick = np.full(n_ticks, float(codec.raw_bytes_per_tick))
    baseline_total = 2.0 * n_ticks * codec.raw_bytes_per_tick
    sent_total = float(sum(a.sum() for a in pay.values()))
    per_dir: dict[str, Any] = {}
    for d in wire.DIRECTIONS:
        per_dir[d] = {
            "packets": int(np.count_nonzero(pay[d])),
            "payload_bytes": int(pay[d].sum()),
            "packet_bytes": int(pkt_bytes[d].sum()),
            "compression": metrics.compression(n_ticks * codec.raw_bytes_per_tick, float(pay[d].sum())),
            "min_instant_compression": metrics.min_instant_compression(raw_per_tick, pay[d], window),
        }
    margins = np.concatenate([tr.margin_fwd, tr.margin_bwd])
    min_margin = float(margins.min())
    counters = {"operator": op.counters.as_dict(), "teleoperator": to.counters.as_dict()}
    summary: dict[str, Any] = {
        "codec": codec.spec,
        "class": codec.klass,
        "I": metrics.transparency(tr.v_hsi, tr.v_to, tr.f_hsi, tr.f_to, dt),
        "compression": metrics.compression(baseline_total, sent_total),
        "min_instant_compression": min(per_dir[d]["min_instant_compression"] for d in wire.DIRECTIONS),
        "passive": bool(min_margin >= -ENERGY_TOLERANCE),
        "min_energy_margin": min_margin,
        "added_delay_ticks": codec.added_delay_ticks,
        "energy": {
            "forward": {
                "sent": op.energy_sent,
                "played": to.energy_played,
                "min_margin": float(tr.margin_fwd.min()),
            },
            "backward": {
                "sent": to.energy_sent,
                "played": op.energy_played,
                "min_margin": float(tr.margin_bwd.min()),
            },
        },
        "directions": per_dir,
        "counters": counters,
    }
    return CaseResult(codec.spec, summary, tr)


def run_set(codecs: list[str], base: SimConfig) -> tuple[dict[str, Any], list[CaseResult]]:
    """Run each codec with the same config; returns the ``results.json`` document and the traces."""
    base = base.resolved()
    cases = [run_case(replace(base, codec=spec)) for spec in codecs]
    i_max = max((c.summary["I"] for c in cases), default=0.0)
    for c in cases:
        c.summary["I_norm"] = c.summary["I"] / i_max if i_max > 0 else 0.0
    doc: dict[str, Any] = {
        "dt": base.dt,
        "duration": base.duration,
        "delay_ms": base.delay_ms,
        "scenario": base.scenario,
        "dof": base.dof,
        "b": base.b,
        "full_scale": base.full_scale,
        "window_ms": base.window_ms,
        "cases": [c.summary for c in cases],
    }
    return doc, cases
