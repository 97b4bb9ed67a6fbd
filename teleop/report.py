"""Merge the two processes' logs into one report: ``report.json``, PNG plots and a text summary.

Every figure here is read from the logs: bytes counted at the sockets, ticks counted by the loops,
signals recorded by the nodes.  Signals are aligned by tick index (the handshake's common start).
The logs are the processes' ``ROLE.mcap`` files (``transport.mcaplog``: per-tick channels and the
summary), read with the ``mcap`` library; a session without a fixed end is compared with
``teleop sim`` over the ticks both sides actually ran.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from transport.mcaplog import read_log

from . import devices, metrics, plots, scenarios
from .port import wire_block
from .sim import SimConfig, run_case

Array = npt.NDArray[np.float64]


def _load(log_dir: Path, role: str) -> tuple[dict[str, Any], dict[str, Array]]:
    """One process's summary and per-tick arrays (from tick 0), from its ``ROLE.mcap``."""
    path = log_dir / f"{role}.mcap"
    return _read(str(path), path.stat().st_mtime_ns)


@functools.lru_cache(maxsize=2)
def _read(path: str, mtime_ns: int) -> tuple[dict[str, Any], dict[str, Array]]:
    """Read once per file version (the report and the plots both need it)."""
    summary, arrays = read_log(Path(path))
    if not summary:
        raise ValueError(f"{path} has no summary: the process did not finish its log")
    return summary, arrays


def _both(log_dir: Path) -> tuple[dict[str, Any], dict[str, Array], dict[str, Any], dict[str, Array]]:
    """Both processes' logs, their arrays cut to the ticks both sides' logs cover (a session without
    a fixed end stops at a slightly different tick on each side)."""
    op, a_op = _load(log_dir, "operator")
    to, a_to = _load(log_dir, "teleoperator")
    n = min(len(a_op["v"]), len(a_to["v"]))
    cut = {k: v if k == "lateness_ns" else v[:n] for k, v in a_op.items()}
    cut_to = {k: v if k == "lateness_ns" else v[:n] for k, v in a_to.items()}
    return op, cut, to, cut_to


def _wire(sender: dict[str, Any], receiver: dict[str, Any]) -> dict[str, Any]:
    """One direction's wire block from the two processes' port summaries (as ``teleop sim``'s)."""
    return wire_block(sender["sent"], receiver["received"])


def _true_margin(sender: dict[str, Array], receiver: dict[str, Array]) -> Array:
    """Per receiver tick: the energy the sender's own log says it had put into the packets the
    receiver had accepted by then, minus the energy played since the receiver's last energy epoch
    (eq. 5).  Aligned by sequence number, so no clock is trusted: the newest seq accepted by each
    receiver tick is looked up in the sender's log (the survivor's, after a peer restart: only the
    receiver's last epoch is compared).  Older logs without seqs fall back to time alignment."""
    if "rx_seq" not in receiver or "tx_seq" not in sender:
        return _true_margin_by_time(sender, receiver)
    played = receiver["energy_played_epoch"]
    sent_ticks = np.flatnonzero(sender["tx_seq"] >= 0)
    seqs, energy = sender["tx_seq"][sent_ticks], sender["energy_sent"][sent_ticks]
    rx = receiver["rx_seq"]
    idx = np.searchsorted(seqs, rx, side="left")
    found = (rx >= 0) & (idx < seqs.size) & (seqs[np.minimum(idx, max(seqs.size - 1, 0))] == rx)
    sent = np.where(found, energy[np.minimum(idx, max(energy.size - 1, 0))] if energy.size else 0.0, 0.0)
    last_epoch = receiver["peer_epoch"] == receiver["peer_epoch"].max()
    ok = last_epoch & ~np.isnan(played) & ((rx < 0) | found)
    return np.where(ok, sent - played, np.nan)


