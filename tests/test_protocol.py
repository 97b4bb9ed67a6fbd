"""The sans-I/O session-control protocol: handshakes in memory with fake clocks, parsing fuzzed.

Nothing here opens a socket or reads a clock: both handshakes are driven against each other by a
small event loop over integer "true time", the teleoperator's clock offset by a known amount.

Every datagram the state machines take or return is an authenticated envelope (``teleop.session.auth``):
hello, welcome and reject under the handshake key, start and started under the session keys.  The
helpers below seal what a test sends as a peer holding the key would (``to_hs``: a hello to the
teleoperator, ``op_hs``: a welcome or reject to the operator, ``to_ss`` / ``op_ss``: the same under
the session keys), and open what the state machines send, checking key, kind and direction
(``from_hs`` / ``from_ss``: the teleoperator's replies, ``from_op_hs`` / ``from_op_ss``: the
operator's datagrams).  ``parse`` and ``encode`` work on bare bodies and are tested on those.
"""

from __future__ import annotations

import builtins
import contextlib
import dataclasses
import io
import itertools
import math
import os
import pathlib
import random
import re
from collections.abc import Callable, Iterator
from typing import Any

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import teleop.session.link.netem
import teleop.session.settings
from teleop import limits
from teleop.control.codecs import CodecError
from teleop.devices.scenarios import SCENARIOS
from teleop.session import auth, protocol, wire
from teleop.session.auth import HANDSHAKE, SESSION, AuthError
from teleop.session.protocol import (
    BACKWARD,
    FORWARD,
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

Addr = tuple[str, int]
OP: Addr = ("10.0.0.1", 40000)
STRANGER: Addr = ("10.0.0.66", 50000)
MS = 1_000_000
S = 1_000_000_000
T0 = 1_000 * S  # the operator's clock at the start of every test

PARAMS = SessionParams(session=7, codec="cq:8", scenario="step", dof=1, b=1.0, full_scale=2.0, duration=5.0)
FAST = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])

PSK = bytes(range(32))  # the deployment's pre-shared key
OTHER_PSK = bytes(range(1, 33))  # another deployment's
NONCE_OP = bytes(range(16))  # the operator's nonce
NONCE_TO = bytes(range(100, 116))  # the teleoperator's
NONCES = (NONCE_OP, NONCE_TO)
OTHER_NONCE = bytes(range(200, 216))  # a restarted peer's
OLD_NONCE = bytes(range(50, 66))  # the operator's of an earlier, recorded handshake

_counters = itertools.count(1)  # every datagram sealed here has a counter never used before


def pack(m: object) -> bytes:
    out: bytes = msgpack.packb(m, use_bin_type=True)
    return out


def hello_map(**change: object) -> dict[str, object]:
    m: dict[str, object] = {
        "t": "hello",
        "v": PROTOCOL_VERSION,
        "t_ns": T0,
        "nonce": NONCE_OP,
        **PARAMS.to_msg(),
    }
    m.update(change)
    return m


def welcome(t_ns: int, t2: int, t3: int, session: int = 7) -> Welcome:
    """The teleoperator's welcome, with its nonce."""
    return Welcome(session, t_ns, t2, t3, NONCE_TO)


def _key(kind: int, direction: int, psk: bytes, session: int, nonces: tuple[bytes, bytes]) -> bytes:
    if kind == HANDSHAKE:
        return auth.handshake_key(psk)
    return auth.session_keys(psk, session, *nonces)[direction]


def seal(
    body: bytes,
    direction: int,
    kind: int,
    *,
    psk: bytes = PSK,
    session: int = 7,
    nonces: tuple[bytes, bytes] = NONCES,
) -> bytes:
    """``body`` in the envelope a peer holding ``psk`` would send it in."""
    key = _key(kind, direction, psk, session, nonces)
    return auth.Sealer(key, kind, direction, counter=next(_counters)).seal(body)


def unseal(
    data: bytes,
    direction: int,
    kind: int,
    *,
    psk: bytes = PSK,
    session: int = 7,
    nonces: tuple[bytes, bytes] = NONCES,
) -> Message:
    """The message in an envelope that verifies under that key, kind and direction (else AuthError)."""
    _, body = auth.Opener(_key(kind, direction, psk, session, nonces), kind, direction).verify(data)
    return parse(body)


def to_hs(body: bytes, **kw: Any) -> bytes:
    """A datagram from the operator to the teleoperator under the handshake key (a hello)."""
    return seal(body, FORWARD, HANDSHAKE, **kw)


def to_ss(body: bytes, **kw: Any) -> bytes:
    """A datagram from the operator to the teleoperator under the session key (a start)."""
    return seal(body, FORWARD, SESSION, **kw)


def from_hs(data: bytes, **kw: Any) -> Message:
    """The teleoperator's reply under the handshake key (a welcome or reject), verified and parsed."""
    return unseal(data, BACKWARD, HANDSHAKE, **kw)


def from_ss(data: bytes, **kw: Any) -> Message:
    """The teleoperator's reply under the session key (a started), verified and parsed."""
    return unseal(data, BACKWARD, SESSION, **kw)


def op_hs(body: bytes, **kw: Any) -> bytes:
    """A datagram from the teleoperator to the operator under the handshake key (welcome, reject)."""
    return seal(body, BACKWARD, HANDSHAKE, **kw)


def op_ss(body: bytes, **kw: Any) -> bytes:
    """A datagram from the teleoperator to the operator under the session key (a started)."""
    return seal(body, BACKWARD, SESSION, **kw)


def from_op_hs(data: bytes, **kw: Any) -> Message:
    """The operator's datagram under the handshake key (a hello), verified and parsed."""
    return unseal(data, FORWARD, HANDSHAKE, **kw)


def from_op_ss(data: bytes, **kw: Any) -> Message:
    """The operator's datagram under the session key (a start), verified and parsed."""
    return unseal(data, FORWARD, SESSION, **kw)


