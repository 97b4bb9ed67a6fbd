"""The sans-I/O session-control protocol: handshakes in memory with fake clocks, parsing fuzzed.

Nothing here opens a socket or reads a clock: both handshakes are driven against each other by a
small event loop over integer "true time", the teleoperator's clock offset by a known amount.
"""

from __future__ import annotations

import builtins
import contextlib
import dataclasses
import io
import math
import os
import pathlib
import re
from collections.abc import Callable, Iterator
from typing import Any

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import transport.netem
from teleop import limits, protocol, wire
from teleop.codecs import CodecError
from teleop.protocol import (
    MAX_CONTROL_BYTES,
    MAX_TIMESTAMP,
    PROTOCOL_VERSION,
    Bye,
    Hello,
    Message,
    OperatorHandshake,
    ProtocolError,
    Reject,
    SessionParams,
    Start,
    Started,
    TeleoperatorHandshake,
    Welcome,
    encode,
    is_control,
    ntp_offset,
    parse,
)
from teleop.scenarios import SCENARIOS

Addr = tuple[str, int]
OP: Addr = ("10.0.0.1", 40000)
STRANGER: Addr = ("10.0.0.66", 50000)
MS = 1_000_000
S = 1_000_000_000
T0 = 1_000 * S  # the operator's clock at the start of every test

PARAMS = SessionParams(session=7, codec="cq:8", scenario="step", dof=1, b=1.0, full_scale=2.0, duration=5.0)
FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def pack(m: object) -> bytes:
    out: bytes = msgpack.packb(m, use_bin_type=True)
    return out


def hello_map(**change: object) -> dict[str, object]:
    m: dict[str, object] = {"t": "hello", "v": PROTOCOL_VERSION, "t_ns": T0, **PARAMS.to_msg()}
    m.update(change)
    return m


def one(replies: list[tuple[bytes, Addr]], to: Addr) -> Message:
    """The single reply of a receive, sent to ``to``, parsed."""
    assert len(replies) == 1
    data, dest = replies[0]
    assert dest == to
    return parse(data)


# --------------------------------------------------------------------------------------------
# both handshakes against each other
# --------------------------------------------------------------------------------------------
def drive(
    op: OperatorHandshake,
    to: TeleoperatorHandshake,
    *,
    offset: int,
    fwd: Callable[[int], int | None],
    back: Callable[[int], int | None],
    limit_ns: int = 60 * S,
) -> int:
    """Run both until neither has anything left to do; returns the true time at the end.

    True time is the operator's clock; the TO's clock reads ``true + offset``.  ``fwd(i)`` /
    ``back(j)`` give the one-way delay of the i-th datagram each way (None: lost)."""
    net: list[tuple[int, int, str, bytes]] = []  # (arrival, order, destination, data)
    sent = {"to": 0, "op": 0}
    order = 0

    def send(dest: str, data: bytes, now: int) -> None:
        nonlocal order
        i = sent[dest]
        sent[dest] += 1
        d = fwd(i) if dest == "to" else back(i)
        if d is not None:
            net.append((now + d, order, dest, data))
            order += 1

    now = T0
    while now < T0 + limit_ns:
        for data in op.poll(now):
            send("to", data, now)
        to.poll(now + offset)
        if (op.finished or to.error) and not net:
            break
        timers = [t for t, _, _, _ in net]
        if not op.finished:
            timers.append(op.next_timer())
        if not to.finished:
            timers.append(to.next_timer() - offset)
        now = max(now, min(timers))
        net.sort()
        while net and net[0][0] <= now:
            _, _, dest, data = net.pop(0)
            if dest == "op":
                op.receive(data, now)
            else:
                for reply, addr in to.receive(data, OP, now + offset):
                    assert addr == OP
                    send("op", reply, now)
    return now


@pytest.mark.parametrize("offset", [0, 123_456_789, -777 * S, 5 * S + 1])
@pytest.mark.parametrize("delay", [1, 250_000, 7 * MS, 40 * MS])
def test_handshakes_agree_on_the_clock_and_the_start(offset: int, delay: int) -> None:
    op = OperatorHandshake(PARAMS, now_ns=T0, timeout_s=5)
    to = TeleoperatorHandshake({"codec": "cq:8", "dof": 1}, now_ns=T0 + offset, timeout_s=5)
    end = drive(op, to, offset=offset, fwd=lambda i: delay, back=lambda i: delay)
    assert op.done and to.done and op.error is None and to.error is None
    assert op.offset_ns == offset  # symmetric delays: NTP is exact
    assert op.rtt_ns == 2 * delay
    assert op.answers == 8 and to.welcomes == 8 and op.rejected == 0 and to.rejected == 0
    assert to.start_ns == op.start_ns + offset  # the same instant on the TO's clock
    assert to.params == PARAMS and to.peer == OP and not to.rejoin
    assert op.start_ns - end >= op.start_margin_ns  # confirmed before the start itself


