"""Argument types and the option groups shared by several commands.

Every type here turns a bad value into one ``argparse.ArgumentTypeError`` that says what is wrong
and what is allowed; the ranges come from :mod:`teleop.limits`, the same table the handshake parser
holds a peer's proposal to.  Checks that need more than one option (a duration against the DoF, a
folder that must be writable) are in :mod:`teleop.cli.settings`.
"""

from __future__ import annotations

import argparse
import difflib
import math
import re
import socket
from collections.abc import Callable, Sequence
from typing import Any, NoReturn, TypeAlias

from teleop.control.codecs import ACCEPTED, CodecError, CodecSpec, expand
from teleop.devices.scenarios import SCENARIOS
from teleop.errors import TeleopError
from teleop.errors import one_line as one_line  # (its home was here: callers import it from here)
from teleop.limits import (
    MAX_B,
    MAX_CODEC_SPEC_LEN,
    MAX_DOF,
    MAX_LINK_TIMEOUT_S,
    MAX_NETEM_SPEC_LEN,
    MAX_RANGE,
    MAX_SEED,
    MAX_SESSION,
    MAX_VARIATION,
    MIN_LINK_TIMEOUT_S,
)
from teleop.session.settings import DEFAULTS, Passivity
from teleop.session.verdict import Bounds

MAX_GRACE_US = 900.0  # the wait for a late payload must end well within the 1 ms tick
MAX_CONNECT_TIMEOUT_S = 86400.0  # a day: longer waits overflow the loop's nanosecond clock
CONNECT_TIMEOUT_S = 10.0  # the operator's wait for its robot's answer
MAX_PORT = 65535


class CliError(TeleopError):
    """A bad argument: printed as ``teleop: error: ...`` with exit status 2."""


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line naming the command's help, not a usage dump.

    No abbreviations (``--dur 5`` is not ``--duration 5``: a typo must not become another flag,
    and a new flag must not break a command line that abbreviated an old one); an unknown flag or
    choice says the closest known one."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        ns, extras = super().parse_known_args(args, namespace)
        flags = [a for a in extras if a.startswith("-")]
        if flags and " " in self.prog:  # a command's parser: it knows its own flags
            self.error(f"unrecognized arguments: {' '.join(extras)}{self._closest(flags[0])}")
        return ns, extras

    def _closest(self, flag: str) -> str:
        """``; did you mean --x?`` for the known flag closest to ``flag`` (its ``=value`` aside)."""
        known = [o for o in self._option_string_actions if o.startswith("--")]
        near = difflib.get_close_matches(flag.split("=", 1)[0], known, n=1, cutoff=0.6)
        return f"; did you mean {near[0]}?" if near else ""

    def error(self, message: str) -> NoReturn:
        m = _INVALID_CHOICE.search(message)
        if m is not None:
            near = difflib.get_close_matches(m[1], re.findall(r"'([^']*)'", m[2]), n=1, cutoff=0.6)
            message += f"; did you mean {near[0]}?" if near else ""
        self.exit(2, f"teleop: error: {message} (see '{self.prog} --help')\n")


_INVALID_CHOICE = re.compile(r"invalid choice: '([^']*)' \(choose from (.*)\)")


#: What ``add_subparsers`` returns; each command module adds its parser(s) to it.
Subcommands: TypeAlias = "argparse._SubParsersAction[Parser]"


# --- argument types --------------------------------------------------------------------------------


def _finite(what: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{what} must be a number, got {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"{what} must be a finite number, got {text!r}")
    return v


def positive_float(what: str, hi: float | None = None, unit: str = "") -> Callable[[str], float]:
    """A finite number > 0 (and <= ``hi`` when given)."""
    most = "" if hi is None else f" and <= {hi:g}{' ' + unit if unit else ''}"

    def parse(text: str) -> float:
        v = _finite(what, text)
        if v <= 0 or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"{what} must be > 0{most}, got {text!r}")
        return v

    return parse


