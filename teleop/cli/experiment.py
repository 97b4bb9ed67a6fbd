"""``teleop experiment``: the paper's Section VI study, N seeded runs per codec, Fig. 15.

In virtual time (``teleop sim``'s runner) by default; with ``--real``, each run is a real
``teleop run`` session (two processes on 127.0.0.1), one after another, reusing that command's
code with its options, seed by seed, every codec in turn.  Each real run writes
``DIR/runs/CODEC-seedN/report.json`` (its logs are removed unless ``--keep-logs``: about 2 MB per
run); a run whose processes did not both record most of the session is left out as incomplete.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import shutil
import sys
from pathlib import Path
from typing import Any

from teleop.cli.args import (
    CliError,
    Parser,
    Subcommands,
    add_model_args,
    add_netem_args,
    add_passivity_args,
    codec_set,
    int_range,
    nonneg_float,
)
from teleop.cli.progress import Progress
from teleop.cli.settings import channel, check_duration, fresh_out, private_dir, sim_config
from teleop.control.codecs import ACCEPTED
from teleop.devices.scenarios import SCENARIOS
from teleop.files import write_new
from teleop.limits import MAX_SEED
from teleop.session.verdict import POOR_EXIT

MAX_RUNS = 1000


def _settings(args: argparse.Namespace, dof: int, duration: float) -> dict[str, Any]:
    return {
        "scenario": args.scenario,
        "dof": dof,
        "duration": duration,
        "variation": args.variation,
        "passivity": args.passivity,
        "seeds": [args.seed, args.seed + args.runs - 1],
        "transport": args.transport if args.real else None,
        "netem": {
            "forward": channel(args).netem_forward,
            "backward": channel(args).netem_backward,
        },
    }


def _sim_runs(args: argparse.Namespace, codecs: list[str], progress: Progress) -> dict[str, list[Any]]:
    from teleop.offline.experiment import sim_run

    base = sim_config(args)
    runs: dict[str, list[Any]] = {spec: [] for spec in codecs}
    for seed in range(args.seed, args.seed + args.runs):
        for spec in codecs:
            runs[spec].append(r := sim_run(base, spec, seed))
            progress.step(f"{spec} seed {seed}" + ("" if r.passive else " NOT PASSIVE"))
    return runs


def _run_args(args: argparse.Namespace, spec: str, seed: int, out: Path) -> argparse.Namespace:
    """``teleop run``'s options for one session: its defaults, then every option given here."""
    from teleop.cli import run

    parser = Parser(prog="teleop")
    run.add_parser(parser.add_subparsers(dest="command"))
    ns = parser.parse_args(["run"])
    for k, v in vars(args).items():
        if k in vars(ns) and k not in ("func", "command", "out", "codec"):
            setattr(ns, k, v)
    ns.codec, ns.seed, ns.out = spec, seed, str(out)
    ns.no_sim = ns.no_plots = ns.no_live = True
    return ns


def _real_run(args: argparse.Namespace, spec: str, seed: int, out: Path) -> Any:
    """One ``teleop run`` session; its printed summary goes to ``out/run.log``."""
    from teleop.cli.run import cmd_run
    from teleop.offline.experiment import RunResult, host_figures, incomplete, real_passive

    ns = _run_args(args, spec, seed, out)
    buf = io.StringIO()
    try:
        with contextlib.redirect_stdout(buf):
            rc = cmd_run(ns)
    except CliError as e:
        return RunResult(seed, False, error=str(e)), 1
    finally:
        write_new(out / "run.log", buf.getvalue().encode())
        if not args.keep_logs:
            shutil.rmtree(out / "logs", ignore_errors=True)
    rep = json.loads((out / "report.json").read_text())
    # A poor session (exit 3: its link lost, its watchdog busy) ran and is measured: its figures
    # count, and its passivity is judged as every run's is.
    ran = rc in (0, POOR_EXIT)
    error = None if ran else f"teleop run exited with {rc} (exit codes {rep.get('exit_codes')})"
    error = error or incomplete(rep)
    return RunResult(seed, real_passive(rep), rep["phases"], error, host_figures(rep)), rc


def _real_runs(
    args: argparse.Namespace, codecs: list[str], out: Path, progress: Progress
) -> dict[str, list[Any]]:
    from teleop.offline.plots import safe_name

    runs: dict[str, list[Any]] = {spec: [] for spec in codecs}
    # Seed by seed, every codec in turn: a host that gets busier during the experiment then
    # slows every codec alike, instead of the codecs that happen to run last.
    for seed in range(args.seed, args.seed + args.runs):
        for spec in codecs:
            folder = private_dir(out / "runs" / f"{safe_name(spec)}-seed{seed}", "--out")
            r, rc = _real_run(args, spec, seed, folder)
            runs[spec].append(r)
            progress.step(f"{spec} seed {seed}" + (f" FAILED: {r.error}" if r.error else ""))
            if rc == 130:
                raise KeyboardInterrupt
    return runs


