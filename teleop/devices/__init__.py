"""Devices: the operator's HSI (with its human) and the teleoperator's robot, behind one interface.

A device is what a node drives at its end of the channel.  Each tick it gives its response to the
port as an affine map of the port's variable, computed from its state alone, then is advanced with
the values the port settled on (the form of ``teleop.devices.models``), so a stiff device keeps the
closed-form port solution of ``teleop.session.node``:

* **HSI** (operator side): ``affine(now) -> (v0, Y)`` with ``v = v0 - Y F`` this tick (its velocity,
  yielding to the force it renders through the admittance ``Y >= 0``), then ``advance(now, v, F)``
  renders ``F``.  A real device that only measures its velocity has ``Y = 0``.
* **Robot** (teleoperator side): ``affine(now) -> (f0, Z)`` with ``F = f0 + Z v`` this tick (the
  contact force it reports for a commanded velocity ``v``, ``Z >= 0``), then ``advance(now, v, F)``
  commands ``v``.

``Y`` and ``Z`` are per DoF (diagonal).  A device may also have ``summary() -> dict`` (written to the
logs and the sim results) and ``close()``.

**Choosing one.** ``--hsi SPEC`` and ``--robot SPEC``; ``SPEC`` is ``NAME[:ARG]`` where ``NAME`` is a
built-in (:data:`BUILTIN`), an entry point of the group ``teleop.devices`` (a third-party package
registers ``name = "package.module:Class"`` there), or ``package.module:Class[:ARG]``.  The object
named must have ``role = "hsi"`` or ``"robot"`` and is called ``factory(dof=..., dt=..., arg=...)``.
The default is the scenario's own model (named like the scenario).  A spec only ever comes from the
local command line: nothing from the network names a device, a module or a file.

**Hardware.** Only a session (``teleop teleoperator``, ``teleop operator``, and the two processes
``teleop run`` starts) builds a device that is hardware; an offline tool (``teleop sim``,
``experiment``, ``sweep``, ``report``, ``teleop run``'s report) refuses it, or skips what would
build it, in one line, so it never connects to an arm.  A built-in says so in :data:`BUILTIN`
(``franka`` is hardware; the models and ``mujoco`` are not); a third-party factory declares
``hardware = False`` to be simulated offline, and one that does not declare it is taken for
hardware (the safe default: a tool that cannot tell never builds it).

**A real driver** is wrapped by :class:`DriverHsi` (a device that reports its velocity and renders a
force) or :class:`DriverRobot` (one that takes a velocity command and reports a force), which add
the safety rules a real device needs: zero force (and no motion) when the driver's data is stale or
implausible, and saturation of what is commanded.
"""

from __future__ import annotations

import importlib
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import metadata
from typing import Any, Protocol

import numpy as np

from teleop.devices.models import (
    Array,
    LtiEnvironment,
    ProtocolEnvironment,
    ProtocolHuman,
    ProtocolPlan,
    StepHuman,
)
from teleop.errors import DeviceError as DeviceError  # a device's error, where its users look
from teleop.limits import MAX_DOF

ROLES = ("hsi", "robot")
ENTRY_POINT_GROUP = "teleop.devices"
MAX_SPEC_LEN = 512  # a device spec is a local name, module path or file path: bounded like one
_MODULE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")
_ATTR = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")


class Device(Protocol):
    """What a node drives: the HSI (``v = v0 - Y F``) or the robot (``F = f0 + Z v``), see above."""

    def affine(self, now: float) -> tuple[Array, Array]: ...

    def advance(self, now: float, v: Array, f: Array) -> None: ...


Factory = Callable[..., Device]


@dataclass(frozen=True)
class Builtin:
    factory: Factory
    usage: str  # how it is named on the command line, e.g. "mujoco[:SCENE.xml]"
    description: str
    check: Callable[[str | None, int], None] | None = None  # checks ARG (and a DoF) before a session
    max_dof: int = MAX_DOF  # the most DoF it drives: a robot refuses a session with more (its envelope)
    hardware: bool = False  # it drives a real device: only a session builds it (see above)
    #: Takes the device before a session answers anyone (e.g. connects to the arm and checks it),
    #: DeviceError in one line if it cannot; returns a release callable.  Hardware only.
    claim: Callable[[str | None], Callable[[], None]] | None = None


def _no_arg(name: str, arg: str | None) -> None:
    if arg is not None:
        raise DeviceError(f"{name!r} takes no argument, got {name}:{arg}")


