"""The ``teleop`` command."""

from __future__ import annotations

import argparse
import contextlib
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


def format_watchdog(cases: list[dict[str, Any]]) -> str:
    """Per case and direction: what the link did (observed) and what the watchdog saw and did."""
    lines = [
        f"{'codec':<10} {'dir':<9} {'loss %':>7} {'delay ms':>9} {'reord':>6} {'dup':>5} "
        f"{'violations':>10} {'ctrl ticks':>10} {'dissipated J':>12} {'lost':>5}"
    ]
    for c in cases:
        for d in ("forward", "backward"):
            lk, pv = c["link"][d], c["passivity"][d]
            delay = "-" if lk["delay_ms"]["mean"] is None else f"{lk['delay_ms']['mean']:.2f}"
            lines.append(
                f"{c['codec']:<10} {d:<9} {100 * lk['loss']:>7.2f} {delay:>9} {lk['reordered']:>6} "
                f"{lk['duplicates']:>5} {pv['violations']:>10} {pv['controller_active_ticks']:>10} "
                f"{pv['energy_dissipated']:>12.3e} {pv['link_lost_events']:>5}"
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
            **_channel_kwargs(args),
        ).resolved()
        doc, cases = run_set(codecs, base)
    except (ValueError, CodecError) as e:
        raise CliError(str(e)) from None
    print(
        f"teleop sim: scenario {base.scenario}, {base.dof} DoF, b = {base.b:g}, delay {base.delay_ms:g} ms, "
        f"{base.duration:g} s at {1 / base.dt:g} Hz, wave range +-{base.full_scale:g}"
    )
    impaired = bool(base.netem_forward or base.netem_backward)
    if impaired:
        print(
            f"netem forward: {base.netem_forward or '-'}   backward: {base.netem_backward or '-'}   "
            f"seed {base.seed}"
        )
    print(format_table(doc["cases"]))
    if impaired or base.on_loss != "zero" or not base.controller:
        print(format_watchdog(doc["cases"]))
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


def _addr(what: str) -> Any:
    def parse(text: str) -> tuple[str, int]:
        from transport.udp import parse_addr

        try:
            return parse_addr(text, what)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None

    return parse


def _netem(args: argparse.Namespace, direction: str) -> str:
    """The impairment spec of one direction: --netem-DIRECTION, else --netem, else none."""
    specific = getattr(args, f"netem_{direction}", None)
    return str(specific if specific is not None else (getattr(args, "netem", None) or ""))


def _add_netem_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--netem",
        metavar="SPEC",
        help='impair both directions, netem grammar, e.g. "delay 50ms 5ms '
        'loss 2%%" (see README); "trace FILE" for a Mahimahi-style trace',
    )
    p.add_argument(
        "--netem-forward", metavar="SPEC", help="impair operator -> teleoperator only (overrides --netem)"
    )
    p.add_argument(
        "--netem-backward", metavar="SPEC", help="impair teleoperator -> operator only (overrides --netem)"
    )
    p.add_argument("--seed", type=int, default=0, help="seed of the impairment shims (default 0)")


def _add_passivity_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--on-loss",
        choices=["zero", "hold"],
        default="zero",
        help="what a receiver plays when nothing is queued (default zero; hold is bounded by the "
        "passivity controller)",
    )
    p.add_argument(
        "--no-controller",
        action="store_true",
        help="turn the passivity controller off (the watchdog still observes and counts violations)",
    )
    p.add_argument(
        "--link-timeout",
        type=_positive_float("link timeout"),
        default=50.0,
        metavar="MS",
        help="silence before a side goes to its safe state, ms (default 50)",
    )


def _channel_kwargs(args: argparse.Namespace) -> dict[str, Any]:
    """Impairment and passivity settings, the same for `teleop sim` and a real session."""
    return {
        "netem_forward": _netem(args, "forward"),
        "netem_backward": _netem(args, "backward"),
        "seed": args.seed,
        "on_loss": args.on_loss,
        "controller": not args.no_controller,
        "link_timeout": args.link_timeout / 1e3,
    }


