"""``--robot franka:HOST[:OPTIONS]``: a Franka arm (FR3 or Panda) through pylibfranka, torque control.

**Control law.** Each robot millisecond the arm's state is read (``readOnce``: it blocks until the
robot's next tick, so the robot's clock paces the session, see :attr:`FrankaRobot.paced`) and a
Cartesian impedance about a set-point is commanded (gravity is the robot's own)::

    F   = sat(K (x_d - x) - D xdot, max_force)                 translation, base frame
    M   = K_rot e_R - D_rot w                                  the starting orientation is held
    tau = J^T [F; M] + N (k_ns (q_0 - q) - d_ns dq) - d_q dq + coriolis(q, dq)

with ``N`` the dynamically inconsistent nullspace projector ``I - J^T pinv(J^T)``.  The torque is
clamped to the joints' limits and to a rate of ``max_torque_rate`` N m per millisecond (pylibfranka
0.21 does not expose libfranka's ``limit_rate``/``cutoff_frequency`` arguments, so this module does
it).

**The channel.** DoF ``i`` is base-frame axis ``x``, ``y``, ``z`` in that order (1 DoF: x; 2: x, y;
3: x, y, z); the pose at the start is the origin.  The commanded velocity ``v`` (the port's, from
``advance``) moves the set-point, ``x_d += v dt`` with ``dt`` the session time between two ticks
(a missed tick integrates over both); the set-point's speed is capped at ``max_velocity`` and its
distance from the measured end-effector at ``max_offset`` (a lost link or a fast hand cannot wind
up a spring).  The axes the channel does not drive are held at their start.  With ``v = 0`` (the
teleoperator's command when the link is lost) the set-point stops and the arm holds it.

**The force reported** (``affine -> (f0, Z)``, ``Z = 0``): the force the robot exerts on its
environment along the channel's axes (pushing into the floor reads positive along the push), from
``force=``:

* ``spring`` (default): the impedance's spring force ``K (x_d - x)`` (capped): the force at the
  set-point, the port's exact dual of ``v`` (so the robot's port is a spring, a damper to ground
  and the arm: passive); at rest in contact it equals the contact force.  The one source that sees
  contact on franky-sim;
* ``ext``: ``-O_F_ext_hat_K`` (libfranka's estimate of the external wrench on the arm; 0 on
  franky-sim);
* ``joints``: ``-pinv(J_v^T) (tau_J - tau_J_d - g(q))``, the measured joint torques less the
  command and gravity (on franky-sim ``tau_J`` is the command plus gravity, so this reads 0).

It is low-pass filtered (first order, ``cutoff`` Hz, on the robot's own time step).

**Stale data.** A state is stale if a value is not finite, or if it is not plausible: the
end-effector moved further since the last good state than the arm can (``PLAUSIBLE_MARGIN`` x
:data:`MAX_EE_SPEED` x the robot time between them), a joint did (the same margin on
:data:`MAX_DQ`), or a joint's velocity exceeds that margin on its limit.  A stale state is never
used: the set-point does not move, the last good force is held, the last torque is sent again, and
it is counted (``stale_reads``; ``implausible_reads`` of them finite but implausible);
``max_stale`` stale reads in a row end the session.

**Only a session connects.** The device is hardware (``teleop.devices``): an offline tool never
builds it.  A teleoperator takes the arm with :func:`claim` before it answers any operator (a busy
or faulted arm is one line, with libfranka's reason), and libfranka's blocking calls (connect, a
read outside the control loop, starting the control) run with SIGINT/SIGTERM at their default
action, since pylibfranka holds the interpreter while it waits: Ctrl-C ends the process at once.

**Faults.** A libfranka ``ControlException``/``NetworkException``, or the robot leaving ``Move``
(a reflex, the user stop), raises :class:`RobotFault` with the robot's reason on the next
:meth:`FrankaRobot.wait`; nothing is commanded after it.  ``automatic_error_recovery`` runs at the
start only with the ``recover`` option.  :meth:`FrankaRobot.close` sends a last command with
``motion_finished`` (the arm stops without a reflex); it may be called twice and after a fault.
"""

from __future__ import annotations

import contextlib
import ipaddress
import math
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from teleop.devices.models import Array
from teleop.errors import DeviceError

