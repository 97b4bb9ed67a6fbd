"""The session lifecycle in virtual time: two endpoints on a seeded virtual network (tests/vnet.py).

Deterministic and fast (a simulated second costs tens of milliseconds): restarts of either side at
0.2, 4, 50 and 200 ms round trip, outages, a genuine takeover, a relay to another robot, replayed
hellos crowding a start, lost start/started/bye, a peer asking for more than the robot affords, and
the timers at each step.  Every session checks the energy balance (eq. 5) it ends with.
"""

from __future__ import annotations

from typing import Any

import msgpack
import pytest

from teleop.session import auth, protocol
from teleop.session.endpoint import State
from teleop.session.events import (
    EndReason,
    Failed,
    LinkLost,
    LinkRestored,
    PeerRestarted,
    Replaced,
    SessionEnded,
    SessionStarted,
)
from teleop.session.protocol import Failure
from teleop.session.rejoin import REJOIN_OFFER_INTERVAL_NS
from teleop.session.settings import Envelope
from teleop.session.summary import SessionSummary

from .vnet import EVE, MS, OP, PSK, TO, TO_B, Host, VirtualNet, params

RTTS_MS = (0.2, 4.0, 50.0, 200.0)
TO_OFFSET = 5_000_000_000  # the teleoperator's clock runs 5 s ahead of the operator's


def running(*hosts: Host) -> Any:
    return lambda: all(h.ep.state == State.RUNNING for h in hosts)


def start(net: VirtualNet, duration: float = 6.0, **kw: Any) -> tuple[Host, Host]:
    to = net.teleoperator(offset_ns=TO_OFFSET)
    op = net.operator(params(duration=duration, **kw))
    net.seconds(5.0, stop=running(op, to))
    assert op.ep.state == to.ep.state == State.RUNNING, (op.events, to.events)
    return op, to


def ended(h: Host) -> dict[str, Any]:
    (ev,) = h.of(SessionEnded)[-1:]
    return SessionSummary(ev.summary).document()


def assert_passive(s: dict[str, Any]) -> None:
    """Eq. (5) per direction, as the watchdog saw it: what this side played never exceeded what the
    peer reported sending (margin >= 0), and the controller acted on every tick that would have."""
    pv = s["passivity"]
    assert pv["min_margin"] >= -1e-9, pv
    assert pv["controller_active_ticks"] == pv["violations"], pv


@pytest.mark.parametrize("rtt_ms", RTTS_MS)
def test_a_session_starts_and_completes_at_any_round_trip(rtt_ms: float) -> None:
    net = VirtualNet(rtt_ms / 2)
    op, to = start(net, duration=1.0)
    net.seconds(3.0)
    for h in (op, to):
        assert h.ep.state == State.CLOSED
        s = ended(h)
        assert s["completed"] and s["end"] == "completed" and s["peer_said_bye"]
        assert_passive(s)
    # The clocks differ by 5 s; the start is placed within half the round trip (symmetric: exact).
    (so,), (st,) = op.started(), to.started()
    assert abs(st.start_ns - (so.start_ns + TO_OFFSET)) <= rtt_ms * MS / 2
    assert abs(so.offset_ns - TO_OFFSET) <= rtt_ms * MS / 2


@pytest.mark.parametrize("rtt_ms", RTTS_MS)
def test_a_restarted_teleoperator_rejoins_at_any_round_trip(rtt_ms: float) -> None:
    """Killed mid-session and restarted at its address: the operator's rejoin offers reach the
    new process, the start is placed on its clock within rtt/2, and the session runs to its end."""
    net = VirtualNet(rtt_ms / 2)
    op, _ = start(net, duration=8.0)
    net.seconds(1.0)
    net.kill(TO)
    net.seconds(0.3)
    to2 = net.teleoperator(offset_ns=9 * TO_OFFSET)  # a new process, its clock anywhere
    t0 = net.now
    net.seconds(4.0, stop=lambda: to2.ep.state == State.RUNNING)
    assert to2.ep.state == State.RUNNING
    assert net.now - t0 <= 2_000_000_000, "a restart rejoins within 2 s"
    (rj,) = op.of(PeerRestarted)
    (st,) = to2.started()
    assert st.joined_late and st.k0 > 0
    assert abs(st.start_ns - (op.ep.start_ns + 9 * TO_OFFSET)) <= rj.rtt_ns // 2 + 1
    net.seconds(10.0)
    s_op, s_to = ended(op), ended(to2)
    assert s_op["completed"] and s_to["completed"] and s_op["rejoin"]["rejoins"] == 1
    for s in (s_op, s_to):
        assert_passive(s)
    assert s_op["received"]["packets"] > 0 and s_to["received"]["packets"] > 0


