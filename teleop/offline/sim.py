"""``teleop sim``: a deterministic virtual-time run of the two nodes joined by a channel.

The runner owns the clock.  Tick ``n`` of the operator is ``now = n dt``; its packet enters the
forward link, then the teleoperator ticks at ``(n + phase) dt`` with whatever is due, and its packet
enters the backward link.  ``phase`` is where a real teleoperator ticks too: when the operator's
packet is due, from the forward transit it measured (``teleop.session.link.phase``; here the link's delay
and no jitter, so just past the arrival).  With delay ``T`` per direction a forward packet is played
at tick ``n + T/dt`` and a backward one at the operator's tick ``n + ceil(2 T/dt + phase)``: the
round trip of two loops that each tick once, the floor of any causal implementation (two real
processes cannot do better).  The paper's ``I_ref = 0`` assumes the loop solved algebraically
across the channel; here ``none`` at ``T = 0`` shows the small residual of that one-tick floor and
of 16-bit quantisation, and the report says so.

Packets cross the links as wire bytes (``teleop.session.wire``), so the sim exercises the same parsing as
the real processes, and payload and packet sizes are counted, not estimated.

Impairment: each direction may carry a netem spec (``SimConfig.netem_forward`` /
``netem_backward``, grammar in ``teleop.session.link.netem``; ``trace FILE`` gives a Mahimahi trace link).  A
spec *replaces* ``delay_ms`` for its direction (write ``delay`` into the spec); ``delay_ms`` still
applies to a direction without one.  Direction ``i`` (0 forward, 1 backward) is seeded
``2 seed + i``, so the two directions (and neighbouring seeds) draw independent streams and the
same config gives the same bits.  What each link actually did is measured at the receiver by
``teleop.session.link.linkstats.LinkObserver`` and reported per case under ``link``.  The sim delivers at
tick granularity: a packet due at ``t`` is taken at the first tick ``n dt >= t``, so the observed
one-way delay is the link's delay rounded *up* to the tick (e.g. netem's uniform jitter on
50 +- 5 ms is observed on a 1 ms grid, mean about 0.5 ms higher).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.typing as npt

from teleop import devices
from teleop.control import metrics
from teleop.control.codecs import Codec, make_codec
from teleop.devices import scenarios
from teleop.session import wire
from teleop.session.link.netem import Link
from teleop.session.link.phase import latency
from teleop.session.node import PortOptions
from teleop.session.port import ConstantDelayLink, MemorySink, Port, make_node, make_shim, wire_block
from teleop.session.settings import DEFAULT_ENVELOPE, Channel, Envelope

if TYPE_CHECKING:
    from teleop.session.protocol import SessionParams

Array = npt.NDArray[np.float64]

#: The paper's Section V set.
SECTION_V_CODECS = ("none", "ids:2", "ids:50", "eds:2", "eds:50", "cq:8")
__all__ = ["ConstantDelayLink", "SimConfig", "deliveries", "run_case", "run_set", "taken_early"]
ENERGY_TOLERANCE = 1e-9  # J: float rounding in cumulative sums, far below any real violation


@dataclass(frozen=True)
class SimConfig(Channel):
    """One run: the channel's settings (:class:`teleop.session.settings.Channel`, the same as a real
    session's) and the model's.  ``None`` means the scenario's default (``teleop.devices.scenarios``)."""

    delay_ms: float = 0.0  # constant one-way delay of a direction without a netem spec
    duration: float | None = None
    dt: float = 0.001
    dof: int | None = None
    b: float | None = None
    full_scale: float | None = None
    scenario: str = "step"
    window_ms: float = 100.0
    session: int = 1
    # Ticks ``auto`` keeps at least, at the teleoperator (forward) and the operator (backward):
    # what a real run's buffers settled on, to compare with one (teleop.offline.report).
    playout_floor: tuple[int, int] = (0, 0)
    hsi: str | None = None  # --hsi spec (teleop.devices); None: the scenario's human
    robot: str | None = None  # --robot spec; None: the scenario's environment
    envelope: Envelope | None = None  # the robot's (teleop.session.settings); None: :meth:`robot_envelope`
    # A real run's deliveries to replay (:func:`deliveries`): per direction (forward, backward), for
    # each sender tick, the receiver tick that took its payload (NOT_TAKEN: never; NOT_SENT: the real
    # sender sent nothing then, so a payload the sim sends is delivered as it would be).  None: the
    # sim's own schedule.  Its caller drops the netem specs (the deliveries hold what the link did)
    # and plays with no allowance (``playout="0"``: the run's buffer delay is in them too); its
    # buffers release each payload when it is taken (``PlayoutBuffer(hold=False)``).
    deliveries: tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]] | None = field(
        default=None, compare=False, repr=False
    )
    # With them, the run's teleoperator's send phase per tick (its record's ``send_phase``; -1 or
    # beyond the array: the replay's own target): iDS/eDS then send at the run's ticks.
    send_phases: npt.NDArray[np.int64] | None = field(default=None, compare=False, repr=False)

    @classmethod
    def of_session(cls, p: SessionParams, **sim: Any) -> SimConfig:
        """The simulation of a real session with parameters ``p`` (``sim``: the sim's own fields)."""
        model = {
            "scenario": p.scenario,
            "dof": p.dof,
            "b": p.b,
            "full_scale": p.full_scale,
            "duration": p.duration,
            "dt": p.dt,
            "session": p.session,  # its size on the wire counts in the byte figures
        }
        return cls(**{**model, **p.channel_fields(), **sim})

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
        dof = c.dof
        c = replace(c, playout=c.check_channel(netem_files=True))  # canonical; ValueError says what is wrong
        if c.tdpa and c.full_scale is not None:
            make_codec(c.codec_spec, dof, c.full_scale, power=True)  # CodecError: not on power variables
        scenarios.get(c.scenario).make(dof, c.dt, c.seed, c.variation)  # ModelError says what is wrong
        if not c.window_ms >= c.dt * 1e3:
            raise ValueError(f"window must be at least one tick ({c.dt * 1e3} ms), got {c.window_ms}")
        for role, dev in (("hsi", c.hsi), ("robot", c.robot)):
            if dev is not None:
                # DeviceError (a ValueError) lists what is available, or says it is hardware: the
                # sim never connects to a real device (teleop.devices, "Hardware").
                devices.offline(dev, role, "the sim")
        return c

    def port_options(self) -> PortOptions:
        return PortOptions.of(self)

    def robot_envelope(self) -> Envelope:
        """The robot's envelope in this run: ``envelope``, else a default robot's widened to admit
        this run's own settings (``Envelope.admitting``), as ``teleop run`` starts its
        teleoperator: what a real robot started for this run's settings runs inside."""
        if self.envelope is not None:
            return self.envelope
        assert self.full_scale is not None and self.b is not None and self.dof is not None, "resolved() first"
        return DEFAULT_ENVELOPE.admitting(self)  # type: ignore[arg-type]

    def shims(self) -> dict[str, Link | None]:
        """One shim per direction: the netem spec if given, else ``delay_ms`` of constant delay."""
        specs = (self.netem_forward, self.netem_backward)
        return {
            d: make_shim(specs[i], self.seed, i, self.delay_ms / 1e3) for i, d in enumerate(wire.DIRECTIONS)
        }


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
    wire_bytes: dict[str, Array] = field(default_factory=dict)  # on the wire as it left the shim
    # The sequence numbers each side sent and had accepted by each tick, as a real log has them
    # (``operator``/``teleoperator`` -> (tx_seq, rx_seq)): what :func:`deliveries` reads.
    seqs: dict[str, tuple[npt.NDArray[np.int64], npt.NDArray[np.int64]]] = field(default_factory=dict)
    send_phase: npt.NDArray[np.int64] = field(
        default_factory=lambda: np.zeros(0, np.int64)
    )  # the teleoperator's