MAX_DOF = 3
AXES = ("x", "y", "z")
FORCE_SOURCES = ("spring", "ext", "joints")
RT_MODES = ("auto", "enforce", "ignore")
#: FR3 (and Panda) joint torque limits, N m.
TAU_MAX = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])
#: Collision thresholds (libfranka's cartesian_impedance_control example): N m per joint, N / N m.
COLLISION_TAU = [20.0, 20.0, 18.0, 18.0, 16.0, 14.0, 12.0]
COLLISION_F = [20.0, 20.0, 20.0, 25.0, 25.0, 25.0]
_HOSTNAME = re.compile(
    r"^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?)*$"
)
_ROBOT_DT = 0.001  # s: the robot's tick
STARTUP_READS = 10  # reads after the start during which the mode may still say Idle
SETTLE_TICKS = 1000  # robot ticks (1 s) the arm may take to come to rest when the session ends
REST_DQ = 0.01  # rad/s: every joint slower than this is at rest
#: FR3 limits a state is held to (Franka's datasheet; the Panda's are lower): the end-effector's
#: translational speed, m/s, and each joint's speed, rad/s.
MAX_EE_SPEED = 3.0
MAX_DQ = np.array([2.62, 2.62, 2.62, 2.62, 5.26, 4.18, 5.26])
#: A state is implausible beyond this multiple of the arm's limits (noise and a late tick's time
#: stamp stay far inside it; a pose off by centimetres in a millisecond does not).
PLAUSIBLE_MARGIN = 2.0
#: s a teleoperator waits for the arm to answer before a session (libfranka itself waits forever
#: on an arm another client holds).
CLAIM_TIMEOUT_S = 10.0


class RobotFault(DeviceError):
    """The arm stopped the session (a reflex, the user stop, a lost connection): its reason, one line."""


@dataclass(frozen=True)
class FrankaOptions:
    """What OPTIONS may set: ``key=value`` (or a flag) separated by ``,`` or ``:``."""

    stiffness: float = 1500.0  # N/m, translation (franky-sim's arm resists like ~100-200 N/m)
    damping: float = 80.0  # N s/m (about critical for the arm's ~1 kg at the end-effector)
    rot_stiffness: float = 30.0  # N m/rad, holds the starting orientation
    rot_damping: float = 4.0  # N m s/rad
    nullspace: float = 5.0  # N m/rad toward the starting joint angles, in the nullspace
    joint_damping: float = 0.5  # N m s/rad on every joint
    max_velocity: float = 0.25  # m/s, of the set-point
    max_force: float = 30.0  # N, of the impedance force
    max_offset: float = 0.05  # m, set-point from the measured end-effector
    max_torque_rate: float = 1.0  # N m per ms (libfranka's kMaxTorqueRate)
    cutoff: float = 30.0  # Hz, the reported force's low-pass
    force: str = "spring"  # spring | ext | joints
    rt: str = "auto"  # auto | enforce | ignore (libfranka's RealtimeConfig)
    max_stale: int = 20  # stale reads in a row that end the session
    recover: bool = False  # automatic_error_recovery at the start


#: key -> (low, high) of each number option (inclusive), what the error message names.
RANGES: dict[str, tuple[float, float]] = {
    "stiffness": (0.0, 3000.0),
    "damping": (0.0, 300.0),
    "rot_stiffness": (0.0, 300.0),
    "rot_damping": (0.0, 30.0),
    "nullspace": (0.0, 50.0),
    "joint_damping": (0.0, 10.0),
    "max_velocity": (0.001, 1.0),
    "max_force": (0.1, 100.0),
    "max_offset": (0.001, 0.2),
    "max_torque_rate": (0.01, 10.0),
    "cutoff": (0.1, 500.0),
    "max_stale": (1, 1000),
}


def _allowed_keys() -> str:
    return ", ".join(f.name for f in fields(FrankaOptions))