def test_a_rejoin_whose_started_is_lost_is_confirmed_by_the_next_resend() -> None:
    """The restarted teleoperator's first started is lost: the operator's next resend of the start
    (sealed anew, so not a replay) is answered, and it stops resending (PROTOCOL.md 4.3 step 6)."""
    net = VirtualNet(1.0)
    op, _ = start(net, duration=6.0)
    net.seconds(0.5)
    net.kill(TO)
    net.seconds(0.3)
    starteds: list[int] = []

    def drop_first_started(now: int, src: Any, dst: Any, data: bytes) -> list[Any]:
        hdr = auth.peek(data)
        body = data[auth.HEADER_BYTES : -auth.TAG_BYTES]
        session_control = hdr is not None and hdr[0] == auth.SESSION and protocol.is_control(body)
        if src == TO and session_control and protocol.parse(body).kind == "started":
            starteds.append(now)
            if len(starteds) == 1:
                return []
        return [(src, dst, data)]

    net.tap = drop_first_started
    to2 = net.teleoperator(offset_ns=TO_OFFSET)
    net.seconds(4.0, stop=lambda: len(starteds) >= 2)
    assert len(starteds) == 2 and starteds[1] - starteds[0] <= 25 * MS  # one resend interval later
    net.seconds(0.1)
    assert op.ep._rejoin.start is None and op.ep._rejoin.resends <= 2
    assert to2.ep.state == State.RUNNING and len(starteds) == 2


def test_the_rejoin_start_error_is_within_half_the_round_trip_when_delays_differ() -> None:
    """1 ms forward, 99 ms back: NTP's offset is off by half the difference, the stated bound."""
    net = VirtualNet((1.0, 99.0))
    op, _ = start(net, duration=8.0)
    net.seconds(0.5)
    net.kill(TO)
    net.seconds(0.2)
    to2 = net.teleoperator(offset_ns=TO_OFFSET)
    net.seconds(4.0, stop=lambda: to2.ep.state == State.RUNNING)
    (rj,) = op.of(PeerRestarted)
    (st,) = to2.started()
    err = st.start_ns - (op.ep.start_ns + TO_OFFSET)
    assert rj.rtt_ns == 100 * MS
    assert 0 < abs(err) <= rj.rtt_ns // 2  # here -49 ms: the bound is met, not beaten
    net.seconds(9.0)
    assert_passive(ended(op))
    assert_passive(ended(to2))


@pytest.mark.parametrize("rtt_ms", RTTS_MS)
def test_a_restarted_operator_replaces_the_silent_one(rtt_ms: float) -> None:
    """The operator process dies; a new one (a new session) takes the teleoperator over once the
    link is lost there.  The old session ends as replaced, the new one runs to its end."""
    net = VirtualNet(rtt_ms / 2)
    _, to = start(net, duration=8.0)
    net.seconds(1.0)
    net.kill(OP)
    net.seconds(0.3)
    op2 = net.operator(params(session=8, duration=2.0), offset_ns=3 * TO_OFFSET)
    t0 = net.now
    net.seconds(5.0, stop=running(op2))
    assert op2.ep.state == State.RUNNING and net.now - t0 <= 2_500_000_000
    (rp,) = to.of(Replaced)
    assert (rp.old_session, rp.new_session) == (7, 8)
    old = [e for e in to.of(SessionEnded) if e.reason == EndReason.REPLACED]
    assert len(old) == 1 and old[0].summary.replaced_by_new_session and not old[0].summary.completed
    net.seconds(4.0)
    assert ended(op2)["completed"] and ended(to)["completed"] and ended(to)["params"]["session"] == 8
    assert_passive(ended(to))
    assert_passive(ended(op2))


