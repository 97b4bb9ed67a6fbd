"""``teleop export``: sessions' logs as a dataset for robot learning (LeRobot v3.0)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from teleop.cli.args import CliError, Subcommands, int_range, one_line, session_id
from teleop.cli.settings import private_dir

MAX_LOG_DIRS = 10_000  # sessions in one export


def task_text(text: str) -> str:
    """A task description: one line of at most MAX_TASK_CHARS printable characters."""
    from teleop.offline.lerobot import MAX_TASK_CHARS

    if not text.strip() or len(text) > MAX_TASK_CHARS or not text.isprintable():
        raise argparse.ArgumentTypeError(
            f"a task is one line of 1 to {MAX_TASK_CHARS} printable characters, got {one_line(text)[:60]!r}"
        )
    return text


def cmd_export(args: argparse.Namespace) -> int:
    """Read each LOGDIR's session as an episode and write the dataset; one line per note."""
    from teleop.files import FileRefused
    from teleop.offline import lerobot
    from teleop.offline.logfile import LogError

    logs = [Path(p) for p in args.logs]
    if len(logs) > MAX_LOG_DIRS:
        raise CliError(f"{len(logs)} log folders: at most {MAX_LOG_DIRS} in one export")
    tasks = args.task or []
    if len(tasks) not in (0, 1, len(logs)):
        raise CliError(
            f"{len(tasks)} --task for {len(logs)} log folders: give one (every episode's), or one per "
            "LOGDIR in their order"
        )
    for d in logs:
        if not d.is_dir():
            raise CliError(f"{d}: not a folder: pass the folders the sessions wrote with --log")
    out = Path(args.out)
    private_dir(out.absolute().parent, "--out")
    started, cpu = time.perf_counter(), time.process_time()
    episodes, texts, dirs = [], [], []
    try:
        for i, d in enumerate(logs):
            for ep in lerobot.read_episodes(d, args.fps, args.session):  # a rejoin: its segments too
                episodes.append(ep)
                dirs.append(d)
                texts.append(tasks[i] if len(tasks) > 1 else tasks[0] if tasks else f"{ep.scenario} scenario")
        notes: list[str] = []
        info = lerobot.export(episodes, texts, out, args.fps, notes)
    except (LogError, lerobot.ExportError, FileRefused) as e:
        raise CliError(f"cannot export: {e}") from None
    except OSError as e:
        raise CliError(f"cannot export into {out}: {e.strerror or e}") from None
    # The wall time, and the CPU it took (every thread): on a shared host the second is the work.
    took, took_cpu = time.perf_counter() - started, time.process_time() - cpu
    for d, ep in zip(dirs, episodes, strict=True):
        for note in ep.notes:
            print(one_line(f"note: {d}: {note}"))
    for note in notes:
        print(one_line(f"note: {note}"))
    seconds = sum(next(iter(ep.ticks.values())).shape[0] * ep.dt for ep in episodes)
    win = round(1 / (args.fps * episodes[0].dt))
    print(
        f"teleop export: {info['total_episodes']} episode(s), {info['total_frames']} frames at "
        f"{args.fps} fps ({win} samples a frame, {seconds:.1f} s of session) into {out} "
        f"(LeRobot {info['codebase_version']}) in {took:.2f} s (CPU {took_cpu:.2f} s); load it with "
        f"LeRobotDataset('local/{out.name}', root='{out}')"
    )
    return 0


def add_parser(sub: Subcommands) -> None:
    ep = sub.add_parser(
        "export",
        help="export sessions' logs as a LeRobot dataset",
        description="Each LOGDIR's session (its operator's and teleoperator's logs, written with --log; "
        "the newest with both) becomes an episode of one LeRobot v3.0 dataset, at full rate: frames "
        "at --fps carry the 1 kHz signals as windows of 1000/fps samples.",
    )
    ep.add_argument("logs", nargs="+", metavar="LOGDIR", help="a folder of one session's logs (repeatable)")
    ep.add_argument("--to", required=True, choices=("lerobot",), help="the dataset format (lerobot: v3.0)")
    ep.add_argument("--out", required=True, metavar="DIR", help="the dataset's folder: new, or empty")
    ep.add_argument(
        "--task",
        action="append",
        type=task_text,
        metavar="TEXT",
        help="what the operator did: once for every episode, or once per LOGDIR in order "
        "(default: the session's scenario)",
    )
    ep.add_argument(
        "--fps",
        type=int_range("--fps", 1, 1000),
        default=50,
        metavar="F",
        help="frames a second (default 50): each frame holds 1000/F samples of each signal; "
        "F must divide 1000",
    )
    ep.add_argument(
        "--session",
        type=session_id,
        default=None,
        metavar="ID",
        help="the session to export when a LOGDIR holds several (default: the newest with both logs)",
    )
    ep.set_defaults(func=cmd_export)
