"""The robot is sovereign (issue 34): its envelope refuses unsafe proposals, saturates what it is
commanded, bounds its energy guard by its own limits, and a device's nonsense never reaches the
books.  Virtual time and the simulation only; the command line's side is in test_cli_validation."""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from teleop.control.wave import WaveImpedance
from teleop.offline.sim import SimConfig, run_case
from teleop.session.events import Failed, HelloRejected, SessionEnded
from teleop.session.node import TeleoperatorNode
from teleop.session.port import make_node
from teleop.session.protocol import Failure, SessionParams
from teleop.session.settings import DEFAULT_ENVELOPE, SETTINGS, Envelope, Passivity, settings_table

from .vnet import VirtualNet, params


def _refused(p: SessionParams, env: Envelope = DEFAULT_ENVELOPE) -> str:
    why = env.check(p)
    assert why is not None, f"{p} was not refused"
    return why


# --- the rules, one by one ------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("change", "field", "flag"),
    [
        ({"full_scale": 2.5}, "range", "--max-range"),
        ({"codec": "cq:16:1000"}, "codec", "--max-range"),  # CQ's RANGE, the 170 m/s attack
        ({"b": 0.001}, "b", "--min-b"),
        ({"b": 200.0}, "b", "--max-b"),
        ({"link_timeout": 10.0}, "link_timeout", "--max-link-timeout"),
        ({"controller": False, "on_loss": "zero"}, "controller", "--allow-no-controller"),
        ({"playout": "300"}, "playout", "--max-playout"),
        ({"dt": 0.002}, "dt", "period"),
    ],
)
def test_each_unsafe_proposal_is_refused_naming_the_field_and_the_limit(
    change: dict[str, Any], field: str, flag: str
) -> None:
    why = _refused(params(**change))
    assert why.startswith(field) and flag in why
    assert "\n" not in why


def test_a_value_just_above_a_limit_never_reads_as_equal_to_it() -> None:
    """Issue 49: %g printed "range 2 exceeds this robot's limit 2" for 2.0000001 against 2."""
    why = _refused(params(full_scale=2.0000001), dataclasses.replace(DEFAULT_ENVELOPE, max_range=2.0))
    assert why.startswith("range 2.0000001 exceeds this robot's limit 2 (--max-range)"), why
    why = _refused(params(b=20.000000000000004), dataclasses.replace(DEFAULT_ENVELOPE, max_b=20.0))
    assert why.startswith("b 20.000000000000004 N s/m exceeds this robot's limit 20 N s/m"), why
    assert _refused(params(full_scale=2.5)).startswith("range 2.5 exceeds this robot's limit 2 ")  # (short)


@given(st.floats(allow_nan=False, allow_infinity=False), st.floats(allow_nan=False, allow_infinity=False))
def test_a_reasons_numbers_are_exact(a: float, b: float) -> None:
    """Each number a reason prints reads back as itself, so two different ones never print alike."""
    from teleop.session.settings import _num

    assert float(_num(a)) == a
    if a != b:
        assert _num(a) != _num(b)


def test_cq_range_under_tdpa_is_held_to_the_robots_power_ranges() -> None:
    why = _refused(params(codec="cq:16:50", passivity="tdpa", full_scale=2.0))
    assert why.startswith("codec") and "--max-range" in why
    assert DEFAULT_ENVELOPE.check(params(codec="cq:16", passivity="tdpa")) is None


def test_a_dof_beyond_the_robot_device_is_refused_not_a_crash() -> None:
    from teleop.devices import max_dof

    why = _refused(params(dof=6), Envelope(max_dof=max_dof("mujoco", "robot")))
    assert why.startswith("dof 6 exceeds this robot's limit 3") and "--robot" in why
    assert max_dof("franka:127.0.0.1", "robot") == 3 and max_dof(None, "robot") == 64