def _step_human(dof: int, dt: float, arg: str | None, **_: Any) -> Device:
    _no_arg("step", arg)
    return StepHuman(dof, dt)


def _protocol_human(dof: int, dt: float, arg: str | None, seed: int = 0, variation: float = 0.0) -> Device:
    _no_arg("protocol", arg)
    return ProtocolHuman(dof, dt, plan=ProtocolPlan.draw(seed, variation))


def _lti_env(dof: int, dt: float, arg: str | None, **_: Any) -> Device:
    _no_arg("step", arg)
    return LtiEnvironment(dof, dt)


def _protocol_env(dof: int, dt: float, arg: str | None, seed: int = 0, variation: float = 0.0) -> Device:
    _no_arg("protocol", arg)
    return ProtocolEnvironment(dof, dt, plan=ProtocolPlan.draw(seed, variation))


def _mujoco(dof: int, dt: float, arg: str | None, seed: int = 0, variation: float = 0.0) -> Device:
    from teleop.devices.mujoco_robot import (
        MujocoRobot,  # imports mujoco: only a teleoperator that asks pays for it
    )

    plan = ProtocolPlan.draw(seed, variation)  # the seeded human's phase times (scripted: 5 s, 10 s)
    return MujocoRobot(dof=dof, dt=dt, arg=arg, foam_at=plan.t_foam, wall_at=plan.t_wall)


def _franka(dof: int, dt: float, arg: str | None, **_: Any) -> Device:
    from teleop.devices.franka import (
        FrankaRobot,  # imports pylibfranka: only a teleoperator that asks pays for it
    )

    return FrankaRobot(dof=dof, dt=dt, arg=arg)


def _franka_claim(arg: str | None) -> Callable[[], None]:
    from teleop.devices.franka import claim as franka_claim

    return franka_claim(arg)


def _franka_check(arg: str | None, dof: int) -> None:
    from teleop.devices.franka import check as franka_check

    franka_check(arg, dof)


def _mujoco_check(arg: str | None, dof: int) -> None:
    from teleop.devices.mujoco_robot import check_scene

    check_scene(arg, dof)


#: The built-in devices by role and name; the scenarios' models are named like the scenarios.
BUILTIN: dict[str, dict[str, Builtin]] = {
    "hsi": {
        "step": Builtin(_step_human, "step", "Section V velocity step"),
        "protocol": Builtin(_protocol_human, "protocol", "Section VI operator (seeded by the session)"),
    },
    "robot": {
        "step": Builtin(_lti_env, "step", "ideal robot in 1/(s+1)"),
        "protocol": Builtin(_protocol_env, "protocol", "ideal robot, Section VI scene (seeded)"),
        "mujoco": Builtin(
            _mujoco,
            "mujoco[:SCENE.xml]",
            "MuJoCo end effector, default scene: free space, foam, wall",
            _mujoco_check,
            max_dof=3,
        ),
        "franka": Builtin(
            _franka,
            "franka:HOST[:OPTIONS]",
            "Franka arm (FR3, Panda) through pylibfranka, Cartesian impedance, paced by the robot",
            _franka_check,
            max_dof=3,
            hardware=True,
            claim=_franka_claim,
        ),
    },
}


@dataclass(frozen=True)
class DeviceSpec:
    """A resolved ``--hsi``/``--robot`` value: what to call, with which argument."""

    role: str
    spec: str  # as given: the label in the logs
    factory: Factory
    arg: str | None
    builtin: bool = False
    hardware: bool = True  # the built-in's flag, or the factory's ``hardware`` (default: it is)

    def build(self, dof: int, dt: float, seed: int = 0, variation: float = 0.0) -> Device:
        """The device for ``dof`` DoF at period ``dt``; DeviceError says what went wrong.  A built-in
        also gets the session's ``seed`` and ``variation`` (the seeded Section VI performance);
        a third-party factory is called with ``dof``, ``dt`` and ``arg`` only."""
        ctx = {"seed": seed, "variation": variation} if self.builtin else {}
        try:
            dev = self.factory(dof=dof, dt=dt, arg=self.arg, **ctx)
        except DeviceError:
            raise
        except (ValueError, TypeError, OSError, RuntimeError, ImportError) as e:
            raise DeviceError(f"{self.role} {self.spec!r}: {e}") from None
        if not callable(getattr(dev, "affine", None)) or not callable(getattr(dev, "advance", None)):
            raise DeviceError(f"{self.role} {self.spec!r} has no affine(now) and advance(now, v, f) methods")
        return dev


