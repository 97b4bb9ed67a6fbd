"""The endpoint's events (``Endpoint.next_event``, ``Scheduler.next_event``), as aioquic keeps
``quic/events.py``: plain frozen records, no behaviour.  The runner turns them into log messages,
console lines and records (``shell.runner``); the tests read them in virtual time.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any, TypeAlias

from teleop.session.admission import Admission
from teleop.session.link import Addr
from teleop.session.protocol import Failure, SessionParams
from teleop.session.schedule import LoopFigures
from teleop.session.summary import EndpointSummary

__all__ = [
    "AdmissionChanged",
    "ClockShifted",
    "EndReason",
    "Event",
    "Failed",
    "HelloRejected",
    "LinkLost",
    "LinkRestored",
    "PeerBye",
    "PeerRestarted",
    "Replaced",
    "SessionEnded",
    "SessionStarted",
    "TicksEnded",
    "Unverified",
]


class EndReason(enum.Enum):
    COMPLETED = "completed"  # the agreed ticks ran
    STOPPED = "stopped"  # stopped locally (a signal)
    PEER_BYE = "peer_bye"  # an open session whose peer said bye
    REPLACED = "replaced"  # teleoperator: a new operator took the silent one's place
    DEVICE_FAULT = "device_fault"  # this side's device ended the session (a reflex): bye says why
    PEER_FAULT = "peer_fault"  # the peer's device ended it: its bye said why
    PEER_SILENT = "peer_silent"  # teleoperator: not one packet from the operator since its start


@dataclass(frozen=True)
class SessionStarted:
    params: SessionParams
    peer: Addr
    start_ns: int  # the session's tick 0 on this clock
    t0_ns: int  # when tick 0 is due on this clock (the teleoperator runs ``phase`` behind)
    k0: int  # the first tick this process runs (> 0: it joined a running session)
    joined_late: bool
    offset_ns: int = 0  # operator: teleoperator's clock - ours, and the exchange's round trip
    rtt_ns: int = 0
    device: Any = None  # the device that paces this session's ticks (a real arm), if any


@dataclass(frozen=True)
class TicksEnded:
    """The session's ticks are over after tick ``k`` (it lingers now, or was replaced).  ``loop``:
    their timing, from the :class:`teleop.session.scheduler.Scheduler` that ran them (None from the
    endpoint itself, whose caller ran them)."""

    k: int
    loop: LoopFigures | None = None


@dataclass(frozen=True)
class AdmissionChanged:
    """What the endpoint can take changed (:meth:`Endpoint.admission`), said by the scheduler: for
    the transport's filter and its length limit (an endpoint whose ticks are timers only)."""

    admission: Admission


@dataclass(frozen=True)
class PeerRestarted:
    """Operator: a restarted teleoperator took the session over (re-keyed, new energy epoch)."""

    k: int
    rtt_ns: int  # of the exchange that placed its start: the start's error is at most half this


@dataclass(frozen=True)
class ClockShifted:
    """The peer's packets seemed to arrive before they were sent: this side's tick 0 moved
    ``ticks`` earlier (its loop skips them), instead of running tick ``k`` (``teleop.session.link.phase``)."""

    k: int
    ticks: int


@dataclass(frozen=True)
class Replaced:
    old_session: int
    new_session: int


@dataclass(frozen=True)
class PeerBye:
    produced: int


@dataclass(frozen=True)
class LinkLost:
    k: int


@dataclass(frozen=True)
class LinkRestored:
    k: int


@dataclass(frozen=True)
class HelloRejected:
    why: str


@dataclass(frozen=True)
class Unverified:
    """Datagrams a waiting robot dropped because their tag did not verify under its key: so far
    ``count``, the last from ``addr`` for ``why``.  Said at the first, then at most once a second:
    a wrong key on one side looks like a missing peer unless the other says what it refused."""

    count: int
    addr: Addr
    why: str


@dataclass(frozen=True)
class SessionEnded:
    reason: EndReason
    summary: EndpointSummary  # SessionSummary(summary).document() is its JSON map


@dataclass(frozen=True)
class Failed:
    reason: Failure
    detail: str


Event: TypeAlias = (
    SessionStarted
    | ClockShifted
    | PeerRestarted
    | Replaced
    | PeerBye
    | LinkLost
    | LinkRestored
    | HelloRejected
    | Unverified
    | SessionEnded
    | Failed
    | TicksEnded
    | AdmissionChanged
)