def flipped(data: bytes, bit: int) -> bytes:
    out = bytearray(data)
    out[bit // 8] ^= 1 << (bit % 8)
    return bytes(out)


def operator(params: SessionParams = PARAMS, **kw: Any) -> OperatorHandshake:
    """An operator's handshake with the test key and nonce (``timeout_s`` 5 unless given)."""
    kw.setdefault("timeout_s", 5)
    kw.setdefault("psk", PSK)
    kw.setdefault("nonce", NONCE_OP)
    return OperatorHandshake(params, now_ns=kw.pop("now_ns", T0), **kw)


def teleoperator(expect: dict[str, object] | None = None, **kw: Any) -> TeleoperatorHandshake:
    """A teleoperator's handshake with the test key and nonce (``timeout_s`` 5 unless given)."""
    kw.setdefault("timeout_s", 5)
    kw.setdefault("psk", PSK)
    kw.setdefault("nonce", NONCE_TO)
    return TeleoperatorHandshake(expect or {}, now_ns=kw.pop("now_ns", T0), **kw)


def one(replies: list[tuple[bytes, Addr]], to: Addr, *, session_key: bool = False, **kw: Any) -> Message:
    """The single reply of a receive, sent to ``to``, verified (handshake key, or the session
    key with ``session_key``; ``kw``: another session id or nonces) and parsed."""
    assert len(replies) == 1
    data, dest = replies[0]
    assert dest == to
    return from_ss(data, **kw) if session_key else from_hs(data, **kw)


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
    op = operator()
    to = teleoperator({"codec": "cq:8", "dof": 1}, now_ns=T0 + offset)
    end = drive(op, to, offset=offset, fwd=lambda i: delay, back=lambda i: delay)
    assert op.done and to.done and op.error is None and to.error is None
    assert op.offset_ns == offset  # symmetric delays: NTP is exact
    assert op.rtt_ns == 2 * delay
    assert op.answers == 8 and to.welcomes == 8 and op.rejected == 0 and to.rejected == 0
    assert op.unauthenticated == 0 and to.unauthenticated == 0 and op.peer_nonce == NONCE_TO
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
    op = operator()
    to = teleoperator(now_ns=T0 + offset)
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
    op = operator()
    to = teleoperator()
    drive(op, to, offset=0, fwd=lambda i: MS, back=lambda i: None if i in (0, 2) else MS)
    assert op.done and to.done and op.answers == 8
    assert op.hellos_sent == 10 and to.welcomes == 10


def test_lost_starts_are_resent() -> None:
    op = operator()
    to = teleoperator()
    drive(op, to, offset=0, fwd=lambda i: None if 8 <= i <= 10 else MS, back=lambda i: MS)
    assert op.done and to.done
    assert to.start_ns == op.start_ns
    assert to.unauthenticated == 0  # each resent start has a fresh counter: none is taken for a replay


# --------------------------------------------------------------------------------------------
# encode / parse (bare bodies: the envelope is the state machines' business)
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
nonces = st.binary(min_size=auth.NONCE_BYTES, max_size=auth.NONCE_BYTES)


@st.composite
def welcomes(draw: st.DrawFn) -> Welcome:
    t2 = draw(timestamps)
    return Welcome(draw(sessions), draw(timestamps), t2, draw(st.integers(t2, MAX_TIMESTAMP)), draw(nonces))


messages = st.one_of(
    st.builds(Hello, session_params(), timestamps, st.booleans(), nonces),
    welcomes(),
    st.builds(Reject, st.none() | sessions, texts, timestamps),
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
    """Today's bytes: a map, kind and version first; hello and welcome carry a 16-byte bin nonce."""
    hello = pack({"t": "hello", "v": 1, "t_ns": 5, "nonce": NONCE_OP, **PARAMS.to_msg()})
    assert encode(Hello(PARAMS, 5, nonce=NONCE_OP)) == hello
    assert parse(hello) == Hello(PARAMS, 5, nonce=NONCE_OP)
    assert encode(welcome(1, 2, 3)) == pack(
        {"t": "welcome", "v": 1, "session": 7, "t_ns": 1, "t2": 2, "t3": 3, "nonce": NONCE_TO}
    )
    assert encode(Start(7, 9, rejoin=True)) == pack(
        {"t": "start", "v": 1, "session": 7, "start_ns": 9, "rejoin": True}
    )
    assert encode(Reject(None, "x")) == pack({"t": "reject", "v": 1, "session": None, "why": "x", "t_ns": 0})
    assert encode(Reject(7, "x", 5)) == pack({"t": "reject", "v": 1, "session": 7, "why": "x", "t_ns": 5})
    assert parse(pack({"t": "reject", "v": 1, "why": "x", "t_ns": 5})) == Reject(None, "x", 5)  # no session
    # The reject of before the echo (no t_ns) is refused: it could not be matched to a hello.
    with pytest.raises(ProtocolError, match="bad reject: missing field 't_ns'"):
        parse(pack({"t": "reject", "v": 1, "session": 7, "why": "x"}))
    assert encode(Bye(7, 3, 0)) == pack(
        {"t": "bye", "v": 1, "session": 7, "produced": 3, "dropped_by_limit": 0}
    )
    # The hello of before authentication (no nonce) is refused.
    with pytest.raises(ProtocolError, match="bad hello: missing field 'nonce'"):
        parse(pack({"t": "hello", "v": 1, "t_ns": 5, **PARAMS.to_msg()}))


def test_the_envelope_of_every_handshake_datagram() -> None:
    """b"T", flags (version 1, key kind, direction), counter 1, 2, ... from each sealer, the body, a tag."""
    op = operator(answers=1)
    (hello,) = op.poll(T0)
    body = encode(Hello(PARAMS, T0, nonce=NONCE_OP))
    assert hello[:1] == b"T" and hello[1] == 0x10 | (HANDSHAKE << 1) | FORWARD
    assert auth.peek(hello) == (HANDSHAKE, FORWARD, 1) and len(hello) == len(body) + auth.OVERHEAD
    assert hello[auth.HEADER_BYTES : -auth.TAG_BYTES] == body
    to = teleoperator()
    ((w, _),) = to.receive(hello, OP, T0 + 2)
    assert auth.peek(w) == (HANDSHAKE, BACKWARD, 1) and from_hs(w) == welcome(T0, T0 + 2, T0 + 2)
    op.receive(w, T0 + 4)
    (start,) = op.poll(T0 + 4)
    assert auth.peek(start) == (SESSION, FORWARD, 1)
    ((started, _),) = to.receive(start, OP, T0 + 5)
    assert auth.peek(started) == (SESSION, BACKWARD, 1) and from_ss(started) == Started(7)
    op.receive(started, T0 + 6)
    assert op.done and to.done


def test_is_control_tells_maps_from_data_packets() -> None:
    pkt = wire.encode(wire.Packet(7, wire.FORWARD, 1, 1, 1000, 0, b"\x00\x01", 0.0))
    assert not is_control(pkt) and not is_control(b"")
    assert all(is_control(bytes([b])) for b in [*range(0x80, 0x90), 0xDE, 0xDF])
    with pytest.raises(ProtocolError, match="not a control message"):
        parse(pkt)


def test_a_reason_is_truncated() -> None:
    why = "x" * 1000
    assert parse(pack({"t": "reject", "v": 1, "session": 7, "why": why, "t_ns": 3})) == Reject(
        7, "x" * limits.MAX_REASON_LEN, 3
    )
    assert parse(encode(Reject(7, why, 3))) == Reject(7, "x" * limits.MAX_REASON_LEN, 3)


WELCOME_MAP: dict[str, object] = {"t": "welcome", "v": 1, "session": 7, "t_ns": 1, "t2": 2, "t3": 3}


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
        (pack(WELCOME_MAP), "bad welcome: missing field 'nonce'"),
        (pack({**WELCOME_MAP, "nonce": bytes(15)}), "nonce must be 16 bytes .* got bytes"),
        (pack({**WELCOME_MAP, "nonce": bytes(17)}), "nonce must be 16 bytes"),
        (pack({**WELCOME_MAP, "nonce": "x" * 16}), "nonce must be 16 bytes \\(msgpack bin\\), got str"),
        (pack(hello_map(nonce=None)), "bad hello: nonce must be 16 bytes"),
        (pack(hello_map(nonce=[0] * 16)), "bad hello: nonce .* got list"),
        (pack(hello_map(nonce=b"")), "bad hello: nonce must be 16 bytes"),
        (pack({k: v for k, v in hello_map().items() if k != "nonce"}), "bad hello: missing field 'nonce'"),
        (pack({"t": "start", "v": 1, "session": 7, "start_ns": -1}), "start_ns must be an integer in 0.."),
        (pack({"t": "start", "v": 1, "session": 7, "start_ns": 2**63}), "start_ns must be"),
        (pack({"t": "start", "v": 1, "session": 7, "start_ns": 1.0}), "start_ns .* got float 1.0"),
        (
            pack({"t": "start", "v": 1, "session": 7, "start_ns": 1, "rejoin": 1}),
            "rejoin must be true or false",
        ),
        (pack({"t": "reject", "v": 1, "session": 7, "why": b"x", "t_ns": 1}), "why must be a string"),
        (pack({"t": "reject", "v": 1, "session": 7, "t_ns": 1}), "missing field 'why'"),
        (pack({"t": "reject", "v": 1, "session": 7, "why": "x"}), "bad reject: missing field 't_ns'"),
        (
            pack({"t": "reject", "v": 1, "session": 7, "why": "x", "t_ns": -1}),
            "t_ns must be an integer in 0..",
        ),
        (pack({"t": "reject", "v": 1, "session": 7, "why": "x", "t_ns": 2**63}), "t_ns must be"),
        (pack({"t": "reject", "v": 1, "session": 7, "why": "x", "t_ns": 1.0}), "t_ns .* got float 1.0"),
        (pack({"t": "reject", "v": 1, "session": 7, "why": "x", "t_ns": True}), "t_ns .* got bool True"),
        (pack({"t": "bye", "v": 1, "session": 7, "produced": 2**32 + 1, "dropped_by_limit": 0}), "produced"),
        (pack(["t", "hello"]), "not a control message"),
        (to_hs(pack(hello_map())), "not a control message"),  # an envelope is not a body
    ],
)
def test_bad_messages_say_why(data: bytes, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        parse(data)


@pytest.mark.parametrize(
    "m,kind,session,t_ns",
    [
        (hello_map(dof=-1), "hello", 7, T0),
        (hello_map(v=2), "hello", 7, T0),  # the version is checked first: the echo is still read
        (hello_map(session="x", t_ns=5), "hello", None, 5),
        (hello_map(nonce=b""), "hello", 7, T0),
        (hello_map(t_ns=-1), "hello", 7, 0),
        (hello_map(t_ns=2**63), "hello", 7, 0),
        (hello_map(t_ns=1.5), "hello", 7, 0),
        (hello_map(t_ns=True), "hello", 7, 0),
        (hello_map(t_ns=str(T0)), "hello", 7, 0),
        ({"t": "hello", "v": 1}, "hello", None, 0),
        ({"t": "welcome", "v": 1, "session": 7, "t_ns": 9}, "welcome", 7, 9),
        ({"v": 1, "t_ns": 9}, None, None, 0),  # no kind: nothing is read
    ],
)
def test_a_protocol_error_carries_what_could_be_read(
    m: dict[str, object], kind: str | None, session: int | None, t_ns: int
) -> None:
    """kind, session and t_ns of a bad message, so that a bad hello's reject can echo its t_ns."""
    with pytest.raises(ProtocolError) as e:
        parse(pack(m))
    assert (e.value.kind, e.value.session, e.value.t_ns) == (kind, session, t_ns)


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
    {**WELCOME_MAP, "nonce": NONCE_TO},
    {"t": "reject", "v": 1, "session": 7, "why": "no", "t_ns": 5},
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
# hostile hellos to a waiting teleoperator (sealed with the key: what a peer holding it may send)
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
        (teleop.session.link.netem, "load_trace"),
        (teleop.session.link.netem, "make_link"),
        (teleop.session.settings, "make_link"),
    ]:
        monkeypatch.setattr(target, name, refuse)
    yield opened
    assert opened == []


def waiting(**kw: Any) -> TeleoperatorHandshake:
    return teleoperator(kw.pop("expect", {}), timeout_s=10, **kw)


def hello(**change: object) -> bytes:
    """A hello map, changed, sealed as the operator's hello."""
    return to_hs(pack(hello_map(**change)))