def _true_margin_by_time(sender: dict[str, Array], receiver: dict[str, Array]) -> Array:
    """Per receiver tick: energy the sender had sent by the instant the receiver played its sample,
    minus energy played so far (eq. 5).  Aligned on the common session clock, not by tick index:
    a receiver tick that waits for a late payload may rightly play a sample the sender produced in
    a *later* tick index."""
    # Played since the receiver's last energy epoch (a restarted peer starts a new one).
    played = receiver.get("energy_played_epoch", receiver["energy_played"])
    if "send_time_s" not in sender or "play_time_s" not in receiver:
        return sender["energy_sent"] - played  # older logs: by tick index
    s_t, r_t = sender["send_time_s"], receiver["play_time_s"]
    ok = ~np.isnan(s_t)
    if not ok.any():
        return np.full(r_t.shape, np.nan)
    s_times, s_energy = s_t[ok], sender["energy_sent"][ok]
    idx = np.searchsorted(s_times, r_t, side="left") - 1  # the sender's last send before the play
    sent = s_energy[np.clip(idx, 0, None)]
    # Before the sender's log begins (it joined late), there is nothing to compare with.
    return np.where(np.isnan(r_t) | (idx < 0), np.nan, sent - played)


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


def _phases(p: dict[str, Any]) -> list[tuple[str, float, float]]:
    """The session's phases from its scenario and seeded plan (older logs: no variation)."""
    return scenarios.get(p["scenario"]).phases(p["seed"], p.get("variation", 0.0), p["duration"])


