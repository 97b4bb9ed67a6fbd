"""The device interface (teleop.devices): resolving --hsi/--robot, third-party devices, adapters."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import shell.process
import teleop.cli.run
import teleop.offline.sim
from teleop import devices
from teleop.cli import main
from teleop.devices import DeviceError, DriverHsi, DriverRobot
from teleop.devices.models import Array, ProtocolEnvironment, ProtocolHuman
from teleop.offline.sim import SimConfig, run_case
from teleop.session.node import PortOptions
from teleop.session.port import make_node

DT = 0.001


class SpringRobot:
    """A third-party robot for the tests: a spring ``k`` N/m, ``--robot tests.test_devices:SpringRobot:K``."""

    role = "robot"
    hardware = False  # a model: teleop sim may build it

    def __init__(self, dof: int, dt: float, arg: str | None) -> None:
        self.k = float(arg) if arg else 100.0
        self.dt = dt
        self.x = np.zeros(dof)
        self.ticks = 0

    def affine(self, now: float) -> tuple[Array, Array]:
        # Implicit spring: F = k (x + v dt), so Z = k dt (passive, like the built-in wall).
        return self.k * self.x, np.full(self.x.shape, self.k * self.dt)

    def advance(self, now: float, v: Array, f: Array) -> None:
        self.x = self.x + v * self.dt
        self.ticks += 1

    def summary(self) -> dict[str, Any]:
        return {"ticks": self.ticks, "k": self.k}


class UndeclaredRobot:
    """A plug-in that does not say whether it is hardware: taken for hardware."""

    role = "robot"

    def __init__(self, dof: int, dt: float, arg: str | None) -> None:
        raise AssertionError("an offline tool built a device that may be hardware")

    def affine(self, now: float) -> tuple[Array, Array]:
        raise AssertionError("never built")

    def advance(self, now: float, v: Array, f: Array) -> None:
        raise AssertionError("never built")


class NotADevice:
    role = "hsi"

    def __init__(self, dof: int, dt: float, arg: str | None) -> None:
        self.dof = dof


def builtin(role: str, name: str) -> devices.Device:
    return devices.make(role, name, 2, DT)


def test_builtins_are_todays_models() -> None:
    assert isinstance(builtin("hsi", "protocol"), ProtocolHuman)
    assert isinstance(builtin("robot", "protocol"), ProtocolEnvironment)


def test_unknown_name_lists_what_is_available() -> None:
    with pytest.raises(DeviceError, match=r"unknown robot 'nope'; available: step, protocol, mujoco\[:SCENE"):
        devices.resolve("nope", "robot")
    with pytest.raises(DeviceError, match=r"unknown hsi 'mujoco'"):
        devices.resolve("mujoco", "hsi")  # the MuJoCo device is a robot


def test_module_class_loading_and_role_check() -> None:
    spec = devices.resolve("tests.test_devices:SpringRobot:250", "robot")
    dev = spec.build(2, DT)
    assert isinstance(dev, SpringRobot) and dev.k == 250.0
    with pytest.raises(DeviceError, match="is not a hsi device"):
        devices.resolve("tests.test_devices:SpringRobot", "hsi")
    with pytest.raises(DeviceError, match="has no 'Missing'"):
        devices.resolve("tests.test_devices:Missing", "robot")
    with pytest.raises(DeviceError, match="cannot import module 'no_such_pkg_xyz'"):
        devices.resolve("no_such_pkg_xyz:Thing", "robot")
    with pytest.raises(DeviceError, match=r"has no affine\(now\)"):
        devices.make("hsi", "tests.test_devices:NotADevice", 1, DT)


def test_entry_point_group(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A package that registers a device in the teleop.devices group is found by its name."""
    dist = tmp_path / "acme_teleop-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: acme-teleop\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[teleop.devices]\nacme-spring = tests.test_devices:SpringRobot\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert "acme-spring (entry point)" in devices.available("robot")
    dev = devices.make("robot", "acme-spring:50", 1, DT)
    assert isinstance(dev, SpringRobot) and dev.k == 50.0


def test_make_node_builds_only_this_sides_device() -> None:
    kw: dict[str, Any] = dict(scenario="protocol", dof=2, dt=DT, b=20.0, codec="none", full_scale=2.0)
    kw.update(session=1, options=PortOptions())
    op = make_node("operator", **kw)
    to = make_node("teleoperator", device="tests.test_devices:SpringRobot", **kw)
    assert isinstance(op.device, ProtocolHuman) and op.device_spec == "protocol"
    assert isinstance(to.device, SpringRobot) and to.device_spec == "tests.test_devices:SpringRobot"


