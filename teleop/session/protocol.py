"""The session-control protocol, sans I/O: hello / welcome / reject / start / started / bye.

Everything here is a pure function of the bytes and the ``now`` it is given (h11 / aioquic style):
it never reads a clock, never touches a socket and never opens a file, so the whole handshake can
be driven in memory with fake clocks and fuzzed with arbitrary bytes.  The runner
(``shell.runner``) owns the socket and the clock and filters peer addresses.

**Wire format.** A control message is a msgpack map ``{"t": kind, "v": 1, ...fields}`` packed with
``use_bin_type=True``; data packets are msgpack arrays (``teleop.session.wire``), so the first byte tells the
two apart (:func:`is_control`).  Timestamps are integer nanoseconds of a monotonic clock: the
operator's for ``t_ns`` (also where a welcome or a reject echoes it), the teleoperator's for ``t2``,
``t3`` and ``start_ns``.

**Trust.** Every field that comes from the network is checked for presence, exact type and the range
this process can afford (``teleop.limits``); anything else raises :class:`ProtocolError`, and only
that.  A netem spec from the network may not name a local file (``trace FILE``) unless the local side
configured that exact spec itself: a peer must not make us open ``/etc/shadow`` or ``/dev/zero``.
A teleoperator never ends its handshake because of what a stranger sent: bad hellos are answered
with a ``reject`` and counted, and it keeps waiting for a good one.

**Authentication** (``teleop.session.auth``).  The state machines take and return whole datagrams: every
message is sealed in the envelope (counter and keyed BLAKE2s tag).  Hello, welcome and reject travel
under the handshake key derived from the pre-shared key; the hello carries the operator's nonce and
the welcome the teleoperator's, and the start, started and everything after use the per-direction
session keys derived from the pre-shared key, the session id and both nonces, so a datagram
captured in one session verifies in no other.  A datagram whose tag does not verify is counted
(``unauthenticated``) and never answered.  After the handshake its ``tx_sealer`` and ``rx_opener``
(counters and replay window) pass on to the port.
"""

from __future__ import annotations

import dataclasses
import enum
import hashlib
import hmac
import math
from collections import deque
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, TypeAlias

import msgpack

from teleop import limits
from teleop.control.codecs import CodecError, CodecSpec, make_codec
from teleop.control.passivity import ON_LOSS
from teleop.control.ratecap import MAX_RATE_BPS, MIN_RATE_BPS
from teleop.control.wave import WaveImpedance
from teleop.devices import scenarios
from teleop.devices.scenarios import SCENARIOS
from teleop.errors import RemoteError
from teleop.session import auth
from teleop.session.link import Addr
from teleop.session.link.netem import NetemError, NetemSpec, parse_netem
from teleop.session.node import PortOptions
from teleop.session.settings import SETTINGS, Channel, Envelope, Passivity

FORWARD, BACKWARD = 0, 1  # the directions of teleop.session.wire: operator -> TO, TO -> operator

__all__ = [
    "MAX_CONTROL_BYTES",
    "MAX_COUNT",
    "MAX_TIMESTAMP",
    "PROTOCOL_VERSION",
    "Bye",
    "Failure",
    "Hello",
    "Message",
    "OperatorHandshake",
    "ProtocolError",
    "Reject",
    "Retry",
    "SessionParams",
    "Start",
    "Started",
    "TeleoperatorHandshake",
    "Welcome",
    "encode",
    "is_control",
    "ntp_offset",
    "parse",
    "start_lead",
]

PROTOCOL_VERSION = 1
#: Largest control datagram accepted, checked before unpacking (a full hello is about 2.3 kB at most).
MAX_CONTROL_BYTES = limits.MAX_CONTROL_BYTES
#: Timestamps are monotonic ns: non-negative and within a signed 64-bit integer.
MAX_TIMESTAMP = 2**63 - 1
#: Bound of the packet counters in ``bye``.
MAX_COUNT = 2**32
#: Bound of the integers of a network-supplied netem spec (tc's are u32): keeps the link's
#: arithmetic in floats finite (a 400-digit cell size would overflow at the first packet).
_MAX_NETEM_INT = 2**32
#: Longest scenario / on_loss name looked up (the names are short; this only bounds error texts).
_MAX_NAME_LEN = 64
#: Reasons of the last rejected hellos that a teleoperator keeps for its report.
REJECTIONS_KEPT = 16
START_AHEAD_NS = 10_000_000_000  # a start at most this far ahead of the teleoperator's clock
NEVER_NS = 1 << 62  # a handshake timer that never comes (about 146 years of the monotonic clock)
START_SLACK_NS = 1_000_000_000  # or this far behind it (a fresh session: the operator leads by 300 ms)
#: The start's lead follows the measured round trip: at least ``start_lead_ns``, and at least
#: ``start_margin_ns + START_LEAD_RTTS * rtt + START_LEAD_SLACK_NS``.  With jitter up to half the
#: one-way delay a round trip may take 3x the smallest one measured; the slack is for one lost
#: start or started.  Unchanged (300 ms) up to a 50 ms round trip; 6.15 s at 2 s.
START_LEAD_RTTS = 3
START_LEAD_SLACK_NS = 100_000_000
#: The start is resent every ``max(start_resend_ns, rtt / START_RESEND_DIV)``: a few per round trip.
START_RESEND_DIV = 8
#: The longest smallest round trip the operator starts at (PROTOCOL.md 4.3): 2 s with 50 % jitter
#: to spare; its start lead (9.15 s) stays within START_AHEAD_NS.
MAX_RTT_NS = 3_000_000_000
BUSY = "busy with another operator"


class Failure(enum.Enum):
    """Why a handshake (or the session it was for) never started: what callers branch on, never
    the error's text (h11's rule)."""

    NO_ANSWER = "no_answer"  # operator: nothing at all within the timeout (absent robot, other key or name)
    THROTTLED = "throttled"  # operator: retries, but no welcome for a hello with the cookie (dropped)
    UNVERIFIED = "unverified"  # operator: no welcome, and answers whose MAC failed (another key?)
    REJECTED = "rejected"  # operator: the teleoperator refused the session
    START_UNCONFIRMED = "start_unconfirmed"  # operator: no started before tick 0
    PEER_CLOCK = "peer_clock"  # operator: the peer's clock is out of range
    ROUND_TRIP = "round_trip"  # operator: even the quickest exchange took longer than MAX_RTT_NS
    NO_OPERATOR = "no_operator"  # teleoperator: no start within the timeout


class ProtocolError(RemoteError):
    """A message that is not valid; the text names the field and what is allowed.

    ``kind`` and ``session`` are what could be read of the message before it failed (None if
    nothing), so that a teleoperator can answer a bad hello with a ``reject`` for its session.
    """

    def __init__(
        self, message: str, *, kind: str | None = None, session: int | None = None, t_ns: int = 0
    ) -> None:
        super().__init__(message)
        self.kind = kind
        self.session = session
        self.t_ns = t_ns  # a hello's t_ns, if it could be read: a reject echoes it


# --------------------------------------------------------------------------------------------
# field checks
# --------------------------------------------------------------------------------------------
def _show(v: object, width: int = 40) -> str:
    """A short repr for error texts: a hostile value must not make a huge message."""
    r = repr(v)
    return r if len(r) <= width else r[: width - 3] + "..."


def _canonical(name: str, sent: str, canonical: str) -> None:
    """:class:`ProtocolError` naming the field and its canonical form unless ``sent`` is it."""
    if sent != canonical:
        raise ProtocolError(
            f"{name} must be sent in its canonical form {_show(canonical)}, got {_show(sent)}"
        )


