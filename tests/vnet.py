"""A virtual-time network for endpoints: seeded, deterministic, milliseconds of wall time a second.

Hosts are :class:`teleop.session.endpoint.Endpoint`\\ s at addresses (their ticks run by the network,
or by a :class:`teleop.session.scheduler.Scheduler` around each), each with its own clock (an offset from
the network's), joined by links with a one-way delay per direction and seeded loss.  The loop jumps
from one instant to the next: a datagram's arrival, an endpoint's timer, a tick's deadline.  An
adversary sees every datagram (``tap``) and may drop, copy, redirect or inject; a host can be killed
and another started at its address (a restart), the link can go dark for a while (an outage), and a
host's loop can stall (``stall``: a starved process, which then drains its socket and catches up).
"""

from __future__ import annotations

import heapq
import random
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from teleop.session import auth
from teleop.session.endpoint import Endpoint, session_port
from teleop.session.events import Event, SessionStarted
from teleop.session.link import Addr
from teleop.session.port import Port, PortKeys
from teleop.session.protocol import SessionParams
from teleop.session.schedule import TickPolicy
from teleop.session.scheduler import Scheduler
from teleop.session.settings import Envelope

PSK = bytes(range(32))
OP, TO, TO_B, EVE = ("10.0.0.1", 5000), ("10.0.0.2", 7000), ("10.0.0.3", 7000), ("10.0.0.66", 6666)
MS = 1_000_000
MAX_CATCHUP = 20  # ticks a host runs back to back before it skips (shell.realtime.Ticker)

#: An adversary: (now, src, dst, data) -> the datagrams to deliver instead, as (src, dst, data).
Tap = Callable[[int, Addr, Addr, bytes], list[tuple[Addr, Addr, bytes]]]


def params(session: int = 7, duration: float = 3.0, **kw: Any) -> SessionParams:
    base: dict[str, Any] = {
        "session": session,
        "codec": "eds:50",
        "scenario": "protocol",
        "dof": 2,
        "b": 20.0,
        "full_scale": 2.0,
        "duration": duration,
        "playout": "auto",
    }
    return SessionParams(**{**base, **kw}).validate()


def port_factory(role: str, device: str | None = None) -> Callable[[SessionParams, int, PortKeys, int], Port]:
    def make(p: SessionParams, k0: int, keys: PortKeys, start_ns: int) -> Port:
        return session_port(role, p, k0, keys, header_bytes=28, device=device)

    return make


@dataclass
class Host:
    addr: Addr
    ep: Endpoint
    offset_ns: int  # this host's clock minus the network's
    events: list[Event] = field(default_factory=list)
    next_k: int | None = None  # the next tick to run (None: no session running)
    sent: int = 0
    #: The endpoint's ticks are a scheduler's timers (``ticks=TickPolicy``): the network does not
    #: tick it, and drives the scheduler instead of the endpoint.  ``spin_ns``: it is also called
    #: that long before each timer, as a precise runner's spin is.
    sched: Scheduler | None = None
    spin_ns: int = 0
    early_for: int | None = None  # the timer it was last called early for

    @property
    def io(self) -> Endpoint | Scheduler:
        """What the network drives: the scheduler if the host has one, else the endpoint."""
        return self.sched if self.sched is not None else self.ep

    def clock(self, t: int) -> int:
        return t + self.offset_ns

    def started(self) -> list[SessionStarted]:
        return [e for e in self.events if isinstance(e, SessionStarted)]

    def of(self, kind: type) -> list[Any]:
        return [e for e in self.events if isinstance(e, kind)]