def test_choices_are_the_robots() -> None:
    env = Envelope(passivity=(Passivity.WAVE,), on_loss=("zero", "conceal"))
    assert "--allow-passivity" in _refused(params(passivity="tdpa"), env)
    assert "--allow-on-loss" in _refused(params(on_loss="hold"), env)
    # Without the controller only what the robot named there: zero unless it said more.
    lax = Envelope(uncontrolled_on_loss=("zero",))
    assert "without the passivity controller" in _refused(params(controller=False, on_loss="hold"), lax)
    assert lax.check(params(controller=False, on_loss="zero")) is None
    assert (
        Envelope(uncontrolled_on_loss=("zero", "hold")).check(params(controller=False, on_loss="hold"))
        is None
    )


def test_a_proposal_within_the_envelope_passes() -> None:
    assert DEFAULT_ENVELOPE.check(params()) is None
    assert DEFAULT_ENVELOPE.check(params(scenario="step", b=1.0, codec="ids:2", link_timeout=0.12)) is None
    # The longest link timeout it takes needs a robot that acts alone that long (--max-act-alone).
    longest = params(scenario="step", b=1.0, codec="ids:2", link_timeout=0.25)
    assert "--max-act-alone" in (DEFAULT_ENVELOPE.check(longest) or "")
    assert Envelope(max_act_alone_ms=352.0).check(longest) is None  # 2 + 250 + 100 ms


def test_an_envelope_with_nonsense_limits_is_refused() -> None:
    for bad in ({"max_range": math.nan}, {"min_b": 30.0}, {"max_velocity": -1.0}, {"passivity": ()}):
        with pytest.raises(ValueError):
            Envelope(**bad)


# --- one settings table -------------------------------------------------------------------------


def test_the_hello_carries_exactly_the_tables_keys_in_its_order() -> None:
    p = params(rate_cap=64e3, playout="2", variation=0.5, passivity="tdpa", codec="pdp:1")
    msg = p.to_msg()
    assert list(msg) == [s.key for s in SETTINGS]
    assert SessionParams.from_msg(msg) == p
    # every field a session agrees on is in the table, once
    fields = {f.name for f in dataclasses.fields(SessionParams)}
    assert sorted(s.field for s in SETTINGS) == sorted(fields)


def test_the_docs_table_is_generated_from_it() -> None:
    table = settings_table()
    for s in SETTINGS:
        assert f"| {s.field} | `{s.key}` |" in table
    assert "--max-link-timeout" in table and "250 ms" in table


# --- in session: refused in one line on both sides ---------------------------------------------


def test_a_refused_proposal_is_one_line_on_both_sides() -> None:
    net = VirtualNet(1.0)
    to = net.teleoperator()
    op = net.operator(params(codec="cq:16:1000"))
    net.seconds(2.0)
    (f,) = op.of(Failed)
    assert f.reason == Failure.REJECTED and "--max-range" in f.detail and "\n" not in f.detail
    assert not to.started()
    (rejected,) = to.of(HelloRejected)
    assert rejected.why.startswith("codec cq:16:1000") and "\n" not in rejected.why


def test_an_operator_that_dies_leaves_the_robot_commanded_no_longer_than_its_cap() -> None:
    """The operator asks the longest link timeout the robot allows, then dies: the robot's
    coupling is gone within that cap plus its fade, and it played no energy that was not sent."""
    env = Envelope(max_link_timeout=0.1)
    net = VirtualNet(1.0)
    to = net.teleoperator(limits=env)
    refused = net.operator(params(link_timeout=10.0), addr=("127.0.0.1", 40001))
    net.seconds(1.0)
    assert refused.of(Failed) and "--max-link-timeout" in refused.of(Failed)[0].detail
    net.kill(refused.addr)
    op = net.operator(params(link_timeout=0.1, duration=0.0))
    net.seconds(2.0)
    assert to.started()
    net.kill(op.addr)
    died = net.now
    node = to.ep.port.node  # type: ignore[union-attr]
    # eds:50: one payload interval (50 ms) + the timeout + the sparse margin, then the fade (0.1 s)
    bound_s = 0.05 + max(env.max_link_timeout, 0.05 + 0.010) + 0.1
    while node.coupling > 0.0:
        net.seconds(0.001)
        assert (net.now - died) / 1e9 <= bound_s + 0.002, "the robot still acts on a dead link"
    assert to.ep.port.node.guard.margin >= -1e-12  # type: ignore[union-attr]


