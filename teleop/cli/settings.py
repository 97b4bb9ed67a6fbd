"""From parsed arguments to the settings of a session, and the checks that need several options.

Everything here runs before a session starts, so a bad value stops the command with a
:class:`~teleop.cli.args.CliError` (``teleop: error: ...``, exit status 2) and nothing half-done.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

from teleop import limits
from teleop.cli.args import CliError, connect_timeout, teleoperator_wait, verdict_bounds
from teleop.control.codecs import CodecError
from teleop.devices.scenarios import SCENARIOS
from teleop.session.settings import DEFAULTS, Channel

if TYPE_CHECKING:  # typed for mypy, imported when used: `teleop --help` loads neither shell nor sim
    from shell.options import EndpointOptions, ZenohOptions
    from teleop.offline.sim import SimConfig
    from teleop.session.protocol import SessionParams


def check_robot(spec: str | None, dof: int) -> None:
    """CliError when ``--robot`` cannot drive ``dof`` DoF (a built-in's check; e.g. mujoco: 1 to 3)."""
    from teleop.devices import DeviceError, check

    if spec is None:
        return
    try:
        check(spec, "robot", dof)
    except DeviceError as e:
        raise CliError(f"--robot {spec}: {e}") from None


def check_duration(duration: float, dof: int, in_memory: bool = False) -> None:
    """CliError when ``duration`` s at ``dof`` DoF (1 kHz) is out of range (``in_memory``: teleop sim,
    which must end and keeps every tick)."""
    try:
        limits.check_duration(duration, dof, dt=0.001, in_memory=in_memory)
    except ValueError as e:
        raise CliError(str(e)) from None


def _file_in_the_way(path: Path) -> Path | None:
    """The first existing component of ``path`` that is not a folder, if any."""
    for p in (*reversed(path.parents), path):
        with contextlib.suppress(OSError):
            if p.exists() and not p.is_dir():
                return p
    return None


def private_dir(path: Path, option: str) -> Path:
    """An output or log folder (every ``--out`` and ``--log``), opened where the user named it
    (``teleop.files.open_dir``: never through a symlink another user could have placed, on the way
    or as the folder), made 0755 if missing
    (whatever the umask: a umask of 002 would make it group-writable, and refused), refused if
    another user can write it or a folder on the way, and checked writable; CliError says why.
    ``shell.logdir.reserve`` walks it again."""
    from teleop.files import FileRefused, open_dir

    try:
        fd = open_dir(path, option, create=True)
    except FileRefused as e:
        blocker = _file_in_the_way(path)
        if blocker is not None and not blocker.is_symlink():
            raise CliError(
                f"{option} {path}: cannot create or write to this folder: {blocker} is a file, not a folder"
            ) from None
        raise CliError(str(e)) from None
    probe = f".teleop-write-check-{os.getpid()}"
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600, dir_fd=fd))
        os.unlink(probe, dir_fd=fd)
    except OSError as e:
        raise CliError(f"{option} {path}: cannot create or write to this folder: {e.strerror or e}") from None
    finally:
        os.close(fd)
    return path


def fresh_out(out: Path, names: list[str]) -> None:
    """CliError, before any work, if OUT already holds one of ``names``: outputs are never
    overwritten (``teleop.files.write_new`` would refuse them only once the work is done)."""
    taken = [n for n in names if os.path.lexists(out / n)]
    if taken:
        raise CliError(f"--out {out} already holds {', '.join(taken)}: outputs are never overwritten")


def netem(args: argparse.Namespace, direction: str) -> str:
    """The impairment spec of one direction: --netem-DIRECTION, else --netem, else none."""
    specific = getattr(args, f"netem_{direction}", None)
    return str(specific if specific is not None else (getattr(args, "netem", None) or ""))


