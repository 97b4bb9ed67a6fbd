"""``teleop sim``: both nodes in virtual time, one case per codec, a table and optional results."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from teleop.cli.args import (
    CliError,
    Subcommands,
    add_device_args,
    add_model_args,
    add_netem_args,
    add_passivity_args,
    codec_set,
    nonneg_float,
)
from teleop.cli.settings import check_duration, fresh_out, private_dir, sim_config
from teleop.control.codecs import ACCEPTED, CodecError
from teleop.devices import describe
from teleop.devices.scenarios import SCENARIOS
from teleop.files import write_new


def codec_width(cases: list[dict[str, Any]]) -> int:
    """The codec column's width: 10, or the longest spec (pdr's self-credit specs are longer)."""
    return max([10, *(len(c["codec"]) for c in cases)])


def format_table(cases: list[dict[str, Any]]) -> str:
    w = codec_width(cases)
    head = (
        f"{'codec':<{w}} {'I':>11} {'I_norm':>7} {'c:1':>7} {'min c:1':>8} {'passive':>8} "
        f"{'min margin J':>13}"
    )
    lines = [head, "-" * len(head)]
    for c in cases:
        lines.append(
            f"{c['codec']:<{w}} {c['I']:>11.4e} {c['I_norm']:>7.3f} {c['compression']:>7.2f} "
            f"{c['min_instant_compression']:>8.2f} {'yes' if c['passive'] else 'NO':>8} "
            f"{c['min_energy_margin']:>13.3e}"
        )
    return "\n".join(lines)


def format_phases(cases: list[dict[str, Any]]) -> str:
    """Per case: I of each phase of the scenario (free, foam, wall) next to the whole run's; a
    phase the run did not reach (shorter than the scenario) shows "-", not an I of 0."""
    w = codec_width(cases)
    names = [n for n in cases[0]["phases"] if n != "all"] if cases else []
    head = f"{'codec':<{w}} " + " ".join(f"{'I ' + n:>11}" for n in names) + f" {'I all':>11}"
    lines = [head, "-" * len(head)]
    for c in cases:
        ph = c["phases"]
        cells = [f"{ph[n]['I']:>11.4e}" if ph[n]["ticks"] else f"{'-':>11}" for n in [*names, "all"]]
        lines.append(f"{c['codec']:<{w}} " + " ".join(cells))
    return "\n".join(lines)


def format_watchdog(cases: list[dict[str, Any]]) -> str:
    """Per case and direction: what the link did (observed) and what the watchdog saw and did."""
    w = codec_width(cases)
    lines = [
        f"{'codec':<{w}} {'dir':<9} {'loss %':>7} {'delay ms':>9} {'reord':>6} {'dup':>5} "
        f"{'violations':>10} {'ctrl ticks':>10} {'dissipated J':>12} {'lost':>5}"
    ]
    for c in cases:
        for d in ("forward", "backward"):
            lk, pv = c["link"][d], c["passivity"][d]
            delay = "-" if lk["delay_ms"]["mean"] is None else f"{lk['delay_ms']['mean']:.2f}"
            lines.append(
                f"{c['codec']:<{w}} {d:<9} {100 * lk['loss']:>7.2f} {delay:>9} {lk['reordered']:>6} "
                f"{lk['duplicates']:>5} {pv['violations']:>10} {pv['controller_active_ticks']:>10} "
                f"{pv['energy_dissipated']:>12.3e} {pv['link_lost_events']:>5}"
            )
    return "\n".join(lines)


def format_distortion(cases: list[dict[str, Any]]) -> str:
    """Per case: eq. (7) next to its delay-compensated form, the HSI-TO drift and the energy the
    passivity controllers dissipated (what separates delay from distortion)."""
    w = codec_width(cases)
    head = (
        f"{'codec':<{w}} {'I':>11} {'I_dc':>11} {'shift ms':>9} {'drift max mm':>12} "
        f"{'drift end mm':>12} {'dissipated J':>12} {'peak F hsi/to N':>15}"
    )
    lines = [head, "-" * len(head)]
    for c in cases:
        sh = c["delay_compensation_ms"]
        shift = f"{sh['forward']:g}/{sh['backward']:g}"
        peak = f"{c['peak_force_N']['hsi']:.2f}/{c['peak_force_N']['to']:.2f}"
        lines.append(
            f"{c['codec']:<{w}} {c['I']:>11.4e} {c['I_dc']:>11.4e} {shift:>9} "
            f"{1e3 * c['drift_m']['max']:>12.3f} {1e3 * c['drift_m']['final']:>12.3f} "
            f"{c['energy_dissipated']['total']:>12.3e} {peak:>15}"
        )
    return "\n".join(lines)


def format_latency(cases: list[dict[str, Any]]) -> str:
    """Per case: sent -> played each way and the round trip (p50/p99 ms), against the link's floor
    (``teleop.session.link.phase.latency``: the same figures as a real run's report)."""
    head = f"{'codec':<10} {'forward ms':>12} {'backward ms':>12} {'round trip ms':>14} {'floor ms':>9}"
    lines = [head, "-" * len(head)]

    def pair(q: dict[str, float | None]) -> str:
        return "-" if q["p50"] is None or q["p99"] is None else f"{q['p50']:.1f}/{q['p99']:.1f}"

    for c in cases:
        lt = c["latency"]
        floor = "-" if lt["floor_ms"] is None else f"{lt['floor_ms']:g}"
        lines.append(
            f"{c['codec']:<10} {pair(lt['forward']):>12} {pair(lt['backward']):>12} "
            f"{pair(lt['round_trip']):>14} {floor:>9}"
        )
    return "\n".join(lines)


def format_tdpa(cases: list[dict[str, Any]]) -> str:
    """Per case and direction: TDPA's observer (energy in at the sender, out at the receiver) and
    its controller (active ticks, dissipated energy)."""
    cw = codec_width(cases)
    head = (
        f"{'codec':<{cw}} {'dir':<9} {'E_in J':>11} {'E_out J':>11} {'min margin J':>13} "
        f"{'ctrl ticks':>10} {'dissipated J':>12}"
    )
    lines = [head, "-" * len(head)]
    for c in cases:
        for d in ("forward", "backward"):
            w = c["tdpa"][d]
            lines.append(
                f"{c['codec']:<{cw}} {d:<9} {w['energy_in']:>11.4e} {w['energy_out']:>11.4e} "
                f"{w['min_margin']:>13.3e} {w['controller_active_ticks']:>10} {w['energy_dissipated']:>12.3e}"
            )
    return "\n".join(lines)


def _write_results(out: Path, doc: dict[str, Any], cases: list[Any]) -> None:
    """OUT/results.json and one PNG of velocities and forces per case."""
    from teleop.offline import plots

    write_new(out / "results.json", (json.dumps(doc, indent=2) + "\n").encode())
    for c, dc in zip(cases, doc["cases"], strict=True):
        tr = c.trace
        phases = {n: (p["start"], p["end"]) for n, p in dc["phases"].items() if n != "all" and "start" in p}
        plots.velocity_force(
            out / f"{plots.safe_name(c.codec)}.png",
            tr.t,
            tr.v_hsi,
            tr.v_to,
            tr.f_hsi,
            tr.f_to,
            f"{c.codec}, {_arch(doc)}, teleop sim, {_impairment(doc)}: I = {c.summary['I']:.3e}, "
            f"c = {c.summary['compression']:.3g}:1",
            phases,
        )
    print(f"wrote {out / 'results.json'} and {len(cases)} PNG plots")


def _arch(doc: dict[str, Any]) -> str:
    return "TDPA" if str(doc.get("passivity")) == "tdpa" else "wave variables"


def _impairment(doc: dict[str, Any]) -> str:
    """The run's links, for a figure's title."""
    net = doc.get("netem") or {}
    fwd, bwd = net.get("forward") or "", net.get("backward") or ""
    if not fwd and not bwd:
        return "no impairment"
    return f"netem {fwd}" if fwd == bwd else f"netem {fwd or 'none'} / {bwd or 'none'}"


def cmd_sim(args: argparse.Namespace) -> int:
    from teleop.offline.sim import SECTION_V_CODECS, run_set

    sc = SCENARIOS[args.scenario]
    duration = args.duration if args.duration is not None else sc.duration
    check_duration(duration, args.dof if args.dof is not None else sc.dof, in_memory=True)
    out = private_dir(Path(args.out), "--out") if args.out is not None else None
    if out is not None:
        fresh_out(out, ["results.json"])
    codecs = list(dict.fromkeys(args.codec or SECTION_V_CODECS))
    base = sim_config(args)
    assert base.b is not None and base.full_scale is not None  # sim_config fills both from the scenario
    try:
        doc, cases = run_set(codecs, base)
    except (ValueError, CodecError, OSError) as e:
        raise CliError(str(e)) from None
    print(
        f"teleop sim: scenario {base.scenario}, {base.dof} DoF, b = {base.b:g}, delay {base.delay_ms:g} ms, "
        f"{base.duration:g} s at {1 / base.dt:g} Hz, wave range +-{base.full_scale:g}"
    )
    if base.tdpa:
        from teleop.session.port import power_ranges

        v_fs, f_fs = power_ranges(base.full_scale, base.b)
        print(f"passivity tdpa: velocity range +-{v_fs:.4g} m/s forward, force range +-{f_fs:.4g} N back")
    impaired = bool(base.netem_forward or base.netem_backward)
    if impaired:
        print(
            f"netem forward: {base.netem_forward or '-'}   backward: {base.netem_backward or '-'}   "
            f"seed {base.seed}"
        )
    print(format_table(doc["cases"]))
    for c in doc["cases"]:
        if (line := describe(c["devices"]["robot"])) is not None:
            print(f"{c['codec']:<{codec_width(doc['cases'])}} {line}")
    if len(doc["cases"][0]["phases"]) > 1:
        print(format_phases(doc["cases"]))
    if impaired or base.on_loss != "conceal" or not base.controller:
        print(format_watchdog(doc["cases"]))
    print(format_distortion(doc["cases"]))
    print(format_latency(doc["cases"]))
    if base.tdpa:
        print(format_tdpa(doc["cases"]))
    if out is not None:
        _write_results(out, doc, cases)
    return 0 if all(c["passive"] for c in doc["cases"]) else 1


def add_parser(sub: Subcommands) -> None:
    s = sub.add_parser(
        "sim",
        help="deterministic virtual-time run of both nodes (paper Section V)",
        description="Run the operator and teleoperator nodes in virtual time joined by a "
        "channel with constant delay; print a table and optionally write results.json "
        "and plots. Exit status 1 if any case lost passivity.",
    )
    s.add_argument(
        "--codec",
        action="extend",
        type=codec_set,
        metavar="SPEC",
        help="codec, repeatable; a set preset (paper) adds each of its codecs (default: the paper's set). "
        f"Accepted: {ACCEPTED}",
    )
    s.add_argument(
        "--delay",
        type=nonneg_float("delay"),
        default=0.0,
        metavar="MS",
        help="one-way delay per direction in ms (default 0)",
    )
    add_model_args(s, "step")
    add_device_args(s, ("hsi", "robot"))
    add_netem_args(s)
    add_passivity_args(s)
    s.add_argument("--out", metavar="DIR", help="write DIR/results.json and one PNG per codec")
    s.set_defaults(func=cmd_sim)