def build(log_dir: Path, transport: str, compare_sim: bool = True) -> dict[str, Any]:
    op, a_op, to, a_to = _both(log_dir)
    p = op["params"]
    dt = p["dt"]
    ticks = len(a_op["v"])  # the ticks both logs cover: the session's, or those run until stopped
    valid = ~(np.isnan(a_op["v"]).any(axis=1) | np.isnan(a_to["v"]).any(axis=1))
    i_real = metrics.transparency(a_op["v"][valid], a_to["v"][valid], a_op["f"][valid], a_to["f"][valid], dt)
    m_fwd = _true_margin(a_op, a_to)
    m_bwd = _true_margin(a_to, a_op)
    rep: dict[str, Any] = {
        "transport": transport,
        "codec": p["codec"],
        "scenario": p["scenario"],
        "duration_s": p["duration"] or ticks * dt,
        "until_stopped": p["duration"] == 0,
        "session": p["session"],
        "dof": p["dof"],
        "b": p["b"],
        "range": p["full_scale"],
        "phase": p["phase"],
        "processes": {
            role: {
                "pid": s["pid"],
                "completed": s["completed"],
                "event_loop": s.get("event_loop"),
                "warnings": s.get("warnings", []),
                "loop": s["loop"],
                "inbound": s["node"],
                "grace": s["grace"],
            }
            for role, s in (("operator", op), ("teleoperator", to))
        },
        "handshake": {"rtt_us": op.get("handshake_rtt_us"), "clock_offset_ns": op.get("clock_offset_ns")},
        "wire": {"forward": _wire(op, to), "backward": _wire(to, op)},
        "transparency": {"I": i_real, "ticks_compared": int(valid.sum())},
        # Per phase of the scenario (free, foam, wall; ``all``: the run): I per DoF and wire rates.
        "phases": metrics.phase_summary(
            a_op["v"],
            a_to["v"],
            a_op["f"],
            a_to["f"],
            dt,
            _phases(p),
            {"forward": a_op["tx_wire"], "backward": a_to["tx_wire"]},
            valid,
        ),
        # Watchdog figures of each direction, measured by its receiver.
        "passivity": {"forward": _passivity(to), "backward": _passivity(op)},
        # What each receiver refused (teleop.auth, the watchdog's physical bound), per direction.
        "security": _security(op, to),
        # What each link did, measured at its receiver from sequence numbers and timestamps.
        "link": {"forward": to["link_received"], "backward": op["link_received"]},
        # Each direction's playout buffer, at its receiver: the delay it played at, late payloads.
        "playout": {"forward": to.get("playout"), "backward": op.get("playout")},
        # The data-rate cap of each direction, at its sender, and whether it held on the wire.
        "rate_cap": {"forward": op.get("rate_cap"), "backward": to.get("rate_cap")},
        # Eq. (4): energy into the communication two-port, forward plus backward margin, per tick.
        "two_port_min_energy": float(np.nanmin(m_fwd + m_bwd)) if np.isfinite(m_fwd + m_bwd).any() else None,
        "energy": {
            "forward": {
                "sent": op["energy"]["sent"],
                "played": to["energy"]["played"],
                "min_margin": float(np.nanmin(m_fwd)) if valid.any() else None,
            },
            "backward": {
                "sent": to["energy"]["sent"],
                "played": op["energy"]["played"],
                "min_margin": float(np.nanmin(m_bwd)) if valid.any() else None,
            },
        },
    }
    # Each side's device as its own log says (a local choice, see teleop.devices).
    rep["devices"] = {"hsi": op.get("device"), "robot": to.get("device")}
    specs = {r: (rep["devices"][r] or {}).get("spec") for r in ("hsi", "robot")}
    # The sim rebuilds the devices only if they are built-ins: a log file never names a module to import.
    sim_devices = {r: devices.builtin_only(specs[r], r) for r in ("hsi", "robot")}
    if any(specs[r] is not None and sim_devices[r] is None for r in specs):
        compare_sim = False
        rep["sim_skipped"] = "a third-party device: the sim rebuilds built-in devices only"
    if compare_sim:
        sim = run_case(
            SimConfig(
                codec=p["codec"],
                scenario=p["scenario"],
                duration=ticks * dt,
                dof=p["dof"],
                b=p["b"],
                full_scale=p["full_scale"],
                dt=dt,
                netem_forward=p["netem_forward"],
                netem_backward=p["netem_backward"],
                seed=p["seed"],
                on_loss=p["on_loss"],
                controller=p["controller"],
                link_timeout=p["link_timeout"],
                rate_cap=p.get("rate_cap", 0.0),
                playout=p.get("playout", "off"),
                # The allowance each real receiver's playout buffer settled on (its median), so the
                # comparison is like for like: delay costs transparency through the wave loop.
                playout_floor=(_settled_allowance(to, dt), _settled_allowance(op, dt)),
                session=p["session"],  # its size on the wire counts in the byte figures
                hsi=sim_devices["hsi"],
                robot=sim_devices["robot"],
                variation=p.get("variation", 0.0),
            )
        )
        i_sim = sim.summary["I"]
        rep["transparency"].update(
            I_sim=i_sim, relative_difference=abs(i_real - i_sim) / i_sim if i_sim else None
        )
        # The simulation's wire blocks, counted by the same port code: equal counts without impairment.
        rep["sim_wire"] = sim.summary["wire"]
    return rep


def write_plots(log_dir: Path, out: Path, rep: dict[str, Any]) -> list[Path]:
    _, a_op, _, a_to = _both(log_dir)
    dt = 1e-3
    n = a_op["v"].shape[0]
    t = np.arange(n, dtype=np.float64) * dt
    files = []
    f1 = out / "signals.png"
    plots.velocity_force(
        f1,
        t,
        a_op["v"],
        a_to["v"],
        a_op["f"],
        a_to["f"],
        f"{rep['codec']} over {rep['transport']}: I = {rep['transparency']['I']:.3e}",
    )
    files.append(f1)
    f2 = out / "bandwidth.png"
    plots.bandwidth(
        f2,
        dt,
        {
            "forward": (a_op["tx_wire"], a_op["tx_baseline_wire"]),
            "backward": (a_to["tx_wire"], a_to["tx_baseline_wire"]),
        },
        window=100,
    )
    files.append(f2)
    f4 = out / "energy.png"
    plots.energy(
        f4,
        dt,
        {
            "forward": (a_op["energy_sent"], a_to["energy_played"], a_to["energy_margin_observed"]),
            "backward": (a_to["energy_sent"], a_op["energy_played"], a_op["energy_margin_observed"]),
        },
    )
    files.append(f4)
    f3 = out / "loop_timing.png"
    plots.timing_histogram(f3, {"operator": a_op["lateness_ns"], "teleoperator": a_to["lateness_ns"]})
    files.append(f3)
    return files


