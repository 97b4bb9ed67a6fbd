"""``--robot franka``: options and limits against a fake arm (no process), then the device and a whole
session against franky-sim (a real server process on loopback, a real pylibfranka client)."""

from __future__ import annotations

import contextlib
import json
import math
import os
import random
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from teleop import devices
from teleop.devices import DeviceError
from teleop.devices.franka import FrankaRobot, RobotFault, parse_arg
from tests.ran import RAN
from tests.waiting import wait_for

TELEOP = [sys.executable, "-m", "teleop.cli"]
SIM = Path(sys.executable).with_name("franky-sim")


# --- a fake arm: enough of pylibfranka's surface for the device's arithmetic and its faults ---------
class _Mode:
    def __init__(self, name: str) -> None:
        self.name = name

    def __str__(self) -> str:
        return f"RobotMode.{self.name}"


class _State:
    def __init__(self, z: float = 0.5, mode: str = "Move") -> None:
        pose = np.eye(4)
        pose[:3, 3] = [0.5, 0.0, z]
        self.O_T_EE = pose.T.reshape(-1).tolist()  # column-major, as libfranka
        self.q = [0.0] * 7
        self.dq = [0.0] * 7
        self.tau_J = [0.0] * 7
        self.tau_J_d = [0.0] * 7
        self.O_F_ext_hat_K = [0.0, 0.0, 5.0, 0.0, 0.0, 0.0]
        self.robot_mode = _Mode(mode)
        self.control_command_success_rate = 1.0
        self.current_errors = ""
        self.last_motion_errors = ""


class _Duration:
    def to_sec(self) -> float:
        return 0.001


class _ControlException(RuntimeError):
    pass


class _Torques:
    def __init__(self, tau: list[float]) -> None:
        self.tau_J = tau
        self.motion_finished = False


class _Lib:
    Torques = _Torques


class _Model:
    def zero_jacobian(self, s: _State) -> list[float]:
        j = np.zeros((6, 7))
        j[:3, :3] = np.eye(3)  # the first three joints move the end-effector along x, y, z
        j[3:, 3:6] = np.eye(3)
        return j.T.reshape(-1).tolist()

    def coriolis(self, s: _State) -> list[float]:
        return [0.0] * 7

    def gravity(self, s: _State) -> list[float]:
        return [0.0] * 7


class _Control:
    def __init__(self, arm: _FakeArm) -> None:
        self.arm = arm

    def readOnce(self) -> tuple[_State, _Duration]:  # pylibfranka's name
        if self.arm.reflex:
            raise _ControlException("libfranka: Move command aborted: motion aborted by reflex! [reflex]")
        return self.arm.next_state, _Duration()

    def writeOnce(self, cmd: _Torques) -> None:
        self.arm.written.append(cmd)


class _FakeArm:
    def __init__(self) -> None:
        self.next_state = _State()
        self.written: list[_Torques] = []
        self.reflex = False
        self.recovered = 0

    def read_once(self) -> _State:
        return self.next_state

    def automatic_error_recovery(self) -> None:
        self.recovered += 1
        self.next_state = _State()

    def set_collision_behavior(self, *a: Any) -> None:
        pass

    def load_model(self) -> _Model:
        return _Model()

    def start_torque_control(self) -> _Control:
        return _Control(self)


def _fake(arg: str = "127.0.0.1", dof: int = 3) -> tuple[FrankaRobot, _FakeArm]:
    arm = _FakeArm()
    return FrankaRobot(dof, 0.001, arg, robot=arm, lib=_Lib()), arm


def _step(dev: FrankaRobot, now: float, v: list[float]) -> np.ndarray:
    dev.wait(0.1)
    f0, z = dev.affine(now)
    vv = np.array(v)
    dev.advance(now, vv, f0 + z * vv)
    return f0