def test_third_party_robot_in_the_sim() -> None:
    """A --robot of one's own runs in teleop sim, stays passive, and its summary reaches the results."""
    r = run_case(SimConfig(scenario="protocol", duration=2.0, robot="tests.test_devices:SpringRobot:200"))
    s = r.summary
    assert s["passive"]
    assert s["devices"]["robot"] == {"spec": "tests.test_devices:SpringRobot:200", "ticks": 2000, "k": 200.0}
    assert s["devices"]["hsi"] == {"spec": "protocol"}
    # the spring pushes back: F = k x, so the force follows the TO's position
    x = np.cumsum(r.trace.v_to[:, 0]) * DT
    assert np.allclose(r.trace.f_to[1:, 0], 200.0 * x[1:], atol=1e-9)


def test_only_a_session_builds_hardware() -> None:
    """franka and a plug-in that does not declare ``hardware = False`` are hardware: an offline tool
    refuses them in one line before building anything; the models, mujoco and a declared model pass."""
    assert [devices.resolve(s, "robot").hardware for s in ("step", "mujoco", "franka:127.0.0.1")] == [
        False,
        False,
        True,
    ]
    assert not devices.resolve("tests.test_devices:SpringRobot", "robot").hardware
    for spec in ("tests.test_devices:UndeclaredRobot", "franka:127.0.0.1"):
        with pytest.raises(DeviceError, match="is hardware: the sim never connects to it") as e:
            run_case(SimConfig(scenario="protocol", duration=0.1, robot=spec))
        assert "\n" not in str(e.value)
    assert devices.is_hardware("franka:10.0.0.2", "robot") and devices.is_hardware("pkg.mod:Arm", "robot")
    assert not devices.is_hardware("mujoco", "robot") and not devices.is_hardware(None, "robot")


