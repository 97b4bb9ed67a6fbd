"""``teleop report``: one report from both processes' logs; also how ``teleop run`` writes its own."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
from typing import Any

from teleop.cli.args import CliError, Subcommands, add_verdict_args, session_id, verdict_bounds
from teleop.cli.settings import private_dir
from teleop.session.verdict import judge_report

#: What a log whose summary was edited or damaged can raise while the report reads it: one line.
_DAMAGE = (KeyError, TypeError, ValueError, ArithmeticError, IndexError, AttributeError)


def write_report(
    logs: Path,
    out: Path,
    args: argparse.Namespace,
    transport: str,
    extra: dict[str, Any] | None = None,
    session: int | None = None,
    command: str = "teleop report",
    skip_sim: str | None = None,
) -> dict[str, Any]:
    """Build the report of ``session`` (default: the newest pair) from LOGS, add ``extra``, write
    OUT/report-SESSION.json (a new file, never over one), then OUT/report.json and the plots as
    the newest report's, print a summary.  Any damage in
    the logs, or a report.json already there, is a :class:`CliError` (one line).  Returns the report."""
    from teleop.cli.args import one_line
    from teleop.files import FileRefused
    from teleop.offline import report as session_report
    from teleop.offline.logfile import LogError

    try:
        traces = tuple(Path(t) for t in getattr(args, "trace", None) or ())
        rep = session_report.build(
            logs, transport, compare_sim=not args.no_sim, session=session, traces=traces, skip_sim=skip_sim
        )
        rep.update(extra or {})
        text = session_report.summary_text(rep, command)
    except LogError as e:
        raise CliError(f"cannot build the report: {e}") from None
    except FileRefused as e:  # a --trace file that is not a regular file of bounded size
        raise CliError(str(e)) from None
    except _DAMAGE as e:  # a summary that is not what this stack writes (edited, another version)
        raise CliError(
            "cannot build the report: a log's summary is not what this stack writes "
            f"({type(e).__name__}: {e})"
        ) from None
    sid, body = rep["session"], json.dumps(rep, indent=2) + "\n"
    kept = _write_new(out, [f"report-{sid}.json", *(f"report-{sid}-{i}.json" for i in range(2, 100))], body)
    # report.json and the plots are always the newest report's (a second run into one folder used
    # to leave report.json the first run's): each is a new file moved over the old name, never
    # written through it; every report is also kept under its session's name.
    latest = _write_new(out, [f".report-{sid}.json.new"], body)
    files = [] if args.no_plots else session_report.write_plots(logs, out, rep, f".{sid}.new")
    try:
        os.replace(latest, out / "report.json")
        plots = [f.with_name(f.name.replace(f".{sid}.new", "")) for f in files]
        for new, plot in zip(files, plots, strict=True):
            os.replace(new, plot)
    except OSError as e:
        raise CliError(f"cannot write {out / 'report.json'}: {e.strerror or e}") from None
    # Text a log holds (a warning, a device name, a file's name) is shown with its control
    # characters escaped: a hostile log cannot drive the terminal.
    print("\n".join(one_line(line) for line in text.split("\n")))
    print(
        f"wrote {out / 'report.json'} (also kept as {kept.name})"
        + (f" and {', '.join(f.name for f in plots)}" if files else "")
    )
    return rep


def _write_new(out: Path, names: list[str], text: str) -> Path:
    """``text`` in the first of ``names`` that is free in ``out`` (created with O_EXCL|O_NOFOLLOW:
    an earlier report is never overwritten, a planted symlink never followed)."""
    from teleop.files import create_new, is_exists

    for name in names:
        path = out / name
        try:
            fd = create_new(path)
        except OSError as e:
            if is_exists(e):
                continue
            raise CliError(f"cannot write {path}: {e.strerror or e}") from None
        try:
            with os.fdopen(fd, "w") as f:
                f.write(text)
        except OSError as e:
            raise CliError(f"cannot write {path}: {e.strerror or e}") from None
        return path
    raise CliError(
        f"{out} already holds {' and '.join(names)}: a report is never overwritten (another --out)"
    )


def cmd_report(args: argparse.Namespace) -> int:
    """Build the report of a session from both processes' logs (for example copied from two hosts)."""
    logs = Path(args.logs)
    if not logs.is_dir():
        raise CliError(f"{logs}: not a folder: pass the folder both processes wrote with --log")
    out = private_dir(Path(args.out) if args.out else logs.parent, "--out")
    rep = write_report(logs, out, args, args.transport, session=args.session)
    verdict = judge_report(rep, verdict_bounds(args))
    print(verdict.line("teleop report"))
    return verdict.exit_status


def add_parser(sub: Subcommands) -> None:
    rp = sub.add_parser(
        "report",
        help="build a report from the two processes' logs",
        description="Merge operator.mcap and teleoperator.mcap (written with --log) "
        "into report.json, plots and a printed summary, ending in a verdict: ok, or poor and why "
        "(exit status 3; see --poor-share).",
    )
    rp.add_argument("logs", metavar="LOGDIR", help="folder holding both processes' logs")
    rp.add_argument("--out", metavar="DIR", help="report folder (default: LOGDIR's parent)")
    rp.add_argument(
        "--transport",
        default="udp",
        choices=("udp", "zenoh"),
        help="the transport the session ran over, recorded in the report (default udp)",
    )
    rp.add_argument(
        "--session",
        type=session_id,
        default=None,
        metavar="ID",
        help="the session to report when LOGDIR holds several (default: the newest with both logs)",
    )
    rp.add_argument(
        "--trace",
        action="append",
        metavar="FILE",
        help="a trace file the session's 'trace FILE' link used (repeatable): the sim is re-run with "
        "it if its SHA-256 is the one the logs recorded (a log's path is never opened)",
    )
    add_verdict_args(rp)
    rp.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    rp.add_argument("--no-sim", action="store_true", help="skip the teleop sim comparison")
    rp.set_defaults(func=cmd_report)