@pytest.mark.parametrize(
    ("arg", "dof", "error"),
    [
        (None, 3, "needs the robot's address"),
        ("127.0.0.1", 4, "drives 1 to 3 DoF"),
        ("127.0.0.1", 0, "drives 1 to 3 DoF"),
        ("bad host!", 1, "is not an IPv4 address or a host name"),
        ("999.1.1.1", 1, "is not an IPv4 address or a host name"),
        ("127.0.0.1:stifness=3", 1, "unknown option 'stifness'; allowed: stiffness, damping"),
        ("127.0.0.1:stiffness=1e9", 1, "stiffness must be in [0, 3000], got '1e9'"),
        ("127.0.0.1:stiffness=nan", 1, "stiffness must be in [0, 3000]"),
        ("127.0.0.1:damping=x", 1, "damping must be a number, got 'x'"),
        ("127.0.0.1:force=magic", 1, "force must be one of spring, ext, joints"),
        ("127.0.0.1:rt=soft", 1, "rt must be one of auto, enforce, ignore"),
        ("127.0.0.1:max_velocity", 1, "option 'max_velocity' needs a value"),
        ("127.0.0.1:cutoff=5,cutoff=6", 1, "option 'cutoff' given twice"),
        ("127.0.0.1:recover=no", 1, "recover is a flag"),
        ("[::1", 1, "an IPv6 address goes in brackets"),
    ],
)
def test_a_bad_spec_is_one_line_before_any_session(arg: str | None, dof: int, error: str) -> None:
    spec = "franka" if arg is None else f"franka:{arg}"
    with pytest.raises(DeviceError) as e:
        devices.check(spec, "robot", dof)
    assert error in str(e.value) and "\n" not in str(e.value)


def test_options_parse_with_commas_or_colons() -> None:
    host, o = parse_arg("127.0.0.1:stiffness=300,damping=30:force=joints,recover")
    assert host == "127.0.0.1"
    assert (o.stiffness, o.damping, o.force, o.recover) == (300.0, 30.0, "joints", True)
    host, o = parse_arg("[::1]:max_stale=5")
    assert host == "::1" and o.max_stale == 5
    assert parse_arg("panda.local")[0] == "panda.local"


def test_v_moves_the_setpoint_along_its_axis_capped_and_the_spring_reads_on_the_environment() -> None:
    dev, _ = _fake("127.0.0.1:max_velocity=0.1,max_offset=0.2,cutoff=500", dof=3)
    for k in range(100):  # 0.1 s at 1 m/s asked along z: capped to 0.1 m/s
        _step(dev, k * 0.001, [0.0, 0.0, -1.0])
    assert dev.x_d - dev.x0 == pytest.approx([0.0, 0.0, -0.01], abs=1e-9)  # 100 ticks of 1 ms at 0.1 m/s
    assert dev.saturated["velocity"] == 100
    f = _step(dev, 0.1, [0.0, 0.0, 0.0])  # the arm (fake) did not move: the spring pulls down
    assert f[2] < -3.0 and abs(f[0]) < 1e-9  # on the environment, along the push: F . v > 0
    assert dev.summary()["port_energy_J"] > 0


def test_the_setpoint_stays_within_max_offset_of_the_arm() -> None:
    dev, _ = _fake("127.0.0.1:max_velocity=1,max_offset=0.01", dof=1)
    for k in range(200):
        _step(dev, k * 0.001, [1.0])
    assert float(np.linalg.norm(dev.x_d - dev.x0)) == pytest.approx(0.01)
    assert dev.saturated["offset"] > 0 and dev.max_drift == pytest.approx(0.01)


def test_torque_rate_is_limited_per_millisecond() -> None:
    dev, arm = _fake("127.0.0.1:max_torque_rate=0.1,max_velocity=1,max_offset=0.2", dof=1)
    for k in range(50):
        _step(dev, k * 0.001, [1.0])
    taus = np.array([c.tau_J for c in arm.written])
    assert np.max(np.abs(np.diff(taus, axis=0))) <= 0.1 + 1e-12 and dev.saturated["torque_rate"] > 0


