"""``teleop run``: a teleoperator and an operator as two processes on 127.0.0.1, then one report.

The two children are ``python -m teleop.cli teleoperator ...`` and ``... operator ...`` (and, for
Zenoh clients without a router, ``... router``); every setting of the session is checked here first
and passed on explicitly, so the children never fall back on a default of their own.

Authenticated with no setup: unless given ``--key-file`` or ``--insecure``, a run makes a new key in
an anonymous memory file (never on disk) that both children inherit and read as
``--key-file /proc/self/fd/N``; it is gone when the last of them exits, whatever ended the run.
"""

from __future__ import annotations

import argparse
import contextlib
import fcntl
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import FrameType
from typing import Any

from teleop.cli.args import (
    MAX_PORT,
    CliError,
    Subcommands,
    add_device_args,
    add_key_args,
    add_live_view_arg,
    add_netem_args,
    add_passivity_args,
    add_process_args,
    add_session_args,
    add_verdict_args,
    connect_timeout,
    int_range,
    verdict_bounds,
)
from teleop.cli.report import write_report
from teleop.cli.settings import check_robot, private_dir, read_key, session_params, write_session_file
from teleop.session.settings import DEFAULT_CODEC, DEFAULT_SCENARIO
from teleop.session.verdict import POOR_EXIT, judge_report

TELEOP = [sys.executable, "-m", "teleop.cli"]


@dataclass
class Network:
    """How the two children reach each other, and what to say about it."""

    teleoperator: list[str]  # network options of the teleoperator's command line
    operator: list[str]  # ... and of the operator's
    where: str  # for the first printed line
    router: list[str] | None = None  # command line of a Zenoh router to start first, if any
    zenoh: dict[str, Any] | None = None  # recorded in report.json


def _free_port(kind: int) -> int:

    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def _network(args: argparse.Namespace, session: int) -> Network:

    if args.transport == "udp":
        port = args.port or _free_port(socket.SOCK_DGRAM)
        return Network(
            teleoperator=["--listen", f"127.0.0.1:{port}"],
            operator=["--peer", f"127.0.0.1:{port}", "--listen", "127.0.0.1:0"],
            where=f"teleoperator on udp 127.0.0.1:{port}",
        )
    prefix = f"teleop/run-{session}"
    zport = args.port or _free_port(socket.SOCK_STREAM)
    zen = ["--transport", "zenoh", "--zenoh-prefix", prefix]
    router: list[str] | None = None
    if args.zenoh_mode == "peer":
        endpoint = f"tcp/127.0.0.1:{zport}"
        to_net = [*zen, "--zenoh-mode", "peer", "--zenoh-listen", endpoint]
        op_net = [*zen, "--zenoh-mode", "peer", "--zenoh-connect", endpoint]
        where = f"zenoh peers, teleoperator listening on {endpoint}"
    else:
        endpoint = args.zenoh_router or f"tcp/127.0.0.1:{zport}"
        if not args.zenoh_router:
            router = [*TELEOP, "router", "--listen", endpoint]
        to_net = op_net = [*zen, "--zenoh-mode", "client", "--zenoh-router", endpoint]
        where = f"zenoh clients through the router at {endpoint}"
    zenoh = {
        "mode": args.zenoh_mode,
        "prefix": prefix,
        "endpoint": endpoint,
        "router_launched": router is not None,
    }
    return Network(to_net, op_net, where, router, zenoh)


@dataclass
class RunKey:
    """The key both children use: their options, and what report.json says about it."""

    options: list[str]  # ["--key-file", PATH] or ["--insecure"]
    source: str  # "ephemeral" (made for this run), "key-file" (--key-file) or "insecure"
    key_id: str  # teleop.session.auth.key_id: names the key without revealing it
    pass_fds: tuple[int, ...] = ()  # descriptors the children inherit (the ephemeral key's)


def _exit_on_signal(signum: int, frame: FrameType | None) -> None:
    raise SystemExit(128 + signum)