@pytest.mark.parametrize("outage_s", (0.1, 1.0, 5.0))
def test_an_outage_keeps_the_session(outage_s: float) -> None:
    """Both sides see the link go and come back: the same session goes on, nobody is replaced or
    rejoined; the teleoperator drops its own operator's rejoin offers."""
    net = VirtualNet(1.0)
    op, to = start(net, duration=outage_s + 3.0)
    net.seconds(0.5)
    net.dark.append((net.now, net.now + round(outage_s * 1e9)))
    net.seconds(outage_s + 4.0)
    for h in (op, to):
        assert h.ep.state == State.CLOSED and len(h.started()) == 1
        assert h.of(LinkLost) and h.of(LinkRestored)
        assert not h.of(PeerRestarted) and not h.of(Replaced)
        assert ended(h)["completed"]
        assert_passive(ended(h))
    assert ended(op)["rejoin"]["offers"] >= outage_s * 1e9 // REJOIN_OFFER_INTERVAL_NS
    assert ended(op)["rejoin"]["rejoins"] == 0


def test_the_teleoperator_ignores_its_own_operators_offers_on_a_one_way_outage() -> None:
    """Only the backward path fails: the operator's link is lost and it offers rejoins, which reach
    the live teleoperator.  It did not restart: each offer is dropped and counted, nothing else."""
    net = VirtualNet(1.0)
    op, to = start(net, duration=6.0)
    net.seconds(0.5)
    t_dark = net.now

    def drop_backward(now: int, src: Any, dst: Any, data: bytes) -> list[Any]:
        if src == TO and t_dark <= now < t_dark + 2_000_000_000:
            return []
        return [(src, dst, data)]

    net.tap = drop_backward
    net.seconds(6.0)
    s_op, s_to = ended(op), ended(to)
    assert s_op["rejoin"]["offers"] >= 7 and s_op["rejoin"]["rejoins"] == 0
    assert s_to["rejoin"]["own_offers_ignored"] == s_op["rejoin"]["offers"]
    assert op.of(LinkLost) and not to.of(LinkLost)
    assert not to.of(Replaced) and not op.of(PeerRestarted) and s_op["completed"] and s_to["completed"]


def test_a_relay_to_another_robot_with_the_same_key_never_runs_a_session_there() -> None:
    """Robot A dies; an attacker at A's address relays the operator's rejoin offers to robot B
    (same deployment key, another name) and B's answers back.  B's handshake key is not A's: B
    cannot verify the offers, stays silent, and the operator never rejoins anyone."""
    net = VirtualNet(1.0)
    op, _ = start(net, duration=6.0)
    b = net.teleoperator(addr=TO_B, name="robot-b")
    net.seconds(0.5)
    net.kill(TO)

    def relay(now: int, src: Any, dst: Any, data: bytes) -> list[Any]:
        if dst == TO:
            return [(EVE, TO_B, data)]
        if src == TO_B and dst == EVE:
            return [(TO, OP, data)]
        return [(src, dst, data)]

    net.tap = relay
    net.seconds(6.0)
    assert not b.started() and b.ep.state in (State.HANDSHAKE, State.FAILED)
    assert b.ep._to_hs is not None and b.ep._to_hs.unauthenticated > 0  # it saw them, could not verify
    assert not op.of(PeerRestarted) and ended(op)["rejoin"]["offers"] > 0


def test_a_fresh_handshake_relayed_to_another_robot_fails_with_no_answer() -> None:
    net = VirtualNet(1.0)
    net.teleoperator(addr=TO_B, name="robot-b")
    op = net.operator(params(), name="robot-a", connect_timeout_s=1.0)

    def relay(now: int, src: Any, dst: Any, data: bytes) -> list[Any]:
        return [(OP, TO_B, data)] if dst == TO else [((TO if src == TO_B else src), dst, data)]

    net.tap = relay
    net.seconds(2.0)
    (f,) = op.of(Failed)
    assert f.reason == Failure.NO_ANSWER and op.ep.state == State.FAILED