# --- saturation is passive ----------------------------------------------------------------------

_f = st.floats(-50.0, 50.0, allow_nan=False)


@pytest.mark.filterwarnings("error::RuntimeWarning")  # the robot's tick computes no NaN it warns of
@settings(max_examples=300, deadline=None)
# A subnormal impedance where the command is 0, with another DoF pushing: inf * 0 once warned.
@example(g=[50.0, 1.0, 0.0], f0=[0.0, 2.0, 0.0], z=[100.0, 5e-324, 0.0], b=2.0, vmax=2.0, fmax=10.0)
@given(
    g=st.lists(_f, min_size=3, max_size=3),
    f0=st.lists(st.floats(-200.0, 200.0, allow_nan=False), min_size=3, max_size=3),
    z=st.lists(st.floats(0.0, 500.0, allow_nan=False), min_size=3, max_size=3),
    b=st.floats(1.0, 20.0),
    vmax=st.floats(0.01, 2.0),
    fmax=st.floats(0.1, 100.0),
)
def test_saturation_is_passive_and_within_the_envelope(
    g: list[float], f0: list[float], z: list[float], b: float, vmax: float, fmax: float
) -> None:
    node = make_node(
        "teleoperator",
        scenario="protocol",
        dof=3,
        dt=1e-3,
        b=b,
        codec="none",
        full_scale=2.0,
        session=1,
        options=params().port_options(),
    )
    node.confine(Envelope(max_velocity=vmax, max_force=fmax, min_b=1.0, max_b=20.0))
    w = WaveImpedance.of(b, 3)
    ga, f0a, za = np.array(g), np.array(f0), np.array(z)
    v = (w.sqrt2b * ga - f0a) / (w.b + za)  # the port's solve at full coupling (teleop.session.node)
    f = f0a + za * v
    assert isinstance(node, TeleoperatorNode) and node.confinement is not None
    cut = node._confined(node.confinement, v, f0a, za)
    vs, fs, fw = cut if cut is not None else (v, f, f)
    h = w.to_wave_out(ga, fw)
    # per DoF: what the channel gives the port covers what the robot gives its environment
    assert np.all(0.5 * (ga**2 - h**2) >= vs * fs - 1e-9 * (1 + np.abs(vs * fs)))
    assert np.all(np.abs(vs) <= vmax * (1 + 1e-12))
    within = np.abs(f0a) <= fmax
    # within the limit: slowed, never reversed; past it: relieved (the force moves back toward it)
    assert np.all(~within | ((np.abs(vs) <= np.abs(v)) & (vs * v >= 0.0)))
    assert np.all(within | (np.abs(fs) <= np.abs(f0a) + 1e-9) | (fs * f0a < 0.0))
    pushing = fs * vs > 0.0
    assert np.all(~pushing | (np.abs(fs) <= fmax * (1 + 1e-9)))


@pytest.mark.parametrize("passivity", ["wave", "tdpa"])
def test_the_robot_stays_within_its_velocity_when_the_operator_pushes_past_it(passivity: Passivity) -> None:
    env = Envelope(max_range=0.5, max_velocity=0.3, max_force=50.0)
    codec = "none" if passivity == "wave" else "pdp:1"
    r = run_case(SimConfig(codec=codec, scenario="step", full_scale=0.5, passivity=passivity, envelope=env))
    assert float(np.max(np.abs(r.trace.v_to))) <= 0.3 + 1e-12
    assert r.summary["counters"]["teleoperator"]["saturated"] > 0
    assert r.summary["passive"]


