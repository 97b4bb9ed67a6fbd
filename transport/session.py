"""A process's side of a session: its options, its transport and its records around the real-time
runner (``transport.runner``: the loop around a sans-I/O :class:`teleop.session.endpoint.Endpoint`).

The session's records (its MCAP log, live view and ``ROLE.json``) are ``transport.records``'s; the
process's options are ``transport.options``'.  SIGINT/SIGTERM stop the session (it lingers); the
logs are still written.
"""

from __future__ import annotations

import asyncio
import math
import signal
import sys
import time
from typing import Any

from teleop.devices import DeviceError
from teleop.session import auth
from teleop.session.endpoint import Endpoint, Monitor, PortFactory, TickPolicy
from teleop.session.protocol import PROTOCOL_VERSION, Pins, SessionParams
from teleop.session.summary import SessionSummary

from . import console
from .base import Transport
from .options import EndpointOptions, Interrupted, ZenohOptions, new_session_id
from .records import RecordError, Records
from .runner import Runner, SessionError, Stop
from .udp import UdpTransport, new_event_loop
from .zenoh import ZENOH_PEER, ZenohTransport, make_config

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
async def _open_transport(opts: EndpointOptions, key: bytes) -> Transport:
    if opts.transport == "udp":
        return await UdpTransport.bind(opts.listen, rcvbuf=opts.udp_rcvbuf)
    if opts.transport == "zenoh":
        z = opts.zenoh or ZenohOptions()
        try:
            config = make_config(z.mode, z.listen, z.connect, z.config_file)
        except ValueError as e:
            raise SessionError(str(e)) from None
        return await ZenohTransport.open(opts.role, z.prefix, config, key=key)
    raise SessionError(f"unknown transport {opts.transport!r}; accepted: udp, zenoh")


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
    tr = await _open_transport(opts, key)
    if opts.role == "teleoperator" and not opts.quiet:
        print(waiting_line(opts, tr), file=sys.stderr, flush=True)
    kw: dict[str, Any] = {
        "now_ns": time.monotonic_ns(),
        "psk": key,
        "connect_timeout_s": opts.connect_timeout,
        "linger_s": opts.linger,
        "grace_us": opts.grace_us,
    }

    def build(make_port: PortFactory, ticks: TickPolicy, monitor: Monitor) -> Endpoint:
        kw.update(ticks=ticks, monitor=monitor)
        if opts.role == "operator":
            peer = ZENOH_PEER if opts.transport == "zenoh" else opts.peer
            assert params is not None and peer is not None
            return Endpoint.operator(params, peer, make_port, **kw)
        return Endpoint.teleoperator(pins or Pins(), make_port, local_limits=opts.local_limits, **kw)

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
    """Run one process's side of a session; returns the exit status (0 ok, 1 error, 130 interrupted)."""
    loop, loop_name = new_event_loop(opts.use_uvloop)
    try:
        summary = loop.run_until_complete(_endpoint(opts, params, pins))
    except Interrupted as e:
        print(f"teleop {opts.role}: {e}", file=sys.stderr)
        return 130
    except (SessionError, DeviceError) as e:  # DeviceError: this side's device cannot run the session
        print(f"teleop {opts.role}: error: {e}", file=sys.stderr)
        return 1
    except OSError as e:
        print(f"teleop {opts.role}: error: {e.strerror or e}", file=sys.stderr)
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
    return 0  # a session without a fixed end stopped by a signal ended as it should


def waiting_line(opts: EndpointOptions, tr: Transport) -> str:
    """Where a robot waits and under which name: a person starting its operator needs both."""
    if opts.transport == "zenoh" and opts.zenoh is not None:
        where = f"zenoh, prefix {opts.zenoh.prefix}"
    else:
        a = tr.local_address
        where = f"udp {a[0]}:{a[1]}"
    wait = opts.connect_timeout
    until = "until stopped (Ctrl-C)" if not math.isfinite(wait) else f"for at most {wait:g} s"
    return (
        f"teleop teleoperator: robot {opts.robot_name!r} on {where}: waiting for an operator {until}"
        f" (teleop operator --robot-name {opts.robot_name} ...)"
    )
