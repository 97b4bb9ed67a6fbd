"""The robot's limits hold on what its device is finally commanded (issue 45): under wave variables
and TDPA, with robots that sense their force a tick late (``Z = 0``) and robots that report their
impedance, in contacts from 10 N/m to 10^6 N/m, through a link loss in contact and a rejoin.

The figures held (``teleop.control.confine``): ``|v| <= max_velocity``; the force past
``max_force`` only on the first tick of a contact the robot had not met, by at most ``K
max_velocity dt``, relieved on the next tick; no tick-rate oscillation (sign changes of the
command) under TDPA beyond wave variables' on the same robot; passive."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import teleop.offline.sim as sim
from teleop.control.confine import CONTACT_MEMORY_S, MAX_STIFFNESS, Confinement, confined
from teleop.session.events import SessionEnded
from teleop.session.node import TeleoperatorNode
from teleop.session.settings import DEFAULT_ENVELOPE, Envelope

from .contact_devices import ImpedanceSpring, SensedSpring
from .vnet import TO, VirtualNet, params

VMAX, FMAX, DT = 0.5, 10.0, 1e-3
LIMITS = Envelope(max_velocity=VMAX, max_force=FMAX, min_b=1.0)
STIFFNESS = (10.0, 1e3, 1e4, 1e6)
HAND = "tests.contact_devices:PushingHand:5"


def _flips(v: Any) -> int:
    """Sign changes of the command on DoF 0, among its samples faster than 1 % of the limit."""
    big = v[np.abs(v[:, 0]) > 0.01 * VMAX, 0]
    return int(np.count_nonzero(np.diff(np.sign(big))))


def _over(forces: Any) -> Any:
    """The ticks whose force is past the limit on some DoF, and their largest excess (N)."""
    f = np.abs(np.asarray(forces)).max(axis=1)
    return np.flatnonzero(f > FMAX * (1 + 1e-9)), f


# --- the rule, on its own -----------------------------------------------------------------------

_v = st.floats(-100.0, 100.0, allow_nan=False)


@settings(max_examples=400, deadline=None)
@given(
    v=st.lists(_v, min_size=3, max_size=3),
    f0=st.lists(st.floats(-1e4, 1e4, allow_nan=False), min_size=3, max_size=3),
    z=st.lists(st.one_of(st.just(0.0), st.floats(1e-6, 1e4)), min_size=3, max_size=3),
    vmax=st.floats(0.01, 3.0),
    fmax=st.floats(0.1, 100.0),
)
def test_the_rule_bounds_the_velocity_and_the_force_it_can_predict(
    v: list[float], f0: list[float], z: list[float], vmax: float, fmax: float
) -> None:
    out, _ = confined(v, f0, z, vmax, fmax)
    for vi, fi, zi, wi in zip(v, f0, z, out, strict=True):
        assert abs(wi) <= vmax
        fe = fi + zi * wi
        if abs(fi) <= fmax:  # within the limit: slowed, never reversed, and it stays within
            assert abs(wi) <= abs(vi) + 1e-12 and wi * vi >= 0.0
            if zi > 0.0:
                assert abs(fe) <= fmax * (1 + 1e-9) + 1e-9
        elif zi > 0.0:  # past it: relieved toward it, at most at the velocity limit
            assert abs(fe) <= abs(fi) or fe * fi < 0.0
            assert abs(fe) <= fmax * (1 + 1e-9) + 1e-9 or abs(wi) == vmax
        else:  # past it with no feedthrough known: no push further into it
            assert wi * fi <= 0.0


def _tick(c: Confinement, f: float, v: float) -> Any:
    """One tick of a 1-DoF device with no feedthrough reporting ``f``, commanded ``v``: the
    stiffness the confinement solves with."""
    zero = np.zeros(1)
    z = c.effective(np.array([f]), zero)
    c.command(np.array([v]), np.array([f]), z)
    return z


@settings(max_examples=200, deadline=None)
@given(k=st.floats(100.0, MAX_STIFFNESS), v=st.floats(1e-4, 1.0), x0=st.floats(1e-3, 0.01))
def test_a_tick_of_motion_within_a_linear_contact_teaches_its_stiffness(
    k: float, v: float, x0: float
) -> None:
    """In contact over a whole tick the force moved by exactly ``K v dt``, however small: the
    next tick solves with ``K dt`` (least squares of the ticks in contact)."""
    c = Confinement(1, DT, max_velocity=1.0, max_force=1e9)
    c._floor = 0.0  # a noiseless sensor (the floor is the sensor's noise, 2 % of max_force)
    _tick(c, k * x0, v)
    z = _tick(c, k * (x0 + v * DT), 0.0)
    assert z[0] == pytest.approx(k * DT, rel=1e-9)


def test_entering_a_contact_within_a_tick_is_a_lower_bound_and_the_contact_corrects_it() -> None:
    k, v = 1e4, 0.5
    c = Confinement(1, DT, max_velocity=1.0, max_force=FMAX)
    _tick(c, 0.0, v)  # free, then half the tick's motion in contact
    z = _tick(c, k * v * DT / 2, 0.001)
    assert z[0] == pytest.approx(k * DT / 2)
    z = _tick(c, k * (v * DT / 2 + 0.001 * DT), 0.0)  # a small motion within it: the true one
    assert z[0] == pytest.approx(k * DT)


def test_free_motion_forgets_a_contact_within_its_memory() -> None:
    c = Confinement(1, DT, max_velocity=1.0, max_force=FMAX)
    _tick(c, 0.0, 0.5)
    assert _tick(c, 5.0, -0.5)[0] == pytest.approx(10.0)  # 5 N in 0.5 mm: 1e4 N/m
    for _ in range(round(5 * CONTACT_MEMORY_S / DT)):
        z = _tick(c, 0.0, -0.5)
    assert z[0] <= 10.0 * math.exp(-5) * 1.01


def test_a_device_that_reports_its_impedance_keeps_it_untouched() -> None:
    c = Confinement(2, DT, max_velocity=1.0, max_force=FMAX)
    z = np.full(2, 40.0)
    z.setflags(write=False)
    for f in (0.0, 5.0, 9.0):
        assert c.effective(np.full(2, f), z) is z
        c.command(np.full(2, 0.3), np.full(2, f), z)


# --- the simulation: every kind of robot, every stiffness, both architectures -------------------


def _run(passivity: str, robot: str, k: float, dof: int = 2) -> tuple[dict[str, Any], Any, Any]:
    """A 0.8 s sim of the hand pushing at 5 m/s into the spring; returns the summary and what the
    robot's device was commanded and felt."""
    ports: list[Any] = []
    make = sim._ports

    def keep(cfg: sim.SimConfig) -> Any:
        got = make(cfg)
        ports.append(got)
        return got

    env = dataclasses.replace(DEFAULT_ENVELOPE, max_velocity=VMAX, max_force=FMAX, min_b=1.0)
    cfg = sim.SimConfig(
        scenario="step",
        codec="cq:16",
        passivity=passivity,  # type: ignore[arg-type]
        b=5.0,
        dof=dof,
        duration=0.8,
        hsi=HAND,
        robot=f"tests.contact_devices:{robot}:{k:g}",
        envelope=env,
    )
    sim._ports = keep
    try:
        res = sim.run_case(cfg)
    finally:
        sim._ports = make
    dev = ports[0][1].node.environment
    return res.summary, np.array(dev.commanded), np.array(dev.forces)