@FAST
@given(
    offset=st.integers(-(10**12), 10**12),
    fwd=st.lists(st.integers(1, 45 * MS), min_size=16, max_size=16),
    back=st.lists(st.integers(1, 45 * MS), min_size=16, max_size=16),
)
def test_the_quickest_exchange_sets_the_offset(offset: int, fwd: list[int], back: list[int]) -> None:
    op = OperatorHandshake(PARAMS, now_ns=T0, timeout_s=5)
    to = TeleoperatorHandshake({}, now_ns=T0 + offset, timeout_s=5)
    drive(op, to, offset=offset, fwd=lambda i: fwd[i % 16], back=lambda i: back[i % 16])
    assert op.done and to.done
    # Hello i (i < 8) is answered by welcome i; the first exchange with the least rtt wins.
    rtts = [fwd[i] + back[i] for i in range(8)]
    best = rtts.index(min(rtts))
    assert op.rtt_ns == rtts[best]
    assert op.offset_ns == offset + (fwd[best] - back[best]) // 2
    assert abs(op.offset_ns - offset) <= op.rtt_ns // 2 + 1
    assert to.start_ns == op.start_ns + op.offset_ns


def test_lost_welcomes_are_resent_after_the_interval() -> None:
    op = OperatorHandshake(PARAMS, now_ns=T0, timeout_s=5)
    to = TeleoperatorHandshake({}, now_ns=T0, timeout_s=5)
    drive(op, to, offset=0, fwd=lambda i: MS, back=lambda i: None if i in (0, 2) else MS)
    assert op.done and to.done and op.answers == 8
    assert op.hellos_sent == 10 and to.welcomes == 10


def test_lost_starts_are_resent() -> None:
    op = OperatorHandshake(PARAMS, now_ns=T0, timeout_s=5)
    to = TeleoperatorHandshake({}, now_ns=T0, timeout_s=5)
    drive(op, to, offset=0, fwd=lambda i: None if 8 <= i <= 10 else MS, back=lambda i: MS)
    assert op.done and to.done
    assert to.start_ns == op.start_ns


# --------------------------------------------------------------------------------------------
# encode / parse
# --------------------------------------------------------------------------------------------
@st.composite
def session_params(draw: st.DrawFn) -> SessionParams:
    dof = draw(st.integers(1, limits.MAX_DOF))
    dt = draw(st.floats(limits.MIN_DT, limits.MAX_DT))
    return SessionParams(
        session=draw(st.integers(1, limits.MAX_SESSION)),
        codec=draw(st.sampled_from(["none", "ids:1", "ids:4", "eds:50", "cq:2", "cq:8", "cq:12:3.5"])),
        scenario=draw(st.sampled_from(sorted(SCENARIOS))),
        dof=dof,
        b=draw(st.floats(1e-9, limits.MAX_B)),
        full_scale=draw(st.floats(1e-9, limits.MAX_RANGE)),
        duration=draw(st.floats(limits.MIN_DURATION_S, limits.max_duration_s(dof, dt))),
        dt=dt,
        phase=draw(st.floats(0.0, 1.0, exclude_max=True)),
        netem_forward=draw(st.sampled_from(["", "delay 10ms", "loss 5% 25%", "rate 1mbit 20"])),
        netem_backward=draw(st.sampled_from(["", "delay 20ms 5ms distribution normal", "duplicate 1%"])),
        seed=draw(st.integers(0, limits.MAX_SEED)),
        on_loss=draw(st.sampled_from(["zero", "hold"])),
        controller=draw(st.booleans()),
        link_timeout=draw(st.floats(limits.MIN_LINK_TIMEOUT_S, limits.MAX_LINK_TIMEOUT_S)),
    )


timestamps = st.integers(0, MAX_TIMESTAMP)
sessions = st.integers(1, limits.MAX_SESSION)
texts = st.text(st.characters(blacklist_categories=["Cs"]), max_size=limits.MAX_REASON_LEN)


@st.composite
def welcomes(draw: st.DrawFn) -> Welcome:
    t2 = draw(timestamps)
    return Welcome(draw(sessions), draw(timestamps), t2, draw(st.integers(t2, MAX_TIMESTAMP)))


messages = st.one_of(
    st.builds(Hello, session_params(), timestamps, st.booleans()),
    welcomes(),
    st.builds(Reject, st.none() | sessions, texts),
    st.builds(Start, sessions, timestamps, st.booleans()),
    st.builds(Started, sessions),
    st.builds(Bye, sessions, st.integers(0, protocol.MAX_COUNT), st.integers(0, protocol.MAX_COUNT)),
)


@settings(max_examples=150, deadline=None)
@given(messages)
def test_round_trip(msg: Message) -> None:
    data = encode(msg)
    assert is_control(data) and len(data) <= MAX_CONTROL_BYTES
    assert parse(data) == msg