def test_a_non_finite_state_is_stale_the_last_force_is_held_and_counted() -> None:
    dev, arm = _fake("127.0.0.1:force=ext,cutoff=500,max_stale=3", dof=3)
    for k in range(50):
        good = _step(dev, k * 0.001, [0.0, 0.0, 0.0])
    assert good[2] == pytest.approx(-5.0, rel=0.01)  # -O_F_ext_hat_K: the force on the environment
    bad = _State()
    bad.q = [math.nan] * 7
    arm.next_state = bad
    f = _step(dev, 0.05, [0.0, 0.0, 0.0])
    assert np.array_equal(f, good) and dev.stale == 1
    assert arm.written[-1].tau_J == arm.written[-2].tau_J  # the last torque, again
    nan_force = _State()
    nan_force.O_F_ext_hat_K = [math.inf] * 6
    arm.next_state = nan_force
    assert np.array_equal(_step(dev, 0.051, [0.0, 0.0, 0.0]), good) and dev.stale == 2
    arm.next_state = bad
    _step(dev, 0.052, [0.0, 0.0, 0.0])
    _step(dev, 0.053, [0.0, 0.0, 0.0])
    _step(dev, 0.054, [0.0, 0.0, 0.0])
    with pytest.raises(RobotFault, match="3 robot states in a row were stale"):
        dev.wait(0.1)


def test_a_finite_state_the_arm_cannot_reach_is_stale_and_never_moves_the_setpoint() -> None:
    """A pose 1 m off for one tick (finite): on main it pulled the set-point max_offset after it and
    the arm 50 mm at 30 N while the channel commanded 0.  Now it is stale: held, counted, unused."""
    dev, arm = _fake("127.0.0.1:force=spring,cutoff=500,max_stale=3", dof=3)
    for k in range(20):
        good = _step(dev, k * 0.001, [0.0, 0.0, 0.0])
    x_d, tau = dev.x_d.copy(), arm.written[-1].tau_J
    arm.next_state = _State(z=1.5)  # 1 m in 1 ms: 333 times what the FR3 can
    f = _step(dev, 0.02, [0.0, 0.0, 0.0])
    assert np.array_equal(f, good) and np.array_equal(dev.x_d, x_d)
    assert arm.written[-1].tau_J == tau  # the last torque again, not a spring toward 1 m
    s = dev.summary()
    assert (s["stale_reads"], s["implausible_reads"], s["saturated"]["offset"]) == (1, 1, 0)
    arm.next_state = _State(z=0.5 + 0.004)  # 4 mm over the 2 ms since the last good state: plausible
    _step(dev, 0.021, [0.0, 0.0, 0.0])
    assert dev.summary()["stale_reads"] == 1 and dev._x[2] == pytest.approx(0.504)
    fast = _State(z=0.504)
    fast.dq = [0.0, 0.0, 0.0, 0.0, 20.0, 0.0, 0.0]  # a joint at 20 rad/s: the FR3's is 5.26
    arm.next_state = fast
    _step(dev, 0.022, [0.0, 0.0, 0.0])
    assert dev.summary()["implausible_reads"] == 2
    line = devices.describe(devices.summary_of(dev, "franka:127.0.0.1"))
    assert line is not None and "stale reads 2 (implausible 2), drift" in line
    jump = _State(z=0.504)
    jump.q = [0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0]  # joint 4 half a radian in a few ms
    arm.next_state = jump
    for k in range(2):  # with the fast joint's: three stale reads in a row, max_stale
        _step(dev, 0.023 + k * 0.001, [0.0, 0.0, 0.0])
    with pytest.raises(RobotFault, match="stale \\(not finite, or not plausible\\)"):
        dev.wait(0.1)


def test_a_reflex_is_a_robot_fault_in_one_line_and_nothing_is_commanded_after_it() -> None:
    dev, arm = _fake()
    _step(dev, 0.0, [0.0, 0.0, 0.0])
    arm.reflex = True
    arm.next_state = _State(mode="Reflex")
    arm.next_state.last_motion_errors = "[joint_reflex]"
    with pytest.raises(RobotFault) as e:
        dev.wait(0.1)
    assert "reflex" in str(e.value) and "\n" not in str(e.value)
    n = len(arm.written)
    dev.advance(0.002, np.zeros(3), np.zeros(3))
    dev.close()
    dev.close()
    assert len(arm.written) == n and dev.summary()["reflex"]