def test_recorded_hellos_replayed_from_elsewhere_cannot_crowd_out_a_start() -> None:
    """1100 authentic hellos recorded from 100 earlier handshakes, replayed from the attacker's own
    address: each gets a small retry and leaves no state; the genuine operator starts."""
    rec = VirtualNet(1.0, seed=1)
    recorded: list[bytes] = []

    def record(now: int, src: Any, dst: Any, data: bytes) -> list[Any]:
        recorded.append(data)
        return [(src, dst, data)]

    rec.tap = record
    for s in range(100):  # operators whose hellos reach an absent robot (with their cookies, later)
        rec.operator(params(session=100 + s), addr=("10.0.1.1", 10000 + s), peer=("10.0.9.9", 1))
    rec.seconds(1.2)
    assert len(recorded) >= 1100
    net = VirtualNet(25.0, seed=2)
    to = net.teleoperator(offset_ns=TO_OFFSET)
    for i, d in enumerate(recorded[:1100]):
        net.inject(EVE, TO, d, delay_ns=i * 50_000)  # 20k/s for 55 ms, then the genuine operator
    op = net.operator(params(duration=1.0))
    net.seconds(5.0, stop=running(op, to))
    assert op.ep.state == to.ep.state == State.RUNNING
    hs = to.ep._to_hs
    assert hs is not None and not hs._candidates  # committed to the genuine operator; none from EVE
    # EVE's source got its burst of retries; the rest was dropped before any MAC check.
    assert hs.retries_sent <= 25 and hs.welcomes < 20 and to.ep.handshake_throttled >= 1000


def test_a_hello_without_a_cookie_leaves_no_state_and_gets_a_small_retry() -> None:
    net = VirtualNet(1.0)
    to = net.teleoperator()
    hs = protocol.OperatorHandshake(params(), now_ns=0, timeout_s=1.0, psk=auth.robot_key(PSK, "robot"))
    (hello,) = hs.poll(0)
    replies: list[bytes] = []
    net.tap = lambda now, src, dst, data: (replies.append(data), [])[1]  # type: ignore[func-returns-value]
    net.inject(EVE, TO, hello)
    net.seconds(0.01)
    assert to.ep._to_hs is not None and to.ep._to_hs.retries_sent == 1 and not to.ep._to_hs._candidates
    assert len(replies) == 1 and len(replies[0]) < len(hello)


@pytest.mark.parametrize("unknown", [list(range(100)), msgpack.ExtType(1, b"ab")], ids=["long array", "ext"])
def test_an_unknown_field_the_peek_cannot_read_does_not_skip_the_cookie(unknown: object) -> None:
    """Unknown keys are ignored (4.1), so a hello may carry any msgpack value under one; its cookie
    is checked all the same (4.3 step 2): a retry, no candidate, never a welcome."""
    net = VirtualNet(1.0)
    to = net.teleoperator()
    k_hs = auth.handshake_key(auth.robot_key(PSK, "robot"))
    fields = {"t": "hello", "v": 1, "t_ns": 5, "nonce": bytes(range(16)), "x": unknown, **params().to_msg()}
    hello = auth.Sealer(k_hs, auth.HANDSHAKE, 0).seal(msgpack.packb(fields, use_bin_type=True))
    replies: list[protocol.Message] = []

    def answers(now: int, src: Any, dst: Any, data: bytes) -> list[Any]:
        replies.append(protocol.parse(auth.Opener(k_hs, auth.HANDSHAKE, 1).verify(data)[1]))
        return []

    net.tap = answers
    net.inject(OP, TO, hello)
    net.seconds(0.01)
    assert [m.kind for m in replies] == ["retry"]
    assert to.ep._to_hs is not None and not to.ep._to_hs._candidates and to.ep._to_hs.welcomes == 0


