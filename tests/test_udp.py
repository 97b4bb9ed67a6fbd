"""The UDP transport on loopback: wake on I/O, receive timestamps, bounded inbox, address parsing."""

from __future__ import annotations

import asyncio
import time

import pytest

from transport.udp import UdpTransport, new_event_loop, parse_addr


async def test_exchange_and_wait() -> None:
    a = await UdpTransport.bind(("127.0.0.1", 0))
    b = await UdpTransport.bind(("127.0.0.1", 0))
    try:
        assert not await b.wait(0.01)  # nothing sent: times out
        t0 = time.monotonic_ns()
        for i in range(5):
            a.send(bytes([i]), b.local_address)
        assert await b.wait(1.0)
        await asyncio.sleep(0.01)
        got = b.drain()
        assert [d for d, _, _ in got] == [bytes([i]) for i in range(5)]
        assert all(addr == a.local_address for _, addr, _ in got)
        assert all(t0 <= t <= time.monotonic_ns() for _, _, t in got)
        assert b.drain() == []
    finally:
        a.close()
        b.close()


async def test_inbox_overflow_is_counted() -> None:
    a = await UdpTransport.bind(("127.0.0.1", 0))
    b = await UdpTransport.bind(("127.0.0.1", 0), inbox_size=10)
    try:
        for i in range(30):
            a.send(i.to_bytes(2, "big"), b.local_address)
        await asyncio.sleep(0.05)
        got = b.drain()
        assert len(got) == 10 and b.inbox_overflow == 20
        assert got[-1][0] == (29).to_bytes(2, "big")  # newest kept
    finally:
        a.close()
        b.close()


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
