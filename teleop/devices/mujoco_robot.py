"""``--robot mujoco[:SCENE.xml]``: the teleoperator's robot and its environment in MuJoCo.

An end effector on slide joints (one per DoF) under a local velocity controller (MuJoCo
``velocity`` actuators, gain ``kv``), stepped once per tick of the teleoperator (the scene's
timestep must be the loop period).  The port's force is read from a force sensor at the wrist
(``ee_force``): the force the robot exerts on what it touches, plus the inertia of the tool
outboard of the sensor.

**Affine form.** The node needs ``F = f0 + Z v`` before it picks ``v``.  Within one step the engine
is linear in the command as long as the set of active contacts does not change (soft constraints,
frictionless contacts), so each tick the robot runs the engine's forward dynamics at the present
state with the last tick's command and once per DoF with that command plus a small probe (``Z``,
the diagonal of ``dF/dv``; the off-diagonal part is measured and reported as ``max_coupling``),
then steps with the command the port settled on.  Linearising at the last command rather than at
zero keeps the contact set of the linearisation that of the step (a foam that a zero command
would leave is still pushed).  Only the acceleration stage is recomputed for a probe, so a tick
costs one collision pass and ``1 + dof`` cheap solves (``bench/mujoco_step.py``).

**Passivity.** The port is the pair (commanded velocity, sensed force).  With all moving mass
outboard of the sensor the sensed force is the controller's own force ``kv (v - qdot)``: a damper
in series with the robot's mass and a passive contact, which is passive in continuous time for
any gain.  Where it cannot be:

* mass inboard of the sensor is hidden from the port; the energy it can return scales with that
  mass over ``kv`` (the default scene's carriage weighs 1 g against a 100 g tool);
* time stepping: the engine integrates the controller implicitly but the sensor reads the explicit
  acceleration, and the force is sampled at the start of the step;
* a contact set that changes inside a step (touching, leaving) breaks the linearisation; the
  difference between the predicted and the sensed force is reported (``max_prediction_error_N``).

**Stale steps.** A step after which the tip moved further along a DoF than the robot can in a
tick, or moves faster than it can (``PLAUSIBLE_MARGIN`` x its speed limit, x ``dt`` for a step:
the largest ``ctrlrange`` of the scene's actuators, or :data:`MAX_SPEED` where they are not
limited), is not plausible (the engine went astray on a finite value): the last plausible state
is restored (held), the step counted (``stale_steps``), and nothing of it is used.  A non-finite
force resets the engine (``engine_resets``).

The robot keeps a passivity observer of its own port, ``E(t) = sum v F dt`` (it starts at rest, so
a passive robot never lets it go below 0): ``min_port_energy_J`` and ``active_ticks`` (ticks with
``E < -1e-9`` J) are in its summary, next to the channel's watchdog.

**Default scene** (``teleop/devices/scenes/default.xml``, shipped as package data): free space; a soft
foam block (a compliant, damped contact) and a stiff wall are mocap bodies that the robot brings in
on the Section VI timeline, as the built-in ``protocol`` environment does: the foam face 1 mm ahead
of the tip at 5 s, the wall 2 cm ahead of it at 10 s (both placed out of contact, so placing them
adds no energy); with ``--variation`` at the seeded human's phase times instead.
"""

from __future__ import annotations

import math
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from teleop.devices.models import Array
from teleop.errors import DeviceError

PROBE = 1e-3  # m/s: the probe command of the linearisation (the response is linear in it)
FOAM_AT, WALL_AT = 5.0, 10.0  # s: Section VI timeline, the scripted run's (--variation 0)
FOAM_GAP, WALL_GAP = 0.001, 0.02  # m ahead of the tip's front
ENERGY_TOLERANCE = 1e-9  # J
MAX_DOF = 3
#: m/s: the tip's speed limit where the scene's actuators have no ``ctrlrange`` (above the 1.5 m/s
#: an envelope commands at most by default); with :data:`PLAUSIBLE_MARGIN`, a step's bound.
MAX_SPEED = 10.0
PLAUSIBLE_MARGIN = 2.0


def default_scene() -> Path:
    return Path(str(resources.files("teleop.devices") / "scenes" / "default.xml"))


def check_scene(arg: str | None, dof: int = 1) -> None:
    """DeviceError unless MuJoCo imports and the scene (default or ``arg``) loads as a robot scene
    of ``dof`` DoF: run before a session starts, so a bad ``--robot mujoco:FILE`` stops the command
    at once."""
    MujocoRobot(dof=dof, dt=0.001, arg=arg)