@dataclass
class CaseResult:
    summary: dict[str, Any]
    trace: Trace

    @property
    def codec(self) -> str:
        """The case's canonical codec spec (its summary says it)."""
        return str(self.summary["codec"])


def _ports(cfg: SimConfig) -> tuple[Port, Port, Codec]:
    assert cfg.dof is not None and cfg.duration is not None and cfg.b is not None
    assert cfg.full_scale is not None
    n_ticks = round(cfg.duration / cfg.dt)
    opts = cfg.port_options()
    shims = cfg.shims()
    ports = []
    for role, d, peer_spec in (
        ("operator", "forward", cfg.netem_backward),
        ("teleoperator", "backward", cfg.netem_forward),
    ):
        node = make_node(
            role,
            scenario=cfg.scenario,
            dof=cfg.dof,
            dt=cfg.dt,
            b=cfg.b,
            codec=cfg.codec,
            full_scale=cfg.full_scale,
            session=cfg.session,
            options=opts,
            device=cfg.hsi if role == "operator" else cfg.robot,
            seed=cfg.seed,
            variation=cfg.variation,
        )
        if role == "teleoperator":
            node.confine(cfg.robot_envelope())
        window = max(1, round(cfg.window_ms / 1e3 / cfg.dt))
        ports.append(
            Port(
                node,
                ticks=n_ticks,
                shim=shims[d],
                peer_spec=peer_spec,
                window_ticks=window,
                playout_floor=cfg.playout_floor[0 if role == "teleoperator" else 1],
                playout_hold=cfg.deliveries is None,  # a replay's deliveries are the run's plays
            )
        )
    if cfg.deliveries is not None and cfg.send_phases is not None:
        ph = np.asarray(cfg.send_phases, dtype=np.int64)
        ports[1].replay_phases = np.where((ph >= 0) & (ph <= MAX_SEND_PHASE), ph, -1)
    return ports[0], ports[1], ports[0].node.tx_codec