def _entry_points() -> dict[str, metadata.EntryPoint]:
    return {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP)}


def available(role: str) -> str:
    """What ``--ROLE`` accepts, for help texts and error messages."""
    names = [b.usage for b in BUILTIN[role].values()]
    names += [f"{n} (entry point)" for n in sorted(_entry_points()) if n not in BUILTIN[role]]
    return ", ".join(names) + ", or package.module:Class[:ARG]"


def _checked(obj: Any, role: str, where: str) -> Factory:
    """``obj`` if it is a factory of a ``role`` device, else DeviceError."""
    declared = getattr(obj, "role", None)
    if declared != role:
        raise DeviceError(
            f"{where} is not a {role} device: it must declare role = {role!r} (it has {declared!r})"
        )
    if not callable(obj):
        raise DeviceError(f"{where} is not callable: it must be a class or a function building the device")
    return obj  # type: ignore[no-any-return]


def resolve(spec: str, role: str) -> DeviceSpec:
    """Resolve a ``--hsi``/``--robot`` value (local command line only); DeviceError lists the choices."""
    if role not in ROLES:
        raise DeviceError(f"role must be one of {', '.join(ROLES)}, got {role!r}")
    if not spec or len(spec) > MAX_SPEC_LEN or not spec.isprintable():
        raise DeviceError(f"{role} must be a printable name of 1 to {MAX_SPEC_LEN} characters")
    name, _, rest = spec.partition(":")
    arg = rest if rest else None
    if name in BUILTIN[role]:
        b = BUILTIN[role][name]
        return DeviceSpec(role, spec, b.factory, arg, builtin=True, hardware=b.hardware)
    eps = _entry_points()
    if name in eps:
        try:
            obj = eps[name].load()
        except Exception as e:  # a broken third-party package: say which, do not crash
            raise DeviceError(f"{role} {name!r}: entry point {eps[name].value} failed to load: {e}") from None
        factory = _checked(obj, role, f"entry point {name!r}")
        return DeviceSpec(role, spec, factory, arg, hardware=_declares_hardware(factory))
    if not rest:
        raise DeviceError(f"unknown {role} {spec!r}; available: {available(role)}")
    attr, _, arg2 = rest.partition(":")
    if not _MODULE.match(name) or not _ATTR.match(attr):
        raise DeviceError(f"unknown {role} {spec!r}; available: {available(role)}")
    try:
        obj = importlib.import_module(name)
    except Exception as e:
        raise DeviceError(f"{role} {spec!r}: cannot import module {name!r}: {e}") from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise DeviceError(f"{role} {spec!r}: module {name!r} has no {attr!r}")
        obj = getattr(obj, part)
    factory = _checked(obj, role, f"{name}:{attr}")
    return DeviceSpec(role, spec, factory, arg2 if arg2 else None, hardware=_declares_hardware(factory))


def _declares_hardware(factory: Factory) -> bool:
    """A third-party factory is hardware unless it says ``hardware = False`` (module docstring)."""
    return getattr(factory, "hardware", True) is not False


def offline(spec: str, role: str, tool: str) -> DeviceSpec:
    """``spec`` resolved for an offline ``tool`` (``teleop sim``, say), which never builds hardware:
    DeviceError in one line if it is."""
    ds = resolve(spec, role)
    if ds.hardware:
        raise DeviceError(
            f"{role} {spec!r} is hardware: {tool} never connects to it (only a session drives it: "
            "teleop teleoperator, or teleop run)"
        )
    return ds


def is_hardware(spec: str | None, role: str) -> bool:
    """Whether a spec read from a log names hardware, without importing anything: a built-in's own
    flag; any other name (a module, an entry point) is taken for hardware."""
    if spec is None:
        return False
    builtin = BUILTIN.get(role, {}).get(spec.partition(":")[0])
    return builtin.hardware if builtin is not None else True


def claim(spec: str | None, role: str) -> Callable[[], None]:
    """Take a hardware built-in before a session answers anyone (it connects and checks the
    device: a busy arm is one DeviceError line, before any welcome); returns its release.  A
    device without a claim (a model, MuJoCo, a third-party one) is built at the session's start."""
    builtin = BUILTIN.get(role, {}).get((spec or "").partition(":")[0])
    if spec is None or builtin is None or builtin.claim is None:
        return lambda: None
    return builtin.claim(spec.partition(":")[2] or None)


