"""A process's side of a session: its options, its transport and its records around the real-time
runner (``shell.runner``: the loop around a sans-I/O :class:`teleop.session.endpoint.Endpoint`).

The session's records (its MCAP log, live view and ``ROLE.json``) are ``shell.records``'s; the
process's options are ``shell.options``'.  SIGINT/SIGTERM stop the session (it lingers); the
logs are still written.
"""

from __future__ import annotations

import asyncio
import math
import signal
import sys
import time
from collections.abc import Callable
from typing import Any

from teleop.devices import DeviceError
from teleop.errors import one_line
from teleop.session import auth
from teleop.session import fleet as fl
from teleop.session.endpoint import Endpoint, PortFactory, State
from teleop.session.protocol import PROTOCOL_VERSION, Pins, SessionParams
from teleop.session.summary import SessionSummary
from teleop.session.verdict import judge_process
from transport.base import Transport
from transport.fleet import Announcer, find_robot
from transport.udp import UdpTransport, new_event_loop
from transport.zenoh import ZENOH_PEER, ZenohTransport, make_config

from . import console
from .options import EndpointOptions, Interrupted, ZenohOptions, new_session_id
from .records import RecordError, Records
from .runner import Runner, SessionError, Stop

__all__ = [
    "PROTOCOL_VERSION",
    "EndpointOptions",
    "SessionError",
    "SessionParams",
    "ZenohOptions",
    "new_session_id",
    "run_endpoint",
]


# --------------------------------------------------------------------------------------------
# entry points
# --------------------------------------------------------------------------------------------
async def _open_transport(
    opts: EndpointOptions, key: bytes, describe: Callable[[], fl.Description] | None = None
) -> Transport:
    """The session's transport.  Over Zenoh a teleoperator announces itself (``describe``, its
    state now: transport.fleet) and an operator given no prefix finds the robot it names."""
    if opts.transport == "udp":
        return await UdpTransport.bind(opts.listen, rcvbuf=opts.udp_rcvbuf)
    if opts.transport == "zenoh":
        z = opts.zenoh or ZenohOptions()
        name = opts.robot_name
        try:
            config = make_config(
                z.mode, z.listen, z.connect, z.config_file, announcing=opts.role == "teleoperator"
            )
        except ValueError as e:
            raise SessionError(str(e)) from None
        locate: Callable[[Any], str] | None = None
        announce: Callable[[Any], Any] | None = None
        prefix = z.prefix or fl.default_prefix(name)
        if opts.role == "operator" and z.prefix is None:
            assert opts.psk is not None
            psk, wait = opts.psk, z.find_timeout

            def locate(session: Any) -> str:
                d = find_robot(session, psk, name, wait)
                found = f"found robot {name} ({d.kind}, {d.dof} DoF, {d.state}) on {d.prefix}"
                print(f"teleop operator: {one_line(found)}")  # (the robot's own description)
                return d.prefix

        elif opts.role == "teleoperator" and describe is not None:

            def announce(session: Any) -> Announcer:
                return Announcer(session, name, key, describe)

        return await ZenohTransport.open(opts.role, prefix, config, key=key, locate=locate, announce=announce)
    raise SessionError(f"unknown transport {opts.transport!r}; accepted: udp, zenoh")


def _describer(
    opts: EndpointOptions, pins: Pins | None, prefix: str, built: list[Endpoint]
) -> Callable[[], fl.Description]:
    """The teleoperator's description now: free until a session is claimed by a handshake, busy while
    it runs (its session id shown only with ``show_holder``).  Read on a Zenoh thread."""
    env = opts.local_limits
    dof = (pins.dof if pins is not None else None) or env.max_dof
    kind = (opts.device or "sim").partition(":")[0][: fl.MAX_KIND] or "sim"
    fields = fl.envelope_fields(env)
    busy_states = (State.STARTING, State.RUNNING, State.LINGER)

    def describe() -> fl.Description:
        ep = built[0] if built else None
        busy = ep is not None and ep.state in busy_states
        holder = ep.params.session if busy and opts.show_holder and ep is not None and ep.params else None
        state = "busy" if busy else "free"
        return fl.Description(opts.robot_name, dof, kind, prefix, state, holder, fields)

    return describe


