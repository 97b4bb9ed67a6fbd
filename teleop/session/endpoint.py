"""One side's whole session, sans I/O: handshake, start, ticks, rejoin, takeover, busy, bye, linger.

An :class:`Endpoint` has aioquic's ``QuicConnection`` surface, the same for both roles::

    ep.receive_datagram(data, addr, now_ns)      # every datagram, with its receive time
    for data, addr in ep.datagrams_to_send(now_ns): sock.sendto(data, addr)
    ep.get_timer()  /  ep.handle_timer(now_ns)   # when to come back even if nothing arrives
    ep.next_event()                              # SessionStarted, TicksEnded, Replaced, ...

The caller runs each tick with ``ep.tick(k, now_ns)`` at ``t0_ns + k dt``: a
:class:`teleop.session.scheduler.Scheduler` beside it (the real-time runner's: its timers, early
drain, early tick, grace, skips, device pacing), or the virtual-time tests' network.  The endpoint
has one mode and no clock of its own; what it receives is handled at once.

It never reads a clock, opens a socket or a file, or sleeps: ``now_ns`` is the caller's monotonic
clock, so the same object runs live in ``shell.runner`` and in virtual time in the tests
(two endpoints joined by the seeded link model, with faults and an adversary).  Every protocol
decision and constant of the session lives here; when each tick runs is the scheduler's.

**The session's life.** ``HANDSHAKE`` (``teleop.session.protocol``'s state machines: the operator's hellos,
the teleoperator's cookie, welcome and start) -> ``STARTING`` (agreed; tick ``k0`` is due at
``t0_ns``; a start resent because our started was lost is still answered) -> ``RUNNING`` ->
``LINGER`` (the shim's last datagrams, ``bye``, packets still in flight counted) -> ``CLOSED``; or
``FAILED`` with a :class:`Failure`.  A teleoperator whose operator was replaced goes from
``RUNNING`` straight to ``STARTING`` of the new session (event :class:`Replaced`).

**Rejoin** (operator, link lost): offers to a restarted teleoperator, so that it can take the
session over (``teleop.session.rejoin``).  The exchange with the smallest round trip places the
start on the teleoperator's clock: its error is at most half that round trip (NTP: the one-way
delays differ by at most the round trip), which PROTOCOL.md states as the rejoin's bound; slow
answers are used, not refused.

**Takeover** (teleoperator, link lost): handshake datagrams, and session datagrams that are not
our operator's, go to a handshake of their own; the session is replaced only when that handshake
completes, i.e. when a start proved the key and our fresh nonce.  Our own operator's rejoin offers
(an outage both sides saw) are dropped and counted: this process did not restart.

**Busy** (teleoperator, link up): another operator's hello gets a retry until it carries a valid
cookie for its address, then ``reject`` "busy"; no reply is ever larger than what was received.
"""

from __future__ import annotations

import enum
import secrets
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any, TypeAlias

from teleop.session import auth, protocol, wire
from teleop.session.admission import FLOOD_HOLD_NS, FLOOD_SAMPLE, Admission, HandshakeLimiter, Strangers
from teleop.session.events import (
    ClockShifted,
    EndReason,
    Event,
    Failed,
    HelloRejected,
    LinkLost,
    LinkRestored,
    PeerBye,
    PeerRestarted,
    Replaced,
    SessionEnded,
    SessionStarted,
    TicksEnded,
    Unverified,
)
from teleop.session.link import Addr
from teleop.session.port import Port, PortKeys, build_refusal
from teleop.session.protocol import Failure, SessionParams
from teleop.session.rejoin import Rejoin
from teleop.session.settings import Envelope
from teleop.session.summary import EndpointSummary, RejoinFigures

__all__ = [
    "GHOST_MARGIN_NS",
    "JOIN_AHEAD_TICKS",
    "Endpoint",
    "PortFactory",
    "State",
    "ghost_round_trip",
    "session_port",
]

JOIN_AHEAD_TICKS = 20  # a late joiner starts this many ticks ahead of now (it still has to set up)
START_GUARD_NS = 2_000_000  # a start closer than this (or past) is joined late
#: Operator: the teleoperator's first data packet is due by tick 0 plus the larger of this and two
#: round trips; a link never heard from is lost a link timeout after that (rejoin offers follow).
SILENT_MIN_NS = 1_000_000_000
#: Teleoperator: a session whose operator sent no data packet by tick 0 (or the commit, if later)
#: plus the start's round trip ``R`` plus this is a ghost: its link is lost then, and the robot ends
#: the session and waits for an operator again (PROTOCOL.md 4.3 step 8).  The first packet of a live
#: session arrives ``R / 2`` after tick 0 without jitter (its one-way delay and the offset's error
#: add up to half the round trip), within ``2 R`` with jitter up to half the delay; the rest is
#: margin for an operator whose first tick is late (its loop starved or still setting up on a loaded
#: host: issue 35), kept within the stated bound ``2 s + R``.
GHOST_MARGIN_NS = 1_900_000_000
#: The part of a start's lead that is not round trips (PROTOCOL.md 4.3 step 5: 3 rtt + 150 ms): a
#: start without ``rtt_ns`` bounds its round trip by (what is left of its lead - this) / 2.
LEAD_FIXED_NS = 150_000_000
BYE_COPIES = 3
LINGER_SHIM_GRACE_NS = 2_000_000_000  # how long after the linger the shim's backlog may still go out
EVENTS_KEPT = 1024  # a flood of rejected hellos cannot grow the event queue