def test_wire_format_is_todays() -> None:
    """The bytes of the old ``_control(kind, **fields)``: a map, kind and version first."""
    old = pack({"t": "hello", "v": 1, "t_ns": 5, **PARAMS.to_msg()})
    assert encode(Hello(PARAMS, 5)) == old
    assert parse(old) == Hello(PARAMS, 5)
    assert encode(Start(7, 9, rejoin=True)) == pack(
        {"t": "start", "v": 1, "session": 7, "start_ns": 9, "rejoin": True}
    )
    assert encode(Reject(None, "x")) == pack({"t": "reject", "v": 1, "session": None, "why": "x"})
    assert parse(pack({"t": "reject", "v": 1, "why": "x"})) == Reject(None, "x")  # session absent
    assert encode(Bye(7, 3, 0)) == pack(
        {"t": "bye", "v": 1, "session": 7, "produced": 3, "dropped_by_limit": 0}
    )


def test_is_control_tells_maps_from_data_packets() -> None:
    pkt = wire.encode(wire.Packet(7, wire.FORWARD, 1, 1, 1000, 0, b"\x00\x01", 0.0))
    assert not is_control(pkt) and not is_control(b"")
    assert all(is_control(bytes([b])) for b in [*range(0x80, 0x90), 0xDE, 0xDF])
    with pytest.raises(ProtocolError, match="not a control message"):
        parse(pkt)


def test_a_reason_is_truncated() -> None:
    why = "x" * 1000
    assert parse(pack({"t": "reject", "v": 1, "session": 7, "why": why})) == Reject(
        7, "x" * limits.MAX_REASON_LEN
    )
    assert parse(encode(Reject(7, why))) == Reject(7, "x" * limits.MAX_REASON_LEN)


@pytest.mark.parametrize(
    "data,match",
    [
        (b"", "not a control message"),
        (b"\xc1", "not a control message"),
        (b"\x80", "t \\(the kind\\) must be one of"),
        (b"\x81\xc1\x00", "not valid msgpack"),
        (b"\x82\xa1t\xa5hello", "not valid msgpack"),  # truncated
        (pack({"t": "hello"}) + b"\x00", "not valid msgpack"),  # trailing bytes
        (b"\x81\xa1t" + b"\xa2\xff\xfe", "not valid msgpack"),  # not UTF-8
        (b"\x81" * 3000, "not valid msgpack"),  # nested too deep
        (b"\xdf\xff\xff\xff\xff", "not valid msgpack"),  # a map of 4 billion pairs
        (pack({1: 2}), "not valid msgpack"),  # a non-string key
        (pack({"t": "hello", "v": 1, "pad": "x" * 5000}), "at most 4096 bytes"),
        (pack({"t": "nope", "v": 1}), "must be one of hello, welcome"),
        (pack({"t": "started", "v": 2, "session": 7}), "protocol version 2 is not supported"),
        (pack({"t": "started", "v": True, "session": 7}), "protocol version True"),
        (pack({"t": "started", "session": 7}), "protocol version None"),
        (pack({"t": "started", "v": 1}), "bad started: missing field 'session'"),
        (pack({"t": "started", "v": 1, "session": 0}), "session must be an integer in 1..4294967295, got 0"),
        (pack({"t": "welcome", "v": 1, "session": 7, "t_ns": 1, "t3": 2}), "missing field 't2'"),
        (pack({"t": "welcome", "v": 1, "session": 7, "t_ns": 1, "t2": 3, "t3": 2}), "t3 .* must not precede"),
        (pack({"t": "start", "v": 1, "session": 7, "start_ns": -1}), "start_ns must be an integer in 0.."),
        (pack({"t": "start", "v": 1, "session": 7, "start_ns": 2**63}), "start_ns must be"),
        (pack({"t": "start", "v": 1, "session": 7, "start_ns": 1.0}), "start_ns .* got float 1.0"),
        (
            pack({"t": "start", "v": 1, "session": 7, "start_ns": 1, "rejoin": 1}),
            "rejoin must be true or false",
        ),
        (pack({"t": "reject", "v": 1, "session": 7, "why": b"x"}), "why must be a string"),
        (pack({"t": "reject", "v": 1, "session": 7}), "missing field 'why'"),
        (pack({"t": "bye", "v": 1, "session": 7, "produced": 2**32 + 1, "dropped_by_limit": 0}), "produced"),
        (pack(["t", "hello"]), "not a control message"),
    ],
)
def test_bad_messages_say_why(data: bytes, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        parse(data)


# --------------------------------------------------------------------------------------------
# fuzz: ProtocolError or a Message, nothing else, for anything
# --------------------------------------------------------------------------------------------
def parse_or_protocol_error(data: bytes) -> None:
    with contextlib.suppress(ProtocolError):  # anything else fails the test
        assert isinstance(parse(data), Hello | Welcome | Reject | Start | Started | Bye)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_fuzz_bytes(data: bytes) -> None:
    parse_or_protocol_error(data)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from([0x80, 0x81, 0x8F, 0xDE, 0xDF]), st.binary(max_size=200))