def channel(args: argparse.Namespace, codec: str = DEFAULTS.codec) -> Channel:
    """The channel's settings (codec, impairment, reconstruction, passivity), parsed once from the
    command line and the same for `teleop sim` and a real session; an option a command lacks keeps
    the one default (``teleop.session.settings.DEFAULTS``).  ``codec``: the one codec of a session (a
    command that runs several sets each case's)."""
    no_controller = getattr(args, "no_controller", not DEFAULTS.controller)
    on_loss = getattr(args, "on_loss", None)
    return Channel(
        codec=codec,
        netem_forward=netem(args, "forward"),
        netem_backward=netem(args, "backward"),
        seed=getattr(args, "seed", DEFAULTS.seed),
        variation=getattr(args, "variation", DEFAULTS.variation),
        # conceal is passive only behind the controller: without it, zero unless asked otherwise
        on_loss=on_loss or ("zero" if no_controller else DEFAULTS.on_loss),
        controller=not no_controller,
        link_timeout=args.link_timeout / 1e3 if hasattr(args, "link_timeout") else DEFAULTS.link_timeout,
        rate_cap=getattr(args, "rate_cap", DEFAULTS.rate_cap),
        playout=getattr(args, "playout", DEFAULTS.playout),
        passivity=getattr(args, "passivity", DEFAULTS.passivity),
    )


def sim_config(args: argparse.Namespace) -> SimConfig:
    """The resolved ``SimConfig`` of a simulating command (sim, sweep, experiment): the model,
    impairment and passivity options; CliError says what is wrong."""
    from teleop.control.codecs import CodecError
    from teleop.offline.sim import SimConfig

    try:
        return SimConfig(
            delay_ms=getattr(args, "delay", 0.0),
            duration=args.duration,
            dof=args.dof,
            b=args.b,
            full_scale=args.range,
            scenario=args.scenario,
            hsi=getattr(args, "hsi", None),
            robot=getattr(args, "robot", None),
            **channel(args).channel_fields(),
        ).resolved()
    except (ValueError, CodecError, OSError) as e:
        raise CliError(str(e)) from None


def session_params(args: argparse.Namespace, session: int) -> SessionParams:
    """The SessionParams an operator proposes (``run`` and ``operator``), every default filled in."""
    from teleop.session.port import build_refusal
    from teleop.session.protocol import SessionParams

    sc = SCENARIOS[args.scenario]
    dof = args.dof if args.dof is not None else sc.dof
    duration = args.duration if args.duration is not None else sc.duration
    check_duration(duration, dof)
    try:
        params = SessionParams(
            session=session,
            scenario=args.scenario,
            dof=dof,
            b=args.b if args.b is not None else sc.b,
            full_scale=args.range if args.range is not None else sc.full_scale,
            duration=duration,
            phase=args.phase,
            **channel(args, args.codec).channel_fields(),
        ).validate()
    except (ValueError, CodecError, OSError) as e:
        raise CliError(str(e)) from None
    why = build_refusal(params)  # what a robot would refuse to build, said here first
    if why is not None:
        raise CliError(why)
    return params


#: A session file is one hello's parameters: a few hundred bytes, refused by size before it is read.
MAX_SESSION_FILE_BYTES = 64 * 1024


def write_session_file(folder: Path, params: SessionParams) -> Path:
    """``params`` as data for ``teleop run``'s children (``--session-file``): the hello's own fields
    (PROTOCOL.md 4.2, ``SessionParams.to_msg``) in JSON, in a new file of the run's private folder.
    Why not flags: turning settings back into options for a child to parse again needed a special
    case per setting (issue 50); the hello's fields have one writer and one strict reader."""
    from teleop.files import FileRefused, write_new

    path = folder / f".session-{params.session}.json"
    body = json.dumps({"session": params.to_msg()}, default=str, indent=1).encode()
    try:
        write_new(path, body)
    except FileRefused as e:
        raise CliError(str(e)) from None
    return path