def run_case(cfg: SimConfig) -> CaseResult:
    """One deterministic run of two ports joined by virtual links; same config, same bits out.

    Within tick ``n``: the backward datagrams the teleoperator's last tick released reach the
    operator, the operator ticks and its forward datagrams due by now reach the teleoperator, which
    ticks at its phase; its own datagrams wait for the operator's next tick (the module docstring).
    With ``cfg.deliveries`` (a real run's, replayed) each payload is taken at the tick the run's
    receiver took it instead, so what the host's stalls did to the run happens here too.
    """
    cfg = cfg.resolved()
    op, to, codec = _ports(cfg)
    dt, n_ticks = cfg.dt, _ticks(op)
    fwd, bwd = cfg.deliveries if cfg.deliveries is not None else (None, None)
    # Datagrams held for a later tick (a replay's late deliveries; the next operator tick's
    # backward ones), with the session time they arrived at.
    due_op: dict[int, list[tuple[bytes, float]]] = {}
    due_to: dict[int, list[bytes]] = {}
    for n in range(n_ticks):
        now = n * dt
        for data, t in due_op.pop(n, ()):
            op.receive(data, t, n)
        at = _taken_at(fwd, n, n)
        for data in op.tick(n, now):
            if at == n:
                to.receive(data, now, n)
            elif at > n:
                due_to.setdefault(at, []).append(data)
        for data in due_to.pop(n, ()):
            to.receive(data, now, n)
        op.sent(n, now)
        op.clock.advance(n)  # (both clocks are the sim's: no skew to take)
        # The teleoperator ticks when the operator's packet is due, as a real one does.
        t_back = (n + to.clock.phase) * dt
        at = _taken_at(bwd, n, n + 1)
        for data in to.tick(n, t_back):
            if at > n:  # taken at the operator's next tick, sent at t_back; a replay's later one then
                due_op.setdefault(at, []).append((data, t_back if at == n + 1 else at * dt))
        to.sent(n, t_back)
        to.clock.advance(n)
    for data, _ in due_op.pop(n_ticks, ()):  # sent at the last tick: observed, not played
        op.receive(data, n_ticks * dt, n_ticks - 1, play=False)
    _drain(to, op, n_ticks, dt)
    _drain(op, to, n_ticks, dt)
    return CaseResult(_summary(cfg, op, to, codec), _trace(op, to, dt))


NOT_TAKEN, NOT_SENT = -1, -2  # SimConfig.deliveries' marks
MAX_SEND_PHASE = 10_000  # ticks: a recorded send phase beyond it is not one (no target reaches it)