def test_fuzz_bytes_that_start_like_a_map(first: int, rest: bytes) -> None:
    parse_or_protocol_error(bytes([first]) + rest)


HOSTILE_NUMBERS: list[object] = [
    math.inf,
    -math.inf,
    math.nan,
    -1,
    -(2**63),
    2**63,
    2**64 - 1,
    1e300,
    -0.0,
    0,
    0.5,
]
HOSTILE: list[object] = [
    *HOSTILE_NUMBERS,
    "1",
    "",
    "x" * 2000,
    True,
    False,
    None,
    [],
    [1],
    {},
    {"a": 1},
    b"\x00",
]
leaves = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**63), 2**64 - 1),
    st.floats(),
    st.text(max_size=20),
    st.binary(max_size=20),
    st.sampled_from(HOSTILE),
)
values = st.recursive(
    leaves,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
    max_leaves=6,
)
FIELD_NAMES = sorted(
    {"t", "v", "t_ns", "t2", "t3", "why", "start_ns", "rejoin", "produced", "dropped_by_limit", *hello_map()}
)


@settings(max_examples=300, deadline=None)
@given(
    st.sampled_from(protocol.KINDS),
    st.dictionaries(st.sampled_from(FIELD_NAMES) | st.text(max_size=8), values, max_size=20),
)
def test_fuzz_maps(kind: str, m: dict[str, object]) -> None:
    parse_or_protocol_error(pack({"t": kind, "v": 1, **m}))
    parse_or_protocol_error(pack(m))


VALID = [
    hello_map(),
    hello_map(rejoin=True, netem_forward="delay 10ms", netem_backward="loss 1%"),
    {"t": "welcome", "v": 1, "session": 7, "t_ns": 1, "t2": 2, "t3": 3},
    {"t": "reject", "v": 1, "session": 7, "why": "no"},
    {"t": "start", "v": 1, "session": 7, "start_ns": 5, "rejoin": True},
    {"t": "started", "v": 1, "session": 7},
    {"t": "bye", "v": 1, "session": 7, "produced": 10, "dropped_by_limit": 0},
]
REMOVED = object()


def test_every_field_of_every_message_replaced_or_removed() -> None:
    """Exhaustive: each valid message, one field at a time, set to each hostile value or removed."""
    outcomes = {"error": 0, "message": 0}
    for base in VALID:
        assert isinstance(parse(pack(base)), Hello | Welcome | Reject | Start | Started | Bye)
        for key in base:
            for bad in [*HOSTILE, REMOVED]:
                m = {k: v for k, v in base.items() if k != key}
                if bad is not REMOVED:
                    m[key] = bad
                try:
                    parse(pack(m))
                    outcomes["message"] += 1
                except ProtocolError:
                    outcomes["error"] += 1
    assert outcomes["error"] > 10 * outcomes["message"]


@settings(max_examples=300, deadline=None)
@given(
    st.sampled_from(VALID),
    st.dictionaries(st.sampled_from(FIELD_NAMES), values, max_size=4),
    st.sets(st.sampled_from(FIELD_NAMES), max_size=3),
)
def test_fuzz_valid_messages_with_fields_replaced_or_removed(
    base: dict[str, object], replaced: dict[str, object], removed: set[str]
) -> None:
    m = {k: v for k, v in {**base, **replaced}.items() if k not in removed}
    parse_or_protocol_error(pack(m))


def test_from_msg_refuses_what_msgpack_could_not_carry() -> None:
    """Called on a dict directly: Python ints beyond any float, odd containers."""
    for key in ("session", "dof", "b", "range", "duration", "dt", "phase", "seed", "link_timeout"):
        for bad in (10**400, -(10**400), object(), 1j):
            with pytest.raises(ProtocolError, match=key):
                SessionParams.from_msg({**PARAMS.to_msg(), key: bad})
    with pytest.raises(ProtocolError, match="must be a map"):
        SessionParams.from_msg([])  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------------
# hostile hellos to a waiting teleoperator
# --------------------------------------------------------------------------------------------
@pytest.fixture
def no_files(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[str]]:
    """Fail the test if anything tries to open a file or load a trace."""
    opened: list[str] = []

    def refuse(*args: Any, **kwargs: Any) -> Any:
        opened.append(repr(args[:1]))
        raise AssertionError(f"tried to open {args[:1]!r}")

    for target, name in [
        (builtins, "open"),
        (io, "open"),
        (os, "open"),
        (pathlib.Path, "open"),
        (pathlib.Path, "read_text"),
        (pathlib.Path, "read_bytes"),
        (transport.netem, "load_trace"),
        (transport.netem, "make_link"),
        (protocol, "make_link"),
    ]:
        monkeypatch.setattr(target, name, refuse)
    yield opened
    assert opened == []


