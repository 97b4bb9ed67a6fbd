"""The operator's rejoin of a restarted teleoperator, sans I/O: its offers, samples and start.

While its link is lost, the operator's endpoint (``teleop.session.endpoint``) offers a rejoin (a
hello of the running session, ``rejoin``) every :data:`REJOIN_OFFER_INTERVAL_NS`, so that a
restarted teleoperator can take the session over.  A retry's cookie is taken and the offer resent
at once; so is the next offer after each welcome, until :data:`REJOIN_SAMPLES` welcomes of one
teleoperator nonce (or :data:`REJOIN_COLLECT_NS`).  The exchange with the smallest round trip
places the start on the teleoperator's clock (its error is at most half that round trip), and that
start is resent, sealed anew each time, until the teleoperator confirms it (at most
:data:`START_RESENDS` times).  :class:`Rejoin` is that state; the endpoint decides when it applies.
"""

from __future__ import annotations

from collections import deque

from teleop.session import protocol
from teleop.session.port import Port
from teleop.session.protocol import SessionParams

__all__ = [
    "REJOIN_COLLECT_NS",
    "REJOIN_OFFER_INTERVAL_NS",
    "REJOIN_SAMPLES",
    "START_RESENDS",
    "START_RESEND_NS",
    "Rejoin",
]

REJOIN_OFFER_INTERVAL_NS = 250_000_000  # operator, link lost: an offer this often
REJOIN_SAMPLES = 4  # welcomes of one restarted teleoperator before the start is placed
REJOIN_COLLECT_NS = 2_000_000_000  # or this long after the first of them
START_RESEND_NS = 20_000_000  # a rejoin's start, until started (or the new peer's data) arrives ...
START_RESENDS = 50  # ... at most this often, each max(START_RESEND_NS, rtt / 8) apart: >= 6 round trips


class Rejoin:
    """One operator session's rejoin state (the module docstring) and its figures."""

    def __init__(self) -> None:
        # t_ns of offers not yet answered: at a 2 s round trip some 16 are in flight
        self.offers: deque[int] = deque(maxlen=64)
        self.next_offer = 0
        self.cookie: bytes | None = None  # the restarted teleoperator's, from its retry
        self.nonce: bytes | None = None  # the teleoperator process the samples are of
        self.samples: list[tuple[int, int]] = []  # (rtt, offset) of one teleoperator nonce
        self.first = 0
        # The start, resent until confirmed: sealed anew each time (a byte-identical copy would be
        # a replay, refused unanswered by the teleoperator that took the first).
        self.start: protocol.Start | None = None
        self.resends = 0
        self.next_resend = 0
        self.interval = START_RESEND_NS
        self.offers_sent = self.retries = self.rejoins = 0

    def timer(self, link_lost: bool) -> int | None:
        """When :meth:`due` has something to send next (None: nothing while the link is up)."""
        timers = [self.next_resend] if self.start is not None else []
        if link_lost:
            timers.append(self.next_offer)
        return min(timers) if timers else None

    def due(self, port: Port, params: SessionParams, now_ns: int) -> list[bytes]:
        """What is due now: the start resent (until confirmed), and an offer while the link is lost."""
        out = []
        if self.start is not None and now_ns >= self.next_resend:
            if self.resends >= START_RESENDS:
                self.start = None
            else:
                out.append(port.seal(self.start))
                self.resends += 1
                self.next_resend = now_ns + self.interval
        if not port.link_lost or now_ns < self.next_offer:
            return out
        self.next_offer = now_ns + REJOIN_OFFER_INTERVAL_NS
        self.offers.append(now_ns)
        hello = protocol.Hello(params, t_ns=now_ns, rejoin=True, nonce=port.keys.nonce, cookie=self.cookie)
        out.append(port.seal(hello))
        self.offers_sent += 1
        return out

    def answers(self, t_ns: int) -> bool:
        """Whether a retry or welcome stamped ``t_ns`` answers an offer of ours (then taken)."""
        if t_ns not in self.offers:
            return False
        self.offers.remove(t_ns)
        return True

    def retried(self, cookie: bytes, now_ns: int) -> None:
        """A retry: the next offer, at once, carries its cookie."""
        self.cookie = cookie
        self.retries += 1
        self.next_offer = now_ns

    def sample(self, nonce: bytes, rtt: int, offset: int, t4: int) -> tuple[int, int] | None:
        """A welcome: one NTP exchange (``rtt``, ``offset``) with teleoperator process ``nonce``.
        Returns the best (rtt, offset) once there are enough (the offers are then done with); else
        None, and the next offer is due at once (the handshake's cadence)."""
        if nonce != self.nonce:  # another (newer) teleoperator process: start over
            self.nonce, self.samples, self.first = nonce, [], t4
        self.samples.append((rtt, offset))
        if len(self.samples) < REJOIN_SAMPLES and t4 - self.first < REJOIN_COLLECT_NS:
            self.next_offer = t4
            return None
        best = min(self.samples)
        self.nonce, self.samples = None, []
        self.offers.clear()
        self.rejoins += 1
        return best

    def place(self, start: protocol.Start, rtt: int, now_ns: int) -> None:
        """The start that places the session on the restarted teleoperator's clock: sent from now,
        a few times a round trip, until confirmed (:attr:`start` None again)."""
        self.start, self.resends, self.next_resend = start, 0, now_ns
        self.interval = max(START_RESEND_NS, rtt // protocol.START_RESEND_DIV)