def parse_options(text: str) -> FrankaOptions:
    """OPTIONS as typed (``stiffness=400,damping=40,force=joints,recover``); DeviceError in one line."""
    opts = FrankaOptions()
    if not text:
        return opts
    seen: set[str] = set()
    for item in re.split(r"[,:]", text):
        if not item:
            continue
        key, eq, value = item.partition("=")
        key = key.strip()
        names = {f.name for f in fields(FrankaOptions)}
        if key not in names:
            raise DeviceError(f"robot 'franka': unknown option {key!r}; allowed: {_allowed_keys()}")
        if key in seen:
            raise DeviceError(f"robot 'franka': option {key!r} given twice")
        seen.add(key)
        if key == "recover":
            if eq and value not in ("1", "true", "yes"):
                raise DeviceError("robot 'franka': recover is a flag (recover, or recover=1)")
            opts = replace(opts, recover=True)
            continue
        if not eq or not value:
            raise DeviceError(f"robot 'franka': option {key!r} needs a value ({key}=VALUE)")
        if key == "force":
            if value not in FORCE_SOURCES:
                raise DeviceError(
                    f"robot 'franka': force must be one of {', '.join(FORCE_SOURCES)}, got {value!r}"
                )
            opts = replace(opts, force=value)
            continue
        if key == "rt":
            if value not in RT_MODES:
                raise DeviceError(f"robot 'franka': rt must be one of {', '.join(RT_MODES)}, got {value!r}")
            opts = replace(opts, rt=value)
            continue
        lo, hi = RANGES[key]
        try:
            num: float = int(value) if key == "max_stale" else float(value)
        except ValueError:
            kind = "an integer" if key == "max_stale" else "a number"
            raise DeviceError(f"robot 'franka': {key} must be {kind}, got {value!r}") from None
        if not (math.isfinite(num) and lo <= num <= hi):
            raise DeviceError(f"robot 'franka': {key} must be in [{lo:g}, {hi:g}], got {value!r}")
        opts = replace(opts, **{key: num})  # type: ignore[arg-type]
    return opts


def parse_arg(arg: str | None) -> tuple[str, FrankaOptions]:
    """``HOST[:OPTIONS]`` (an IPv6 address in brackets: ``[::1]:stiffness=300``) -> (host, options)."""
    if not arg:
        raise DeviceError(
            "robot 'franka' needs the robot's address: franka:HOST[:OPTIONS], e.g. franka:172.16.0.2"
        )
    if arg.startswith("["):
        host, sep, rest = arg[1:].partition("]")
        if not sep or (rest and not rest.startswith(":")):
            raise DeviceError(f"robot 'franka': bad address {arg!r}; an IPv6 address goes in brackets: [::1]")
        rest = rest[1:]
        try:
            ipaddress.IPv6Address(host)
        except ValueError:
            raise DeviceError(f"robot 'franka': {host!r} is not an IPv6 address") from None
    else:
        host, _, rest = arg.partition(":")
        try:
            ipaddress.IPv4Address(host)
        except ValueError:
            if not _HOSTNAME.match(host) or host.replace(".", "").isdigit():
                raise DeviceError(
                    f"robot 'franka': {host!r} is not an IPv4 address or a host name (franka:HOST[:OPTIONS])"
                ) from None
    return host, parse_options(rest)


def _import() -> Any:
    try:
        import pylibfranka
    except ImportError:
        raise DeviceError("robot 'franka' needs pylibfranka: pip install 'teleop[franka]'") from None
    return pylibfranka


def check(arg: str | None, dof: int) -> None:
    """HOST, OPTIONS and the DoF, and that pylibfranka imports: before any session, without touching
    the robot (connecting may take it over)."""
    if not 1 <= dof <= MAX_DOF:
        raise DeviceError(
            f"robot 'franka' drives 1 to {MAX_DOF} DoF (x, y, z of the end-effector), got {dof}"
        )
    parse_arg(arg)
    _import()


def _realtime(lib: Any, mode: str) -> tuple[Any, str]:
    """libfranka's RealtimeConfig: ``auto`` enforces on a PREEMPT_RT kernel, else ignores."""
    if mode == "auto":
        try:
            rt = Path("/sys/kernel/realtime").read_text().strip() == "1"
        except OSError:
            rt = False
        mode = "enforce" if rt else "ignore"
    return (lib.RealtimeConfig.kEnforce if mode == "enforce" else lib.RealtimeConfig.kIgnore), mode