def _session_params(args: argparse.Namespace, session: int) -> Any:
    from transport.session import SessionParams

    sc = SCENARIOS[args.scenario]
    try:
        return SessionParams(
            session=session,
            codec=args.codec,
            scenario=args.scenario,
            dof=args.dof if args.dof is not None else sc.dof,
            b=args.b if args.b is not None else sc.b,
            full_scale=args.range if args.range is not None else sc.full_scale,
            duration=args.duration if args.duration is not None else sc.duration,
            phase=args.phase,
            **_channel_kwargs(args),
        ).validate()
    except (ValueError, CodecError) as e:
        raise CliError(str(e)) from None


def _endpoint_options(args: argparse.Namespace, role: str, listen: tuple[str, int]) -> Any:
    from transport.session import EndpointOptions

    return EndpointOptions(
        role=role,
        listen=listen,
        peer=getattr(args, "peer", None),
        log_dir=Path(args.log) if args.log else None,
        connect_timeout=args.connect_timeout,
        rt_priority=None if args.no_rt else 10,
        use_uvloop=not args.asyncio,
        quiet=args.quiet,
        live=args.live,
        grace_us=args.grace_us,
        transport=args.transport,
        zenoh=_zenoh_options(args) if args.transport == "zenoh" else None,
    )


def _zenoh_options(args: argparse.Namespace) -> Any:
    from transport.session import ZenohOptions

    connect = list(args.zenoh_connect or [])
    if args.zenoh_router:
        connect.append(args.zenoh_router)
    return ZenohOptions(
        mode=args.zenoh_mode,
        listen=list(args.zenoh_listen or []),
        connect=connect,
        prefix=args.zenoh_prefix,
        config_file=args.zenoh_config,
    )


def _add_transport_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--transport", choices=["udp", "zenoh"], default="udp", help="udp (default) or zenoh")
    z = p.add_argument_group("Zenoh (with --transport zenoh; see README)")
    z.add_argument(
        "--zenoh-mode",
        choices=["peer", "client"],
        default="peer",
        help="peer (default: direct, explicit endpoints) or client (through a router)",
    )
    z.add_argument(
        "--zenoh-router",
        metavar="ENDPOINT",
        help="router to connect to in client mode, e.g. tcp/10.0.0.5:7447",
    )
    z.add_argument(
        "--zenoh-listen", action="append", metavar="ENDPOINT", help="endpoint to listen on (repeatable)"
    )
    z.add_argument(
        "--zenoh-connect", action="append", metavar="ENDPOINT", help="endpoint to connect to (repeatable)"
    )
    z.add_argument(
        "--zenoh-prefix",
        default="teleop/default",
        metavar="KEY",
        help="key prefix: data on KEY/forward and KEY/backward (default teleop/default)",
    )
    z.add_argument(
        "--zenoh-config", metavar="FILE", help="Zenoh JSON5 config loaded first (deploy/zenoh/*.json5)"
    )


def cmd_operator(args: argparse.Namespace) -> int:
    from transport.session import new_session_id, run_endpoint

    if args.transport == "udp" and args.peer is None:
        raise CliError("--peer HOST:PORT is required with --transport udp (the teleoperator's address)")
    params = _session_params(args, args.session or new_session_id())
    return run_endpoint(_endpoint_options(args, "operator", args.listen), params)


def cmd_teleoperator(args: argparse.Namespace) -> int:
    from transport.session import run_endpoint

    if args.transport == "udp" and args.listen is None:
        raise CliError("--listen HOST:PORT is required with --transport udp, for example 0.0.0.0:7000")
    expect = {
        "codec": make_codec(args.codec).spec if args.codec else None,
        "scenario": args.scenario,
        "dof": args.dof,
        "b": args.b,
        "full_scale": args.range,
        "duration": args.duration,
    }
    return run_endpoint(
        _endpoint_options(args, "teleoperator", args.listen or ("127.0.0.1", 0)), None, expect
    )


def _free_udp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _free_tcp_port() -> int:
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def cmd_router(args: argparse.Namespace) -> int:
    """A Zenoh session in router mode until SIGINT/SIGTERM."""
    import asyncio
    import signal

    from transport.zenoh import TransportError, run_router

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        await run_router(args.listen, args.config, stop)

    try:
        asyncio.run(main())
    except (TransportError, ValueError) as e:
        raise CliError(str(e)) from None
    return 0