def assert_accepts_a_good_hello(to: TeleoperatorHandshake, unauthenticated: int = 0) -> None:
    """It still welcomes a good hello and confirms its start; ``unauthenticated`` datagrams were
    dropped before (0: everything the test sent so far got through the envelope to the protocol)."""
    assert not to.finished
    assert to.unauthenticated == unauthenticated
    w = one(to.receive(hello(t_ns=42), OP, T0 + 5), OP)
    assert w == welcome(42, T0 + 5, T0 + 5)
    assert to.params == PARAMS and to.peer == OP
    assert one(to.receive(to_ss(encode(Start(7, T0 + S))), OP, T0 + 6), OP, session_key=True) == Started(7)
    assert to.done and to.start_ns == T0 + S and to.unauthenticated == unauthenticated


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
        r = one(to.receive(hello(**{field: spec}), OP, T0), OP)
        assert isinstance(r, Reject) and r.session == 7 and r.t_ns == T0
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
    w = one(to.receive(hello(netem_backward=spec), OP, T0), OP)
    assert isinstance(w, Welcome) and to.params is not None and to.params.netem_backward == spec
    # ... and so is one named in expect; a different path is not.
    to = waiting(expect={"netem_backward": spec})
    assert isinstance(one(to.receive(hello(netem_backward=spec), OP, T0), OP), Welcome)
    to = waiting(local_netem=[spec])
    r = one(to.receive(hello(netem_backward=spec + "x"), OP, T0), OP)
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
        replies = to.receive(hello(**{field: bad}), OP, T0 + i)
        r = one(replies, OP)
        assert isinstance(r, Reject), bad
        assert field in r.why and r.why == to.last_rejection
        assert r.session == (None if field == "session" else 7)
        assert r.t_ns == (0 if field == "t_ns" else T0)  # the echo, if the hello's t_ns could be read
        assert to.rejected == i and not to.finished and to.params is None
    removed = {k: v for k, v in hello_map().items() if k != field}
    r = one(to.receive(to_hs(pack(removed)), OP, T0), OP)
    assert isinstance(r, Reject) and f"missing field {field!r}" in r.why
    assert r.t_ns == (0 if field == "t_ns" else T0)
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
    assert one(to.receive(hello(**change), OP, T0), OP) == Reject(7, why, T0)
    assert to.last_rejection == why and not to.finished
    assert_accepts_a_good_hello(to)


def test_the_operator_reports_the_reject() -> None:
    op = operator(dataclasses.replace(PARAMS, codec="eds:50"))
    to = waiting(expect={"codec": "cq:8"})
    drive(op, to, offset=0, fwd=lambda i: MS, back=lambda i: MS)
    assert op.error == "rejected the session: codec 'eds:50' differs from this teleoperator's 'cq:8'"
    assert not to.finished and to.rejected == 1


def test_bad_values_that_parse_but_are_out_of_range() -> None:
    to = waiting()
    cases = {
        "dof": (limits.MAX_DOF + 1, "dof must be an integer in 1..64, got 65"),
        "duration": (1e9, "duration must be 0 \\(until stopped\\) or 0.1 to 604800 s"),
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
        "nonce": (bytes(15), "nonce must be 16 bytes"),
    }
    for field, (bad, match) in cases.items():
        r = one(to.receive(hello(**{field: bad}), OP, T0), OP)
        assert isinstance(r, Reject) and r.t_ns == T0
        assert re.search(match, r.why), (field, r.why)
        assert "\n" not in r.why and len(r.why) <= limits.MAX_REASON_LEN
    assert to.rejected == len(cases) and not to.finished and to.unauthenticated == 0


def test_garbage_is_counted_and_dropped() -> None:
    to = waiting()
    junk = [
        b"",
        b"\x00" * 50,
        wire.encode(wire.Packet(7, wire.FORWARD, 1, 1, 1000, 0, b"\x00\x01", 0.0)),
        b"\x81" * 3000,
        encode(welcome(1, 2, 3)),
        encode(Bye(7, 1, 0)),
        encode(Start(7, T0)),  # under the handshake key, and no welcome agreed on yet
        pack({"t": "start", "v": 1, "session": 7}),
        pack({"t": "hello", "v": 1, "pad": "x" * 5000}),  # too large to tell it is a hello
    ]
    # Sealed with the key, they reach the protocol, which drops them without an answer ...
    for i, data in enumerate(junk, 1):
        assert to.receive(to_hs(data), STRANGER, T0) == []
        assert to.ignored == i
    assert to.rejected == 0 and not to.finished and to.last_ignored and to.unauthenticated == 0
    # ... bare, they do not even get that far.
    for i, data in enumerate(junk, 1):
        assert to.receive(data, STRANGER, T0) == []
        assert to.unauthenticated == i and to.ignored == len(junk)
    # A start under the session key it would have: there is none before a welcome.
    assert to.receive(to_ss(encode(Start(7, T0))), OP, T0) == []
    assert (
        to.unauthenticated == len(junk) + 1 and "under no welcomed operator's key" in to.last_unauthenticated
    )
    assert to.rejected == 0 and to.ignored == len(junk)
    assert_accepts_a_good_hello(to, unauthenticated=len(junk) + 1)


def test_a_hello_with_an_unknown_version_is_rejected() -> None:
    to = waiting()
    r = one(to.receive(hello(v=2), OP, T0), OP)
    assert r == Reject(7, "protocol version 2 is not supported; this side speaks 1", T0)


def start_of(session: int, nonce_op: bytes, start_ns: int = T0 + S, **kw: Any) -> bytes:
    """The start of the operator with ``nonce_op`` for ``session``, under its session key with
    the teleoperator's nonce NONCE_TO."""
    return to_ss(encode(Start(session, start_ns, **kw)), session=session, nonces=(nonce_op, NONCE_TO))


@pytest.mark.parametrize("session2", [7, 8], ids=["one session", "two sessions"])
@pytest.mark.parametrize("zenoh", [False, True], ids=["two addresses", "one pseudo-address"])
@pytest.mark.parametrize("first", [0, 1], ids=["the first welcomed starts", "the second starts"])
def test_two_operators_are_welcomed_and_the_first_start_wins(session2: int, zenoh: bool, first: int) -> None:
    """No "busy" during the handshake: a hello may be a recording, so it commits to nothing and
    every operator holding the key is welcomed.  The first start that verifies under the session
    key of one of them (proof it saw this teleoperator's nonce) commits to that one; the other's
    start then draws nothing (the runner answers it "busy" once the session runs)."""
    ops = [(OP, 7, NONCE_OP), (OP if zenoh else STRANGER, session2, OTHER_NONCE)]
    params = [dataclasses.replace(PARAMS, session=session) for _, session, _ in ops]
    to = waiting()
    for i, (addr, session, nonce) in enumerate(ops):
        w = one(to.receive(hello(session=session, nonce=nonce, t_ns=T0 + i), addr, T0 + 10 + i), addr)
        assert w == welcome(T0 + i, T0 + 10 + i, T0 + 10 + i, session=session)
        assert to.params == params[i] and to.peer == addr  # the newest welcomed: informational
    # More NTP samples for the first: still welcomed, and now the newest.
    assert isinstance(one(to.receive(hello(t_ns=T0 + 5), OP, T0 + 15), OP), Welcome)
    assert to.params == PARAMS and to.peer == OP
    assert to.welcomes == 3 and to.rejected == to.ignored == to.unauthenticated == 0
    assert not to.finished and to.rx_opener is None and to.tx_sealer is None
    assert list(candidates(to)) == [ops[1], ops[0]]

    (addr_w, session_w, nonce_w), (addr_l, session_l, nonce_l) = ops[first], ops[1 - first]
    loser_start = start_of(session_l, nonce_l, T0 + 2 * S)
    if not zenoh:  # a start from the other's address is tried against that address's candidates only
        assert to.receive(loser_start, addr_w, T0 + 20) == []
        assert to.unauthenticated == 1 and "under no welcomed operator's key" in to.last_unauthenticated
    replies = to.receive(start_of(session_w, nonce_w), addr_w, T0 + 30)
    started = one(replies, addr_w, session_key=True, session=session_w, nonces=(nonce_w, NONCE_TO))
    assert started == Started(session_w)
    assert to.done and to.peer == addr_w and to.params == params[first]
    assert to.start_ns == T0 + S and not to.rejoin and not candidates(to)
    # The port's keys are the winner's: they open its datagrams and not the other's.
    assert to.rx_opener is not None and to.tx_sealer is not None
    fwd_w, bwd_w = auth.session_keys(PSK, session_w, nonce_w, NONCE_TO)
    fwd_l, _ = auth.session_keys(PSK, session_l, nonce_l, NONCE_TO)
    assert to.rx_opener.verify(auth.Sealer(fwd_w, SESSION, FORWARD).seal(b"w"))[1] == b"w"
    assert auth.Opener(bwd_w, SESSION, BACKWARD).verify(to.tx_sealer.seal(b"b"))[1] == b"b"
    with pytest.raises(AuthError, match="tag"):
        to.rx_opener.verify(auth.Sealer(fwd_l, SESSION, FORWARD).seal(b"l"))

    # The other's start, hellos, starts again: nothing, and nothing changes.
    unauthenticated = to.unauthenticated
    for data in [loser_start, hello(session=session_l, nonce=nonce_l), start_of(session_w, nonce_w)]:
        assert to.receive(data, addr_l, T0 + 40) == []
        assert to.last_ignored == "the handshake is over"
    assert to.ignored == 3 and to.unauthenticated == unauthenticated
    assert to.done and to.peer == addr_w and to.params == params[first] and to.start_ns == T0 + S


