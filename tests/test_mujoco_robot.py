"""``--robot mujoco``: the teleoperator's robot in the MuJoCo engine (teleop.devices.mujoco_robot)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

pytest.importorskip("mujoco")

from teleop.devices import DeviceError
from teleop.devices.mujoco_robot import MujocoRobot, default_scene
from teleop.offline.sim import SimConfig, run_case
from tests.ran import RAN

DT = 0.001
Run = tuple[dict[str, Any], np.ndarray, np.ndarray]


def test_default_scene_ships_with_the_package() -> None:
    assert default_scene().is_file()
    assert default_scene().parent.name == "scenes"


@pytest.fixture(scope="module")
def protocol_run() -> Run:
    """One Section VI run against the MuJoCo robot (eds:50, the default of `teleop run`), shared."""
    r = run_case(SimConfig(scenario="protocol", robot="mujoco", codec="eds:50"))
    return r.summary, r.trace.t, r.trace.f_to


def test_protocol_run_is_passive_with_the_controller(protocol_run: Run) -> None:
    s, _, _ = protocol_run
    assert s["min_energy_margin"] >= -1e-9  # the channel, both directions (the watchdog's figure)
    assert s["passive"]
    for d in ("forward", "backward"):
        assert s["passivity"][d]["violations"] == 0
    robot = s["devices"]["robot"]
    # The robot's own port observer: it started at rest and never gave back more than it took.
    assert robot["spec"] == "mujoco" and robot["scene"] == "default"
    assert robot["min_port_energy_J"] >= -1e-9 and robot["active_ticks"] == 0
    assert robot["port_energy_J"] > 0.01  # foam and wall dissipated what the operator pushed in
    assert robot["negative_z_ticks"] == 0
    assert robot["max_coupling"] < 1e-6  # frictionless, axis-aligned: the diagonal form is exact
    assert robot["placed_at_s"] == {"foam": 5.0, "wall": 10.0}


def test_protocol_run_forces_are_plausible(protocol_run: Run) -> None:
    """Free space: next to no force; foam: a few N over centimetres; wall: as much over millimetres."""
    s, t, f = protocol_run
    pen = s["devices"]["robot"]["max_penetration_m"]
    free, foam, wall = (t < 5.0), (t >= 5.0) & (t < 10.0), (t >= 10.0)
    # only the 100 g tool's inertia: small, with spikes where eds:50 steps the velocity every 50 ms
    assert np.median(np.abs(f[free])) < 0.05 and np.abs(f[free]).max() < 1.0
    assert 1.0 < f[foam, 0].max() < 15.0
    assert 0.005 < pen["foam"] < 0.08
    assert 1.0 < f[wall, 0].max() < 30.0
    assert 0.0 < pen["wall"] < 0.005
    stiffness_wall = f[wall, 0].max() / pen["wall"]
    stiffness_foam = f[foam, 0].max() / pen["foam"]
    assert stiffness_wall > 1000.0 and stiffness_wall > 10 * stiffness_foam
    # a contact can only push: any pull is the tool's inertia, no more than in free space
    assert f[foam | wall, 0].min() > -1.0


def test_affine_form_predicts_the_sensed_force_in_steady_contact() -> None:
    """While the contact set holds, ``f0 + Z v`` is what the engine's sensor reads for command v."""
    robot = MujocoRobot(dof=1, dt=DT)
    for n in range(800):  # bring in the wall at 10 s, then push into it at 5 cm/s
        now = 10.0 + n * DT
        f0, z = robot.affine(now)
        v = np.array([0.05])
        robot.advance(now, v, f0 + z * v)
    assert robot.max_penetration["wall"] > 0  # in contact
    robot.max_prediction_error = 0.0  # from here on: steady contact only
    rng = np.random.default_rng(1)
    for n in range(200):
        now = 10.8 + n * DT
        f0, z = robot.affine(now)
        assert z[0] > 0
        v = np.array([0.05 + rng.uniform(-0.01, 0.01)])
        robot.advance(now, v, f0 + z * v)
    assert robot.max_prediction_error < 1e-6
    assert robot.max_force > 2.0