@pytest.mark.parametrize("k", STIFFNESS)
@pytest.mark.parametrize("robot", ["SensedSpring", "ImpedanceSpring"])
@pytest.mark.parametrize("passivity", ["wave", "tdpa"])
def test_a_hand_pushing_at_5_m_s_into_a_spring_meets_the_limits(passivity: str, robot: str, k: float) -> None:
    summary, v, f = _run(passivity, robot, k)
    assert np.abs(v).max() <= VMAX * (1 + 1e-12)
    over, mag = _over(f)
    # one contact: past the limit on its first tick at most, by at most K vmax dt
    assert len(over) <= 1
    assert mag.max() <= FMAX + k * VMAX * DT * (1 + 1e-9)
    assert mag[-1] > 0.5 * min(FMAX, k * 0.05)  # the contact is still being pushed at the end
    assert summary["passive"]
    if passivity == "tdpa":
        assert _flips(v) <= _flips(_run("wave", robot, k)[1]) + 1


def test_a_robot_that_senses_a_stiff_contact_late_no_longer_diverges_under_tdpa() -> None:
    """What main measured: with Z = 0 at 10^4 N/m, TDPA commanded 263.6 m/s and 1391 N."""
    summary, v, f = _run("tdpa", "SensedSpring", 1e4, dof=1)
    assert np.abs(v).max() <= VMAX and np.abs(f).max() <= FMAX * (1 + 1e-9)
    assert _flips(v) <= 1 and summary["passive"]


# --- a session: a link loss in contact, then the robot killed and rejoined ------------------------