def _reason(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


def _finite(*arrays: Array) -> bool:
    return all(bool(np.all(np.isfinite(a))) for a in arrays)


@contextlib.contextmanager
def _blocking() -> Iterator[None]:
    """Around one of libfranka's blocking calls: SIGINT and SIGTERM at their default action (the
    process ends at once).  pylibfranka keeps the interpreter while it waits, so a Python handler
    (KeyboardInterrupt, asyncio's) would run only when the call returns, which on a busy or silent
    arm is never.  Only the main thread may set handlers; elsewhere this does nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    sigs = (signal.SIGINT, signal.SIGTERM)
    old = [signal.getsignal(sig) for sig in sigs]
    for sig in sigs:
        signal.signal(sig, signal.SIG_DFL)
    try:
        yield
    finally:
        for sig, handler in zip(sigs, old, strict=True):
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)


#: What :func:`claim` runs in a child process: connect, read one state, say the mode or the error.
_PROBE = """
import sys
try:
    import pylibfranka as p
    s = p.Robot(sys.argv[1], p.RealtimeConfig.kIgnore).read_once()
    print("mode", str(s.robot_mode).rpartition(".")[2], str(s.current_errors) or str(s.last_motion_errors))
except Exception as e:
    print("error", " ".join(str(e).split()) or type(e).__name__)
"""

#: host -> a robot connected by :func:`claim`, which the session's device takes.
_claimed: dict[str, Any] = {}


def _probe(host: str, timeout_s: float) -> None:
    """Ask the arm in a child process, which can be stopped: libfranka waits forever on an arm
    another client holds, and keeps the interpreter while it does.  DeviceError with its reason."""
    try:
        r = subprocess.run(
            [sys.executable, "-c", _PROBE, host], capture_output=True, text=True, timeout=timeout_s
        )
    except subprocess.TimeoutExpired:
        raise DeviceError(
            f"robot 'franka' at {host}: no answer in {timeout_s:g} s: another client holds the arm "
            "(libfranka takes one at a time), or the address is not a Franka's"
        ) from None
    except OSError as e:
        raise DeviceError(f"robot 'franka' at {host}: cannot start the connection check: {e}") from None
    words = (r.stdout.strip().splitlines() or [""])[-1].split(" ", 2)
    if words[0] == "error":
        raise DeviceError(f"robot 'franka' at {host}: cannot connect: {' '.join(words[1:])}")
    if words[0] != "mode":
        raise DeviceError(
            f"robot 'franka' at {host}: the connection check failed (exit status {r.returncode})"
        )


def claim(arg: str | None, timeout_s: float = CLAIM_TIMEOUT_S) -> Callable[[], None]:
    """Take the arm before a session answers anyone: check it answers (in a child process, bounded
    by ``timeout_s``), then connect and keep the connection for the session's device; a busy,
    unreachable or faulted arm is one DeviceError line with libfranka's reason.  Returns the
    release (the connection is let go if no session took it)."""
    host, opts = parse_arg(arg)
    lib = _import()
    _probe(host, timeout_s)
    cfg, _ = _realtime(lib, opts.rt)
    try:
        with _blocking():
            robot = lib.Robot(host, cfg)
            state = robot.read_once()
    except Exception as e:  # libfranka's NetworkException, IncompatibleVersion, RealtimeException
        raise DeviceError(f"robot 'franka' at {host}: cannot connect: {_reason(e)}") from None
    if _in_error(state) and not opts.recover:
        raise DeviceError(_error_line(host, state))
    _claimed[host] = robot

    def release() -> None:
        _claimed.pop(host, None)

    return release


def _mode_name(state: Any) -> str:
    return str(state.robot_mode).rpartition(".")[2]


def _in_error(state: Any) -> bool:
    return _mode_name(state) in ("Reflex", "UserStopped") or bool(state.current_errors)


def _error_line(host: str, state: Any) -> str:
    return (
        f"robot 'franka' at {host} is in {_mode_name(state)} "
        f"({state.current_errors or state.last_motion_errors}); clear it, or add the option recover"
    )


class FrankaRobot:
    """The teleoperator's robot: a Franka arm under Cartesian impedance (module docstring)."""

    role = "robot"
    #: The robot's clock paces the runner: :meth:`wait` returns once per robot millisecond.
    paced = True

    def __init__(self, dof: int, dt: float, arg: str | None, *, robot: Any = None, lib: Any = None) -> None:
        """``robot``/``lib``: a connected robot and its module (tests); else pylibfranka connects to HOST."""
        if not 1 <= dof <= MAX_DOF:
            raise DeviceError(
                f"robot 'franka' drives 1 to {MAX_DOF} DoF (x, y, z of the end-effector), got {dof}"
            )
        self.host, self.opts = parse_arg(arg)
        self.lib = lib if lib is not None else _import()
        self.dof, self.dt = dof, dt
        o = self.opts
        self.rt_mode = "test"
        if robot is None:
            cfg, self.rt_mode = _realtime(self.lib, o.rt)
            robot = _claimed.pop(self.host, None)  # taken before the session (claim)
            if robot is None:
                try:
                    with _blocking():
                        robot = self.lib.Robot(self.host, cfg)
                except Exception as e:  # libfranka's NetworkException, IncompatibleVersion, RealtimeException
                    raise DeviceError(
                        f"robot 'franka' at {self.host}: cannot connect: {_reason(e)}"
                    ) from None
        self.robot = robot
        try:
            with _blocking():
                state = robot.read_once()
                if _in_error(state):
                    if not o.recover:
                        raise DeviceError(_error_line(self.host, state))
                    robot.automatic_error_recovery()
                    state = robot.read_once()
                robot.set_collision_behavior(COLLISION_TAU, COLLISION_TAU, COLLISION_F, COLLISION_F)
                self.model = robot.load_model()
        except DeviceError:
            raise
        except Exception as e:
            raise DeviceError(f"robot 'franka' at {self.host}: {_reason(e)}") from None
        pose = np.array(state.O_T_EE, dtype=float).reshape(4, 4).T
        q0 = np.array(state.q, dtype=float)
        if not _finite(pose, q0):
            raise DeviceError(f"robot 'franka' at {self.host}: the starting state is not finite")
        self.x0 = pose[:3, 3].copy()  # the channel's origin
        self.r0 = pose[:3, :3].copy()  # the orientation held
        self.q0 = q0
        self.x_d = self.x0.copy()  # the set-point
        self.axes = np.arange(dof)
        self.ctl: Any = None
        self.fault: str | None = None
        self.closed = False
        self._state: Any = None  # the newest read
        self._fresh = False  # a read not yet commanded
        self._good = False  # whether the newest read was finite
        self._x = self.x0.copy()
        self._xdot = np.zeros(3)
        self._j = np.zeros((6, 7))
        self._q = q0.copy()
        self._r = self.r0.copy()
        self._dq = np.zeros(7)
        self._coriolis = np.zeros(7)
        self._robot_dt = _ROBOT_DT
        self._tau = np.zeros(7)  # the last torque commanded
        self._f = np.zeros(dof)  # the filtered force (the last good one)
        self._zero = np.zeros(dof)
        self._last_now: float | None = None
        self._robot_time: float | None = None
        self._stale_run = 0
        self._since_good = 0.0  # s of robot time since the last good state (what it may have moved)
        # figures
        self.reads = 0
        self.stale = 0
        self.implausible = 0  # of the stale reads: finite, but not a state the arm can be in
        self.missed_robot_ticks = 0
        self.success_rate = float(state.control_command_success_rate)
        self.min_success_rate = 1.0
        self.max_drift = 0.0  # m, |x_d - x|
        self.drift = 0.0
        self.saturated = {"velocity": 0, "offset": 0, "force": 0, "torque": 0, "torque_rate": 0}
        self.port_energy = 0.0
        self.min_port_energy = 0.0
        self.max_force = 0.0

    # --- the robot's clock ----------------------------------------------------------------------
    def _fail(self, reason: str) -> RobotFault:
        self.fault = reason
        self.ctl = None  # nothing is commanded after a fault
        return RobotFault(f"robot 'franka' at {self.host}: {reason}")

    def wait(self, timeout_s: float = 0.1) -> bool:
        """Block until the robot's next tick (``readOnce``) and take its state; True when one came.
        ``timeout_s`` is not used: libfranka's own receive timeout raises (a fault) instead."""
        if self.fault is not None:
            raise RobotFault(f"robot 'franka' at {self.host}: {self.fault}")
        if self.closed:
            raise self._fail("closed")
        try:
            if self.ctl is None:
                with _blocking():
                    self.ctl = self.robot.start_torque_control()
            state, duration = self.ctl.readOnce()
        except Exception as e:  # ControlException (a reflex), NetworkException (the link to the arm)
            raise self._fail(self._describe_fault(e)) from None
        mode = _mode_name(state)
        if mode in ("Reflex", "UserStopped") or (mode in ("Idle", "Other") and self.reads >= STARTUP_READS):
            raise self._fail(self._describe_mode(state, mode))
        self.reads += 1
        self._take(state, duration)
        self._fresh = True
        return True

    def _describe_fault(self, e: BaseException) -> str:
        try:
            with _blocking():
                state = self.robot.read_once()
            errors = str(state.last_motion_errors) or str(state.current_errors)
        except Exception:
            errors = ""
        what = _reason(e)
        return f"{what} ({errors})" if errors and errors not in what else what

    def _describe_mode(self, state: Any, mode: str) -> str:
        errors = str(state.current_errors) or str(state.last_motion_errors)
        if mode == "UserStopped":
            return "the user stop is pressed"
        return (
            f"reflex: {errors}"
            if mode == "Reflex"
            else f"the robot left Move ({mode}{': ' + errors if errors else ''})"
        )

    def _take(self, state: Any, duration: Any) -> None:
        """The newest state, checked: a non-finite or implausible value makes the read stale
        (counted, and nothing of it used)."""
        self._state = state
        try:
            dt_robot = float(duration.to_sec())
            pose = np.array(state.O_T_EE, dtype=float).reshape(4, 4).T
            q = np.array(state.q, dtype=float)
            dq = np.array(state.dq, dtype=float)
            j = np.array(self.model.zero_jacobian(state), dtype=float).reshape(7, 6).T
            cor = np.array(self.model.coriolis(state), dtype=float)
            rate = float(state.control_command_success_rate)
        except (TypeError, ValueError) as e:
            raise self._fail(f"unreadable state: {_reason(e)}") from None
        if dt_robot > 1.5 * _ROBOT_DT:
            self.missed_robot_ticks += round(dt_robot / _ROBOT_DT) - 1
        if math.isfinite(rate):
            self.success_rate = rate
            self.min_success_rate = min(self.min_success_rate, rate)
        finite = _finite(pose, q, dq, j, cor) and math.isfinite(dt_robot)
        if finite:
            self._since_good += min(max(dt_robot, _ROBOT_DT), 1.0)
        self._good = finite and self._plausible(pose[:3, 3], q, dq)
        if not self._good:
            self.stale += 1
            self.implausible += finite
            self._stale_run += 1
            return
        self._stale_run, self._since_good = 0, 0.0
        self._robot_dt = min(max(dt_robot, _ROBOT_DT), 0.1)
        self._x = pose[:3, 3]
        self._r = pose[:3, :3]
        self._q, self._dq, self._j, self._coriolis = q, dq, j, cor
        self._xdot = j[:3] @ dq

    def _plausible(self, x: Array, q: Array, dq: Array) -> bool:
        """Whether a finite state is one the arm can be in: since the last good state (the robot
        time ``_since_good``) the end-effector and each joint moved no further than their speed
        limits allow, and no joint is faster than its limit (each with :data:`PLAUSIBLE_MARGIN`)."""
        t, m = self._since_good, PLAUSIBLE_MARGIN
        return (
            float(np.linalg.norm(x - self._x)) <= m * MAX_EE_SPEED * t
            and bool(np.all(np.abs(q - self._q) <= m * MAX_DQ * t))
            and bool(np.all(np.abs(dq) <= m * MAX_DQ))
        )

    # --- the device interface -------------------------------------------------------------------
    def _measured(self) -> Array | None:
        """This read's force along the channel's axes (on the environment), or None if not finite."""
        o, s = self.opts, self._state
        if o.force == "spring":
            f = self._spring()
        elif o.force == "ext":
            f = -np.array(s.O_F_ext_hat_K, dtype=float)[:3]
        else:
            tau = np.array(s.tau_J, dtype=float) - np.array(s.tau_J_d, dtype=float)
            tau -= np.array(self.model.gravity(s), dtype=float)
            f = -np.linalg.pinv(self._j[:3].T) @ tau
        f = f[: self.dof]
        return f if _finite(f) else None

    def _spring(self) -> Array:
        f = self.opts.stiffness * (self.x_d - self._x)
        n = float(np.linalg.norm(f))
        out: Array = f * (self.opts.max_force / n) if n > self.opts.max_force else f
        return out

    def affine(self, now: float) -> tuple[Array, Array]:
        if not self._fresh:  # not paced by a runner: the robot's clock paces this call instead
            self.wait()
        f = self._measured() if self._good else None
        if f is None:
            if self._good:  # the state was finite, the force was not
                self.stale += 1
            return self._f, self._zero
        a = self._robot_dt / (self._robot_dt + 1.0 / (2.0 * math.pi * self.opts.cutoff))
        self._f = self._f + a * (f - self._f)
        return self._f, self._zero

    def advance(self, now: float, v: Array, f: Array) -> None:
        """Move the set-point by ``v`` over the session time since the last tick, then command."""
        if self.ctl is None or not self._fresh:
            return  # closed or faulted (nothing is commanded), or no read to answer
        dt = self.dt if self._last_now is None else min(max(now - self._last_now, 0.0), 0.1)
        self._last_now = now
        vv = np.asarray(v, dtype=float)
        if not _finite(vv):
            vv = self._zero
        o = self.opts
        sp = float(np.linalg.norm(vv))
        if sp > o.max_velocity:
            vv = vv * (o.max_velocity / sp)
            self.saturated["velocity"] += 1
        ff = np.asarray(f, dtype=float)
        if _finite(ff):
            e = self.port_energy + dt * float(vv @ ff)
            self.port_energy = e
            self.min_port_energy = min(self.min_port_energy, e)
            self.max_force = max(self.max_force, float(np.max(np.abs(ff))))
        if self._good:
            self.x_d[: self.dof] += vv * dt
            off = self.x_d - self._x
            d = float(np.linalg.norm(off))
            if d > o.max_offset:
                self.x_d = self._x + off * (o.max_offset / d)
                self.saturated["offset"] += 1
                d = o.max_offset
            self.drift = d
            self.max_drift = max(self.max_drift, d)
            tau = self._torque()
        else:
            tau = self._tau  # stale: the last torque once more
        self._write(tau, finished=False)
        if self._stale_run >= o.max_stale:
            self.fault = f"{self._stale_run} robot states in a row were stale (not finite, or not plausible)"
        self._fresh = False

    def hold(self) -> None:
        """Answer a read without a tick (the robot ran ahead of the session clock): the set-point
        stays where it is, the impedance is commanded from the fresh state."""
        if self.ctl is None or not self._fresh:
            return
        self._write(self._torque() if self._good else self._tau, finished=False)
        self._fresh = False

    def _torque(self) -> Array:
        o = self.opts
        f = o.stiffness * (self.x_d - self._x) - o.damping * self._xdot
        n = float(np.linalg.norm(f))
        if n > o.max_force:
            f = f * (o.max_force / n)
            self.saturated["force"] += 1
        r, r0 = self._r, self.r0
        e_rot = 0.5 * (
            np.cross(r[:, 0], r0[:, 0]) + np.cross(r[:, 1], r0[:, 1]) + np.cross(r[:, 2], r0[:, 2])
        )
        w = self._j[3:] @ self._dq
        m = o.rot_stiffness * e_rot - o.rot_damping * w
        jt = self._j.T
        tau: Array = jt @ np.concatenate([f, m])
        ns = np.eye(7) - jt @ np.linalg.pinv(jt)
        tau += ns @ (o.nullspace * (self.q0 - self._q) - 2.0 * math.sqrt(o.nullspace) * self._dq)
        tau += self._coriolis - o.joint_damping * self._dq
        return tau

    def _limit(self, tau: Array) -> Array:
        step = self.opts.max_torque_rate * self._robot_dt / _ROBOT_DT
        d = np.clip(tau - self._tau, -step, step)
        if np.any(d != tau - self._tau):
            self.saturated["torque_rate"] += 1
        out = np.clip(self._tau + d, -TAU_MAX, TAU_MAX)
        if np.any(out != self._tau + d):
            self.saturated["torque"] += 1
        return out

    def _write(self, tau: Array, finished: bool) -> None:
        out = self._limit(tau) if _finite(tau) else self._tau
        cmd = self.lib.Torques(out.tolist())
        cmd.motion_finished = finished
        try:
            self.ctl.writeOnce(cmd)
        except Exception as e:
            self._fail(self._describe_fault(e))  # raised at the next wait: the tick is over
            return
        self._tau = out

    def close(self) -> None:
        """End the motion: one last command with ``motion_finished`` (after a read, which libfranka
        needs before each write), so the arm stops without a reflex.  Safe twice and after a fault."""
        if self.closed:
            return
        self.closed = True
        ctl, self.ctl = self.ctl, None
        try:
            if ctl is not None and self.fault is None:
                self._settle(ctl)  # ends on a read this last command answers
                cmd = self.lib.Torques(self._tau.tolist())  # the last torque, not a new one
                cmd.motion_finished = True
                ctl.writeOnce(cmd)
        except Exception as e:
            self.fault = f"while stopping: {_reason(e)}"
        finally:
            # Let go of the connection: libfranka takes one client at a time, and a robot object
            # kept alive keeps the arm from the next (the next session, or another program).
            del ctl
            self.robot = self.model = None

    def _settle(self, ctl: Any) -> None:
        """Bring the arm to rest before the motion ends: hold the set-point where the arm is, under
        the same impedance, until every joint is below :data:`REST_DQ` (at most
        :data:`SETTLE_TICKS` robot ticks), so a session that ends mid-stroke stops smoothly.  It
        returns on a read not yet answered: libfranka wants one command for every read."""
        if self._good:
            self.x_d = self._x.copy()
        for i in range(SETTLE_TICKS):
            state, duration = ctl.readOnce()
            self._take(state, duration)
            if i == SETTLE_TICKS - 1 or (self._good and float(np.max(np.abs(self._dq))) < REST_DQ):
                return  # the caller's last command answers this read
            tau = self._limit(self._torque()) if self._good else self._tau
            ctl.writeOnce(self.lib.Torques(tau.tolist()))
            self._tau = tau

    #: Ticks between two samples of :meth:`state` in the log (100 Hz): enough for a 3D view and a
    #: learner at up to 100 frames a second, at a tenth of the log's per-tick cost.
    state_every = 10

    def state(self) -> dict[str, list[float]]:
        """The arm's state for the log (``/teleoperator/state``): the end effector's pose (x, y, z,
        qx, qy, qz, qw, base frame), joint positions ``q`` (rad), velocities ``dq`` (rad/s), measured
        torques ``tau`` (Nm), and the impedance set-point (m).  From the newest good read: no I/O."""
        s = self._state
        tau = [float(t) for t in s.tau_J] if s is not None else [math.nan] * 7
        return {
            "pose": [*map(float, self._x), *_quaternion(self._r)],
            "q": self._q.tolist(),
            "dq": self._dq.tolist(),
            "tau": tau,
            "setpoint": self.x_d.tolist(),
        }

    def status(self) -> str:
        """A few words for the live status line."""
        return (
            f"robot success {self.success_rate:.3f}, missed {self.missed_robot_ticks}, "
            f"drift {1e3 * self.drift:.1f} mm{', FAULT' if self.fault else ''}"
        )

    def summary(self) -> dict[str, Any]:
        o = self.opts
        return {
            "robot": "franka",
            "host": self.host,
            "realtime": self.rt_mode,
            "axes": list(AXES[: self.dof]),
            "force_source": o.force,
            "force_cutoff_hz": o.cutoff,
            "stiffness_N_per_m": o.stiffness,
            "damping_Ns_per_m": o.damping,
            "max_velocity_m_s": o.max_velocity,
            "max_force_N": o.max_force,
            "max_offset_m": o.max_offset,
            "robot_ticks": self.reads,
            "control_command_success_rate": self.success_rate,
            "min_success_rate": self.min_success_rate,
            "missed_robot_ticks": self.missed_robot_ticks,
            "stale_reads": self.stale,
            "implausible_reads": self.implausible,
            "saturated": dict(self.saturated),
            "drift_m": self.drift,
            "max_drift_m": self.max_drift,
            "port_energy_J": self.port_energy,
            "min_port_energy_J": self.min_port_energy,
            "max_port_force_N": self.max_force,
            "setpoint_m": (self.x_d - self.x0).tolist(),
            "reflex": self.fault,
        }


def _quaternion(r: Array) -> list[float]:
    """A rotation matrix as a unit quaternion (x, y, z, w): Foxglove's order."""
    w = math.sqrt(max(0.0, 1.0 + r[0, 0] + r[1, 1] + r[2, 2])) / 2.0
    x = math.copysign(math.sqrt(max(0.0, 1.0 + r[0, 0] - r[1, 1] - r[2, 2])) / 2.0, r[2, 1] - r[1, 2])
    y = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] + r[1, 1] - r[2, 2])) / 2.0, r[0, 2] - r[2, 0])
    z = math.copysign(math.sqrt(max(0.0, 1.0 - r[0, 0] - r[1, 1] + r[2, 2])) / 2.0, r[1, 0] - r[0, 1])
    return [x, y, z, w]