def check(spec: str, role: str, dof: int = 1) -> DeviceSpec:
    """Resolve ``spec`` and check a built-in's argument (a scene file, say) and, when known, the DoF
    now, so a bad value stops the command before a session; a third-party device is only imported,
    never built, here (building one may open hardware)."""
    ds = resolve(spec, role)
    name, _, _ = spec.partition(":")
    builtin = BUILTIN[role].get(name)
    if builtin is not None and builtin.check is not None:
        builtin.check(ds.arg, dof)
    elif builtin is not None and ds.arg is not None:
        raise DeviceError(f"{role} {name!r} takes no argument, got {spec!r}")
    return ds


def max_dof(spec: str | None, role: str) -> int:
    """The most DoF the device named by ``spec`` drives (a built-in's own bound; a third-party
    device's is not known before it is built: :data:`MAX_DOF`)."""
    builtin = BUILTIN[role].get((spec or "").partition(":")[0])
    return builtin.max_dof if builtin is not None else MAX_DOF


def builtin_only(spec: str | None, role: str) -> str | None:
    """``spec`` if it names a built-in device, else None: for specs read from a log file, which may
    name a built-in (and its scene) but never a module to import."""
    if spec is None or spec.partition(":")[0] not in BUILTIN.get(role, {}):
        return None
    return spec


def make(role: str, spec: str, dof: int, dt: float, seed: int = 0, variation: float = 0.0) -> Device:
    """Resolve and build one device: ``make("robot", "mujoco", 2, 0.001)``."""
    return resolve(spec, role).build(dof, dt, seed, variation)


def describe(dev: dict[str, Any]) -> str | None:
    """One line on a device that keeps an observer of its own port (the MuJoCo robot, a Franka arm),
    else None."""
    if dev.get("robot") == "franka":
        return (
            f"robot {dev['spec']}: success rate {dev['control_command_success_rate']:.3f} "
            f"(min {dev['min_success_rate']:.3f}), missed robot ticks {dev['missed_robot_ticks']}, "
            f"stale reads {dev['stale_reads']}"
            + (f" (implausible {n})" if (n := dev.get("implausible_reads")) else "")
            + f", drift {1e3 * dev['drift_m']:.1f} mm "
            f"(max {1e3 * dev['max_drift_m']:.1f}), port energy min {dev['min_port_energy_J']:.3e} J, "
            f"reflex {dev['reflex'] or 'none'}"
        )
    if "min_port_energy_J" not in dev:
        return None
    pen = ", ".join(f"{k} {1e3 * v:.1f} mm" for k, v in dev.get("max_penetration_m", {}).items())
    return (
        f"robot {dev['spec']}: port energy min {dev['min_port_energy_J']:.3e} J "
        f"(active ticks {dev['active_ticks']}), max force {dev['max_force_N']:.2f} N"
        + (f", deepest {pen}" if pen else "")
    )


def summary_of(device: object, spec: str) -> dict[str, Any]:
    """The device's own summary (if it has one) under its spec: what the logs say about it."""
    fn = getattr(device, "summary", None)
    extra = fn() if callable(fn) else {}
    return {"spec": spec, **(extra if isinstance(extra, dict) else {})}


# --- adapters for real drivers ------------------------------------------------------------------


class HsiDriver(Protocol):
    """A haptic device driver: the newest velocity sample and a force command.

    Neither call may block: a driver that talks to hardware keeps the newest sample in memory
    (latest wins) and hands commands to its own thread or to the device's buffered interface.
    ``read`` returns ``(counter, velocity)``: ``counter`` changes with every new sample.
    """

    def read(self) -> tuple[int, Sequence[float]]: ...

    def command(self, force: Array) -> None: ...


class RobotDriver(Protocol):
    """A robot driver: the newest force sample and a velocity command (same rules as HsiDriver)."""

    def read(self) -> tuple[int, Sequence[float]]: ...

    def command(self, velocity: Array) -> None: ...


def saturate(x: Array, limit: float) -> Array:
    """``x`` scaled down to a norm of at most ``limit``: keeps its direction, only removes energy."""
    n = float(np.linalg.norm(x))
    return x * (limit / n) if n > limit else x