def test_a_start_is_tried_against_the_operators_welcomed_from_its_address() -> None:
    """OP's start sent from another address, or a start keyed for an operator welcomed elsewhere,
    verifies under none of that address's candidates."""
    to = waiting()
    one(to.receive(hello(), OP, T0), OP)
    one(to.receive(hello(nonce=OTHER_NONCE), STRANGER, T0), STRANGER)
    assert to.receive(start_of(7, NONCE_OP), STRANGER, T0 + 1) == []
    assert to.receive(start_of(7, OTHER_NONCE), OP, T0 + 1) == []
    assert to.receive(start_of(7, NONCE_OP), ("10.0.0.1", 40001), T0 + 1) == []  # another port
    assert to.receive(start_of(8, NONCE_OP), OP, T0 + 1) == []  # a session no hello proposed
    assert to.unauthenticated == 4 and not to.finished and to.ignored == 0
    assert set(candidates(to).values()) == {(0, 0)}  # no window moved
    # A start for session 8 under OP's session-7 key: authentic, but not what was welcomed.
    assert to.receive(to_ss(encode(Start(8, T0 + S))), OP, T0 + 1) == []
    assert to.ignored == 1 and to.last_ignored == "an unexpected start" and not to.finished
    # A bad hello meanwhile is rejected with its reason, and forgets no candidate.
    r = one(to.receive(hello(dof="x"), STRANGER, T0 + 1), STRANGER)
    assert isinstance(r, Reject) and "dof" in r.why and r.t_ns == T0 and len(candidates(to)) == 2
    assert one(to.receive(start_of(7, NONCE_OP), OP, T0 + 2), OP, session_key=True) == Started(7)
    assert to.done and to.peer == OP


@pytest.mark.parametrize("zenoh", [False, True], ids=["an address each", "one pseudo-address"])
def test_candidates_beyond_max_candidates_evict_the_oldest(zenoh: bool) -> None:
    """At most MAX_CANDIDATES operators are remembered; a new one evicts the oldest, whose start no
    longer verifies.  A hello again makes a candidate the newest (and brings an evicted one back)."""
    n = protocol.MAX_CANDIDATES
    ops = [(("10.0.1.1", 40000) if zenoh else ("10.0.1.1", 40000 + i), bytes([i]) * 16) for i in range(n + 1)]

    def welcome_all(to: TeleoperatorHandshake, which: list[int]) -> None:
        for i in which:
            addr, nonce = ops[i]
            assert isinstance(one(to.receive(hello(nonce=nonce, t_ns=T0 + i), addr, T0 + i), addr), Welcome)

    def commits(which: list[int], i: int) -> bool:
        """Whether operator i's start commits after the hellos of ``which``, in that order."""
        to = waiting()
        welcome_all(to, which)
        addr, nonce = ops[i]
        replies = to.receive(start_of(7, nonce), addr, T0 + 100)
        if not replies:
            assert to.unauthenticated == 1 and not to.finished
            return False
        assert one(replies, addr, session_key=True, nonces=(nonce, NONCE_TO)) == Started(7)
        assert to.done and to.peer == addr
        return True

    to = waiting()
    welcome_all(to, list(range(n)))
    assert len(candidates(to)) == n
    welcome_all(to, [n])
    assert [nonce for _, _, nonce in candidates(to)] == [ops[i][1] for i in range(1, n + 1)]
    assert [commits(list(range(n + 1)), i) for i in range(n + 1)] == [False] + [True] * n
    # A hello again moves operator 0 to the newest: operator 1 is evicted instead.
    order = [*range(n), 0, n]
    assert [commits(order, i) for i in range(n + 1)] == [True, False] + [True] * (n - 1)
    # An evicted operator that says hello again is a candidate again (with a fresh window).
    order = [*range(n + 1), 0]
    assert [commits(order, i) for i in range(n + 1)] == [True, False] + [True] * (n - 1)
    to = waiting()
    welcome_all(to, order)
    assert len(candidates(to)) == n and to.welcomes == n + 2


def test_rejections_are_bounded() -> None:
    to = waiting()
    for i in range(100):
        to.receive(hello(dof=1000 + i), STRANGER, T0)
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
    h = from_op_hs(out[0])
    assert isinstance(h, Hello) and h.nonce == op.nonce
    return h


def test_a_welcome_without_t2_is_counted_not_raised() -> None:
    op = operator()
    h = first_hello(op)
    op.receive(op_hs(pack({"t": "welcome", "v": 1, "session": 7, "t_ns": h.t_ns, "t3": 5})), T0 + MS)
    assert op.rejected == 1 and "missing field 't2'" in op.last_rejection
    assert op.error is None and op.answers == 0
    op.receive(op_hs(encode(welcome(h.t_ns, 5, 6))), T0 + MS)
    assert op.answers == 1 and op.unauthenticated == 0


def test_the_operator_ignores_what_does_not_answer_its_hello() -> None:
    op = operator()
    h = first_hello(op)
    for data, why in [
        (b"", "not a control message"),
        (b"\x81" * 3000, "not valid msgpack"),
        (encode(welcome(h.t_ns + 1, 5, 6)), "a welcome that answers no hello in flight"),  # another hello
        (encode(welcome(h.t_ns, 5, 6, session=8)), "an unexpected welcome for session 8"),
        (encode(Reject(8, "not you", h.t_ns)), "an unexpected reject for session 8"),
        (encode(Reject(None, "nobody", h.t_ns)), "an unexpected reject for session None"),
        (encode(Reject(7, "go away")), "a reject that answers none of our hellos"),  # t_ns 0
        (encode(Reject(7, "go away", h.t_ns + 1)), "a reject that answers none of our hellos"),
        (encode(Started(7)), "a started under the wrong key"),  # no start sent yet, and the wrong key
        (encode(welcome(h.t_ns, 5, 5 + 10 * MS)), "turnaround t3 - t2 exceeds the round trip"),
        (encode(Bye(7, 1, 0)), "a bye under the wrong key"),
    ]:
        op.receive(op_hs(data), T0 + MS)
        assert why in op.last_rejection
    assert op.rejected == 11 and op.error is None and op.answers == 0 and op.unauthenticated == 0
    op.receive(op_ss(encode(Started(7))), T0 + MS)  # no session keys yet either
    assert op.unauthenticated == 1 and "before the session keys exist" in op.last_unauthenticated
    good = op_hs(encode(welcome(h.t_ns, 5, 6)))
    op.receive(good, T0 + MS)
    op.receive(good, T0 + MS)  # a duplicate counts once
    op.receive(op_hs(encode(welcome(h.t_ns, 5, 6))), T0 + MS)  # and so does a resent one
    assert op.answers == 1 and op.rejected == 13
    op.receive(op_hs(encode(Reject(7, "go away", h.t_ns))), T0 + 2 * MS)  # answers our hello
    assert op.error == "rejected the session: go away" and op.poll(T0 + 3 * MS) == []


def test_the_operator_times_out_without_answers() -> None:
    op = operator(timeout_s=1)
    sent = []
    now = T0
    while not op.finished:
        sent += op.poll(now)
        if op.finished:
            break
        assert op.next_timer() > now
        now = op.next_timer()
    assert op.error == "never answered within 1 s (10 hellos sent, 0 retries taken)" and now == T0 + S
    assert op.failure == protocol.Failure.NO_ANSWER  # nothing at all came back: the key is not blamed
    assert len(sent) == op.hellos_sent == 10
    hellos = [from_op_hs(d) for d in sent]
    assert [h.t_ns for h in hellos if isinstance(h, Hello)] == [T0 + i * 100 * MS for i in range(10)]
    assert [auth.peek(d) for d in sent] == [(HANDSHAKE, FORWARD, i) for i in range(1, 11)]


def test_the_operator_proceeds_at_the_timeout_with_some_answers() -> None:
    op = operator(timeout_s=1)
    h = first_hello(op)
    op.receive(op_hs(encode(welcome(h.t_ns, T0 + 5 * S + 3 * MS, T0 + 5 * S + 3 * MS))), T0 + 6 * MS)
    now, starts, counters = T0 + 6 * MS, [], []
    while not op.finished:
        for d in op.poll(now):
            if auth.peek(d) == (HANDSHAKE, FORWARD, op.hellos_sent):
                assert isinstance(from_op_hs(d), Hello)  # more NTP samples until the timeout
                continue
            m = from_op_ss(d)
            assert isinstance(m, Start)
            starts.append((now, m))
            counters.append(auth.peek(d))
        now = op.next_timer()
    assert op.error == "did not confirm the start (13 start(s) sent)"  # and it refused nothing
    assert op.answers == 1 and op.offset_ns == 5 * S and op.rtt_ns == 6 * MS
    t_first = starts[0][0]
    assert t_first == T0 + S and op.start_ns == t_first + 300 * MS
    assert [t for t, _ in starts] == [t_first + i * 20 * MS for i in range(13)]  # until 50 ms before
    assert {m for _, m in starts} == {Start(7, op.start_ns + 5 * S, rtt_ns=op.rtt_ns)}
    assert counters == [(SESSION, FORWARD, i) for i in range(1, 14)]  # a resent start is not a replay