def _got(v: object) -> str:
    return f"got {type(v).__name__} {_show(v)}"


def _num(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _field(m: Mapping[str, object], name: str) -> object:
    if name not in m:
        raise ProtocolError(f"missing field {name!r}")
    return m[name]


def _int(m: Mapping[str, object], name: str, lo: int, hi: int) -> int:
    v = _field(m, name)
    if type(v) is not int:  # bool is an int subclass: refused
        raise ProtocolError(f"{name} must be an integer in {lo}..{hi}, {_got(v)}")
    if not lo <= v <= hi:
        raise ProtocolError(f"{name} must be an integer in {lo}..{hi}, got {_show(v)}")
    return v


def _timestamp(m: Mapping[str, object], name: str) -> int:
    return _int(m, name, 0, MAX_TIMESTAMP)


def _float(m: Mapping[str, object], name: str) -> float:
    """A finite number (int or float, not bool); its range is checked by the caller."""
    v = _field(m, name)
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ProtocolError(f"{name} must be a finite number, {_got(v)}")
    try:
        f = float(v)
    except OverflowError:
        f = math.inf
    if not math.isfinite(f):
        raise ProtocolError(f"{name} must be a finite number, got {_show(v)}")
    return f


def _str(m: Mapping[str, object], name: str, max_len: int) -> str:
    v = _field(m, name)
    if not isinstance(v, str):
        raise ProtocolError(f"{name} must be a string of at most {max_len} characters, {_got(v)}")
    if len(v) > max_len:
        raise ProtocolError(f"{name} must be a string of at most {max_len} characters, got {len(v)}")
    return v


def _bool(m: Mapping[str, object], name: str, default: bool | None = None) -> bool:
    if default is not None and name not in m:
        return default
    v = _field(m, name)
    if not isinstance(v, bool):
        raise ProtocolError(f"{name} must be true or false, {_got(v)}")
    return v


def _between(name: str, v: float, lo: float, hi: float) -> None:
    if not lo <= v <= hi:  # also refuses nan
        raise ValueError(f"{name} must be in {_num(lo)}..{_num(hi)}, got {_show(v)}")


def _positive(name: str, v: float, hi: float) -> None:
    if not 0 < v <= hi:
        raise ValueError(f"{name} must be > 0 and <= {_num(hi)}, got {_show(v)}")


def _check_netem_numbers(name: str, spec: NetemSpec) -> None:
    """Finite floats and u32-sized integers, so the link's arithmetic never overflows."""
    for f in dataclasses.fields(spec):
        v = getattr(spec, f.name)
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"{name}: {f.name} must be finite, got {v!r}")
        if isinstance(v, int) and not isinstance(v, bool) and not -_MAX_NETEM_INT <= v <= _MAX_NETEM_INT:
            raise ValueError(f"{name}: {f.name} must be within +-2**32, got {_show(v)}")


def _first_line(e: Exception) -> str:
    """NetemError texts end with the whole grammar: a reason sent to a peer keeps the first line."""
    return str(e).split("\n", 1)[0]


# --------------------------------------------------------------------------------------------
# session parameters
# --------------------------------------------------------------------------------------------
_NETEM_FIELDS = ("netem_forward", "netem_backward")


def configured_netem(expect: Mapping[str, object]) -> frozenset[str]:
    """The netem specs a teleoperator was configured with (its ``expect``): the only ones a hello
    may repeat when they name a trace file."""
    return frozenset(v for k in _NETEM_FIELDS if isinstance(v := expect.get(k), str))


#: What an optional field left out of a hello means (PROTOCOL.md 4.2): what a session meant before the
#: field existed, so an older peer's hello keeps its meaning.  Not a default
#: (teleop.session.settings has those).
WIRE_ABSENT: dict[str, Any] = {
    "rate_cap": 0.0,
    "playout": "off",
    "variation": 0.0,
    "passivity": Passivity.WAVE,
}


@dataclass(frozen=True)
class SessionParams(Channel):
    """What the handshake agrees on: the model's settings and the channel's (:class:`Channel`)."""

    session: int
    scenario: str
    dof: int
    b: float
    full_scale: float
    duration: float
    dt: float = 0.001
    phase: float = 0.5  # the teleoperator's ticks run this fraction of a period behind the operator's

    def _check_ranges(self) -> None:
        """ValueError naming the first field outside what this process can afford (teleop.limits).

        The order matters: the duration's bound depends on dof and dt, checked first."""
        _between("session", self.session, 1, limits.MAX_SESSION)
        if len(self.scenario) > _MAX_NAME_LEN or self.scenario not in SCENARIOS:
            raise ValueError(f"scenario must be one of {', '.join(SCENARIOS)}, got {_show(self.scenario)}")
        _between("dof", self.dof, 1, limits.MAX_DOF)
        _positive("b", self.b, limits.MAX_B)
        _between("range", self.full_scale, limits.MIN_RANGE, limits.MAX_RANGE)  # subnormal: refused
        _between("dt", self.dt, limits.MIN_DT, limits.MAX_DT)
        limits.check_duration(self.duration, self.dof, self.dt)
        if not 0.0 <= self.phase < 1.0:
            raise ValueError(f"phase must be in [0, 1) periods, got {_show(self.phase)}")
        _between("seed", self.seed, 0, limits.MAX_SEED)
        if self.on_loss not in ON_LOSS:
            raise ValueError(f"on_loss must be one of {', '.join(ON_LOSS)}, got {_show(self.on_loss)}")
        _between("link_timeout", self.link_timeout, limits.MIN_LINK_TIMEOUT_S, limits.MAX_LINK_TIMEOUT_S)
        if self.rate_cap != 0.0:
            _between("rate_cap", self.rate_cap, MIN_RATE_BPS, MAX_RATE_BPS)
        _between("variation", self.variation, 0.0, limits.MAX_VARIATION)
        if len(self.codec) > limits.MAX_CODEC_SPEC_LEN:
            raise ValueError(f"codec must be at most {limits.MAX_CODEC_SPEC_LEN} characters")
        for name in _NETEM_FIELDS:
            if len(getattr(self, name)) > limits.MAX_NETEM_SPEC_LEN:
                raise ValueError(f"{name} must be at most {limits.MAX_NETEM_SPEC_LEN} characters")

    def validate(self) -> SessionParams:
        """Check settings typed locally; raise ValueError/CodecError saying what is wrong.

        Returns self with the codec spec canonical.  Unlike :meth:`from_msg`, a ``trace FILE`` spec
        is allowed (the user named the file) and is loaded here to check it."""
        scenarios.get(self.scenario)
        self._check_ranges()
        WaveImpedance.of(self.b, self.dof)
        playout = self.check_channel(netem_files=True)
        for name in _NETEM_FIELDS:
            text = getattr(self, name)
            if text.split()[:1] not in ([], ["trace"]):
                _check_netem_numbers(name, parse_netem(text))
        make_codec(self.codec_spec, self.dof, self.full_scale, power=self.tdpa)  # CodecError: not under TDPA
        return dataclasses.replace(self, playout=playout)

    def port_options(self) -> PortOptions:
        return PortOptions.of(self)

    @property
    def until_stopped(self) -> bool:
        """A session without a fixed end: it runs until a signal or the peer's bye."""
        return self.duration == limits.UNTIL_STOPPED

    @property
    def span_s(self) -> float:
        """The longest the session can last, s (an open one: :data:`teleop.limits.MAX_DURATION_S`)."""
        return limits.MAX_DURATION_S if self.until_stopped else self.duration

    @property
    def ticks(self) -> int:
        """Ticks of the session (an open one: as many as :attr:`span_s` holds)."""
        return round(self.span_s / self.dt)

    @classmethod
    def from_msg(cls, m: Mapping[str, object], *, local_netem: Collection[str] = ()) -> SessionParams:
        """Parameters proposed by a peer, checked strictly; raises :class:`ProtocolError` only.

        Every field must be present with its exact type and within ``teleop.limits``.  A netem spec
        naming a trace file is refused unless that exact string is in ``local_netem`` (what this
        side configured itself); no file is ever opened here."""
        if not isinstance(m, Mapping):
            raise ProtocolError(f"session parameters must be a map, {_got(m)}")
        fields: dict[str, Any] = dict(
            session=_int(m, "session", 1, limits.MAX_SESSION),
            codec=_str(m, "codec", limits.MAX_CODEC_SPEC_LEN),
            scenario=_str(m, "scenario", _MAX_NAME_LEN),
            dof=_int(m, "dof", 1, limits.MAX_DOF),
            b=_float(m, "b"),
            full_scale=_float(m, "range"),
            duration=_float(m, "duration"),
            dt=_float(m, "dt"),
            phase=_float(m, "phase"),
            netem_forward=_str(m, "netem_forward", limits.MAX_NETEM_SPEC_LEN),
            netem_backward=_str(m, "netem_backward", limits.MAX_NETEM_SPEC_LEN),
            seed=_int(m, "seed", 0, limits.MAX_SEED),
            on_loss=_str(m, "on_loss", _MAX_NAME_LEN),
            controller=_bool(m, "controller"),
            link_timeout=_float(m, "link_timeout"),
            rate_cap=_float(m, "rate_cap") if "rate_cap" in m else WIRE_ABSENT["rate_cap"],
            playout=_str(m, "playout", _MAX_NAME_LEN) if "playout" in m else WIRE_ABSENT["playout"],
            variation=_float(m, "variation") if "variation" in m else WIRE_ABSENT["variation"],
            passivity=_str(m, "passivity", _MAX_NAME_LEN) if "passivity" in m else WIRE_ABSENT["passivity"],
        )
        codec = fields.pop("codec")
        try:
            # The spec is parsed here, once, as the wire spells it (no presets, no named parameters).
            p = cls(codec=CodecSpec.parse(codec, local=False), **fields)
            p._check_ranges()
            for name in _NETEM_FIELDS:
                _check_peer_netem(name, getattr(p, name), local_netem)
            WaveImpedance.of(p.b, p.dof)
            playout = p.check_channel(netem_files=False)
            make_codec(p.codec_spec, p.dof, p.full_scale, power=p.tdpa)  # CodecError: not under TDPA
            # Only the canonical spellings (PROTOCOL.md 3.5, 4.1): ' eds:50', 'EDS:50', 'eds:050', an
            # Arabic-Indic digit or playout '1_0' named the same session as the canonical text and
            # were taken (issue 49); the hello's text is what both sides log and compare.
            _canonical("codec", codec, p.codec)
            if "playout" in m:
                _canonical("playout", fields["playout"], playout)
        except ProtocolError:
            raise
        except (CodecError, ValueError, ArithmeticError) as e:  # the validators of other modules
            raise ProtocolError(str(e)) from None
        return dataclasses.replace(p, playout=playout)

    def to_msg(self) -> dict[str, Any]:
        """The hello's parameters: every setting of ``teleop.session.settings.SETTINGS`` under its key, in
        the table's order.  The optional ones (:data:`WIRE_ABSENT`) are sent only when set, so a
        session without them is byte-for-byte what it was before they existed."""
        return {
            s.key: getattr(self, s.field)
            for s in SETTINGS
            if s.field not in WIRE_ABSENT or getattr(self, s.field) != WIRE_ABSENT[s.field]
        }