@settings(max_examples=25, deadline=None)
@given(
    start=st.sampled_from([0.0, 5.0, 10.0]),  # free space, foam, foam and wall
    commands=st.lists(st.tuples(st.floats(-0.3, 0.4), st.floats(-0.2, 0.2)), min_size=20, max_size=300),
    hold=st.integers(1, 30),
)
def test_robot_port_is_passive_for_arbitrary_commands(
    start: float, commands: list[tuple[float, float]], hold: int
) -> None:
    """Property: whatever velocity the port commands (held ``hold`` ticks each), the energy into the
    robot's port, sum v F dt with F the force the port used, never goes below zero (it starts at
    rest): the robot with its controller, contacts and time stepping gives back no energy."""
    robot = MujocoRobot(dof=2, dt=DT)
    energy = 0.0
    n = 0
    for c in commands:
        v = np.array(c)
        for _ in range(hold):
            now = start + n * DT
            f0, z = robot.affine(now)
            f = f0 + z * v
            robot.advance(now, v, f)
            energy += DT * float(v @ f)
            assert energy >= -1e-9
            n += 1
    assert robot.active_ticks == 0 and robot.min_port_energy >= -1e-9


def test_bad_scenes_are_one_line_errors(tmp_path: Path) -> None:
    scene = tmp_path / "s.xml"
    scene.write_text(default_scene().read_text().replace('timestep="0.001"', 'timestep="0.002"'))
    with pytest.raises(DeviceError, match="timestep must be the loop period"):
        MujocoRobot(dof=2, dt=DT, arg=str(scene))
    scene.write_text(default_scene().read_text().replace('name="ee_force"', 'name="other"'))
    with pytest.raises(DeviceError, match="no force sensor named 'ee_force'"):
        MujocoRobot(dof=2, dt=DT, arg=str(scene))
    scene.write_text(
        default_scene()
        .read_text()
        .replace('<velocity name="vx" joint="x" kv="200"/>', '<position name="vx" joint="x" kp="200"/>')
    )
    with pytest.raises(DeviceError, match="velocity actuator"):
        MujocoRobot(dof=2, dt=DT, arg=str(scene))
    scene.write_text("<mujoco><worldbod")
    with pytest.raises(DeviceError, match="XML parse error"):
        MujocoRobot(dof=2, dt=DT, arg=str(scene))
    with pytest.raises(DeviceError, match="1 to 3 DoF"):
        MujocoRobot(dof=4, dt=DT)


def test_a_scene_without_timeline_bodies_stays_static(tmp_path: Path) -> None:
    """A scene of one's own without mocap foam/wall: the robot only steps it (free space here)."""
    text = default_scene().read_text()
    a, b = text.index("<!-- Parked"), text.index("</worldbody>")
    scene = tmp_path / "free.xml"
    scene.write_text(text[:a] + text[b:])
    robot = MujocoRobot(dof=1, dt=DT, arg=str(scene))
    for n in range(12000):
        now = n * DT
        f0, z = robot.affine(now)
        v = np.array([0.1])
        robot.advance(now, v, f0 + z * v)
    assert robot.placed == {}
    assert abs(robot.position()[0] - 1.2) < 0.01  # followed the command: 0.1 m/s for 12 s
    assert robot.max_force < 25.0  # the first tick's step of command, then nothing


def test_the_scene_switches_phase_when_the_seeded_human_does() -> None:
    """With --variation the foam and the wall come in at the seeded plan's phase times (drawn from
    the same seed on both sides), not at the scripted 5 s and 10 s."""
    from teleop import devices
    from teleop.devices.models import ProtocolPlan

    plan = ProtocolPlan.draw(3, 1.5)
    assert abs(plan.t_foam - 5.0) > 1e-3 and abs(plan.t_wall - 10.0) > 1e-3  # this seed moves both
    robot = devices.make("robot", "mujoco", 1, DT, seed=3, variation=1.5)
    assert isinstance(robot, MujocoRobot)
    for n in range(11000):
        now = n * DT
        f0, _z = robot.affine(now)
        robot.advance(now, np.zeros(1), f0)
    assert robot.placed["foam"] == pytest.approx(plan.t_foam, abs=DT)
    assert robot.placed["wall"] == pytest.approx(plan.t_wall, abs=DT)
    scripted = devices.make("robot", "mujoco", 1, DT)
    assert isinstance(scripted, MujocoRobot) and (scripted.foam_at, scripted.wall_at) == (5.0, 10.0)


def test_port_observer_counts_energy_the_robot_gives_back() -> None:
    """The observer is not a formality: a port that reports a force against the motion (energy out
    of the robot) shows as a negative port energy and counted active ticks."""
    robot = MujocoRobot(dof=1, dt=DT)
    for n in range(50):
        now = 10.0 + n * DT
        f0, z = robot.affine(now)
        v = np.array([0.05])
        robot.advance(now, v, -(f0 + z * v))  # as if the robot pushed the operator along
    assert robot.min_port_energy < -1e-9 and robot.active_ticks > 0