def test_lost_start_and_started_are_resent_and_a_lost_bye_still_ends_the_session() -> None:
    """The first start and the first started are lost, and every bye: the handshake resends, the
    session runs, and both sides end it by its agreed length."""
    net = VirtualNet(2.0)
    dropped: dict[str, int] = {"start": 0, "started": 0, "bye": 0}
    keys: dict[str, Any] = {}

    def lossy(now: int, src: Any, dst: Any, data: bytes) -> list[Any]:
        hdr = auth.peek(data)
        if hdr is None or hdr[0] != auth.SESSION or len(data) > 80:
            return [(src, dst, data)]
        body = data[auth.HEADER_BYTES : -auth.TAG_BYTES]
        try:
            msg = protocol.parse(body)
        except protocol.ProtocolError:
            return [(src, dst, data)]
        if msg.kind in ("start", "started") and not dropped[msg.kind]:
            dropped[msg.kind] += 1
            return []
        if msg.kind == "bye":
            dropped["bye"] += 1
            return []
        keys.setdefault(msg.kind, 0)
        return [(src, dst, data)]

    net.tap = lossy
    op, to = start(net, duration=1.0)
    net.seconds(3.0)
    assert dropped["start"] == dropped["started"] == 1 and dropped["bye"] >= 6
    for h in (op, to):
        s = ended(h)
        assert s["completed"] and not s["peer_said_bye"]
        assert_passive(s)


def test_a_peer_cannot_raise_the_robots_range_beyond_its_local_limit() -> None:
    net = VirtualNet(1.0)
    to = net.teleoperator(limits=Envelope(max_range=2.0))
    op = net.operator(params(full_scale=1e6))
    net.seconds(2.0)
    (f,) = op.of(Failed)
    assert f.reason == Failure.REJECTED and "--max-range" in f.detail
    assert not to.started()


def test_timers_at_each_step() -> None:
    """aioquic's habit: what the endpoint asks to be woken for, step by step."""
    net = VirtualNet(1.0)
    to = net.teleoperator(offset_ns=0, connect_timeout_s=10.0)
    assert to.ep.get_timer() == 10_000_000_000  # the teleoperator waits for a start until its timeout
    op = net.operator(params(duration=0.5), connect_timeout_s=3.0)
    assert op.ep.get_timer() == 100 * MS  # the hello went out at 0; the next is due after 100 ms
    net.run(2 * MS + 1)  # hello -> retry (1 ms) -> hello with the cookie at once
    assert op.ep._op_hs is not None and op.ep._op_hs.retries == 1
    net.seconds(1.0, stop=lambda: op.ep.state == State.STARTING)
    assert op.ep.state == State.STARTING and op.ep.get_timer() is None  # ticks are not timers
    net.seconds(2.0)
    assert op.ep.finished and op.ep.get_timer() is None


def test_handshake_work_per_source_is_rate_limited() -> None:
    """A source that sends hellos far faster than any operator gets its burst answered, then is
    dropped before the MAC; the running session's own peer is never limited."""
    net = VirtualNet(1.0)
    to = net.teleoperator()
    hs = protocol.OperatorHandshake(params(), now_ns=0, timeout_s=1.0, psk=auth.robot_key(PSK, "robot"))
    hellos = [
        hs.hs_sealer.seal(protocol.encode(protocol.Hello(params(), t, nonce=bytes(16))))
        for t in range(1, 501)
    ]
    for i, h in enumerate(hellos):
        net.inject(EVE, TO, h, delay_ns=i * 100_000)  # 10k/s for 50 ms
    net.seconds(0.1)
    assert to.ep._to_hs is not None and to.ep._to_hs.retries_sent <= 23  # a burst of 20, then 50/s for 50 ms
    assert to.ep.handshake_throttled >= 470


def test_a_datagram_longer_than_any_of_its_kind_is_refused_by_length_alone() -> None:
    """A 60 kB datagram with a handshake header, or with a session header in a 2-DoF session, is
    dropped before its MAC is computed (counted); the session goes on."""
    from teleop.session import wire

    net = VirtualNet(1.0)
    _, to = start(net, duration=1.0)
    hs_junk = b"T\x10" + (1).to_bytes(8, "big") + bytes(60_000)  # flags 0x10: handshake key, forward
    ss_junk = b"T\x12" + (5).to_bytes(8, "big") + bytes(wire.max_session_datagram_bytes(2))
    for i in range(50):
        net.inject(EVE, TO, hs_junk, delay_ns=i * MS)
        net.inject(OP, TO, ss_junk, delay_ns=i * MS)  # even from the peer's own address
    net.seconds(3.0)
    s = ended(to)
    assert s["oversize_refused"] == 100 and s["completed"]
    assert s["security"]["rejected"] == 0  # never reached the MAC check
    assert wire.max_session_datagram_bytes(2) < 5000 < wire.MAX_DATAGRAM_BYTES