@dataclass(frozen=True)
class Pins:
    """What a teleoperator was configured with: a hello must match every field that is not None
    (the rest are the operator's to choose, within :class:`Envelope`)."""

    codec: str | None = None  # canonical spec
    scenario: str | None = None
    dof: int | None = None
    b: float | None = None
    full_scale: float | None = None
    duration: float | None = None
    netem_forward: str | None = None
    netem_backward: str | None = None
    rate_cap: float | None = None

    @classmethod
    def of(cls, expect: Pins | Mapping[str, object]) -> Pins:
        """``expect`` as Pins: a map names :class:`SessionParams` fields (ValueError for others)."""
        if isinstance(expect, Pins):
            return expect
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(expect) - names
        if unknown:
            pins = ", ".join(sorted(names))
            raise ValueError(f"a teleoperator cannot pin {', '.join(sorted(unknown))}; it pins {pins}")
        return cls(**expect)  # type: ignore[arg-type]

    def pinned(self) -> dict[str, object]:
        """The fields that are pinned, by name."""
        return {f.name: v for f in dataclasses.fields(self) if (v := getattr(self, f.name)) is not None}


def _check_peer_netem(name: str, text: str, local_netem: Collection[str]) -> None:
    """Parse a network-supplied netem spec without ever opening a file (``make_link`` would)."""
    toks = text.split()
    if toks and toks[0] == "trace":
        if text not in local_netem:
            raise ProtocolError(
                f"{name} {_show(text)}: a peer may not name a local file (trace FILE); "
                "only a trace this side configured itself is accepted"
            )
        if len(toks) != 2:
            raise ProtocolError(f"{name} {_show(text)}: expected exactly 'trace FILE'")
        return  # this side's own spec: checked (and loaded) when it was configured
    try:
        _check_netem_numbers(name, parse_netem(text))
    except NetemError as e:
        raise ProtocolError(f"{name}: {_first_line(e)}") from None


# --------------------------------------------------------------------------------------------
# messages
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Hello:
    """operator -> TO: the proposed session and the operator's clock when sent (NTP's t1)."""

    kind: ClassVar[str] = "hello"
    params: SessionParams
    t_ns: int
    rejoin: bool = False  # offered mid-session to a teleoperator that restarted
    nonce: bytes = bytes(auth.NONCE_BYTES)  # the operator's: with the TO's, it keys the session
    cookie: bytes | None = None  # the teleoperator's address-bound cookie (a Retry's), once it sent one


@dataclass(frozen=True)
class Welcome:
    """TO -> operator: the hello's ``t_ns`` echoed, with the TO's clock at arrival (t2) and reply (t3)."""

    kind: ClassVar[str] = "welcome"
    session: int
    t_ns: int
    t2: int
    t3: int
    nonce: bytes = bytes(auth.NONCE_BYTES)  # the teleoperator's: with the operator's, it keys the session


@dataclass(frozen=True)
class Reject:
    """TO -> operator: the hello is refused; ``session`` is None when the hello had no valid one."""

    kind: ClassVar[str] = "reject"
    session: int | None
    why: str
    t_ns: int = 0  # the refused hello's, echoed: a recorded reject cannot end a later handshake


@dataclass(frozen=True)
class Retry:
    """TO -> operator: "say hello again with this cookie" (QUIC's Retry, DTLS's HelloVerifyRequest).

    The cookie is a MAC of the hello's source address, its nonce and a coarse time under a secret
    only the teleoperator holds: it keeps no state for the hello, and a recorded hello replayed from
    another address (or later than :data:`COOKIE_LIFETIME_NS`) never gets past it."""

    kind: ClassVar[str] = "retry"
    session: int | None
    t_ns: int  # the hello's, echoed: the operator takes only a retry that answers its own hello
    cookie: bytes


@dataclass(frozen=True)
class Start:
    """operator -> TO: tick 0 of the session at ``start_ns`` on the TO's clock; ``rtt_ns``: the round
    trip of the exchange that placed it (optional), which bounds when the TO may call the session a
    ghost (PROTOCOL.md 4.3 step 8)."""

    kind: ClassVar[str] = "start"
    session: int
    start_ns: int
    rejoin: bool = False
    rtt_ns: int | None = None


