"""Hostile datagrams (``bench.fuzz``): in memory against the sans-I/O port and handshake, and a short
attack on two real processes on loopback.

The in-memory tests feed the same forgeries the benchmark sends into :class:`teleop.session.port.Port` and
the handshake state machines, where every datagram's fate can be accounted for exactly; they also
show that the forgeries are well made: sealed with the insecure key they do verify when the ports
run with it, and then only the watchdog stands between them and the energy budget.  The
integration test runs about 10^4 datagrams against a live session (blind, and on-path when this
process may sniff ``lo`` and spoof a source address) and checks the verdict of ``bench.fuzz``.
"""

from __future__ import annotations

import math
import random
import secrets
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest

from bench import fuzz
from teleop.session import auth, protocol, wire
from teleop.session.node import PortOptions
from teleop.session.port import Port, make_node, port_keys

SESSION = 4242
TICKS = 2000
OP_ADDR = ("127.0.0.1", 40001)
STRANGER = ("127.0.0.1", 40666)


def _params(session: int = SESSION, duration: float = TICKS / 1000) -> protocol.SessionParams:
    return protocol.SessionParams(
        session=session,
        codec="eds:50",
        scenario="protocol",
        dof=2,
        b=20.0,
        full_scale=2.0,
        duration=duration,
    )


@dataclass
class Pair:
    """An operator's and a teleoperator's port after a handshake (keys from both nonces)."""

    op: Port
    to: Port
    nonce_op: bytes
    nonce_to: bytes


def _pair(psk: bytes, session: int = SESSION, playout: str = "off") -> Pair:
    n_op, n_to = secrets.token_bytes(auth.NONCE_BYTES), secrets.token_bytes(auth.NONCE_BYTES)
    ports = []
    for role, d in (("operator", wire.FORWARD), ("teleoperator", wire.BACKWARD)):
        node = make_node(
            role,
            scenario="protocol",
            dof=2,
            dt=0.001,
            b=20.0,
            codec="eds:50",
            full_scale=16.0,
            session=session,
            # off: what arrives is handed to the node at once, so a forgery's fate is the node's
            options=PortOptions(playout=playout),
        )
        ports.append(Port(node, ticks=TICKS, keys=port_keys(psk, d, session, n_op, n_to)))
    return Pair(ports[0], ports[1], n_op, n_to)


def _handshake_datagrams(pair: Pair, session: int = SESSION) -> list[tuple[int, bytes]]:
    """What an on-path sniffer sees of the handshake: a hello and a welcome (nonces in clear)."""
    hello = protocol.Hello(_params(session), t_ns=1, nonce=pair.nonce_op)
    welcome = protocol.Welcome(session, t_ns=1, t2=2, t3=3, nonce=pair.nonce_to)
    return [(wire.FORWARD, pair.op.seal(hello)), (wire.BACKWARD, pair.to.seal(welcome))]


def _recording(psk: bytes) -> list[tuple[int, bytes]]:
    """Datagrams of an earlier session under the same pre-shared key (what old_session_replay sends)."""
    pair = _pair(psk, session=SESSION + 1)
    rec = _handshake_datagrams(pair, SESSION + 1)
    for k in range(200):
        rec += [(wire.FORWARD, d) for d in pair.op.tick(k, k * 1e-3)]
        rec += [(wire.BACKWARD, d) for d in pair.to.tick(k, k * 1e-3)]
    return rec


@dataclass
class Fates:
    """What became of the hostile datagrams one port received."""

    sent: int = 0
    answered: int = 0  # authentic control messages returned to the session logic (replays)
    reached_node: int = 0  # data packets handed to the node (past the tag and the replay window)


def _attack_in_memory(
    psk: bytes, per_tick: int = 3, seed: int = 7, playout: str = "off"
) -> tuple[Pair, dict[str, Fates], int]:
    """A session of TICKS ticks in memory; each tick, ``per_tick`` hostile datagrams of every class
    the forge can make now reach each port, half as if spoofed (from the peer), half blind."""
    pair = _pair(psk, playout=playout)
    cap = fuzz.Capture()
    for d, data in _handshake_datagrams(pair):
        cap.add(d, data)
    rng = random.Random(seed)
    forge = fuzz.Forge(rng, cap, _recording(psk))
    fates = {"operator": Fates(), "teleoperator": Fates()}
    genuine = 0
    for k in range(TICKS):
        t = k * 1e-3
        for src, dst, d in ((pair.op, pair.to, wire.FORWARD), (pair.to, pair.op, wire.BACKWARD)):
            for data in src.tick(k, t):
                cap.add(d, data)
                dst.receive(data, t, k)
                genuine += 1
        for role, port, d in (("teleoperator", pair.to, wire.FORWARD), ("operator", pair.op, wire.BACKWARD)):
            usable = [c for c in fuzz.CLASSES if forge.available(c, d)]
            for _ in range(per_tick):
                data = forge.make(rng.choice(usable), d)
                fates[role].sent += 1
                before = port.node.counters.received
                if port.receive(data, t, k, from_peer=rng.random() < 0.5) is not None:
                    fates[role].answered += 1
                fates[role].reached_node += port.node.counters.received - before
    return pair, fates, genuine