@pytest.mark.parametrize("passivity", ["wave", "tdpa"])
def test_the_robot_pushes_a_wall_no_harder_than_its_max_force(passivity: Passivity) -> None:
    """The protocol task's wall pushes reach about 7 N (wave) and 1.5 N (TDPA): a robot whose
    envelope says 1 N is slowed into the wall, never reversed, and stays passive."""
    env = Envelope(max_force=1.0)
    r = run_case(SimConfig(codec="none", scenario="protocol", passivity=passivity, envelope=env))
    pushing = r.trace.f_to * r.trace.v_to > 0.0
    assert float(np.max(np.abs(r.trace.f_to[pushing]))) <= 1.0 + 1e-9
    assert r.summary["counters"]["teleoperator"]["saturated"] > 0
    assert r.summary["passive"]


def test_the_robots_guard_is_bounded_by_its_own_range_not_the_sessions() -> None:
    node = make_node(
        "teleoperator",
        scenario="protocol",
        dof=2,
        dt=1e-3,
        b=20.0,
        codec="none",
        full_scale=2.0,
        session=1,
        options=params().port_options(),
    )
    node.confine(Envelope(max_range=1.0))
    assert node.guard.max_power == pytest.approx(0.5 * 2 * 1.0**2)


# --- a device is a peer we do not trust either ----------------------------------------------------


@functools.cache
def _clean_forward_packets(cfg: SimConfig) -> int:
    """The forward packets of a run with well-behaved devices: the same run for either faulty side,
    so run once per config (the simulation is deterministic)."""
    return int(run_case(cfg).summary["directions"]["forward"]["packets"])


@pytest.mark.parametrize("passivity", ["wave", "tdpa"])
@pytest.mark.parametrize("side", ["robot", "hsi"])
def test_a_device_that_says_nan_costs_only_the_ticks_it_covers(side: str, passivity: Passivity) -> None:
    bad = "300,301,700,1200"
    device = f"tests.faulty_devices:Faulty{'Robot' if side == 'robot' else 'Hsi'}:{bad}"
    codec = "eds:50" if passivity == "wave" else "pdp:1"
    base = SimConfig(codec=codec, scenario="protocol", duration=2.0, passivity=passivity)
    faulty = (
        dataclasses.replace(base, robot=device) if side == "robot" else dataclasses.replace(base, hsi=device)
    )
    r = run_case(faulty)
    clean_packets = _clean_forward_packets(base)
    role = "teleoperator" if side == "robot" else "operator"
    assert r.summary["counters"][role]["device_stale"] == 4
    assert r.summary["passive"] and math.isfinite(r.summary["I"])
    for key in ("v_hsi", "f_hsi", "v_to", "f_to", "margin_fwd", "margin_bwd"):
        assert np.all(np.isfinite(getattr(r.trace, key)))
    # The link never noticed: every packet the clean run carried was carried and accepted.
    for role_ in ("operator", "teleoperator"):
        assert r.summary["counters"][role_]["malformed"] == 0
    assert r.summary["directions"]["forward"]["packets"] > 0.9 * clean_packets
    for d in ("forward", "backward"):
        assert r.summary["passivity"][d]["link_lost_events"] == 0


def test_a_robot_that_says_nan_in_a_session_keeps_the_link() -> None:
    """In a two-endpoint session (virtual time): NaN and inf from the robot's device neither lose
    the link nor make a book NaN; the operator accepts every backward packet."""
    net = VirtualNet(1.0)
    to = net.teleoperator(device="tests.faulty_devices:FaultyRobot:500,501,900")
    op = net.operator(params(duration=2.0))
    net.seconds(4.0)
    for h in (op, to):
        (ended,) = h.of(SessionEnded)
        s: Any = ended.summary
        assert s.completed
    port = to.ep.port
    assert port is not None and port.node.counters.device_stale == 3
    assert math.isfinite(port.node.energy_sent) and math.isfinite(op.ep.port.node.guard.margin)  # type: ignore[union-attr]
    assert op.ep.port.node.counters.malformed == 0  # type: ignore[union-attr]
    assert op.ep.port.node.guard.report.link_lost_events == 0  # type: ignore[union-attr]


