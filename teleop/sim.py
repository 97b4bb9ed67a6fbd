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

Impairment: each direction may carry a netem spec (``SimConfig.netem_forward`` /
``netem_backward``, grammar in ``transport.netem``; ``trace FILE`` gives a Mahimahi trace link).  A
spec *replaces* ``delay_ms`` for its direction (write ``delay`` into the spec); ``delay_ms`` still
applies to a direction without one.  Direction ``i`` (0 forward, 1 backward) is seeded
``2 seed + i``, so the two directions (and neighbouring seeds) draw independent streams and the
same config gives the same bits.  What each link actually did is measured at the receiver by
``transport.linkstats.LinkObserver`` and reported per case under ``link``.  The sim delivers at
tick granularity: a packet due at ``t`` is taken at the first tick ``n dt >= t``, so the observed
one-way delay is the link's delay rounded *up* to the tick (e.g. netem's uniform jitter on
50 +- 5 ms is observed on a 1 ms grid, mean about 0.5 ms higher).
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import numpy.typing as npt

from transport.linkstats import LinkObserver
from transport.netem import Link, NetemStats, make_link

from . import metrics, scenarios, wire
from .codecs import make_codec
from .node import OperatorNode, PortOptions, TeleoperatorNode
from .wave import WaveImpedance

Array = npt.NDArray[np.float64]

#: The paper's Section V set.
SECTION_V_CODECS = ("none", "ids:2", "ids:50", "eds:2", "eds:50", "cq:8")
ENERGY_TOLERANCE = 1e-9  # J: float rounding in cumulative sums, far below any real violation


class ConstantDelayLink:
    """A lossless link with constant delay: ``send(now, data)``, ``due(now) -> [data]``.

    Same interface as the netem shim's link model (``transport.netem.Link``), so the runner does not
    care which it has.
    """

    def __init__(self, delay: float) -> None:
        if delay < 0:
            raise ValueError(f"delay must be >= 0 s, got {delay}")
        self.delay = delay
        self.stats = NetemStats()
        self._heap: list[tuple[float, int, bytes]] = []
        self._n = 0

    def send(self, now: float, data: bytes) -> None:
        heapq.heappush(self._heap, (now + self.delay, self._n, data))
        self._n += 1
        self.stats.sent += 1

    def due(self, now: float) -> list[bytes]:
        out = []
        limit = now + 1e-9
        while self._heap and self._heap[0][0] <= limit:
            out.append(heapq.heappop(self._heap)[2])
        self.stats.delivered += len(out)
        return out

    def next_due(self) -> float | None:
        return self._heap[0][0] if self._heap else None


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
    netem_forward: str = ""  # netem spec for operator -> TO; non-empty replaces delay_ms there
    netem_backward: str = ""  # netem spec for TO -> operator
    seed: int = 0  # link seeds: 2 seed forward, 2 seed + 1 backward (a spec's own ``seed N`` wins)
    on_loss: str = "zero"  # receivers' reconstruction when nothing is queued (teleop.node.PortOptions)
    controller: bool = True  # passivity controller on both receivers
    link_timeout: float = 0.05  # s of silence before a side goes to its safe state

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
        PortOptions(on_loss=c.on_loss, controller=c.controller, link_timeout=c.link_timeout)  # checks them
        if not c.window_ms >= c.dt * 1e3:
            raise ValueError(f"window must be at least one tick ({c.dt * 1e3} ms), got {c.window_ms}")
        for spec in (c.netem_forward, c.netem_backward):
            if spec.strip():
                make_link(spec, c.seed)  # NetemError (a ValueError) says which token is wrong
        return c

    def links(self) -> dict[str, Link]:
        """One link per direction: the netem spec if given, else ``delay_ms`` of constant delay."""
        out: dict[str, Link] = {}
        for i, (d, spec) in enumerate(
            zip(wire.DIRECTIONS, (self.netem_forward, self.netem_backward), strict=True)
        ):
            out[d] = (
                make_link(spec, 2 * self.seed + i) if spec.strip() else ConstantDelayLink(self.delay_ms / 1e3)
            )
        return out


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
    opts = PortOptions(on_loss=cfg.on_loss, controller=cfg.controller, link_timeout=cfg.link_timeout)
    op = OperatorNode(human=human, wave=wave, tx=codec, rx=codec, session=cfg.session, dt=dt, options=opts)
    to = TeleoperatorNode(
        environment=env, wave=wave, tx=codec, rx=codec, session=cfg.session, dt=dt, options=opts
    )
    links = cfg.links()
    fwd, bwd = links["forward"], links["backward"]
    specs = {"forward": cfg.netem_forward, "backward": cfg.netem_backward}
    observers = {d: LinkObserver(specs[d]) for d in wire.DIRECTIONS}
    obs_fwd, obs_bwd = observers["forward"], observers["backward"]

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
            _deliver(op, obs_bwd, now, data)
        p = op.tick(now)
        if p is not None:
            data = wire.encode(p)
            pay["forward"][n] = len(p.payload)
            pkt_bytes["forward"][n] = len(data)
            fwd.send(now, data)
        for data in fwd.due(now):
            _deliver(to, obs_fwd, now, data)
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
    for d in wire.DIRECTIONS:
        _drain(links[d], observers[d], n_ticks, dt)

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
        # Eq. (4): energy into the communication two-port = forward margin + backward margin.
        "two_port_min_energy": float((tr.margin_fwd + tr.margin_bwd).min()),
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
        # The watchdog of each direction, at its receiver (margins from in-band reports).
        "passivity": {"forward": to.passivity.as_dict(), "backward": op.passivity.as_dict()},
        "directions": per_dir,
        "counters": counters,
        "link": {
            d: observers[d].summary(
                sent=links[d].stats.sent, dropped_by_limit=links[d].stats.dropped_by_limit
            )
            for d in wire.DIRECTIONS
        },
    }
    return CaseResult(codec.spec, summary, tr)


def _deliver(node: OperatorNode | TeleoperatorNode, obs: LinkObserver, now: float, data: bytes) -> None:
    """``node.receive(data)``, parsing once and showing every parseable datagram to the observer.

    A datagram that does not parse (only a ``corrupt`` spec makes those) is counted by the node as
    malformed and not observed: the receiver cannot tell its seq.
    """
    try:
        p = wire.decode(data)
    except wire.WireError as e:
        node.malformed(str(e))
        return
    obs.observe(now, p.seq, p.t_us / 1e6, len(data))
    node.receive_packet(p)


def _drain(link: Link, obs: LinkObserver, n: int, dt: float) -> None:
    """Show the observer what was still in flight at the end, at the ticks it would have arrived.

    The nodes have stopped and do not see these; without them the observer would count the last
    ``delay / dt`` packets as lost and miss the longest delays (a rate-limited queue's backlog).
    """
    while (t := link.next_due()) is not None:
        n = max(n, math.ceil(t / dt - 1e-6))
        for data in link.due(n * dt):
            try:
                p = wire.decode(data)
            except wire.WireError:
                continue
            obs.observe(n * dt, p.seq, p.t_us / 1e6, len(data))
        n += 1


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
        "netem": {"forward": base.netem_forward, "backward": base.netem_backward},
        "seed": base.seed,
        "cases": [c.summary for c in cases],
    }
    return doc, cases
