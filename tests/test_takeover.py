"""The teleoperator's takeover rule, fed datagrams directly (no sockets, no clock of its own).

A teleoperator whose link is lost hands hellos to a takeover handshake, so that a restarted
operator can replace a dead one.  Its *own* operator offers rejoins during the same outage (they
are meant for a restarted teleoperator): those must not be taken as a new operator, or a session
that nobody restarted is split in two.
"""

from __future__ import annotations

import time
from typing import Any

import pytest

from teleop import auth, protocol, wire
from teleop.port import port_keys
from transport.session import EndpointOptions, SessionParams, _make_port, _Runner, _Stop

OP_ADDR = ("127.0.0.1", 40001)
OTHER_ADDR = ("127.0.0.1", 40002)
NONCE_OP, NONCE_TO = bytes(range(16)), bytes(range(16, 32))


class FakeTransport:
    """What the runner calls on a transport: datagrams in through ``drain``, out into ``sent``."""

    def __init__(self) -> None:
        self.inbox: list[tuple[bytes, Any, int]] = []
        self.sent: list[tuple[bytes, Any]] = []
        self.header_bytes = 28  # IPv4 + UDP

    def send(self, data: bytes, addr: Any) -> None:
        self.sent.append((data, addr))

    def drain(self) -> list[tuple[bytes, Any, int]]:
        out, self.inbox = self.inbox, []
        return out


def _params(session: int) -> SessionParams:
    return SessionParams(
        session=session, codec="none", scenario="protocol", dof=2, b=20.0, full_scale=2.0, duration=15.0
    )


@pytest.fixture
def lost() -> tuple[_Runner, FakeTransport, bytes]:
    """A teleoperator 200 ticks into session 7, its operator silent since tick 0 (link lost)."""
    psk = auth.generate_key()
    params = _params(7)
    opts = EndpointOptions(role="teleoperator", listen=("127.0.0.1", 0), psk=psk)
    tr = FakeTransport()
    keys = port_keys(psk, wire.BACKWARD, params.session, NONCE_OP, NONCE_TO)
    port = _make_port(opts, tr, params, 0, keys, None)  # type: ignore[arg-type]
    runner = _Runner(opts, tr, OP_ADDR, params, port, time.monotonic_ns(), _Stop())  # type: ignore[arg-type]
    # One payload from the operator arms the link supervision; then silence.
    op_opts = EndpointOptions(role="operator", listen=("127.0.0.1", 0), psk=psk)
    op_keys = port_keys(psk, wire.FORWARD, params.session, NONCE_OP, NONCE_TO)
    op_port = _make_port(op_opts, FakeTransport(), params, 0, op_keys, None)  # type: ignore[arg-type]
    tr.inbox += [(d, OP_ADDR, time.monotonic_ns()) for d in op_port.tick(0, 0.0)]
    runner.drain(0)
    for k in range(200):
        port.tick(k, k * params.dt)
    assert runner.node.link_lost
    return runner, tr, psk


def _hello(psk: bytes, params: SessionParams, rejoin: bool, nonce: bytes = NONCE_OP) -> bytes:
    sealer = auth.Sealer(auth.handshake_key(psk), auth.HANDSHAKE, wire.FORWARD, 5)
    hello = protocol.Hello(params, t_ns=time.monotonic_ns(), rejoin=rejoin, nonce=nonce)
    return sealer.seal(protocol.encode(hello))


def _welcomes(tr: FakeTransport) -> list[Any]:
    return [addr for data, addr in tr.sent if auth.peek(data) and auth.peek(data)[0] == auth.HANDSHAKE]  # type: ignore[index]


def test_our_own_operators_rejoin_offer_is_not_a_takeover(lost: tuple[_Runner, FakeTransport, bytes]) -> None:
    runner, tr, psk = lost
    for _ in range(3):  # an offer every 250 ms while the outage lasts
        tr.inbox.append((_hello(psk, runner.params, rejoin=True), OP_ADDR, time.monotonic_ns()))
        runner.drain(200)
    assert runner.own_hellos_ignored == 3
    assert runner.takeover is None and runner.handover is None and not runner.replaced
    assert _welcomes(tr) == []  # nothing answered: our operator waits for the link to return


def test_a_new_operator_from_the_same_address_is_still_welcomed(
    lost: tuple[_Runner, FakeTransport, bytes],
) -> None:
    """A restarted operator bound to the same port proposes a new session id: a takeover."""
    runner, tr, psk = lost
    tr.inbox.append((_hello(psk, _params(8), rejoin=False, nonce=bytes(16)), OP_ADDR, time.monotonic_ns()))
    runner.drain(200)
    assert runner.own_hellos_ignored == 0
    assert runner.takeover is not None and _welcomes(tr) == [OP_ADDR]


@pytest.mark.parametrize("addr", [OTHER_ADDR, OP_ADDR])
def test_a_forged_or_foreign_hello_is_not_counted_as_ours(
    lost: tuple[_Runner, FakeTransport, bytes], addr: Any
) -> None:
    """Only an authentic hello of our session from our peer's address is dropped as our own; a
    forged one (wrong key) goes to the takeover handshake, which refuses it unanswered."""
    runner, tr, _ = lost
    forged = _hello(auth.generate_key(), runner.params, rejoin=True)
    tr.inbox.append((forged, addr, time.monotonic_ns()))
    runner.drain(200)
    assert runner.own_hellos_ignored == 0
    assert _welcomes(tr) == [] and runner.takeover is not None and runner.takeover.unauthenticated == 1
