"""The ``teleop`` parser and ``main``: every error is one line, ``teleop: error: ...``, exit status 2."""

from __future__ import annotations

import argparse
from collections.abc import Sequence

from ..files import FileRefused
from . import conformance, endpoints, experiment, keygen, report, run, sim, sweep
from .args import CliError, Parser

#: Control characters (C0, DEL, C1) shown escaped: a file name or a log's text in an error must
#: keep it one line, and must not drive the terminal (an escape sequence in a planted file's name).
_CONTROL = {c: f"\\x{c:02x}" for c in (*range(0x20), *range(0x7F, 0xA0))}


def one_line(text: object) -> str:
    """``text`` with every control character escaped (newlines too): what an error prints."""
    return str(text).translate(_CONTROL)


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
