"""Merge the two processes' logs into one report: ``report.json``, PNG plots and a text summary.

Every figure here is read from the logs: bytes counted at the sockets, ticks counted by the loops,
signals recorded by the nodes.  Signals are aligned by tick index (the handshake's common start).
The logs are the processes' ``ROLE.mcap`` files (``shell.mcaplog``: per-tick channels and the
summary), read with the ``mcap`` library; a session without a fixed end is compared with
``teleop sim`` over the ticks both sides actually ran.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from teleop import devices, limits
from teleop.control import metrics
from teleop.devices import scenarios
from teleop.files import MAX_TRACE_BYTES, read_regular
from teleop.offline import plots
from teleop.offline.logfile import LogError, checked_params, find_pair, iter_ticks, log_session, read_session
from teleop.offline.sim import (
    NOT_SENT,
    NOT_TAKEN,
    SimConfig,
    deliveries,
    run_case,
    taken_early,
)
from teleop.session.link.phase import latency
from teleop.session.port import wire_block
from teleop.session.protocol import SessionParams

Array = npt.NDArray[np.float64]
Block = dict[str, npt.NDArray[Any]]

#: The report's topics (the waves are for viewers; no figure here needs them).
TOPICS = ("signals", "energy", "wire", "loop")
#: Receiver ticks wait this long for the sender's log before their margin is computed: a payload
#: accepted at tick k was sent at a sender tick <= k (a common clock), this is slack for its error.
LOOKAHEAD_TICKS = 1000
#: ``teleop sim`` re-runs at most this much of a session (it keeps every tick: under 1 MB and
#: 0.18 s of CPU per simulated second, measured), and the real I is compared over the same ticks.
SIM_CAP_S = 300.0
PLOT_POINTS = 1 << 17  # samples kept per plotted series: every tick up to 131 s, then thinned
BANDWIDTH_WINDOW = 100  # ticks per bandwidth point (100 ms at 1 kHz)
HIST_US = 100_000  # the lateness histogram's 1 us bins; later ticks are kept one by one


def _trace_specs(
    paths: dict[str, Path], p: SessionParams, traces: tuple[Path, ...]
) -> tuple[dict[str, str], str | None]:
    """The netem specs the sim re-runs with: a ``trace FILE`` spec's path (what the log names) is
    replaced by a file the user gave (``--trace``) whose SHA-256 is the one the log recorded
    (``/ROLE/session``'s ``traces``, teleop.files.trace_digests); returns (specs, None), or
    (specs, why the sim cannot be re-run)."""
    specs = {"forward": p.netem_forward, "backward": p.netem_backward}
    used = [d for d, spec in specs.items() if spec.split()[:1] == ["trace"]]
    if not used:
        return specs, None
    recorded: dict[str, dict[str, Any]] = {}
    for path in paths.values():
        got = read_session(path).get("traces")
        for d, entry in (got if isinstance(got, dict) else {}).items():
            if isinstance(entry, dict) and isinstance(entry.get("sha256"), str):
                recorded[d] = entry
    given = {hashlib.sha256(read_regular(f, MAX_TRACE_BYTES, "--trace")).hexdigest(): f for f in traces}
    missing = []
    for d in used:
        entry = recorded.get(d)
        if entry is None:
            missing.append(f"{d}: no digest in the logs")
        elif entry["sha256"] in given:
            specs[d] = f"trace {given[entry['sha256']]}"
        else:
            missing.append(f"{d}: sha256 {entry['sha256'][:16]}..., {entry.get('bytes')} bytes")
    if missing:
        return specs, (
            f"the session ran a trace link ({'; '.join(missing)}): a report never opens a file a log "
            "names; pass the same trace file with --trace FILE to re-run the simulation"
        )
    return specs, None


def _paired(
    a: Iterator[tuple[int, Block]], b: Iterator[tuple[int, Block]]
) -> Iterator[tuple[int, Block, Block]]:
    """Both logs' blocks cut to the same ticks; ends with the shorter log (a session without a fixed
    end stops at a slightly different tick on each side)."""
    have: list[tuple[int, Block] | None] = [None, None]
    its = (a, b)
    while True:
        for i in (0, 1):
            if have[i] is None:
                nxt = next(its[i], None)
                if nxt is None:
                    return
                have[i] = nxt
        (k0, x), (_, y) = have[0], have[1]  # type: ignore[misc]
        m = min(len(x["ran"]), len(y["ran"]))
        yield k0, {n: v[:m] for n, v in x.items()}, {n: v[:m] for n, v in y.items()}
        for i, blk in ((0, x), (1, y)):
            rest = len(blk["ran"]) - m
            have[i] = (k0 + m, {n: v[m:] for n, v in blk.items()}) if rest else None


class _Grow:
    """A numpy array appended to in place (capacity doubling), for ``searchsorted`` over it."""

    def __init__(self, dtype: Any) -> None:
        self._a = np.zeros(1024, dtype=dtype)
        self.n = 0

    def extend(self, x: npt.NDArray[Any]) -> None:
        if self.n + x.size > self._a.size:
            self._a = np.resize(self._a, max(2 * self._a.size, self.n + x.size))
        self._a[self.n : self.n + x.size] = x
        self.n += x.size

    @property
    def values(self) -> npt.NDArray[Any]:
        return self._a[: self.n]


def _keep_min_by_epochs(store: dict[tuple[int, int], float], values: Array, op: Block, to: Block) -> None:
    """The minimum of ``values`` (per tick, NaN: none) kept per pair of the two receivers' epochs."""
    fin = np.isfinite(values)
    if fin.any():
        pairs = np.stack([to["peer_epoch"][fin], op["peer_epoch"][fin]], axis=1)
        for e_to, e_op in np.unique(pairs, axis=0).tolist():
            sel = (to["peer_epoch"] == e_to) & (op["peer_epoch"] == e_op) & fin
            _keep_min(store, (e_to, e_op), values[sel])


