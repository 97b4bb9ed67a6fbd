"""The real processes: ``teleop operator``, ``teleop teleoperator`` and ``teleop router`` (Zenoh).

The operator and the teleoperator authenticate each other's datagrams with a pre-shared key
(:mod:`teleop.session.auth`): ``--key-file FILE``, or ``--insecure`` to say out loud that there is none.
The router takes no key: it forwards opaque bytes, and the endpoints authenticate end to end.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from teleop.cli.args import (
    MAX_CONNECT_TIMEOUT_S,
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
    float_range,
    int_range,
    nonneg_float,
    positive_float,
    rate_cap,
    session_id,
    udp_addr,
    zenoh_config_file,
)
from teleop.cli.settings import (
    check_duration,
    check_robot,
    endpoint_options,
    netem,
    read_session_file,
    session_params,
)
from teleop.control.passivity import ON_LOSS
from teleop.devices.scenarios import SCENARIOS
from teleop.limits import MAX_B, MAX_LINK_TIMEOUT_S, MAX_RANGE, MIN_LINK_TIMEOUT_S
from teleop.session.playout import MAX_EXTRA_MS
from teleop.session.settings import (
    DEFAULT_CODEC,
    DEFAULT_ENVELOPE,
    DEFAULT_SCENARIO,
    MAX_ACT_ALONE_MS,
    MAX_BACKWARD_HOLD_MS,
    MAX_BACKWARD_QUEUE,
    MIN_FADE_S,
    PASSIVITY,
    Envelope,
    Passivity,
)

if TYPE_CHECKING:
    from teleop.session.protocol import SessionParams


def cmd_operator(args: argparse.Namespace) -> int:
    from shell.options import new_session_id
    from shell.process import run_endpoint

    if args.transport == "udp" and args.peer is None:
        raise CliError("--peer HOST:PORT is required with --transport udp (the teleoperator's address)")
    if args.session_file is not None:  # teleop run's: its settings as data, the session flags unread
        params = read_session_file(args.session_file)
    else:
        params = session_params(args, args.session or new_session_id())
    return run_endpoint(endpoint_options(args, "operator", args.listen), params)


def cmd_teleoperator(args: argparse.Namespace) -> int:
    from shell.process import run_endpoint
    from teleop.session.protocol import Pins  # what this robot was configured with: a hello must match

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
    # teleop run's robot admits exactly the session its user chose for both sides (a file of data,
    # read by the hello's parser), and knows its impairment (a trace file only its own may name).
    told = read_session_file(args.session_file) if args.session_file is not None else None
    pins = Pins(
        codec=args.codec,  # canonical already (the --codec type)
        scenario=args.scenario,
        dof=args.dof,
        b=args.b,
        full_scale=args.range,
        duration=args.duration,
        netem_forward=(told.netem_forward if told else netem(args, "forward")) or None,
        netem_backward=(told.netem_backward if told else netem(args, "backward")) or None,
        rate_cap=args.rate_cap,
    )
    envelope = robot_envelope(args, told)  # before the endpoint: a bad limit stops here, in one line
    opts = endpoint_options(args, "teleoperator", args.listen or ("127.0.0.1", 0))
    opts.local_limits = envelope
    from teleop.cli.args import one_line
    from teleop.devices import DeviceError, claim

    try:
        # A hardware robot is taken before any operator is answered: an arm another teleoperator
        # holds (or one in a reflex) is one line now, not a welcome and then a failed start.
        release = claim(args.robot, "robot")
    except DeviceError as e:
        print(f"teleop teleoperator: error: {one_line(e)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("teleop teleoperator: interrupted while taking the robot", file=sys.stderr)
        return 130
    opts.show_holder = args.show_holder
    try:
        return run_endpoint(opts, None, pins)
    finally:
        release()


def _names(text: str | None, allowed: tuple[str, ...], flag: str) -> tuple[str, ...] | None:
    """A comma-separated subset of ``allowed`` (None: not given); CliError says what is allowed."""
    if text is None:
        return None
    names = tuple(dict.fromkeys(n.strip() for n in text.split(",") if n.strip()))
    bad = [n for n in names if n not in allowed]
    if bad or not names:
        raise CliError(f"{flag} {text!r}: must name some of {', '.join(allowed)}, comma-separated")
    return names


def _scaled(lim: _Limit, v: float) -> float:
    """A limit's field value in its flag's unit (an integer field stays an integer)."""
    return v * lim.scale if lim.scale != 1.0 else v


def _unscaled(lim: _Limit, v: float) -> float:
    """A limit's flag value in its field's unit (an integer flag stays an integer)."""
    return v / lim.scale if lim.scale != 1.0 else v


def robot_envelope(args: argparse.Namespace, told: SessionParams | None = None) -> Envelope:
    """This robot's envelope (``teleop.session.settings.Envelope``), what it affords whatever an operator
    proposes: each limit from its flag, else the default; a pinned --range or --b widens the
    default limit to it (a robot is never refused its own setting), and one given beyond an
    explicit limit is an error.  ``told``: the session of a ``--session-file``, which a robot whose
    user chose it for both sides admits (widened just enough; its device's DoF stays its limit)."""
    env = _envelope(args)
    if told is None:
        return env
    admitted = env.admitting(told).owning_backward(told.netem_backward)
    return dataclasses.replace(admitted, max_dof=env.max_dof)


def _envelope(args: argparse.Namespace) -> Envelope:
    e = DEFAULT_ENVELOPE

    def widened(
        given: float | None, pinned: float | None, default: float, flag: str, pin: str, hi: bool
    ) -> float:
        if given is None:
            return default if pinned is None else (max(default, pinned) if hi else min(default, pinned))
        if pinned is not None and (pinned > given if hi else pinned < given):
            raise CliError(f"{pin} {pinned:g} is {'beyond' if hi else 'below'} {flag} {given:g}")
        return given

    max_range = widened(args.max_range, args.range, e.max_range, "--max-range", "--range", True)
    max_b = widened(args.max_b, args.b, e.max_b, "--max-b", "--b", True)
    min_b = widened(args.min_b, args.b, e.min_b, "--min-b", "--b", False)
    if min_b > max_b:
        raise CliError(f"--min-b {min_b:g} exceeds --max-b {max_b:g}")
    from teleop.devices import max_dof

    archs = _names(args.allow_passivity, PASSIVITY, "--allow-passivity")
    limits: dict[str, Any] = {
        lim.field: _unscaled(lim, getattr(args, lim.dest)) for lim in LIMITS if not lim.widens
    }
    try:
        return Envelope(
            max_dof=max_dof(args.robot, "robot"),
            max_range=max_range,
            min_b=min_b,
            max_b=max_b,
            passivity=tuple(map(Passivity, archs)) if archs else e.passivity,
            on_loss=_names(args.allow_on_loss, ON_LOSS, "--allow-on-loss") or e.on_loss,
            uncontrolled_on_loss=_names(args.allow_no_controller, ON_LOSS, "--allow-no-controller") or (),
            **limits,
        ).owning_backward(netem(args, "backward"))

    except ValueError as err:
        raise CliError(str(err)) from None


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
    add_session_args(o, DEFAULT_CODEC, DEFAULT_SCENARIO)
    add_device_args(o, ("hsi",))
    add_netem_args(o)
    add_passivity_args(o)
    add_endpoint_args(o)
    add_key_args(o, "required unless --insecure")
    add_transport_args(o)
    add_session_file_arg(o, "propose the session FILE holds instead of the one the session flags make")
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
    add_envelope_args(t)
    add_device_args(t, ("robot",))
    add_netem_specs(t, teleoperator=True)
    add_endpoint_args(t)
    add_key_args(t, "required unless --insecure")
    add_transport_args(t)
    t.add_argument(
        "--wait",
        type=nonneg_float("wait", MAX_CONNECT_TIMEOUT_S, "s"),
        default=None,
        metavar="S",
        help="give up (exit 1) if no operator says hello within S seconds (default 0: wait until "
        "stopped, printing where it listens and what it refused)",
    )
    t.add_argument(
        "--show-holder",
        action="store_true",
        help="over Zenoh, this robot's description (teleop robots) names the session holding it "
        "(default: busy, without whose)",
    )
    add_session_file_arg(t, "admit the session FILE holds (its settings and its impairment), as a robot "
                         "whose user chose them for both sides")  # fmt: skip
    t.set_defaults(func=cmd_teleoperator)


def add_session_file_arg(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument(
        "--session-file",
        metavar="FILE",
        help=f"{what}: a session's settings as data (JSON: the hello's fields, PROTOCOL.md 4.2), how "
        "teleop run hands them to its two processes",
    )


@dataclass(frozen=True)
class _Limit:
    """One numeric limit of the robot's envelope on the command line."""

    field: str  # of teleop.session.settings.Envelope
    flag: str
    scale: float  # the flag's unit per the field's (ms per s: 1e3)
    parse: Callable[[str], float]
    metavar: str
    help: str  # "{default}" is the default, in the flag's unit
    widens: str | None = None  # a pinned --range/--b widens the default to it (robot_envelope)

    @property
    def dest(self) -> str:
        return self.flag[2:].replace("-", "_")


#: The envelope's numeric limits: their flags and what :func:`robot_envelope` reads, from one list.
LIMITS: tuple[_Limit, ...] = (
    _Limit(
        "max_range", "--max-range", 1.0, positive_float("max range", MAX_RANGE, "sqrt(W)"), "R",
        "the largest wave range an operator may choose, CQ's RANGE included (default {default}, or "
        "--range if larger)", "range",
    ),
    _Limit(
        "min_b", "--min-b", 1.0, positive_float("min b", MAX_B, "N s/m"), "B",
        "the smallest wave impedance an operator may choose: a small b turns a small wave into a fast "
        "motion (default {default}, or --b if smaller)", "b",
    ),
    _Limit(
        "max_b", "--max-b", 1.0, positive_float("max b", MAX_B, "N s/m"), "B",
        "the largest wave impedance an operator may choose (default {default}, or --b if larger)", "b",
    ),
    _Limit(
        "max_link_timeout", "--max-link-timeout", 1e3,
        float_range("max link timeout", MIN_LINK_TIMEOUT_S * 1e3, MAX_LINK_TIMEOUT_S * 1e3, "ms"), "MS",
        "the longest link timeout an operator may ask: how long this robot acts on a silent link "
        "(default {default})",
    ),
    _Limit(
        "max_playout_ms", "--max-playout", 1.0, nonneg_float("max playout", MAX_EXTRA_MS, "ms"), "MS",
        "the largest fixed playout delay an operator may ask (default {default})",
    ),
    _Limit(
        "max_act_alone_ms", "--max-act-alone", 1.0,
        float_range("max act alone", MIN_FADE_S * 1e3, MAX_ACT_ALONE_MS, "ms"), "MS",
        "the longest this robot acts after its operator's last packet: playout + the link timeout "
        "with the codec's payload interval + its fade, which it shortens to fit; a proposal that "
        "does not fit is refused (default {default})",
    ),
    _Limit(
        "max_backward_queue", "--max-backward-queue", 1.0,
        int_range("max backward queue", 1, MAX_BACKWARD_QUEUE), "PACKETS",
        "the most packets an operator's backward impairment (--netem-backward's limit) may make this "
        "robot's outgoing shim hold: its memory is at most that many datagrams (default {default})",
    ),
    _Limit(
        "max_backward_hold_ms", "--max-backward-hold", 1.0,
        nonneg_float("max backward hold", MAX_BACKWARD_HOLD_MS, "ms"), "MS",
        "the longest an operator's backward impairment may make this robot's shim hold a packet: "
        "delay, the jitter's widest draw and a rate's full queue (default {default})",
    ),
    _Limit(
        "max_velocity", "--max-velocity", 1.0, positive_float("max velocity", 1e3, "m/s"), "M_S",
        "the fastest this robot is ever commanded, m/s per DoF (default {default})",
    ),
    _Limit(
        "max_force", "--max-force", 1.0, positive_float("max force", 1e5, "N"), "N",
        "the largest contact force this robot pushes to, N per DoF: it is slowed, never reversed, "
        "beyond it (default {default})",
    ),
)  # fmt: skip


def add_envelope_args(t: argparse.ArgumentParser) -> None:
    """The robot's envelope (``teleop.session.settings.Envelope``, the rules of ``SETTINGS``): what it
    affords whatever a key-holding operator proposes; a proposal beyond it is refused."""
    e = DEFAULT_ENVELOPE
    g = t.add_argument_group(
        "the robot's envelope (a proposal beyond it is refused in one line naming the field and the "
        "limit; see docs/guides/passivity.md)"
    )
    g.add_argument(
        "--rate-cap",
        type=rate_cap,
        default=None,
        metavar="RATE",
        help="accept only an operator proposing this rate cap (netem's units, e.g. 64kbit)",
    )
    for lim in LIMITS:
        default = _scaled(lim, getattr(e, lim.field))
        g.add_argument(
            lim.flag,
            type=lim.parse,
            default=None if lim.widens else default,
            metavar=lim.metavar,
            help=lim.help.format(default=f"{default:g}"),
        )
    g.add_argument(
        "--allow-passivity",
        metavar="LIST",
        default=None,
        help=f"the architectures this robot runs, comma-separated (default {','.join(e.passivity)})",
    )
    g.add_argument(
        "--allow-on-loss",
        metavar="LIST",
        default=None,
        help="the reconstructions this robot plays on a loss, comma-separated "
        f"(default {','.join(e.on_loss)}; without the controller: --allow-no-controller's)",
    )
    g.add_argument(
        "--allow-no-controller",
        nargs="?",
        const="zero",
        default=None,
        metavar="LIST",
        help="let an operator turn the passivity controller off (refused otherwise), with the "
        "reconstructions named, comma-separated (default zero, the passive one; hold and conceal "
        "generate energy without the controller)",
    )


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