async def _endpoint(opts: EndpointOptions, params: SessionParams | None, pins: Pins | None) -> SessionSummary:
    if opts.psk is None:
        raise SessionError("no key: give the pre-shared key (teleop keygen) or choose insecure")
    try:
        key = auth.robot_key(opts.psk, opts.robot_name)
    except ValueError as e:
        raise SessionError(str(e)) from None
    loop = asyncio.get_running_loop()
    stop = Stop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, stop, sig)
    built: list[Endpoint] = []  # the endpoint, once built: what the robot's description reads
    z = opts.zenoh or ZenohOptions()
    describe = _describer(opts, pins, (z.prefix or fl.default_prefix(opts.robot_name)).strip("/"), built)
    tr = await _open_transport(opts, key, describe)
    if opts.role == "teleoperator" and not opts.quiet:
        print(waiting_line(opts, tr), file=sys.stderr, flush=True)
    kw: dict[str, Any] = {
        "now_ns": time.monotonic_ns(),
        "psk": key,
        "connect_timeout_s": opts.connect_timeout,
        "linger_s": opts.linger,
    }

    def build(make_port: PortFactory) -> Endpoint:
        if opts.role == "operator":
            peer = ZENOH_PEER if opts.transport == "zenoh" else opts.peer
            assert params is not None and peer is not None
            return Endpoint.operator(params, peer, make_port, **kw)
        ep = Endpoint.teleoperator(pins or Pins(), make_port, local_limits=opts.local_limits, **kw)
        built.append(ep)
        return ep

    records = Records(opts.role, opts.log_dir, opts.live_view, opts.live_view_host)
    try:
        summary = await Runner(opts, tr, stop, records, build).run()
        await asyncio.to_thread(records.wait_finished)
        return summary
    except RecordError as e:
        raise SessionError(str(e)) from None
    finally:
        tr.close()
        records.close()


def run_endpoint(opts: EndpointOptions, params: SessionParams | None = None, pins: Pins | None = None) -> int:
    """Run one process's side of a session; returns the exit status (0 ok, 1 error, 3 a poor session:
    :mod:`teleop.session.verdict`, 130 interrupted)."""
    loop, loop_name = new_event_loop(opts.use_uvloop)
    try:
        summary = loop.run_until_complete(_endpoint(opts, params, pins))
    except Interrupted as e:
        print(f"teleop {opts.role}: {one_line(e)}", file=sys.stderr)
        return 130
    except (SessionError, DeviceError) as e:  # DeviceError: this side's device cannot run the session
        # (a peer's text among it: the robot's reject why, escaped on one line; issue 49)
        print(f"teleop {opts.role}: error: {one_line(e)}", file=sys.stderr)
        return 1
    except OSError as e:
        print(f"teleop {opts.role}: error: {one_line(e.strerror or e)}", file=sys.stderr)
        return 1
    finally:
        loop.close()
    proc = summary.process
    assert proc is not None
    console.last_line(opts, summary, loop_name)
    if summary.endpoint.fault:  # a device ended the session (this side's or the peer's): said above
        return 1
    if proc.stopped_by_signal is not None and not summary.endpoint.params.until_stopped:
        return 128 + proc.stopped_by_signal
    # A session without a fixed end stopped by a signal ended as it should: judged as any other.
    verdict = judge_process(summary.document(), opts.bounds)
    if not opts.quiet:
        print(verdict.line(f"teleop {opts.role}"), file=sys.stderr)
    return verdict.exit_status


def waiting_line(opts: EndpointOptions, tr: Transport) -> str:
    """Where a robot waits and under which name: a person starting its operator needs both."""
    if opts.transport == "zenoh":
        prefix = (opts.zenoh.prefix if opts.zenoh else None) or fl.default_prefix(opts.robot_name)
        where = f"zenoh, keys {prefix.strip('/')}"
    else:
        a = tr.local_address
        where = f"udp {a[0]}:{a[1]}"
    wait = opts.connect_timeout
    until = "until stopped (Ctrl-C)" if not math.isfinite(wait) else f"for at most {wait:g} s"
    return (
        f"teleop teleoperator: robot {opts.robot_name!r} on {where}: waiting for an operator {until}"
        f" (teleop operator --robot-name {opts.robot_name} ...)"
    )