def test_the_start_is_confirmed() -> None:
    op = operator(timeout_s=1, answers=1)
    h = first_hello(op)
    op.receive(op_hs(encode(welcome(h.t_ns, 10, 10))), T0 + 2 * MS)
    assert op.next_timer() <= T0 + 2 * MS  # poll at once
    (start,) = op.poll(T0 + 2 * MS)
    assert from_op_ss(start) == Start(7, op.start_ns + op.offset_ns, rtt_ns=op.rtt_ns)
    op.receive(op_ss(encode(Started(8))), T0 + 3 * MS)
    assert not op.done and op.rejected == 1
    op.receive(op_ss(encode(Started(7))), T0 + 3 * MS)
    assert op.done and op.error is None and op.poll(T0 + 4 * MS) == []
    assert op.unauthenticated == 0


def test_an_offset_that_puts_the_start_out_of_range() -> None:
    op = operator(timeout_s=1, answers=1)
    h = first_hello(op)
    op.receive(op_hs(encode(welcome(h.t_ns, MAX_TIMESTAMP, MAX_TIMESTAMP))), T0 + MS)
    assert op.poll(T0 + MS) == [] and op.error is not None and "out of range" in op.error


# --------------------------------------------------------------------------------------------
# the teleoperator's timeout
# --------------------------------------------------------------------------------------------
def test_the_teleoperator_times_out() -> None:
    to = teleoperator(timeout_s=2)
    assert to.next_timer() == T0 + 2 * S
    to.poll(T0 + 2 * S - 1)
    assert to.error is None
    to.poll(T0 + 2 * S)
    assert to.error == "no operator said hello within 2 s"


def test_the_teleoperator_timeout_mentions_the_rejected_hellos() -> None:
    to = teleoperator({"codec": "cq:8"}, timeout_s=2)
    to.receive(hello(dof=-1), STRANGER, T0)
    to.receive(hello(codec="eds:50"), STRANGER, T0)
    to.receive(to_hs(pack(hello_map(dof=-2)), psk=OTHER_PSK), STRANGER, T0)  # not counted as rejected
    to.poll(T0 + 3 * S)
    assert to.error == (
        "no operator said hello within 2 s (2 hello(s) rejected, the last: "
        "codec 'eds:50' differs from this teleoperator's 'cq:8')"
    )
    to = teleoperator(timeout_s=2)
    to.receive(hello(), OP, T0)
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
    with pytest.raises(ValueError, match=r"netem_backward: trace .*none: No such file"):
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
    to = teleoperator()
    one(to.receive(hello(), OP, T0), OP)
    replies = to.receive(to_ss(encode(Start(PARAMS.session, T0 + int(delta_s * 1e9), rejoin))), OP, T0)
    assert to.done is accepted and (len(replies) == 1) is accepted
    if accepted:
        assert one(replies, OP, session_key=True) == Started(7)
    else:
        assert to.ignored == 1 and "from now" in to.last_ignored


# --------------------------------------------------------------------------------------------
# authentication: what a datagram without the key, or under another key, cannot do
# --------------------------------------------------------------------------------------------
def _envelope(flags: int, counter: int, rest: bytes) -> bytes:
    """Bytes that look like an envelope (magic, flags, counter) with anything after: no valid tag."""
    return b"T" + bytes([flags]) + counter.to_bytes(8, "big") + rest


def hello_dg(**kw: Any) -> bytes:
    """A good hello's body, sealed as the operator's hello with ``kw`` (psk, ...)."""
    return to_hs(pack(hello_map()), **kw)


UNAUTHENTIC_HELLOS: dict[str, tuple[Callable[[], bytes], str]] = {
    # name: (the datagram, what last_unauthenticated says)
    "another psk": (lambda: hello_dg(psk=OTHER_PSK), "tag"),
    "the insecure key": (lambda: hello_dg(psk=auth.INSECURE_KEY), "tag"),
    "bare, no envelope": (lambda: pack(hello_map()), "not a teleop envelope"),
    "random bytes": (lambda: random.Random(1).randbytes(300), "not a teleop envelope"),
    "empty": (lambda: b"", "not a teleop envelope"),
    "a header and no tag": (lambda: _envelope(0x10, 1, pack(hello_map())), "tag"),
    "a zero tag": (lambda: _envelope(0x10, 1, pack(hello_map()) + bytes(auth.TAG_BYTES)), "tag"),
    "the tag cut short": (lambda: hello_dg()[:-1], "tag"),
    "counter 0": (lambda: _envelope(0x10, 0, hello_dg()[auth.HEADER_BYTES :]), "not a teleop envelope"),
    "envelope version 2": (lambda: b"T\x20" + hello_dg()[2:], "not a teleop envelope"),
    "the welcome's direction": (lambda: seal(pack(hello_map()), BACKWARD, HANDSHAKE), "direction"),
    "the session key": (lambda: to_ss(pack(hello_map())), "under no welcomed operator's key"),
}


@pytest.mark.parametrize("name", list(UNAUTHENTIC_HELLOS))
def test_an_unauthenticated_hello_is_counted_and_never_answered(name: str) -> None:
    make, why = UNAUTHENTIC_HELLOS[name]
    to = waiting()
    for i in range(1, 4):
        assert to.receive(make(), STRANGER, T0 + i) == []  # no reply: no amplification, no oracle
        assert to.unauthenticated == i and why in to.last_unauthenticated
    assert to.rejected == to.ignored == to.welcomes == 0 and not to.rejections
    assert to.params is None and to.peer is None and to.rx_opener is None and to.tx_sealer is None
    to.poll(T0 + 9 * S)
    assert not to.finished  # it keeps waiting ...
    assert_accepts_a_good_hello(to, unauthenticated=3)  # ... and then accepts a good one


def test_every_bit_flip_of_a_hello_is_unauthenticated() -> None:
    to = waiting()
    good = hello_dg()
    bits = 8 * len(good)
    for bit in range(bits):
        assert to.receive(flipped(good, bit), OP, T0) == []
    assert to.unauthenticated == bits and to.rejected == to.ignored == to.welcomes == 0
    assert to.params is None and to.rx_opener is None
    assert isinstance(one(to.receive(good, OP, T0), OP), Welcome)


def test_without_the_key_a_hello_draws_no_reject_and_no_welcome() -> None:
    """What draws a reject from a holder of the key draws nothing at all from anyone else."""
    to = waiting(expect={"codec": "cq:8"})
    bad = [
        hello_map(dof=-1),
        hello_map(codec="eds:50"),
        hello_map(v=2),
        hello_map(netem_forward="trace /etc/shadow"),
        {"t": "hello", "v": 1, "session": 7},
    ]
    for n, m in enumerate(bad, 1):
        assert to.receive(to_hs(pack(m), psk=OTHER_PSK), STRANGER, T0) == []
        assert to.unauthenticated == n and to.rejected == 0
    for n, m in enumerate(bad, 1):  # the same bodies under the right key: rejected, with a reason
        assert isinstance(one(to.receive(to_hs(pack(m)), STRANGER, T0), STRANGER), Reject)
        assert to.rejected == n
    assert isinstance(one(to.receive(hello(), OP, T0), OP), Welcome)
    # With OP welcomed, another holder of the key is welcomed too (a hello commits to nothing);
    # one without the key is not answered, not even from OP's address, and changes nothing.
    assert one(to.receive(hello(session=8), STRANGER, T0), STRANGER) == welcome(T0, T0, T0, session=8)
    assert to.receive(to_hs(pack(hello_map(session=8)), psk=OTHER_PSK), STRANGER, T0) == []
    assert to.receive(to_hs(pack(hello_map(session=9)), psk=OTHER_PSK), OP, T0) == []
    assert to.unauthenticated == len(bad) + 2 and to.rejected == len(bad) and to.welcomes == 2
    assert to.params == dataclasses.replace(PARAMS, session=8) and to.peer == STRANGER  # the newest welcomed
    assert sorted(candidates(to)) == [(OP, 7, NONCE_OP), (STRANGER, 8, NONCE_OP)]


def test_peers_with_different_keys_never_agree() -> None:
    op = operator(timeout_s=1)
    to = teleoperator(psk=OTHER_PSK, timeout_s=2)
    drive(op, to, offset=0, fwd=lambda i: MS, back=lambda i: MS)
    assert op.error == "never answered within 1 s (10 hellos sent, 0 retries taken)" and op.hellos_sent == 10
    assert op.answers == 0 and op.failure == protocol.Failure.NO_ANSWER  # another key stays silent
    assert to.unauthenticated == 10 and to.welcomes == to.rejected == to.ignored == 0
    assert to.params is None and not to.done


def welcomed(nonce_op: bytes = NONCE_OP, **kw: Any) -> TeleoperatorHandshake:
    """A teleoperator that has welcomed OP's hello (carrying ``nonce_op``) for session 7."""
    to = waiting(**kw)
    assert one(to.receive(hello(nonce=nonce_op), OP, T0), OP) == welcome(T0, T0, T0)
    assert to.rx_opener is None and to.tx_sealer is None  # a candidate's keys, until a start commits
    assert list(candidates(to)) == [(OP, 7, nonce_op)]
    return to


def candidates(to: TeleoperatorHandshake) -> dict[tuple[Addr, int, bytes], tuple[int, int]]:
    """The operators ``to`` welcomed and has not committed to, oldest first: (address, session,
    nonce) -> the replay window (highest counter, bitmap) of its session key."""
    return {(c.addrs[0], *k): (c.rx_opener.highest, c.rx_opener._seen) for k, c in to._candidates.items()}


