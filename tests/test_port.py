"""The sans-I/O port shared by `teleop sim` and the real-time runner."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop.offline.sim import SimConfig, run_case
from teleop.session import auth, wire
from teleop.session.node import PortOptions
from teleop.session.port import WIRE_KEYS, MemorySink, Port, make_node, make_shim

U32 = 2**32 - 1


@given(
    session=st.integers(1, U32),
    k=st.integers(0, 2**40),
    t_us=st.integers(0, 2**63),
    payload_len=st.sampled_from([0, 1, 4, 12, 255, 256, 70_000]),
)
def test_packet_size_is_the_encoded_length(session: int, k: int, t_us: int, payload_len: int) -> None:
    seq = min(k, U32)
    p = wire.Packet(session, 1, seq, k, t_us, 0, bytes(payload_len), 3.25)
    assert int(wire.packet_size(session, seq, k, t_us, payload_len)) == len(wire.encode(p))
    assert wire.encoded_size(p) == len(wire.encode(p))  # the scalar twin the rate cap uses


def _pair(codec: str = "none", ticks: int = 300, netem: str = "") -> tuple[Port, Port]:
    opts = PortOptions()
    ports = []
    for role, d in (("operator", 0), ("teleoperator", 1)):
        node = make_node(
            role,
            scenario="protocol",
            dof=2,
            dt=1e-3,
            b=20.0,
            codec=codec,
            full_scale=2.0,
            session=7,
            options=opts,
        )
        ports.append(Port(node, ticks=ticks, shim=make_shim(netem, 0, d)))
    return ports[0], ports[1]


def test_baseline_is_counted_as_if_encoded_every_tick() -> None:
    """The closed-form baseline gives the figure the old loop got by encoding a packet per tick."""
    op, to = _pair(ticks=300)
    for k in range(300):
        for d in op.tick(k, k * 1e-3):
            to.receive(d, k * 1e-3, k)
        to.tick(k, k * 1e-3)
    s = op.summary()["sent"]
    raw = bytes(op.raw_payload_len)
    energy = op.node.energy_sent
    sealer = auth.Sealer(bytes(32), auth.SESSION, 0)  # the envelope's size does not depend on the key
    packets = [wire.Packet(7, 0, k, k, k * 1000, 0, raw, energy) for k in range(300)]
    expected = [len(sealer.seal(wire.encode(p))) + 28 for p in packets]
    assert s["baseline_packets"] == 300
    assert s["baseline_wire_bytes"] == sum(expected)
    assert s["baseline_payload_bytes"] == 300 * len(raw)
    # codec none sends every tick a packet the size of the baseline's, up to seq/tick/t_us encodings
    assert s["packets"] == 300 and abs(s["compression_payload"] - 1.0) < 1e-12


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200))
def test_receive_never_raises_and_counts(data: bytes) -> None:
    _, to = _pair(ticks=10)
    msg = to.receive(data, 0.0, 3)
    # Random bytes never authenticate: refused and counted, and nothing reaches the node.
    assert msg is None and to.security.rejected == 1
    assert to.node.counters.received == 0 and to.rx.packets == 0


def test_receive_counts_bytes_at_their_tick() -> None:
    op, to = _pair(ticks=10)
    data = op.tick(0, 0.0)[0]
    to.receive(data, 0.0, 2500)  # a tick in a later chunk: counted there (no session length needed)
    assert to.rx.packets == 1
    to.receive(b"junk", 0.0, -5)
    assert to.rx.packets == 1 and to.security.rejected == 1
    to.finish()
    assert isinstance(to.sink, MemorySink)
    rx = to.sink.arrays()["rx_wire"]
    assert rx.size == 2501 and rx[2500] == len(data) + 28 and rx[:2500].sum() == 0


def test_sim_wire_block_has_the_report_keys_and_counts_agree() -> None:
    s = run_case(SimConfig(codec="eds:50", scenario="protocol", duration=2.0)).summary
    for d in ("forward", "backward"):
        w = s["wire"][d]
        assert tuple(w) == WIRE_KEYS
        assert w["packets"] == s["directions"][d]["packets"] == 40
        assert w["received_packets"] == w["packets"] and w["lost"] == 0
        assert w["payload_bytes"] == s["directions"][d]["payload_bytes"]
        assert abs(w["compression_payload"] - 50.0) < 1e-9


def test_sim_wire_block_under_loss_counts_what_left_the_shim() -> None:
    s = run_case(SimConfig(codec="none", duration=2.0, netem_forward="loss 10%", seed=1)).summary
    w, produced = s["wire"]["forward"], s["directions"]["forward"]["packets"]
    assert w["packets"] < produced  # the shim dropped some before the socket
    assert w["received_packets"] == w["packets"] and w["lost"] == 0  # nothing lost after the socket
    assert s["link"]["forward"]["loss"] > 0.05


def test_recorder_marks_the_ticks_that_ran() -> None:
    op, _ = _pair(ticks=50)
    for k in (0, 1, 2, 10):
        op.tick(k, k * 1e-3)
    op.finish()
    assert isinstance(op.sink, MemorySink)
    a = op.sink.arrays()
    assert list(np.flatnonzero(~np.isnan(a["play_time_s"]))) == [0, 1, 2, 10]
    assert np.isnan(a["v"][5]).all()
    # the uncompressed stream had every tick from the first to the last, skipped ones included
    assert op.summary()["sent"]["baseline_packets"] == 11


@settings(max_examples=20, deadline=None)
@given(st.lists(st.integers(1, 1600), min_size=1, max_size=6), st.booleans())
def test_a_deferred_seal_gives_the_same_record_and_figures(steps: list[int], settle: bool) -> None:
    """The runner's ``defer`` (a closed chunk sealed by settle() after the send, a step a call, the
    next one made there) changes when the work is done, not what: the same chunks, arrays and
    summaries as a seal in the tick, whether settle() runs after every tick or never, over gaps
    that skip chunks."""
    ks = [sum(steps[: i + 1]) for i in range(len(steps))]
    runs = []
    for defer in (False, True):
        op, to = _pair(ticks=ks[-1] + 1)
        op.rec.defer = to.rec.defer = defer
        for k in range(ks[-1] + 1):
            if k not in ks and k % 7:  # the operator runs a few ticks, with gaps (a stalled loop)
                continue
            for d in op.tick(k, k * 1e-3):
                to.receive(d, k * 1e-3, k)
            if defer and settle:
                op.settle()
            for d in to.tick(k, k * 1e-3):
                op.receive(d, k * 1e-3, k)
            if defer and settle:
                to.settle()
        runs.append([(p.summary(), p.sink) for p in (op, to)])
    for (s0, sink0), (s1, sink1) in zip(*runs, strict=True):
        assert s0 == s1
        assert isinstance(sink0, MemorySink) and isinstance(sink1, MemorySink)
        assert [c.k0 for c in sink0.chunks] == [c.k0 for c in sink1.chunks]
        a0, a1 = sink0.arrays(), sink1.arrays()
        assert a0.keys() == a1.keys()
        for name in a0:
            np.testing.assert_array_equal(a0[name], a1[name], err_msg=name)


def test_a_deferred_seal_is_spread_over_three_settles() -> None:
    """Each settle() runs one step of a closed chunk's seal (bytes and baseline, the compression
    window, the sink), so no single gap between two ticks holds all of it (issue 37: the whole seal
    and the sink's pickle in one gap started the next tick up to 1.5 ms late)."""
    op, _ = _pair(ticks=3000)
    op.rec.defer = True
    assert isinstance(op.sink, MemorySink)
    for k in range(op.rec.chunk_ticks + 1):
        op.tick(k, k * 1e-3)  # tick chunk_ticks closes the first chunk
    assert op.sink.chunks == [] and op.tx.baseline_packets == 0
    op.settle()
    assert op.sink.chunks == [] and op.tx.baseline_packets == op.rec.chunk_ticks  # step 1: baseline
    op.settle()
    assert op.sink.chunks == [] and op.tx._seen_ticks == op.rec.chunk_ticks  # step 2: the window
    op.settle()
    assert [c.k0 for c in op.sink.chunks] == [0]  # step 3: the sink


def test_forged_tampered_and_replayed_datagrams_change_nothing() -> None:
    """Issue 11: nothing unauthenticated reaches the node, the link figures or the energy budget."""
    op, to = _pair(ticks=50)
    good = op.tick(0, 0.0)[0]
    to.receive(good, 0.0, 0)
    state = (to.node.counters.accepted, to.node.peer_energy_sent, to.observer.summary()["received"])
    # a forgery under another key, claiming far more energy with a far-future seq
    forged_pkt = wire.Packet(7, 0, 10**6, 10**6, 0, 0, bytes(4), 1e300)
    forged = auth.Sealer(bytes(range(32)), auth.SESSION, 0).seal(wire.encode(forged_pkt))
    tampered = bytearray(good)
    tampered[15] ^= 1
    for data in (forged, bytes(tampered), good[:-1], b"X" + good[1:]):
        assert to.receive(data, 0.001, 1) is None
    assert to.security.rejected == 4
    to.receive(good, 0.001, 1)  # the genuine datagram again: a replay
    assert to.security.replayed == 1
    after = (to.node.counters.accepted, to.node.peer_energy_sent, to.observer.summary()["received"])
    assert after[:2] == state[:2]
    assert after[2] == state[2] + 1  # the replay was authentic: the link saw a duplicate, nothing more


def test_copies_of_an_authentic_hello_are_dropped_before_they_are_parsed() -> None:
    """A flood of one recorded hello costs a tag check per copy: only the first is handled."""
    from teleop.session import protocol

    op, to = _pair(ticks=10)
    params = protocol.SessionParams(
        session=99, codec="none", scenario="protocol", dof=2, b=20.0, full_scale=2.0, duration=1.0
    )
    hello = op.seal(protocol.Hello(params, t_ns=5, nonce=bytes(16)))
    assert isinstance(to.receive(hello, 0.0, 0, from_peer=False), protocol.Hello)
    for _ in range(1000):
        assert to.receive(hello, 0.0, 0, from_peer=False) is None
    assert to.security.replayed == 1000 and to.security.rejected == 0


def test_a_late_payloads_leftover_is_not_the_payload_due() -> None:
    """Issue 37: a payload taken late (or what is left of it) is not tick k's payload, so a
    loop that runs a tick early only when its payload is here waits for it (grace) instead of
    running the tick before it and slipping a tick for good."""
    op, to = _pair("none")
    held: list[bytes] = []
    for k in range(8):
        t = k * 1e-3
        out = op.tick(k, t)
        if k == 5:
            held = out  # tick 5's packet comes after the teleoperator ran tick 5
        else:
            for data in held + out:
                to.receive(data, t, k)
            held = []
        if k == 6:
            assert to.payload_ready(6)  # its own payload came
        if k == 5:
            assert not to.payload_ready(5)
        to.tick(k, t + 0.5e-3)
        if k == 5:
            for data in held:
                to.receive(data, t + 0.9e-3, 6)  # late: released at tick 6 at once (then its leftover)
            held = []
            assert to.playout.pending(6)
            assert not to.payload_ready(6)  # tick 6's payload is packet 6, not late packet 5