class VirtualNet:
    def __init__(
        self,
        one_way_ms: float | tuple[float, float] = 0.1,
        loss: float = 0.0,
        seed: int = 0,
        jitter: float = 0.0,
    ) -> None:
        """``jitter``: each datagram's delay is the direction's times 1 + U(0, jitter) (seeded;
        datagrams may overtake each other)."""
        fwd, bwd = one_way_ms if isinstance(one_way_ms, tuple) else (one_way_ms, one_way_ms)
        self.delay_ns = {"fwd": round(fwd * MS), "bwd": round(bwd * MS)}
        self.loss = loss
        self.jitter = jitter
        self.rng = random.Random(seed)
        self.now = 0
        self.hosts: dict[Addr, Host] = {}
        self._q: list[tuple[int, int, Addr, Addr, bytes]] = []
        self._seq = 0
        self.dark: list[tuple[int, int]] = []  # outages: [start, end) of the network's time
        self.tap: Tap | None = None
        self.delivered = self.dropped = 0
        self.stalled: dict[Addr, int] = {}  # host -> the network time its loop runs again

    def rand(self) -> Callable[[int], bytes]:
        return self.rng.randbytes

    # --- hosts --------------------------------------------------------------------------------
    def operator(
        self,
        p: SessionParams,
        *,
        addr: Addr = OP,
        peer: Addr = TO,
        name: str = "robot",
        offset_ns: int = 0,
        device: str | None = None,
        **kw: Any,
    ) -> Host:
        ep = kw.get("cls", Endpoint).operator(
            p,
            peer,
            port_factory("operator", device),
            now_ns=self.now + offset_ns,
            psk=auth.robot_key(PSK, name),
            rng=self.rand(),
            **{k: v for k, v in kw.items() if k not in ("cls", "spin_ns", "ticks")},
        )
        return self._add(addr, ep, offset_ns, kw)

    def teleoperator(
        self,
        *,
        addr: Addr = TO,
        name: str = "robot",
        offset_ns: int = 5_000_000_000,
        expect: dict[str, Any] | None = None,
        limits: Envelope | None = None,
        device: str | None = None,
        **kw: Any,
    ) -> Host:
        ep = kw.get("cls", Endpoint).teleoperator(
            expect or {},
            port_factory("teleoperator", device),
            now_ns=self.now + offset_ns,
            psk=auth.robot_key(PSK, name),
            local_limits=limits,
            rng=self.rand(),
            **{k: v for k, v in kw.items() if k not in ("cls", "spin_ns", "ticks")},
        )
        return self._add(addr, ep, offset_ns, kw)

    def _add(self, addr: Addr, ep: Endpoint, offset_ns: int, kw: dict[str, Any] | None = None) -> Host:
        """``kw``: the endpoint's options, ``ticks`` (a :class:`TickPolicy`: a scheduler runs its
        ticks as timers) and ``spin_ns`` (Host)."""
        policy: TickPolicy | None = (kw or {}).get("ticks")
        sched = Scheduler(ep, policy) if policy is not None else None
        h = self.hosts[addr] = Host(addr, ep, offset_ns, sched=sched, spin_ns=(kw or {}).get("spin_ns", 0))
        self._flush(h)
        return h

    def stall(self, addr: Addr, until_ns: int) -> None:
        """The host's loop runs nothing before ``until_ns`` (network time): no tick, no timer, and
        what reaches it waits in its socket, read in order when it wakes, before its next tick."""
        self.stalled[addr] = until_ns

    def _asleep(self, addr: Addr) -> bool:
        until = self.stalled.get(addr)
        if until is not None and self.now >= until:
            del self.stalled[addr]
        return addr in self.stalled

    def kill(self, addr: Addr) -> Host:
        """The process at ``addr`` dies: it sends nothing more, and what reaches it is lost."""
        return self.hosts.pop(addr)

    # --- datagrams ----------------------------------------------------------------------------
    def inject(self, src: Addr, dst: Addr, data: bytes, delay_ns: int = 0) -> None:
        self._seq += 1
        heapq.heappush(self._q, (self.now + delay_ns, self._seq, src, dst, data))

    def _send(self, src: Addr, dst: Addr, data: bytes) -> None:
        out = [(src, dst, data)] if self.tap is None else self.tap(self.now, src, dst, data)
        for s, d, b in out:
            if any(a <= self.now < z for a, z in self.dark) or (self.loss and self.rng.random() < self.loss):
                self.dropped += 1
                continue
            to_operator = (h := self.hosts.get(d)) is not None and h.ep.role == "operator"
            delay = self.delay_ns["bwd" if to_operator else "fwd"]
            if self.jitter:
                delay += round(delay * self.jitter * self.rng.random())
            self.inject(s, d, b, delay)

    def _flush(self, h: Host) -> None:
        io = h.io
        for data, dst in io.datagrams_to_send(h.clock(self.now)):
            h.sent += 1
            self._send(h.addr, dst, data)
        while (ev := io.next_event()) is not None:
            h.events.append(ev)
            if isinstance(ev, SessionStarted) and h.sched is None:
                h.next_k = ev.k0
        if not h.ep.running:
            h.next_k = None

    # --- time ---------------------------------------------------------------------------------
    def _deadline(self, h: Host) -> int | None:
        """The network time of the host's next tick, or of its timer (the earlier)."""
        if self.stalled and self._asleep(h.addr):
            return self.stalled[h.addr]
        ep = h.ep
        t = None
        if h.next_k is not None and (p := ep.params) is not None:
            t = ep.t0_ns + h.next_k * round(p.dt * 1e9) - h.offset_ns
        if (timer := h.io.get_timer()) is not None:
            if h.spin_ns and h.early_for != timer:  # called a spin before it (Host.spin_ns)
                timer -= h.spin_ns
            timer = max(timer - h.offset_ns, self.now)
            if t is None or timer < t:
                t = timer
        return t

    def run(self, until_ns: int, stop: Callable[[], bool] | None = None) -> None:
        """Advance the network's clock to ``until_ns`` (or until ``stop()``).

        Each turn jumps to the earliest instant anything happens (a datagram's arrival, a host's
        timer or tick), delivers what has arrived by then, then runs each host's due timer and tick.
        Written for speed (most of a virtual session's time outside the endpoints is this loop),
        with the same instants and the same order of everything as the plain form."""
        q = self._q
        hosts = self.hosts
        while self.now < until_ns and not (stop and stop()):
            t = until_ns
            for h in hosts.values():
                d = self._deadline(h)
                if d is not None and d < t:
                    t = d
            if q and q[0][0] < t:
                t = q[0][0]
            if t > self.now:
                self.now = t
            now = self.now
            while q and q[0][0] <= now:
                _, _, src, dst, data = heapq.heappop(q)
                to = hosts.get(dst)
                if to is None:
                    self.dropped += 1
                    continue
                # In its socket until it wakes (and before its ticks then).
                if self.stalled and self._asleep(dst):
                    self._seq += 1
                    heapq.heappush(q, (self.stalled[dst], self._seq, src, dst, data))
                    continue
                self.delivered += 1
                to.io.receive_datagram(data, src, now + to.offset_ns)
                self._flush(to)
            for h in list(hosts.values()):
                if self.stalled and self._asleep(h.addr):
                    continue
                ep, io = h.ep, h.io
                local = now + h.offset_ns  # the host's clock
                timer = io.get_timer()
                if timer is not None and local >= timer:
                    io.handle_timer(local)
                    self._flush(h)
                elif timer is not None and h.spin_ns and h.early_for != timer and local >= timer - h.spin_ns:
                    h.early_for = timer  # in the spin: it may work early
                    io.handle_timer(local)
                    self._flush(h)
                if h.next_k is not None and (p := ep.params) is not None:
                    period = round(p.dt * 1e9)
                    due = ep.t0_ns + h.next_k * period
                    if local - due > MAX_CATCHUP * period:  # as the real Ticker: skip
                        h.next_k += (local - due) // period
                        due = ep.t0_ns + h.next_k * period
                    if local >= due:
                        k = h.next_k
                        h.next_k += 1
                        ep.tick(k, local)
                        self._flush(h)

    def seconds(self, s: float, stop: Callable[[], bool] | None = None) -> None:
        self.run(self.now + round(s * 1e9), stop)
