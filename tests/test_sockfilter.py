"""The kernel socket filter (transport.sockfilter) on real loopback sockets, and the endpoint's
admission it is compiled from: what passes is what the endpoint could take, what it refuses is
counted in the socket's kernel drops (issue 21)."""

from __future__ import annotations

import socket
from collections.abc import Iterator
from typing import Any

import pytest

from teleop.session import auth, wire
from teleop.session.admission import FLOOD_SAMPLE, Admission, Strangers
from teleop.session.endpoint import State
from tests.waiting import wait_for
from transport.sockfilter import compile_filter
from transport.udp import UdpTransport, kernel_drops

from .vnet import EVE, MS, TO, VirtualNet, params

HS = b"T\x10" + b"\x00" * 7 + b"\x01"  # a handshake envelope's header (kind 0, direction 0)
HS_BACK = b"T\x11" + b"\x00" * 7 + b"\x01"  # direction 1
SESSION = b"T\x12" + b"\x00" * 7 + b"\x01"  # session key
MARKER = b"m"  # the peer's last datagram of an exchange (see _exchange)


def _udp() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    return s


Socks = tuple[UdpTransport, socket.socket, socket.socket]


@pytest.fixture
def socks() -> Iterator[Socks]:
    """A bound transport, its peer's socket and a stranger's."""
    tr = UdpTransport()
    sock = _udp()
    sock.setblocking(False)
    tr._sock = sock
    peer, eve = _udp(), _udp()
    yield tr, peer, eve
    tr.close()
    peer.close()
    eve.close()


def sock_of(tr: UdpTransport) -> socket.socket:
    assert tr._sock is not None
    return tr._sock


def _exchange(tr: UdpTransport, sends: list[tuple[socket.socket, bytes]]) -> list[tuple[bytes, bool]]:
    """Send each, then drain: (data, from the peer?) of what got through.  A marker from the peer
    (which every admission here takes) follows them: once it is read, each of them has been
    filtered, taken or dropped (loopback keeps one sender's datagrams in order)."""
    me = tr.local_address
    for s, d in sends:
        s.sendto(d, me)
    sends[0][0].sendto(MARKER, me)
    got: list[tuple[bytes, Any, int]] = []

    def marked() -> bool:
        got.extend(tr.drain())
        return any(d == MARKER for d, _, _ in got)

    wait_for(marked, 5.0, "the marker")
    return [(d, a == sends[0][0].getsockname()) for d, a, _ in got if d != MARKER]


def test_a_teleoperator_in_session_takes_its_peer_and_strangers_handshakes(socks: Socks) -> None:
    tr, peer, eve = socks
    tr.admit(Admission(100, peer.getsockname(), Strangers.HANDSHAKE, 60, 1))
    got = _exchange(
        tr,
        [
            (peer, b"x" * 100),  # the peer: anything up to the bound
            (peer, b"y" * 101),  # one byte over: refused
            (eve, b"junk"),  # a stranger's non-envelope
            (eve, SESSION + bytes(20)),  # a stranger's session-key datagram
            (eve, HS + bytes(20)),  # a stranger's handshake: passes (busy or a retry)
            (eve, HS_BACK + bytes(20)),
            (eve, HS + bytes(50)),  # 60 bytes: the handshake bound
            (eve, HS + bytes(51)),  # 61: refused
        ],
    )
    assert got == [
        (b"x" * 100, True),
        (HS + bytes(20), False),
        (HS_BACK + bytes(20), False),
        (HS + bytes(50), False),
    ]
    assert kernel_drops(sock_of(tr)) == 4
    assert tr.report()["filter"] == {"updates": 1, "error": None, "strangers": "handshake", "sample": 1}


def test_an_operator_in_session_takes_its_teleoperator_alone(socks: Socks) -> None:
    tr, peer, eve = socks
    tr.admit(Admission(100, peer.getsockname(), Strangers.NONE, 60, 1))
    got = _exchange(tr, [(peer, HS + bytes(5)), (eve, HS + bytes(5)), (eve, b"z")])
    assert got == [(HS + bytes(5), True)]
    assert kernel_drops(sock_of(tr)) == 2


def test_without_a_peer_only_the_length_is_bounded(socks: Socks) -> None:
    tr, peer, eve = socks
    tr.admit(Admission(100, None, Strangers.ALL, 60, 1))
    got = _exchange(tr, [(peer, b"a" * 100), (eve, b"b" * 100), (eve, b"c" * 101)])
    assert [d for d, _ in got] == [b"a" * 100, b"b" * 100]


