"""The real processes: ``teleop operator``, ``teleop teleoperator`` and ``teleop router`` (Zenoh).

The operator and the teleoperator authenticate each other's datagrams with a pre-shared key
(:mod:`teleop.auth`): ``--key-file FILE``, or ``--insecure`` to say out loud that there is none.
The router takes no key: it forwards opaque bytes, and the endpoints authenticate end to end.
"""

from __future__ import annotations

import argparse
import os
from typing import Any

from ..limits import MAX_B, MAX_RANGE
from ..scenarios import SCENARIOS
from .args import (
    CliError,
    Subcommands,
    add_device_args,
    add_endpoint_args,
    add_key_args,
    add_netem_args,
    add_netem_specs,
    add_passivity_args,
    add_robot_name_arg,
    add_session_args,
    add_transport_args,
    positive_float,
    session_id,
    udp_addr,
    zenoh_config_file,
)
from .settings import check_duration, check_robot, endpoint_options, netem, session_params

#: What a teleoperator affords by default: the largest range and impedance of a built-in scenario.
DEFAULT_MAX_RANGE = max(sc.full_scale for sc in SCENARIOS.values())
DEFAULT_MAX_B = max(sc.b for sc in SCENARIOS.values())


def cmd_operator(args: argparse.Namespace) -> int:
    from transport.options import new_session_id
    from transport.session import run_endpoint

    if args.transport == "udp" and args.peer is None:
        raise CliError("--peer HOST:PORT is required with --transport udp (the teleoperator's address)")
    params = session_params(args, args.session or new_session_id())
    return run_endpoint(endpoint_options(args, "operator", args.listen), params)


def cmd_teleoperator(args: argparse.Namespace) -> int:
    from transport.session import run_endpoint

    from ..protocol import Pins  # what this robot was configured with: a hello must match

    activated = os.environ.get("LISTEN_PID") == str(os.getpid())  # systemd passed the socket
    if args.transport == "udp" and args.listen is None and not activated:
        raise CliError(
            "--listen HOST:PORT is required with --transport udp, for example 0.0.0.0:7000 "
            "(or start it from a systemd socket unit: deploy/systemd/teleop-teleoperator.socket)"
        )
    if args.duration is not None:
        # The DoF is the operator's unless given here (or by --scenario): then the widest bound, 1 DoF.
        dof = args.dof
        if dof is None:
            dof = SCENARIOS[args.scenario].dof if args.scenario is not None else 1
        check_duration(args.duration, dof)
    if args.dof is not None:
        check_robot(args.robot, args.dof)
    pins = Pins(
        codec=args.codec,  # canonical already (the --codec type)
        scenario=args.scenario,
        dof=args.dof,
        b=args.b,
        full_scale=args.range,
        duration=args.duration,
        netem_forward=netem(args, "forward") or None,
        netem_backward=netem(args, "backward") or None,
    )
    opts = endpoint_options(args, "teleoperator", args.listen or ("127.0.0.1", 0))
    opts.local_limits = local_limits(args)
    return run_endpoint(opts, None, pins)


def local_limits(args: argparse.Namespace) -> Any:
    """What this robot affords whatever an operator proposes: --max-range/--max-b (a pinned --range
    or --b is its own limit), and --dof if given."""
    from ..protocol import LocalLimits

    max_range = args.max_range if args.max_range is not None else max(DEFAULT_MAX_RANGE, args.range or 0.0)
    max_b = args.max_b if args.max_b is not None else max(DEFAULT_MAX_B, args.b or 0.0)
    if args.range is not None and args.range > max_range:
        raise CliError(f"--range {args.range:g} exceeds --max-range {max_range:g}")
    if args.b is not None and args.b > max_b:
        raise CliError(f"--b {args.b:g} exceeds --max-b {max_b:g}")
    return LocalLimits(max_range=max_range, max_b=max_b)


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


def add_operator_parser(sub: Subcommands) -> None:
    o = sub.add_parser(
        "operator",
        help="the HSI side: simulated human and haptic device",
        description="Run the operator (HSI) process: it says hello to the teleoperator at "
        "--peer, agrees the session, and runs its 1 kHz loop.",
    )
    o.add_argument(
        "--peer",
        type=udp_addr("--peer"),
        default=None,
        metavar="HOST:PORT",
        help="the teleoperator's UDP address (required with --transport udp)",
    )
    o.add_argument(
        "--listen",
        type=udp_addr("--listen"),
        default=("0.0.0.0", 0),
        metavar="HOST:PORT",
        help="local address to bind (default 0.0.0.0:0, any free port)",
    )
    o.add_argument("--session", type=session_id, default=0, help="session id (default: random)")
    add_robot_name_arg(
        o,
        "--robot-name",
        "the name of the robot to reach (its --name): bound into every key, so a robot of another "
        "name never answers, even with the same key",
    )
    add_session_args(o, "eds:50", "protocol")
    add_device_args(o, ("hsi",))
    add_netem_args(o)
    add_passivity_args(o)
    add_endpoint_args(o)
    add_key_args(o, "required unless --insecure")
    add_transport_args(o)
    o.set_defaults(func=cmd_operator)


def add_teleoperator_parser(sub: Subcommands) -> None:
    t = sub.add_parser(
        "teleoperator",
        help="the TO side: simulated robot and environment",
        description="Run the teleoperator (TO) process: it waits on --listen for an operator, "
        "accepts its session (or rejects it if an option given here differs), and runs its "
        "1 kHz loop.",
    )
    t.add_argument(
        "--listen",
        type=udp_addr("--listen"),
        default=None,
        metavar="HOST:PORT",
        help="UDP address to wait on, for example 0.0.0.0:7000 (required with --transport udp)",
    )
    add_robot_name_arg(
        t, "--name", "this robot's name; operators reach it with --robot-name NAME. Give each robot its own"
    )
    add_session_args(t, None, None)
    t.add_argument(
        "--max-range",
        type=positive_float("max range", MAX_RANGE, "sqrt(W)"),
        default=None,
        metavar="R",
        help="the largest wave range an operator may choose when --range is not given "
        f"(default {DEFAULT_MAX_RANGE:g}, the built-in scenarios' largest)",
    )
    t.add_argument(
        "--max-b",
        type=positive_float("max b", MAX_B, "N s/m"),
        default=None,
        metavar="B",
        help="the largest wave impedance an operator may choose when --b is not given "
        f"(default {DEFAULT_MAX_B:g})",
    )
    add_device_args(t, ("robot",))
    add_netem_specs(t, teleoperator=True)
    add_endpoint_args(t)
    add_key_args(t, "required unless --insecure")
    add_transport_args(t)
    t.set_defaults(func=cmd_teleoperator)


def add_router_parser(sub: Subcommands) -> None:
    ro = sub.add_parser(
        "router",
        help="a Zenoh router (a Zenoh session in router mode)",
        description="Run a Zenoh router until Ctrl-C, for --zenoh-mode client sessions. It takes no "
        "key: it forwards opaque bytes, and the operator and teleoperator authenticate every datagram "
        "end to end with theirs (--key-file), so a router never holds a key it could leak.",
    )
    ro.add_argument(
        "--listen",
        action="append",
        required=True,
        metavar="ENDPOINT",
        help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    ro.add_argument(
        "--config",
        metavar="FILE",
        type=zenoh_config_file,
        help="Zenoh JSON5 config (deploy/zenoh/router.json5, TLS variants; a regular file of at most 1 MiB)",
    )
    ro.set_defaults(func=cmd_router)