class _Margin:
    """One direction's true margin, eq. (5), per receiver tick: the energy the sender's own log says
    it had put into the packets the receiver had accepted by then, minus the energy played since the
    receiver's last energy epoch.  Aligned by sequence number, so no clock is trusted: the newest
    seq accepted by each receiver tick is looked up in the sender's log (16 bytes kept per packet
    sent).  Only the receiver's last epoch counts (a restarted peer starts a new one), so minima
    are kept per epoch and the last one chosen at the end."""

    def __init__(self) -> None:
        self.seqs, self.energy = _Grow(np.int64), _Grow(np.float64)
        self.min_by_epoch: dict[int, float] = {}
        self.last_epoch = 0

    def sent(self, s: Block) -> None:
        out = s["tx_seq"] >= 0
        self.seqs.extend(s["tx_seq"][out])
        self.energy.extend(s["energy_sent"][out])

    def per_tick(self, r: Block) -> Array:
        """The margin of each of these receiver ticks (NaN: nothing to compare), any epoch."""
        seqs, energy = self.seqs.values, self.energy.values
        rx = r["rx_seq"]
        if seqs.size:
            idx = np.minimum(np.searchsorted(seqs, rx, side="left"), seqs.size - 1)
            found = (rx >= 0) & (seqs[idx] == rx)
            sent = np.where(found, energy[idx], 0.0)
        else:
            found, sent = np.zeros(rx.size, dtype=bool), np.zeros(rx.size)
        played = r["energy_played_epoch"]
        ok = ~np.isnan(played) & ((rx < 0) | found)
        m: Array = np.where(ok, sent - played, np.nan)
        epochs = r["peer_epoch"]
        if epochs.size:
            self.last_epoch = max(self.last_epoch, int(epochs.max()))
        for e in np.unique(epochs[np.isfinite(m)]).tolist():
            _keep_min(self.min_by_epoch, e, m[(epochs == e) & np.isfinite(m)])
        return m

    def minimum(self) -> float:
        return self.min_by_epoch.get(self.last_epoch, math.nan)


class _Thin:
    """Every ``stride``-th tick of some series for the plots, ``stride`` doubling whenever more
    than :data:`PLOT_POINTS` are kept: an hour's session plots from a few MB."""

    def __init__(self) -> None:
        self.stride = 1
        self.k: list[npt.NDArray[np.int64]] = []
        self.cols: dict[str, list[Array]] = {}

    def add(self, k: npt.NDArray[np.int64], **series: Array) -> None:
        keep = k % self.stride == 0
        self.k.append(k[keep])
        for name, v in series.items():
            self.cols.setdefault(name, []).append(v[keep])
        if sum(x.size for x in self.k) > PLOT_POINTS:
            self.stride *= 2
            k_all, cols = self.get()
            keep = k_all % self.stride == 0
            self.k = [k_all[keep]]
            self.cols = {n: [v[keep]] for n, v in cols.items()}

    def get(self) -> tuple[npt.NDArray[np.int64], dict[str, Array]]:
        if not self.k:
            return np.zeros(0, dtype=np.int64), {}
        return np.concatenate(self.k), {n: np.concatenate(v) for n, v in self.cols.items()}


@dataclass
class _Windowed:
    """Sums over the last :data:`BANDWIDTH_WINDOW` ticks, carried across blocks."""

    tail: Array = field(default_factory=lambda: np.zeros(0))

    def add(self, k0: int, x: Array) -> tuple[npt.NDArray[np.int64], Array]:
        """(tick each window ends at, its sum) for the windows ending in this block."""
        w = BANDWIDTH_WINDOW
        xs = np.concatenate([self.tail, np.nan_to_num(x)])
        first = k0 - self.tail.size  # the tick of xs[0]
        self.tail = xs[-(w - 1) :] if w > 1 else np.zeros(0)
        if xs.size < w:
            return np.zeros(0, dtype=np.int64), np.zeros(0)
        cs = np.concatenate(([0.0], np.cumsum(xs)))
        return first + w - 1 + np.arange(xs.size - w + 1), cs[w:] - cs[:-w]


class _Lateness:
    """One loop's tick lateness (start minus deadline) as a histogram of 1 us bins."""

    def __init__(self) -> None:
        self.counts = np.zeros(HIST_US, dtype=np.int64)
        self.beyond: list[float] = []
        self.ticks = 0

    def add(self, lateness_ns: npt.NDArray[np.int64]) -> None:
        us = lateness_ns // 1000
        self.ticks += us.size
        inside = us[(us >= 0) & (us < HIST_US)]
        self.counts += np.bincount(inside, minlength=HIST_US)[:HIST_US]
        self.beyond.extend(us[us >= HIST_US].astype(float).tolist())

    def values(self) -> tuple[Array, Array]:
        """(lateness in us, ticks at it), for a weighted histogram."""
        at = np.flatnonzero(self.counts)
        b = np.asarray(self.beyond, dtype=np.float64)
        return np.concatenate([at.astype(np.float64), b]), np.concatenate(
            [self.counts[at].astype(np.float64), np.ones(b.size)]
        )


def _keep_min(table: dict[Any, float], key: Any, values: Array) -> None:
    """``table[key]``: the least of ``values`` seen under ``key`` so far."""
    table[key] = min(float(values.min()), table.get(key, math.inf))