def test_under_a_flood_strangers_handshakes_are_sampled(socks: Socks) -> None:
    """1 in FLOOD_SAMPLE kept at random (SKF_AD_RANDOM); the peer's all."""
    tr, peer, eve = socks
    tr.admit(Admission(200, peer.getsockname(), Strangers.HANDSHAKE, 60, FLOOD_SAMPLE))
    me = tr.local_address
    n = 50 * FLOOD_SAMPLE
    for _ in range(n):
        eve.sendto(HS + bytes(10), me)
    for _ in range(100):
        peer.sendto(b"p", me)
    got: list[tuple[bytes, Any, int]] = []

    def peers_all_in() -> bool:  # the peer's last came after every stranger's (one host, in order)
        got.extend(tr.drain())
        return sum(1 for _, a, _ in got if a == peer.getsockname()) >= 100

    wait_for(peers_all_in, 5.0, "the peer's 100 datagrams")
    strangers = sum(1 for _, a, _ in got if a == eve.getsockname())
    assert sum(1 for _, a, _ in got if a == peer.getsockname()) == 100
    assert 10 <= strangers <= 120  # expected 50; a binomial this far out has odds below 1e-9
    assert kernel_drops(sock_of(tr)) == n - strangers


def test_the_filter_is_installed_once_per_change(socks: Socks) -> None:
    tr, peer, _ = socks
    a = Admission(100, peer.getsockname(), Strangers.HANDSHAKE, 60, 1)
    tr.admit(a)
    tr.admit(Admission(*a))
    assert tr.filter_updates == 1
    tr.admit(a._replace(sample=FLOOD_SAMPLE))
    assert tr.filter_updates == 2


def test_a_peer_that_is_not_an_ipv4_literal_bounds_the_length_alone() -> None:
    a = Admission(100, ("robot.local", 7000), Strangers.NONE, 60, 1)
    assert compile_filter(a) == compile_filter(a._replace(peer=None, strangers=Strangers.ALL))
    assert compile_filter(a, socket.AF_INET6) == compile_filter(a._replace(peer=None))
    with pytest.raises(ValueError, match="power of two"):
        compile_filter(Admission(100, ("127.0.0.1", 1), Strangers.HANDSHAKE, 60, 3))


def test_the_endpoints_admission_follows_the_session() -> None:
    """Teleoperator: anyone in the handshake; its operator and strangers' handshakes in session,
    sampled while its limiter drops them and for a second after; everyone once a takeover is
    possible (its operator silent).  Operator: its teleoperator alone, throughout."""
    net = VirtualNet(1.0)
    to = net.teleoperator()
    op = net.operator(params(duration=8.0))
    a = to.ep.admission(to.clock(net.now))
    assert (a.peer, a.strangers) == (None, Strangers.ALL)
    assert op.ep.admission(0) == Admission(
        op.ep.max_datagram_bytes, TO, Strangers.NONE, a.max_handshake_bytes, 1
    )
    net.seconds(1.0)
    assert to.ep.state == State.RUNNING
    now = to.clock(net.now)
    a = to.ep.admission(now)
    assert (a.peer, a.strangers, a.sample) == (op.addr, Strangers.HANDSHAKE, 1)
    assert (
        a.max_bytes == to.ep.max_datagram_bytes and a.max_handshake_bytes == wire.MAX_HANDSHAKE_DATAGRAM_BYTES
    )
    hello = HS + bytes(100)
    for i in range(100):  # beyond the per-source burst: the limiter drops
        to.ep.receive_datagram(hello, EVE, now + i * MS // 100)
    assert to.ep.handshake_throttled > 0
    assert to.ep.admission(now + MS).sample == FLOOD_SAMPLE
    assert to.ep.admission(now + 2_000 * MS).sample == 1  # a quiet second later
    net.dark.append((net.now, net.now + 1_000 * MS))  # the operator falls silent
    net.seconds(0.5)
    a = to.ep.admission(to.clock(net.now))
    assert (a.peer, a.strangers) == (None, Strangers.ALL)
    assert op.ep.admission(0).strangers == Strangers.NONE and auth.HANDSHAKE == 0


def test_a_filter_the_kernel_refuses_is_reported_once_and_the_loop_refuses_instead(
    socks: Socks, monkeypatch: pytest.MonkeyPatch
) -> None:
    tr, peer, eve = socks

    def refuse(sock: socket.socket, prog: object) -> None:
        raise OSError(22, "Invalid argument")

    monkeypatch.setattr("transport.sockfilter.attach", refuse)
    tr.admit(Admission(100, peer.getsockname(), Strangers.NONE, 60, 1))
    tr.admit(Admission(100, peer.getsockname(), Strangers.HANDSHAKE, 60, 1))
    assert tr.filter_updates == 0 and len(tr.warnings) == 1 and "no kernel socket filter" in tr.warnings[0]
    assert tr.report()["filter"]["error"] == "OSError: [Errno 22] Invalid argument"
    got = _exchange(tr, [(peer, b"p"), (eve, b"junk")])  # nothing refused in the kernel: both read
    assert len(got) == 2 and kernel_drops(sock_of(tr)) == 0
