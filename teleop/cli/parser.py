"""The ``teleop`` parser and ``main``: every error is one line, ``teleop: error: ...``, exit status 2."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence

from teleop.cli import (
    config,
    conformance,
    doctor,
    endpoints,
    experiment,
    export,
    keygen,
    report,
    robots,
    run,
    sim,
    sweep,
)
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
    export.add_parser(sub)
    keygen.add_parser(sub)
    conformance.add_parser(sub)
    doctor.add_parser(sub)
    for name in config.COMMANDS:
        config.add_config_args(sub.choices[name])
    return p


def _commands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(sub.choices)


def main(argv: Sequence[str] | None = None) -> int:
    _local_plugins()
    parser = build_parser()
    commands = _commands(parser)
    try:
        argv = config.expand(sys.argv[1:] if argv is None else argv, commands)
    except (CliError, FileRefused) as e:
        parser.exit(2, f"teleop: error: {one_line(e)}\n")
    args = parser.parse_args(argv)
    if getattr(args, "print_config", False):
        print(config.text(args.command, commands[args.command], argv[1:]), end="")
        return 0
    try:
        rc: int = args.func(args)
    except CliError as e:
        parser.exit(2, f"teleop: error: {one_line(e)}\n")
    except FileRefused as e:  # an output already there, a full disk: teleop.files
        parser.exit(2, f"teleop: error: {one_line(e)}\n")
    except KeyboardInterrupt:
        return 130
    return rc


def _local_plugins() -> None:
    """The current folder at the end of the import path, as ``python -m`` has it at the start: a
    device plug-in there (``--robot mydevices:Arm``) is found without ``PYTHONPATH=.``, and being
    last it never shadows an installed module (numpy, teleop itself)."""
    here = os.getcwd()
    if "" not in sys.path and here not in sys.path:
        sys.path.append(here)