@contextlib.contextmanager
def _exit_cleanly_on_termination() -> Iterator[None]:
    """SIGTERM or SIGHUP (a closed terminal) unwind like an error: children stopped, key removed."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    for sig in (signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(sig) is signal.SIG_DFL:
            previous[sig] = signal.signal(sig, _exit_on_signal)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


@contextlib.contextmanager
def run_key(args: argparse.Namespace) -> Iterator[RunKey]:
    """The key of one run: --insecure, --key-file (checked now), or a new one that never lands on
    disk: it is held in an anonymous memory file (``memfd_create``, mode 0600, sealed) that the
    children inherit and read as ``--key-file /proc/self/fd/N``, with a key file's checks.

    Why not a file in a private temporary folder: ``kill -9`` of ``teleop run`` left it behind
    (nothing runs to remove it); a memory file is gone once the last process holding it exits."""
    from teleop.session import auth

    if args.insecure:
        yield RunKey(["--insecure"], "insecure", auth.key_id(auth.INSECURE_KEY))
        return
    if args.key_file is not None:
        key = read_key(args.key_file)
        yield RunKey(["--key-file", os.path.abspath(args.key_file)], "key-file", auth.key_id(key))
        return
    key = auth.generate_key()
    try:
        fd = os.memfd_create("teleop-run-key", os.MFD_CLOEXEC | os.MFD_ALLOW_SEALING)
    except (AttributeError, OSError) as e:  # not Linux
        raise CliError(
            f"cannot hold the run's key in memory ({getattr(e, 'strerror', None) or e}): "
            "pass --key-file FILE (teleop keygen FILE)"
        ) from None
    try:
        os.fchmod(fd, 0o600)
        os.write(fd, (key.hex() + "\n").encode())
        seals = fcntl.F_SEAL_SEAL | fcntl.F_SEAL_SHRINK | fcntl.F_SEAL_GROW | fcntl.F_SEAL_WRITE
        fcntl.fcntl(fd, fcntl.F_ADD_SEALS, seals)  # the children read it; nobody changes it
        read_key(f"/proc/self/fd/{fd}")  # the very checks the children make
        with _exit_cleanly_on_termination():
            yield RunKey(["--key-file", f"/proc/self/fd/{fd}"], "ephemeral", auth.key_id(key), (fd,))
    finally:
        os.close(fd)


@dataclass
class Commands:
    """The command lines of one run."""

    net: Network
    teleoperator: list[str]
    operator: list[str]


def build_commands(args: argparse.Namespace, params: Any, logs: Path, key: RunKey) -> Commands:
    """Both children's command lines: network, process and key options, and the session as data.

    The session goes to both as a file of the hello's fields (``--session-file``), never re-spelled
    as flags: the operator proposes it, the teleoperator admits exactly it (the user chose it for
    both sides) and knows its impairment (a trace file only its own may name)."""
    net = _network(args, params.session)
    session = ["--session-file", str(write_session_file(logs, params))]
    common = [*_process_options(args, logs), *key.options, *session]
    # Each side's device is its own local choice: the robot goes to the teleoperator only.
    robot = ["--robot", args.robot] if args.robot is not None else []
    hsi = ["--hsi", args.hsi] if args.hsi is not None else []
    view_op, view_to = _live_view_options(args)
    to_cmd = [*TELEOP, "teleoperator", *net.teleoperator, *robot, *view_to, *common]
    live = [] if args.no_live else ["--live", *(["--wide"] if args.wide else [])]
    op_cmd = [*TELEOP, "operator", *net.operator, *live, *hsi, *view_op, *common]
    return Commands(net, to_cmd, op_cmd)


def _process_options(args: argparse.Namespace, logs: Path) -> list[str]:
    """Options both children get: where to log, how long to wait, which loop."""
    common = ["--log", str(logs), "--connect-timeout", str(connect_timeout(args)), "--quiet"]
    common += ["--no-rt"] if args.no_rt else []
    common += ["--asyncio"] if args.asyncio else []
    common += ["--tick-at", args.tick_at]
    return common


def _live_view_options(args: argparse.Namespace) -> tuple[list[str], list[str]]:
    """--live-view PORT: the operator's view on PORT, the teleoperator's on PORT + 1 (0: free ones)."""
    port = args.live_view
    if port is None:
        return [], []
    if port == MAX_PORT:
        raise CliError(f"--live-view needs PORT and PORT + 1 (one per process): at most {MAX_PORT - 1}")
    return ["--live-view", str(port)], ["--live-view", str(port + 1 if port else 0)]


def _die_with_parent() -> None:
    """In a child: get SIGTERM if the launcher dies, so no process is left orphaned."""
    import ctypes

    with contextlib.suppress(OSError):
        ctypes.CDLL("libc.so.6").prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def _spawn(cmd: list[str], pass_fds: tuple[int, ...] = ()) -> subprocess.Popen[bytes]:
    return subprocess.Popen(cmd, preexec_fn=_die_with_parent, pass_fds=pass_fds)


def _stop(procs: list[subprocess.Popen[bytes]]) -> None:
    """SIGINT to every process still running, then wait for each (killing one that hangs; 30 s:
    a process finishes its MCAP log, whose writer may be some chunks behind, before it exits)."""
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for p in procs:
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def _start_router(net: Network) -> subprocess.Popen[bytes] | None:
    if net.router is None:
        return None
    router = _spawn(net.router)
    time.sleep(0.5)
    if router.poll() is not None:
        raise CliError(f"the Zenoh router failed to start on {net.zenoh and net.zenoh['endpoint']}")
    return router


def _run_pair(
    to_cmd: list[str], op_cmd: list[str], timeout: float, pass_fds: tuple[int, ...] = ()
) -> tuple[dict[str, int | None], bool]:
    """Run the teleoperator, then the operator, until both exit (or ``timeout`` s, then CliError).

    Returns their exit codes and whether Ctrl-C stopped them.
    """
    procs = [_spawn(to_cmd, pass_fds)]
    interrupted = False
    try:
        time.sleep(0.3)  # let the teleoperator bind before the operator says hello
        procs.append(_spawn(op_cmd, pass_fds))
        limit = time.monotonic() + timeout
        while any(p.poll() is None for p in procs):
            if time.monotonic() > limit:
                raise CliError("the processes did not finish in time; stopped them")
            if any(p.returncode not in (None, 0, POOR_EXIT) for p in procs):
                for p in procs:  # one side failed: do not leave the other waiting
                    if p.poll() is None:
                        p.send_signal(signal.SIGTERM)
            time.sleep(0.05)
    except KeyboardInterrupt:
        interrupted = True
        print("teleop run: interrupted; stopping both processes", file=sys.stderr)
    finally:
        _stop(procs)
    operator = procs[1].returncode if len(procs) > 1 else None
    return {"teleoperator": procs[0].returncode, "operator": operator}, interrupted


def exits(codes: dict[str, int | None]) -> str:
    """How each process ended, as words: ``teleoperator exited 1, operator stopped by SIGTERM``."""

    def one(code: int | None) -> str:
        if code is None:
            return "never started"
        if code < 0:
            try:
                return f"stopped by {signal.Signals(-code).name}"
            except ValueError:
                return f"stopped by signal {-code}"
        if code == POOR_EXIT:
            return f"exited {code} (a poor session)"
        return "exited 0 (ok)" if code == 0 else f"exited {code}"

    return ", ".join(f"{role} {one(code)}" for role, code in codes.items())


def cmd_run(args: argparse.Namespace) -> int:
    from shell.options import new_session_id

    params = session_params(args, new_session_id())
    check_robot(args.robot, params.dof)
    out = private_dir(Path(args.out), "--out")
    logs = private_dir(out / "logs", "--out")
    # Logs of earlier runs stay: this run's files get names of their own (shell.logdir), and
    # the report pairs them by this session's id.
    with run_key(args) as key:
        cmds = build_commands(args, params, logs, key)
        net = cmds.net
        length = "until Ctrl-C" if params.until_stopped else f"{params.duration:g} s"
        print(
            f"teleop run: {net.where}; {params.codec}, {params.scenario}, {length}; logs in {logs}",
            flush=True,
        )
        if args.live_view is not None:
            view = (
                "free ports (see each process's log)"
                if args.live_view == 0
                else (f"ws://127.0.0.1:{args.live_view} (operator) and :{args.live_view + 1} (teleoperator)")
            )
            print(f"teleop run: live view (Foxglove WebSocket) on {view}", flush=True)
        # The children stop on SIGINT whatever they inherited (asyncio installs their handlers), so
        # the launcher must too: started with SIGINT ignored (`teleop run &` in a script, nohup), it
        # missed the Ctrl-C its children obeyed and reported their exit 130 as a failure.
        signal.signal(signal.SIGINT, signal.default_int_handler)
        router = _start_router(net)
        try:
            wait = connect_timeout(args)
            timeout = math.inf if params.until_stopped else params.duration + 2 * wait + 10
            codes, interrupted = _run_pair(cmds.teleoperator, cmds.operator, timeout, key.pass_fds)
        finally:
            if router is not None:
                _stop([router])
    from teleop.offline.logfile import LogError, find_pair

    try:
        find_pair(logs, params.session)
    except LogError:
        raise CliError(f"no report: a process failed before its loop ran ({exits(codes)})") from None
    extra: dict[str, Any] = {"exit_codes": codes, "auth": {"key": key.source, "key_id": key.key_id}}
    if net.zenoh is not None:
        extra["zenoh"] = net.zenoh
    # After a Ctrl-C the report is written but neither the sim re-run nor the plots drawn (seconds
    # of work): every command ends within a second of Ctrl-C; `teleop report LOGS` does both later.
    skip = "interrupted (Ctrl-C); teleop report LOGS builds the comparison" if interrupted else None
    if interrupted and not args.no_plots:
        args.no_plots = True
        print(f"teleop run: interrupted: plots not drawn (teleop report {logs} draws them)", flush=True)
    rep = write_report(
        logs, out, args, args.transport, extra, session=params.session, command="teleop run", skip_sim=skip
    )
    if interrupted and not params.until_stopped:  # an open session ends with Ctrl-C: that is no error
        print("teleop run: verdict: interrupted (exit 130)", flush=True)
        return 130
    if any(c not in (0, POOR_EXIT) for c in codes.values()):
        print(f"teleop run: verdict: failed (exit 1): {exits(codes)}", flush=True)
        return 1
    # Each child judged its own side (exit 3: poor); the report judges both and the real I too.
    verdict = judge_report(rep, verdict_bounds(args))
    print(verdict.line("teleop run"), flush=True)
    return verdict.exit_status


def add_parser(sub: Subcommands) -> None:
    r = sub.add_parser(
        "run",
        help="launch operator and teleoperator as two processes on 127.0.0.1 and report",
        description="Launch both processes on 127.0.0.1 over UDP, wait for them, gather both logs and "
        "write OUT/report.json, PNG plots and a printed summary. Ctrl-C stops both cleanly. Their "
        "datagrams are authenticated with a key made for this run unless --key-file or --insecure "
        "is given.",
    )
    add_session_args(r, DEFAULT_CODEC, DEFAULT_SCENARIO)
    add_device_args(r, ("hsi", "robot"))
    add_netem_args(r)
    add_passivity_args(r)
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
    r.add_argument(
        "--port",
        type=int_range("port", 0, MAX_PORT, " (0: a free one)"),
        default=0,
        help="teleoperator UDP port (default: a free one)",
    )
    add_process_args(r)
    add_verdict_args(r)
    add_key_args(r, "default: a new key for this run, held in memory and handed to both processes")
    r.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    r.add_argument("--no-sim", action="store_true", help="skip the teleop sim comparison in the report")
    r.add_argument("--no-live", action="store_true", help="no status line every second during the run")
    r.add_argument("--wide", action="store_true", help="the status line in full, past 120 columns")
    add_live_view_arg(
        r,
        "serve both processes' log channels live over the Foxglove WebSocket protocol: the operator "
        "on 127.0.0.1:PORT, the teleoperator on PORT + 1 (default 8765; 0: free ports)",
    )
    r.set_defaults(func=cmd_run)