def cmd_experiment(args: argparse.Namespace) -> int:
    from teleop.offline.experiment import aggregate, format_paired, format_table
    from teleop.offline.sim import SECTION_V_CODECS

    sc = SCENARIOS[args.scenario]
    dof = args.dof if args.dof is not None else sc.dof
    duration = args.duration if args.duration is not None else sc.duration
    check_duration(duration, dof)
    if args.seed + args.runs - 1 > MAX_SEED:
        raise CliError(f"--seed + --runs - 1 must be at most {MAX_SEED} (run i uses seed + i - 1)")
    if not args.real and (args.transport != "udp" or args.keep_logs):
        raise CliError("--transport and --keep-logs apply to real sessions: add --real")
    if args.real and args.delay:
        raise CliError("--delay is for the simulation; real sessions take --netem 'delay N ms'")
    out = private_dir(Path(args.out), "--out")
    fresh_out(out, ["experiment.json", "runs"])  # a run's report.json is read back: none stale
    codecs = list(dict.fromkeys(args.codec or SECTION_V_CODECS))
    where = f"real sessions over {args.transport}" if args.real else "simulation"
    print(
        f"teleop experiment: {len(codecs)} codecs x {args.runs} runs, {args.scenario} scenario, "
        f"{dof} DoF, {duration:g} s, variation {args.variation:g}, seeds {args.seed}.."
        f"{args.seed + args.runs - 1}, {where}",
        flush=True,
    )
    progress = Progress(len(codecs) * args.runs, sys.stderr, "teleop experiment: ")
    runs = _real_runs(args, codecs, out, progress) if args.real else _sim_runs(args, codecs, progress)
    doc = aggregate(runs, args.runs, args.real, _settings(args, dof, duration))
    write_new(out / "experiment.json", (json.dumps(doc, indent=2) + "\n").encode())
    from teleop.offline import plots

    plots.experiment_bars(out / "fig15.png", doc, plots.experiment_title(doc))
    print(format_table(doc))
    if paired := format_paired(doc):
        print(paired)
    for c in doc["cases"]:
        for r in c["per_run"]:
            if r["error"] or not r["passive"]:
                print(f"  {c['codec']} seed {r['seed']}: {r['error'] or 'NOT PASSIVE'}")
    print(f"wrote {out / 'experiment.json'} and {out / 'fig15.png'}")
    return 0 if all(c["passive"] for c in doc["cases"]) else 1


def add_parser(sub: Subcommands) -> None:
    e = sub.add_parser(
        "experiment",
        help="the paper's Section VI study: N seeded runs per codec, per-phase mean and spread (Fig. 15)",
        description="Run every codec over the same N seeded humans (run i uses --seed + i - 1; "
        "--variation scales how much they differ), in the simulation or with --real as real "
        "two-process sessions one after another (teleop run). Writes DIR/experiment.json and "
        "DIR/fig15.png. Exit status 1 if a run was not passive (or did not complete).",
    )
    e.add_argument(
        "--runs",
        type=int_range("runs", 1, MAX_RUNS),
        default=10,
        help="runs per codec (default 10, as in the paper)",
    )
    e.add_argument(
        "--codec",
        action="extend",
        type=codec_set,
        metavar="SPEC",
        help="codec, repeatable; a set preset (paper) adds each of its codecs (default: the paper's set). "
        f"Accepted: {ACCEPTED}",
    )
    e.add_argument("--real", action="store_true", help="real two-process sessions instead of the simulation")
    e.add_argument(
        "--transport", choices=["udp", "zenoh"], default="udp", help="with --real: transport (default udp)"
    )
    e.add_argument(
        "--delay",
        type=nonneg_float("delay"),
        default=0.0,
        metavar="MS",
        help="simulation: one-way delay per direction in ms (default 0)",
    )
    e.add_argument("--keep-logs", action="store_true", help="with --real: keep each run's logs")
    add_model_args(e, "protocol")
    add_netem_args(e, variation_default=1.0)
    add_passivity_args(e)
    e.add_argument("--out", required=True, metavar="DIR", help="write DIR/experiment.json and DIR/fig15.png")
    e.set_defaults(func=cmd_experiment)