def _taken_at(dl: npt.NDArray[np.int64] | None, n: int, nominal: int) -> int:
    """The tick a payload sent at tick ``n`` is taken at: ``dl[n]`` when a replay says (its
    NOT_TAKEN: never), else ``nominal`` (the sim's own schedule, and a tick the run sent nothing at)."""
    if dl is None or n >= len(dl) or dl[n] == NOT_SENT:
        return nominal
    return int(dl[n])


def taken_early(fwd: npt.NDArray[np.int64], bwd: npt.NDArray[np.int64]) -> tuple[int, int]:
    """Payloads (forward, backward) of :func:`deliveries` taken before the sim's order of ticks lets
    them be: within tick n the sim runs the operator, then the teleoperator (which takes the operator's
    tick-n payload at n at the earliest), whose payload the operator takes at n + 1 at the earliest.  A
    real receiver that stalled past its peer's next tick took that one early (a teleoperator 1 ms late
    at tick 0 took the operator's tick 1 there: a CI run); a replay takes each at the earliest tick it
    can, so with any of them it is approximate."""
    fwd, bwd = np.asarray(fwd, dtype=np.int64), np.asarray(bwd, dtype=np.int64)
    f = np.count_nonzero((fwd >= 0) & (fwd < np.arange(len(fwd))))
    b = np.count_nonzero((bwd >= 0) & (bwd < np.arange(len(bwd)) + 1))
    return int(f), int(b)


def deliveries(tx_seq: npt.ArrayLike, rx_seq: npt.ArrayLike) -> npt.NDArray[np.int64]:
    """For each tick of a sender's log, the tick of the receiver's log that took its payload: the
    first whose newest accepted sequence number (``rx_seq``) reached the one sent (``tx_seq``;
    -1 at a tick that sent nothing: NOT_SENT).  A payload never reached is NOT_TAKEN; one that a
    newer overtook is taken with it (and dropped as stale by the node, as it was).  Both logs
    count ticks from the session's tick 0."""
    tx = np.asarray(tx_seq, dtype=np.int64)
    rx = np.maximum.accumulate(np.asarray(rx_seq, dtype=np.int64))
    out = np.full(tx.shape, NOT_SENT, dtype=np.int64)
    sent = tx >= 0
    at = np.searchsorted(rx, tx[sent], side="left")
    out[sent] = np.where(at < len(rx), at, NOT_TAKEN)
    return out


def _trace(op: Port, to: Port, dt: float) -> Trace:
    """Whole-session arrays from the two ports' in-memory records."""
    op.finish()
    to.finish()
    assert isinstance(op.sink, MemorySink) and isinstance(to.sink, MemorySink) and op.ticks is not None
    ao, at = op.sink.arrays(op.ticks), to.sink.arrays(op.ticks)
    tr = Trace(
        t=np.arange(op.ticks, dtype=np.float64) * dt,
        v_hsi=ao["v"],
        f_hsi=ao["f"],
        v_to=at["v"],
        f_to=at["f"],
        margin_fwd=ao["energy_sent"] - at["energy_played"],
        margin_bwd=at["energy_sent"] - ao["energy_played"],
    )
    tr.payload_bytes = {"forward": ao["produced_payload"], "backward": at["produced_payload"]}
    tr.packet_bytes = {"forward": ao["produced_packet"], "backward": at["produced_packet"]}
    tr.wire_bytes = {"forward": ao["tx_wire"], "backward": at["tx_wire"]}
    tr.seqs = {"operator": (ao["tx_seq"], ao["rx_seq"]), "teleoperator": (at["tx_seq"], at["rx_seq"])}
    tr.send_phase = at["send_phase"]
    return tr


def _directions(cfg: SimConfig, tr: Trace, n_ticks: int, codec: Codec) -> dict[str, Any]:
    """Each direction's packets, bytes and compression (average and minimum instantaneous)."""
    window = max(1, round(cfg.window_ms / 1e3 / cfg.dt))
    raw_per_tick = np.full(n_ticks, float(codec.raw_bytes_per_tick))
    pay = tr.payload_bytes
    return {
        d: {
            "packets": int(np.count_nonzero(pay[d])),
            "payload_bytes": int(pay[d].sum()),
            "packet_bytes": int(tr.packet_bytes[d].sum()),
            "compression": metrics.compression(n_ticks * codec.raw_bytes_per_tick, float(pay[d].sum())),
            "min_instant_compression": metrics.min_instant_compression(raw_per_tick, pay[d], window),
        }
        for d in wire.DIRECTIONS
    }


