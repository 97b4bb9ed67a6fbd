"""``teleop report``: one report from both processes' logs; also how ``teleop run`` writes its own."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from .args import CliError, Subcommands
from .settings import writable_dir

LOG_FILES = [f"{role}.mcap" for role in ("operator", "teleoperator")]


def write_report(
    logs: Path, out: Path, args: argparse.Namespace, transport: str, extra: dict[str, Any] | None = None
) -> None:
    """Build the report from LOGS, add ``extra``, write OUT/report.json and the plots, print a summary."""
    from .. import report as session_report

    rep = session_report.build(logs, transport, compare_sim=not args.no_sim)
    rep.update(extra or {})
    (out / "report.json").write_text(json.dumps(rep, indent=2) + "\n")
    files = [] if args.no_plots else session_report.write_plots(logs, out, rep)
    print(session_report.summary_text(rep))
    print(f"wrote {out / 'report.json'}" + (f" and {', '.join(f.name for f in files)}" if files else ""))


def cmd_report(args: argparse.Namespace) -> int:
    """Build the report of a session from both processes' logs (for example copied from two hosts)."""
    logs = Path(args.logs)
    missing = [name for name in LOG_FILES if not (logs / name).exists()]
    if missing:
        raise CliError(f"{logs} lacks {', '.join(missing)}: pass the folder both processes wrote with --log")
    # Not a directory, a FIFO (which would block the read) or a device: only files are opened.
    odd = [name for name in LOG_FILES if not (logs / name).is_file()]
    if odd:
        raise CliError(f"{', '.join(str(logs / n) for n in odd)}: not a regular file (a log is one)")
    out = writable_dir(Path(args.out) if args.out else logs.parent, "--out")
    from teleop.logfile import LogError

    try:
        write_report(logs, out, args, args.transport)
    except LogError as e:
        raise CliError(f"cannot build the report: {e}") from None
    return 0


def add_parser(sub: Subcommands) -> None:
    rp = sub.add_parser(
        "report",
        help="build a report from the two processes' logs",
        description="Merge operator.mcap and teleoperator.mcap (written with --log) "
        "into report.json, plots and a printed summary.",
    )
    rp.add_argument("logs", metavar="LOGDIR", help="folder holding both processes' logs")
    rp.add_argument("--out", metavar="DIR", help="report folder (default: LOGDIR's parent)")
    rp.add_argument(
        "--transport",
        default="udp",
        choices=("udp", "zenoh"),
        help="the transport the session ran over, recorded in the report (default udp)",
    )
    rp.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    rp.add_argument("--no-sim", action="store_true", help="skip the teleop sim comparison")
    rp.set_defaults(func=cmd_report)