def _die_with_parent() -> None:
    """In a child: get SIGTERM if the launcher dies, so no process is left orphaned."""
    import ctypes
    import signal

    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6").prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def cmd_run(args: argparse.Namespace) -> int:
    import signal
    import subprocess
    import time

    from transport.session import new_session_id

    from . import report

    params = _session_params(args, new_session_id())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    logs = out / "logs"
    for stale in ("operator.json", "teleoperator.json", "operator.npz", "teleoperator.npz"):
        (logs / stale).unlink(missing_ok=True)
    port = args.port or _free_udp_port()
    common = ["--log", str(logs), "--connect-timeout", str(args.connect_timeout), "--quiet"]
    common += ["--no-rt"] if args.no_rt else []
    common += ["--asyncio"] if args.asyncio else []
    router_cmd: list[str] | None = None
    zenoh_info: dict[str, Any] | None = None
    if args.transport == "udp":
        to_net = ["--listen", f"127.0.0.1:{port}"]
        op_net = ["--peer", f"127.0.0.1:{port}", "--listen", "127.0.0.1:0"]
        where = f"teleoperator on udp 127.0.0.1:{port}"
    else:
        prefix = f"teleop/run-{params.session}"
        zport = args.port or _free_tcp_port()
        zen = ["--transport", "zenoh", "--zenoh-prefix", prefix]
        if args.zenoh_mode == "peer":
            endpoint = f"tcp/127.0.0.1:{zport}"
            to_net = [*zen, "--zenoh-mode", "peer", "--zenoh-listen", endpoint]
            op_net = [*zen, "--zenoh-mode", "peer", "--zenoh-connect", endpoint]
            where = f"zenoh peers, teleoperator listening on {endpoint}"
        else:
            endpoint = args.zenoh_router or f"tcp/127.0.0.1:{zport}"
            if not args.zenoh_router:
                router_cmd = [sys.executable, "-m", "teleop.cli", "router", "--listen", endpoint]
            to_net = op_net = [*zen, "--zenoh-mode", "client", "--zenoh-router", endpoint]
            where = f"zenoh clients through the router at {endpoint}"
        zenoh_info = {
            "mode": args.zenoh_mode,
            "prefix": prefix,
            "endpoint": endpoint,
            "router_launched": router_cmd is not None,
        }
    to_cmd = [sys.executable, "-m", "teleop.cli", "teleoperator", *to_net, *common]
    op_cmd = [
        sys.executable,
        "-m",
        "teleop.cli",
        "operator",
        *op_net,
        *([] if args.no_live else ["--live"]),
        "--session",
        str(params.session),
        "--codec",
        params.codec,
        "--scenario",
        params.scenario,
        "--dof",
        str(params.dof),
        "--b",
        repr(params.b),
        "--range",
        repr(params.full_scale),
        "--duration",
        repr(params.duration),
        "--phase",
        repr(params.phase),
        "--netem-forward",
        params.netem_forward,
        "--netem-backward",
        params.netem_backward,
        "--seed",
        str(params.seed),
        "--on-loss",
        params.on_loss,
        "--link-timeout",
        repr(params.link_timeout * 1e3),
        *(["--no-controller"] if not params.controller else []),
        *common,
    ]
    print(
        f"teleop run: {where}; {params.codec}, {params.scenario}, {params.duration:g} s; logs in {logs}",
        flush=True,
    )
    router = None
    if router_cmd is not None:
        router = subprocess.Popen(router_cmd, preexec_fn=_die_with_parent)
        time.sleep(0.5)
        if router.poll() is not None:
            raise CliError(f"the Zenoh router failed to start on {zenoh_info and zenoh_info['endpoint']}")
    procs = [subprocess.Popen(to_cmd, preexec_fn=_die_with_parent)]
    time.sleep(0.3)  # let the teleoperator bind before the operator says hello
    procs.append(subprocess.Popen(op_cmd, preexec_fn=_die_with_parent))
    interrupted = False
    limit = time.monotonic() + params.duration + 2 * args.connect_timeout + 10
    try:
        while any(p.poll() is None for p in procs):
            if time.monotonic() > limit:
                raise CliError("the processes did not finish in time; stopped them")
            if any(p.returncode not in (None, 0) for p in procs):
                for p in procs:  # one side failed: do not leave the other waiting
                    if p.poll() is None:
                        p.send_signal(signal.SIGTERM)
            time.sleep(0.05)
    except KeyboardInterrupt:
        interrupted = True
        print("teleop run: interrupted; stopping both processes", file=sys.stderr)
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs:
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        if router is not None:
            router.send_signal(signal.SIGINT)
            try:
                router.wait(timeout=5)
            except subprocess.TimeoutExpired:
                router.kill()
                router.wait()
    codes = {"teleoperator": procs[0].returncode, "operator": procs[1].returncode}
    if not all((logs / f"{r}.json").exists() for r in codes):
        raise CliError(f"no report: a process failed before its loop ran (exit codes {codes})")
    rep = report.build(logs, args.transport, compare_sim=not args.no_sim)
    rep["exit_codes"] = codes
    if zenoh_info is not None:
        rep["zenoh"] = zenoh_info
    (out / "report.json").write_text(json.dumps(rep, indent=2) + "\n")
    files = [] if args.no_plots else report.write_plots(logs, out, rep)
    print(report.summary_text(rep))
    print(f"wrote {out / 'report.json'}" + (f" and {', '.join(f.name for f in files)}" if files else ""))
    if interrupted:
        return 130
    return 0 if all(c == 0 for c in codes.values()) else 1


