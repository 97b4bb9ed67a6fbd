"""The ``teleop`` command."""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .codecs import ACCEPTED, CodecError, make_codec
from .scenarios import SCENARIOS


class CliError(Exception):
    """A bad argument: printed as ``teleop: error: ...`` with exit status 2."""


def _positive_float(what: str) -> Any:
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a number, got {text!r}") from None
        if not math.isfinite(v) or v <= 0:
            raise argparse.ArgumentTypeError(f"{what} must be > 0, got {text!r}")
        return v

    return parse


def _nonneg_float(what: str) -> Any:
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be a number, got {text!r}") from None
        if not math.isfinite(v) or v < 0:
            raise argparse.ArgumentTypeError(f"{what} must be >= 0, got {text!r}")
        return v

    return parse


def _dof(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"DoF must be an integer 1..64, got {text!r}") from None
    if not 1 <= v <= 64:
        raise argparse.ArgumentTypeError(f"DoF must be an integer 1..64, got {text!r}")
    return v


def _codec(text: str) -> str:
    try:
        return make_codec(text).spec
    except CodecError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def format_table(cases: list[dict[str, Any]]) -> str:
    head = (
        f"{'codec':<10} {'I':>11} {'I_norm':>7} {'c:1':>7} {'min c:1':>8} {'passive':>8} {'min margin J':>13}"
    )
    lines = [head, "-" * len(head)]
    for c in cases:
        lines.append(
            f"{c['codec']:<10} {c['I']:>11.4e} {c['I_norm']:>7.3f} {c['compression']:>7.2f} "
            f"{c['min_instant_compression']:>8.2f} {'yes' if c['passive'] else 'NO':>8} "
            f"{c['min_energy_margin']:>13.3e}"
        )
    return "\n".join(lines)


def cmd_sim(args: argparse.Namespace) -> int:
    from . import plots
    from .sim import SECTION_V_CODECS, SimConfig, run_set

    codecs = args.codec or list(SECTION_V_CODECS)
    try:
        base = SimConfig(
            delay_ms=args.delay,
            duration=args.duration,
            dof=args.dof,
            b=args.b,
            full_scale=args.range,
            scenario=args.scenario,
        ).resolved()
        doc, cases = run_set(codecs, base)
    except (ValueError, CodecError) as e:
        raise CliError(str(e)) from None
    print(
        f"teleop sim: scenario {base.scenario}, {base.dof} DoF, b = {base.b:g}, delay {base.delay_ms:g} ms, "
        f"{base.duration:g} s at {1 / base.dt:g} Hz, wave range +-{base.full_scale:g}"
    )
    print(format_table(doc["cases"]))
    if args.out is not None:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "results.json").write_text(json.dumps(doc, indent=2) + "\n")
        for c in cases:
            tr = c.trace
            plots.velocity_force(
                out / f"{plots.safe_name(c.codec)}.png",
                tr.t,
                tr.v_hsi,
                tr.v_to,
                tr.f_hsi,
                tr.f_to,
                f"{c.codec}: I = {c.summary['I']:.3e}, c = {c.summary['compression']:.3g}:1",
            )
        print(f"wrote {out / 'results.json'} and {len(cases)} PNG plots")
    return 0 if all(c["passive"] for c in doc["cases"]) else 1


def _add_model_args(p: argparse.ArgumentParser) -> None:
    """Scenario and model options shared by every command that runs the nodes."""
    p.add_argument(
        "--scenario",
        choices=list(SCENARIOS),
        default="step",
        help="step (Section V) or protocol (Section VI); default step",
    )
    p.add_argument(
        "--duration",
        type=_positive_float("duration"),
        default=None,
        metavar="S",
        help="seconds to run (default: the scenario's, 5 for step, 15 for protocol)",
    )
    p.add_argument("--dof", type=_dof, default=None, help="degrees of freedom (default: the scenario's)")
    p.add_argument(
        "--b",
        type=_positive_float("wave impedance b"),
        default=None,
        help="wave impedance b > 0, N s/m (default: the scenario's, 1 for step, 20 for protocol)",
    )
    p.add_argument(
        "--range",
        type=_positive_float("range"),
        default=None,
        metavar="R",
        help="full scale of the raw 16-bit wave format, sqrt(W) (default: the scenario's)",
    )


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="teleop", description="Networked haptic teleoperation with passive LDR.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser(
        "sim",
        help="deterministic virtual-time run of both nodes (paper Section V)",
        description="Run the operator and teleoperator nodes in virtual time joined by a "
        "channel with constant delay; print a table and optionally write results.json "
        "and plots. Exit status 1 if any case lost passivity.",
    )
    s.add_argument(
        "--codec",
        action="append",
        type=_codec,
        metavar="SPEC",
        help=f"codec, repeatable (default: the paper's set). Accepted: {ACCEPTED}",
    )
    s.add_argument(
        "--delay",
        type=_nonneg_float("delay"),
        default=0.0,
        metavar="MS",
        help="one-way delay per direction in ms (default 0)",
    )
    _add_model_args(s)
    s.add_argument("--out", metavar="DIR", help="write DIR/results.json and one PNG per codec")
    s.set_defaults(func=cmd_sim)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        rc: int = args.func(args)
    except CliError as e:
        parser.exit(2, f"teleop: error: {e}\n")
    except KeyboardInterrupt:
        return 130
    return rc


if __name__ == "__main__":
    sys.exit(main())