def test_a_robot_in_reflex_at_the_start_needs_recover() -> None:
    arm = _FakeArm()
    arm.next_state = _State(mode="Reflex")
    with pytest.raises(DeviceError, match="add the option recover"):
        FrankaRobot(3, 0.001, "127.0.0.1", robot=arm, lib=_Lib())
    FrankaRobot(3, 0.001, "127.0.0.1:recover", robot=arm, lib=_Lib())
    assert arm.recovered == 1


def test_libfrankas_blocking_calls_leave_ctrl_c_to_the_kernel() -> None:
    """pylibfranka keeps the interpreter while it waits (a busy arm: forever), so no Python handler
    could run: during the connect SIGINT/SIGTERM are at their default action (the process ends at
    once); the handlers are back afterwards."""
    seen: list[tuple[Any, Any]] = []
    arm = _FakeArm()

    class Lib(_Lib):
        class RealtimeConfig:
            kIgnore, kEnforce = "ignore", "enforce"

        def Robot(self, host: str, cfg: str) -> _FakeArm:  # pylibfranka's name
            seen.append((signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)))
            return arm

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    FrankaRobot(3, 0.001, "127.0.0.1:rt=ignore", lib=Lib())
    assert seen == [(signal.SIG_DFL, signal.SIG_DFL)]
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_close_finishes_the_motion_once() -> None:
    dev, arm = _fake()
    _step(dev, 0.0, [0.0, 0.0, 0.0])
    dev.close()
    dev.close()
    assert [c.motion_finished for c in arm.written] == [False, True]


# --- against franky-sim -----------------------------------------------------------------------------
try:
    import pylibfranka

    HAVE_PYLIBFRANKA = True
except ImportError:  # the only reason to skip: the client library is not installed
    HAVE_PYLIBFRANKA = False
needs_pylibfranka = pytest.mark.skipif(
    not HAVE_PYLIBFRANKA, reason="import pylibfranka failed: pip install 'teleop[franka]'"
)


class Sim:
    """A franky-sim of the test's own: its loopback address and what it printed (its log)."""

    def __init__(self, host: str, proc: subprocess.Popen[str]) -> None:
        self.host, self.proc = host, proc
        self.lines: list[str] = []
        self._changed = threading.Condition()

    def drain(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            with self._changed:
                self.lines.append(line)
                self._changed.notify_all()
        with self._changed:
            self.lines.append("")  # its end
            self._changed.notify_all()

    def wait_line(self, text: str, after: int = 0, timeout_s: float = 120.0) -> int | None:
        """The index of the first line from ``after`` on holding ``text`` (None: the sim ended, or
        ``timeout_s`` went by)."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while True:
                for i in range(after, len(self.lines)):
                    if text in self.lines[i]:
                        return i
                    if self.lines[i] == "":
                        return None
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._changed.wait(left)

    def accepted(self) -> int:
        """Connections the server accepted so far (its -v log says each)."""
        with self._changed:
            return sum("Accepted new connection" in line for line in self.lines)


def _own_address() -> str:
    """A loopback address of this test's (127.X.Y.Z, never 127.0.0.1: a user's franky-sim starts
    there), free on libfranka's port."""
    for _ in range(50):
        host = f"127.{random.randrange(1, 255)}.{random.randrange(256)}.{random.randrange(1, 255)}"
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            try:
                s.bind((host, 1337))
            except OSError:
                continue
        return host
    pytest.fail("no free loopback address for franky-sim")


@pytest.fixture(scope="module")
def franky_sim() -> Iterator[Sim]:
    """A franky-sim server of the module's own, on a loopback address of its own (``--hostname``),
    so a user's franky-sim (on 127.0.0.1, as the Franka guide starts it) or another worktree's test
    is never reached; waited for by its "Connect to the server using 'HOST'" line, killed at the end."""
    if not SIM.exists():
        pytest.fail(f"{SIM} is missing: pip install 'teleop[franka]'")
    host = _own_address()
    p = subprocess.Popen(
        [str(SIM), "-s", "mujoco", "-v", "--hostname", host],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        bufsize=1,
    )
    sim = Sim(host, p)
    threading.Thread(target=sim.drain, daemon=True).start()
    try:
        i = sim.wait_line("Connect to the server using")
        if i is None:
            pytest.fail(f"franky-sim did not start: {''.join(sim.lines)[-500:]}")
        assert f"'{host}'" in sim.lines[i], sim.lines[i]  # bound where asked, not elsewhere
        yield sim
    finally:
        p.kill()
        p.wait(10)


