"""The ``teleop`` parser and ``main``: every error is one line, ``teleop: error: ...``, exit status 2."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from teleop.cli import conformance, endpoints, experiment, keygen, report, robots, run, sim, sweep
from teleop.cli.args import CliError, Parser, one_line
from teleop.files import FileRefused


def build_parser() -> argparse.ArgumentParser:
    p = Parser(prog="teleop", description="Networked haptic teleoperation with passive LDR.")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    sim.add_parser(sub)
    sweep.add_parser(sub)
    experiment.add_parser(sub)
    run.add_parser(sub)
    endpoints.add_operator_parser(sub)
    endpoints.add_teleoperator_parser(sub)
    endpoints.add_router_parser(sub)
    robots.add_parser(sub)
    report.add_parser(sub)
    keygen.add_parser(sub)
    conformance.add_parser(sub)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        rc: int = args.func(args)
    except CliError as e:
        parser.exit(2, f"teleop: error: {one_line(e)}\n")
    except FileRefused as e:  # an output already there, a full disk: teleop.files
        parser.exit(2, f"teleop: error: {one_line(e)}\n")
    except KeyboardInterrupt:
        return 130
    return rc