def waiting(**kw: Any) -> TeleoperatorHandshake:
    return TeleoperatorHandshake(kw.pop("expect", {}), now_ns=T0, timeout_s=10, **kw)


def assert_accepts_a_good_hello(to: TeleoperatorHandshake) -> None:
    assert not to.finished
    w = one(to.receive(pack(hello_map(t_ns=42)), OP, T0 + 5), OP)
    assert w == Welcome(7, 42, T0 + 5, T0 + 5)
    assert to.params == PARAMS and to.peer == OP
    assert one(to.receive(encode(Start(7, T0 + S)), OP, T0 + 6), OP) == Started(7)
    assert to.done and to.start_ns == T0 + S


@pytest.mark.parametrize(
    "spec",
    [
        "trace /etc/shadow",
        "trace /dev/zero",
        "  trace   /etc/shadow ",
        "trace /etc/shadow extra",
        "trace",
        "delay 10ms trace /etc/shadow",
    ],
)
@pytest.mark.parametrize("field", ["netem_backward", "netem_forward"])
def test_a_peer_may_not_name_a_file(no_files: list[str], field: str, spec: str) -> None:
    to = waiting()
    whys = []
    for _ in range(3):
        r = one(to.receive(pack(hello_map(**{field: spec})), OP, T0), OP)
        assert isinstance(r, Reject) and r.session == 7
        assert field in r.why
        if spec.split()[0] == "trace":
            assert "a peer may not name a local file" in r.why
        whys.append(r.why)
    assert to.rejected == 3 and to.last_rejection == whys[0] and list(to.rejections) == whys
    assert to.params is None and to.error is None
    assert_accepts_a_good_hello(to)


def test_a_trace_this_side_configured_is_accepted_without_opening_it(no_files: list[str]) -> None:
    with pytest.raises(AssertionError):  # the guard works
        open("/etc/hostname")  # noqa: SIM115
    no_files.clear()
    spec = "trace /srv/traces/lte.down"
    to = waiting(local_netem=[spec])
    w = one(to.receive(pack(hello_map(netem_backward=spec)), OP, T0), OP)
    assert isinstance(w, Welcome) and to.params is not None and to.params.netem_backward == spec
    # ... and so is one named in expect; a different path is not.
    to = waiting(expect={"netem_backward": spec})
    assert isinstance(one(to.receive(pack(hello_map(netem_backward=spec)), OP, T0), OP), Welcome)
    to = waiting(local_netem=[spec])
    r = one(to.receive(pack(hello_map(netem_backward=spec + "x")), OP, T0), OP)
    assert isinstance(r, Reject) and "may not name a local file" in r.why


NUMERIC_FIELDS = ["session", "dof", "duration", "dt", "seed", "link_timeout", "phase", "t_ns", "b", "range"]
BAD_NUMBERS: list[object] = [
    math.inf,
    -math.inf,
    math.nan,
    2**64 - 1,
    2**63,
    1e300,
    -1,
    -1.5,
    "1",
    True,
    None,
    [1],
    {},
]


@pytest.mark.parametrize("field", NUMERIC_FIELDS)
def test_hostile_numbers_are_rejected_and_the_teleoperator_keeps_waiting(
    no_files: list[str], field: str
) -> None:
    to = waiting()
    for i, bad in enumerate(BAD_NUMBERS, 1):
        replies = to.receive(pack(hello_map(**{field: bad})), OP, T0 + i)
        r = one(replies, OP)
        assert isinstance(r, Reject), bad
        assert field in r.why and r.why == to.last_rejection
        assert r.session == (None if field == "session" else 7)
        assert to.rejected == i and not to.finished and to.params is None
    removed = {k: v for k, v in hello_map().items() if k != field}
    r = one(to.receive(pack(removed), OP, T0), OP)
    assert isinstance(r, Reject) and f"missing field {field!r}" in r.why
    assert len(to.rejections) == 14 and to.error is None
    assert_accepts_a_good_hello(to)


@pytest.mark.parametrize(
    "change,why",
    [
        ({"codec": "eds:50"}, "codec 'eds:50' differs from this teleoperator's 'cq:8'"),
        ({"dof": 2}, "dof 2 differs from this teleoperator's 1"),
    ],
)
def test_a_hello_that_differs_from_expect_is_rejected(change: dict[str, object], why: str) -> None:
    to = waiting(expect={"codec": "cq:8", "dof": 1, "scenario": None})
    assert one(to.receive(pack(hello_map(**change)), OP, T0), OP) == Reject(7, why)
    assert to.last_rejection == why and not to.finished
    assert_accepts_a_good_hello(to)