def summary_text(rep: dict[str, Any]) -> str:
    lines = [
        f"teleop run: {rep['scenario']} scenario, codec {rep['codec']}, {rep['dof']} DoF, "
        f"{rep['duration_s']:g} s over {rep['transport']}"
    ]
    for role, pr in rep["processes"].items():
        lp = pr["loop"]
        pe = lp["period_error_us"]
        lines.append(
            f"  {role:<12} pid {pr['pid']:<7} ticks {lp['ticks']:>6}  overruns {lp['overruns']:>3}  "
            f"skipped {lp['skipped']:>3}  period error p50 {pe['p50']:6.1f}  p99 {pe['p99']:7.1f}  "
            f"p99.9 {pe['p999']:7.1f}  max {pe['max']:7.0f} us  CPU {100 * lp['cpu_fraction']:4.1f}%  "
            f"late packets waited for {pr['grace']['waits']}, missed {pr['grace']['missed']}"
        )
    for d, w in rep["wire"].items():
        lines.append(
            f"  {d:<9} {w['packets']:>6} packets  {w['wire_bytes']:>8} B on the wire "
            f"(baseline {w['baseline_wire_bytes']} B)  compression payload {w['compression_payload']:.2f}:1 "
            f"wire {w['compression_wire']:.2f}:1  min instantaneous (100 ms) "
            f"{w['min_instant_compression_wire']:.2f}:1  received {w['received_packets']}"
        )
    tr = rep["transparency"]
    extra = ""
    if "I_sim" in tr:
        diff = 100 * tr["relative_difference"]
        extra = f"  (teleop sim, same settings: {tr['I_sim']:.4e}; difference {diff:.1f}%)"
    lines.append(f"  transparency I = {tr['I']:.4e}{extra}")
    if len(rep.get("phases", {})) > 1:
        ran = [f"{n} {b['I']:.4e}" for n, b in rep["phases"].items() if n != "all" and b["ticks"]]
        missed = [n for n, b in rep["phases"].items() if n != "all" and not b["ticks"]]
        lines.append(
            "  per phase: " + "  ".join(ran) + (f"  (not reached: {', '.join(missed)})" if missed else "")
        )
    for d, pv in rep["passivity"].items():
        lk = rep["link"][d]
        delay = lk["delay_ms"]["mean"]
        lines.append(
            f"  watchdog {d:<9} violations {pv['violations']}  "
            f"controller active {pv['controller_active_ticks']} ticks  "
            f"dissipated {pv['energy_dissipated']:.3e} J  min margin {pv['min_margin']:.3e} J  "
            f"link lost {pv['link_lost_events']}x  |  link: loss {100 * lk['loss']:.2f}%  "
            f"delay {'-' if delay is None else f'{delay:.2f}'} ms  reordered {lk['reordered']}  "
            f"duplicates {lk['duplicates']}"
        )
    for d, pl in rep.get("playout", {}).items():
        if pl and pl["mode"] != "off" and pl["delay_ms"]["p50"] is not None:
            dl = pl["delay_ms"]
            lines.append(
                f"  playout  {d:<9} {pl['mode']}: played at send + {dl['p50']:.0f} ms (p50), "
                f"{dl['p99']:.0f} ms (p99), max {dl['max']:.0f} ms; late {pl['late']}, "
                f"reordered and put back in order {pl['reordered_fixed']}"
            )
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
        f"  energy margin (sent - played) min: forward {e['forward']['min_margin']:.3e} J, "
        f"backward {e['backward']['min_margin']:.3e} J; two-port (eq. 4) {rep['two_port_min_energy']:.3e} J"
    )
    return "\n".join(lines)