def cmd_report(args: argparse.Namespace) -> int:
    """Build the report of a session from both processes' logs (for example copied from two hosts)."""
    from . import report

    logs = Path(args.logs)
    missing = [
        f"{r}.{x}"
        for r in ("operator", "teleoperator")
        for x in ("json", "npz")
        if not (logs / f"{r}.{x}").exists()
    ]
    if missing:
        raise CliError(f"{logs} lacks {', '.join(missing)}: pass the folder both processes wrote with --log")
    out = Path(args.out) if args.out else logs.parent
    out.mkdir(parents=True, exist_ok=True)
    rep = report.build(logs, args.transport, compare_sim=not args.no_sim)
    (out / "report.json").write_text(json.dumps(rep, indent=2) + "\n")
    files = [] if args.no_plots else report.write_plots(logs, out, rep)
    print(report.summary_text(rep))
    print(f"wrote {out / 'report.json'}" + (f" and {', '.join(f.name for f in files)}" if files else ""))
    return 0


def _add_process_args(p: argparse.ArgumentParser) -> None:
    """Options of a process's loop, shared by `operator`, `teleoperator` and `run` (which passes them on)."""
    p.add_argument(
        "--connect-timeout",
        type=_positive_float("connect timeout"),
        default=10.0,
        metavar="S",
        help="give up if the peer does not answer within S seconds (default 10)",
    )
    p.add_argument("--no-rt", action="store_true", help="do not ask for SCHED_FIFO priority")
    p.add_argument("--asyncio", action="store_true", help="use the stdlib asyncio loop instead of uvloop")


def _add_endpoint_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--log", metavar="DIR", help="write ROLE.json and ROLE.npz logs to DIR")
    _add_process_args(p)
    p.add_argument("--quiet", action="store_true", help="no summary line at the end")
    p.add_argument("--live", action="store_true", help="print a status line every second (traffic, watchdog)")
    p.add_argument(
        "--grace-us",
        type=_nonneg_float("grace"),
        default=400.0,
        metavar="US",
        help="wait up to US microseconds into a tick for a payload that is due (default 400)",
    )