@dataclass(frozen=True)
class Started:
    """TO -> operator: the start is confirmed."""

    kind: ClassVar[str] = "started"
    session: int


@dataclass(frozen=True)
class Bye:
    """Either way at the end: packets the sender's node produced, and those its shim tail-dropped;
    ``why``: non-empty when the sender's device ended the session (a robot's reflex), printed by the peer."""

    kind: ClassVar[str] = "bye"
    session: int
    produced: int
    dropped_by_limit: int
    why: str = ""


Message: TypeAlias = Hello | Welcome | Reject | Retry | Start | Started | Bye
KINDS = ("hello", "welcome", "reject", "retry", "start", "started", "bye")
#: Kinds that travel under the handshake key (the rest under the session keys).
HANDSHAKE_KINDS = (Hello, Welcome, Reject, Retry)


def encode(msg: Message) -> bytes:
    """The datagram of a control message (the caller builds valid messages; ``why`` is truncated)."""
    fields: dict[str, Any]
    if isinstance(msg, Hello):
        fields = {
            "t_ns": msg.t_ns,
            "nonce": msg.nonce,
            **({"rejoin": True} if msg.rejoin else {}),
            **({"cookie": msg.cookie} if msg.cookie is not None else {}),
            **msg.params.to_msg(),
        }
    elif isinstance(msg, Welcome):
        fields = {"session": msg.session, "t_ns": msg.t_ns, "t2": msg.t2, "t3": msg.t3, "nonce": msg.nonce}
    elif isinstance(msg, Reject):
        fields = {"session": msg.session, "why": msg.why[: limits.MAX_REASON_LEN], "t_ns": msg.t_ns}
    elif isinstance(msg, Retry):
        fields = {"session": msg.session, "t_ns": msg.t_ns, "cookie": msg.cookie}
    elif isinstance(msg, Start):
        fields = {
            "session": msg.session,
            "start_ns": msg.start_ns,
            **({"rtt_ns": msg.rtt_ns} if msg.rtt_ns is not None else {}),
            **({"rejoin": True} if msg.rejoin else {}),
        }
    elif isinstance(msg, Started):
        fields = {"session": msg.session}
    else:
        fields = {"session": msg.session, "produced": msg.produced, "dropped_by_limit": msg.dropped_by_limit}
        if msg.why:
            fields["why"] = msg.why[: limits.MAX_REASON_LEN]
    out: bytes = msgpack.packb({"t": msg.kind, "v": PROTOCOL_VERSION, **fields}, use_bin_type=True)
    return out


def is_control(data: bytes) -> bool:
    """True if ``data`` starts like a msgpack map (fixmap, map16, map32): a control message, not a
    data packet (those are arrays).  Says nothing about validity: :func:`parse` does."""
    return bool(data) and (0x80 <= data[0] <= 0x8F or data[0] in (0xDE, 0xDF))


def _t_ns_of(m: Mapping[str, object]) -> int:
    t = m.get("t_ns")
    return t if type(t) is int and 0 <= t <= MAX_TIMESTAMP else 0


def _session_of(m: Mapping[str, object]) -> int | None:
    s = m.get("session")
    return s if type(s) is int and 1 <= s <= limits.MAX_SESSION else None


def _nonce(m: Mapping[str, object]) -> bytes:
    v = _field(m, "nonce")
    if type(v) is not bytes or len(v) != auth.NONCE_BYTES:
        raise ProtocolError(f"nonce must be {auth.NONCE_BYTES} bytes (msgpack bin), {_got(v)}")
    return v


def _cookie(m: Mapping[str, object]) -> bytes:
    v = _field(m, "cookie")
    if type(v) is not bytes or len(v) != COOKIE_BYTES:
        raise ProtocolError(f"cookie must be {COOKIE_BYTES} bytes (msgpack bin), {_got(v)}")
    return v


# --------------------------------------------------------------------------------------------
# cookies: no per-operator state before the operator proved it can receive at its address
# --------------------------------------------------------------------------------------------
COOKIE_BYTES = 16
#: A cookie's time bucket: 2**33 ns (8.6 s); the current and the previous bucket are accepted, so a
#: cookie lives 8.6 to 17.2 s, long enough for a handshake at any round trip the protocol serves.
COOKIE_BUCKET_SHIFT = 33
COOKIE_LIFETIME_NS = 2 << COOKIE_BUCKET_SHIFT
_COOKIE_PERSON = b"tlpcook1"


def make_cookie(secret: bytes, addr: Addr, nonce: bytes, now_ns: int, bucket_delta: int = 0) -> bytes:
    """The cookie of a hello with ``nonce`` from ``addr`` at ``now_ns``: a MAC under ``secret``."""
    bucket = (now_ns >> COOKIE_BUCKET_SHIFT) - bucket_delta
    data = f"{addr[0]}|{addr[1]}|{bucket}".encode() + bytes(nonce)
    return hashlib.blake2s(data, key=secret, digest_size=COOKIE_BYTES, person=_COOKIE_PERSON).digest()


def cookie_ok(secret: bytes, cookie: object, addr: Addr, nonce: object, now_ns: int) -> bool:
    """Whether ``cookie`` is ours for this address and nonce, made in this time bucket or the last."""
    if type(cookie) is not bytes or type(nonce) is not bytes or len(nonce) != auth.NONCE_BYTES:
        return False
    return any(hmac.compare_digest(cookie, make_cookie(secret, addr, nonce, now_ns, d)) for d in (0, 1))


def _parse_fields(kind: str, m: Mapping[str, object], local_netem: Collection[str]) -> Message:
    if kind == "hello":
        params = SessionParams.from_msg(m, local_netem=local_netem)
        cookie = _cookie(m) if "cookie" in m else None
        return Hello(params, _timestamp(m, "t_ns"), _bool(m, "rejoin", False), _nonce(m), cookie)
    if kind == "retry":
        session = None if m.get("session") is None else _int(m, "session", 1, limits.MAX_SESSION)
        return Retry(session, _timestamp(m, "t_ns"), _cookie(m))
    if kind == "reject":
        session = None if m.get("session") is None else _int(m, "session", 1, limits.MAX_SESSION)
        why = _field(m, "why")
        if not isinstance(why, str):
            raise ProtocolError(f"why must be a string, {_got(why)}")
        return Reject(session, why[: limits.MAX_REASON_LEN], _timestamp(m, "t_ns"))
    session = _int(m, "session", 1, limits.MAX_SESSION)
    if kind == "welcome":
        t_ns, t2, t3 = _timestamp(m, "t_ns"), _timestamp(m, "t2"), _timestamp(m, "t3")
        if t3 < t2:
            raise ProtocolError(f"t3 (reply sent) must not precede t2 (hello received), got {t3} < {t2}")
        return Welcome(session, t_ns, t2, t3, _nonce(m))
    if kind == "start":
        rtt = _timestamp(m, "rtt_ns") if "rtt_ns" in m else None
        return Start(session, _timestamp(m, "start_ns"), _bool(m, "rejoin", False), rtt)
    if kind == "started":
        return Started(session)
    why = m.get("why", "")
    if not isinstance(why, str):
        raise ProtocolError(f"why must be a string, {_got(why)}")
    return Bye(
        session,
        _int(m, "produced", 0, MAX_COUNT),
        _int(m, "dropped_by_limit", 0, MAX_COUNT),
        why[: limits.MAX_REASON_LEN],
    )