class MujocoRobot:
    """The teleoperator's robot in MuJoCo (see the module docstring)."""

    role = "robot"

    def __init__(
        self, dof: int, dt: float, arg: str | None = None, foam_at: float = FOAM_AT, wall_at: float = WALL_AT
    ) -> None:
        """``foam_at``/``wall_at``: when the timeline places the foam and the wall (s), the seeded
        human's phase boundaries (:class:`teleop.devices.models.ProtocolPlan`), so the scene switches phase
        when the operator's human expects it, as the built-in environment does."""
        self.foam_at, self.wall_at = foam_at, wall_at
        try:
            import mujoco
        except ImportError:
            raise DeviceError(
                "robot 'mujoco' needs the MuJoCo engine: pip install 'teleop[mujoco]' (or mujoco)"
            ) from None
        self._mj = mujoco
        path = Path(arg) if arg else default_scene()
        self.scene = str(path) if arg else "default"
        if not 1 <= dof <= MAX_DOF:
            raise DeviceError(f"robot 'mujoco' drives 1 to {MAX_DOF} DoF (slide joints), got {dof}")
        if not path.is_file():
            raise DeviceError(f"robot 'mujoco': scene file {str(path)!r} does not exist")
        try:
            m = mujoco.MjModel.from_xml_path(str(path))
        except ValueError as e:  # the compiler's message names the element and the line
            raise DeviceError(f"robot 'mujoco': scene {str(path)!r}: {' '.join(str(e).split())}") from None
        self._check(m, dof, dt)
        self.m = m
        self.d = mujoco.MjData(m)
        self.dof = dof
        self.dt = dt
        self._sensor = int(m.sensor("ee_force").adr[0])
        self._site = int(m.sensor("ee_force").objid[0])
        self._integrate = (
            mujoco.mj_Euler if m.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER else mujoco.mj_implicit
        )
        self._timeline = self._timeline_bodies(m)
        self._f0 = np.zeros(dof)
        self._z = np.zeros(dof)
        # observer of the robot's own port
        self.port_energy = 0.0
        self.min_port_energy = 0.0
        self.active_ticks = 0
        self.max_force = 0.0
        self.max_prediction_error = 0.0
        self.max_coupling = 0.0
        self.negative_z_ticks = 0
        self.engine_resets = 0
        self.placed: dict[str, float] = {}
        self.max_penetration: dict[str, float] = {}  # m, deepest tip front past each timeline face
        mujoco.mj_forward(m, self.d)
        # Each DoF's joint axis in the world frame (slide joints on a non-rotating chain: constant).
        self._axes = np.array([self.d.xaxis[m.actuator_trnid[i, 0]] for i in range(dof)])
        self._sensed = self.d.sensordata[self._sensor : self._sensor + 3]  # a view: always current
        # A site carried by slide joints only keeps its orientation: project once, not every tick.
        fixed = all(m.jnt_type[j] == mujoco.mjtJoint.mjJNT_SLIDE for j in self._chain_joints(m))
        self._proj = self._axes @ self.d.site_xmat[self._site].reshape(3, 3) if fixed else None
        self._pick: list[tuple[int, float]] | None = None
        if self._proj is not None and np.allclose(np.abs(self._proj).max(axis=1), 1.0):
            self._pick = [
                (int(np.abs(row).argmax()), float(np.sign(row[np.abs(row).argmax()]))) for row in self._proj
            ]
        self._ctrl = self.d.ctrl  # a view of the engine's buffer
        self._last = [0.0] * dof  # the last command: where the next tick is linearised
        self._skip = mujoco.mjtStage.mjSTAGE_VEL
        limited = [bool(m.actuator_ctrllimited[i]) for i in range(dof)]
        speed = float(np.max(np.abs(m.actuator_ctrlrange[:dof]))) if all(limited) else MAX_SPEED
        self.max_speed = PLAUSIBLE_MARGIN * speed  # m/s along a DoF (docstring)
        self.max_step = self.max_speed * dt  # m along a DoF in one tick
        self.stale_steps = 0
        self._good = (self.d.qpos.copy(), self.d.qvel.copy())  # the last plausible state: held

    def _check(self, m: Any, dof: int, dt: float) -> None:
        mj = self._mj
        if abs(m.opt.timestep - dt) > 1e-12:
            raise DeviceError(
                f"robot 'mujoco': the scene's timestep must be the loop period {dt:g} s, "
                f"got {m.opt.timestep:g}"
            )
        if m.opt.integrator not in (
            mj.mjtIntegrator.mjINT_EULER,
            mj.mjtIntegrator.mjINT_IMPLICIT,
            mj.mjtIntegrator.mjINT_IMPLICITFAST,
        ):
            raise DeviceError(
                "robot 'mujoco': the scene's integrator must be Euler, implicit or implicitfast"
            )
        if m.nu < dof:
            raise DeviceError(f"robot 'mujoco': the scene has {m.nu} actuators, {dof} DoF need one each")
        for i in range(m.nu):
            j = int(m.actuator_trnid[i, 0])
            kv = float(m.actuator_gainprm[i, 0])
            velocity = (
                m.actuator_trntype[i] == mj.mjtTrn.mjTRN_JOINT
                and m.jnt_type[j] == mj.mjtJoint.mjJNT_SLIDE
                and m.actuator_dyntype[i] == mj.mjtDyn.mjDYN_NONE
                and kv > 0
                and float(m.actuator_biasprm[i, 1]) == 0.0
                and float(m.actuator_biasprm[i, 2]) == -kv
            )
            if not velocity:
                raise DeviceError(
                    f"robot 'mujoco': actuator {i} must be a velocity actuator (kv > 0) on a slide joint"
                )
        try:
            s = m.sensor("ee_force")
        except KeyError:
            raise DeviceError("robot 'mujoco': the scene has no force sensor named 'ee_force'") from None
        if s.type[0] != mj.mjtSensor.mjSENS_FORCE:
            raise DeviceError("robot 'mujoco': sensor 'ee_force' must be a force sensor")

    def _chain_joints(self, m: Any) -> list[int]:
        """The joints between the force sensor's site and the world."""
        out: list[int] = []
        b = int(m.site_bodyid[self._site])
        while b > 0:
            out += range(int(m.body_jntadr[b]), int(m.body_jntadr[b]) + int(m.body_jntnum[b]))
            b = int(m.body_parentid[b])
        return out

    def _timeline_bodies(self, m: Any) -> dict[str, tuple[int, float]]:
        """Mocap bodies ``foam``/``wall`` with a box geom, and the tip: (mocap id, box half-depth)."""
        out: dict[str, tuple[int, float]] = {}
        try:
            self._tip = int(m.geom("tip").id)
        except KeyError:
            return out
        self._tip_radius = float(m.geom_rbound[self._tip])
        for name in ("foam", "wall"):
            try:
                b = m.body(name)
            except KeyError:
                continue
            if b.mocapid[0] < 0 or m.body_geomnum[b.id] < 1:
                continue
            g = int(m.body_geomadr[b.id])
            out[name] = (int(b.mocapid[0]), float(m.geom_size[g, 0]) + float(m.geom_pos[g, 0]))
        return out

    def _place(self, name: str, gap: float, now: float) -> None:
        """Put a timeline body ``gap`` m ahead of the tip's front along DoF 0, out of contact."""
        mj, m, d = self._mj, self.m, self.d
        mj.mj_kinematics(m, d)
        mocap, half = self._timeline[name]
        tip = d.geom_xpos[self._tip]
        front = float(tip[0]) + self._tip_radius
        d.mocap_pos[mocap] = [front + gap + half, tip[1], tip[2]]
        self.placed[name] = now
        self.max_penetration[name] = 0.0

    def _force(self) -> list[float]:
        """The sensed force along each DoF's joint axis, world frame (the site may be rotated)."""
        if self._pick is not None:  # each DoF's axis is a sensor axis: no matrix product needed
            f = self._sensed.tolist()
            return [sign * f[k] for k, sign in self._pick]
        if self._proj is not None:
            return list((self._proj @ self._sensed).tolist())
        f_world = self.d.site_xmat[self._site].reshape(3, 3) @ self._sensed
        return list((self._axes @ f_world).tolist())

    def affine(self, now: float) -> tuple[Array, Array]:
        mj, m, d = self._mj, self.m, self.d
        if self._timeline and now >= self.foam_at:
            for name, at, gap in (("foam", self.foam_at, FOAM_GAP), ("wall", self.wall_at, WALL_GAP)):
                if name in self._timeline and name not in self.placed and now >= at:
                    self._place(name, gap, now)
        ctrl = self._ctrl
        base = self._last  # linearise at the last command: the contact set most likely holds there
        ctrl[: self.dof] = base
        mj.mj_forward(m, d)
        fb = self._force()
        z = self._z
        f0 = self._f0
        z_sum = 0.0
        for i in range(self.dof):  # plain floats: numpy calls on 1-3 numbers cost more than the math
            ctrl[i] = base[i] + PROBE
            mj.mj_forwardSkip(m, d, self._skip, 0)
            col = self._force()
            ctrl[i] = base[i]
            zi = (col[i] - fb[i]) / PROBE
            if zi < 0.0:  # an active response: never let the port divide by b + Z <= 0
                self.negative_z_ticks += 1
                zi = 0.0
            z[i] = zi
            z_sum += zi
            f0[i] = fb[i] - zi * base[i]
            if self.dof > 1:  # the part of dF/dv the diagonal form leaves out, relative to it
                off = 0.0
                for j in range(self.dof):
                    if j != i:
                        off += abs(col[j] - fb[j])
                off /= PROBE
                if off > self.max_coupling * zi:
                    self.max_coupling = off / max(zi, 1e-12)
        if not math.isfinite(sum(fb) + z_sum):  # the engine diverged (a scene of one's own, say)
            self._reset()
            f0[:] = 0.0
            z[:] = 0.0
        return f0, z

    def _reset(self) -> None:
        """Back to rest, the placed bodies kept: what MuJoCo's own mj_step does on divergence,
        counted (``engine_resets``) and reported as no force this tick."""
        mj, m, d = self._mj, self.m, self.d
        placed = d.mocap_pos.copy()
        mj.mj_resetData(m, d)
        d.mocap_pos[:] = placed
        self._last = [0.0] * self.dof
        self.engine_resets += 1
        mj.mj_forward(m, d)
        self._good = (d.qpos.copy(), d.qvel.copy())

    def advance(self, now: float, v: Array, f: Array) -> None:
        mj, m, d = self._mj, self.m, self.d
        self._ctrl[: self.dof] = v
        self._last = v.tolist()
        mj.mj_forwardSkip(m, d, self._skip, 0)
        sensed = self._force()
        self._integrate(m, d)
        qpos, qvel = self._good
        n = self.dof
        # not finite, or further (or faster) than the robot can go
        if not (
            bool(np.all(np.abs(d.qpos[:n] - qpos[:n]) <= self.max_step))
            and bool(np.all(np.abs(d.qvel[:n]) <= self.max_speed))
        ):
            d.qpos[:], d.qvel[:] = qpos, qvel
            mj.mj_forward(m, d)
            self.stale_steps += 1
        else:
            self._good = (d.qpos.copy(), d.qvel.copy())
        fl, vl = f.tolist(), v.tolist()
        for i in range(self.dof):
            fi = fl[i]
            err = abs(sensed[i] - fi)
            if err > self.max_prediction_error:
                self.max_prediction_error = err
            if abs(fi) > self.max_force:
                self.max_force = abs(fi)
            self.port_energy += self.dt * vl[i] * fi
        if self.port_energy < self.min_port_energy:
            self.min_port_energy = self.port_energy
        if self.port_energy < -ENERGY_TOLERANCE:
            self.active_ticks += 1
        if self.placed:
            front = float(d.geom_xpos[self._tip, 0]) + self._tip_radius
            for name in self.placed:
                mocap, half = self._timeline[name]
                pen = front - (float(d.mocap_pos[mocap, 0]) - half)
                if pen > self.max_penetration[name]:
                    self.max_penetration[name] = pen

    def position(self) -> Array:
        """The tip's position along each DoF (m): for tests and plots."""
        return np.asarray(self.d.qpos[: self.dof], dtype=float).copy()

    #: Ticks between two samples of :meth:`state` in the log (100 Hz): enough for a 3D view and a
    #: learner at up to 100 frames a second, at a tenth of the log's per-tick cost.
    state_every = 10

    def state(self) -> dict[str, list[float]]:
        """The robot's state for the log (``/teleoperator/state``): the tip's pose in the world
        (x, y, z, qx, qy, qz, qw: the force sensor's site) and its position along each DoF (m)."""
        quat = np.zeros(4)
        self._mj.mju_mat2Quat(quat, self.d.site_xmat[self._site])
        w, x, y, z = quat.tolist()
        return {
            "pose": [*self.d.site_xpos[self._site].tolist(), x, y, z, w],
            "position": self.d.qpos[: self.dof].tolist(),
        }

    def summary(self) -> dict[str, Any]:
        return {
            "engine": f"mujoco {self._mj.__version__}",
            "scene": self.scene,
            "port_energy_J": self.port_energy,
            "min_port_energy_J": self.min_port_energy,
            "active_ticks": self.active_ticks,
            "max_force_N": self.max_force,
            "max_prediction_error_N": self.max_prediction_error,
            "max_coupling": self.max_coupling,
            "negative_z_ticks": self.negative_z_ticks,
            "engine_resets": self.engine_resets,
            "stale_steps": self.stale_steps,
            "placed_at_s": dict(self.placed),
            "max_penetration_m": dict(self.max_penetration),
        }