class State(enum.Enum):
    HANDSHAKE = "handshake"
    STARTING = "starting"
    RUNNING = "running"
    LINGER = "linger"
    CLOSED = "closed"
    FAILED = "failed"


#: Makes a session's port: (params, first tick, keys, tick 0 on this clock) -> Port.  The shell's
#: factory adds its log sink and device; tests give one with an in-memory record.
PortFactory: TypeAlias = Callable[[SessionParams, int, PortKeys, int], Port]


def ghost_round_trip(stated_ns: int | None, lead_left_ns: int) -> int:
    """The round trip a teleoperator allows its operator's first packet (PROTOCOL.md 4.3 step 8):
    the one the start states, else what a lead of 3 rtt + 150 ms leaves room for (without jitter,
    2.5 rtt + 150 ms of it are left when the start arrives, whatever the path's asymmetry); at
    most ``MAX_RTT_NS``."""
    rtt = stated_ns if stated_ns is not None else (lead_left_ns - LEAD_FIXED_NS) // 2
    return min(max(rtt, 0), protocol.MAX_RTT_NS)


def _addr(a: Addr) -> str:
    return f"{a[0]}:{a[1]}"


class Endpoint:
    """One side of a session (see the module docstring).  Build it with :meth:`operator` or
    :meth:`teleoperator`."""

    def __init__(
        self,
        role: str,
        make_port: PortFactory,
        *,
        now_ns: int,
        psk: bytes,
        connect_timeout_s: float = 10.0,
        linger_s: float = 0.2,
        rng: Callable[[int], bytes] = secrets.token_bytes,
    ) -> None:
        if role not in ("operator", "teleoperator"):
            raise ValueError(f"role must be operator or teleoperator, got {role!r}")
        self.role = role
        self._make_port = make_port
        self.psk = psk
        self.connect_timeout_s = connect_timeout_s
        self.linger_ns = round(linger_s * 1e9)
        self._rng = rng
        self.state = State.HANDSHAKE
        self._events: deque[Event] = deque(maxlen=EVENTS_KEPT)
        self._out: list[tuple[bytes, Addr]] = []
        self.port: Port | None = None
        self.params: SessionParams | None = None
        self.peer: Addr | None = None
        self.start_ns = self.t0_ns = self.k0 = 0
        self.k = 0  # the last tick run (or k0 before the first)
        # The tick a datagram received now belongs to: the one about to run (what the playout
        # buffer measures transit against; counting it against the last one run plays a tick early).
        self._rx_k = 0
        self._reset_session_state()
        self._handshake_info: dict[str, Any] = {}
        self.peer_nonce: bytes | None = None  # operator: the teleoperator's, from the welcome it took
        self.offset_ns = 0  # operator: the teleoperator's clock minus ours
        self._link_lost = False
        # operator
        self._op_hs: protocol.OperatorHandshake | None = None
        self._rejoin = Rejoin()  # a restarted teleoperator's (teleop.session.rejoin)
        # teleoperator
        self._to_hs: protocol.TeleoperatorHandshake | None = None
        self._takeover: protocol.TeleoperatorHandshake | None = None
        self._expect = protocol.Pins()
        self._limits = Envelope()
        self._cookie_secret = rng(32)
        self._limiter = HandshakeLimiter()
        self._hs_sealer: auth.Sealer | None = None  # teleoperator: K_hs, one counter per process
        # The longest datagram of each key kind (index: auth.HANDSHAKE, auth.SESSION); the session
        # bound is narrowed to the agreed DoF once a session starts.
        self._max_len = [wire.MAX_HANDSHAKE_DATAGRAM_BYTES, wire.MAX_DATAGRAM_BYTES]
        self.oversize = self._rejections_seen = 0
        self._unverified_seen, self._unverified_next = 0, 0
        self.ghost_ns: int | None = None  # teleoperator: when a session never heard from ends
        self.start_rtt_ns: int | None = None  # teleoperator: the round trip its start stated
        self.committed_ns = 0  # teleoperator: when it committed to the session's start
        self._linger_end = 0

    def _reset_session_state(self) -> None:
        """What each session starts with (at start-up, for a takeover, after a ghost)."""
        self._stopped = False
        self._ended: EndReason | None = None
        self.peer_bye: protocol.Bye | None = None
        self.fault_why = ""  # what this side's device said when it ended the session (fault)
        self.replaced = False
        self.foreign = 0  # datagrams from an address other than the peer's, dropped
        self.own_offers_ignored = self.busy_rejects = self.retries_sent = 0
        self._bye_sent = False

    # --- construction -----------------------------------------------------------------------
    @classmethod
    def operator(
        cls, params: SessionParams, peer: Addr, make_port: PortFactory, *, now_ns: int, psk: bytes, **kw: Any
    ) -> Endpoint:
        """The operator's endpoint: it says hello to ``peer`` at once (``datagrams_to_send``)."""
        ep = cls("operator", make_port, now_ns=now_ns, psk=psk, **kw)
        ep.params, ep.peer = params, peer
        ep._op_hs = protocol.OperatorHandshake(
            params, now_ns=now_ns, timeout_s=ep.connect_timeout_s, psk=psk, nonce=ep._rng(auth.NONCE_BYTES)
        )
        return ep

    @classmethod
    def teleoperator(
        cls,
        expect: protocol.Pins | Mapping[str, object],
        make_port: PortFactory,
        *,
        now_ns: int,
        psk: bytes,
        local_limits: Envelope | None = None,
        **kw: Any,
    ) -> Endpoint:
        """The teleoperator's endpoint: it waits for an operator whose hello suits ``expect`` (fields
        of :class:`SessionParams`; None: the operator's choice, within ``local_limits``)."""
        ep = cls("teleoperator", make_port, now_ns=now_ns, psk=psk, **kw)
        ep._expect = protocol.Pins.of(expect)
        ep._limits = local_limits or Envelope()
        ep._to_hs = ep._new_to_handshake(now_ns)
        return ep

    def _new_to_handshake(self, now_ns: int) -> protocol.TeleoperatorHandshake:
        """A teleoperator's handshake (at start-up, for a takeover, after a ghost).  They all seal
        with one handshake sealer: its counter runs on across them and the sessions (PROTOCOL.md
        2.3: a counter is never reused under K_hs; a fresh sealer each time started again at 1)."""
        hs = protocol.TeleoperatorHandshake(
            self._expect,
            now_ns=now_ns,
            timeout_s=self.connect_timeout_s,
            psk=self.psk,
            nonce=self._rng(auth.NONCE_BYTES),
            cookie_secret=self._cookie_secret,
            local_limits=self._limits,
            defer_t3=True,
            admit=self._limiter.allow,
            vet=lambda p: build_refusal(p, self._limits),
        )
        if self._hs_sealer is None:
            self._hs_sealer = hs.hs_sealer
        hs.hs_sealer = self._hs_sealer
        return hs

    # --- the surface ------------------------------------------------------------------------
    def next_event(self) -> Event | None:
        return self._events.popleft() if self._events else None

    @property
    def running(self) -> bool:
        """Ticks are due (``STARTING`` or ``RUNNING``)."""
        return self.state in (State.STARTING, State.RUNNING)

    @property
    def finished(self) -> bool:
        return self.state in (State.CLOSED, State.FAILED)

    @property
    def max_datagram_bytes(self) -> int:
        """The longest datagram this endpoint can take now (either key kind): a transport may refuse
        a longer one by its length alone, before copying it (``transport.udp``)."""
        return max(self._max_len)

    def admission(self, now_ns: int) -> Admission:
        """What this endpoint can take now (:class:`Admission`); the runner passes it to its transport
        when it changes.  A teleoperator in session takes strangers' handshake datagrams (another
        operator is told it is busy), sampled while its limiter is dropping them; once its operator
        is silent (a takeover is possible, PROTOCOL.md 4.5) everything.  An operator in session takes
        only its teleoperator's.  In the handshake: an operator its teleoperator's, a teleoperator
        anyone's."""
        hs_max = self._max_len[auth.HANDSHAKE]
        running = self.state in (State.STARTING, State.RUNNING, State.LINGER)
        if self.role == "operator":
            return Admission(max(self._max_len), self.peer, Strangers.NONE, hs_max, 1)
        if not running or self.port is None or self._takeover_possible(self.port):
            return Admission(max(self._max_len), None, Strangers.ALL, hs_max, 1)
        last = self._limiter.last_drop_ns
        flooded = last is not None and now_ns - last < FLOOD_HOLD_NS
        return Admission(
            max(self._max_len), self.peer, Strangers.HANDSHAKE, hs_max, FLOOD_SAMPLE if flooded else 1
        )

    @property
    def handshake_throttled(self) -> int:
        """Handshake datagrams dropped over the per-source or global budget (HandshakeLimiter)."""
        return self._limiter.dropped

    def receive_datagram(self, data: bytes, addr: Addr, now_ns: int) -> None:
        """A datagram from ``addr`` received at ``now_ns``, handled at once.  Never raises: whatever
        it is, it is taken, or counted and dropped."""
        hdr = auth.peek(data)
        if hdr is not None and len(data) > self._max_len[hdr[0]]:
            self.oversize += 1  # longer than any message of its key kind: refused by length alone
            return
        handshake = hdr is not None and hdr[0] == auth.HANDSHAKE
        if handshake and addr != self.peer and self._busy() and not self._limiter.allow(addr, now_ns):
            return  # busy, over the handshake budget: dropped before the MAC (HandshakeLimiter)
        if self.state == State.HANDSHAKE:
            if self._op_hs is not None:
                if addr == self.peer:
                    self._op_hs.receive(data, now_ns)
                else:
                    self.foreign += 1
                self._check_operator_handshake(now_ns)
            elif self._to_hs is not None:
                self._out += self._to_hs.receive(data, addr, now_ns)
                self._report_rejections(self._to_hs, now_ns)
                if self._to_hs.done:
                    self._from_to_handshake(self._to_hs, now_ns)
        elif self.state in (State.STARTING, State.RUNNING, State.LINGER):
            self._session_datagram(data, hdr, addr, now_ns)

    def datagrams_to_send(self, now_ns: int) -> list[tuple[bytes, Addr]]:
        """What to send now (a welcome is stamped with ``now_ns`` as it leaves: NTP's t3)."""
        if self.state == State.HANDSHAKE and self._op_hs is not None:
            assert self.peer is not None
            self._out += [(d, self.peer) for d in self._op_hs.poll(now_ns)]
            self._check_operator_handshake(now_ns)
        if self.role == "teleoperator":
            for hs in (self._to_hs, self._takeover):
                if hs is not None:
                    self._out += hs.datagrams_to_send(now_ns)
        if self.state == State.LINGER:
            self._linger(now_ns)
        out, self._out = self._out, []
        return out

    def get_timer(self) -> int | None:
        """When :meth:`handle_timer` must be called next (ns on the caller's clock), for the
        handshake, the rejoin and the linger (the ticks are the caller's); None: nothing is due."""
        if self.state == State.HANDSHAKE:
            hs = self._op_hs or self._to_hs
            assert hs is not None
            return hs.next_timer()
        if self.state == State.RUNNING and self.role == "operator":
            return self._rejoin.timer(self._link_lost)
        if self.state == State.LINGER:
            if not self._bye_sent:
                due = self._shim_due_ns()
                return min(due, self._linger_end + LINGER_SHIM_GRACE_NS) if due is not None else 0
            return self._linger_end
        return None

    def handle_timer(self, now_ns: int) -> None:
        """The timer is due: the handshake's retries and timeouts, a rejoin's offers, the linger."""
        if self.state == State.HANDSHAKE and self._to_hs is not None:
            self._to_hs.poll(now_ns)
            if self._to_hs.error is not None:
                self._fail(self._to_hs.failure or Failure.NO_OPERATOR, self._to_hs.error)
        elif self.state == State.HANDSHAKE:
            self._check_operator_handshake(now_ns)  # datagrams_to_send polls it
        elif self.state == State.RUNNING and self.role == "operator":
            self._operator_timers(now_ns)
        elif self.state == State.LINGER:
            self._linger(now_ns)

    def fault(self, now_ns: int, why: str) -> None:
        """This side's device ended the session (a robot's reflex): the session lingers and ends, and
        its bye carries ``why`` so the peer can say it.  Nothing is ticked after it."""
        self.fault_why = why
        self._stopped = True
        if self.state in (State.STARTING, State.RUNNING):
            self._end(EndReason.DEVICE_FAULT, now_ns)
        elif self.state == State.HANDSHAKE:
            self.state = State.CLOSED

    def stop(self, now_ns: int) -> None:
        """Stop locally (a signal): the session lingers and ends (:class:`SessionEnded`)."""
        self._stopped = True
        if self.state in (State.STARTING, State.RUNNING):
            self._end(EndReason.STOPPED, now_ns)
        elif self.state == State.HANDSHAKE:
            self.state = State.CLOSED

    # --- ticks --------------------------------------------------------------------------------
    def session_time(self, now_ns: int) -> float:
        """Seconds on the common session clock (tick 0 of the session is 0)."""
        return (now_ns - self.start_ns) / 1e9

    def tick(self, k: int, now_ns: int) -> bool:
        """Run tick ``k`` at ``now_ns``; its datagrams go out with :meth:`datagrams_to_send`.  A
        ``k`` at or past the session's end (a stall skipped over it) ends the session instead.
        Returns whether the tick ran (its model and record): the loop's figures count only those."""
        assert self.port is not None and self.params is not None and self.peer is not None
        if not self.running:
            return False
        if k >= self.params.ticks:
            self._end(EndReason.COMPLETED, now_ns)
            return False
        self.state = State.RUNNING
        port = self.port
        if shift := port.clock.take_skew():
            # The peer's packets arrived before they were sent: our tick 0 is later than the peer's.
            # Tick k is not run: it lies ``shift`` ticks in the past now, and the loop goes on from
            # the present (teleop.session.link.phase), before our model has run on the wrong clock.
            self.start_ns -= shift * round(self.params.dt * 1e9)
            self.t0_ns -= shift * round(self.params.dt * 1e9)
            port.playout.forget_transits()
            self._events.append(ClockShifted(k, shift))
            return False
        # The tick runs on its deadline's time, as in ``teleop sim``: an outgoing shim timed from the
        # clock released a packet on its due tick or the next as the loop's few microseconds of
        # lateness (or an early tick's spin) fell (measured: half of a 10 ms link's packets a tick
        # late, and auto playout a tick up for good).
        deadline = self.t0_ns + k * round(self.params.dt * 1e9)
        if self.role == "operator":
            self._operator_timers(now_ns)
        for data in port.tick(k, self.session_time(deadline)):
            self._out.append((data, self.peer))
        # Stamped once the sample exists and before it leaves: the peer cannot play it earlier,
        # so the true margin (teleop.offline.report) never counts a sample as played before it was sent.
        port.sent(k, self.session_time(max(now_ns, deadline)))
        self.k, self._rx_k = k, k + 1
        self._retime(k)
        lost = port.link_lost
        if lost != self._link_lost:
            self._link_lost = lost
            self._events.append(LinkLost(k) if lost else LinkRestored(k))
            if lost:
                self._rejoin.next_offer = now_ns
        if lost and self.role == "teleoperator" and not port.heard_from_peer:
            self._end(EndReason.PEER_SILENT, now_ns)  # a ghost: free the robot for an operator
        elif k + 1 >= self.params.ticks:
            self._end(EndReason.COMPLETED, now_ns)
        elif self.params.until_stopped and self.peer_bye is not None:
            self._end(EndReason.PEER_BYE, now_ns)
        elif self.peer_bye is not None and self.peer_bye.why:
            self._end(EndReason.PEER_FAULT, now_ns)
        return True

    def _retime(self, k: int) -> None:
        """The teleoperator's phase follows where the operator's packets land (``teleop.session.link.phase``),
        so that it ticks when the operator's packet is due (a skewed tick 0 is put right before a
        tick, in :meth:`tick`).  The runner reads :attr:`t0_ns` before each tick."""
        port, params = self.port, self.params
        assert port is not None and params is not None
        port.clock.advance(k)
        self.t0_ns = self.start_ns + round(port.clock.phase * params.dt * 1e9)

    # --- handshake outcomes ------------------------------------------------------------------
    def _check_operator_handshake(self, now_ns: int) -> None:
        hs = self._op_hs
        if hs is None or self.state != State.HANDSHAKE:
            return
        if hs.error is not None:
            self._fail(hs.failure or Failure.NO_ANSWER, hs.error)
        elif hs.done:
            assert hs.tx_sealer is not None and hs.rx_opener is not None and self.params and self.peer
            keys = PortKeys(hs.tx_sealer, hs.rx_opener, hs.hs_sealer, hs.hs_opener, self.psk, hs.nonce)
            self._handshake_info = {"clock_offset_ns": hs.offset_ns, "handshake_rtt_us": hs.rtt_ns / 1e3}
            self.peer_nonce, self.offset_ns = hs.peer_nonce, hs.offset_ns
            first_due = hs.start_ns + max(SILENT_MIN_NS, 2 * hs.rtt_ns)
            started = SessionStarted(
                self.params, self.peer, hs.start_ns, hs.start_ns, 0, False, hs.offset_ns, hs.rtt_ns
            )
            self._begin(started, keys, first_due)

    def _from_to_handshake(self, hs: protocol.TeleoperatorHandshake, now_ns: int) -> None:
        """A teleoperator handshake completed: run its session (late, if it already runs)."""
        assert hs.done and hs.params is not None and hs.peer is not None
        assert hs.tx_sealer is not None and hs.rx_opener is not None
        keys = PortKeys(hs.tx_sealer, hs.rx_opener, hs.hs_sealer, hs.hs_opener, self.psk, hs.nonce)
        p = hs.params
        period = round(p.dt * 1e9)
        t0 = hs.start_ns + round(p.phase * p.dt * 1e9)
        late = hs.rejoin or now_ns > t0 - START_GUARD_NS
        k0 = max(0, -(-(now_ns - t0) // period) + JOIN_AHEAD_TICKS) if late else 0
        self._handshake_info = {"joined_late": late}
        self.start_rtt_ns, self.committed_ns = hs.start_rtt_ns, now_ns
        self.ghost_ns = max(hs.start_ns, now_ns) + ghost_round_trip(hs.start_rtt_ns, hs.start_ns - now_ns)
        self.ghost_ns += GHOST_MARGIN_NS
        self._begin(SessionStarted(p, hs.peer, hs.start_ns, t0, k0, late), keys, self.ghost_ns, lost_at=True)

    def _begin(self, ev: SessionStarted, keys: PortKeys, first_due_ns: int, lost_at: bool = False) -> None:
        """The session ``ev`` says starts (and is said, once it does).  ``first_due_ns``: when the
        peer's first packet is due (its link lost a link timeout later); ``lost_at``: when the link
        is lost if no packet came (the teleoperator's ghost)."""
        params, start_ns, k0 = ev.params, ev.start_ns, ev.k0
        self.params, self.peer, self.start_ns, self.t0_ns = params, ev.peer, start_ns, ev.t0_ns
        self.k0 = self.k = self._rx_k = k0
        self._max_len[auth.SESSION] = wire.max_session_datagram_bytes(params.dof)
        self.port = self._make_port(params, k0, keys, start_ns)
        if self.role == "teleoperator":
            # Whatever the factory built, the robot runs inside its own envelope: saturated
            # commands and an energy guard bounded by its limits, never the operator's numbers,
            # and acting no longer than its cap after its operator's last packet.
            self.port.confine(self._limits)
        if k0:
            self.port.joined_late()
        self.port.expect_first_by((first_due_ns - start_ns) / 1e9, lost_at=lost_at)
        self.state = State.STARTING
        self._link_lost = False
        self._events.append(ev)

    def _fail(self, reason: Failure, detail: str) -> None:
        self.state = State.FAILED
        self._events.append(Failed(reason, detail))

    def _report_rejections(self, hs: protocol.TeleoperatorHandshake, now_ns: int = 0) -> None:
        new = hs.rejected - self._rejections_seen
        self._rejections_seen = hs.rejected
        for why in list(hs.rejections)[-min(new, 3) :] if new > 0 else ():
            self._events.append(HelloRejected(why))
        n = hs.unauthenticated
        if n > self._unverified_seen and (self._unverified_seen == 0 or now_ns >= self._unverified_next):
            self._unverified_seen, self._unverified_next = n, now_ns + 1_000_000_000
            addr = hs.last_unauthenticated_from or ("", 0)
            self._events.append(Unverified(n, addr, hs.last_unauthenticated))

    # --- during the session -------------------------------------------------------------------
    def _session_datagram(
        self, data: bytes, hdr: tuple[int, int, int] | None, addr: Addr, now_ns: int
    ) -> None:
        """``hdr``: ``auth.peek(data)``, read once by :meth:`receive_datagram` (the 1 kHz path)."""
        port = self.port
        assert port is not None
        if addr != self.peer and (hdr is None or hdr[0] == auth.SESSION):
            # Not our peer's and not a handshake datagram: unless a takeover may be under way (our
            # operator went silent, PROTOCOL.md 4.5) it can only be refused.  Counted as the full
            # path would count it, for a fraction of its cost (a flood of junk: issue 21).
            possible = self._takeover_possible(port)
            if not possible:
                self._takeover = None
            if hdr is None or not possible:
                self.foreign += 1
                port.refuse_foreign(hdr is not None)
                return
        if self._to_takeover(data, hdr, addr, now_ns):
            return
        if hdr is not None and hdr[0] == auth.HANDSHAKE:
            self._handshake_datagram(data, addr, now_ns)
            return
        t = self.session_time(now_ns)
        k = self.k if self.state == State.LINGER else self._rx_k
        play = self.state != State.LINGER  # STARTING too: the peer's first payload may come first
        if addr != self.peer:
            port.receive(data, t, k, play, from_peer=False)  # counted as a rejection
            self.foreign += 1
            return
        # The jump bound on the clock the handshake's window ran on (PROTOCOL.md 2.4), not the
        # session's, which starts again at tick 0 and moves with it.
        msg = port.receive(data, t, k, play, clock=now_ns / 1e9)
        if msg is not None:
            self._control(msg, now_ns)

    def _control(self, msg: protocol.Message, now_ns: int) -> None:
        """An in-session control message from the peer (session key)."""
        assert self.params is not None and self.port is not None
        if getattr(msg, "session", None) != self.params.session:
            return
        if isinstance(msg, protocol.Start) and self.role == "teleoperator":
            self._out.append((self.port.seal(protocol.Started(self.params.session)), self._peer()))
        elif isinstance(msg, protocol.Started) and self._rejoin.start is not None:
            self._rejoin.start = None  # the restarted teleoperator confirmed our rejoin's start
        elif isinstance(msg, protocol.Bye) and self.peer_bye is None:
            self.peer_bye = msg
            self._events.append(PeerBye(msg.produced))

    def _handshake_datagram(self, data: bytes, addr: Addr, now_ns: int) -> None:
        """A handshake-key datagram mid-session: a rejoin's retry or welcome (operator), another
        operator's hello or our own operator's rejoin offer (teleoperator)."""
        port, params = self.port, self.params
        assert port is not None and params is not None
        body = port.open_handshake(data)
        if body is None:
            return
        if self.role == "teleoperator":
            seen = protocol.peek_hello(body)
            if seen is None:
                return
            session, t_ns, nonce, cookie = seen
            if session == params.session:
                self.own_offers_ignored += 1  # our operator offering a rejoin: we did not restart
                return
            if type(nonce) is not bytes or len(nonce) != auth.NONCE_BYTES:
                return
            if not protocol.cookie_ok(self._cookie_secret, cookie, addr, nonce, now_ns):
                self.retries_sent += 1
                retry = protocol.Retry(
                    session, t_ns, protocol.make_cookie(self._cookie_secret, addr, nonce, now_ns)
                )
                self._out.append((port.seal(retry), addr))
                return
            self.busy_rejects += 1
            self._out.append((port.seal(protocol.Reject(session, protocol.BUSY, t_ns)), addr))
            return
        if addr != self.peer:
            self.foreign += 1
            return
        msg = port.control(body)
        if not isinstance(msg, protocol.Retry | protocol.Welcome) or msg.session != params.session:
            return
        if not self._rejoin.answers(msg.t_ns):
            return
        if isinstance(msg, protocol.Retry):
            self._rejoin.retried(msg.cookie, now_ns)
            self._operator_timers(now_ns)
            return
        offset, rtt = protocol.ntp_offset(msg.t_ns, msg.t2, msg.t3, now_ns)
        if rtt >= 0:
            self._rejoin_sample(msg.nonce, rtt, offset, now_ns)

    def _peer(self) -> Addr:
        assert self.peer is not None
        return self.peer

    # --- operator: rejoin a restarted teleoperator (teleop.session.rejoin) -----------------------
    def _operator_timers(self, now_ns: int) -> None:
        port, params = self.port, self.params
        assert port is not None and params is not None
        self._out += [(d, self._peer()) for d in self._rejoin.due(port, params, now_ns)]

    def _rejoin_sample(self, nonce: bytes, rtt: int, offset: int, t4: int) -> None:
        """A restarted teleoperator welcomed an offer: one NTP exchange; with enough, the start."""
        port, params = self.port, self.params
        assert port is not None and params is not None
        best = self._rejoin.sample(nonce, rtt, offset, t4)
        if best is not None:
            rtt, offset = best
            port.peer_restarted(nonce)  # its new nonce keys the rest of the session
            start = protocol.Start(params.session, start_ns=self.start_ns + offset, rejoin=True, rtt_ns=rtt)
            self._rejoin.place(start, rtt, t4)
            self._events.append(PeerRestarted(self.k, rtt))
        self._operator_timers(t4)

    # --- teleoperator: takeover by a new operator --------------------------------------------
    def _to_takeover(self, data: bytes, hdr: tuple[int, int, int] | None, addr: Addr, now_ns: int) -> bool:
        """Teleoperator whose operator went silent: handshake datagrams, and session datagrams that
        are not our peer's, go to a handshake of their own.  Returns whether ``data`` was taken."""
        port, params = self.port, self.params
        assert port is not None and params is not None
        if not self._takeover_possible(port):
            self._takeover = None
            return False
        if hdr is None or (hdr[0] == auth.SESSION and port.verifies(data)):
            return False
        if hdr[0] == auth.HANDSHAKE and addr == self.peer and self._own_offer(data):
            self.own_offers_ignored += 1
            return True
        hs = self._takeover
        if hs is not None:
            hs.poll(now_ns)
        if hs is None or hs.error is not None:
            if hdr[0] != auth.HANDSHAKE:
                return False
            hs = self._takeover = self._new_to_handshake(now_ns)
        self._out += hs.receive(data, addr, now_ns)
        if hs.done:
            old = params.session
            self.replaced = True
            self._end(EndReason.REPLACED, now_ns)
            self._takeover = None
            self._out += hs.datagrams_to_send(now_ns)
            self._reset_session_state()
            self._from_to_handshake(hs, now_ns)
            assert self.params is not None
            self._events.append(Replaced(old, self.params.session))
        return True

    def _busy(self) -> bool:
        """A teleoperator whose session runs with its link up: a stranger can start nothing here."""
        running = self.state in (State.STARTING, State.RUNNING, State.LINGER)
        return self.role == "teleoperator" and running and not self._takeover_possible(self.port)

    def _takeover_possible(self, port: Port | None) -> bool:
        """A teleoperator whose running session's link is lost may be taken over (PROTOCOL.md 4.5)."""
        running = self.role == "teleoperator" and self.state == State.RUNNING
        return running and port is not None and port.link_lost

    def _own_offer(self, data: bytes) -> bool:
        """Whether ``data`` is an authentic hello of this very session (our operator's rejoin offer)."""
        assert self.port is not None and self.params is not None
        try:
            body = self.port.keys.hs_rx.verify(data)[1]
        except auth.AuthError:
            return False
        seen = protocol.peek_hello(body)
        return seen is not None and seen[0] == self.params.session

    def _listen_again(self, now_ns: int) -> None:
        """Teleoperator: back to the handshake, as at start-up (a new nonce, its connect timeout)."""
        self._reset_session_state()
        self.state = State.HANDSHAKE
        self.port, self.params, self.peer, self._takeover = None, None, None, None
        self._max_len[auth.SESSION] = wire.MAX_DATAGRAM_BYTES
        self._rejections_seen = 0
        self._to_hs = self._new_to_handshake(now_ns)

    # --- the end ------------------------------------------------------------------------------
    def _end(self, reason: EndReason, now_ns: int) -> None:
        """The ticks are over: linger (unless replaced: its operator is gone), then close."""
        self._ended = reason
        self._events.append(TicksEnded(self.k))
        if reason == EndReason.REPLACED:
            self._close()
            return
        if reason == EndReason.PEER_SILENT:
            # Nobody to linger for: the session ends at once and the robot waits for an operator
            # again (a late one of this session gets welcomed as a rejoin, PROTOCOL.md 4.4).
            self._close()
            self._listen_again(now_ns)
            return
        self.state = State.LINGER
        self._linger_end = now_ns + self.linger_ns
        self._bye_sent = False
        self._linger(now_ns)

    def _shim_due_ns(self) -> int | None:
        assert self.port is not None
        due = self.port.next_due()
        return None if due is None else self.start_ns + round(due * 1e9)

    def _linger(self, now_ns: int) -> None:
        """Deliver what the shim still holds, say bye, and count what is still in flight, so that
        sender and receiver counts can be compared; the bye tells the receiver how many packets
        there were."""
        port, params = self.port, self.params
        assert port is not None and params is not None
        if not self._bye_sent:
            for data in port.flush(self.session_time(now_ns), max(port.rec.last, 0)):
                self._out.append((data, self._peer()))
            if port.next_due() is None or now_ns >= self._linger_end + LINGER_SHIM_GRACE_NS:
                shim = port.shim_stats()
                bye = protocol.Bye(
                    params.session, port.produced(), shim["dropped_by_limit"] if shim else 0, self.fault_why
                )
                # Sealed one by one: each copy its own counter (a byte-identical copy is a replay).
                self._out += [(port.seal(bye), self._peer()) for _ in range(BYE_COPIES)]
                self._bye_sent = True
        if self._bye_sent and now_ns >= self._linger_end:
            self._close()

    def _close(self) -> None:
        assert self._ended is not None
        summary = self.summary()
        self.state = State.CLOSED
        self._events.append(SessionEnded(self._ended, summary))

    def summary(self) -> EndpointSummary:
        """This session's figures: the port's, and the session's around it (the runner adds the
        loop's, the process's and the transport's: :class:`teleop.session.summary.ProcessSummary`)."""
        port, params = self.port, self.params
        assert port is not None and params is not None
        bye = self.peer_bye
        shim = port.shim_stats()
        spec_tx = params.netem_forward if self.role == "operator" else params.netem_backward
        ended = self._ended
        completed = ended == EndReason.COMPLETED or (
            params.until_stopped and ended in (EndReason.STOPPED, EndReason.PEER_BYE)
        )
        return EndpointSummary(
            role=self.role,
            peer=_addr(self._peer()),
            completed=bool(completed),
            end=ended.value if ended else None,
            peer_said_bye=bye is not None,
            first_tick=self.k0,
            replaced_by_new_session=ended == EndReason.REPLACED,
            rejoin=RejoinFigures(
                offers=self._rejoin.offers_sent,
                retries=self._rejoin.retries,
                rejoins=self._rejoin.rejoins,
                own_offers_ignored=self.own_offers_ignored,
            ),
            busy_rejects=self.busy_rejects,
            handshake_throttled=self._limiter.dropped,
            oversize_refused=self.oversize,
            retries_sent=self.retries_sent,
            foreign=self.foreign,
            shim={"spec": spec_tx, **shim} if shim else None,
            params=params,
            handshake=dict(self._handshake_info),
            port=port.summary(
                peer_produced=bye.produced if bye else None,
                peer_dropped_by_limit=bye.dropped_by_limit if bye else 0,
            ),
            fault=self.fault_why or (bye.why if bye is not None else ""),
        )


# ``--playout auto``'s floor in a real process: none, as in ``teleop sim``.  A payload a fraction of a
# tick late (a stalled sender, the scheduler) is waited for by grace, and the teleoperator ticks when
# the operator's payload is due (``session.link.phase``); a floor of one tick cost every payload a tick.
REAL_PLAYOUT_FLOOR_TICKS = 0


def session_port(
    role: str,
    params: SessionParams,
    k0: int,
    keys: PortKeys,
    *,
    header_bytes: int,
    sink: Any = None,
    device: str | None = None,
    playout_floor: int = REAL_PLAYOUT_FLOOR_TICKS,
) -> Port:
    """A session's port as a real process runs it: its node (``device`` or the scenario's), its
    outgoing shim (seeded as in ``teleop sim``), its counters, and ``sink`` for the record."""
    from teleop.session.port import make_shim, session_node

    node = session_node(role, params, device)
    fwd, bwd = params.netem_forward, params.netem_backward
    spec_tx, spec_rx = (fwd, bwd) if role == "operator" else (bwd, fwd)
    return Port(
        node,
        ticks=params.ticks,
        shim=make_shim(spec_tx, params.seed, node.tx_direction),
        peer_spec=spec_rx,
        header_bytes=header_bytes,
        first_tick=k0,
        keys=keys,
        playout_floor=playout_floor,
        sink=sink,
        window_ticks=max(1, round(0.1 / params.dt)),
        phase=params.phase,
    )