# --- teleop run: both children from the table -----------------------------------------------------


def test_run_hands_its_children_the_table_and_its_robot_admits_exactly_that(tmp_path: Any) -> None:
    """``teleop run``'s user chose the settings for both sides: both children get them as data (a
    session file, no session flag re-spelled), the operator proposes every setting of the table as
    given, and the robot's envelope admits them (and, with the defaults, nothing wider)."""
    from teleop.cli.endpoints import robot_envelope
    from teleop.cli.parser import build_parser
    from teleop.cli.run import TELEOP, RunKey, build_commands
    from teleop.cli.settings import read_session_file, session_params

    argv = ["run", "--range", "16", "--b", "0.5", "--no-controller", "--link-timeout", "1000"]
    argv += ["--playout", "300", "--codec", "cq:8", "--rate-cap", "64kbit", "--passivity", "tdpa"]
    args = build_parser().parse_args(argv)
    params = session_params(args, 9)
    assert DEFAULT_ENVELOPE.check(params) is not None  # a default robot would refuse these
    cmds = build_commands(args, params, tmp_path, RunKey(["--insecure"], "insecure", "0"))
    for cmd in (cmds.operator, cmds.teleoperator):
        assert not {"--codec", "--range", "--b", "--playout", "--max-range", "--allow-passivity"} & set(cmd)
    op = build_parser().parse_args(cmds.operator[len(TELEOP) :])
    assert read_session_file(op.session_file) == params
    to = build_parser().parse_args(cmds.teleoperator[len(TELEOP) :])
    env = robot_envelope(to, read_session_file(to.session_file))
    assert env.check(params) is None
    assert env == DEFAULT_ENVELOPE.admitting(params)
    plain_args = build_parser().parse_args(["run"])
    plain = build_commands(
        plain_args, session_params(plain_args, 10), tmp_path, RunKey(["--insecure"], "insecure", "0")
    )
    to = build_parser().parse_args(plain.teleoperator[len(TELEOP) :])
    assert robot_envelope(to, read_session_file(to.session_file)) == DEFAULT_ENVELOPE


def test_a_session_file_is_read_as_strictly_as_a_hello(tmp_path: Any) -> None:
    """A session file is data a process reads: refused by size and kind first, then every field
    held as a hello's is, each failure one line naming the file."""
    from teleop.cli.args import CliError
    from teleop.cli.parser import build_parser
    from teleop.cli.settings import read_session_file, session_params, write_session_file

    params = session_params(build_parser().parse_args(["run", "--codec", "ids:2"]), 11)
    good = write_session_file(tmp_path, params)
    assert read_session_file(str(good)) == params
    with pytest.raises(CliError, match="outputs are never overwritten"):
        write_session_file(tmp_path, params)  # never over an earlier one
    cases = {
        "bad.json": (b"{not json", "not a session file"),
        "list.json": (b"[1, 2]", "not a session file"),
        "dof.json": (good.read_bytes().replace(b'"dof": 2', b'"dof": 0'), "dof must be"),
        "codec.json": (good.read_bytes().replace(b'"ids:2"', b'"IDS:2"'), "codec"),
        "big.json": (b" " * (70 * 1024), "bytes"),
    }
    for name, (body, said) in cases.items():
        (tmp_path / name).write_bytes(body)
        with pytest.raises(CliError, match=said) as e:
            read_session_file(str(tmp_path / name))
        assert "\n" not in str(e.value) and (name in str(e.value)), str(e.value)
