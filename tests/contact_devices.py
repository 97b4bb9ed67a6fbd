"""Devices for the envelope's tests (issue 45): a hand that pushes hard, and a robot against a
spring whose force it senses one tick late (``Z = 0``, as a torque-sensing arm reports it) or
knows as an impedance (``Z = K dt``).

``--hsi tests.contact_devices:PushingHand:SPEED`` pushes every DoF at SPEED m/s (default 5)
through a stiff hand (admittance ``Y``, m/s per N).  ``--robot
tests.contact_devices:SensedSpring:K`` and ``...:ImpedanceSpring:K`` put a spring of K N/m
(default 1e4) ``GAP`` ahead of the robot on every DoF, in both directions (a slot: pushing either
way meets it).  Each robot keeps what it was finally commanded (``commanded``, ``forces``): the
values a test holds the envelope to.
"""

from __future__ import annotations

import numpy as np

from teleop.devices.models import Array

GAP = 0.005  # m: the spring's distance from where the robot starts


class PushingHand:
    """A hand pushing at ``speed`` m/s on every DoF, yielding little to force (``Y``)."""

    role = "hsi"
    hardware = False  # a model: teleop sim may build it (teleop.devices)
    Y = 0.02  # m/s per N

    def __init__(self, dof: int, dt: float, arg: str | None) -> None:
        self._v0 = np.full(dof, float(arg or 5.0))
        self._y = np.full(dof, self.Y)
        self._y.setflags(write=False)

    def affine(self, now: float) -> tuple[Array, Array]:
        return self._v0.copy(), self._y

    def advance(self, now: float, v: Array, f: Array) -> None:
        pass


class _Spring:
    role = "robot"
    hardware = False

    def __init__(self, dof: int, dt: float, arg: str | None) -> None:
        self.k = float(arg or 1e4)
        self.dt = dt
        self.x = np.zeros(dof)
        self.commanded: list[Array] = []
        self.forces: list[Array] = []  # the spring's force after each tick's motion (N)

    def force(self) -> Array:
        """The spring's force now: it pushes back on a robot that went past ``GAP`` either way
        (F, like the command, positive along +x)."""
        pen = np.abs(self.x) - GAP
        return np.where(pen > 0.0, np.sign(self.x) * self.k * pen, 0.0)

    def advance(self, now: float, v: Array, f: Array) -> None:
        self.commanded.append(np.array(v, dtype=float))
        self.x = self.x + v * self.dt
        self.forces.append(self.force())


class SensedSpring(_Spring):
    """The force the last tick left, with no feedthrough: what a force-sensing arm reports."""

    def __init__(self, dof: int, dt: float, arg: str | None) -> None:
        super().__init__(dof, dt, arg)
        self._z = np.zeros(dof)
        self._z.setflags(write=False)

    def affine(self, now: float) -> tuple[Array, Array]:
        return self.force(), self._z


class ImpedanceSpring(_Spring):
    """The same spring as an impedance: the force at the end of the tick, ``f0 + K dt v`` in
    contact (the built-in wall's implicit spring)."""

    def affine(self, now: float) -> tuple[Array, Array]:
        pen = np.abs(self.x) - GAP
        z = np.where(pen > 0.0, self.k * self.dt, 0.0)
        return self.force(), z