@pytest.fixture
def no_session(monkeypatch: pytest.MonkeyPatch) -> None:
    def trip(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("a session started despite a bad argument")

    monkeypatch.setattr(shell.process, "run_endpoint", trip)
    monkeypatch.setattr(teleop.offline.sim, "run_set", trip)
    monkeypatch.setattr(teleop.cli.run, "_spawn", trip)


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["sim", "--robot", "nope"], "unknown robot 'nope'; available: step, protocol, mujoco"),
        (["sim", "--hsi", "nope"], "unknown hsi 'nope'; available: step, protocol, or package"),
        (["sim", "--robot", "step:3"], "robot 'step' takes no argument"),
        (["sim", "--robot", "mujoco:/no/such/scene.xml"], "scene file '/no/such/scene.xml' does not exist"),
        (["sim", "--robot", "os.path:join"], "os.path:join is not a robot device"),
        (["teleoperator", "--insecure", "--listen", "127.0.0.1:0", "--robot", "x.y:Z"], "cannot import"),
        (["operator", "--insecure", "--peer", "127.0.0.1:9", "--hsi", "mujoco"], "unknown hsi 'mujoco'"),
        (["run", "--robot", "nope"], "unknown robot 'nope'"),
        (["run", "--robot", "mujoco", "--dof", "4"], "robot 'mujoco' drives 1 to 3 DoF"),
        (
            ["teleoperator", "--insecure", "--listen", "127.0.0.1:0", "--robot", "mujoco", "--dof", "5"],
            "1 to 3 DoF",
        ),
    ],
)
def test_cli_rejects_a_bad_device(
    argv: list[str], message: str, no_session: None, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2, err
    assert err.startswith("teleop: error: ") and len(err.strip().splitlines()) == 1, err
    assert message in err


def test_run_passes_each_device_to_its_own_side_only(tmp_path: Path) -> None:
    from teleop.cli.run import RunKey, build_commands

    args = argparse.Namespace(
        transport="udp",
        port=7999,
        no_live=True,
        connect_timeout=5.0,
        no_rt=True,
        asyncio=False,
        tick_at="wake",
        live_view=None,
    )
    args.robot, args.hsi = "mujoco", "step"
    params = teleop.cli.settings.session_params(
        argparse.Namespace(
            scenario="protocol", dof=None, duration=1.0, b=None, range=None, codec="none", phase=0.5,
            netem=None, netem_forward=None, netem_backward=None, seed=0, on_loss=None,
            no_controller=False, link_timeout=50.0, rate_cap=0.0, playout="auto", variation=0.0,
        ),
        1,
    )  # fmt: skip
    cmds = build_commands(args, params, tmp_path, RunKey(["--insecure"], "insecure", "0"))
    assert cmds.teleoperator[cmds.teleoperator.index("--robot") + 1] == "mujoco"
    assert "--hsi" not in cmds.teleoperator
    assert cmds.operator[cmds.operator.index("--hsi") + 1] == "step"
    assert "--robot" not in cmds.operator


# --- adapters for real drivers -----------------------------------------------------------------


class FakeDriver:
    """A driver whose sample the test sets; it records what it is commanded."""

    def __init__(self, dof: int) -> None:
        self.counter = 0
        self.sample: list[float] = [0.0] * dof
        self.commands: list[Array] = []

    def push(self, sample: list[float]) -> None:
        self.counter += 1
        self.sample = sample

    def read(self) -> tuple[int, list[float]]:
        return self.counter, self.sample

    def command(self, x: Array) -> None:
        self.commands.append(np.array(x))


def test_hsi_adapter_renders_zero_force_when_the_data_goes_stale() -> None:
    drv = FakeDriver(2)
    hsi = DriverHsi(drv, 2, max_force=5.0, max_velocity=1.0, stale_after=0.003)
    drv.push([0.1, -0.2])
    v0, y = hsi.affine(0.0)
    assert v0.tolist() == [0.1, -0.2] and y.tolist() == [0.0, 0.0]
    hsi.advance(0.0, v0, np.array([1.0, 2.0]))
    assert drv.commands[-1].tolist() == [1.0, 2.0]
    for k in range(1, 6):  # no new sample: fresh for 3 ms, then stale
        now = k * DT
        v0, _ = hsi.affine(now)
        hsi.advance(now, v0, np.array([1.0, 2.0]))
        stale = now > 0.003 + 1e-12
        assert drv.commands[-1].tolist() == ([0.0, 0.0] if stale else [1.0, 2.0])
        assert v0.tolist() == ([0.0, 0.0] if stale else [0.1, -0.2])
    drv.push([0.3, 0.0])  # data again: force again
    v0, _ = hsi.affine(0.006)
    hsi.advance(0.006, v0, np.array([1.0, 0.0]))
    assert drv.commands[-1].tolist() == [1.0, 0.0]
    assert hsi.summary()["stale_ticks"] == 2


@pytest.mark.parametrize("bad", [[float("nan"), 0.0], [0.0, float("inf")], [2.0, 0.0], [0.1]])
def test_hsi_adapter_treats_an_implausible_sample_as_a_fault(bad: list[float]) -> None:
    drv = FakeDriver(2)
    hsi = DriverHsi(drv, 2, max_force=5.0, max_velocity=1.0)
    drv.push(bad)
    v0, _ = hsi.affine(0.0)
    hsi.advance(0.0, v0, np.array([1.0, 1.0]))
    assert v0.tolist() == [0.0, 0.0] and drv.commands[-1].tolist() == [0.0, 0.0]
    assert hsi.summary()["faults"] == 1


finite = st.floats(-1e3, 1e3, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(
    steps=st.lists(
        st.tuples(
            st.booleans(), st.lists(st.floats(-2.0, 2.0), min_size=2, max_size=2), st.tuples(finite, finite)
        ),
        min_size=1,
        max_size=40,
    ),
    max_force=st.floats(0.1, 50.0),
)
def test_hsi_adapter_only_removes_energy(
    steps: list[tuple[bool, list[float], tuple[float, float]]], max_force: float
) -> None:
    """Whatever the driver reports and the port asks, the device renders ``a F`` with ``0 <= a <= 1``
    (same direction, never more, zero on stale or implausible data): the power it delivers to the
    hand, ``v F_rendered``, never exceeds the port's in magnitude nor changes sign."""
    drv = FakeDriver(2)
    hsi = DriverHsi(drv, 2, max_force=max_force, max_velocity=1.0, stale_after=0.002)
    for k, (new, sample, force) in enumerate(steps):
        if new:
            drv.push(sample)
        now = k * DT
        v0, _ = hsi.affine(now)
        f = np.array(force)
        hsi.advance(now, v0, f)
        out = drv.commands[-1]
        assert float(np.linalg.norm(out)) <= max_force * (1 + 1e-12)
        fresh = max(abs(x) for x in drv.sample) <= 1.0
        if not fresh:
            assert out.tolist() == [0.0, 0.0]
        a = float(np.dot(out, f)) / max(float(np.dot(f, f)), 1e-300)
        assert -1e-12 <= a <= 1 + 1e-12
        assert np.allclose(out, a * f, atol=1e-9 * max(1.0, float(np.abs(f).max())))


def test_robot_adapter_holds_still_and_reports_no_force_when_stale() -> None:
    drv = FakeDriver(1)
    robot = DriverRobot(drv, 1, max_force=50.0, max_velocity=0.5, stale_after=0.002)
    drv.push([3.0])
    f0, z = robot.affine(0.0)
    assert f0.tolist() == [3.0] and z.tolist() == [0.0]
    robot.advance(0.0, np.array([2.0]), f0)
    assert drv.commands[-1].tolist() == [0.5]  # saturated to max_velocity
    for k in (1, 2, 3):
        f0, _ = robot.affine(k * DT)
        robot.advance(k * DT, np.array([0.1]), f0)
    assert f0.tolist() == [0.0] and drv.commands[-1].tolist() == [0.0]
    assert robot.summary() == {"stale_ticks": 1, "faults": 0, "saturated_ticks": 1}