class _Fresh:
    """Tracks whether a driver's samples are fresh: a new counter within ``stale_after`` s, finite,
    of the right size and within ``limit`` (an implausible sample is a fault, treated as stale)."""

    def __init__(self, dof: int, stale_after: float, limit: float) -> None:
        if not stale_after > 0 or not limit > 0:
            raise DeviceError("stale_after and the sample limit must be > 0")
        self.dof = dof
        self.stale_after = stale_after
        self.limit = limit
        self._counter: int | None = None
        self._at = -math.inf
        self.stale_ticks = 0
        self.faults = 0

    def sample(self, now: float, counter: int, values: Sequence[float]) -> Array | None:
        """The sample if it may be used this tick, else None (then the device must be safe)."""
        if counter != self._counter:
            self._counter, self._at = counter, now
        x = np.asarray(values, dtype=float)
        if x.shape != (self.dof,) or not np.all(np.isfinite(x)) or float(np.max(np.abs(x))) > self.limit:
            self.faults += 1
            return None
        if now - self._at > self.stale_after:
            self.stale_ticks += 1
            return None
        return x


class _DriverDevice:
    """What both adapters share: the driver's sample checked for freshness and plausibility (else
    the safe state: zero out, zero commanded), and the command saturated to ``limit`` (norm)."""

    def __init__(
        self, driver: HsiDriver | RobotDriver, dof: int, *, limit: float, plausible: float, stale_after: float
    ) -> None:
        self.driver = driver
        self.limit = limit
        self._fresh = _Fresh(dof, stale_after, plausible)
        self._zero = np.zeros(dof)
        self._safe = True
        self.saturated_ticks = 0

    def affine(self, now: float) -> tuple[Array, Array]:
        y = self._fresh.sample(now, *self.driver.read())
        self._safe = y is None
        return (self._zero if y is None else y), self._zero

    def _command(self, x: Array) -> None:
        if self._safe:
            self.driver.command(self._zero)
            return
        out = saturate(x, self.limit)
        self.saturated_ticks += out is not x
        self.driver.command(out)

    def summary(self) -> dict[str, Any]:
        return {
            "stale_ticks": self._fresh.stale_ticks,
            "faults": self._fresh.faults,
            "saturated_ticks": self.saturated_ticks,
        }


class DriverHsi(_DriverDevice):
    """A real haptic device as the operator's HSI: velocity in, force out, with safety rules.

    * velocity: the driver's newest sample (``Y = 0``: the device is a velocity source this tick);
    * **stale or implausible data** (no new sample for ``stale_after`` s, a non-finite or oversized
      value): the device is told to render **zero force** and the port sees zero velocity, so no
      motion is commanded from data that no longer describes the hand;
    * **saturation**: the rendered force is scaled to a norm of at most ``max_force`` N (its
      direction kept), which only removes energy: the device cannot be told more than it may do.
    """

    role = "hsi"

    def __init__(
        self,
        driver: HsiDriver,
        dof: int,
        *,
        max_force: float,
        max_velocity: float,
        stale_after: float = 0.005,
    ) -> None:
        if not max_force > 0:
            raise DeviceError(f"max_force must be > 0 N, got {max_force}")
        super().__init__(driver, dof, limit=max_force, plausible=max_velocity, stale_after=stale_after)
        self.max_force = max_force

    def advance(self, now: float, v: Array, f: Array) -> None:
        self._command(f)


class DriverRobot(_DriverDevice):
    """A real robot as the teleoperator's device: velocity command out, measured force in.

    * force: the driver's newest sample (``Z = 0``: measured after the motion, so one tick late;
      against a contact of stiffness ``k`` keep ``b`` above ``k dt`` or the loop rings);
    * **stale or implausible force data**: the robot is commanded **zero velocity** (it holds still)
      and the port reports **zero force**, so nothing stale is fed back to the operator;
    * **saturation**: the commanded velocity to ``max_velocity`` m/s (norm, direction kept).
    """

    role = "robot"

    def __init__(
        self,
        driver: RobotDriver,
        dof: int,
        *,
        max_force: float,
        max_velocity: float,
        stale_after: float = 0.005,
    ) -> None:
        if not max_velocity > 0:
            raise DeviceError(f"max_velocity must be > 0 m/s, got {max_velocity}")
        super().__init__(driver, dof, limit=max_velocity, plausible=max_force, stale_after=stale_after)
        self.max_velocity = max_velocity

    def advance(self, now: float, v: Array, f: Array) -> None:
        self._command(v)