def nonneg_float(what: str, hi: float | None = None, unit: str = "", why: str = "") -> Callable[[str], float]:
    """A finite number >= 0 (and <= ``hi`` when given; ``why`` says where the bound comes from)."""
    most = "" if hi is None else f" and <= {hi:g}{' ' + unit if unit else ''}{why}"

    def parse(text: str) -> float:
        v = _finite(what, text)
        if v < 0 or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"{what} must be >= 0{most}, got {text!r}")
        return v

    return parse


def float_range(what: str, lo: float, hi: float, unit: str) -> Callable[[str], float]:
    """A finite number in ``lo..hi``, both included."""

    def parse(text: str) -> float:
        v = _finite(what, text)
        if not lo <= v <= hi:
            span = f"{lo:g} to {hi:g}" + (f" {unit}" if unit else "")
            raise argparse.ArgumentTypeError(f"{what} must be {span}, got {text!r}")
        return v

    return parse


def int_range(what: str, lo: int, hi: int, note: str = "") -> Callable[[str], int]:
    """An integer in ``lo..hi``, both included (``note`` adds what a special value means)."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            v = None
        if v is None or not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"{what} must be an integer {lo}..{hi}{note}, got {text!r}")
        return v

    return parse


def playout(text: str) -> str:
    from teleop.session.playout import parse_playout

    try:
        return parse_playout(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def rate_cap(text: str) -> float:
    """A rate in netem's units (``64kbit``; ``kbps`` are bytes/s), within teleop.control.ratecap's range."""
    from teleop.control.ratecap import MAX_RATE_BPS, MIN_RATE_BPS
    from teleop.session.link.netem import NetemError, parse_rate

    try:
        bps = parse_rate(text)
    except NetemError as e:
        raise argparse.ArgumentTypeError(f"rate cap {text!r}: {e}") from None
    if not MIN_RATE_BPS <= bps <= MAX_RATE_BPS:
        raise argparse.ArgumentTypeError(
            f"rate cap must be {MIN_RATE_BPS / 1e3:g}kbit to {MAX_RATE_BPS / 1e9:g}gbit (per second), "
            f"got {text!r}"
        )
    return bps


def session_id(text: str) -> int:
    return int_range("session", 0, MAX_SESSION, " (0: a random one)")(text)


def dof(text: str) -> int:
    return int_range("DoF", 1, MAX_DOF)(text)


MAX_TYPED_SPEC_LEN = 256  # a spec as typed (named parameters spell more than the wire's 64)


def codec(text: str) -> CodecSpec:
    """One codec: the spec, parsed here once (presets and named parameters resolved)."""
    return codec_set(text, one=True)[0]


def codec_set(text: str, one: bool = False) -> list[CodecSpec]:
    """One ``--codec`` of a command that runs several: a spec, or a preset naming a set (``paper``)."""
    if len(text) > MAX_TYPED_SPEC_LEN:
        raise argparse.ArgumentTypeError(
            f"codec spec must be at most {MAX_TYPED_SPEC_LEN} characters, got {len(text)}"
        )
    try:
        specs = [CodecSpec.parse(text)] if one else expand(text)
    except CodecError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    for spec in specs:  # what goes on the wire: the hello's bound
        if len(spec) > MAX_CODEC_SPEC_LEN:
            raise argparse.ArgumentTypeError(
                f"codec spec {spec} must be at most {MAX_CODEC_SPEC_LEN} characters, got {len(spec)}"
            )
    return specs


def passivity(text: str) -> Passivity:
    try:
        return Passivity.of(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


def netem_spec(text: str) -> str:
    """A netem spec or ``trace FILE``, checked by building its link (so a trace file is read now)."""
    from teleop.session.link.netem import make_link

    if len(text) > MAX_NETEM_SPEC_LEN:
        raise argparse.ArgumentTypeError(
            f"netem spec must be at most {MAX_NETEM_SPEC_LEN} characters, got {len(text)}"
        )
    try:
        make_link(text, 0)
    except OSError as e:
        name = e.filename if e.filename is not None else text.split(maxsplit=1)[-1]
        raise argparse.ArgumentTypeError(
            f"netem: cannot read the trace file {name!r}: {e.strerror or e} "
            "(a trace is a text file of ms timestamps, one a line)"
        ) from None
    except UnicodeDecodeError:
        raise argparse.ArgumentTypeError(
            f"netem: the trace file {text.split(maxsplit=1)[-1]!r} is not text "
            "(a trace is a text file of ms timestamps, one a line)"
        ) from None
    except ValueError as e:  # NetemError: names the bad token and gives the grammar
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


def zenoh_config_file(text: str) -> str:
    """A Zenoh JSON5 config file: a regular file of at most ``teleop.files.MAX_CONFIG_BYTES``
    (a FIFO or a device is refused by its type, before it is opened), checked now; the session
    reads it again the same way."""
    from teleop.files import MAX_CONFIG_BYTES, FileRefused, read_regular

    try:
        read_regular(text, MAX_CONFIG_BYTES, "cannot load Zenoh config")
    except FileRefused as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


def udp_addr(what: str) -> Callable[[str], tuple[str, int]]:
    """``HOST:PORT`` with HOST resolved to an IPv4 address now, so a bad name fails before a session."""

    def parse(text: str) -> tuple[str, int]:
        from transport.udp import parse_addr

        try:
            host, port = parse_addr(text, what)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
        try:
            infos = socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_DGRAM)
        except (OSError, ValueError) as e:  # gaierror; UnicodeError for a bad IDNA label
            why = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
            raise argparse.ArgumentTypeError(
                f"cannot resolve host {host!r} to an IPv4 address ({why})"
            ) from None
        return str(infos[0][4][0]), port

    return parse


# --- option groups ---------------------------------------------------------------------------------


def add_model_args(p: argparse.ArgumentParser, scenario_default: str | None) -> None:
    """Scenario and model options shared by every command that runs the nodes."""
    default_text = scenario_default or "whatever the operator proposes"
    p.add_argument(
        "--scenario",
        choices=list(SCENARIOS),
        default=scenario_default,
        help=f"step (Section V) or protocol (Section VI); default {default_text}",
    )
    p.add_argument(
        "--duration",
        type=nonneg_float("duration", why=" (0: until stopped)"),
        default=None,
        metavar="S",
        help="seconds to run, 0 to run until Ctrl-C/SIGTERM or the peer's bye (teleop sim: > 0) "
        "(default: the scenario's, 5 for step, 15 for protocol)",
    )
    p.add_argument("--dof", type=dof, default=None, help="degrees of freedom (default: the scenario's)")
    p.add_argument(
        "--b",
        type=positive_float("wave impedance b", MAX_B, "N s/m"),
        default=None,
        help="wave impedance b > 0, N s/m (default: the scenario's, 1 for step, 20 for protocol)",
    )
    p.add_argument(
        "--range",
        type=positive_float("range", MAX_RANGE, "sqrt(W)"),
        default=None,
        metavar="R",
        help="full scale of the raw 16-bit wave format, sqrt(W) (default: the scenario's)",
    )


def robot_name(flag: str) -> Callable[[str], str]:
    """A robot's name (teleop.session.auth.check_robot_name): a bad one says what is allowed."""

    def parse(text: str) -> str:
        from teleop.session.auth import check_robot_name

        try:
            return check_robot_name(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(f"{flag}: {e}") from None

    return parse


def add_robot_name_arg(p: argparse.ArgumentParser, flag: str, help: str) -> None:
    """``--name`` (a teleoperator's) or ``--robot-name`` (whom an operator reaches): bound into every key."""
    from teleop.session.auth import DEFAULT_ROBOT_NAME

    p.add_argument(
        flag,
        type=robot_name(flag),
        default=DEFAULT_ROBOT_NAME,
        metavar="NAME",
        help=f"{help} (default {DEFAULT_ROBOT_NAME!r})",
    )


def device_spec(role: str) -> Callable[[str], str]:
    """A ``--hsi``/``--robot`` spec, resolved now (teleop.devices): a bad one lists what is available."""

    def parse(text: str) -> str:
        from teleop.devices import DeviceError, check

        try:
            check(text, role)
        except DeviceError as e:
            raise argparse.ArgumentTypeError(str(e)) from None
        return text

    return parse


def add_device_args(p: argparse.ArgumentParser, roles: tuple[str, ...]) -> None:
    """``--hsi`` (operator side) and/or ``--robot`` (teleoperator side): a local choice of each side."""
    from teleop.devices import BUILTIN, ENTRY_POINT_GROUP

    what = {
        "hsi": "the operator's HSI device with its human",
        "robot": "the teleoperator's robot in its environment",
    }
    for role in roles:
        p.add_argument(
            f"--{role}",
            type=device_spec(role),
            default=None,
            metavar="SPEC",
            help=f"{what[role]} (default: the scenario's model). Accepted: "
            f"{', '.join(b.usage for b in BUILTIN[role].values())}, a {ENTRY_POINT_GROUP} entry point, "
            "or package.module:Class[:ARG] (see docs/guides/devices.md)",
        )


def add_session_args(
    p: argparse.ArgumentParser, codec_default: str | None, scenario_default: str | None
) -> None:
    """The session an operator proposes (or a teleoperator insists on): codec, scenario, model."""
    p.add_argument(
        "--codec",
        type=codec,
        default=codec_default,
        metavar="SPEC",
        help=f"codec (default {codec_default or 'whatever the operator proposes'}). Accepted: {ACCEPTED}",
    )
    add_model_args(p, scenario_default)
    p.add_argument("--phase", type=float, default=0.5, help=argparse.SUPPRESS)


def add_netem_specs(p: argparse.ArgumentParser, teleoperator: bool = False, repeatable: bool = False) -> None:
    """--netem and its per-direction overrides.  On the teleoperator they say which impairment it
    accepts from the operator's hello (a ``trace FILE`` only when named here: a peer may not make
    this side read a file of its choosing).  ``repeatable`` (teleop sweep): one front per --netem."""
    what = "accept only an operator impairing" if teleoperator else "impair"
    p.add_argument(
        "--netem",
        type=netem_spec,
        metavar="SPEC",
        action="append" if repeatable else "store",
        help=f'{what} both directions, netem grammar, e.g. "delay 50ms 5ms '
        'loss 2%%" (see docs/guides/netem.md); "trace FILE" for a Mahimahi-style trace'
        + ('; repeatable: one Pareto front per impairment ("" for none)' if repeatable else ""),
    )
    p.add_argument(
        "--netem-forward",
        type=netem_spec,
        metavar="SPEC",
        help=f"{what} operator -> teleoperator with SPEC (overrides --netem)",
    )
    p.add_argument(
        "--netem-backward",
        type=netem_spec,
        metavar="SPEC",
        help=f"{what} teleoperator -> operator with SPEC (overrides --netem)",
    )


def add_netem_args(
    p: argparse.ArgumentParser, variation_default: float = 0.0, repeatable: bool = False
) -> None:
    add_netem_specs(p, repeatable=repeatable)
    p.add_argument(
        "--seed",
        type=int_range("seed", 0, MAX_SEED),
        default=DEFAULTS.seed,
        help=f"seed of the impairment shims and of the human's variation (default {DEFAULTS.seed})",
    )
    p.add_argument(
        "--variation",
        type=float_range("variation", 0.0, MAX_VARIATION, "(0: the scripted run)"),
        default=variation_default,
        metavar="X",
        help="protocol scenario: vary the human as a person repeating the task does, seeded by --seed "
        "(stroke, push timing and depth, phase times, arm and grip stiffness); 1 = the documented "
        f"spread, 0 = the scripted run (default {variation_default:g})",
    )


def add_passivity_args(p: argparse.ArgumentParser, repeatable: bool = False) -> None:
    p.add_argument(
        "--passivity",
        type=passivity,
        choices=list(Passivity),
        default=None if repeatable else DEFAULTS.passivity,
        action="append" if repeatable else "store",
        help="how the channel is kept passive: wave (default) sends scattering waves (eq. 3-5); tdpa "
        "sends velocity forward and force back with each side's input energy, and an adaptive damper "
        "at each side dissipates what the channel would generate (time-domain passivity approach). "
        "tdpa takes every codec but dct",
    )
    p.add_argument(
        "--on-loss",
        choices=["conceal", "hold", "zero"],
        default=None,
        help="what a receiver plays when nothing is queued: conceal (default) holds the last sample "
        "for one payload interval, then fades it; hold keeps it; zero plays nothing.  conceal and hold "
        "are played only within the energy budget (the passivity controller); with --no-controller "
        "the default is zero",
    )
    p.add_argument(
        "--no-controller",
        action="store_true",
        help="turn the passivity controller off (the watchdog still observes and counts violations)",
    )
    p.add_argument(
        "--link-timeout",
        type=float_range("link timeout", MIN_LINK_TIMEOUT_S * 1e3, MAX_LINK_TIMEOUT_S * 1e3, "ms"),
        default=DEFAULTS.link_timeout * 1e3,
        metavar="MS",
        help=f"silence before a side goes to its safe state, ms (default {DEFAULTS.link_timeout * 1e3:g})",
    )
    p.add_argument(
        "--playout",
        type=playout,
        default=DEFAULTS.playout,
        metavar="auto|MS|off",
        help="receivers' playout (jitter) buffer: play each payload at its send tick plus the lowest "
        "delay seen plus an allowance: auto follows the observed lateness, MS fixes it, off plays "
        f"payloads as they arrive (default {DEFAULTS.playout})",
    )
    p.add_argument(
        "--rate-cap",
        type=rate_cap,
        default=DEFAULTS.rate_cap,
        metavar="RATE",
        help="hard cap on each direction's data rate, whole datagrams in any 100 ms window, in netem's "
        "rate units (e.g. 64kbit, 8kbps); the encoder holds payloads back to keep it (default: none)",
    )


TICK_AT = ("wake", "deadline")


def add_process_args(p: argparse.ArgumentParser) -> None:
    """Options of a process's loop, shared by `operator`, `teleoperator` and `run` (which passes them on)."""
    p.add_argument(
        "--connect-timeout",
        type=positive_float("connect timeout", MAX_CONNECT_TIMEOUT_S, "s"),
        default=None,
        metavar="S",
        help=f"give up if the peer does not answer within S seconds (default {CONNECT_TIMEOUT_S:g}; "
        "a teleoperator waits for its operator until stopped, see its --wait)",
    )
    p.add_argument("--no-rt", action="store_true", help="do not ask for SCHED_FIFO priority nor lock memory")
    p.add_argument("--asyncio", action="store_true", help="use the stdlib asyncio loop instead of uvloop")
    p.add_argument(
        "--tick-at",
        choices=TICK_AT,
        default="wake",
        help="wake (default): run each tick as the loop wakes before its deadline, in the time its spin "
        "would burn, and send at the deadline; deadline: run it from the deadline (a device read in the "
        "tick is then sampled on the deadline instead of up to the spin before it)",
    )


def add_verdict_args(p: argparse.ArgumentParser) -> None:
    """The bounds of a session's verdict (teleop.session.verdict): past them it is poor, exit 3."""
    p.add_argument(
        "--poor-share",
        type=float_range("--poor-share", 0.0, 100.0, "%"),
        default=100 * Bounds.share,
        metavar="PCT",
        help="a session is poor (its last line says why, exit status 3) when its link was lost, or "
        "when the watchdog flagged, the passivity controller acted on, or the loop skipped or "
        f"missed more than PCT%% of its ticks (default {100 * Bounds.share:g})",
    )
    p.add_argument(
        "--poor-i-factor",
        type=float_range("--poor-i-factor", 1.0, 1e9, ""),
        default=Bounds.i_factor,
        metavar="F",
        help="with both logs (run, report): a session is also poor when its transparency I is more "
        f"than F times off teleop sim's with the same settings (default {Bounds.i_factor:g})",
    )


def verdict_bounds(args: argparse.Namespace) -> Bounds:
    return Bounds(share=args.poor_share / 100, i_factor=getattr(args, "poor_i_factor", Bounds.i_factor))


def add_endpoint_args(p: argparse.ArgumentParser) -> None:
    """Options of one real process: its logs, its loop, what it prints."""
    p.add_argument(
        "--log", metavar="DIR", help="write ROLE.mcap (streamed as the session runs) and ROLE.json to DIR"
    )
    add_live_view_arg(
        p,
        "serve the log's channels live over the Foxglove WebSocket protocol on "
        f"127.0.0.1:PORT (default {LIVE_VIEW_PORT}; 0: any free port)",
    )
    add_process_args(p)
    add_verdict_args(p)
    p.add_argument("--quiet", action="store_true", help="no summary line at the end")
    p.add_argument("--live", action="store_true", help="print a status line every second (traffic, watchdog)")
    p.add_argument(
        "--wide",
        action="store_true",
        help="--live's line in full (link transit, handshake round trip), past 120 columns",
    )
    p.add_argument(
        "--grace-us",
        type=nonneg_float("grace", MAX_GRACE_US, "us", " (within the 1 ms tick)"),
        default=400.0,
        metavar="US",
        help="wait up to US microseconds into a tick for a payload that is due (default 400)",
    )
    p.add_argument(
        "--udp-rcvbuf",
        type=int_range("UDP receive buffer", 64, 65536, " KiB"),
        default=16384,
        metavar="KIB",
        help="the UDP socket's receive buffer to ask for, in KiB (default 16384): junk arriving between "
        "two ticks waits there instead of pushing genuine datagrams out; ROLE.json says what was obtained",
    )


LIVE_VIEW_PORT = 8765  # Foxglove's default WebSocket port


def add_live_view_arg(p: argparse.ArgumentParser, help_text: str) -> None:
    """--live-view [PORT]: the Foxglove WebSocket live view (``shell.mcaplog``)."""
    p.add_argument(
        "--live-view",
        nargs="?",
        const=LIVE_VIEW_PORT,
        default=None,
        type=int_range("live view port", 0, MAX_PORT, " (0: a free one)"),
        metavar="PORT",
        help=help_text,
    )


def add_key_args(p: argparse.ArgumentParser, default: str) -> None:
    """--key-file FILE or --insecure (not both): the pre-shared key that authenticates every datagram."""
    g = p.add_argument_group(
        "authentication (every datagram carries a counter and a MAC tag; see docs/guides/security.md)"
    )
    k = g.add_mutually_exclusive_group()
    k.add_argument(
        "--key-file",
        metavar="FILE",
        help=f"the pre-shared key, the same on both hosts (make one with 'teleop keygen FILE'); {default}",
    )
    k.add_argument(
        "--insecure",
        action="store_true",
        help="run unauthenticated: a key everyone knows, so the tag checks integrity only and anyone "
        "who can send a datagram can drive the robot (a lab on a closed network only)",
    )


def add_transport_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--transport", choices=["udp", "zenoh"], default="udp", help="udp (default) or zenoh")
    z = p.add_argument_group("Zenoh (with --transport zenoh; see docs/guides/zenoh.md)")
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
        default=None,
        metavar="KEY",
        help="key prefix: data on KEY/forward and KEY/backward (default: a teleoperator's is "
        "teleop/robots/NAME, announced with its name; an operator finds the robot it names and uses its)",
    )
    z.add_argument(
        "--zenoh-config",
        metavar="FILE",
        type=zenoh_config_file,
        help="Zenoh JSON5 config loaded first (deploy/zenoh/*.json5; a regular file of at most 1 MiB)",
    )


def connect_timeout(args: argparse.Namespace) -> float:
    """``--connect-timeout``, or its default: how long an operator waits for its robot's answer."""
    given: float | None = getattr(args, "connect_timeout", None)
    return CONNECT_TIMEOUT_S if given is None else given


def teleoperator_wait(args: argparse.Namespace) -> float:
    """How long a teleoperator waits for an operator's hello: ``--wait`` (0: until stopped), else
    ``--connect-timeout`` if given (``teleop run`` bounds its child so), else until stopped.  A
    robot is started before its operator, often by another person in another terminal: it waits."""
    wait: float | None = getattr(args, "wait", None)
    if wait is not None:
        return math.inf if wait == 0 else wait
    given: float | None = getattr(args, "connect_timeout", None)
    return math.inf if given is None else given
