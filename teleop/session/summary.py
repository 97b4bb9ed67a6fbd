"""The summary of one process's session, typed, and the one place ``ROLE.json`` is laid out.

Three parts are built by three owners: the port's figures (:meth:`teleop.session.port.Port.summary`), the
endpoint's session around them (:class:`EndpointSummary`, :meth:`teleop.session.endpoint.Endpoint.summary`),
and the process's (:class:`ProcessSummary`: the loop, the transport, the key, the log; built by the
real runner, which reads clocks and sockets).  :meth:`SessionSummary.document` lays them out as the
JSON document PROTOCOL.md documents (``ROLE.json``, and the same map in the MCAP log), so there is
one layout however many places write it.  The port's sections stay maps: they are figures of the
counters, the link observer, the playout buffer and the watchdog, each documented where it is made.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

from teleop.session.protocol import SessionParams


@dataclass(frozen=True)
class RejoinFigures:
    """Rejoins of this session (PROTOCOL.md 4.4)."""

    offers: int  # teleoperator: rejoin offers sent; operator: offers received
    retries: int  # operator: starts resent before the teleoperator confirmed
    rejoins: int  # times the session was rejoined after a restart
    own_offers_ignored: int  # teleoperator: offers that were its own operator's, already running


@dataclass(frozen=True)
class EndpointSummary:
    """One session as the sans-I/O endpoint saw it: how it ended, the handshake, the port's figures."""

    role: str
    peer: str
    completed: bool
    end: str | None  # teleop.session.events.EndReason's value
    peer_said_bye: bool
    first_tick: int
    replaced_by_new_session: bool
    rejoin: RejoinFigures
    busy_rejects: int
    handshake_throttled: int
    oversize_refused: int
    retries_sent: int
    foreign: int  # datagrams from an address other than the peer's, dropped
    shim: dict[str, Any] | None  # the outgoing netem shim's spec and counters
    params: SessionParams
    handshake: dict[str, Any]  # clock_offset_ns and handshake_rtt_us, or joined_late
    port: dict[str, Any]  # teleop.session.port.Port.summary: sent, received, link_received, ...
    fault: str = ""  # why a device ended the session (this side's, or the peer's bye said), else ""
    #: The scheduler's grace figures (limit_us, waits, missed, waited_us_total: it fills them in);
    #: empty from an endpoint whose caller ran its ticks.
    grace: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class LogFigures:
    """What the log writer did: the file, the messages, what it dropped, why it stopped."""

    mcap: str | None
    messages: int
    dropped_chunks: int
    live_view_port: int | None
    error: str | None


@dataclass
class ProcessSummary:
    """What the real process adds: the transport's drops, the loop's timing, the key, the log."""

    pid: int
    local: str
    transport: str
    robot: str
    auth: str  # "blake2s-128" or "insecure"
    key_id: str
    event_loop: str
    stopped_by_signal: int | None = None
    waited_for_session_s: float | None = None
    loop: dict[str, Any] | None = None  # shell.realtime.LoopStats.summary
    warnings: list[str] = field(default_factory=list)
    # The transport's counters (Transport.report: inbox_overflow, socket_errors, oversize refused by
    # length before any work; UDP also its receive buffer and the kernel's drops), under ``received``.
    received: dict[str, Any] = field(default_factory=dict)
    log: LogFigures | None = None


@dataclass
class SessionSummary:
    """The endpoint's summary of one session and the process's around it."""

    endpoint: EndpointSummary
    process: ProcessSummary | None = None

    def document(self, **extra: Any) -> dict[str, Any]:
        """The JSON map (``ROLE.json``): the endpoint's fields, the port's sections at the top level,
        the process's fields, with the transport's drops under ``received`` and the key under
        ``security``; ``extra`` (``end_t`` in the MCAP log) last."""
        e = self.endpoint
        port = {k: dict(v) if isinstance(v, dict) else v for k, v in e.port.items()}
        port["received"]["foreign"] = e.foreign
        doc: dict[str, Any] = {
            "role": e.role,
            "peer": e.peer,
            "completed": e.completed,
            "end": e.end,
            "peer_said_bye": e.peer_said_bye,
            **({"fault": e.fault} if e.fault else {}),
            "first_tick": e.first_tick,
            "replaced_by_new_session": e.replaced_by_new_session,
            "rejoin": dataclasses.asdict(e.rejoin),
            "busy_rejects": e.busy_rejects,
            "handshake_throttled": e.handshake_throttled,
            "oversize_refused": e.oversize_refused,
            "retries_sent": e.retries_sent,
            "shim": e.shim,
            "grace": dict(e.grace),
            "params": dataclasses.asdict(e.params),
            **e.handshake,
            **port,
        }
        p = self.process
        if p is not None:
            doc["received"].update(p.received)
            doc["security"].update(auth=p.auth, key_id=p.key_id)
            doc.update(
                pid=p.pid,
                local=p.local,
                transport=p.transport,
                stopped_by_signal=p.stopped_by_signal,
                robot=p.robot,
                waited_for_session_s=p.waited_for_session_s,
                loop=p.loop,
                warnings=list(p.warnings),
                event_loop=p.event_loop,
            )
            if p.log is not None:
                doc["log"] = dataclasses.asdict(p.log)
        return {**doc, **extra}