def read_session_file(path: str) -> SessionParams:
    """The session a ``--session-file`` holds, read by the hello's parser (``SessionParams.from_msg``:
    every field present, typed and in range; the file's own netem specs are its owner's, as a
    teleoperator's flags are); CliError in one line if it is not one."""
    from teleop.errors import one_line
    from teleop.files import FileRefused, read_regular
    from teleop.session.protocol import ProtocolError, SessionParams

    try:
        doc = json.loads(read_regular(path, MAX_SESSION_FILE_BYTES, "--session-file"))
        m = doc["session"]
        own = [v for k in ("netem_forward", "netem_backward") if isinstance(v := m.get(k), str)]
        return SessionParams.from_msg(m, local_netem=own)
    except FileRefused as e:  # (its text names the flag and the file)
        raise CliError(one_line(e)) from None
    except ProtocolError as e:
        raise CliError(f"--session-file {path}: {one_line(e)}") from None
    except (ValueError, KeyError, TypeError, AttributeError) as e:  # not JSON, not a map, no session
        why = f"{type(e).__name__}: {one_line(e)}"
        raise CliError(f"--session-file {path}: not a session file ({why})") from None


NO_KEY = (
    "no key: pass --key-file FILE (make one with 'teleop keygen FILE') or --insecure to run unauthenticated"
)


def read_key(path: str) -> bytes:
    """The pre-shared key in ``path``; CliError (one line: which file, what is wrong, the fix) if bad."""
    from teleop.session import auth

    try:
        key = auth.read_key_file(path)
    except ValueError as e:
        raise CliError(str(e)) from None
    if key == auth.INSECURE_KEY:  # everyone knows it: do not let it pass for a secret
        raise CliError(f"key file {path} holds the all-zero key everyone knows; use --insecure to say so")
    return key


def endpoint_key(args: argparse.Namespace) -> tuple[bytes, bool]:
    """(psk, insecure) of one process: --key-file's key, or with --insecure the key everyone knows."""
    from teleop.session import auth

    if args.insecure:
        return auth.INSECURE_KEY, True
    if args.key_file is None:
        raise CliError(NO_KEY)
    return read_key(args.key_file), False


def endpoint_options(args: argparse.Namespace, role: str, listen: tuple[str, int]) -> EndpointOptions:
    """The EndpointOptions of one real process (``operator`` or ``teleoperator``)."""
    from shell.options import EndpointOptions

    log_dir = private_dir(Path(args.log), "--log") if args.log else None
    psk, insecure = endpoint_key(args)
    return EndpointOptions(
        role=role,
        listen=listen,
        peer=getattr(args, "peer", None),
        log_dir=log_dir,
        connect_timeout=teleoperator_wait(args) if role == "teleoperator" else connect_timeout(args),
        rt_priority=None if args.no_rt else 10,
        use_uvloop=not args.asyncio,
        tick_at=args.tick_at,
        quiet=args.quiet,
        bounds=verdict_bounds(args),
        live=args.live,
        wide=args.wide,
        grace_us=args.grace_us,
        udp_rcvbuf=args.udp_rcvbuf * 1024,
        transport=args.transport,
        zenoh=zenoh_options(args) if args.transport == "zenoh" else None,
        psk=psk,
        insecure=insecure,
        device=getattr(args, "hsi" if role == "operator" else "robot", None),
        live_view=args.live_view,
        robot_name=getattr(args, "robot_name" if role == "operator" else "name", "robot"),
    )


def zenoh_options(args: argparse.Namespace) -> ZenohOptions:
    from shell.options import ZenohOptions

    connect = list(args.zenoh_connect or [])
    if args.zenoh_router:
        connect.append(args.zenoh_router)
    return ZenohOptions(
        mode=args.zenoh_mode,
        listen=list(args.zenoh_listen or []),
        connect=connect,
        prefix=args.zenoh_prefix,
        config_file=args.zenoh_config,
        find_timeout=connect_timeout(args),  # its default where a command has none (conformance)
    )