def test_the_operator_reports_the_reject() -> None:
    op = OperatorHandshake(dataclasses.replace(PARAMS, codec="eds:50"), now_ns=T0, timeout_s=5)
    to = waiting(expect={"codec": "cq:8"})
    drive(op, to, offset=0, fwd=lambda i: MS, back=lambda i: MS)
    assert op.error == "rejected the session: codec 'eds:50' differs from this teleoperator's 'cq:8'"
    assert not to.finished and to.rejected == 1


def test_bad_values_that_parse_but_are_out_of_range() -> None:
    to = waiting()
    cases = {
        "dof": (limits.MAX_DOF + 1, "dof must be an integer in 1..64, got 65"),
        "duration": (1e9, "duration must be 0.1 to"),
        "dt": (1.0, "dt must be in 0.0001..0.01"),
        "phase": (1.0, "phase must be in \\[0, 1\\)"),
        "b": (0.0, "b must be > 0"),
        "codec": ("zip:9", "unknown codec"),
        "scenario": ("moon", "scenario must be one of step, protocol"),
        "on_loss": ("explode", "on_loss must be one of zero, hold"),
        "controller": (1, "controller must be true or false"),
        "netem_forward": ("delay 1e999s", "delay must be finite"),
        "netem_backward": ("rate 1bit " + "9" * 400, "packet_overhead must be within"),
        "seed": (limits.MAX_SEED + 1, "seed must be an integer in 0..4294967295"),
        "link_timeout": (11.0, "link_timeout must be in 0.001..10"),
    }
    for field, (bad, match) in cases.items():
        r = one(to.receive(pack(hello_map(**{field: bad})), OP, T0), OP)
        assert isinstance(r, Reject)
        assert re.search(match, r.why), (field, r.why)
        assert "\n" not in r.why and len(r.why) <= limits.MAX_REASON_LEN
    assert to.rejected == len(cases) and not to.finished


def test_garbage_is_counted_and_dropped() -> None:
    to = waiting()
    junk = [
        b"",
        b"\x00" * 50,
        wire.encode(wire.Packet(7, wire.FORWARD, 1, 1, 1000, 0, b"\x00\x01", 0.0)),
        b"\x81" * 3000,
        encode(Welcome(7, 1, 2, 3)),
        encode(Bye(7, 1, 0)),
        encode(Start(7, T0)),  # no welcome agreed on yet
        pack({"t": "start", "v": 1, "session": 7}),
        pack({"t": "hello", "v": 1, "pad": "x" * 5000}),  # too large to tell it is a hello
    ]
    for i, data in enumerate(junk, 1):
        assert to.receive(data, STRANGER, T0) == []
        assert to.ignored == i
    assert to.rejected == 0 and not to.finished and to.last_ignored
    assert_accepts_a_good_hello(to)


def test_a_hello_with_an_unknown_version_is_rejected() -> None:
    to = waiting()
    r = one(to.receive(pack(hello_map(v=2)), OP, T0), OP)
    assert r == Reject(7, "protocol version 2 is not supported; this side speaks 1")


def test_busy_with_another_operator() -> None:
    to = waiting()
    assert isinstance(one(to.receive(pack(hello_map()), OP, T0), OP), Welcome)
    busy = Reject(8, "busy with another operator")
    assert one(to.receive(pack(hello_map(session=8)), STRANGER, T0), STRANGER) == busy
    assert one(to.receive(pack(hello_map(session=8)), OP, T0), OP) == busy  # same address (Zenoh)
    assert one(to.receive(pack(hello_map()), STRANGER, T0), STRANGER) == Reject(7, busy.why)  # same session
    assert one(to.receive(pack(hello_map(dof="x")), STRANGER, T0), STRANGER) == Reject(7, busy.why)
    assert to.receive(encode(Start(7, T0)), STRANGER, T0) == []  # a stranger cannot start it
    assert to.receive(encode(Start(8, T0)), OP, T0) == []
    assert to.rejected == 4 and to.ignored == 2 and to.peer == OP
    # our operator's hellos are still answered (more NTP samples), then its start
    assert isinstance(one(to.receive(pack(hello_map(t_ns=9)), OP, T0 + 1), OP), Welcome)
    assert one(to.receive(encode(Start(7, T0 + S, rejoin=True)), OP, T0 + 2), OP) == Started(7)
    assert to.done and to.rejoin and to.start_ns == T0 + S
    assert to.receive(pack(hello_map()), OP, T0 + 3) == []  # over: the runner's loop takes it from here


def test_rejections_are_bounded() -> None:
    to = waiting()
    for i in range(100):
        to.receive(pack(hello_map(dof=1000 + i)), STRANGER, T0)
    assert to.rejected == 100 and len(to.rejections) == protocol.REJECTIONS_KEPT
    assert to.rejections[-1] == to.last_rejection and "1099" in to.last_rejection
    assert to.last_rejected_addr == STRANGER