START = encode(Start(7, T0 + S))

#: name: (the start datagram, the counter it lands in: "ignored" reached the protocol, "unauthenticated" not)
WRONG_KEY_STARTS: dict[str, tuple[Callable[[], bytes], str]] = {
    "the handshake key": (lambda: to_hs(START), "ignored"),
    "the handshake key, backward": (lambda: op_hs(START), "unauthenticated"),
    "another psk": (lambda: to_ss(START, psk=OTHER_PSK), "unauthenticated"),
    "another session id": (lambda: to_ss(START, session=8), "unauthenticated"),
    "another operator nonce": (lambda: to_ss(START, nonces=(OTHER_NONCE, NONCE_TO)), "unauthenticated"),
    "another teleoperator nonce": (lambda: to_ss(START, nonces=(NONCE_OP, OTHER_NONCE)), "unauthenticated"),
    "the nonces swapped": (lambda: to_ss(START, nonces=(NONCE_TO, NONCE_OP)), "unauthenticated"),
    "the backward key (a reflected started)": (lambda: op_ss(START), "unauthenticated"),
    "bare, no envelope": (lambda: START, "unauthenticated"),
}


@pytest.mark.parametrize("name", list(WRONG_KEY_STARTS))
def test_a_start_under_any_other_key_is_not_accepted(name: str) -> None:
    make, counter = WRONG_KEY_STARTS[name]
    to = welcomed()
    assert to.receive(make(), OP, T0 + 1) == []
    assert not to.done and to.start_ns == 0
    assert (to.ignored, to.unauthenticated) == ((1, 0) if counter == "ignored" else (0, 1))
    if counter == "ignored":
        assert to.last_ignored == "a start under the wrong key"
    assert candidates(to) == {(OP, 7, NONCE_OP): (0, 0)}  # the window did not move
    start = to_ss(START)
    assert one(to.receive(start, OP, T0 + 2), OP, session_key=True) == Started(7)
    assert to.done and to.start_ns == T0 + S and to.peer == OP
    assert to.rx_opener is not None and (SESSION, FORWARD, to.rx_opener.highest) == auth.peek(start)


def run_handshake(
    op: OperatorHandshake, to: TeleoperatorHandshake, capture: list[bytes] | None = None, now: int = T0
) -> None:
    """The operator (answers=1) and the teleoperator, lossless, 1 ms each way, from ``now``; what
    the operator sends is appended to ``capture``."""
    while not op.finished:
        for d in op.poll(now):
            if capture is not None:
                capture.append(d)
            for reply, _ in to.receive(d, OP, now + MS):
                op.receive(reply, now + 2 * MS)
        now = max(now + 2 * MS, op.next_timer())
    assert op.done and to.done


def test_a_captured_start_does_not_start_another_handshake() -> None:
    """Keys bound to both nonces and the session: a recorded start replayed into a new handshake
    fails authentication there, whichever side restarted."""
    captured: list[bytes] = []
    run_handshake(operator(answers=1), teleoperator(), captured)
    old_hello, old_start = captured
    assert isinstance(from_op_hs(old_hello), Hello) and isinstance(from_op_ss(old_start), Start)

    # The teleoperator restarted (new nonce).  The recorded hello is still authentic (the handshake
    # key does not change) and is welcomed, but the recorded start was keyed with the old nonce.
    to = teleoperator(nonce=OTHER_NONCE)
    assert isinstance(one(to.receive(old_hello, OP, T0 + S), OP), Welcome)
    assert to.receive(old_start, OP, T0 + S + 1) == []
    assert to.unauthenticated == 1 and not to.done
    assert to.last_unauthenticated == "a session datagram under no welcomed operator's key"

    # The operator restarted (new nonce), the same teleoperator nonce: the same.
    to = teleoperator()
    assert one(to.receive(hello(nonce=OTHER_NONCE), OP, T0), OP) == welcome(T0, T0, T0)
    assert to.receive(old_start, OP, T0 + 1) == []
    assert to.unauthenticated == 1 and not to.done

    # Same nonces (as if reused), another session id: the same.
    to = teleoperator()
    assert isinstance(one(to.receive(hello(session=8), OP, T0), OP), Welcome)
    assert to.receive(old_start, OP, T0 + 1) == []
    assert to.unauthenticated == 1 and not to.done


EARLIER = T0 - 600 * S  # the clock of an earlier run: its hellos' t_ns are none of this run's


def recorded(session: int = 7) -> tuple[bytes, bytes]:
    """(hello, start) recorded from an earlier handshake: another operator nonce (OLD_NONCE),
    another teleoperator nonce (OTHER_NONCE), ten minutes earlier; the hello's t_ns is EARLIER."""
    captured: list[bytes] = []
    p = dataclasses.replace(PARAMS, session=session)
    old_op = operator(p, answers=1, nonce=OLD_NONCE, now_ns=EARLIER)
    run_handshake(old_op, teleoperator(nonce=OTHER_NONCE, now_ns=EARLIER), captured, now=EARLIER)
    old_hello, old_start = captured
    assert from_op_hs(old_hello) == Hello(p, EARLIER, nonce=OLD_NONCE)
    return old_hello, old_start


def run_with_replays(
    op: OperatorHandshake, to: TeleoperatorHandshake, replays: list[tuple[bytes, Addr]]
) -> tuple[int, list[bytes]]:
    """The operator (at OP) and the teleoperator, lossless, 1 ms each way, with every (datagram,
    source address) of ``replays`` reaching the teleoperator just before each datagram of the
    operator.  Replies to OP reach the operator (over Zenoh, what is sent to one reaches all).
    Returns (the rounds: the operator's datagrams, the replies sent elsewhere: the attacker's)."""
    rounds, elsewhere, now = 0, [], T0
    while not op.finished:
        for d in op.poll(now):
            rounds += 1
            for data, src in [*replays, (d, OP)]:
                for reply, dest in to.receive(data, src, now + MS):
                    if dest == OP:
                        op.receive(reply, now + 2 * MS)
                    else:
                        elsewhere.append(reply)
        now = max(now + 2 * MS, op.next_timer())
    return rounds, elsewhere


def assert_keys_agree(op: OperatorHandshake, to: TeleoperatorHandshake) -> None:
    """The port's keys of both sides open each other's datagrams (no key was switched)."""
    assert op.tx_sealer and op.rx_opener and to.tx_sealer and to.rx_opener
    now = (op.start_ns + 1) / 1e9
    assert to.rx_opener.open(op.tx_sealer.seal(b"forward"), now)[1] == b"forward"
    assert op.rx_opener.open(to.tx_sealer.seal(b"backward"), now)[1] == b"backward"