def parse(data: bytes, *, local_netem: Collection[str] = ()) -> Message:
    """The message in a control datagram; raises :class:`ProtocolError`, and only that, for any bytes.

    ``local_netem``: netem specs this side configured itself, which a hello may repeat even if they
    name a trace file (see :meth:`SessionParams.from_msg`)."""
    if not isinstance(data, bytes | bytearray | memoryview):
        raise ProtocolError(f"a datagram must be bytes, {_got(data)}")
    if len(data) > MAX_CONTROL_BYTES:
        raise ProtocolError(f"a control message must be at most {MAX_CONTROL_BYTES} bytes, got {len(data)}")
    if not is_control(bytes(data[:1])):
        raise ProtocolError("not a control message (a control message is a msgpack map)")
    try:
        m = _unpack_control(data)
    except Exception as e:  # msgpack raises several types (FormatError, StackError, UnicodeDecodeError...)
        raise ProtocolError(f"not valid msgpack: {type(e).__name__}") from None
    if not isinstance(m, dict):
        raise ProtocolError("not a control message (a control message is a msgpack map)")
    kind = m.get("t")
    if not isinstance(kind, str) or kind not in KINDS:
        raise ProtocolError(f"t (the kind) must be one of {', '.join(KINDS)}, got {_show(kind)}")
    session = _session_of(m)
    v = m.get("v")
    if type(v) is not int or v != PROTOCOL_VERSION:
        raise ProtocolError(
            f"protocol version {_show(v)} is not supported; this side speaks {PROTOCOL_VERSION}",
            kind=kind,
            session=session,
            t_ns=_t_ns_of(m),
        )
    try:
        return _parse_fields(kind, m, local_netem)
    except ProtocolError as e:
        raise ProtocolError(f"bad {kind}: {e}", kind=kind, session=session, t_ns=_t_ns_of(m)) from None


def ntp_offset(t1: int, t2: int, t3: int, t4: int) -> tuple[int, int]:
    """(offset, rtt) from NTP's four timestamps: request sent t1 and reply received t4 on the local
    clock, request received t2 and reply sent t3 on the peer's; ``peer clock = local + offset``.

    The offset is exact when the two one-way delays are equal; otherwise it is off by half their
    difference, which is why the handshake keeps the exchange with the smallest rtt."""
    return ((t2 - t1) + (t3 - t4)) // 2, (t4 - t1) - (t3 - t2)


def start_lead(rtt_ns: int, min_lead_ns: int = 300_000_000, margin_ns: int = 50_000_000) -> int:
    """How far ahead of now the operator sets tick 0 after an exchange of round trip ``rtt_ns``:
    the start must reach the TO and its started come back before ``margin_ns`` ahead of tick 0,
    with jitter (3 smallest round trips) and one loss (:data:`START_LEAD_SLACK_NS`) to spare."""
    return max(min_lead_ns, margin_ns + START_LEAD_RTTS * max(0, rtt_ns) + START_LEAD_SLACK_NS)