def _add_session_args(p: argparse.ArgumentParser, codec_default: str | None) -> None:
    p.add_argument(
        "--codec",
        type=_codec,
        default=codec_default,
        metavar="SPEC",
        help=f"codec (default {codec_default}). Accepted: {ACCEPTED}",
    )
    _add_model_args(p)
    p.add_argument("--phase", type=float, default=0.5, help=argparse.SUPPRESS)


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
    _add_netem_args(s)
    _add_passivity_args(s)
    s.add_argument("--out", metavar="DIR", help="write DIR/results.json and one PNG per codec")
    s.set_defaults(func=cmd_sim)

    r = sub.add_parser(
        "run",
        help="launch operator and teleoperator as two processes on 127.0.0.1 and report",
        description="Launch both processes on 127.0.0.1 over UDP, wait for them, gather both logs and "
        "write OUT/report.json, PNG plots and a printed summary. Ctrl-C stops both cleanly.",
    )
    _add_session_args(r, "eds:50")
    _add_netem_args(r)
    _add_passivity_args(r)
    r.set_defaults(scenario="protocol")
    r.add_argument("--transport", choices=["udp", "zenoh"], default="udp", help="transport (default udp)")
    r.add_argument(
        "--zenoh-mode",
        choices=["peer", "client"],
        default="peer",
        help="with zenoh: peer (direct, default) or client (through a router; one is started "
        "unless --zenoh-router is given)",
    )
    r.add_argument("--zenoh-router", metavar="ENDPOINT", help="with zenoh client mode: an existing router")
    r.add_argument("--out", default="teleop-run", metavar="DIR", help="report folder (default ./teleop-run)")
    r.add_argument("--port", type=int, default=0, help="teleoperator UDP port (default: a free one)")
    _add_process_args(r)
    r.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    r.add_argument("--no-sim", action="store_true", help="skip the teleop sim comparison in the report")
    r.add_argument("--no-live", action="store_true", help="no status line every second during the run")
    r.set_defaults(func=cmd_run)

    o = sub.add_parser(
        "operator",
        help="the HSI side: simulated human and haptic device",
        description="Run the operator (HSI) process: it says hello to the teleoperator at "
        "--peer, agrees the session, and runs its 1 kHz loop.",
    )
    o.add_argument(
        "--peer",
        type=_addr("--peer"),
        default=None,
        metavar="HOST:PORT",
        help="the teleoperator's UDP address (required with --transport udp)",
    )
    o.add_argument(
        "--listen",
        type=_addr("--listen"),
        default=("0.0.0.0", 0),
        metavar="HOST:PORT",
        help="local address to bind (default 0.0.0.0:0, any free port)",
    )
    o.add_argument("--session", type=int, default=0, help="session id (default: random)")
    _add_session_args(o, "eds:50")
    _add_netem_args(o)
    _add_passivity_args(o)
    o.set_defaults(scenario="protocol")
    _add_endpoint_args(o)
    _add_transport_args(o)
    o.set_defaults(func=cmd_operator)

    t = sub.add_parser(
        "teleoperator",
        help="the TO side: simulated robot and environment",
        description="Run the teleoperator (TO) process: it waits on --listen for an operator, "
        "accepts its session (or rejects it if an option given here differs), and runs its "
        "1 kHz loop.",
    )
    t.add_argument(
        "--listen",
        type=_addr("--listen"),
        default=None,
        metavar="HOST:PORT",
        help="UDP address to wait on, for example 0.0.0.0:7000 (required with --transport udp)",
    )
    _add_session_args(t, None)
    t.set_defaults(scenario=None)
    _add_endpoint_args(t)
    _add_transport_args(t)
    t.set_defaults(func=cmd_teleoperator)

    ro = sub.add_parser(
        "router",
        help="a Zenoh router (a Zenoh session in router mode)",
        description="Run a Zenoh router until Ctrl-C, for --zenoh-mode client sessions.",
    )
    ro.add_argument(
        "--listen",
        action="append",
        required=True,
        metavar="ENDPOINT",
        help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    ro.add_argument(
        "--config", metavar="FILE", help="Zenoh JSON5 config (deploy/zenoh/router.json5, TLS variants)"
    )
    ro.set_defaults(func=cmd_router)

    rp = sub.add_parser(
        "report",
        help="build a report from the two processes' logs",
        description="Merge operator.json/.npz and teleoperator.json/.npz (written with --log) "
        "into report.json, plots and a printed summary.",
    )
    rp.add_argument("logs", metavar="LOGDIR", help="folder holding both processes' logs")
    rp.add_argument("--out", metavar="DIR", help="report folder (default: LOGDIR's parent)")
    rp.add_argument("--transport", default="udp", help="transport name to record (default udp)")
    rp.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    rp.add_argument("--no-sim", action="store_true", help="skip the teleop sim comparison")
    rp.set_defaults(func=cmd_report)
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