@pytest.mark.parametrize("old_session", [7, 9])
def test_a_replayed_hello_from_another_address_locks_nobody_out(old_session: int) -> None:
    """A hello recorded from an earlier handshake and replayed to a fresh teleoperator from another
    address is welcomed (a hello proves only that someone once held the key) but commits to
    nothing: the genuine operator's handshake, with the replay sent again and again, completes."""
    old_hello, old_start = recorded(old_session)
    old_params = dataclasses.replace(PARAMS, session=old_session)
    to = teleoperator()
    assert one(to.receive(old_hello, STRANGER, T0), STRANGER) == welcome(EARLIER, T0, T0, session=old_session)
    assert to.params == old_params and to.peer == STRANGER and not to.finished  # the newest welcomed
    assert to.receive(old_start, STRANGER, T0) == []  # keyed with the old nonces
    assert to.unauthenticated == 1 and to.rx_opener is None

    op = operator()
    rounds, to_attacker = run_with_replays(op, to, [(old_hello, STRANGER), (old_start, STRANGER)])
    assert op.done and to.done and op.error is None and to.error is None
    assert to.peer == OP and to.params == PARAMS and to.start_ns == op.start_ns and not to.rejoin
    assert op.answers == 8 and op.rejected == 0 and op.unauthenticated == 0
    assert rounds == 9  # 8 hellos and a start
    # Byte-identical copies of the recording are dropped as replays, unanswered: only its first
    # copy (above) was welcomed, and it never got further.
    assert to_attacker == [] and to.unauthenticated == 1 + 2 * rounds
    assert to.welcomes == 8 + 1
    assert_keys_agree(op, to)

    # Without a genuine operator, the replay alone never commits: the teleoperator times out.
    to = teleoperator()
    for i in range(10):
        replies = to.receive(old_hello, STRANGER, T0 + i * S // 2)
        assert len(replies) == (i == 0) and to.receive(old_start, STRANGER, T0 + i * S // 2) == []
    to.poll(T0 + 5 * S)
    assert not to.done and to.error == "the operator never sent start within 5 s"


def test_a_replayed_hello_on_the_same_address_and_session_switches_no_keys() -> None:
    """Over Zenoh every operator has one pseudo-address: an old hello (old nonce, same session)
    interleaved with the genuine handshake makes a second candidate, not a key switch, and the
    genuine start still commits.  The welcomes of the replay reach the operator, which refuses them."""
    old_hello, old_start = recorded(7)
    to = teleoperator()
    op = operator()
    rounds, elsewhere = run_with_replays(op, to, [(old_hello, OP), (old_start, OP)])
    assert elsewhere == []
    assert op.done and to.done and op.error is None and to.error is None
    assert to.peer == OP and to.params == PARAMS and to.start_ns == op.start_ns
    assert rounds == 9 and op.answers == 8 and to.welcomes == 8 + 1  # the recording's first copy
    assert op.rejected == 1  # the replay's one welcome: it answers none of the operator's hellos
    assert to.unauthenticated == rounds + rounds - 1 and op.unauthenticated == 0  # starts, copies
    assert_keys_agree(op, to)
    assert to.receive(old_hello, OP, T0 + 2 * S) == [] and to.last_ignored == "the handshake is over"


def test_a_recorded_reject_does_not_end_a_later_handshake() -> None:
    """A reject echoes the t_ns of the hello it refuses: one recorded from an earlier handshake
    answers none of a later operator's hellos, and is refused however often it comes."""
    old_op = operator(dataclasses.replace(PARAMS, codec="eds:50"), nonce=OLD_NONCE, now_ns=EARLIER)
    old_to = teleoperator({"codec": "cq:8"}, nonce=OTHER_NONCE, now_ns=EARLIER)
    (old_hello,) = old_op.poll(EARLIER)
    ((old_reject, _),) = old_to.receive(old_hello, OP, EARLIER + MS)
    why = "codec 'eds:50' differs from this teleoperator's 'cq:8'"
    assert from_hs(old_reject) == Reject(7, why, EARLIER)
    old_op.receive(old_reject, EARLIER + 2 * MS)
    assert old_op.error == f"rejected the session: {why}"  # it did end the handshake it answered

    op = operator()
    to = teleoperator()
    now, replayed = T0, 0
    while not op.finished:
        for d in op.poll(now):
            for reply, _ in to.receive(d, OP, now + MS):
                op.receive(old_reject, now + 2 * MS)  # just before each reply of the teleoperator
                replayed += 1
                assert op.error is None and op.last_rejection == "a reject that answers none of our hellos"
                op.receive(reply, now + 2 * MS)
        now = max(now + 2 * MS, op.next_timer())
    assert op.done and to.done and op.error is None
    assert replayed == 9 and op.rejected == replayed and op.answers == 8  # 8 welcomes and the started
    assert_keys_agree(op, to)


@pytest.mark.parametrize(
    "echo,ends",
    [
        (lambda ts: ts[-1], True),
        (lambda ts: ts[-64], True),
        (lambda ts: ts[-65], False),  # older than the last 64 hellos
        (lambda ts: ts[-1] + 1, False),
        (lambda ts: 0, False),  # what a reject of a hello with an unreadable t_ns echoes
    ],
    ids=["the last hello", "the 64th last", "the 65th last", "no hello", "zero"],
)
def test_a_reject_ends_the_handshake_if_it_echoes_one_of_our_hellos(
    echo: Callable[[list[int]], int], ends: bool
) -> None:
    op = operator(timeout_s=10)
    ts: list[int] = []
    now = T0
    while len(ts) < 65:
        ts.append(first_hello(op, now).t_ns)
        now = op.next_timer()
    assert ts == [T0 + i * 100 * MS for i in range(65)]
    op.receive(op_hs(encode(Reject(7, "no", echo(ts)))), now)
    if ends:
        assert op.error == "rejected the session: no" and op.rejected == 0
    else:
        assert op.error is None and op.rejected == 1
        assert op.last_rejection == "a reject that answers none of our hellos"


def test_a_replayed_start_draws_no_second_started() -> None:
    """Once done the teleoperator answers nothing (the runner's port takes over, with the replay
    window the start's counter is already in); before, its window refuses a second copy."""
    to = welcomed()
    far = to_ss(encode(Start(7, T0 + 3600 * S)))  # authentic but refused: an hour ahead
    assert to.receive(far, OP, T0) == [] and to.ignored == 1 and "from now" in to.last_ignored
    assert to.receive(far, OP, T0) == []  # its counter was taken: now it is a replay
    assert to.ignored == 1 and to.unauthenticated == 1 and "already seen" in to.last_unauthenticated

    start = to_ss(START)
    assert one(to.receive(start, OP, T0 + 1), OP, session_key=True) == Started(7)
    assert to.done and to.start_ns == T0 + S
    for i in range(3):
        assert to.receive(start, OP, T0 + 2 + i) == []
    assert to.ignored == 4 and to.last_ignored == "the handshake is over" and to.start_ns == T0 + S
    assert to.unauthenticated == 1  # a finished handshake does not even open what it gets
    assert to.rx_opener is not None
    with pytest.raises(AuthError) as e:  # the window handed to the port refuses it too
        to.rx_opener.open(start, (T0 + 5) / 1e9)
    assert e.value.reason == "replay"


def test_the_operator_does_not_count_a_welcome_it_cannot_authenticate() -> None:
    op = operator()
    h = first_hello(op)
    body = encode(welcome(h.t_ns, 5, 6))
    good = op_hs(body)
    for data in [
        op_hs(body, psk=OTHER_PSK),  # a teleoperator of another deployment
        op_hs(body, psk=auth.INSECURE_KEY),
        body,  # bare
        flipped(good, 8 * auth.HEADER_BYTES + 3),  # a bit of the body
        flipped(good, 8 * len(good) - 1),  # a bit of the tag
        to_hs(body),  # the operator's own direction (a reflection)
        op_ss(body),  # no session keys yet
        b"",
    ]:
        op.receive(data, T0 + MS)
    assert op.unauthenticated == 8 and op.answers == 0 and op.rejected == 0 and op.peer_nonce is None
    # A reject nobody with the key sent does not end it either, even one that echoes the hello.
    op.receive(op_hs(encode(Reject(7, "go away", h.t_ns)), psk=OTHER_PSK), T0 + MS)
    assert op.error is None and op.unauthenticated == 9
    op.receive(good, T0 + MS)
    assert op.answers == 1 and op.peer_nonce == NONCE_TO and op.unauthenticated == 9


def starting(**kw: Any) -> tuple[OperatorHandshake, bytes]:
    """An operator (answers=1) that has had its welcome and sent its first start."""
    op = operator(answers=1, **kw)
    h = first_hello(op)
    op.receive(op_hs(encode(welcome(h.t_ns, 10, 10))), T0 + 2 * MS)
    (start,) = op.poll(T0 + 2 * MS)
    assert op.rx_opener is not None and op.tx_sealer is not None
    return op, start


def test_the_operator_takes_a_started_only_under_its_session_key() -> None:
    op, start = starting()
    started = encode(Started(7))
    for data in [
        op_ss(started, nonces=(NONCE_OP, OTHER_NONCE)),  # another teleoperator's session
        op_ss(started, nonces=(OTHER_NONCE, NONCE_TO)),
        op_ss(started, session=8),
        op_ss(started, psk=OTHER_PSK),
        to_ss(started),  # the forward key
        start,  # its own start reflected
        started,  # bare
    ]:
        op.receive(data, T0 + 3 * MS)
        assert not op.done
    assert op.unauthenticated == 7 and op.rejected == 0
    good = op_ss(started)
    op.receive(good, T0 + 3 * MS)
    assert op.done and op.error is None and op.unauthenticated == 7


def test_a_started_under_the_handshake_key_does_not_finish_the_operator() -> None:
    op, _ = starting()
    op.receive(op_hs(encode(Started(7))), T0 + 3 * MS)
    assert not op.done and op.error is None
    assert op.rejected == 1 and op.last_rejection == "a started under the wrong key"
    op.receive(op_ss(encode(Started(7))), T0 + 3 * MS)
    assert op.done and op.rejected == 1 and op.unauthenticated == 0


def test_the_operator_takes_welcome_and_reject_only_under_the_handshake_key() -> None:
    """Under the session key (which a teleoperator uses only for started), a welcome or a reject,
    even one that answers our hello, is refused."""
    op = operator(answers=2)
    h = first_hello(op)
    op.receive(op_hs(encode(welcome(h.t_ns, 10, 10))), T0 + 2 * MS)
    h2 = first_hello(op, T0 + 2 * MS)
    op.receive(op_ss(encode(welcome(h2.t_ns, 10, 10))), T0 + 3 * MS)  # no session keys yet
    assert op.unauthenticated == 1 and op.answers == 1
    op.receive(op_hs(encode(welcome(h2.t_ns, 10, 10))), T0 + 3 * MS)
    (start,) = op.poll(T0 + 3 * MS)  # now the session keys exist
    assert op.rx_opener is not None and isinstance(from_op_ss(start), Start)
    for body, kind in [
        (encode(Reject(7, "go away", h2.t_ns)), "reject"),
        (encode(welcome(h2.t_ns, 10, 10)), "welcome"),
    ]:
        op.receive(op_ss(body), T0 + 4 * MS)
        assert op.last_rejection == f"a {kind} under the wrong key"
    assert op.rejected == 2 and op.error is None and not op.done and op.unauthenticated == 1
    op.receive(op_hs(encode(Reject(7, "go away", h2.t_ns))), T0 + 4 * MS)
    assert op.error == "rejected the session: go away"


def agreed(nonce_op: bytes, nonce_to: bytes) -> tuple[OperatorHandshake, TeleoperatorHandshake]:
    op = operator(nonce=nonce_op)
    to = teleoperator(nonce=nonce_to)
    drive(op, to, offset=0, fwd=lambda i: MS, back=lambda i: MS)
    assert op.done and to.done
    return op, to


def test_after_the_handshake_the_keys_agree() -> None:
    op, to = agreed(NONCE_OP, NONCE_TO)
    assert op.tx_sealer and op.rx_opener and to.tx_sealer and to.rx_opener
    # The port goes on from the handshake's counters: the started (1) and the starts sent.
    assert to.tx_sealer.counter == 2 and op.rx_opener.highest == 1
    assert to.rx_opener.highest == op.tx_sealer.counter - 1
    now = (op.start_ns + 1) / 1e9
    for i in range(3):
        data = f"forward {i}".encode()
        assert to.rx_opener.open(op.tx_sealer.seal(data), now)[1] == data
        data = f"backward {i}".encode()
        assert op.rx_opener.open(to.tx_sealer.seal(data), now)[1] == data
    # The documented derivation, one key per direction: a datagram reflected to its sender fails.
    fwd, bwd = auth.session_keys(PSK, 7, NONCE_OP, NONCE_TO)
    assert auth.Opener(fwd, SESSION, FORWARD).verify(op.tx_sealer.seal(b"x"))[1] == b"x"
    assert auth.Opener(bwd, SESSION, BACKWARD).verify(to.tx_sealer.seal(b"y"))[1] == b"y"
    with pytest.raises(AuthError, match="direction"):
        op.rx_opener.verify(op.tx_sealer.seal(b"x"))
    with pytest.raises(AuthError, match="tag"):  # the backward key under forward flags
        op.rx_opener.verify(auth.Sealer(fwd, SESSION, BACKWARD).seal(b"x"))

    # Another pair of nonces (either side restarted): keys that open nothing of the first pair's.
    for n_op, n_to in [(OTHER_NONCE, NONCE_TO), (NONCE_OP, OTHER_NONCE), (NONCE_TO, NONCE_OP)]:
        op2, to2 = agreed(n_op, n_to)
        assert op2.tx_sealer and op2.rx_opener and to2.tx_sealer and to2.rx_opener
        for sealer, opener in [
            (op.tx_sealer, to2.rx_opener),
            (op2.tx_sealer, to.rx_opener),
            (to.tx_sealer, op2.rx_opener),
            (to2.tx_sealer, op.rx_opener),
        ]:
            with pytest.raises(AuthError, match="tag"):
                opener.verify(sealer.seal(b"data"))


# --------------------------------------------------------------------------------------------
# fuzz: bytes without the key change nothing and raise nothing
# --------------------------------------------------------------------------------------------
GENUINE = [hello_dg(), op_hs(encode(welcome(T0, 1, 2))), to_ss(START), op_ss(encode(Started(7)))]
unauthentic = st.one_of(
    st.binary(max_size=400),
    st.builds(_envelope, st.integers(0, 255), st.integers(0, 2**64 - 1), st.binary(max_size=300)),
    st.builds(lambda d, bit: flipped(d, bit % (8 * len(d))), st.sampled_from(GENUINE), st.integers(0, 2**16)),
    st.builds(
        lambda body, d, k: seal(body, d, k, psk=OTHER_PSK),
        st.sampled_from([pack(hello_map()), START, encode(Started(7)), encode(welcome(T0, 1, 2))]),
        st.sampled_from([FORWARD, BACKWARD]),
        st.sampled_from([HANDSHAKE, SESSION]),
    ),
)


def _to_state(to: TeleoperatorHandshake) -> tuple[object, ...]:
    opener = to.rx_opener
    window = None if opener is None else (opener.highest, opener._seen)
    return (
        *(to.done, to.error, to.params, to.peer, to.start_ns, to.welcomes, to.rejected, to.ignored),
        *(window, candidates(to)),
    )


def _op_state(op: OperatorHandshake) -> tuple[object, ...]:
    opener = op.rx_opener
    window = None if opener is None else (opener.highest, opener._seen)
    return (op.done, op.error, op.params, op.answers, op.rejected, op.peer_nonce, op.start_ns, window)


@FAST
@given(st.lists(unauthentic, min_size=1, max_size=8))
def test_fuzz_unauthenticated_datagrams_change_nothing(datagrams: list[bytes]) -> None:
    """Arbitrary bytes to both state machines, waiting or mid-handshake: no exception, no reply,
    no change to done / params / anything else but the ``unauthenticated`` count."""
    tos = [waiting(), welcomed(), welcomed()]
    one(tos[2].receive(hello(nonce=OTHER_NONCE), OP, T0), OP)  # two candidates at OP's address
    ops = [operator(), starting()[0]]
    first_hello(ops[0])
    before = [_to_state(to) for to in tos], [_op_state(op) for op in ops]
    for data in datagrams:
        for to in tos:
            assert to.receive(data, OP, T0 + MS) == []
        for op in ops:
            op.receive(data, T0 + 3 * MS)
    assert ([_to_state(to) for to in tos], [_op_state(op) for op in ops]) == before
    assert [to.unauthenticated for to in tos] == [len(datagrams)] * 3
    assert [op.unauthenticated for op in ops] == [len(datagrams)] * 2


authentic_bodies = st.one_of(
    st.binary(max_size=300),
    st.builds(
        lambda kind, m: pack({"t": kind, "v": 1, **m}),
        st.sampled_from(protocol.KINDS),
        st.dictionaries(st.sampled_from(FIELD_NAMES), values, max_size=8),
    ),
    st.builds(
        lambda base, m: pack({**base, **m}),
        st.sampled_from(VALID),
        st.dictionaries(st.sampled_from(FIELD_NAMES), values, max_size=2),
    ),
)


@FAST
@given(st.lists(st.tuples(st.booleans(), authentic_bodies), min_size=1, max_size=6))
def test_fuzz_authentic_garbage_never_raises(items: list[tuple[bool, bytes]]) -> None:
    """Anything sealed under the right keys: never an exception, and every reply verifies."""
    to = welcomed()
    op, _ = starting()
    for session_key, body in items:
        for reply, addr in to.receive(to_ss(body) if session_key else to_hs(body), OP, T0 + MS):
            assert addr == OP
            assert isinstance(from_ss(reply) if to.done else from_hs(reply), Welcome | Reject | Started)
        op.receive(op_ss(body) if session_key else op_hs(body), T0 + 3 * MS)


def test_one_recording_replayed_from_many_ports_evicts_nobody() -> None:
    """A recorded hello replayed from more ports than there are candidate slots takes one slot (a
    slot per nonce), and a recording of the genuine hello replayed from elsewhere cannot take the
    genuine operator's address away: its start still commits."""
    to = waiting()
    genuine = hello(nonce=NONCE_OP)
    assert isinstance(one(to.receive(genuine, OP, T0), OP), Welcome)
    old = hello(nonce=bytes([0xAA]) * 16)  # an earlier run's hello
    for port in range(3 * protocol.MAX_CANDIDATES):
        stranger = ("10.0.0.66", 50000 + port)
        assert len(to.receive(old, stranger, T0 + 1)) == (port == 0)  # copies: dropped as replays
        assert to.receive(genuine, stranger, T0 + 1) == []  # the genuine hello, recorded and replayed
    assert len(candidates(to)) == 2
    assert one(to.receive(start_of(7, NONCE_OP), OP, T0 + 2), OP, session_key=True) == Started(7)
    assert to.done and to.peer == OP


def test_an_unconfirmed_start_says_what_the_operator_refused_meanwhile() -> None:
    """The start's failure names what this side saw (the intermittent 'did not confirm the start'
    of a loaded host: did a started come and fail to verify, or did none come in time?)."""
    op = operator(timeout_s=1)
    h = first_hello(op)
    op.receive(op_hs(encode(welcome(h.t_ns, T0 + 5 * S + 3 * MS, T0 + 5 * S + 3 * MS))), T0 + 6 * MS)
    now = T0 + 6 * MS
    forged = auth.Sealer(bytes(32), SESSION, BACKWARD).seal(encode(Started(7)))  # another key
    while not op.finished:
        if op.poll(now) and op.starts_sent == 1:
            op.receive(forged, now)
        now = op.next_timer()
    assert op.failure == protocol.Failure.START_UNCONFIRMED
    assert op.error == (
        "did not confirm the start (13 start(s) sent; 1 datagram(s) refused unverified, the last: tag)"
    )


@pytest.mark.parametrize(
    "field,sent,canonical",
    [
        ("codec", " cq:8", "cq:8"),
        ("codec", "CQ:8", "cq:8"),
        ("codec", "cq:08", "cq:8"),
        ("codec", "cq:\u0668", "cq:8"),  # an Arabic-Indic 8
        ("playout", "1_0", "10"),
        ("playout", " 2", "2"),
        ("playout", "2ms", "2"),
        ("playout", "OFF", "off"),
        ("playout", "\u0662", "2"),
    ],
)
def test_a_hello_with_a_non_canonical_spelling_is_rejected_naming_the_field(
    field: str, sent: str, canonical: str
) -> None:
    """Issue 49: the robot took these as the canonical value; PROTOCOL.md 4.1 asks for the canonical
    spelling, and the reject names the field and that form."""
    to = waiting()
    r = one(to.receive(hello(**{field: sent}), OP, T0), OP)
    assert isinstance(r, Reject) and r.t_ns == T0, r
    want = f"bad hello: {field} must be sent in its canonical form {canonical!r}, got {sent!r}"
    assert r.why == want, r.why
    assert to.params is None
    to = waiting()  # the canonical spelling itself is welcome
    assert isinstance(one(to.receive(hello(**{field: canonical}), OP, T0), OP), Welcome)