@pytest.mark.parametrize(
    ("robot", "k"), [("SensedSpring", 1e4), ("SensedSpring", 1e6), ("ImpedanceSpring", 1e6)]
)
@pytest.mark.parametrize("passivity", ["wave", "tdpa"])
def test_the_limits_hold_through_a_link_loss_in_contact_and_a_rejoin(
    passivity: str, robot: str, k: float
) -> None:
    net = VirtualNet(1.0)
    device = f"tests.contact_devices:{robot}:{k:g}"
    p = params(codec="cq:16", b=5.0, passivity=passivity, duration=2.2, scenario="step")
    robots = [net.teleoperator(device=device, limits=LIMITS)]
    op = net.operator(p, device=HAND)
    net.seconds(0.4)  # in contact by now (GAP at 0.5 m/s: 10 ms)
    net.dark.append((net.now, net.now + 500_000_000))  # 0.5 s with no datagram either way
    net.seconds(0.7)
    net.kill(TO)
    net.seconds(0.15)
    robots.append(net.teleoperator(device=device, limits=LIMITS, offset_ns=5_000_000_000))
    net.seconds(2.5, stop=lambda: bool(op.of(SessionEnded)))
    assert op.of(SessionEnded)
    nodes = [h.ep.port.node for h in robots if h.ep.port is not None]
    assert len(nodes) == 2, "the robot rejoined"
    for node in nodes:
        assert isinstance(node, TeleoperatorNode)
        dev = node.environment
        assert isinstance(dev, (SensedSpring, ImpedanceSpring))
        v, f = np.array(dev.commanded), np.array(dev.forces)
        assert len(v) > 300 and np.abs(v).max() <= VMAX * (1 + 1e-12)
        over, mag = _over(f)
        # each robot process meets the contact anew: its first tick in it at most
        assert len(over) <= 1 and mag.max() <= FMAX + k * VMAX * DT * (1 + 1e-9)
        assert node.guard.margin >= -1e-9


# --- TDPA's robot, tick by tick on random signals --------------------------------------------------


class _Scripted:
    """A robot device whose ``affine`` plays a script of ``(f0, Z)`` and keeps what it was commanded."""

    def __init__(self, script: list[tuple[list[float], list[float]]]) -> None:
        self.script, self.k = script, 0
        self.commanded: list[Any] = []

    def affine(self, now: float) -> tuple[Any, Any]:
        f0, z = self.script[self.k % len(self.script)]
        self.k += 1
        return np.array(f0), np.array(z)

    def advance(self, now: float, v: Any, f: Any) -> None:
        self.commanded.append(np.array(v))


_f0 = st.floats(-500.0, 500.0, allow_nan=False)


@settings(max_examples=150, deadline=None)
@given(
    steps=st.lists(
        st.tuples(
            st.lists(st.floats(-5.0, 5.0), min_size=2, max_size=2),  # the velocity received
            st.lists(_f0, min_size=2, max_size=2),
            st.lists(st.one_of(st.just(0.0), st.floats(0.0, 1e3)), min_size=2, max_size=2),
            st.floats(0.0, 0.05),  # J the operator reports more this tick
        ),
        min_size=1,
        max_size=40,
    ),
    vmax=st.floats(0.05, 2.0),
    fmax=st.floats(1.0, 100.0),
)
def test_tdpas_robot_on_random_signals_stays_within_its_limits_and_its_budget(
    steps: list[Any], vmax: float, fmax: float
) -> None:
    """Whatever it is sent and whatever its device reports: the device is never commanded past
    ``max_velocity``, and the network's books hold ``E_out <= E_in`` (the envelope acts on the
    device's side of the controller, never on the books)."""
    from teleop.session.port import make_node
    from tests.vnet import params as vparams

    node = make_node(
        "teleoperator",
        scenario="step",
        dof=2,
        dt=DT,
        b=5.0,
        codec="none",
        full_scale=2.0,
        session=1,
        options=vparams(passivity="tdpa").port_options(),
    )
    node.confine(Envelope(max_velocity=vmax, max_force=fmax, min_b=1.0))
    assert isinstance(node, TeleoperatorNode)
    dev = _Scripted([(f0, z) for _, f0, z, _ in steps])
    node.environment = dev
    received = iter([np.array(v) for v, _, _, _ in steps])
    node.decoder.next = lambda: next(received)  # type: ignore[method-assign]
    reported = 0.0
    for k, (_, _, _, more) in enumerate(steps):
        reported += more
        node.guard.sent(reported, k * DT)
        node.tick(k * DT)
        assert np.abs(dev.commanded[-1]).max() <= vmax * (1 + 1e-12)
        assert node.guard.margin >= -1e-9 * (1 + reported)