def test_a_flood_of_garbage_is_counted_and_the_session_completes() -> None:
    net = VirtualNet(1.0, seed=3)
    op, to = start(net, duration=1.0)
    rng = net.rng
    for i in range(3000):
        net.inject(EVE, TO, rng.randbytes(rng.randrange(1, 200)), delay_ns=i * 200_000)
        net.inject(EVE, OP, b"T\x11" + rng.randbytes(40), delay_ns=i * 200_000)
    net.seconds(3.0)
    for h in (op, to):
        s = ended(h)
        assert s["completed"]
        assert_passive(s)
    assert ended(to)["received"]["foreign"] >= 3000


def test_foreign_junk_takes_the_cheap_path_with_the_full_paths_counts(monkeypatch: Any) -> None:
    """Link up: a datagram from another address that is not a handshake datagram can only be
    refused, so it never reaches Port.receive; it is counted (foreign, security.rejected, the same
    last rejection) as the full path counts it."""
    net = VirtualNet(1.0, seed=5)
    _, to = start(net, duration=1.0)
    port = to.ep.port
    assert port is not None
    real, foreign_calls = port.receive, []

    def spy(
        data: bytes, t: float, k: int, play: bool = True, from_peer: bool = True, clock: float | None = None
    ) -> Any:
        if not from_peer:
            foreign_calls.append(data)
        return real(data, t, k, play, from_peer, clock)

    monkeypatch.setattr(port, "receive", spy)
    rejected, foreign = port.security.rejected, to.ep.foreign
    session_junk = [b"T\x12" + (i + 1).to_bytes(8, "big") + bytes(60) for i in range(100)]
    for i, junk in enumerate(session_junk):
        net.inject(EVE, TO, bytes(100), delay_ns=i * 100_000)  # not an envelope
        net.inject(EVE, TO, junk, delay_ns=i * 100_000)  # a session header, no valid tag
    net.seconds(0.05)
    assert not foreign_calls and not port.node.link_lost
    assert port.security.rejected - rejected == 200 and to.ep.foreign - foreign == 200
    cheap = port.security.last_rejection
    real(session_junk[0], 0.0, 0, False, from_peer=False)  # the full path, for comparison
    assert port.security.last_rejection == cheap and port.security.rejected - rejected == 201
    net.seconds(3.0)
    assert ended(to)["completed"]


def test_every_event_is_typed_and_failures_are_enums() -> None:
    net = VirtualNet(1.0)
    op = net.operator(params(), connect_timeout_s=0.5)  # nobody there
    net.seconds(1.0)
    (f,) = op.of(Failed)
    assert isinstance(f.reason, Failure) and f.reason == Failure.NO_ANSWER
    assert not op.of(SessionStarted)


def test_a_session_of_two_endpoints_is_teleop_sim_to_the_bit() -> None:
    """One code path: two endpoints on a 0.1 ms virtual link play exactly what ``teleop sim`` plays
    with the real runner's playout floor (none) at both receivers (eq. 7's I equal to the bit).
    A receive counted against the wrong tick, or a first payload dropped before tick 0, breaks it."""
    from teleop.control import metrics
    from teleop.offline.sim import SimConfig, run_case
    from teleop.session.port import MemorySink

    net = VirtualNet(0.1)
    op, to = start(net, duration=3.0)
    net.seconds(4.0)
    assert op.ep.port is not None and to.ep.port is not None
    pa, pt = op.ep.port, to.ep.port
    assert isinstance(pa.sink, MemorySink) and isinstance(pt.sink, MemorySink) and pa.ticks == 3000
    ao, at = pa.sink.arrays(pa.ticks), pt.sink.arrays(pa.ticks)
    i_endpoints = metrics.transparency(ao["v"], at["v"], ao["f"], at["f"], 1e-3)
    sim = run_case(
        SimConfig(codec="eds:50", scenario="protocol", duration=3.0, playout="auto", playout_floor=(0, 0))
    )
    assert i_endpoints == sim.summary["I"]