def _energy(tr: Trace, o: dict[str, Any], t: dict[str, Any]) -> dict[str, Any]:
    """Energy sent and played each way (the operator's view ``o``, the teleoperator's ``t``)."""
    return {
        "forward": {
            "sent": o["energy"]["sent"],
            "played": t["energy"]["played"],
            "min_margin": float(tr.margin_fwd.min()),
        },
        "backward": {
            "sent": t["energy"]["sent"],
            "played": o["energy"]["played"],
            "min_margin": float(tr.margin_bwd.min()),
        },
    }


def _summary(cfg: SimConfig, op: Port, to: Port, codec: Codec) -> dict[str, Any]:
    n_ticks, dt = _ticks(op), cfg.dt
    tr = _trace(op, to, dt)
    baseline_total = 2.0 * n_ticks * codec.raw_bytes_per_tick
    per_dir = _directions(cfg, tr, n_ticks, codec)
    sent_total = float(sum(a.sum() for a in tr.payload_bytes.values()))
    side = {
        "forward": op.summary(peer_produced=_sent_into(to.shim, to), peer_dropped_by_limit=_dropped(to)),
        "backward": to.summary(peer_produced=_sent_into(op.shim, op), peer_dropped_by_limit=_dropped(op)),
    }
    # side["forward"] is the operator's own view: it sent forward and received (observed) backward.
    o, t = side["forward"], side["backward"]
    margins = np.concatenate([tr.margin_fwd, tr.margin_bwd])
    min_margin = float(margins.min())
    summary: dict[str, Any] = {
        "codec": str(codec.spec),
        "class": codec.klass,
        "I": metrics.transparency(tr.v_hsi, tr.v_to, tr.f_hsi, tr.f_to, dt),
        # Per phase of the scenario (free, foam, wall; ``all``: the run): I per DoF, wire rates (Fig. 15).
        "phases": metrics.phase_summary(
            tr.v_hsi,
            tr.v_to,
            tr.f_hsi,
            tr.f_to,
            dt,
            _phases(cfg),
            tr.wire_bytes,
        ),
        "compression": metrics.compression(baseline_total, sent_total),
        "min_instant_compression": min(per_dir[d]["min_instant_compression"] for d in wire.DIRECTIONS),
        "passive": bool(min_margin >= -ENERGY_TOLERANCE),
        "min_energy_margin": min_margin,
        "added_delay_ticks": codec.added_delay_ticks,
        # Eq. (4): energy into the communication two-port = forward margin + backward margin.
        "two_port_min_energy": float((tr.margin_fwd + tr.margin_bwd).min()),
        "energy": _energy(tr, o, t),
        # The watchdog of each direction, at its receiver (margins from in-band reports).
        "passivity": {"forward": _no_dir(t["passivity"]), "backward": _no_dir(o["passivity"])},
        "directions": per_dir,
        # The same per-direction block as report.json's: counted where the datagrams leave and arrive.
        "wire": {
            "forward": wire_block(o["sent"], t["received"]),
            "backward": wire_block(t["sent"], o["received"]),
        },
        "counters": {"operator": op.node.counters.as_dict(), "teleoperator": to.node.counters.as_dict()},
        "link": {"forward": t["link_received"], "backward": o["link_received"]},
        # The data-rate cap of each direction, at its sender, and whether it held (teleop.control.ratecap).
        "rate_cap": {"forward": o["rate_cap"], "backward": t["rate_cap"]},
        # Each direction's playout buffer, at its receiver (teleop.session.playout).
        "playout": {"forward": t["playout"], "backward": o["playout"]},
        # Sent -> played per direction and the round trip, against the link's floor (session.link.phase).
        "latency": latency(
            {"forward": t["playout"], "backward": o["playout"]},
            {"forward": t["clock"], "backward": o["clock"]},
            dt,
        ),
        # What each receiver refused (teleop.session.auth): forgeries, corruption, replays and duplicates.
        "security": {"forward": t["security"], "backward": o["security"]},
        # Each side's device (teleop.devices): its spec and, if it keeps one, its own port observer.
        "devices": {"hsi": o["device"], "robot": t["device"]},
        "passivity_architecture": cfg.passivity,
    }
    summary.update(_delay_and_distortion(cfg, tr, summary))
    return summary


