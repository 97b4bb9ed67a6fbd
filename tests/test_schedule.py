"""Ticks as timers (``teleop.session.schedule``, ``Scheduler(endpoint, TickPolicy(...))``), in virtual
time: the policy the real-time runner used to hold (early drain, early tick, grace, skips, the
loop's figures, admission changes, a device that paces the ticks) runs in the scheduler beside the
endpoint, driven only by ``get_timer``/``handle_timer`` (tests/vnet.py calls it as a precise runner
does: also ``spin_ns`` before each timer)."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

from teleop.session.admission import Strangers
from teleop.session.endpoint import Endpoint, State
from teleop.session.events import AdmissionChanged, SessionEnded, TicksEnded
from teleop.session.schedule import EARLY_MARGIN_NS, LoopFigures, TickPolicy
from teleop.session.scheduler import Scheduler
from teleop.session.summary import SessionSummary

from .vnet import EVE, MS, OP, Host, VirtualNet, params

TO_OFFSET = 5_000_000_000
SPIN_NS = 100_000


class Spy(Endpoint):
    """Records when each tick ran (the tick's number and the clock it was given)."""

    ticked: list[tuple[int, int]]  # (k, the clock it was given)
    early: list[int]  # ticks run before their deadline
    ran: list[int]  # ticks that ran (their model and record), of those asked for

    def __init__(self, *args: Any, **kw: Any) -> None:
        super().__init__(*args, **kw)
        self.ticked, self.early, self.ran = [], [], []

    def tick(self, k: int, now_ns: int) -> bool:
        self.ticked.append((k, now_ns))
        if self.params is not None and now_ns < self.t0_ns + k * round(self.params.dt * 1e9):
            self.early.append(k)
        ran = super().tick(k, now_ns)
        if ran:
            self.ran.append(k)
        return ran


def pair(
    net: VirtualNet, duration: float = 1.0, policy: TickPolicy | None = None, spin_ns: int = 0, **kw: Any
) -> tuple[Host, Host]:
    policy = policy or TickPolicy()
    to = net.teleoperator(offset_ns=TO_OFFSET, ticks=policy, spin_ns=spin_ns, cls=Spy)
    op = net.operator(params(duration=duration, **kw), ticks=policy, spin_ns=spin_ns, cls=Spy)
    return op, to


def sched(h: Host) -> Scheduler:
    """The scheduler that runs the host's ticks."""
    assert h.sched is not None
    return h.sched


def summary(h: Host) -> dict[str, Any]:
    (ev,) = h.of(SessionEnded)[-1:]
    return SessionSummary(ev.summary).document()


def loop_of(h: Host) -> LoopFigures:
    (ev,) = h.of(TicksEnded)
    loop: LoopFigures = ev.loop
    return loop


def test_a_timed_session_completes_every_tick_on_its_deadline_and_counts_its_departures() -> None:
    net = VirtualNet(0.5)
    op, to = pair(net, duration=1.0)
    net.seconds(8.0)
    for h in (op, to):
        assert h.ep.state == State.CLOSED
        s = summary(h)
        assert s["completed"] and s["end"] == "completed"
        loop = loop_of(h)
        (st,) = h.started()
        assert loop.ticks + loop.skipped == 1000 - st.k0 and loop.skipped == 0
        assert loop.overruns == 0
        # Called on each deadline exactly (virtual time): no lateness; the datagrams left then, or
        # after a grace wait for a payload (a tick due with its payload missing runs when it comes).
        assert loop.lateness_q.max_abs == 0
        assert loop.send_lateness_q.max_abs <= sched(h).grace_limit_ns
        assert loop.send_lateness_q.count == loop.ticks
        ks = [k for k, _ in h.ep.ticked]  # type: ignore[attr-defined]
        assert ks == list(range(st.k0, 1000)), "every tick once, in order"
    # The SessionEnded of each side comes after its TicksEnded (the ticks, then the linger).
    kinds = [type(e) for e in op.events]
    assert kinds.index(TicksEnded) < kinds.index(SessionEnded)


def test_the_early_tick_runs_in_the_spin_and_its_datagrams_leave_on_the_deadline() -> None:
    net = VirtualNet(0.5)
    op, to = pair(net, duration=1.0, spin_ns=SPIN_NS)
    net.seconds(8.0)
    for h in (op, to):
        assert summary(h)["completed"]
        loop = loop_of(h)
        # Never before the deadline (the percentiles are of absolute values: the early ones are
        # checked by the spy below), and after it only by a grace wait.
        assert loop.send_lateness_q.max_abs <= sched(h).grace_limit_ns
        ticked, early = h.ep.ticked, h.ep.early  # type: ignore[attr-defined]
        # All but the last tick (whose bye must not overtake it) and those waiting for a payload.
        assert len(early) >= 0.9 * len(ticked), (len(early), len(ticked))
        assert 999 not in early


def test_an_early_tick_changes_nothing_the_peers_see() -> None:
    """The same seeded session run from the deadline and in the spin: the same packets, counted
    alike on both sides, and the same figures of what was played."""
    out = []
    for spin in (0, SPIN_NS):
        net = VirtualNet(2.0, seed=3)
        op, to = pair(net, duration=1.0, spin_ns=spin)
        net.seconds(8.0)
        out.append([(summary(h)["sent"], summary(h)["received"]["packets"]) for h in (op, to)])
    assert out[0] == out[1]


def test_the_early_drain_feeds_while_each_datagram_ends_before_the_margin_and_the_rest_at_the_deadline() -> (
    None
):
    """``--tick-at deadline``: in the spin the endpoint feeds one datagram a call while its cost
    (learned from the times it is called at) still ends a margin before the deadline; the rest are
    fed, in order, at the deadline, before the tick."""
    net = VirtualNet(0.5)
    _op, to = pair(net, duration=4.0, policy=TickPolicy(early_tick=False))
    net.seconds(5.0, stop=lambda: to.ep.state == State.RUNNING and net.now > 2_000_000_000)
    ep, io, now = to.ep, sched(to), to.clock(net.now)
    while (deadline := io.get_timer()) is not None and deadline <= now:  # what is due at once
        io.handle_timer(now)
        io.datagrams_to_send(now)
    assert deadline is not None
    now = deadline - TickPolicy().early_ns + 10_000  # in the spin
    before = ep.foreign
    for i in range(20):
        io.receive_datagram(b"junk %d" % i, EVE, now)  # a stranger's: each fed is counted foreign
    assert ep.foreign == before, "queued while the ticks run, not fed"
    fed_at = []
    cost = 25_000  # each call comes this long after the last: what feeding one cost
    while now < deadline:
        n = ep.foreign
        io.handle_timer(now)
        if ep.foreign > n:
            fed_at.append(now)
        now += cost
    early = ep.foreign - before
    assert 1 <= early < 20
    assert all(t + cost <= deadline - EARLY_MARGIN_NS + 30_000 for t in fed_at)  # within its estimate
    assert fed_at[-1] <= deadline - EARLY_MARGIN_NS
    ticked = len(ep.ticked)  # type: ignore[attr-defined]
    io.handle_timer(deadline)
    assert ep.foreign - before == 20, "the rest at the deadline"
    assert len(ep.ticked) == ticked + 1  # type: ignore[attr-defined]


def test_grace_waits_for_a_late_payload_and_the_tick_runs_when_it_comes() -> None:
    """A payload due and missing at the deadline: the timer is the grace limit and a caller should
    wait on its socket (``awaiting_payload``); the datagram that brings it lets the tick run."""
    net = VirtualNet(0.5)
    _op, to = pair(net, duration=3.0)
    waits = []
    steps = 0
    while to.ep.state != State.CLOSED and steps < 200_000:
        steps += 1
        net.run(net.now + 50_000)
        if sched(to).awaiting_payload:
            t = sched(to).get_timer()
            assert t is not None
            waits.append(t - to.clock(net.now))
    s = summary(to)
    assert s["completed"]
    g = s["grace"]
    assert g["waits"] > 0 and waits
    assert max(waits) <= sched(to).grace_limit_ns
    assert g["waited_us_total"] <= g["waits"] * sched(to).grace_limit_ns / 1e3 + 1e-6
    assert g["missed"] < g["waits"], "some payloads came within grace and their tick ran then"


def test_a_stall_skips_the_ticks_it_missed_counted_and_the_session_clock_stays_true() -> None:
    net = VirtualNet(0.5)
    op, _to = pair(net, duration=3.0)
    net.seconds(5.0, stop=lambda: op.ep.state == State.RUNNING and net.now > 1_000_000_000)
    net.stall(OP, net.now + 100 * MS)
    net.seconds(8.0)
    loop = loop_of(op)
    (st,) = op.started()
    assert loop.skipped >= 80
    assert loop.ticks + loop.skipped == 3000 - st.k0
    ks = [k for k, _ in op.ep.ticked]  # type: ignore[attr-defined]
    assert ks == sorted(set(ks)), "no tick twice"


def test_admission_changes_are_events_the_kernel_filter_follows() -> None:
    net = VirtualNet(0.5)
    op, to = pair(net, duration=1.0)
    net.seconds(8.0)
    seen = [e.admission.strangers for e in to.of(AdmissionChanged)]
    # Listening: anyone; in session: strangers' handshakes only (busy); ended: anyone again.
    assert seen[0] == Strangers.ALL and Strangers.HANDSHAKE in seen
    assert [e.admission.strangers for e in op.of(AdmissionChanged)][-1] == Strangers.NONE
    for h in (op, to):
        adm = [e.admission for e in h.of(AdmissionChanged)]
        assert all(a != b for a, b in itertools.pairwise(adm)), "only changes"


class PacedDevice:
    """A device with its own clock: the test says when it ticked (``wait`` is the runner's)."""

    paced = True

    def __init__(self) -> None:
        self.holds = 0

    def wait(self, timeout_s: float) -> bool:
        raise AssertionError("the endpoint never waits on a device")

    def hold(self) -> None:
        self.holds += 1


def test_a_device_paced_session_runs_the_tick_its_clock_says_missed_ahead_and_silent() -> None:
    """Each call after the device ticked runs the session tick the clock says: the one due nearest
    (ticks it skipped are missed deadlines, counted, never run), never one twice, none while it is
    over a tick ahead (it holds); silent for a second, the session ends with a fault."""
    dev = PacedDevice()
    net = VirtualNet(0.5)
    _op, to = pair(net, duration=30.0)
    net.seconds(5.0, stop=lambda: to.ep.state == State.STARTING)
    (st,) = to.started()
    assert st.device is None  # the sim's devices do not pace; this one does, from here on:
    ep: Any = to.ep
    io: Any = sched(to)
    io._device = dev  # (a model's device: the test gives the scheduler a paced one, as a start would)
    period, k0 = 1_000_000, st.k0

    def device_tick(t: int) -> None:
        io.handle_timer(t)
        io.datagrams_to_send(t)
        while (timer := io.get_timer()) is not None and timer <= t:  # the settle, at once
            io.handle_timer(t)

    t = st.t0_ns + (k0 + 10) * period
    net.run(t - to.offset_ns)  # (the network delivers; it runs no tick of a paced endpoint)
    assert ep.ticked == []
    device_tick(t)  # ten ticks after the first: those are missed
    device_tick(t + 1)  # at once again: the next tick (a tick ahead at most)
    device_tick(t + 2)  # over a tick ahead: it holds
    assert [k for k, _ in ep.ticked] == [k0 + 10, k0 + 11] and dev.holds == 1
    device_tick(t + 6 * period)  # five device ticks missed: the tick the clock says
    assert [k for k, _ in ep.ticked] == [k0 + 10, k0 + 11, k0 + 16]
    assert io._loop.missed == 10 + 4 and io._loop.ahead == 1 and io._loop.ticks == 3
    timer = io.get_timer()
    assert timer == t + 6 * period + 1_000_000_000
    io.handle_timer(timer)  # silent for a second
    assert ep.state == State.LINGER and "did not tick for 1.0 s" in ep.fault_why
    assert any(isinstance(e, TicksEnded) for e in iter(io.next_event, None))


def test_figures_percentiles_are_of_the_deadline_instant() -> None:
    loop = LoopFigures(1_000_000)
    for i, late in enumerate([0, 10_000, 2_000_000, 5_000]):
        loop.started(late, i * 1_000_000 + late)
        loop.departed(i * 1_000_000 + late + 1_000, i * 1_000_000)
    assert loop.ticks == 4 and loop.overruns == 1
    assert np.isclose(loop.lateness_q.max_abs, 2_000_000)
    assert loop.send_lateness_q.count == 4


def test_a_takeover_and_a_ghost_run_on_timed_ticks_each_session_with_its_own_figures() -> None:
    """The operator dies mid-session; a new one takes the robot over once its link is lost (the
    old session's ticks end, replaced, the new one's start), and runs to its end.  Then a session
    whose operator never sends ends as a ghost, and the robot serves the next operator."""
    policy = TickPolicy()
    net = VirtualNet(1.0)
    _, to = pair(net, duration=8.0, spin_ns=SPIN_NS)
    net.seconds(6.0, stop=lambda: to.ep.state == State.RUNNING)
    net.seconds(1.0)
    net.kill(OP)
    net.seconds(0.3)
    op2 = net.operator(
        params(session=8, duration=2.0), offset_ns=3 * TO_OFFSET, ticks=policy, spin_ns=SPIN_NS
    )
    net.seconds(8.0)
    ends = to.of(SessionEnded)
    assert [e.reason.value for e in ends] == ["replaced", "completed"]
    assert summary(op2)["completed"] and summary(to)["params"]["session"] == 8
    old, new = (e.loop for e in to.of(TicksEnded))
    assert old is not new and new.ticks + new.skipped == 2000 - to.started()[1].k0
    assert old.send_lateness_q.count == old.ticks and new.send_lateness_q.count == new.ticks
    # A ghost (another robot process): its operator is gone once its start was confirmed.
    net = VirtualNet(1.0)
    to = net.teleoperator(offset_ns=TO_OFFSET, ticks=policy, spin_ns=SPIN_NS)
    ghost = net.operator(params(session=9, duration=0.0), ticks=policy)
    net.seconds(20.0, stop=lambda: ghost.ep.state != State.HANDSHAKE)
    net.kill(OP)
    net.seconds(10.0, stop=lambda: bool(to.of(SessionEnded)))
    assert to.of(SessionEnded)[-1].reason.value == "peer_silent" and to.ep.state == State.HANDSHAKE
    (ticks_ended,) = to.of(TicksEnded)
    assert ticks_ended.loop.ticks > 0
    op4 = net.operator(params(session=10, duration=1.0), ticks=policy, spin_ns=SPIN_NS)
    net.seconds(10.0)
    assert summary(op4)["completed"] and summary(to)["completed"] and summary(to)["params"]["session"] == 10


def test_an_early_tick_that_ends_the_session_still_counts_its_deadline() -> None:
    """An open session whose operator stops: the robot's tick that sees the bye ends it (often a
    tick run early); every tick run is in the loop's figures, as every one is in the log."""
    net = VirtualNet(0.5)
    op, to = pair(net, duration=0.0, spin_ns=SPIN_NS)
    net.seconds(6.0, stop=lambda: to.ep.state == State.RUNNING)
    net.seconds(0.5)
    sched(op).stop(op.clock(net.now))
    net.seconds(3.0)
    for h in (op, to):
        assert summary(h)["completed"], h.addr
        assert loop_of(h).ticks == len(h.ep.ran), h.addr  # type: ignore[attr-defined]
    assert summary(to)["end"] == "peer_bye" and to.ep.early  # type: ignore[attr-defined]


def test_a_robot_stopped_while_it_waits_for_a_payload_counts_only_the_ticks_it_ran() -> None:
    """Its operator falls silent, the robot's tick waits in grace, and a signal stops it there: that
    tick never runs, so the loop's figures do not count it (CI saw 1801 counted against 1800 logged)."""
    net = VirtualNet(0.5)
    _op, to = pair(net, duration=0.0)
    net.seconds(6.0, stop=lambda: to.ep.state == State.RUNNING)
    net.seconds(0.5)
    net.stall(OP, net.now + 10_000 * MS)  # silent: nothing more from the operator
    steps = 0
    while not sched(to).awaiting_payload and steps < 20_000:
        steps += 1
        net.run(net.now + 50_000)
    assert sched(to).awaiting_payload
    sched(to).stop(to.clock(net.now))
    net.seconds(2.0)
    assert summary(to)["end"] == "stopped"
    ran = to.ep.ran  # type: ignore[attr-defined]
    assert loop_of(to).ticks == len(ran)