def _refused(port: Port) -> int:
    s = port.security
    return s.rejected + s.replayed + s.counter_jumps


# --- in memory ------------------------------------------------------------------------------------


def test_forge_makes_every_class() -> None:
    psk = auth.generate_key()
    pair = _pair(psk)
    cap = fuzz.Capture()
    for d, data in _handshake_datagrams(pair):
        cap.add(d, data)
    for k in range(60):
        for d, port in ((wire.FORWARD, pair.op), (wire.BACKWARD, pair.to)):
            for data in port.tick(k, k * 1e-3):
                cap.add(d, data)
    assert cap.key_context == (SESSION, pair.nonce_op, pair.nonce_to)  # learnt from the handshake
    assert cap.learned[wire.FORWARD].session == SESSION
    forge = fuzz.Forge(random.Random(1), cap, _recording(psk))
    for cls in fuzz.CLASSES:
        for d in (wire.FORWARD, wire.BACKWARD):
            assert forge.available(cls, d), cls
            data = forge.make(cls, d)
            assert isinstance(data, bytes)
            assert len(data) <= fuzz.MAX_OVERSIZED
            if cls == "oversized":
                assert len(data) > fuzz.MAX_DATAGRAM
    # A blind attacker has no captures: only the classes that need none.
    blind = fuzz.Forge(random.Random(1))
    assert {c for c in fuzz.CLASSES if blind.available(c, 0)} == set(fuzz.CLASSES) - fuzz.CAPTURE_CLASSES - {
        "old_session_replay"
    }


def test_hostile_control_messages_are_all_refused_by_the_parser() -> None:
    """Every body is invalid (the generator keeps only those), and the set covers what it should."""
    bodies = fuzz.hostile_control_bodies(random.Random(3))
    assert len(bodies) >= 400
    for body in bodies:
        with pytest.raises(protocol.ProtocolError):
            protocol.parse(body)
    assert sum(b"/etc/shadow" in b for b in bodies) >= 4
    assert any(b"\xcb\x7f\xf8" in b for b in bodies)  # a NaN (msgpack float64 0x7ff8...)


def test_a_key_holder_sending_hostile_handshakes_is_refused() -> None:
    """Sealed with the real handshake key (a rogue key holder), every hostile hello reaches the
    parser and is answered with a reject or ignored; the teleoperator keeps waiting."""
    psk = auth.generate_key()
    hs = protocol.TeleoperatorHandshake({}, now_ns=0, timeout_s=10, psk=psk, nonce=bytes(16))
    sealer = auth.Sealer(auth.handshake_key(psk), auth.HANDSHAKE, wire.FORWARD)
    bodies = fuzz.hostile_control_bodies(random.Random(4))
    for i, body in enumerate(bodies):
        hs.receive(sealer.seal(body), STRANGER, i)
    assert not hs.finished
    assert hs.rejected + hs.ignored == len(bodies)
    assert hs.unauthenticated == 0  # they all verified: the parser refused them
    assert hs.welcomes == 0


def test_every_forgery_is_refused_before_the_node() -> None:
    psk = auth.generate_key()
    pair, fates, genuine = _attack_in_memory(psk)
    for role, port, peer in (("teleoperator", pair.to, pair.op), ("operator", pair.op, pair.to)):
        f = fates[role]
        # Exactly accounted for: refused by the port, or an authentic handshake replay handed to
        # the session logic (which ignores a hello or welcome of its own or another session).
        assert _refused(port) + f.answered == f.sent, role
        assert f.reached_node == 0, role
        assert port.security.rejected > 0 and port.security.replayed > 0, role
        node = port.node
        assert node.counters.accepted == node.counters.received == peer.node.seq, role  # genuine only
        assert node.counters.malformed == node.counters.stale == 0, role
        s = port.summary()
        assert s["security"]["energy_reports_clamped"] == 0, role
        assert node.energy_played <= peer.node.energy_sent, role
        assert s["passivity"]["min_margin"] >= -1e-9, role
        assert port.control_rejected == 0, role  # nothing hostile reached the parser
    assert genuine == pair.op.node.seq + pair.to.node.seq


@pytest.mark.parametrize("playout", ["off", "auto"])
def test_with_the_insecure_key_forgeries_verify_and_the_watchdog_bounds_them(playout: str) -> None:
    """The forgeries are well made: under --insecure (a key everyone knows) the re-CRC'd ones are
    accepted, and the watchdog's physical bound clamps their 1e300 J energy reports.  With the
    playout buffer (the default, auto) a forgery stamped far from the genuine ones may never be
    released to the node; the bound holds either way."""
    pair, fates, _ = _attack_in_memory(auth.INSECURE_KEY, playout=playout)
    clamped = 0
    for role, port in (("teleoperator", pair.to), ("operator", pair.op)):
        node = port.node
        # Forgeries got through to the node (a far-future seq then makes the genuine ones stale).
        assert playout != "off" or fates[role].reached_node > 0, role
        assert port.control_rejected > 0, role  # hostile control messages reached the parser
        clamped += node.passivity.energy_reports_clamped
        assert node.guard.reported_in < 1e6, role  # not 1e300: bounded by physics
        assert node.passivity.min_margin >= -1e-9, role  # never plays beyond the (clamped) budget
    assert clamped > 0


