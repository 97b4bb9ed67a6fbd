"""``teleop sweep``: a grid of codecs in simulation; sweep.json, a table and pareto.png."""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path

from teleop.cli.args import (
    CliError,
    Subcommands,
    add_model_args,
    add_netem_args,
    add_passivity_args,
    codec_set,
    int_range,
)
from teleop.cli.progress import Progress
from teleop.cli.settings import check_duration, fresh_out, private_dir, sim_config
from teleop.control.codecs import ACCEPTED, CodecError, CodecSpec
from teleop.devices.scenarios import SCENARIOS
from teleop.files import write_new
from teleop.session.settings import Passivity


def _progress_for() -> Callable[[int, int, str], None]:
    """``run_sweep``'s progress callback: :class:`Progress` with the time left."""
    bar: list[Progress] = []

    def step(done: int, total: int, spec: str) -> None:
        if not bar:
            bar.append(Progress(total, sys.stderr, "  "))
        bar[0].step(spec)

    return step


def _grid(args: argparse.Namespace, passivity: Passivity) -> list[CodecSpec]:
    """The codecs of one front: --codec, or the default grid (under tdpa, its codecs that apply to
    power variables)."""
    from teleop.control.codecs import POWER_CODECS
    from teleop.offline.sweep import DEFAULT_GRID

    codecs = list(dict.fromkeys(args.codec or [CodecSpec.parse(c) for c in DEFAULT_GRID]))
    if passivity == Passivity.TDPA:
        codecs = [c for c in codecs if c.name in POWER_CODECS]
    return codecs


def cmd_sweep(args: argparse.Namespace) -> int:
    from teleop.offline import plots
    from teleop.offline.sweep import format_table, run_sweep

    sc = SCENARIOS[args.scenario]
    duration = args.duration if args.duration is not None else sc.duration
    check_duration(duration, args.dof if args.dof is not None else sc.dof)
    out = private_dir(Path(args.out), "--out")
    netems = list(dict.fromkeys(args.netem or [None]))  # one front per --netem, in order, each once
    passivities = list(dict.fromkeys(args.passivity or [Passivity.WAVE]))
    many = len(netems) * len(passivities) > 1
    fresh_out(out, ["sweep.json", "pareto.png", *(["fronts.png"] if many else [])])
    docs = []
    for net in netems:
        for passivity in passivities:
            one = argparse.Namespace(**{**vars(args), "netem": net, "passivity": passivity})
            codecs = _grid(one, passivity)
            if not codecs:
                raise CliError(f"no codec of --codec applies under --passivity {passivity}")
            workers = args.jobs or min(len(codecs), os.cpu_count() or 1)
            base = sim_config(one)
            try:
                print(
                    f"teleop sweep: {len(codecs)} codecs, {passivity}, scenario {base.scenario}, "
                    f"{base.duration:g} s, netem {base.netem_forward or '-'} / {base.netem_backward or '-'}, "
                    f"{workers} workers",
                    file=sys.stderr,
                )
                doc = run_sweep(codecs, base, workers=workers, progress=_progress_for())
            except (ValueError, CodecError, OSError) as e:
                raise CliError(str(e)) from None
            print(f"{passivity}, netem {base.netem_forward or 'none'}:")
            print(format_table(doc))
            docs.append(doc)
    # One front: the document as before.  Several: {"fronts": [...]}, one document each.
    body = docs[0] if not many else {"fronts": docs}
    write_new(out / "sweep.json", (json.dumps(body, indent=2) + "\n").encode())
    first = docs[0]
    net0 = first["netem"]["forward"] or "no impairment"
    plots.pareto(
        out / "pareto.png", first["cases"], f"teleop sweep: {first['scenario']}, {net0}, {first['passivity']}"
    )
    written = [out / "sweep.json", out / "pareto.png"]
    if many:
        plots.pareto_fronts(out / "fronts.png", docs, f"teleop sweep: {first['scenario']}")
        written.append(out / "fronts.png")
    print("wrote " + ", ".join(str(w) for w in written))
    bad = [
        f"{c['codec']} ({d['passivity']}, {d['netem']['forward'] or 'none'})"
        for d in docs
        for c in d["cases"]
        if not c["passive"]
    ]
    if bad:
        print(f"NOT passive: {', '.join(bad)}", file=sys.stderr)
        return 1
    return 0


def add_parser(sub: Subcommands) -> None:
    s = sub.add_parser(
        "sweep",
        help="packet rate against transparency over a grid of codecs (simulation, Pareto front)",
        description="Run a grid of codecs in teleop sim with the same settings, in parallel; print a "
        "table sorted by wire rate, write DIR/sweep.json and DIR/pareto.png (I against wire kbit/s, "
        "Pareto front drawn). --netem and --passivity are repeatable: one front per impairment and "
        "architecture, all in DIR/fronts.png (one panel per impairment, wave and tdpa side by side) and "
        'sweep.json as {"fronts": [...]}. Exit status 1 if a case lost passivity.',
    )
    s.add_argument(
        "--codec",
        action="extend",
        type=codec_set,
        metavar="SPEC",
        help="codec, repeatable; a set preset (paper) adds each of its codecs (default: a grid over every "
        f"family, every point of the front included). Accepted: {ACCEPTED}",
    )
    add_model_args(s, "protocol")
    add_netem_args(s, repeatable=True)
    add_passivity_args(s, repeatable=True)
    s.add_argument(
        "--jobs",
        type=int_range("jobs", 1, 256),
        default=None,
        metavar="N",
        help="parallel processes (default: one per core)",
    )
    s.add_argument("--out", metavar="DIR", required=True, help="write DIR/sweep.json and DIR/pareto.png")
    s.set_defaults(func=cmd_sweep)
