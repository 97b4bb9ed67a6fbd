"""What an endpoint takes from whom, before it does any work: the handshake budget and the admission.

:class:`HandshakeLimiter` bounds what handshake datagrams may cost (per source address and in all);
:class:`Admission` says what the endpoint can take now, for a transport able to refuse the rest
before it reaches the process (``transport.sockfilter``).  Sans I/O, like the endpoint.
"""

from __future__ import annotations

import enum
from typing import NamedTuple

from teleop.session.link import Addr

__all__ = [
    "FLOOD_HOLD_NS",
    "FLOOD_SAMPLE",
    "HANDSHAKE_BURST_ALL",
    "Admission",
    "HandshakeLimiter",
    "Strangers",
]

HANDSHAKE_RATE = 50.0  # handshake datagrams/s one source address may cost us (burst 20) ...
HANDSHAKE_BURST = 20.0
HANDSHAKE_RATE_ALL = 1000.0  # ... and all sources together (burst 200): bounds the loop's cost
HANDSHAKE_BURST_ALL = 200.0
#: Reserved for hellos with a valid cookie (a sender proven to receive at its address): a flood of
#: cookie-less hellos (recordings replayed from many ports) cannot spend it.
HANDSHAKE_RATE_COOKIE = 250.0
HANDSHAKE_BURST_COOKIE = 50.0
LIMITER_SOURCES = 4096  # source addresses remembered (oldest forgotten first)
#: Under a handshake flood (the limiter dropped within FLOOD_HOLD_NS) a transport that can filter
#: keeps strangers' handshake datagrams 1 in FLOOD_SAMPLE (see Admission).
FLOOD_SAMPLE = 64
FLOOD_HOLD_NS = 1_000_000_000


class Strangers(enum.IntEnum):
    """What an endpoint takes from addresses other than its peer (:class:`Admission`)."""

    ALL = 0  # anything (no peer yet, or a takeover is possible)
    HANDSHAKE = 1  # handshake-key datagrams only (another operator's hello gets busy or a retry)
    NONE = 2  # nothing (an operator in session: only its teleoperator speaks to it)


class Admission(NamedTuple):
    """What the endpoint can take now, for a transport able to refuse datagrams before they reach
    the process (``transport.udp`` compiles it into a kernel socket filter).  Only a coarse
    prefilter: the endpoint still checks every datagram that passes, and a transport that ignores
    this (Zenoh, a test) only counts the refusals elsewhere; the sampling under a flood may also
    drop another operator's hello the limiter would have passed (during a session it could only
    have been answered busy or with a retry, and hellos are retried).  Issue 21: a flood
    costs a syscall and a Python loop turn per datagram if it reaches the process, nothing if the
    kernel refuses it."""

    max_bytes: int  # any datagram longer than this (either key kind)
    peer: Addr | None  # None: no peer (yet), everyone is treated as the peer
    strangers: Strangers
    max_handshake_bytes: int  # a stranger's handshake datagram longer than this is refused
    sample: int  # strangers' handshake datagrams kept 1 in ``sample`` (1: all; >1 under a flood)


class HandshakeLimiter:
    """Token buckets on handshake work: per source address and for all sources together.

    A hello costs an unpack, maybe a full parse (~0.2 ms) and a reply; a genuine operator sends a
    few a second.  **Who may spend a budget** (issue 35): while the robot waits for an operator (or
    may be taken over), a handshake datagram is charged only once its MAC verified, so junk, whatever
    address it claims, spends no one's budget (it costs a MAC and is counted ``unauthenticated``);
    a hello with a valid cookie for its source is charged to buckets of its own (per source, and a
    global share reserved for them), so recorded cookie-less hellos replayed from many ports cannot
    spend what a genuine operator's second hello needs.  While a session runs with its link up, no
    stranger can start anything (busy): strangers' handshake datagrams are charged before the MAC
    (``cookie`` False), which keeps a flood's cost to a dictionary lookup each and drives the kernel
    filter's sampling (:class:`Admission`).  The running session's peer is never limited."""

    def __init__(self) -> None:
        # (source, cookie-bearing) -> (tokens, last refill ns): the two kinds never share a bucket
        self._per: dict[tuple[Addr, bool], tuple[float, int]] = {}
        self._all = (HANDSHAKE_BURST_ALL, 0)
        self._cookie = (HANDSHAKE_BURST_COOKIE, 0)
        self.dropped = 0
        self.last_drop_ns: int | None = None

    @staticmethod
    def _take(tokens: float, last: int, now_ns: int, rate: float, burst: float) -> tuple[float, bool]:
        tokens = min(burst, tokens + max(0, now_ns - last) * rate / 1e9)
        return (tokens - 1.0, True) if tokens >= 1.0 else (tokens, False)

    def allow(self, addr: Addr, now_ns: int, cookie: bool = False) -> bool:
        """Whether one more handshake datagram from ``addr`` may be worked on (``cookie``: a hello
        whose MAC verified and whose cookie is valid for ``addr``)."""
        key = (addr, cookie)
        tokens, last = self._per.pop(key, (HANDSHAKE_BURST, now_ns))
        tokens, ok = self._take(tokens, last, now_ns, HANDSHAKE_RATE, HANDSHAKE_BURST)
        self._per[key] = (tokens, now_ns)  # newest last
        if len(self._per) > LIMITER_SOURCES:
            del self._per[next(iter(self._per))]
        if ok and cookie:
            rate, burst = HANDSHAKE_RATE_COOKIE, HANDSHAKE_BURST_COOKIE
            c_tokens, reserved = self._take(*self._cookie, now_ns, rate, burst)
            self._cookie = (c_tokens, now_ns)
            if reserved:
                return True  # (else the general share, below)
        if ok:
            all_tokens, ok = self._take(*self._all, now_ns, HANDSHAKE_RATE_ALL, HANDSHAKE_BURST_ALL)
            self._all = (all_tokens, now_ns)
        if not ok:
            self.dropped += 1
            self.last_drop_ns = now_ns
        return ok
