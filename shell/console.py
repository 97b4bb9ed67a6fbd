"""What a real-time process says of its endpoint's events: console lines and the process's summary.

Text only, kept out of the runner (``shell.runner``) so that the runner stays the loop: the
hints of a failed handshake, the lines of a replaced or skewed session, ``ROLE.json``'s process
section, and the last line of a run.
"""

from __future__ import annotations

import asyncio
import os
import sys
from typing import Any

from teleop.errors import one_line
from teleop.session import auth
from teleop.session.events import (
    ClockShifted,
    EndReason,
    Event,
    Failed,
    HelloRejected,
    LinkLost,
    LinkRestored,
    PeerRestarted,
    Replaced,
    SessionEnded,
    Unverified,
)
from teleop.session.protocol import Failure
from teleop.session.summary import ProcessSummary, SessionSummary
from transport.base import Addr, Transport

from .options import EndpointOptions

__all__ = ["addr_text", "clock_shift_text", "failure", "last_line", "log_line", "process_summary", "say"]


def addr_text(a: Addr) -> str:
    return f"{a[0]}:{a[1]}"


def failure(opts: EndpointOptions, tr: Transport, ev: Failed) -> str:
    """A failed handshake as one line, with a hint at the likely cause."""
    o = opts
    if o.role == "teleoperator":
        return f"{ev.detail} on {addr_text(tr.local_address)}"
    peer = addr_text(o.peer) if o.peer is not None else "zenoh"
    hint = ""
    if ev.reason == Failure.NO_ANSWER:  # nothing came back: absent, unreachable, or silent
        hint = (
            f" (nothing came back: is `teleop teleoperator --listen {peer} --name {o.robot_name}`"
            " running and reachable? A robot of another name, or another key, stays silent too)"
        )
    elif ev.reason == Failure.THROTTLED:
        hint = " (it answered with retries only: it dropped our hellos with their cookie; flooded?)"
    elif ev.reason == Failure.UNVERIFIED:  # the one case that points at the key
        hint = (
            f" (answers came whose MAC did not verify: does the teleoperator hold the same key,"
            f" with --name {o.robot_name}?)"
        )
    return f"peer {peer} {ev.detail}{hint}"


def clock_shift_text(ev: ClockShifted) -> str:
    return f"tick 0 moved {ev.ticks} ticks earlier at tick {ev.k}: the peer's packets came before they left"


def log_line(ev: Event) -> tuple[str, str] | None:
    """The log's event (name, text) for ``ev``, if it has one (the session start's is the runner's)."""
    if isinstance(ev, ClockShifted):
        return "clock_shifted", clock_shift_text(ev)
    if isinstance(ev, PeerRestarted | LinkLost | LinkRestored):
        name = {PeerRestarted: "peer_rejoined", LinkLost: "link_lost", LinkRestored: "link_restored"}
        return name[type(ev)], f"tick {ev.k}"
    return None


def say(opts: EndpointOptions, ev: Event) -> None:
    """The console's line for ``ev``, if it has one."""
    role, line = opts.role, None
    if isinstance(ev, HelloRejected):
        line = f"rejected the operator: {ev.why}"
    elif isinstance(ev, Unverified):
        line = (
            f"refused {ev.count} datagram(s) whose tag failed, the last from {addr_text(ev.addr)} "
            f"({ev.why}): an operator with a different key, or naming another robot?"
        )
    elif isinstance(ev, Replaced) and not opts.quiet:
        line = f"session {ev.old_session} replaced by a new operator"
    elif isinstance(ev, ClockShifted) and not opts.quiet:
        line = f"clock skew: {clock_shift_text(ev)}"
    elif isinstance(ev, SessionEnded) and ev.reason == EndReason.PEER_SILENT:
        line = (
            f"session {ev.summary.params.session} ended: not one packet from"
            f" the operator since its start; waiting for an operator"
        )
    elif isinstance(ev, SessionEnded) and ev.reason == EndReason.PEER_FAULT:
        line = f"the peer's device ended the session: {ev.summary.fault}"
    if line is not None:  # a peer's text among it (a reject's or bye's why): escaped, one line
        print(f"teleop {role}: {one_line(line)}", file=sys.stderr, flush=True)


def process_summary(
    opts: EndpointOptions,
    tr: Transport,
    stopped_by: int | None,
    waited_s: float | None,
    loop: dict[str, object] | None,
    warnings: list[str],
) -> ProcessSummary:
    """``ROLE.json``'s process section: what the endpoint cannot know."""
    o = opts
    return ProcessSummary(
        pid=os.getpid(),
        local=addr_text(tr.local_address),
        transport=o.transport,
        robot=o.robot_name,
        auth="insecure" if o.insecure else "blake2s-128",
        key_id=auth.key_id(o.psk or b""),
        event_loop=type(asyncio.get_running_loop()).__module__.split(".")[0],
        stopped_by_signal=stopped_by,
        waited_for_session_s=waited_s,
        loop=loop,
        warnings=warnings,
        received=tr.report(),  # oversize: refused by length (Transport.max_datagram)
    )


def last_line(opts: EndpointOptions, summary: SessionSummary, loop_name: str) -> None:
    """The run's last line: the loop's timing and the traffic."""
    proc = summary.process
    if opts.quiet or proc is None or not proc.loop:
        return
    lp: Any = proc.loop
    port = summary.endpoint.port
    pe = lp["period_error_us"]
    print(
        f"teleop {opts.role} [{loop_name}]: {lp['ticks']} ticks, overruns {lp['overruns']}, "
        f"period error p50/p99/max {pe['p50']:.1f}/{pe['p99']:.1f}/{pe['max']:.0f} us, "
        f"CPU {100 * lp['cpu_fraction']:.0f}%, sent {port['sent']['packets']} packets, "
        f"received {port['received']['packets']}",
        file=sys.stderr,
    )