def test_the_handshake_completes_under_hostile_datagrams() -> None:
    """Both handshake state machines, fed hostile datagrams between every genuine one."""
    psk = auth.generate_key()
    params = _params()
    op = protocol.OperatorHandshake(params, now_ns=0, timeout_s=5, psk=psk, nonce=secrets.token_bytes(16))
    to = protocol.TeleoperatorHandshake({}, now_ns=0, timeout_s=5, psk=psk, nonce=secrets.token_bytes(16))
    cap = fuzz.Capture()
    rng = random.Random(5)
    forge = fuzz.Forge(rng, cap, _recording(psk))
    now = 0
    while not (op.finished and to.finished) and now < 5_000_000_000:
        for data in op.poll(now):
            cap.add(wire.FORWARD, data)
            for reply, addr in to.receive(data, OP_ADDR, now):
                assert addr == OP_ADDR
                cap.add(wire.BACKWARD, reply)
                op.receive(reply, now)
        for _ in range(20):
            cls = rng.choice([c for c in fuzz.CLASSES if forge.available(c, wire.FORWARD)])
            for reply, addr in to.receive(
                forge.make(cls, wire.FORWARD), rng.choice((OP_ADDR, STRANGER)), now
            ):
                if addr == OP_ADDR:
                    op.receive(reply, now)
            cls = rng.choice([c for c in fuzz.CLASSES if forge.available(c, wire.BACKWARD)])
            op.receive(forge.make(cls, wire.BACKWARD), now)
        now += 250_000
    assert op.done and to.done, (op.error, to.error)
    assert to.params == params and to.peer == OP_ADDR
    assert op.unauthenticated > 0 and to.unauthenticated > 0


# --- two real processes ---------------------------------------------------------------------------

N_DATAGRAMS = 10_000
RATE = 4000.0


@pytest.fixture(scope="module")
def attacked(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """One short session attacked with N_DATAGRAMS (blind, and on-path where permitted)."""
    probe = fuzz.probe_on_path()
    spoofer = fuzz.Spoofer() if probe["spoof"] else None
    work = tmp_path_factory.mktemp("fuzz")
    try:
        with fuzz.key_dir() as keys:
            psk = auth.read_key_file(keys / "fuzz.key")
            run, _ = fuzz.run_session(
                work,
                "attack",
                keys / "fuzz.key",
                math.ceil(N_DATAGRAMS / RATE) + fuzz.SETTLE_S,
                sniff=probe["sniff"],
                spoofer=spoofer,
                datagrams=N_DATAGRAMS,
                rate=RATE,
                recorded=_recording(psk),
            )
    finally:
        if spoofer is not None:
            spoofer.close()
    figs = fuzz.figures(run)
    yield {"probe": probe, "figures": figs, "verdict": fuzz.verdict(figs), "run": run}


@pytest.mark.integration
def test_both_processes_survive_and_refuse_the_attack(attacked: dict[str, Any]) -> None:
    figs, v = attacked["figures"], attacked["verdict"]
    run = attacked["run"]
    assert run.exit_codes == {"teleoperator": 0, "operator": 0}, run.stderr
    for role, err in run.stderr.items():
        assert "Traceback" not in err, (role, err)
    att = figs["attack"]
    assert att["total"] >= 0.9 * N_DATAGRAMS, att  # the attack ran (bounded by the session's time)
    rep = figs["report"]
    assert rep["completed"] == {"operator": True, "teleoperator": True}
    sec = rep["security"]
    for d, role in (("forward", "teleoperator"), ("backward", "operator")):
        assert att["by_target"][role]["total"] > 0
        assert sec["rejected"][d] > 0, d
        e = rep["energy"][d]
        assert e["min_margin"] >= -1e-9, d
        assert e["played"] <= e["sent"], d
        # Every forgery is refused before the watchdog: nothing for it to clamp.
        assert sec["energy_reports_clamped"][d] == 0, d
        assert sec["counter_jumps"][d] == 0, d  # only an authentic datagram can jump
    assert v["ok"], v["failures"]


@pytest.mark.integration
def test_on_path_forgeries_are_refused(attacked: dict[str, Any]) -> None:
    probe = attacked["probe"]
    if not (probe["sniff"] and probe["spoof"]):
        pytest.skip(f"on-path attack not permitted here: {probe['notes']}")
    figs = attacked["figures"]
    att, sec = figs["attack"], figs["report"]["security"]
    assert att["by_route"]["spoofed"] > 0
    for cls in fuzz.CAPTURE_CLASSES:
        assert att["by_class"][cls] > 0, cls
    # Exact replays from the genuine peer's address verify, and the replay window refuses them.
    assert sec["replayed"]["forward"] > 0 and sec["replayed"]["backward"] > 0