def _connect(sim: Sim, spec: str) -> FrankaRobot:
    """The device on the test's own franky-sim, which must see the connection (not a user's
    server); the claim bounds the wait (libfranka waits forever on a busy server)."""
    before = sim.accepted()
    devices.claim(spec, "robot")
    dev = devices.make("robot", spec, 3, 0.001)
    assert isinstance(dev, FrankaRobot)
    assert sim.accepted() > before, "the device did not reach the test's own franky-sim"
    return dev


def _run_device(dev: FrankaRobot, seconds: float, v: list[float], t0: float) -> tuple[float, np.ndarray]:
    """Tick the device on its own clock for ``seconds`` of the robot's time (franky-sim's runs slower
    than the wall clock when its client is slow) at ``v``; returns (time, last force)."""
    t, f = t0, np.zeros(dev.dof)
    start = dev.reads
    vv = np.array(v)
    while (dev.reads - start) * 0.001 < seconds:
        dev.wait(0.1)
        t = t0 + (dev.reads - start) * 0.001
        f, z = dev.affine(t)
        dev.advance(t, vv, f + z * vv)
    return t, f


def _pos(dev: FrankaRobot) -> np.ndarray:
    return np.asarray(dev._x - dev.x0)  # the measured end-effector from the origin (test only)


