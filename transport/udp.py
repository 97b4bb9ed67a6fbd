"""UDP datagrams on a non-blocking socket that the 1 kHz loop reads itself; the event loop (uvloop
when available, the default, else stdlib asyncio) only wakes it for a datagram outside the ticks.

**Why not asyncio's datagram transport.** Its reader takes a few datagrams per event-loop pass
(libuv's 32 under uvloop, one under asyncio) and the loop gets one pass per tick, so a flood of
50k small datagrams a second outran it (~32 read a tick, bench/results/flood.json) and filled the
socket's buffer: the kernel then dropped genuine payloads with the junk.  It also built a bytes
object of each datagram's full length before anyone could refuse it.

**Drain.** :meth:`UdpTransport.drain` reads the socket until it is empty, at most ``budget``
datagrams a call (a flood cannot hold the tick; the rest waits in the kernel's queue for the next
drain, not lost; ``drain_budget_hits`` counts the drains that stopped there).

**Cheap refusal.** Every datagram is received into one preallocated buffer of ``max_datagram``
bytes with ``MSG_TRUNC``: the kernel copies only what fits and returns the true length, so a
longer datagram is recognised and counted (``oversize``) for one system call and a bounded copy,
with no allocation, before it is queued, hashed or parsed.  The runner narrows ``max_datagram`` to
its endpoint's bound when a session starts (4122 bytes at 2 DoF), so a 60 kB datagram costs a
4 kB copy instead of two 60 kB ones.

**Receive buffer.** The socket asks for ``rcvbuf`` bytes (default 16 MiB; never less than it has):
the junk that arrives between two drains, or during a stall of the host, waits there instead of
pushing genuine payloads out.  With CAP_NET_ADMIN it is set with SO_RCVBUFFORCE; otherwise
``net.core.rmem_max`` caps it and :attr:`UdpTransport.warnings` says what was obtained.  What the
kernel still dropped on this socket (a full buffer) is read with SO_MEMINFO (``kernel_drops``).

**Kernel filter.** :meth:`UdpTransport.admit` installs the endpoint's :class:`Admission` as a socket
filter (``transport.sockfilter``): in a session, what the endpoint would refuse anyway (too long, a
stranger's non-handshake datagram, and under a handshake flood most strangers' handshakes) is
dropped by the kernel before the loop reads it, and counted in ``kernel_drops`` with the overflow.
Where the kernel refuses the filter, the warning says so and the drain above still refuses it all.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import os
import socket
import struct
import sys
import time
from typing import Any

from teleop.session.admission import Admission
from teleop.session.wire import MAX_DATAGRAM_BYTES

from . import sockfilter
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


UDP_MAX_PAYLOAD = 65535  # no UDP datagram is longer (65507 over IPv4, 65527 over IPv6)
# Linux accounts a datagram's whole buffer (~830 B for 100 B, ~61 kB for 60 kB on loopback) against
# twice what is asked: 16 MiB holds ~40k small datagrams (0.4 s of a 100k/s flood between two drains)
# or ~550 of 60 kB (5 ms of one at 100k/s; 4 MiB, 1.4 ms of it, lost some with the junk).
DEFAULT_RCVBUF_BYTES = 16 << 20
MAX_RCVBUF_BYTES = 64 << 20
MIN_RCVBUF_BYTES = 64 << 10
DRAIN_BUDGET = 512  # datagrams one drain reads at most: 5 ticks' worth of a 100k/s flood
_SO_MEMINFO = getattr(socket, "SO_MEMINFO", 55)  # Linux >= 4.6: u32[SK_MEMINFO_VARS]
_SK_MEMINFO_DROPS = 8
_SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)


def set_rcvbuf(sock: socket.socket, want: int) -> tuple[int, str | None]:
    """Ask for a receive buffer of ``want`` bytes; returns (what the kernel reports, a warning or None).

    Linux doubles what is asked (its accounting counts each datagram's overhead) and reports the
    doubled figure.  SO_RCVBUFFORCE (CAP_NET_ADMIN) may exceed ``net.core.rmem_max``; SO_RCVBUF is
    capped by it.  A buffer already larger (systemd's ``ReceiveBuffer=``) is kept."""
    if not MIN_RCVBUF_BYTES <= want <= MAX_RCVBUF_BYTES:
        raise ValueError(f"receive buffer must be {MIN_RCVBUF_BYTES}..{MAX_RCVBUF_BYTES} bytes, got {want}")
    have = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    if have >= want:
        return have, None
    try:
        sock.setsockopt(socket.SOL_SOCKET, _SO_RCVBUFFORCE, want)
    except OSError:  # not permitted (no CAP_NET_ADMIN) or not Linux: rmem_max caps it
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, want)
    got = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    if got >= want:
        return got, None
    return got, (
        f"UDP receive buffer {got} bytes, asked {want} (net.core.rmem_max caps it without CAP_NET_ADMIN);"
        " a flood between two ticks may push genuine datagrams out"
    )


def kernel_drops(sock: socket.socket) -> int | None:
    """Datagrams the kernel dropped on ``sock`` (a full receive buffer), or None where unknown."""
    if sys.platform != "linux":
        return None
    try:
        info = sock.getsockopt(socket.SOL_SOCKET, _SO_MEMINFO, 4 * (_SK_MEMINFO_DROPS + 1))
    except OSError:
        return None
    if len(info) < 4 * (_SK_MEMINFO_DROPS + 1):
        return None
    return int(struct.unpack_from("I", info, 4 * _SK_MEMINFO_DROPS)[0])


#: Linux's SO_TIMESTAMPNS (also its control message's type; Python 3.11 does not name it): each
#: datagram's arrival as a struct timespec of the real-time clock.
_SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("=qq")
_STAMP_SPACE = socket.CMSG_SPACE(_TIMESPEC.size) if hasattr(socket, "CMSG_SPACE") else 0


def _kernel_stamps(sock: socket.socket) -> bool:
    """Ask the kernel to stamp each datagram's arrival; False where it cannot (then read times)."""
    if not sys.platform.startswith("linux") or not _STAMP_SPACE:
        return False
    try:
        sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
    except OSError:
        return False
    return True


def _wake(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


class UdpTransport:
    """A bound UDP socket: ``send(data, addr)``, ``drain() -> [(data, addr, t_rx_ns)]``.

    ``t_rx_ns`` is the datagram's arrival on the monotonic clock: the kernel's stamp on Linux, else
    when ``drain`` read it.  ``max_datagram``: longer
    datagrams are counted in ``oversize`` and dropped (see the module's docstring).
    """

    header_bytes = 28  # UDP (8) + IPv4 (20): on the wire below every datagram

    def __init__(self, budget: int = DRAIN_BUDGET, rcvbuf: int = DEFAULT_RCVBUF_BYTES) -> None:
        if budget < 1:
            raise ValueError(f"drain budget must be >= 1, got {budget}")
        self.budget = budget
        self.rcvbuf_asked = rcvbuf
        self.rcvbuf_bytes = 0  # what the kernel reports once bound
        self.warnings: list[str] = []
        self.inbox_overflow = 0  # no inbox: what is not drained waits in the kernel's queue
        self.drain_budget_hits = 0
        self.oversize = 0
        self.socket_errors = 0
        self.last_socket_error = ""
        self._sock: socket.socket | None = None
        self._stamps = False  # the kernel stamps arrivals (SO_TIMESTAMPNS)
        self._buf = bytearray(0)
        self._view = memoryview(self._buf)
        self.max_datagram = MAX_DATAGRAM_BYTES
        self._admission: Admission | None = None
        self.filter_updates = 0  # filters installed (one per change of the endpoint's admission)
        self.filter_error = ""  # why the kernel refused the filter (then the drain refuses all)

    @property
    def max_datagram(self) -> int:
        """The longest datagram taken (at most ``UDP_MAX_PAYLOAD``, which no datagram exceeds)."""
        return len(self._buf)

    @max_datagram.setter
    def max_datagram(self, n: int) -> None:
        n = max(1, min(int(n), UDP_MAX_PAYLOAD))
        if n != len(self._buf):
            self._buf = bytearray(n)
            self._view = memoryview(self._buf)

    @classmethod
    async def bind(
        cls, local: Addr, budget: int = DRAIN_BUDGET, rcvbuf: int = DEFAULT_RCVBUF_BYTES
    ) -> UdpTransport:
        """Bind ``local``; OSError (for example EADDRINUSE) propagates with the address in it."""
        self = cls(budget, rcvbuf)
        sock = inherited_socket()  # socket activation: systemd bound it (``local`` is not used)
        if sock is None:
            sock = _bind(local)
        sock.setblocking(False)
        self._sock = sock
        self._stamps = _kernel_stamps(sock)
        self.rcvbuf_bytes, warning = set_rcvbuf(sock, rcvbuf)
        if warning is not None:
            self.warnings.append(warning)
        return self

    @property
    def local_address(self) -> Addr:
        assert self._sock is not None
        host, port = self._sock.getsockname()[:2]
        return str(host), int(port)

    def admit(self, admission: Admission) -> None:
        """Let the kernel refuse what ``admission`` excludes (module docstring); a no-op when it has
        not changed.  A filter the kernel refuses is reported once and the drain goes on refusing."""
        if admission == self._admission or self._sock is None or self.filter_error:
            return
        self._admission = admission
        try:
            sockfilter.attach(self._sock, sockfilter.compile_filter(admission, self._sock.family))
        except OSError as e:
            self.filter_error = f"{type(e).__name__}: {e}"
            why = f"no kernel socket filter ({self.filter_error}): floods are refused in the loop"
            self.warnings.append(why)
            return
        self.filter_updates += 1

    def send(self, data: bytes, addr: Addr) -> None:
        """Send at once; a failure (a full send buffer, an unreachable network) is counted, not raised."""
        assert self._sock is not None
        try:
            self._sock.sendto(data, addr)
        except OSError as e:
            self._error(e)

    def drain(self) -> list[tuple[bytes, Addr, int]]:
        """Every datagram waiting in the socket (at most ``budget``), oldest first."""
        out: list[tuple[bytes, Addr, int]] = []
        sock = self._sock
        if sock is None:
            return out
        buf, view, limit, clock = self._buf, self._view, len(self._buf), time.monotonic_ns
        if self._stamps:
            return self._drain_stamped(sock, out)
        recv = sock.recvfrom_into
        for _ in range(self.budget):
            try:
                n, addr = recv(buf, 0, socket.MSG_TRUNC)  # n: the datagram's true length
            except BlockingIOError:
                return out
            except OSError as e:
                self._error(e)
                return out
            if n > limit:  # by its true length alone: only ``limit`` bytes were copied
                self.oversize += 1
                continue
            out.append((bytes(view[:n]), addr, clock()))
        self.drain_budget_hits += 1
        return out

    def _drain_stamped(
        self, sock: socket.socket, out: list[tuple[bytes, Addr, int]]
    ) -> list[tuple[bytes, Addr, int]]:
        """:meth:`drain` with each datagram's arrival as the kernel stamped it (``SO_TIMESTAMPNS``,
        the real-time clock, moved onto the monotonic one): where the peer's packets land on our tick
        grid is what the teleoperator's phase follows (``teleop.session.link.phase``), and the loop reads
        its socket only when it wakes for a tick, which would stamp them all at its own wake-up."""
        view, limit = self._view, len(self._buf)
        mono = time.monotonic_ns()
        to_mono = mono - time.time_ns()
        recv = sock.recvmsg_into
        for _ in range(self.budget):
            try:
                n, anc, _flags, addr = recv([view], _STAMP_SPACE, socket.MSG_TRUNC)
            except BlockingIOError:
                return out
            except OSError as e:
                self._error(e)
                return out
            if n > limit:
                self.oversize += 1
                continue
            t_rx = 0
            for level, kind, data in anc:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(data) >= 16:
                    sec, nsec = _TIMESPEC.unpack_from(data)
                    t_rx = sec * 1_000_000_000 + nsec + to_mono
            # Never later than now, nor before the drain began reading (a clock step in between).
            now = time.monotonic_ns()
            out.append((bytes(view[:n]), addr, min(t_rx, now) if t_rx else now))
        self.drain_budget_hits += 1
        return out

    async def wait(self, timeout: float) -> bool:
        """Wait until the socket is readable (woken by I/O, not a timer); False on timeout."""
        assert self._sock is not None
        loop = asyncio.get_running_loop()
        fut: asyncio.Future[None] = loop.create_future()
        fd = self._sock.fileno()
        loop.add_reader(fd, _wake, fut)
        try:
            await asyncio.wait_for(fut, max(timeout, 0.0))
        except TimeoutError:
            return False
        finally:
            loop.remove_reader(fd)
        return True

    def report(self) -> dict[str, Any]:
        """The transport's counters for ``ROLE.json``'s ``received`` (kernel drops: since it opened)."""
        return {
            "inbox_overflow": self.inbox_overflow,
            "socket_errors": self.socket_errors,
            "oversize": self.oversize,
            "drain_budget_hits": self.drain_budget_hits,
            "rcvbuf_asked": self.rcvbuf_asked,
            "rcvbuf_bytes": self.rcvbuf_bytes,
            # Refused by the socket filter or dropped by a full buffer (the kernel counts both).
            "kernel_drops": kernel_drops(self._sock) if self._sock is not None else None,
            "filter": self._filter_report(),
        }

    def _filter_report(self) -> dict[str, Any]:
        a = self._admission
        return {
            "updates": self.filter_updates,
            "error": self.filter_error or None,
            "strangers": a.strangers.name.lower() if a is not None else None,
            "sample": a.sample if a is not None else None,
        }

    def _error(self, e: OSError) -> None:
        self.socket_errors += 1
        self.last_socket_error = f"{type(e).__name__}: {e}"

    def close(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
            self._sock = None


def _bind(local: Addr) -> socket.socket:
    """A UDP socket bound to ``local`` (the first of its addresses that binds), or OSError saying why."""
    host, port = local
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
    except socket.gaierror as e:
        raise OSError(errno.EINVAL, f"cannot bind UDP {host}:{port}: {e.strerror}") from None
    err: OSError | None = None
    for family, kind, proto, _, addr in infos:
        sock = socket.socket(family, kind, proto)
        try:
            sock.bind(addr)
            return sock
        except OSError as e:
            sock.close()
            err = e
    assert err is not None
    reason = os.strerror(err.errno) if err.errno else str(err)
    raise OSError(err.errno, f"cannot bind UDP {host}:{port}: {reason}") from None