def _delay_and_distortion(cfg: SimConfig, tr: Trace, summary: dict[str, Any]) -> dict[str, Any]:
    """Figures next to eq. (7) that separate delay from distortion (issue 23): ``I_dc``, eq. (7)
    with the measured one-way delays taken out (``teleop.control.metrics.delay_compensated``), the
    position drift between HSI and TO, and the energy the passivity controllers dissipated."""
    dt = cfg.dt
    shift = {d: metrics.one_way_ticks(summary["playout"][d], summary["link"][d], dt) for d in wire.DIRECTIONS}
    pv = summary["passivity"]
    out: dict[str, Any] = {
        "I_dc": metrics.delay_compensated(
            tr.v_hsi, tr.v_to, tr.f_hsi, tr.f_to, dt, shift["forward"], shift["backward"]
        ),
        "delay_compensation_ms": {d: shift[d] * dt * 1e3 for d in wire.DIRECTIONS},
        "drift_m": metrics.position_drift(tr.v_hsi, tr.v_to, dt, shift["forward"]),
        # How hard the contact felt at each end (N, norm over DoF): eq. (7) compares the two ends
        # only, so a soft wall rendered alike at both scores well; this shows it.
        "peak_force_N": {
            "hsi": float(np.sqrt((tr.f_hsi**2).sum(axis=1)).max(initial=0.0)),
            "to": float(np.sqrt((tr.f_to**2).sum(axis=1)).max(initial=0.0)),
        },
        "energy_dissipated": {
            "forward": pv["forward"]["energy_dissipated"],
            "backward": pv["backward"]["energy_dissipated"],
            "total": pv["forward"]["energy_dissipated"] + pv["backward"]["energy_dissipated"],
        },
    }
    if cfg.tdpa:
        # TDPA's watchdog per direction (Artigas et al.'s observer): E_in at the sending port, E_out
        # at the receiving one, as each counted them; the receiver's view of E_in is the report.
        en = summary["energy"]
        out["tdpa"] = {
            d: {
                "energy_in": en[d]["sent"],
                "energy_out": en[d]["played"],
                "min_margin": en[d]["min_margin"],
                "controller_active_ticks": pv[d]["controller_active_ticks"],
                "energy_dissipated": pv[d]["energy_dissipated"],
                "violations_observed": pv[d]["violations"],
            }
            for d in wire.DIRECTIONS
        }
    return out


def _phases(cfg: SimConfig) -> list[tuple[str, float, float]]:
    assert cfg.duration is not None
    return scenarios.get(cfg.scenario).phases(cfg.seed, cfg.variation, cfg.duration)


def _ticks(port: Port) -> int:
    """The simulated session's length (a simulation always has one)."""
    assert port.ticks is not None
    return port.ticks


def _no_dir(p: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in p.items() if k != "direction"}


def _sent_into(shim: Link | None, sender: Port) -> int:
    """Packets the sender put on its link (the shim's count, or every packet without a shim)."""
    return shim.stats.sent if shim is not None else sender.produced()


def _dropped(sender: Port) -> int:
    return sender.shim.stats.dropped_by_limit if sender.shim is not None else 0


def _drain(sender: Port, receiver: Port, n: int, dt: float) -> None:
    """Show the receiver what was still in flight at the end, at the ticks it would have arrived.

    The nodes have stopped and do not play these; without them the observer would count the last
    ``delay / dt`` packets as lost and miss the longest delays (a rate-limited queue's backlog).
    """
    while (t := sender.next_due()) is not None:
        n = max(n, math.ceil(t / dt - 1e-6))
        for data in sender.flush(n * dt, _ticks(sender) - 1):
            receiver.receive(data, n * dt, _ticks(receiver) - 1, play=False)
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
        "hsi": base.hsi or base.scenario,
        "robot": base.robot or base.scenario,
        "variation": base.variation,
        "passivity": base.passivity,
        "cases": [c.summary for c in cases],
    }
    return doc, cases