@pytest.mark.integration
@needs_pylibfranka
@pytest.mark.serial
def test_the_device_against_franky_sim(franky_sim: Sim) -> None:
    dev = _connect(franky_sim, f"franka:{franky_sim.host}:force=spring")
    try:
        # Up first (the server keeps the arm where the last client left it): along z only, ~v t.
        # Settle first: on franky-sim the arm sags about 1 cm when the torque loop takes over (a load
        # its gravity model does not carry, against K): the displacements are measured from there.
        t, _ = _run_device(dev, 1.0, [0.0, 0.0, 0.0], 0.0)
        base = _pos(dev)
        t, _ = _run_device(dev, 1.0, [0.0, 0.0, 0.05], t)
        up = _pos(dev) - base
        sp = dev.x_d - dev.x0
        assert sp[2] == pytest.approx(0.05, rel=0.01)  # the set-point moved v t (the robot's t)
        assert up[2] > 0.02 and abs(up[0]) < 0.01 and abs(up[1]) < 0.005  # the arm follows, lagging
        # v = 0: it stops at about v t and holds there.
        t, _ = _run_device(dev, 1.0, [0.0, 0.0, 0.0], t)
        held = _pos(dev)
        # About v t: franky-sim's gravity model differs from its physics by a pose-dependent load
        # that resists like a 100-200 N/m spring (docs/guides/franka.md): 5% short at K = 1500.
        assert held[2] - base[2] == pytest.approx(0.05, rel=0.12)
        t, _ = _run_device(dev, 0.5, [0.0, 0.0, 0.0], t)
        assert float(np.linalg.norm(_pos(dev) - held)) < 0.002
        # Along x.
        t, _ = _run_device(dev, 0.6, [0.05, 0.0, 0.0], t)
        t, _ = _run_device(dev, 1.0, [0.0, 0.0, 0.0], t)
        moved = _pos(dev) - held
        assert moved[0] == pytest.approx(0.03, rel=0.12) and abs(moved[1]) < 0.005 and abs(moved[2]) < 0.008
        # Free space: only franky-sim's own model error, which the spring holds off (its gravity
        # model and its physics differ by a pose-dependent load: ~9 N here, docs/guides/franka.md);
        # well below the contact force.  Down into the floor: the force reads along the push.
        _, free = _run_device(dev, 0.3, [0.0, 0.0, 0.0], t)
        assert float(np.linalg.norm(free)) < 0.5 * dev.opts.max_force
        t, f = _run_device(dev, 4.0, [0.0, 0.0, -0.25], t)
        assert dev.x0[2] + _pos(dev)[2] < 0.05  # at the floor (z ~ 0.01 m)
        assert f[2] < -10.0 and abs(f[2]) <= dev.opts.max_force + 1e-6  # pushing down: F_z < 0, F.v > 0
        s = dev.summary()
        assert s["control_command_success_rate"] == 1.0 and s["stale_reads"] == 0 and s["reflex"] is None
        _run_device(dev, 2.0, [0.0, 0.0, 0.25], t)  # back up (0.5 m) for the next test
    finally:
        dev.close()
        dev.close()
    state = pylibfranka.Robot(franky_sim.host, pylibfranka.RealtimeConfig.kIgnore).read_once()
    assert str(state.robot_mode).endswith("Idle") and max(abs(x) for x in state.dq) < 0.05


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.integration
@needs_pylibfranka
@pytest.mark.serial
def test_a_session_driving_franky_sim(franky_sim: Sim, tmp_path: Path) -> None:
    port = _free_port()
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    to = subprocess.Popen(
        [
            *TELEOP,
            "teleoperator",
            "--robot",
            f"franka:{franky_sim.host}",
            "--dof",
            "3",
            "--insecure",
            "--listen",
            f"127.0.0.1:{port}",
            "--log",
            str(tmp_path),
            "--quiet",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    before = franky_sim.accepted()
    with contextlib.ExitStack() as stack:
        stack.callback(to.kill)  # a no-op once it exited
        op = subprocess.run(
            [
                *TELEOP,
                "operator",
                "--dof",
                "3",
                "--insecure",
                "--peer",
                f"127.0.0.1:{port}",
                "--duration",
                "5",
                "--log",
                str(tmp_path),
                "--quiet",
            ],
            capture_output=True,
            text=True,
            timeout=120,
            env=env,
        )
        _, to_err = to.communicate(timeout=60)
    assert op.returncode in RAN, op.stderr
    assert to.returncode in RAN, to_err
    role = json.loads((tmp_path / "teleoperator.json").read_text())
    dev, loop = role["device"], role["loop"]
    assert role["completed"] and "fault" not in role
    assert dev["robot"] == "franka" and dev["reflex"] is None and dev["stale_reads"] == 0
    assert dev["control_command_success_rate"] == 1.0
    # The device's own observer of its port (sum v F dt with the reported, low-passed force) may
    # dip by micro-joules: the filter lags the spring, and franky-sim's model error is a
    # conservative field that returns what it stored.  The channel's passivity is the report's.
    # That holds while franky-sim keeps up with half the session clock (0.57-0.74 of it on a quiet
    # host): starved by a loaded host (a user's franky-sim beside it, other tests) to 0.21-0.33, the
    # set-point moves several session ms per robot ms, the model error stores and returns more, and
    # the observer was measured at -0.01 to -0.33 J in such runs (at 0.42-0.44: above -3e-7 J).
    kept_up = dev["robot_ticks"] / (loop["ticks"] + loop["missed_deadlines"]) >= 0.5
    assert dev["min_port_energy_J"] > -1e-5 or not kept_up, (dev["min_port_energy_J"], dev["robot_ticks"])
    assert dev["max_drift_m"] <= dev["max_offset_m"] + 1e-9
    assert loop["device_paced"] and loop["ticks"] + loop["missed_deadlines"] >= 4990
    # The teleoperator reached the test's own server: its check, then its connection.
    assert franky_sim.accepted() >= before + 2
    before = franky_sim.accepted()
    rep = subprocess.run(  # the sim comparison asked for: the report must not build the arm
        [*TELEOP, "report", str(tmp_path), "--no-plots", "--out", str(tmp_path / "r")],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert rep.returncode in RAN, rep.stderr
    report = json.loads((tmp_path / "r" / "report.json").read_text())
    assert report["two_port_min_energy"] >= -1e-9  # eq. (4): the channel stayed passive
    for d in ("forward", "backward"):
        assert report["energy"][d]["min_margin"] >= -1e-9
    assert f"robot franka:{franky_sim.host}: success rate 1.000" in rep.stdout
    assert "paced by its device: missed deadlines" in rep.stdout
    assert f"teleop sim not re-run: the robot franka:{franky_sim.host} is hardware" in rep.stdout
    assert franky_sim.accepted() == before  # the report never connected to the arm
    state = pylibfranka.Robot(franky_sim.host, pylibfranka.RealtimeConfig.kIgnore).read_once()
    assert str(state.robot_mode).endswith("Idle") and not str(state.current_errors).strip("[]")


@pytest.mark.integration
@needs_pylibfranka
@pytest.mark.serial
def test_a_second_teleoperator_on_a_held_arm_says_why_before_it_answers_anyone(
    franky_sim: Sim, tmp_path: Path
) -> None:
    """One arm, one teleoperator: the first takes the arm before it listens; the second cannot (on
    franky-sim libfranka would wait forever), says so in one line and exits before it listens or
    logs.  Ctrl-C ends the first within a second."""
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}

    def teleoperator(log: Path) -> subprocess.Popen[str]:
        cmd = [*TELEOP, "teleoperator", "--robot", f"franka:{franky_sim.host}", "--dof", "3", "--insecure"]
        cmd += ["--listen", f"127.0.0.1:{_free_port()}", "--log", str(log), "--quiet"]
        cmd += ["--connect-timeout", "120"]  # it waits for an operator while the second tries
        return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)

    n = len(franky_sim.lines)
    first = teleoperator(tmp_path / "first")
    with contextlib.ExitStack() as stack:
        stack.callback(first.kill)
        probe = franky_sim.wait_line("Accepted new connection", n, timeout_s=30)
        assert (
            probe is not None and franky_sim.wait_line("Accepted new connection", probe + 1, 30) is not None
        )
        assert first.poll() is None  # it holds the arm, waiting for an operator
        t0 = time.monotonic()
        second = subprocess.run(
            [*TELEOP, "teleoperator", "--robot", f"franka:{franky_sim.host}", "--dof", "3", "--insecure",
             "--listen", f"127.0.0.1:{_free_port()}", "--log", str(tmp_path / "second")],
            capture_output=True, text=True, timeout=60, env=env,
        )  # fmt: skip
        assert second.returncode == 1 and time.monotonic() - t0 < 30
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in second.stderr, second.stderr
        assert lines[0].startswith(f"teleop teleoperator: error: robot 'franka' at {franky_sim.host}: ")
        assert "another client holds the arm" in lines[0]
        assert not (tmp_path / "second").exists() or not any((tmp_path / "second").iterdir())  # no session
        # A third, interrupted while it waits for the held arm: it says so within a second, and
        # its check (a child process) is gone.  (The interpreter's own exit after that took up to
        # 2 s on a loaded host, whatever the robot: not what is measured here.)
        third = teleoperator(tmp_path / "third")
        stack.callback(third.kill)
        probe_pid = _child(third.pid)
        assert _interrupted(third, "interrupted while taking the robot") < 1.0
        assert third.wait(timeout=10) == 130
        assert wait_for(lambda: not Path(f"/proc/{probe_pid}").exists() or _zombie(probe_pid), 5)
        # The first, waiting for an operator with the arm held, says so within a second too.
        assert _interrupted(first, "stopped while waiting for an operator") < 1.0
        assert first.wait(timeout=10) == 130


def _interrupted(p: subprocess.Popen[str], says: str) -> float:
    """SIGINT to ``p``; the seconds until its stderr says ``says`` (a reader thread takes the time)."""
    said: list[float] = []

    def read() -> None:
        assert p.stderr is not None
        for line in p.stderr:
            if says in line:
                said.append(time.monotonic())

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    t0 = time.monotonic()
    p.send_signal(signal.SIGINT)
    reader.join(timeout=10)
    assert said, f"it did not say {says!r}"
    return said[0] - t0


def _child(pid: int) -> int:
    """``pid``'s child that checks the arm (its command line runs pylibfranka; Linux /proc), waited for."""

    def probe() -> int | None:
        for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split():
            with contextlib.suppress(OSError):
                if b"pylibfranka" in Path(f"/proc/{c}/cmdline").read_bytes():
                    return int(c)
        return None

    found = wait_for(probe, 30, "the teleoperator's arm check (a child process)")
    assert found is not None
    return found


def _zombie(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True
