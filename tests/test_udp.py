"""The UDP transport on loopback: wake on I/O, receive timestamps, the drain budget, the receive
buffer, address parsing."""

from __future__ import annotations

import socket
import time
from typing import Any

import pytest

from tests.waiting import await_for, udp_queued
from transport.udp import (
    MAX_RCVBUF_BYTES,
    MIN_RCVBUF_BYTES,
    UdpTransport,
    kernel_drops,
    new_event_loop,
    parse_addr,
    set_rcvbuf,
)


async def test_exchange_and_wait() -> None:
    a = await UdpTransport.bind(("127.0.0.1", 0))
    b = await UdpTransport.bind(("127.0.0.1", 0))
    try:
        assert not await b.wait(0.01)  # nothing sent: times out
        t0 = time.monotonic_ns()
        for i in range(5):
            a.send(bytes([i]), b.local_address)
        assert await b.wait(1.0)
        got: list[tuple[bytes, Any, int]] = []

        def all_five() -> bool:
            got.extend(b.drain())
            return len(got) >= 5

        await await_for(all_five, 5.0, "the five datagrams")
        assert [d for d, _, _ in got] == [bytes([i]) for i in range(5)]
        assert all(addr == a.local_address for _, addr, _ in got)
        assert all(t0 <= t <= time.monotonic_ns() for _, _, t in got)
        assert b.drain() == []
    finally:
        a.close()
        b.close()


async def test_drain_budget_leaves_the_rest_in_the_kernel() -> None:
    """A drain reads at most ``budget`` datagrams; the rest waits for the next drain, oldest first."""
    a = await UdpTransport.bind(("127.0.0.1", 0))
    b = await UdpTransport.bind(("127.0.0.1", 0), budget=10)
    try:
        a.send(b"..", b.local_address)  # one datagram of the same size: what the kernel counts for it
        assert await b.wait(5.0)
        one = udp_queued(b.local_address[1])
        assert one > 0 and len(b.drain()) == 1
        for i in range(25):
            a.send(i.to_bytes(2, "big"), b.local_address)
        await await_for(lambda: udp_queued(b.local_address[1]) >= 25 * one, 5.0, "the 25 datagrams queued")
        got = [b.drain() for _ in range(4)]
        assert [len(g) for g in got] == [10, 10, 5, 0]
        assert [d for g in got for d, _, _ in g] == [i.to_bytes(2, "big") for i in range(25)]
        assert b.drain_budget_hits == 2 and b.inbox_overflow == 0
        assert b.report()["kernel_drops"] == 0
    finally:
        a.close()
        b.close()


async def test_receive_buffer_is_set_and_reported() -> None:
    """The asked buffer is obtained (root: SO_RCVBUFFORCE) or a warning says what was; ROLE.json's
    ``received`` gets both figures."""
    want = 2 << 20
    b = await UdpTransport.bind(("127.0.0.1", 0), rcvbuf=want)
    try:
        got = b._sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) if b._sock else 0
        assert got == b.rcvbuf_bytes
        assert got >= want or (b.warnings and f"{got} bytes, asked {want}" in b.warnings[0])
        r = b.report()
        assert r["rcvbuf_asked"] == want and r["rcvbuf_bytes"] == got
    finally:
        b.close()


def test_receive_buffer_is_bounded_and_never_shrunk() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        with pytest.raises(ValueError, match="receive buffer must be"):
            set_rcvbuf(s, MAX_RCVBUF_BYTES + 1)
        big = s.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        assert set_rcvbuf(s, MIN_RCVBUF_BYTES) == (big, None)  # already larger: kept


def test_kernel_drops_are_read_from_the_socket() -> None:
    """A full receive buffer: the kernel's drops on this socket are what SO_MEMINFO reports."""
    with (
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as rx,
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx,
    ):
        rx.bind(("127.0.0.1", 0))
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a few datagrams fit
        for _ in range(200):
            tx.sendto(bytes(1000), rx.getsockname())
        drops = kernel_drops(rx)
        assert drops is not None and 100 < drops < 200


def test_uvloop_is_the_default() -> None:
    loop, name = new_event_loop()
    try:
        assert name == "uvloop"
    finally:
        loop.close()


@pytest.mark.parametrize(
    "text,msg",
    [
        ("localhost", "must be HOST:PORT"),
        (":80", "must be HOST:PORT"),
        ("h:x", "port must be an integer"),
        ("h:70000", "port must be an integer"),
    ],
)
def test_parse_addr_errors(text: str, msg: str) -> None:
    with pytest.raises(ValueError, match=msg):
        parse_addr(text, "--peer")


def test_parse_addr() -> None:
    assert parse_addr("127.0.0.1:7000", "x") == ("127.0.0.1", 7000)
    assert parse_addr("[::1]:7000", "x") == ("::1", 7000)


class _CappedSocket:
    """A socket as an unprivileged process sees it: SO_RCVBUFFORCE refused, SO_RCVBUF capped by
    net.core.rmem_max (here 1 MiB), the kernel reporting twice what it set."""

    def __init__(self) -> None:
        self.rcvbuf = 212992

    def getsockopt(self, level: int, opt: int) -> int:
        return self.rcvbuf

    def setsockopt(self, level: int, opt: int, value: int) -> None:
        if opt != socket.SO_RCVBUF:
            raise PermissionError(1, "Operation not permitted")
        self.rcvbuf = 2 * min(value, 1 << 20)


def test_a_capped_receive_buffer_is_reported_as_obtained() -> None:
    got, warning = set_rcvbuf(_CappedSocket(), 16 << 20)  # type: ignore[arg-type]
    assert got == 2 << 20
    assert warning is not None and f"{2 << 20} bytes, asked {16 << 20}" in warning
    assert set_rcvbuf(_CappedSocket(), 1 << 20) == (2 << 20, None)  # type: ignore[arg-type]