# --------------------------------------------------------------------------------------------
# the operator's side
# --------------------------------------------------------------------------------------------
class OperatorHandshake:
    """The operator's handshake: hellos until enough welcomes, then the start until ``started``.

    Drive it with :meth:`receive` (datagrams from the peer's address only) and :meth:`poll` (what
    to send now), and call poll again at :meth:`next_timer` or after a receive.  It ends with
    ``done`` (``offset_ns``, ``rtt_ns``, ``start_ns`` set) or ``error`` set.  Malformed and
    irrelevant datagrams are counted in ``rejected``, never raised.

    A hello goes out when the previous one was answered or ``hello_interval_ns`` ran out.  After
    ``answers`` welcomes, or at the timeout with at least one, the start is set ahead by the lead
    (:func:`start_lead_ns`: ``start_lead_ns``, more at a long round trip; on this clock, the message
    carries it on the TO's clock) and resent every ``start_resend_ns`` (a few per round trip) until
    confirmed, giving up ``start_margin_ns`` before the start itself.
    """

    def __init__(
        self,
        params: SessionParams,
        *,
        now_ns: int,
        timeout_s: float,
        answers: int = 8,
        hello_interval_ns: int = 100_000_000,
        start_lead_ns: int = 300_000_000,
        start_resend_ns: int = 20_000_000,
        start_margin_ns: int = 50_000_000,
        psk: bytes = auth.INSECURE_KEY,
        nonce: bytes = bytes(auth.NONCE_BYTES),
    ) -> None:
        if answers < 1 or hello_interval_ns <= 0 or start_resend_ns <= 0:
            raise ValueError("answers, hello_interval_ns and start_resend_ns must be positive")
        if not 0 <= start_margin_ns < start_lead_ns:
            raise ValueError("start_margin_ns must be in [0, start_lead_ns)")
        self.params = params
        self.timeout_s = timeout_s
        self.answers_wanted = answers
        self.hello_interval_ns = hello_interval_ns
        self.start_lead_ns = start_lead_ns
        self.start_resend_ns = start_resend_ns
        self.start_margin_ns = start_margin_ns
        self._give_up = now_ns + round(timeout_s * 1e9)
        # t_ns of the hellos in flight, not yet answered: a welcome may answer any of them, so a
        # round trip longer than the hello interval still completes (NTP's t1 is the one it echoes).
        self._in_flight: deque[int] = deque(maxlen=64)
        self._next_hello = now_ns
        self._best: tuple[int, int] | None = None  # (rtt, offset) of the quickest exchange
        self._starting = False
        self._next_start = 0
        self._start_deadline = 0
        self.answers = 0
        self.hellos_sent = 0
        self.starts_sent = 0
        self.done = False
        self.error: str | None = None
        self.failure: Failure | None = None  # why, when ``error`` is set
        self.offset_ns = 0  # TO clock - operator clock
        self.rtt_ns = 0
        self.start_ns = 0  # tick 0 on the operator's clock
        self.rejected = 0
        self.last_rejection = ""
        # Authentication (teleop.session.auth): hellos and welcomes under the handshake key; the start and
        # everything after under the session keys, derived from the psk and both nonces.
        self.psk, self.nonce = psk, nonce
        k_hs = auth.handshake_key(psk)
        self.hs_sealer = auth.Sealer(k_hs, auth.HANDSHAKE, FORWARD)
        self.hs_opener = auth.Opener(k_hs, auth.HANDSHAKE, BACKWARD)
        self.peer_nonce: bytes | None = None
        self.tx_sealer: auth.Sealer | None = None
        self.rx_opener: auth.Opener | None = None
        self.unauthenticated = 0  # datagrams whose tag did not verify: dropped, never answered
        self.last_unauthenticated = ""
        self._hellos: deque[int] = deque(maxlen=64)  # t_ns of our hellos: what a reject must echo
        self.cookie: bytes | None = None  # the teleoperator's, from its retry
        self.retries = 0

    @property
    def finished(self) -> bool:
        return self.done or self.error is not None

    def _open(self, data: bytes, now_ns: int) -> tuple[int, bytes] | None:
        """(key kind, body) of an authenticated datagram, or None (counted)."""
        try:
            hdr = auth.peek(data)
            if hdr is None:
                raise auth.AuthError("header", "not a teleop envelope")
            if hdr[0] == auth.HANDSHAKE:
                return auth.HANDSHAKE, self.hs_opener.verify(data)[1]
            if self.rx_opener is None:
                raise auth.AuthError("kind", "a session datagram before the session keys exist")
            return auth.SESSION, self.rx_opener.open(data, now_ns / 1e9)[1]
        except auth.AuthError as e:
            self.unauthenticated += 1
            self.last_unauthenticated = str(e)
            return None

    def _refuse(self, why: str) -> None:
        self.rejected += 1
        self.last_rejection = why

    def receive(self, data: bytes, now_ns: int) -> None:
        """A datagram from the peer, received at ``now_ns`` (NTP's t4 for a welcome)."""
        if self.finished:
            return
        opened = self._open(data, now_ns)
        if opened is None:
            return
        key_kind, body = opened
        try:
            msg = parse(body)
            if (key_kind == auth.HANDSHAKE) != isinstance(msg, Welcome | Reject | Retry):
                raise ProtocolError(f"a {msg.kind} under the wrong key")
        except ProtocolError as e:
            self._refuse(str(e))
            return
        session = self.params.session
        if isinstance(msg, Reject) and msg.session == session:
            if msg.t_ns not in self._hellos:  # a recorded reject of an earlier handshake: stale
                self._refuse("a reject that answers none of our hellos")
                return
            self.error, self.failure = f"rejected the session: {msg.why}", Failure.REJECTED
        elif isinstance(msg, Retry) and msg.session == session and not self._starting:
            if msg.t_ns not in self._in_flight:
                self._refuse("a retry that answers no hello in flight (late or duplicated)")
                return
            self._in_flight.clear()  # hellos without the cookie: their answers are retries too
            self.cookie = msg.cookie  # every later hello carries it
            self.retries += 1
            self._next_hello = now_ns  # say hello again at once, with the cookie
        elif isinstance(msg, Welcome) and msg.session == session and not self._starting:
            if msg.t_ns not in self._in_flight:
                self._refuse("a welcome that answers no hello in flight (late or duplicated)")
                return
            offset, rtt = ntp_offset(msg.t_ns, msg.t2, msg.t3, now_ns)
            if rtt < 0:
                self._refuse(f"a welcome whose turnaround t3 - t2 exceeds the round trip (rtt {rtt} ns)")
                return
            self._in_flight.remove(msg.t_ns)  # one answer per hello
            if self._best is None or rtt < self._best[0]:
                self._best = (rtt, offset)
            self.peer_nonce = msg.nonce  # the newest: a teleoperator restarted meanwhile has a new one
            self.answers += 1
            self._next_hello = now_ns  # the next hello goes out at once
        elif isinstance(msg, Started) and msg.session == session and self._starting:
            self.done = True
        else:
            self._refuse(f"an unexpected {msg.kind} for session {getattr(msg, 'session', None)}")

    def _begin_start(self, now_ns: int) -> None:
        assert self._best is not None
        self.rtt_ns, self.offset_ns = self._best
        if self.rtt_ns > MAX_RTT_NS:
            self.error = (
                f"the round trip {self.rtt_ns / 1e9:.3g} s exceeds the {MAX_RTT_NS / 1e9:g} s"
                " the protocol serves"
            )
            self.failure = Failure.ROUND_TRIP
            return
        lead = start_lead(self.rtt_ns, self.start_lead_ns, self.start_margin_ns)
        self.start_ns = now_ns + lead
        self.start_resend_ns = max(self.start_resend_ns, self.rtt_ns // START_RESEND_DIV)
        if not 0 <= self.start_ns + self.offset_ns <= MAX_TIMESTAMP:
            self.error = f"the peer's clock is out of range (offset {self.offset_ns} ns)"
            self.failure = Failure.PEER_CLOCK
            return
        assert self.peer_nonce is not None
        fwd, bwd = auth.session_keys(self.psk, self.params.session, self.nonce, self.peer_nonce)
        self.tx_sealer = auth.Sealer(fwd, auth.SESSION, FORWARD)
        self.rx_opener = auth.Opener(bwd, auth.SESSION, BACKWARD)
        self._starting = True
        self._next_start = now_ns
        self._start_deadline = self.start_ns - self.start_margin_ns

    def poll(self, now_ns: int) -> list[bytes]:
        """What to send at ``now_ns``; may end the handshake with ``error`` (timeout)."""
        if self.finished:
            return []
        if not self._starting:
            if self.answers >= self.answers_wanted or (now_ns >= self._give_up and self._best is not None):
                self._begin_start(now_ns)
                if self.error is not None:
                    return []
            elif now_ns >= self._give_up:
                self.error, self.failure = self._unanswered()
                return []
            elif now_ns >= self._next_hello:
                self._in_flight.append(now_ns)
                self._hellos.append(now_ns)
                self._next_hello = now_ns + self.hello_interval_ns
                self.hellos_sent += 1
                hello = Hello(self.params, now_ns, nonce=self.nonce, cookie=self.cookie)
                return [self.hs_sealer.seal(encode(hello))]
            else:
                return []
        if now_ns >= self._start_deadline:
            self.error, self.failure = self._unconfirmed(), Failure.START_UNCONFIRMED
            return []
        if now_ns >= self._next_start:
            self._next_start = now_ns + self.start_resend_ns
            self.starts_sent += 1
            assert self.tx_sealer is not None
            start = Start(self.params.session, self.start_ns + self.offset_ns, rtt_ns=self.rtt_ns)
            return [self.tx_sealer.seal(encode(start))]
        return []

    def _unanswered(self) -> tuple[str, Failure]:
        """The handshake's failure when no welcome came, with what this side saw: nothing at all
        (absent, unreachable, or another key or name: such a robot stays silent), only retries (it
        drops our hellos with their cookie: throttled), or datagrams whose MAC failed (another key,
        or someone else answering)."""
        seen = f"{self.hellos_sent} hellos sent, {self.retries} retries taken"
        if self.unauthenticated:
            seen += f", {self.unauthenticated} datagram(s) that did not verify ({self.last_unauthenticated})"
        if self.rejected:
            seen += f", {self.rejected} refused ({self.last_rejection})"
        why = f"never answered within {self.timeout_s:g} s ({seen})"
        if self.unauthenticated:
            return why, Failure.UNVERIFIED
        if self.retries:
            return why, Failure.THROTTLED
        return why, Failure.NO_ANSWER

    def _unconfirmed(self) -> str:
        """The start's failure, with what this side saw: whether its starts left, and what it refused
        (a started it could not open or parse would be there; none at all: none arrived in time)."""
        seen = [f"{self.starts_sent} start(s) sent"]
        if self.unauthenticated:
            last = self.last_unauthenticated
            seen.append(f"{self.unauthenticated} datagram(s) refused unverified, the last: {last}")
        if self.rejected:
            seen.append(f"{self.rejected} refused, the last: {self.last_rejection}")
        return f"did not confirm the start ({'; '.join(seen)})"

    def next_timer(self) -> int:
        """When :meth:`poll` must be called next (ns, this clock); meaningless once finished."""
        if self._starting:
            return min(self._next_start, self._start_deadline)
        if self.answers >= self.answers_wanted:
            return self._next_hello  # the receive time of the last welcome: at once
        return min(self._next_hello, self._give_up)


# --------------------------------------------------------------------------------------------
# the teleoperator's side
# --------------------------------------------------------------------------------------------
MAX_CANDIDATES = 64  # operators (nonces) welcomed at once before one proves itself with a start
SEEN_TAGS = 1024  # handshake datagrams remembered to drop byte-identical replays
CANDIDATE_ADDRS = 4  # addresses a start for one nonce may come from: the first seen, and the latest


@dataclass
class _Candidate:
    """An operator the teleoperator welcomed: its proposal and the session keys it would use."""

    params: SessionParams
    rx_opener: auth.Opener
    tx_sealer: auth.Sealer
    addrs: list[Addr]  # where its hellos came from: the first, then the latest (bounded)

    def seen_from(self, addr: Addr) -> None:
        """A hello for this nonce from ``addr``.  The first address stays: a recording of the
        genuine hello replayed from elsewhere cannot take the genuine operator's address away."""
        if addr in self.addrs:
            return
        if len(self.addrs) >= CANDIDATE_ADDRS:
            del self.addrs[1]
        self.addrs.append(addr)


def _unpack_control(body: bytes) -> object:
    """The msgpack object of a control body, under the limits of :func:`parse` (raises on garbage)."""
    return msgpack.unpackb(
        bytes(body),
        raw=False,
        strict_map_key=True,
        max_str_len=MAX_CONTROL_BYTES,
        max_bin_len=MAX_CONTROL_BYTES,
        max_array_len=MAX_CONTROL_BYTES,
        max_map_len=64,
        max_ext_len=MAX_CONTROL_BYTES,
    )


def peek_hello(body: bytes) -> tuple[int | None, int, object, object] | None:
    """(session, t_ns, nonce, cookie) of a body that looks like a hello, else None: read before the
    full parse (its codec and netem checks cost ~0.2 ms), so a hello without a valid cookie costs
    an unpack, not a parse.  Values are unchecked except session and t_ns.

    It unpacks under exactly :func:`parse`'s limits: a body it cannot read is one the full parse
    refuses too, so no hello reaches a welcome without its cookie checked (PROTOCOL.md 4.3 step 2)."""
    if len(body) > MAX_CONTROL_BYTES or not is_control(bytes(body[:1])):
        return None
    try:
        m = _unpack_control(body)
    except Exception:  # msgpack's several error types: the full parse says what is wrong
        return None
    if not isinstance(m, dict) or m.get("t") != "hello":
        return None
    return _session_of(m), _t_ns_of(m), m.get("nonce"), m.get("cookie")


class TeleoperatorHandshake:
    """The teleoperator's handshake: welcome a good hello, confirm that operator's start.

    ``expect``: what this teleoperator was configured with (:class:`Pins`, or a map of its fields;
    None: anything).  ``local_netem`` lists netem specs configured here that a hello may repeat even
    if they name a trace file; the netem specs in ``expect`` are added to it.

    A bad hello (malformed, or differing from ``expect``) is answered with a ``reject`` carrying the
    reason, counted in ``rejected`` / ``last_rejection`` / ``rejections`` (the last 16 reasons), and
    the handshake goes on waiting: a stranger must not be able to stop the robot's endpoint.  Other
    garbage is counted in ``ignored`` and dropped.  It ends with ``done`` (``params``, ``peer``,
    ``start_ns`` on this clock, ``rejoin``) or, from :meth:`poll` at the timeout, ``error``.

    Several operators may be welcomed at once (up to ``MAX_CANDIDATES`` nonces); the first whose start
    verifies under the session key derived from its nonce and ours wins.  A hello alone proves only
    that someone once held the key (it may be a recording), so it commits to nothing; the start
    proves that its sender saw our fresh nonce.  Once the session runs, the endpoint answers other
    operators "busy".

    ``cookie_secret`` (the endpoint always gives one): a hello without a valid cookie for its source
    address is answered with a small :class:`Retry` and leaves no state, so hellos recorded and
    replayed from another address never reach the candidates.  ``limits``: what this side affords
    (:class:`Envelope`); ``vet``: why a proposal within it still cannot run (None: it can).
    ``defer_t3``: welcomes wait in :meth:`datagrams_to_send` to be stamped with NTP's reply time t3
    as they leave (a sans-I/O caller has no clock to hand in).
    """

    def __init__(
        self,
        expect: Pins | Mapping[str, object],
        *,
        now_ns: int,
        timeout_s: float,
        local_netem: Collection[str] = (),
        psk: bytes = auth.INSECURE_KEY,
        nonce: bytes = bytes(auth.NONCE_BYTES),
        cookie_secret: bytes | None = None,
        local_limits: Envelope | None = None,
        defer_t3: bool = False,
        admit: Callable[[Addr, int, bool], bool] | None = None,
        vet: Callable[[SessionParams], str | None] | None = None,
    ) -> None:
        self.expect = Pins.of(expect).pinned()
        self.local_netem = frozenset(local_netem) | configured_netem(self.expect)
        self.timeout_s = timeout_s
        # inf: a robot that waits for its operator until it is stopped
        self._give_up = now_ns + round(timeout_s * 1e9) if math.isfinite(timeout_s) else NEVER_NS
        self.params: SessionParams | None = None
        self.peer: Addr | None = None
        self.start_ns = 0
        self.rejoin = False
        self.start_rtt_ns: int | None = None  # the round trip the start states (``Start.rtt_ns``)
        self.done = False
        self.error: str | None = None
        self.failure: Failure | None = None  # why, when ``error`` is set
        self.welcomes = 0
        self.rejected = 0
        self.last_rejection = ""
        self.last_rejected_addr: Addr | None = None
        self.rejections: deque[str] = deque(maxlen=REJECTIONS_KEPT)
        self.ignored = 0
        self.last_ignored = ""
        self.psk, self.nonce = psk, nonce
        k_hs = auth.handshake_key(psk)
        self.hs_sealer = auth.Sealer(k_hs, auth.HANDSHAKE, BACKWARD)
        self.hs_opener = auth.Opener(k_hs, auth.HANDSHAKE, FORWARD)
        self.tx_sealer: auth.Sealer | None = None
        self.rx_opener: auth.Opener | None = None
        # Operators welcomed but not yet committed to: (session, nonce) -> their params, addresses
        # and session keys.  Only a start under one of these keys (proof that the sender knows our
        # fresh nonce) commits; so a replayed hello, which cannot produce one, locks nobody out.
        self._candidates: dict[tuple[int, bytes], _Candidate] = {}  # (session, operator nonce)
        self._seen = auth.SeenTags(SEEN_TAGS)
        self.unauthenticated = 0  # datagrams whose tag did not verify: dropped, never answered
        self.last_unauthenticated = ""
        self.last_unauthenticated_from: Addr | None = None  # (the address it came from, as seen)
        self.cookie_secret = cookie_secret
        self.local_limits = local_limits or Envelope()
        self.retries_sent = 0  # hellos without a valid cookie, answered with a retry, nothing kept
        self.defer_t3 = defer_t3
        self._drafts: list[tuple[Welcome, Addr]] = []  # welcomes waiting for their t3 (defer_t3)
        # The handshake budget (the endpoint's HandshakeLimiter): asked once a hello's MAC verified,
        # with whether it carries a valid cookie for its source, so that unauthenticated datagrams
        # (a stranger's junk, whatever address it claims) spend nobody's budget.
        self.admit = admit
        self.throttled = 0
        # Builds what the session would build from a proposal within the envelope, and says in one
        # line why it cannot run (the endpoint's ``teleop.session.port.build_refusal``): a welcome
        # is a promise that the session starts (issue 45).
        self.vet = vet

    @property
    def finished(self) -> bool:
        return self.done or self.error is not None

    def datagrams_to_send(self, now_ns: int) -> list[tuple[bytes, Addr]]:
        """The welcomes drafted since the last call, stamped ``t3 = now_ns`` (``defer_t3``)."""
        out = [
            (self.hs_sealer.seal(encode(dataclasses.replace(w, t3=max(w.t2, now_ns)))), addr)
            for w, addr in self._drafts
        ]
        self._drafts.clear()
        return out

    def _retry(
        self, addr: Addr, seen: tuple[int | None, int, object, object] | None, cookie_valid: bool, now_ns: int
    ) -> list[tuple[bytes, Addr]] | None:
        """A retry for a hello without a valid cookie for ``addr`` (None: it has one, or is no hello)."""
        if self.cookie_secret is None or seen is None or cookie_valid:
            return None
        session, t_ns, nonce, _ = seen
        if type(nonce) is not bytes or len(nonce) != auth.NONCE_BYTES:
            return None  # malformed: the full parse rejects it
        self.retries_sent += 1
        retry = Retry(session, t_ns, make_cookie(self.cookie_secret, addr, nonce, now_ns))
        return [(self.hs_sealer.seal(encode(retry)), addr)]

    def _open(self, data: bytes, addr: Addr, now_ns: int) -> tuple[_Candidate | None, bytes] | None:
        """(the candidate whose session key it verifies under, or None for the handshake key; the
        body) of an authenticated datagram, or None (counted, never answered: an unauthenticated
        sender learns nothing and cannot use this endpoint as an amplifier)."""
        try:
            hdr = auth.peek(data)
            if hdr is None:
                raise auth.AuthError("header", "not a teleop envelope")
            if hdr[0] == auth.HANDSHAKE:
                body = self.hs_opener.verify(data)[1]
                self._seen.check(data)  # a byte-identical copy is a replay: dropped before parsing
                return None, body
            for c in reversed(self._candidates.values()):
                if addr not in c.addrs:
                    continue
                try:
                    counter, body = c.rx_opener.verify(data)
                except auth.AuthError:
                    continue
                c.rx_opener.accept(counter, now_ns / 1e9)
                return c, body
            raise auth.AuthError("tag", "a session datagram under no welcomed operator's key")
        except auth.AuthError as e:
            self.unauthenticated += 1
            self.last_unauthenticated = str(e)
            self.last_unauthenticated_from = addr
            return None

    def _reject(self, addr: Addr, session: int | None, why: str, t_ns: int) -> list[tuple[bytes, Addr]]:
        why = why[: limits.MAX_REASON_LEN]
        self.rejected += 1
        self.last_rejection = why
        self.last_rejected_addr = addr
        self.rejections.append(why)
        return [(self.hs_sealer.seal(encode(Reject(session, why, t_ns))), addr)]

    def _ignore(self, why: str) -> list[tuple[bytes, Addr]]:
        self.ignored += 1
        self.last_ignored = why
        return []

    def _mismatch(self, p: SessionParams) -> str | None:
        for k, want in self.expect.items():
            got = getattr(p, k)
            if want is not None and got != want:
                return f"{k} {got!r} differs from this teleoperator's {want!r}"
        why = self.local_limits.check(p)
        if why is None and self.vet is not None:
            why = self.vet(p)
        return why

    def receive(
        self, data: bytes, addr: Addr, now_ns: int, reply_clock: Callable[[], int] | None = None
    ) -> list[tuple[bytes, Addr]]:
        """A datagram from ``addr`` received at ``now_ns``; returns the replies to send.

        ``reply_clock``: read once, as late as possible, for a welcome's ``t3`` (NTP's reply time;
        stamping it at receive would bias the clock offset by half this side's processing time).
        None: ``t3 = now_ns`` (tests, fake clocks)."""
        if self.finished:
            return self._ignore("the handshake is over")
        opened = self._open(data, addr, now_ns)
        if opened is None:
            return []
        cand, body = opened
        if cand is None:
            seen = peek_hello(body) if self.cookie_secret is not None else None
            valid = seen is not None and cookie_ok(self.cookie_secret or b"", seen[3], addr, seen[2], now_ns)
            if self.admit is not None and not self.admit(addr, now_ns, valid):
                self.throttled += 1  # over its budget: dropped unanswered, before the full parse
                return []
            if (retry := self._retry(addr, seen, valid, now_ns)) is not None:
                return retry
        try:
            msg = parse(body, local_netem=self.local_netem)
            if (cand is None) != isinstance(msg, Hello):
                raise ProtocolError(f"a {msg.kind} under the wrong key")
        except ProtocolError as e:
            if e.kind != "hello":
                return self._ignore(str(e))
            return self._reject(addr, e.session, str(e), e.t_ns)
        if isinstance(msg, Hello):
            return self._hello(msg, addr, now_ns, reply_clock)
        if isinstance(msg, Start) and cand is not None and msg.session == cand.params.session:
            return self._start(msg, cand, addr, now_ns)
        return self._ignore(f"an unexpected {msg.kind}")

    def _hello(
        self, msg: Hello, addr: Addr, now_ns: int, reply_clock: Callable[[], int] | None
    ) -> list[tuple[bytes, Addr]]:
        """Welcome an authentic hello that suits this teleoperator, and remember its keys."""
        p = msg.params
        why = self._mismatch(p)
        if why is not None:
            return self._reject(addr, p.session, why, msg.t_ns)
        self.params, self.peer = p, addr  # the newest welcomed (what the timeout message names)
        self.welcomes += 1
        # One slot per nonce, whatever address it comes from: replaying one recorded hello from
        # many ports takes one slot, so evicting a genuine operator needs MAX_CANDIDATES recordings.
        key = (p.session, msg.nonce)
        cand = self._candidates.pop(key, None)
        if cand is None:
            if len(self._candidates) >= MAX_CANDIDATES:
                del self._candidates[next(iter(self._candidates))]  # the oldest
            fwd, bwd = auth.session_keys(self.psk, p.session, msg.nonce, self.nonce)
            rx, tx = auth.Opener(fwd, auth.SESSION, FORWARD), auth.Sealer(bwd, auth.SESSION, BACKWARD)
            cand = _Candidate(p, rx, tx, [addr])
        cand.seen_from(addr)
        self._candidates[key] = cand  # newest last
        if self.defer_t3:
            self._drafts.append((Welcome(p.session, msg.t_ns, t2=now_ns, t3=now_ns, nonce=self.nonce), addr))
            return []
        t3 = now_ns if reply_clock is None else max(now_ns, reply_clock())
        welcome = Welcome(p.session, msg.t_ns, t2=now_ns, t3=t3, nonce=self.nonce)
        return [(self.hs_sealer.seal(encode(welcome)), addr)]

    def _start(self, msg: Start, cand: _Candidate, addr: Addr, now_ns: int) -> list[tuple[bytes, Addr]]:
        """A start under a candidate's session key: commit to that operator."""
        # The loop sleeps until start_ns: a start far off would park the endpoint, so it must lie
        # within the session (a rejoin joins a running one) and a few seconds ahead.
        earliest = now_ns - (int(cand.params.span_s * 1e9) if msg.rejoin else START_SLACK_NS)
        if not earliest <= msg.start_ns <= now_ns + START_AHEAD_NS:
            return self._ignore(f"a start {(msg.start_ns - now_ns) / 1e9:+.3g} s from now")
        self.params, self.peer = cand.params, addr
        self.rx_opener, self.tx_sealer = cand.rx_opener, cand.tx_sealer
        self.start_ns, self.rejoin, self.done = msg.start_ns, msg.rejoin, True
        self.start_rtt_ns = msg.rtt_ns
        self._candidates.clear()
        return [(self.tx_sealer.seal(encode(Started(msg.session))), addr)]

    def poll(self, now_ns: int) -> None:
        """Ends the handshake with ``error`` once ``timeout_s`` has passed without a start."""
        if self.finished or now_ns < self._give_up:
            return
        what = "no operator said hello" if self.params is None else "the operator never sent start"
        self.error, self.failure = f"{what} within {self.timeout_s:g} s", Failure.NO_OPERATOR
        if self.rejected:
            self.error += f" ({self.rejected} hello(s) rejected, the last: {self.last_rejection})"

    def next_timer(self) -> int:
        """When :meth:`poll` must be called next (ns, this clock): the timeout."""
        return self._give_up