@pytest.mark.integration
def test_teleop_run_with_the_mujoco_robot(tmp_path: Path) -> None:
    """Two real processes, 2 s: the teleoperator runs the engine, the operator its own human; the
    report carries both devices, and the robot's port and the channel stayed passive."""
    out = tmp_path / "run"
    r = subprocess.run(
        [
            *(sys.executable, "-m", "teleop.cli", "run", "--robot", "mujoco", "--duration", "2"),
            *("--out", str(out), "--no-plots", "--no-live"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode in RAN, r.stderr
    rep = json.loads((out / "report.json").read_text())
    assert rep["devices"]["hsi"] == {"spec": "protocol"}  # the operator built no robot
    robot = rep["devices"]["robot"]
    assert robot["spec"] == "mujoco" and robot["engine"].startswith("mujoco ")
    assert robot["min_port_energy_J"] >= -1e-9 and robot["active_ticks"] == 0
    assert rep["energy"]["forward"]["min_margin"] >= -1e-9
    assert rep["energy"]["backward"]["min_margin"] >= -1e-9
    assert "I_sim" in rep["transparency"]  # the sim rebuilt the built-in robot for the comparison
    assert "robot mujoco: port energy min" in r.stdout


def test_a_diverging_engine_is_reset_and_reports_no_force() -> None:
    """Non-finite state (an exploding scene of one's own): back to rest, zero force, counted."""
    robot = MujocoRobot(dof=2, dt=DT)
    robot.d.qvel[0] = float("nan")
    f0, z = robot.affine(0.0)
    assert f0.tolist() == [0.0, 0.0] and z.tolist() == [0.0, 0.0]
    assert robot.engine_resets == 1
    f0, z = robot.affine(DT)  # at rest again: the robot is usable
    assert np.all(np.isfinite(f0)) and z[0] > 0


def test_a_step_further_than_the_robot_can_go_is_stale_and_the_state_held(tmp_path: Path) -> None:
    """A finite but implausible step (the engine astray: the tip at 500 m/s) is undone and counted,
    the next steps are normal; with a ``ctrlrange`` the scene's own limit is the bound."""
    robot = MujocoRobot(dof=2, dt=DT)
    assert robot.max_step == pytest.approx(2 * 10.0 * DT)
    v = np.array([0.1, 0.0])
    for n in range(10):
        f0, z = robot.affine(n * DT)
        robot.advance(n * DT, v, f0 + z * v)
    held = robot.position()
    robot.d.qvel[0] = 500.0  # 0.5 m in one tick
    f0, z = robot.affine(10 * DT)
    robot.advance(10 * DT, v, f0 + z * v)
    assert np.array_equal(robot.position(), held) and robot.summary()["stale_steps"] == 1
    f0, z = robot.affine(11 * DT)
    robot.advance(11 * DT, v, f0 + z * v)
    assert 0 < robot.position()[0] - held[0] < 1e-3 and robot.stale_steps == 1  # about v dt: used
    text = default_scene().read_text().replace('kv="200"/>', 'kv="200" ctrlrange="-0.5 0.5"/>')
    scene = tmp_path / "limited.xml"
    scene.write_text(text)
    assert MujocoRobot(dof=3, dt=DT, arg=str(scene)).max_step == pytest.approx(2 * 0.5 * DT)


def test_a_gain_beyond_the_integrators_reach_shows_as_an_active_port(tmp_path: Path) -> None:
    """Where the robot cannot be passive: explicit Euler with kv dt / m = 10 (the stability limit
    is 2; the default scene integrates the controller implicitly).  The observer sees the engine
    giving energy back under the same kind of held commands the passivity property uses."""
    scene = tmp_path / "euler.xml"
    text = default_scene().read_text().replace('integrator="implicitfast"', 'integrator="Euler"')
    scene.write_text(text.replace('kv="200"', 'kv="1000"'))
    robot = MujocoRobot(dof=1, dt=DT, arg=str(scene))
    rng = np.random.default_rng(0)
    n = 0
    for _ in range(20):
        v = np.array([rng.uniform(-0.3, 0.4)])
        for _ in range(int(rng.integers(1, 30))):
            f0, z = robot.affine(n * DT)
            robot.advance(n * DT, v, f0 + z * v)
            n += 1
    assert robot.active_ticks > 0 and robot.min_port_energy < -1e-9
