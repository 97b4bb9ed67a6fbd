"""UDP datagrams on asyncio, with uvloop when available (the default) and stdlib asyncio otherwise.

The protocol callback only appends to a bounded inbox; the 1 kHz loop drains it once per tick.
Anything that overflows the inbox is counted, never silently lost.  A datagram longer than the
protocol's largest (``teleop.wire.MAX_DATAGRAM_BYTES``) is refused by its length alone, before it
is queued, hashed or parsed, and counted in ``oversize``.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import socket
import time
from collections import deque

from teleop.wire import MAX_DATAGRAM_BYTES

from .base import Addr


def new_event_loop(use_uvloop: bool = True) -> tuple[asyncio.AbstractEventLoop, str]:
    """An event loop and its name: uvloop if asked for and installed, else stdlib asyncio."""
    if use_uvloop:
        try:
            import uvloop

            return uvloop.new_event_loop(), "uvloop"
        except ImportError:  # pragma: no cover - uvloop is a dependency on Linux
            pass
    return asyncio.new_event_loop(), "asyncio"


def parse_addr(text: str, what: str) -> Addr:
    """``HOST:PORT`` -> (host, port); ValueError says what is wrong and what is allowed."""
    host, sep, port = text.rpartition(":")
    if not sep or not host:
        raise ValueError(f"{what} must be HOST:PORT (for example 127.0.0.1:7000), got {text!r}")
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"{what}: port must be an integer 0..65535, got {port!r}") from None
    if not 0 <= p <= 65535:
        raise ValueError(f"{what}: port must be an integer 0..65535, got {p}")
    return host.strip("[]"), p


class _Protocol(asyncio.DatagramProtocol):
    def __init__(self, owner: UdpTransport) -> None:
        self.owner = owner

    def datagram_received(self, data: bytes, addr: Addr) -> None:
        o = self.owner
        if len(data) > MAX_DATAGRAM_BYTES:  # by length alone: nothing else is spent on it
            o.oversize += 1
            return
        if len(o.inbox) == o.inbox.maxlen:
            o.inbox_overflow += 1
        o.inbox.append((data, addr, time.monotonic_ns()))
        w = o._waiter
        if w is not None and not w.done():
            w.set_result(None)

    def error_received(self, exc: Exception) -> None:
        self.owner.socket_errors += 1
        self.owner.last_socket_error = f"{type(exc).__name__}: {exc}"


SD_LISTEN_FDS_START = 3  # sd_listen_fds(3): the first socket systemd passes


def inherited_socket() -> socket.socket | None:
    """The datagram socket systemd bound for this process (socket activation), or None.

    With ``deploy/systemd/teleop-teleoperator.socket`` the socket belongs to systemd and outlives the
    process: across a crash and restart nobody else can bind the robot's port in between (a squatter
    that did could relay the operator elsewhere), and the service needs no privilege to bind it."""
    if os.environ.get("LISTEN_PID") != str(os.getpid()):
        return None
    n = os.environ.get("LISTEN_FDS", "0")
    if n != "1":
        why = f"socket activation passed {n} sockets; teleop takes exactly one (ListenDatagram=)"
        raise OSError(errno.EINVAL, why)
    sock = socket.socket(fileno=SD_LISTEN_FDS_START)
    if sock.type != socket.SOCK_DGRAM:
        sock.detach()
        raise OSError(errno.EINVAL, "the socket systemd passed is not a datagram socket (ListenDatagram=)")
    sock.setblocking(False)
    for name in ("LISTEN_PID", "LISTEN_FDS", "LISTEN_FDNAMES"):  # not for our children
        os.environ.pop(name, None)
    return sock


class UdpTransport:
    """A bound UDP socket: ``send(data, addr)``, ``drain() -> [(data, addr, t_rx_ns)]``.

    ``t_rx_ns`` is the monotonic clock when the event loop handed the datagram over.
    """

    header_bytes = 28  # UDP (8) + IPv4 (20): on the wire below every datagram

    def __init__(self, inbox_size: int = 4096) -> None:
        self.inbox: deque[tuple[bytes, Addr, int]] = deque(maxlen=inbox_size)
        self._waiter: asyncio.Future[None] | None = None
        self.inbox_overflow = 0
        self.oversize = 0
        self.socket_errors = 0
        self.last_socket_error = ""
        self._transport: asyncio.DatagramTransport | None = None

    @classmethod
    async def bind(cls, local: Addr, inbox_size: int = 4096) -> UdpTransport:
        """Bind ``local``; OSError (for example EADDRINUSE) propagates with the address in it."""
        self = cls(inbox_size)
        loop = asyncio.get_running_loop()
        try:
            sock = inherited_socket()
            if sock is not None:  # socket activation: systemd bound it (``local`` is not used)
                transport, _ = await loop.create_datagram_endpoint(lambda: _Protocol(self), sock=sock)
            else:
                transport, _ = await loop.create_datagram_endpoint(lambda: _Protocol(self), local_addr=local)
        except OSError as e:
            # uvloop wraps the reason (EADDRINUSE: "Address already in use") as the cause.
            root = e.__cause__ if isinstance(e.__cause__, OSError) else e
            reason = os.strerror(root.errno) if root.errno else str(root)
            raise OSError(root.errno, f"cannot bind UDP {local[0]}:{local[1]}: {reason}") from None
        self._transport = transport
        return self

    @property
    def local_address(self) -> Addr:
        assert self._transport is not None
        host, port = self._transport.get_extra_info("sockname")[:2]
        return str(host), int(port)

    def send(self, data: bytes, addr: Addr) -> None:
        assert self._transport is not None
        self._transport.sendto(data, addr)

    def drain(self) -> list[tuple[bytes, Addr, int]]:
        items = list(self.inbox)
        self.inbox.clear()
        return items

    async def wait(self, timeout: float) -> bool:
        """Wait until a datagram is in the inbox (woken by I/O, not a timer); False on timeout."""
        if self.inbox:
            return True
        self._waiter = asyncio.get_running_loop().create_future()
        try:
            await asyncio.wait_for(self._waiter, max(timeout, 0.0))
        except TimeoutError:
            return False
        finally:
            self._waiter = None
        return True

    def close(self) -> None:
        if self._transport is not None:
            with contextlib.suppress(Exception):
                self._transport.close()
            self._transport = None