class _Fold:
    """The report's whole-session figures, folded a block of ticks at a time from both logs: eq. (7)
    per phase and DoF, wire rates per phase, the true energy margins (eq. 4-5), and the plots'
    thinned series.  Memory: the plots' series, a lookahead of ticks and 16 bytes per packet sent."""

    def __init__(
        self,
        phases: list[tuple[str, float, float]],
        dof: int,
        dt: float,
        shifts: tuple[int, int] | None = None,
    ) -> None:
        self.dt = dt
        # I_dc and the drift, with the one-way delays in ticks (forward, backward) the summaries
        # measured; None when a summary is missing (a killed process): then they are not reported.
        self.shifts = shifts
        self.delay = metrics.DelayDistortionFold(dof, dt, *shifts) if shifts is not None else None
        # Phases as given (clipped to the run's length at the end, by metrics.phase_ticks) and their
        # bounds in ticks, unclipped, to sum each block's ticks into.
        self.phases = phases
        self.bounds = [(n, metrics.first_tick(a, dt), metrics.first_tick(b, dt)) for n, a, b in phases]
        names = [n for n, _, _ in phases] + ["all"]
        self.i_dof = {n: np.zeros(dof) for n in names}
        self.counted = dict.fromkeys(names, 0)
        self.packets = {d: dict.fromkeys(names, 0) for d in ("forward", "backward")}
        self.bytes = {d: dict.fromkeys(names, 0.0) for d in ("forward", "backward")}
        self.sim_ticks = round(SIM_CAP_S / dt)
        self.i_sim_window = 0.0
        # Each side's tx_seq, rx_seq and lateness over the sim's ticks: the run's deliveries, which a
        # second sim replays (teleop.offline.sim.deliveries), and the teleoperator's send phase; 56
        # bytes a tick, for SIM_CAP_S at most.
        self.seqs: dict[str, list[npt.NDArray[np.int64]]] = {
            n: [] for n in ("op_tx", "op_rx", "to_tx", "to_rx", "to_phase", "op_late_us", "to_late_us")
        }
        self.fwd, self.bwd = _Margin(), _Margin()
        self.two_port: dict[tuple[int, int], float] = {}
        self.two_port_clock: dict[tuple[int, int], float] = {}
        self.n = 0
        self.any_valid = False
        self.queue: deque[tuple[int, Block, Block]] = deque()
        self.seen = 0
        self.signals, self.energy, self.bandwidth = _Thin(), _Thin(), _Thin()
        self.windows = {n: _Windowed() for n in ("fwd", "fwd_base", "bwd", "bwd_base")}
        self.lateness = {"operator": _Lateness(), "teleoperator": _Lateness()}

    def add(self, k0: int, op: Block, to: Block) -> None:
        """Take a block of both logs; blocks run once the senders' logs are LOOKAHEAD_TICKS ahead."""
        self.fwd.sent(op)
        self.bwd.sent(to)
        self.queue.append((k0, op, to))
        self.seen = k0 + len(op["ran"])
        while self.queue and self.queue[0][0] + len(self.queue[0][1]["ran"]) + LOOKAHEAD_TICKS <= self.seen:
            self._run(*self.queue.popleft())

    def finish(self) -> None:
        while self.queue:
            self._run(*self.queue.popleft())

    def _run(self, k0: int, op: Block, to: Block) -> None:
        n = len(op["ran"])
        k = np.arange(k0, k0 + n, dtype=np.int64)
        self.n = k0 + n
        valid = np.asarray(~(np.isnan(op["v"]).any(axis=1) | np.isnan(to["v"]).any(axis=1)), dtype=bool)
        self.any_valid |= bool(valid.any())
        dv, df = op["v"] - to["v"], to["f"] - op["f"]
        per_tick = np.where(valid[:, None], dv * dv + df * df, 0.0)  # eq. (7)'s integrand per DoF
        wire = {"forward": np.nan_to_num(op["tx_wire"]), "backward": np.nan_to_num(to["tx_wire"])}
        for name, a, b in [*self.bounds, ("all", 0, k0 + n)]:
            lo, hi = max(a, k0) - k0, min(b, k0 + n) - k0
            if hi <= lo:
                continue
            self.i_dof[name] += per_tick[lo:hi].sum(axis=0)
            self.counted[name] += int(np.count_nonzero(valid[lo:hi]))
            for d, w in wire.items():
                self.packets[d][name] += int(np.count_nonzero(w[lo:hi]))
                self.bytes[d][name] += float(w[lo:hi].sum())
        self.i_sim_window += float(per_tick[: max(0, self.sim_ticks - k0)].sum())
        m = max(0, self.sim_ticks - k0)
        if m:
            for side, blk in (("op", op), ("to", to)):
                self.seqs[f"{side}_tx"].append(np.asarray(blk["tx_seq"][:m], dtype=np.int64))
                self.seqs[f"{side}_rx"].append(np.asarray(blk["rx_seq"][:m], dtype=np.int64))
                # How late each tick's loop began (us; the reader's fill, 0, for a tick not run,
                # which sent nothing): whether a payload taken late was its sender's (``sender_late``).
                began_ns = np.asarray(blk["lateness_ns"][:m], dtype=np.int64)
                self.seqs[f"{side}_late_us"].append(began_ns // 1000)
            # The teleoperator's send phase (NaN: not recorded, a log from before it was; the reader
            # bounds every value, the sim refuses one out of range: teleop.offline.sim._ports).
            ph = np.asarray(to["send_phase"][:m], dtype=np.float64)
            self.seqs["to_phase"].append(np.where(np.isfinite(ph), ph, -1).astype(np.int64))
        m_fwd, m_bwd = self.fwd.per_tick(to), self.bwd.per_tick(op)
        _keep_min_by_epochs(self.two_port, m_fwd + m_bwd, op, to)
        # Eq. (4) on the session clock: each side's energy sent by tick k (reported or not) against
        # what both played by tick k, as teleop.offline.sim measures it.  The margins above count a sender's
        # energy only once a packet carrying it was accepted, which a self-crediting pdr (cKAPPA)
        # outruns by design: it plays on energy it is sending and has not reported yet.  This one
        # trusts the handshake's clock offset (its error shifts the sides by a fraction of the RTT).
        fwd_clock = op["energy_sent"] - to["energy_played_epoch"]
        bwd_clock = to["energy_sent"] - op["energy_played_epoch"]
        _keep_min_by_epochs(self.two_port_clock, fwd_clock + bwd_clock, op, to)
        self.signals.add(k, v_op=op["v"], v_to=to["v"], f_op=op["f"], f_to=to["f"])
        if self.delay is not None:
            self.delay.add(op["v"], to["v"], op["f"], to["f"])
        self.energy.add(
            k,
            fwd_sent=op["energy_sent"],
            fwd_played=to["energy_played"],
            fwd_margin=to["energy_margin_observed"],
            bwd_sent=to["energy_sent"],
            bwd_played=op["energy_played"],
            bwd_margin=op["energy_margin_observed"],
        )
        wire_bytes = {
            "fwd": op["tx_wire"], "fwd_base": op["tx_baseline_wire"],
            "bwd": to["tx_wire"], "bwd_base": to["tx_baseline_wire"],
        }  # fmt: skip
        sums = {name: self.windows[name].add(k0, x) for name, x in wire_bytes.items()}
        ends = sums["fwd"][0]  # every series' windows end at the same ticks
        if ends.size:
            self.bandwidth.add(ends, **{name: s for name, (_, s) in sums.items()})
        self.lateness["operator"].add(op["lateness_ns"][op["ran"]])
        self.lateness["teleoperator"].add(to["lateness_ns"][to["ran"]])

    # --- the figures, once every block is in ------------------------------------------------------
    def phase_summary(self) -> dict[str, dict[str, Any]]:
        """metrics.phase_summary's figures: per phase I per DoF, ticks, packets/s and bits/s."""
        out: dict[str, dict[str, Any]] = {}
        for name, sl in metrics.phase_ticks(self.n, self.dt, self.phases).items():
            lo, hi = sl.start, sl.stop
            span = (hi - lo) * self.dt
            i_dof = self.i_dof[name] * self.dt
            out[name] = {
                "I": float(i_dof.sum()),
                "I_dof": [float(x) for x in i_dof],
                "start": round(lo * self.dt, 9),
                "end": round(hi * self.dt, 9),
                "ticks": self.counted[name],
                "packets_per_s": {
                    d: self.packets[d][name] / span if span > 0 else None for d in self.packets
                },
                "wire_bps": {d: 8.0 * self.bytes[d][name] / span if span > 0 else None for d in self.bytes},
            }
        return out

    def min_two_port(self) -> float | None:
        return self.two_port.get((self.fwd.last_epoch, self.bwd.last_epoch))

    def min_two_port_clock(self) -> float | None:
        return self.two_port_clock.get((self.fwd.last_epoch, self.bwd.last_epoch))


def fold_logs(
    op_log: Path,
    to_log: Path,
    phases: list[tuple[str, float, float]],
    dof: int,
    dt: float,
    max_tick: int | None = None,
    shifts: tuple[int, int] | None = None,
) -> _Fold:
    """One pass over both processes' logs, a block of ticks at a time (teleop.offline.logfile.iter_ticks);
    ``max_tick``: the session's length in ticks, beyond which a log is refused; ``shifts``: the
    one-way delays in ticks for I_dc and the drift (teleop.control.metrics.DelayDistortionFold)."""
    fold = _Fold(phases, dof, dt, shifts)
    ops, tos = iter_ticks(op_log, TOPICS, max_tick), iter_ticks(to_log, TOPICS, max_tick)
    for k0, a_op, a_to in _paired(ops, tos):
        fold.add(k0, a_op, a_to)
    fold.finish()
    if fold.n == 0:
        raise LogError(f"{op_log} and {to_log} hold no tick both processes ran")
    return fold


@dataclass
class _Logs:
    """Both logs of one session: their paths, summaries (``{}``: the process was killed before
    it wrote one), the checked parameters, notes on the folder, and the fold of their ticks."""

    paths: dict[str, Path]
    summaries: dict[str, dict[str, Any]]
    params: SessionParams
    notes: list[str]
    fold: _Fold


@functools.lru_cache(maxsize=2)
def _fold_of(op_path: str, to_path: str, mtimes: tuple[int, int]) -> _Logs:
    """Both logs read and folded once per version of the files (the report and the plots both
    need it)."""
    paths = {"operator": Path(op_path), "teleoperator": Path(to_path)}
    summaries, params = {}, {}
    for role, path in paths.items():
        _, summaries[role], params[role] = log_session(path)
    p = checked_params(paths["operator"], params["operator"])
    ticks = round((p.duration or limits.MAX_DURATION_S) / p.dt)
    # A session without a fixed end: its last phase lasts until the end of the log.
    phases = _phases(p, p.duration or 1e9)
    fold = fold_logs(
        paths["operator"],
        paths["teleoperator"],
        phases,
        p.dof,
        p.dt,
        ticks + 1,
        _shifts(summaries, p.dt),
    )
    return _Logs(paths, summaries, p, [], fold)


def _delay_figures(fold: _Fold) -> dict[str, Any]:
    """Next to eq. (7): I_dc (the measured one-way delays taken out), the HSI-TO position drift, and
    the delays used, as ``teleop sim`` reports them; nothing when a summary was missing."""
    if fold.delay is None or fold.shifts is None:
        return {}
    return {
        "I_dc": fold.delay.i_dc,
        "drift_m": fold.delay.drift(),
        "delay_compensation_ms": {
            d: s * fold.dt * 1e3 for d, s in zip(("forward", "backward"), fold.shifts, strict=True)
        },
    }


def _shifts(summaries: dict[str, dict[str, Any]], dt: float) -> tuple[int, int] | None:
    """(forward, backward) one-way delays in ticks as each receiver measured them (its playout
    buffer's median release delay, else its link's mean delay: ``teleop.control.metrics.one_way_ticks``, the
    rule ``teleop sim`` uses), or None when a summary lacks them."""
    try:
        return tuple(  # type: ignore[return-value]
            metrics.one_way_ticks(summaries[role]["playout"], summaries[role]["link_received"], dt)
            for role in ("teleoperator", "operator")
        )
    except (KeyError, TypeError):
        return None


def _load(log_dir: Path, session: int | None = None) -> _Logs:
    op, to, notes = find_pair(log_dir, session)
    logs = _fold_of(str(op), str(to), (op.stat().st_mtime_ns, to.stat().st_mtime_ns))
    return dataclasses.replace(logs, notes=notes)


def _wire(sender: dict[str, Any], receiver: dict[str, Any]) -> dict[str, Any]:
    """One direction's wire block from the two processes' port summaries (as ``teleop sim``'s)."""
    return wire_block(sender["sent"], receiver["received"])


def _passivity(receiver: dict[str, Any]) -> dict[str, Any]:
    p = dict(receiver["passivity"])
    p.pop("direction", None)
    return p


def _settled_allowance(receiver: dict[str, Any], dt: float) -> int:
    """Ticks of playout allowance a receiver used most (the median over its payloads; at least
    the auto mode's floor): the floor of the simulation that compares with this run."""
    pl = receiver.get("playout") or {}
    floor = int(pl.get("auto_floor_ticks", 0))
    p50 = (pl.get("extra_ms") or {}).get("p50")
    return floor if p50 is None else max(floor, round(p50 * 1e-3 / dt))


def _security(op: dict[str, Any], to: dict[str, Any]) -> dict[str, Any]:
    """``security``: how the datagrams were protected and what each receiver refused."""
    o, t = op.get("security", {}), to.get("security", {})
    out: dict[str, Any] = {"auth": o.get("auth"), "key_id": o.get("key_id")}
    for key in ("rejected", "replayed", "counter_jumps", "energy_reports_clamped"):
        out[key] = {"forward": t.get(key), "backward": o.get(key)}
    return out


def _phases(p: SessionParams, duration: float) -> list[tuple[str, float, float]]:
    """The session's phases from its scenario and seeded plan (older logs: no variation)."""
    return scenarios.get(p.scenario).phases(p.seed, p.variation, duration)


def _process(s: dict[str, Any]) -> dict[str, Any] | None:
    if not s:
        return None
    return {
        "pid": s["pid"],
        "completed": s["completed"],
        "event_loop": s.get("event_loop"),
        "warnings": s.get("warnings", []),
        "loop": s["loop"],
        "inbound": s["node"],
        "grace": s["grace"],
    }


def _energy(fold: _Fold, op: dict[str, Any], to: dict[str, Any]) -> dict[str, Any]:
    """Energy sent and played each way, from each side's summary, and the margins' minima."""
    return {
        "forward": {
            "sent": (op.get("energy") or {}).get("sent"),
            "played": (to.get("energy") or {}).get("played"),
            "min_margin": fold.fwd.minimum() if fold.any_valid else None,
        },
        "backward": {
            "sent": (to.get("energy") or {}).get("sent"),
            "played": (op.get("energy") or {}).get("played"),
            "min_margin": fold.bwd.minimum() if fold.any_valid else None,
        },
    }


def _compare_sim(
    rep: dict[str, Any], logs: _Logs, compare_sim: bool, skip_sim: str | None, traces: tuple[Path, ...]
) -> None:
    """``teleop sim`` with the session's settings beside the real I, or ``sim_skipped`` saying why
    not: the caller's reason, a trace file not given, a third-party or hardware device (said even
    when no sim was asked for)."""
    fold, p = logs.fold, logs.params
    op, to = logs.summaries["operator"], logs.summaries["teleoperator"]
    dt, ticks = p.dt, fold.n
    netem = {"forward": p.netem_forward, "backward": p.netem_backward}
    if compare_sim and skip_sim is not None:  # the caller's reason (a Ctrl-C: end within a second)
        compare_sim = False
        rep["sim_skipped"] = skip_sim
    if compare_sim:
        netem, why = _trace_specs(logs.paths, p, traces)
        if why is not None:
            compare_sim = False
            rep["sim_skipped"] = why
    specs = {r: (rep["devices"][r] or {}).get("spec") for r in ("hsi", "robot")}
    # The sim rebuilds the devices only if they are built-ins: a log file never names a module to import.
    sim_devices = {r: devices.builtin_only(specs[r], r) for r in ("hsi", "robot")}
    # ... and never one that is hardware: a report is offline, only a session touches an arm.
    hardware = [
        f"{r} {specs[r]}" for r in ("hsi", "robot") if sim_devices[r] and devices.is_hardware(specs[r], r)
    ]
    if hardware:
        compare_sim = False
        rep["sim_skipped"] = f"the {' and the '.join(hardware)} is hardware, which the sim never connects to"
    elif any(specs[r] is not None and sim_devices[r] is None for r in specs):
        compare_sim = False
        rep["sim_skipped"] = "a third-party device: the sim rebuilds built-in devices only"
    if compare_sim:
        sim_ticks = min(ticks, fold.sim_ticks)
        sim = run_case(
            SimConfig.of_session(
                p,
                duration=sim_ticks * dt,
                netem_forward=netem["forward"],
                netem_backward=netem["backward"],
                # The allowance each real receiver's playout buffer settled on (its median), so the
                # comparison is like for like: delay costs transparency through the wave loop.
                playout_floor=(_settled_allowance(to, dt), _settled_allowance(op, dt)),
                hsi=sim_devices["hsi"],
                robot=sim_devices["robot"],
            )
        )
        i_sim = sim.summary["I"]
        # A long session is compared over its first SIM_CAP_S: the real I over those ticks.
        i_cmp = fold.i_sim_window * dt
        rep["transparency"].update(
            I_sim=i_sim,
            sim_s=sim_ticks * dt,
            I_over_sim_s=i_cmp,
            relative_difference=abs(i_cmp - i_sim) / i_sim if i_sim else None,
        )
        # The simulation's wire blocks, counted by the same port code: equal counts without impairment.
        rep["sim_wire"] = sim.summary["wire"]
        _replay(rep, fold, p, sim_ticks, sim_devices)


def build(
    log_dir: Path,
    transport: str,
    compare_sim: bool = True,
    skip_sim: str | None = None,
    session: int | None = None,
    traces: tuple[Path, ...] = (),
) -> dict[str, Any]:
    """The report of one session whose two logs are in ``log_dir`` (``session``, or the newest
    with both logs: ``teleop.offline.logfile.find_pair``), from one streamed pass over both.

    Nothing a log says is trusted: the parameters are checked as a hello's are, no path a log names
    is opened (a session over a ``trace FILE`` link is not re-simulated: the report says so), and a
    log whose process was killed (no summary) is reported from its ticks, the summary's figures
    left out (``summary_missing``).  ``traces``: trace files the user names, used by the sim only
    where their SHA-256 is the one a log recorded."""
    logs = _load(log_dir, session)
    fold, p = logs.fold, logs.params
    op, to = logs.summaries["operator"], logs.summaries["teleoperator"]
    both = bool(op) and bool(to)
    dt = p.dt
    ticks = fold.n  # the ticks both logs cover: the session's, or those run until stopped
    phases = fold.phase_summary()
    i_real = phases["all"]["I"]
    rep: dict[str, Any] = {
        "transport": transport,
        "codec": p.codec,
        "architecture": str(p.passivity),
        "scenario": p.scenario,
        "duration_s": p.duration or ticks * dt,
        "until_stopped": p.duration == 0,
        "session": p.session,
        "dof": p.dof,
        "b": p.b,
        "range": p.full_scale,
        "phase": p.phase,
        "logs": {role: path.name for role, path in logs.paths.items()},
        "processes": {role: _process(s) for role, s in (("operator", op), ("teleoperator", to))},
        "handshake": {"rtt_us": op.get("handshake_rtt_us"), "clock_offset_ns": op.get("clock_offset_ns")},
        "wire": {"forward": _wire(op, to), "backward": _wire(to, op)} if both else None,
        "transparency": {"I": i_real, "ticks_compared": phases["all"]["ticks"], **_delay_figures(logs.fold)},
        # Per phase of the scenario (free, foam, wall; ``all``: the run): I per DoF and wire rates.
        "phases": phases,
        # Watchdog figures of each direction, measured by its receiver.
        "passivity": {"forward": _passivity(to), "backward": _passivity(op)} if both else None,
        # What each receiver refused (teleop.session.auth, the watchdog's physical bound), per direction.
        "security": _security(op, to),
        # What each link did, measured at its receiver from sequence numbers and timestamps.
        "link": {"forward": to.get("link_received"), "backward": op.get("link_received")},
        # Each direction's playout buffer, at its receiver: the delay it played at, late payloads.
        "playout": {"forward": to.get("playout"), "backward": op.get("playout")},
        # Sent -> played per direction and the round trip, against the floor of the measured link.
        "latency": latency(
            {"forward": to.get("playout"), "backward": op.get("playout")},
            {"forward": to.get("clock"), "backward": op.get("clock")},
            dt,
        ),
        # Where each receiver saw its peer's packets land on its tick grid (teleop.session.link.phase): the
        # transits, the teleoperator's phase, and any move of tick 0 (a skewed handshake offset).
        "clock": {"forward": to.get("clock"), "backward": op.get("clock")},
        # The data-rate cap of each direction, at its sender, and whether it held on the wire.
        "rate_cap": {"forward": op.get("rate_cap"), "backward": to.get("rate_cap")},
        # Eq. (4): energy into the communication two-port, forward plus backward margin, per tick.
        "two_port_min_energy": fold.min_two_port(),
        # The same on the session clock: every tick's energy in, reported or not (Fold._run).
        "two_port_min_energy_clock": fold.min_two_port_clock(),
        "energy": _energy(fold, op, to),
    }
    missing = [role for role, s in logs.summaries.items() if not s]
    if missing:
        rep["summary_missing"] = missing  # killed before it finished its log: its ticks are reported
    if logs.notes:
        rep["notes"] = logs.notes
    # Each side's device as its own log says (a local choice, see teleop.devices).
    rep["devices"] = {"hsi": op.get("device"), "robot": to.get("device")}
    _compare_sim(rep, logs, compare_sim, skip_sim, traces)
    return rep


def _replay(
    rep: dict[str, Any], fold: _Fold, p: SessionParams, sim_ticks: int, sim_devices: dict[str, str | None]
) -> None:
    """``transparency.replay``: the sim once more with the run's own deliveries (each payload
    taken at the tick the run's receiver took it: ``teleop.offline.sim.deliveries``), so the
    difference a host's stalls made (a payload a tick late: with ``none``, a force spike of about
    ``b v``) is told from a difference in the code, which the replay would still show.

    Exact (to the order of the sums) where no tick was skipped and no payload was taken early (see
    ``taken_early``), over jitter too: the teleoperator's
    iDS/eDS send at the phase the run's record keeps (``send_phase``, its playout target then).  pdp's
    credit follows the lag it measured on the run's clock, which the replay measures on its ticks:
    approximate where the two differ.  A log without ``send_phase`` (written before it was kept)
    replays iDS/eDS at the replay's own target: approximate under jitter.  Not replayed
    when a link lost packets (the logs do not tell a lost payload from one taken with the next, which a
    codec that queues its updates plays differently) or a peer restarted (its sequence numbers start
    again)."""
    links = [rep["link"][d] or {} for d in ("forward", "backward")]
    if any((lk.get("loss") or 0) > 0 for lk in links):
        rep["transparency"]["replay"] = {"skipped": "a link lost packets"}
        return
    if any((e or 0) for e in (fold.fwd.last_epoch, fold.bwd.last_epoch)):
        rep["transparency"]["replay"] = {"skipped": "a peer restarted"}
        return
    sq = {n: np.concatenate(a) if a else np.zeros(0, np.int64) for n, a in fold.seqs.items()}
    fwd, bwd = deliveries(sq["op_tx"], sq["to_rx"]), deliveries(sq["to_tx"], sq["op_rx"])
    ticks = np.arange(len(fwd))
    late, usual = {}, {}  # payloads taken later than the direction's median lag (send to take)
    stalled = {}  # ... of which the sender's loop began the sending tick half a period late or more
    half_us = p.dt * 1e6 / 2
    for d, at, sender_late in (("forward", fwd, sq["op_late_us"]), ("backward", bwd, sq["to_late_us"])):
        lag = (at - ticks)[at >= 0]
        usual[d] = int(np.median(lag)) if lag.size else 0
        taken_late = (at >= 0) & (at - ticks > usual[d])
        late[d] = int(np.count_nonzero(taken_late))
        stalled[d] = int(np.count_nonzero(taken_late & (sender_late >= half_us)))  # (same ticks: one fold)
    never = {d: int(np.count_nonzero(a == NOT_TAKEN)) for d, a in (("forward", fwd), ("backward", bwd))}
    early = dict(zip(("forward", "backward"), taken_early(fwd, bwd), strict=True))
    sim = run_case(
        SimConfig.of_session(
            p,
            duration=sim_ticks * p.dt,
            netem_forward="",  # what the links did is in the deliveries
            netem_backward="",
            # The deliveries are the run's plays, its buffer's delay in them: the replay's buffers
            # release each payload when taken and, with no allowance, keep a target from their
            # transits, which the teleoperator's iDS/eDS send phase follows (the run's own target
            # on a link of constant delay; under jitter, approximated).
            playout="0",
            hsi=sim_devices["hsi"],
            robot=sim_devices["robot"],
            deliveries=(fwd, bwd),
            send_phases=sq["to_phase"],
        )
    )
    i_real, i_rep = rep["transparency"]["I_over_sim_s"], float(sim.summary["I"])
    rep["transparency"]["replay"] = {
        "I": i_rep,
        "relative_difference": abs(i_real - i_rep) / i_rep if i_rep else None,
        "lag_ticks": usual,  # send tick to the tick that took it, the median
        "taken_late": late,  # taken later than that
        "sender_late": stalled,  # ... sent from a tick its loop began half a period late or more
        "taken_early": early,  # before the sim's order of ticks can take it: replayed later
        "never_taken": never,
        "not_sent": {
            "forward": int(np.count_nonzero(fwd == NOT_SENT)),
            "backward": int(np.count_nonzero(bwd == NOT_SENT)),
        },
    }


def write_plots(log_dir: Path, out: Path, rep: dict[str, Any], suffix: str = "") -> list[Path]:
    """signals.png, bandwidth.png, energy.png and loop_timing.png (``signals-SUFFIX.png`` ... with
    a suffix), new files, from the fold's thinned series (every tick of a session up to about two
    minutes; a longer one's every 2nd, 4th, ... tick)."""
    fold = _load(log_dir, rep["session"]).fold
    dt = fold.dt
    files = []
    what = figure_title(rep)
    k, sig = fold.signals.get()
    t = k.astype(np.float64) * dt
    f1 = out / f"signals{suffix}.png"
    phases = {
        n: (float(p["start"]), float(p["end"]))
        for n, p in (rep.get("phases") or {}).items()
        if n != "all" and isinstance(p, dict) and "start" in p and "end" in p
    }
    title = f"{what}: I = {rep['transparency']['I']:.3e}"
    plots.velocity_force(f1, t, sig["v_op"], sig["v_to"], sig["f_op"], sig["f_to"], title, phases)
    files.append(f1)
    f2 = out / f"bandwidth{suffix}.png"
    k, bw = fold.bandwidth.get()
    t = (k + 1).astype(np.float64) * dt  # a window is plotted at its end
    plots.bandwidth(
        f2,
        BANDWIDTH_WINDOW * dt,
        {
            "forward": (t, bw.get("fwd"), bw.get("fwd_base")),
            "backward": (t, bw.get("bwd"), bw.get("bwd_base")),
        },
        f"{what}: bandwidth",
    )
    files.append(f2)
    f4 = out / f"energy{suffix}.png"
    k, en = fold.energy.get()
    plots.energy(
        f4,
        k.astype(np.float64) * dt,
        {
            "forward": (en["fwd_sent"], en["fwd_played"], en["fwd_margin"]),
            "backward": (en["bwd_sent"], en["bwd_played"], en["bwd_margin"]),
        },
        f"{what}: energy",
    )
    files.append(f4)
    f3 = out / f"loop_timing{suffix}.png"
    lateness = {r: late.values() for r, late in fold.lateness.items()}
    plots.timing_histogram(f3, lateness, f"{what}: tick lateness of the two loops")
    files.append(f3)
    return files


def figure_title(rep: dict[str, Any]) -> str:
    """What a figure shows, in its title: codec, architecture, transport and impairment."""
    link = rep.get("link") or {}
    specs = {d: (link.get(d) or {}).get("spec") or "" for d in ("forward", "backward")}
    if not any(specs.values()):
        net = "no impairment"
    elif specs["forward"] == specs["backward"]:
        net = f"netem {specs['forward']}"
    else:
        net = f"netem {specs['forward'] or 'none'} / {specs['backward'] or 'none'}"
    arch = {"wave": "wave variables", "tdpa": "TDPA"}.get(str(rep.get("architecture")), "")
    return ", ".join(x for x in (str(rep.get("codec")), arch, f"over {rep.get('transport')}", net) if x)


def _process_lines(rep: dict[str, Any]) -> list[str]:
    """Each process's loop, then each direction's packets and bytes on the wire."""
    lines: list[str] = []
    for role, pr in rep["processes"].items():
        if pr is None:
            lines.append(
                f"  {role:<12} SUMMARY MISSING: the process did not finish its log (killed?); "
                "the figures below are from the ticks it logged"
            )
            continue
        lp = pr["loop"]
        pe = lp["period_error_us"]
        lines.append(
            f"  {role:<12} pid {pr['pid']:<7} ticks {lp['ticks']:>6}  overruns {lp['overruns']:>3}  "
            f"skipped {lp['skipped']:>3}  period error p50 {pe['p50']:6.1f}  p99 {pe['p99']:7.1f}  "
            f"p99.9 {pe['p999']:7.1f}  max {pe['max']:7.0f} us  CPU {100 * lp['cpu_fraction']:4.1f}%  "
            f"late packets waited for {pr['grace']['waits']}, missed {pr['grace']['missed']}"
            + (f"  host steal {st:.0f} ms" if _plausible_ms(st := lp.get("host_steal_ms")) else "")
            + (
                f"  paced by its device: missed deadlines {lp['missed_deadlines']}"
                if lp.get("device_paced")
                else ""
            )
        )
    for d, w in (rep["wire"] or {}).items():
        lines.append(
            f"  {d:<9} {w['packets']:>6} packets  {w['wire_bytes']:>8} B on the wire "
            f"(baseline {w['baseline_wire_bytes']} B)  compression payload {w['compression_payload']:.2f}:1 "
            f"wire {w['compression_wire']:.2f}:1  min instantaneous (100 ms) "
            f"{w['min_instant_compression_wire']:.2f}:1  received {w['received_packets']}"
        )
    return lines


def _transparency_lines(rep: dict[str, Any]) -> list[str]:
    """I (eq. 7) against the sim's, the replay with this run's deliveries, per phase, I_dc."""
    lines: list[str] = []
    tr = rep["transparency"]
    extra = ""
    if "I_sim" in tr:
        diff = 100 * tr["relative_difference"]
        extra = f"  (teleop sim, same settings: {tr['I_sim']:.4e}; difference {diff:.1f}%)"
        if tr["sim_s"] < rep["duration_s"] - 1e-6:  # float ticks * dt: not a cut
            extra = (
                f"  (over the first {tr['sim_s']:g} s: {tr['I_over_sim_s']:.4e}; teleop sim, same "
                f"settings: {tr['I_sim']:.4e}; difference {diff:.1f}%)"
            )
    lines.append(f"  transparency I = {tr['I']:.4e}{extra}")
    rp = tr.get("replay") or {}
    if "I" in rp:
        tl, nv, lg = rp["taken_late"], rp["never_taken"], rp["lag_ticks"]
        rd = rp["relative_difference"]
        diff = "" if rd is None else f"; difference {100 * rd:.1f}%"
        te = rp.get("taken_early") or {}
        if te.get("forward") or te.get("backward"):  # the replay cannot take those as early
            diff += f" (taken early, replayed later: {te.get('forward', 0)}/{te.get('backward', 0)})"
        sl = rp.get("sender_late")  # (a report of a version before it has none)
        why = f" (sent from a tick half a period late: {sl['forward']}/{sl['backward']})" if sl else ""
        lines.append(
            f"  with this run's deliveries (taken after the median lag of {lg['forward']}/{lg['backward']} "
            f"ticks: {tl['forward']}/{tl['backward']}{why}, never {nv['forward']}/{nv['backward']}, forward/"
            f"backward): teleop sim I = {rp['I']:.4e}{diff}"
        )
    elif "skipped" in rp:
        lines.append(f"  with this run's deliveries: not replayed ({rp['skipped']})")
    if len(rep.get("phases", {})) > 1:
        ran = [f"{n} {b['I']:.4e}" for n, b in rep["phases"].items() if n != "all" and b["ticks"]]
        missed = [n for n, b in rep["phases"].items() if n != "all" and not b["ticks"]]
        lines.append(
            "  per phase: " + "  ".join(ran) + (f"  (not reached: {', '.join(missed)})" if missed else "")
        )
    if "I_dc" in tr:
        dc, drift = tr["delay_compensation_ms"], tr["drift_m"]
        lines.append(
            f"  delay taken out ({dc['forward']:g} / {dc['backward']:g} ms): I_dc = {tr['I_dc']:.4e}  "
            f"HSI-TO drift max {1e3 * drift['max']:.2f} mm, at the end {1e3 * drift['final']:.2f} mm"
        )
    return lines


def _channel_lines(rep: dict[str, Any]) -> list[str]:
    """Each direction's watchdog and link, then its playout buffer."""
    lines: list[str] = []
    for d, pv in (rep["passivity"] or {}).items():
        lk = rep["link"][d]
        delay = lk["delay_ms"]["p50"]  # the median: a skew put right in session leaves early samples
        lines.append(
            f"  watchdog {d:<9} violations {pv['violations']}  "
            f"controller active {pv['controller_active_ticks']} ticks  "
            f"dissipated {pv['energy_dissipated']:.3e} J  min margin {pv['min_margin']:.3e} J  "
            f"link lost {pv['link_lost_events']}x  |  link: loss {100 * lk['loss']:.2f}%  "
            f"delay p50 {_delay(delay)}  reordered {lk['reordered']}  "
            f"duplicates {lk['duplicates']}"
        )
    for d, pl in rep.get("playout", {}).items():
        if pl and pl["mode"] != "off" and pl["delay_ms"]["p50"] is not None:
            dl, ex = pl["delay_ms"], pl.get("extra_ms") or {}
            cost = ""
            if pl["mode"] == "auto" and ex.get("p50") is not None:
                cost = f"; allowance for lateness {ex['p50']:.0f} ms (p50), {ex['p99']:.0f} ms (p99)"
            lines.append(
                f"  playout  {d:<9} {pl['mode']}: released at send tick + {dl['p50']:.0f} ms (p50), "
                f"{dl['p99']:.0f} ms (p99), max {dl['max']:.0f} ms{cost}; late {pl['late']}, "
                f"reordered and put back in order {pl['reordered_fixed']}"
            )
    return lines


def summary_text(rep: dict[str, Any], command: str = "teleop run") -> str:
    """The printed report; its first line names the ``command`` that printed it."""
    lines = [
        f"{command}: {rep['scenario']} scenario, codec {rep['codec']}, {rep['dof']} DoF, "
        f"{rep['duration_s']:g} s over {rep['transport']}"
    ]
    lines += _process_lines(rep)
    lines += _transparency_lines(rep)
    lines += _channel_lines(rep)
    lines += _latency_lines(rep)
    for d, cap in rep.get("rate_cap", {}).items():
        if cap:
            lines.append(
                f"  rate cap {d:<9} {cap['bps'] / 1e3:g} kbit/s: "
                f"at most {cap['limit_bytes_per_window']:.0f} B "
                f"per {cap['window_ms']:g} ms, peak {cap['peak_bytes_per_window']:.0f} B, "
                f"{'held' if cap['held'] else 'NOT held'}; {cap['held_back']} payloads held back"
            )
    sec = rep.get("security", {})
    if sec.get("auth"):
        how = "INSECURE (no key: integrity only)" if sec["auth"] == "insecure" else sec["auth"]
        lines.append(
            f"  security   {how}"
            f"  key {sec['key_id']}  rejected {sec['rejected']['forward']}/{sec['rejected']['backward']}"
            f"  replayed {sec['replayed']['forward']}/{sec['replayed']['backward']}"
            f"  energy reports clamped {sec['energy_reports_clamped']['forward']}/"
            f"{sec['energy_reports_clamped']['backward']}  (forward/backward)"
        )
    robot = (rep.get("devices") or {}).get("robot")
    if robot and (line := devices.describe(robot)) is not None:
        lines.append(f"  {line}")
    e = rep["energy"]
    lines.append(
        f"  energy margin (sent - played) min: forward {_e(e['forward']['min_margin'])} J, "
        f"backward {_e(e['backward']['min_margin'])} J; two-port (eq. 4) {_e(rep['two_port_min_energy'])} J"
        + (
            f", on the session clock {_e(rep['two_port_min_energy_clock'])} J"
            if rep.get("two_port_min_energy_clock") is not None
            else ""
        )
    )
    if "sim_skipped" in rep:
        lines.append(f"  teleop sim not re-run: {rep['sim_skipped']}")
    lines += [f"  note: {n}" for n in rep.get("notes", [])]
    return "\n".join(lines)


def _plausible_ms(x: Any) -> bool:
    """A duration from a log's summary worth printing: a number, not NaN, not negative, under a
    year (the log is a file, and files are not trusted: anything else is left out of the line)."""
    return type(x) in (int, float) and 0 <= x < 3.2e10


def _latency_lines(rep: dict[str, Any]) -> list[str]:
    """Sent -> played per direction, the round trip and its floor; a clock that moved (skew)."""
    lt = rep.get("latency") or {}
    out = []

    def ms(q: dict[str, float | None]) -> str:
        return (
            "-" if q.get("p50") is None else f"p50 {q['p50']:.1f}  p99 {q['p99']:.1f}  max {q['max']:.1f} ms"
        )

    if lt.get("forward") and lt["forward"].get("p50") is not None:
        out.append(f"  latency  forward   sent -> played {ms(lt['forward'])}   backward {ms(lt['backward'])}")
        floor = lt.get("floor_ms")
        link = lt.get("link_round_trip_ms")
        out.append(
            f"  latency  round trip {ms(lt['round_trip'])}"
            + (
                f"  (floor of this link {floor:g} ms: its round trip {link:.2f} ms and processing;"
                f" teleoperator phase {lt['phase']:.2f} of a tick)"
                if floor is not None and link is not None
                else ""
            )
        )
    for d, who in (("forward", "teleoperator"), ("backward", "operator")):
        c = (rep.get("clock") or {}).get(d) or {}
        if c.get("skew_shift_ms"):
            out.append(
                f"  clock    the {who} moved its tick 0 {c['skew_shift_ms']:g} ms earlier in session: its"
                " peer's packets arrived before they were sent (the handshake's offset was skewed,"
                " an asymmetric delay while it ran)"
            )
    return out


def _delay(ms: float | None) -> str:
    """A one-way delay (ms); one below zero is no delay but a clock error, and said so."""
    if ms is None:
        return "- ms"
    return f"{ms:.2f} ms" if ms >= 0 else "below 0 (the clocks' offset is wrong)"


def _e(x: float | None) -> str:
    return "-" if x is None else f"{x:.3e}"