def test_expect_must_name_session_parameters() -> None:
    with pytest.raises(ValueError, match="colour"):
        TeleoperatorHandshake({"colour": "red"}, now_ns=0, timeout_s=1)


# --------------------------------------------------------------------------------------------
# the operator against a bad or silent peer
# --------------------------------------------------------------------------------------------
def first_hello(op: OperatorHandshake, now: int = T0) -> Hello:
    out = op.poll(now)
    assert len(out) == 1
    h = parse(out[0])
    assert isinstance(h, Hello)
    return h


def test_a_welcome_without_t2_is_counted_not_raised() -> None:
    op = OperatorHandshake(PARAMS, now_ns=T0, timeout_s=5)
    h = first_hello(op)
    op.receive(pack({"t": "welcome", "v": 1, "session": 7, "t_ns": h.t_ns, "t3": 5}), T0 + MS)
    assert op.rejected == 1 and "missing field 't2'" in op.last_rejection
    assert op.error is None and op.answers == 0
    op.receive(encode(Welcome(7, h.t_ns, 5, 6)), T0 + MS)
    assert op.answers == 1


def test_the_operator_ignores_what_does_not_answer_its_hello() -> None:
    op = OperatorHandshake(PARAMS, now_ns=T0, timeout_s=5)
    h = first_hello(op)
    for data in [
        b"",
        b"\x81" * 3000,
        encode(Welcome(7, h.t_ns + 1, 5, 6)),  # answers another hello
        encode(Welcome(8, h.t_ns, 5, 6)),  # another session
        encode(Reject(8, "not you")),
        encode(Reject(None, "nobody")),
        encode(Started(7)),  # no start sent yet
        encode(Welcome(7, h.t_ns, 5, 5 + 10 * MS)),  # turnaround longer than the round trip
        encode(Bye(7, 1, 0)),
    ]:
        op.receive(data, T0 + MS)
    assert op.rejected == 9 and op.error is None and op.answers == 0
    op.receive(encode(Welcome(7, h.t_ns, 5, 6)), T0 + MS)
    op.receive(encode(Welcome(7, h.t_ns, 5, 6)), T0 + MS)  # a duplicate counts once
    assert op.answers == 1 and op.rejected == 10
    op.receive(encode(Reject(7, "go away")), T0 + 2 * MS)
    assert op.error == "rejected the session: go away" and op.poll(T0 + 3 * MS) == []


def test_the_operator_times_out_without_answers() -> None:
    op = OperatorHandshake(PARAMS, now_ns=T0, timeout_s=1)
    sent = []
    now = T0
    while not op.finished:
        sent += op.poll(now)
        if op.finished:
            break
        assert op.next_timer() > now
        now = op.next_timer()
    assert op.error == "never answered within 1 s" and now == T0 + S
    assert len(sent) == op.hellos_sent == 10
    assert [parse(d).t_ns for d in sent] == [T0 + i * 100 * MS for i in range(10)]  # type: ignore[union-attr]


def test_the_operator_proceeds_at_the_timeout_with_some_answers() -> None:
    op = OperatorHandshake(PARAMS, now_ns=T0, timeout_s=1)
    h = first_hello(op)
    op.receive(encode(Welcome(7, h.t_ns, T0 + 5 * S + 3 * MS, T0 + 5 * S + 3 * MS)), T0 + 6 * MS)
    now, starts = T0 + 6 * MS, []
    while not op.finished:
        for d in op.poll(now):
            m = parse(d)
            if isinstance(m, Start):
                starts.append((now, m))
        now = op.next_timer()
    assert op.error == "did not confirm the start"
    assert op.answers == 1 and op.offset_ns == 5 * S and op.rtt_ns == 6 * MS
    t_first = starts[0][0]
    assert t_first == T0 + S and op.start_ns == t_first + 300 * MS
    assert [t for t, _ in starts] == [t_first + i * 20 * MS for i in range(13)]  # until 50 ms before
    assert {m for _, m in starts} == {Start(7, op.start_ns + 5 * S)}


def test_the_start_is_confirmed() -> None:
    op = OperatorHandshake(PARAMS, now_ns=T0, timeout_s=1, answers=1)
    h = first_hello(op)
    op.receive(encode(Welcome(7, h.t_ns, 10, 10)), T0 + 2 * MS)
    assert op.next_timer() <= T0 + 2 * MS  # poll at once
    (start,) = op.poll(T0 + 2 * MS)
    assert parse(start) == Start(7, op.start_ns + op.offset_ns)
    op.receive(encode(Started(8)), T0 + 3 * MS)
    assert not op.done and op.rejected == 1
    op.receive(encode(Started(7)), T0 + 3 * MS)
    assert op.done and op.error is None and op.poll(T0 + 4 * MS) == []


