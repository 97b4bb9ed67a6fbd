"""Energy guard (observer + controller) and link supervision, driven with exact fake time."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from teleop.control.codecs import make_codec
from teleop.control.passivity import EnergyGuard
from teleop.control.wave import WaveImpedance
from teleop.devices.models import LtiEnvironment, StepHuman
from teleop.session import wire
from teleop.session.node import OperatorNode, PortOptions, TeleoperatorNode

DT = 1e-3


@settings(max_examples=100, deadline=None)
@given(
    hnp.arrays(np.float64, (200, 2), elements=st.floats(-10, 10)),
    st.lists(st.floats(0, 1e-2), min_size=200, max_size=200),
)
def test_controller_never_plays_more_than_reported(x: np.ndarray, increments: list[float]) -> None:
    """Whatever is proposed, with the controller the played energy stays within what was reported."""
    g = EnergyGuard(DT, controller=True)
    reported = 0.0
    for k in range(200):
        reported += increments[k]
        g.sent(reported)
        y = g.admit(x[k])
        assert np.all(np.abs(y) <= np.abs(x[k]) + 1e-15)  # only scales down
        assert g.played <= reported + 1e-12
    assert g.report.min_margin >= -1e-12
    assert g.report.energy_dissipated >= 0


def test_observer_sees_violations_without_controller() -> None:
    g = EnergyGuard(DT, controller=False)
    g.sent(1e-6)
    y = g.admit(np.array([1.0]))  # 0.5 mJ proposed, 1 uJ available
    assert y[0] == 1.0 and g.report.violations == 1 and g.report.controller_active_ticks == 0
    assert g.report.min_margin == pytest.approx(1e-6 - 0.5e-3)


def test_controller_scales_to_the_budget() -> None:
    g = EnergyGuard(DT, controller=True)
    g.sent(0.25e-3)
    y = g.admit(np.array([1.0, 0.0]))
    assert y[0] == pytest.approx(np.sqrt(0.5)) and g.played == pytest.approx(0.25e-3)
    assert g.report.violations == 1 and g.report.controller_active_ticks == 1
    assert g.report.energy_dissipated == pytest.approx(0.25e-3)
    g.sent(0.1e-3)  # an older (reordered) report never lowers the budget
    assert g.reported_in == 0.25e-3


def _pair(options: PortOptions, spec: str = "none") -> tuple[OperatorNode, TeleoperatorNode]:
    w = WaveImpedance.of(1.0, 1)
    c = make_codec(spec, 1, 2.0)
    op = OperatorNode(
        human=StepHuman(1, DT, t_step=0.0), wave=w, tx=c, rx=c, session=1, dt=DT, options=options
    )
    to = TeleoperatorNode(
        environment=LtiEnvironment(1, DT), wave=w, tx=c, rx=c, session=1, dt=DT, options=options
    )
    return op, to


def _run(op: OperatorNode, to: TeleoperatorNode, ticks: range, deliver: bool) -> None:
    for k in ticks:
        p = op.tick(k * DT)
        if deliver and p is not None:
            to.receive(wire.encode(p))
        q = to.tick(k * DT)
        if deliver and q is not None:
            op.receive(wire.encode(q))


def test_hold_on_loss_violates_without_controller_and_not_with_it() -> None:
    for controller in (False, True):
        op, to = _pair(PortOptions(on_loss="hold", controller=controller, link_timeout=10.0))
        _run(op, to, range(0, 300), deliver=True)
        _run(op, to, range(300, 400), deliver=False)  # total loss: the TO holds g_r
        true_margin = op.energy_sent - to.energy_played
        if controller:
            assert to.passivity.violations > 0 and to.passivity.controller_active_ticks > 0
            assert true_margin >= -1e-12 and to.passivity.min_margin >= -1e-12
        else:
            assert to.passivity.violations > 90  # it saw every held tick generate energy
            # It played more than every delivered packet carried: energy from nowhere.
            assert to.energy_played > to.peer_energy_sent + 1e-4
            assert to.passivity.min_margin < -1e-4


def test_link_lost_safe_state_and_recovery() -> None:
    op, to = _pair(PortOptions(link_timeout=0.05, fade_time=0.1))
    _run(op, to, range(0, 500), deliver=True)
    assert to.passivity.link_lost_events == 0 and to.coupling == 1.0
    _run(op, to, range(500, 800), deliver=False)
    assert to.link_lost and op.link_lost
    assert to.passivity.link_lost_events == 1 and op.passivity.link_lost_events == 1
    assert to.coupling == 0.0 and op.coupling == 0.0  # faded out after 50 ms + 100 ms
    assert (
        np.all(to.v == 0.0) and np.all(op.f == 0.0) and np.all(to.wave_out == 0.0)
    )  # safe: no motion, no force
    _run(op, to, range(800, 1100), deliver=True)
    assert not to.link_lost and to.coupling == 1.0 and op.coupling == 1.0  # resumed
    assert 240 <= to.passivity.link_lost_ticks <= 260  # 300 silent ticks minus the 50 ms timeout
    assert op.energy_sent - to.energy_played >= -1e-12


def test_sparse_codec_is_not_a_lost_link() -> None:
    op, to = _pair(PortOptions(link_timeout=0.05), spec="eds:100")
    _run(op, to, range(0, 1000), deliver=True)
    assert to.passivity.link_lost_events == 0 and op.passivity.link_lost_events == 0


def test_bad_options() -> None:
    with pytest.raises(ValueError, match="on_loss must be one of zero, hold"):
        PortOptions(on_loss="repeat")


def test_energy_epochs_never_carry_budget_across_incarnations() -> None:
    g = EnergyGuard(DT, controller=True)
    g.sent(1.0)
    g.admit(np.array([1.0]))
    # The peer restarted: its reports start again from 0, the old budget is gone.
    g.new_epoch(joined_late=False)
    assert g.margin == 0.0
    assert g.admit(np.array([1.0]))[0] == 0.0  # nothing reported yet in this epoch
    g.sent(0.25e-3)
    assert g.admit(np.array([1.0]))[0] == pytest.approx(np.sqrt(0.5))
    # Joining late: the first report is the origin, whatever the sender sent before.
    h = EnergyGuard(DT, controller=True)
    h.new_epoch(joined_late=True)
    h.sent(123.0)
    assert h.margin == 0.0
    h.sent(123.0 + 0.5e-3)
    assert h.admit(np.array([1.0]))[0] == pytest.approx(1.0)


def test_a_report_beyond_what_the_wire_can_carry_is_clamped_and_counted() -> None:
    """Defence in depth: even an authenticated forgery cannot grant a budget out of nothing."""
    g = EnergyGuard(1e-3, max_power=4.0, burst_s=0.2)  # 2 DoF, range 2: 1/2 * 2 * 2**2 W
    g.sent(1e-3, now=0.0)
    assert g.reported_in == 1e-3 and g.report.energy_reports_clamped == 0
    g.sent(1e300, now=0.001)  # the attack of issue 11: one packet claiming 1e300 J
    assert g.report.energy_reports_clamped == 1
    assert g.reported_in <= 1e-3 + 4.0 * 0.2 + 1e-12  # at most the bucket's depth
    g.sent(1e300, now=0.002)
    assert g.reported_in <= 1e-3 + 4.0 * 0.201 + 1e-12  # then only what 1 ms can carry
    assert g.report.energy_reports_clamped == 2


def test_genuine_reports_are_never_clamped() -> None:
    """A sender at full power, its reports delayed and bunched by jitter, stays within the bound."""
    g = EnergyGuard(1e-3, max_power=4.0, burst_s=0.2)
    rng = np.random.default_rng(1)
    sent = np.cumsum(np.full(5000, 4.0 * 1e-3))  # saturated waves every tick
    arrival = np.arange(5000) * 1e-3 + rng.uniform(0, 0.15, 5000)  # up to 150 ms of jitter
    order = np.argsort(arrival)
    for i in order:
        g.sent(float(sent[i]), now=float(arrival[i]))
    assert g.report.energy_reports_clamped == 0 and g.reported_in == sent[-1]