def test_an_offset_that_puts_the_start_out_of_range() -> None:
    op = OperatorHandshake(PARAMS, now_ns=T0, timeout_s=1, answers=1)
    h = first_hello(op)
    op.receive(encode(Welcome(7, h.t_ns, MAX_TIMESTAMP, MAX_TIMESTAMP)), T0 + MS)
    assert op.poll(T0 + MS) == [] and op.error is not None and "out of range" in op.error


# --------------------------------------------------------------------------------------------
# the teleoperator's timeout
# --------------------------------------------------------------------------------------------
def test_the_teleoperator_times_out() -> None:
    to = TeleoperatorHandshake({}, now_ns=T0, timeout_s=2)
    assert to.next_timer() == T0 + 2 * S
    to.poll(T0 + 2 * S - 1)
    assert to.error is None
    to.poll(T0 + 2 * S)
    assert to.error == "no operator said hello within 2 s"


def test_the_teleoperator_timeout_mentions_the_rejected_hellos() -> None:
    to = TeleoperatorHandshake({"codec": "cq:8"}, now_ns=T0, timeout_s=2)
    to.receive(pack(hello_map(dof=-1)), STRANGER, T0)
    to.receive(pack(hello_map(codec="eds:50")), STRANGER, T0)
    to.poll(T0 + 3 * S)
    assert to.error == (
        "no operator said hello within 2 s (2 hello(s) rejected, the last: "
        "codec 'eds:50' differs from this teleoperator's 'cq:8')"
    )
    to = TeleoperatorHandshake({}, now_ns=T0, timeout_s=2)
    to.receive(pack(hello_map()), OP, T0)
    to.poll(T0 + 2 * S)
    assert to.error == "the operator never sent start within 2 s"


# --------------------------------------------------------------------------------------------
# ntp_offset, and local validation
# --------------------------------------------------------------------------------------------
def test_ntp_offset() -> None:
    # TO clock = operator + 1000; 10 out, 30 back, 5 spent at the TO.
    assert ntp_offset(100, 1110, 1115, 145) == (1000 - 10, 45 - 5)
    assert ntp_offset(0, 1010, 1010, 20) == (1000, 20)


def test_validate_allows_a_local_trace(tmp_path: pathlib.Path) -> None:
    trace = tmp_path / "link.trace"
    trace.write_text("1\n2\n5\n")
    p = dataclasses.replace(PARAMS, netem_backward=f"trace {trace}", codec="CQ:8")
    assert p.validate().codec == "cq:8"
    with pytest.raises(ValueError, match=r"netem_backward: cannot read the trace .*none: No such file"):
        dataclasses.replace(PARAMS, netem_backward=f"trace {tmp_path / 'none'}").validate()


@pytest.mark.parametrize(
    "change,match",
    [
        ({"dof": 65}, "dof must be in 1..64"),
        ({"dt": 1.0}, "dt must be in"),
        ({"duration": math.nan}, "duration must be"),
        ({"duration": 1e9}, "duration must be"),
        ({"phase": 1.0}, "phase"),
        ({"seed": -1}, "seed"),
        ({"link_timeout": 100.0}, "link_timeout"),
        ({"b": math.inf}, "b must be"),
        ({"full_scale": 0.0}, "range must be"),
        ({"session": 0}, "session"),
        ({"scenario": "moon"}, "unknown scenario"),
        ({"on_loss": "explode"}, "on_loss"),
        ({"netem_forward": "delay 1e999s"}, "delay must be finite"),
        ({"netem_forward": "jitter"}, "unknown option"),
        ({"netem_forward": "   "}, None),
    ],
)
def test_validate_applies_the_same_ranges(change: dict[str, object], match: str | None) -> None:
    p = dataclasses.replace(PARAMS, **change)  # type: ignore[arg-type]
    if match is None:
        p.validate()
        return
    with pytest.raises(ValueError, match=match):
        p.validate()


def test_validate_raises_codec_error() -> None:
    with pytest.raises(CodecError):
        dataclasses.replace(PARAMS, codec="zip").validate()


@pytest.mark.parametrize(
    "delta_s,rejoin,accepted",
    [
        (0.3, False, True),
        (-0.5, False, True),
        (-5.0, False, False),
        (3600.0, False, False),
        (-5.0, True, True),
        (-100.0, True, False),
        (11.0, True, False),
    ],
)
def test_a_start_far_from_now_is_ignored(delta_s: float, rejoin: bool, accepted: bool) -> None:
    """The teleoperator sleeps until the start: one far off would park it (a hostile start)."""
    to = TeleoperatorHandshake({}, now_ns=T0, timeout_s=5)
    one(to.receive(pack(hello_map()), OP, T0), OP)
    replies = to.receive(encode(Start(PARAMS.session, T0 + int(delta_s * 1e9), rejoin)), OP, T0)
    assert to.done is accepted and (len(replies) == 1) is accepted
    if not accepted:
        assert to.ignored == 1 and "from now" in to.last_ignored
