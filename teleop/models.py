"""Operator and environment models, discretised at the loop rate.

**Discretisation.** Every linear model is a SISO transfer function per DoF, discretised with the
bilinear (Tustin) transform ``s = (2/dt)(z-1)/(z+1)`` and run in direct form II transposed.  Tustin
maps a positive-real (passive) continuous model to a positive-real discrete one, so the discrete
human and environment stay passive, which is the premise of every passivity argument here.

**Algebraic loops.** Tustin keeps a direct feedthrough ``D`` (for example ``s/(s+0.5)`` has D ~ 1),
so at each tick a model's output depends on its own input.  Each model therefore exposes its
response for the coming tick as an *affine* map of its input, ``y = y0 + D u``, computed from its
state alone (``affine``), then is advanced with the values the port actually settled on
(``advance``).  The ports (``teleop.node``) solve the resulting linear equations in closed form:
no iteration, no extra delay.  Piecewise models (a wall that is touched or not) pick their branch
from the state at the start of the tick.

Section V models: the human exerts a velocity step and reacts to force through the admittance
``Y_h(s) = s/(s+0.5)``: ``v_hsi = v_step - Y_h F_hsi``; the environment is the impedance
``Z_e(s) = 1/(s+1)``: ``F_to = Z_e v_to``; HSI and TO are ideal (unity) transducers.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np
import numpy.typing as npt
from numpy.polynomial import polynomial as P

Array = npt.NDArray[np.float64]


class ModelError(ValueError):
    """A model's parameters are invalid."""


class DiscreteLTI:
    """``y = H(s) u`` per channel, Tustin-discretised, direct form II transposed.

    ``num`` and ``den`` are continuous-time coefficients, highest power first (as in
    python-control); ``H`` must be proper.
    """

    def __init__(self, num: Sequence[float], den: Sequence[float], dt: float, channels: int) -> None:
        if dt <= 0:
            raise ModelError(f"dt must be > 0, got {dt}")
        num_a = np.trim_zeros(np.asarray(num, dtype=float), "f")
        den_a = np.trim_zeros(np.asarray(den, dtype=float), "f")
        if den_a.size == 0 or num_a.size > den_a.size:
            raise ModelError(f"transfer function must be proper with a non-zero denominator: {num}/{den}")
        n = den_a.size - 1
        c = 2.0 / dt
        # Ascending-power polynomials in z of N(c (z-1)/(z+1)) (z+1)^n, likewise D.
        zm1, zp1 = np.array([-1.0, 1.0]), np.array([1.0, 1.0])

        def bilinear(coeffs_desc: Array) -> Array:
            out = np.zeros(n + 1)
            deg = coeffs_desc.size - 1
            for i, a in enumerate(coeffs_desc):
                k = deg - i  # power of s
                term = a * c**k * P.polymul(P.polypow(zm1, k), P.polypow(zp1, n - k))
                out[: term.size] += term
            return out

        bz = bilinear(num_a)[::-1]  # descending powers of z == ascending powers of z^-1
        az = bilinear(den_a)[::-1]
        if az[0] == 0:
            raise ModelError("discretised denominator is degenerate")
        self.b = bz / az[0]
        self.a = az / az[0]
        self.order = n
        self.z = np.zeros((n, channels))

    @property
    def feedthrough(self) -> float:
        """D: the part of this tick's output proportional to this tick's input."""
        return float(self.b[0])

    def free(self) -> Array:
        """The part of this tick's output that the state alone determines."""
        return self.z[0] if self.order else np.zeros(self.z.shape[1])

    def advance(self, u: Array) -> Array:
        """Commit this tick's input; returns the output ``D u + free``."""
        y = self.b[0] * u + (self.z[0] if self.order else 0.0)
        for i in range(self.order - 1):
            self.z[i] = self.b[i + 1] * u - self.a[i + 1] * y + self.z[i + 1]
        if self.order:
            self.z[-1] = self.b[-1] * u - self.a[-1] * y
        return np.asarray(y, dtype=float)


class Human(Protocol):
    """Operator holding the HSI, admittance causality: ``v = v0 - Y * F`` this tick."""

    def affine(self, now: float) -> tuple[Array, Array]: ...

    def advance(self, now: float, v: Array, f: Array) -> None: ...


class Environment(Protocol):
    """Remote environment at the TO, impedance causality: ``F = f0 + Z * v`` this tick."""

    def affine(self, now: float) -> tuple[Array, Array]: ...

    def advance(self, now: float, v: Array, f: Array) -> None: ...


class StepHuman:
    """Section V: a velocity step ``amplitude`` at ``t_step`` through the admittance s/(s+0.5)."""

    def __init__(
        self,
        dof: int,
        dt: float,
        amplitude: float = 1.0,
        t_step: float = 0.1,
        num: Sequence[float] = (1.0, 0.0),
        den: Sequence[float] = (1.0, 0.5),
    ) -> None:
        self.amplitude = amplitude
        self.t_step = t_step
        self.admittance = DiscreteLTI(num, den, dt, dof)
        self._y = np.full(dof, self.admittance.feedthrough)
        self._half_dt = dt / 2.0

    def reference(self, now: float) -> Array:
        on = now + self._half_dt >= self.t_step
        return np.full(self._y.shape, self.amplitude if on else 0.0)

    def affine(self, now: float) -> tuple[Array, Array]:
        return self.reference(now) - self.admittance.free(), self._y

    def advance(self, now: float, v: Array, f: Array) -> None:
        self.admittance.advance(f)


class LtiEnvironment:
    """An impedance ``F = Z_e(s) v`` per DoF; Section V uses ``Z_e = 1/(s+1)``."""

    def __init__(
        self, dof: int, dt: float, num: Sequence[float] = (1.0,), den: Sequence[float] = (1.0, 1.0)
    ) -> None:
        self.impedance = DiscreteLTI(num, den, dt, dof)
        self._z = np.full(dof, self.impedance.feedthrough)

    def affine(self, now: float) -> tuple[Array, Array]:
        return self.impedance.free(), self._z

    def advance(self, now: float, v: Array, f: Array) -> None:
        self.impedance.advance(v)


def _smooth_steps(t: float, knots: Sequence[tuple[float, float]], ramp: float) -> float:
    """Piecewise-constant profile ``[(t_start, value), ...]`` with raised-cosine ramps of ``ramp`` s."""
    v = 0.0
    for t0, target in knots:
        if t < t0:
            break
        a = min(1.0, (t - t0) / ramp)
        v = v + (target - v) * 0.5 * (1.0 - np.cos(np.pi * a)) if a < 1.0 else target
    return v


class ProtocolHuman:
    """Section VI's operator: free motion 0-5 s, a push into foam 5-10 s, two wall pushes 10-15 s.

    Intended velocity ``v_ref(t)`` per DoF; the hand yields to force through the sum of two
    admittances: the arm, a mass-spring-damper ``s / (m s^2 + d s + k)``, and the grip on the handle,
    a spring-damper ``s / (c s + k_g)``.  Pushing against something stiff, the hand ends up pressing
    with about ``k`` times the intended penetration.

    Why the grip matters: at high frequency the arm's mass alone would make the HSI a velocity
    source, which reflects every incoming wave (reflection coefficient -1), and a discrete loop
    whose other end also reflects (the TO in free space, +1) then rings at the Nyquist frequency
    after any glitch.  The grip's damping ``c`` is what the port sees at high frequency; with
    ``c`` equal to the wave impedance ``b`` (20 N s/m by default) the HSI absorbs reflections.
    DoF 0 is the pushing direction; any further DoF moves laterally (a slow sine).
    """

    def __init__(
        self,
        dof: int,
        dt: float,
        m: float = 1.0,
        d: float = 20.0,
        k: float = 300.0,
        c_grip: float = 20.0,
        k_grip: float = 2000.0,
    ) -> None:
        self.dof = dof
        arm_num, arm_den = np.array([1.0, 0.0]), np.array([m, d, k])
        grip_num, grip_den = np.array([1.0, 0.0]), np.array([c_grip, k_grip])
        num = np.polyadd(np.polymul(arm_num, grip_den), np.polymul(grip_num, arm_den))
        den = np.polymul(arm_den, grip_den)
        self.admittance = DiscreteLTI(tuple(num), tuple(den), dt, dof)
        self._y = np.full(dof, self.admittance.feedthrough)
        self._ref = np.zeros(dof)

    @staticmethod
    def push_profile(t: float) -> float:
        w = 2 * np.pi * 0.5
        if t < 5.0:  # free space: 0.5 Hz strokes of +-5 cm
            return float(0.05 * w * np.sin(w * t))
        knots = [
            (5.0, 0.04),
            (7.0, 0.0),
            (7.5, -0.04),
            (9.5, 0.0),  # into the foam and out
            (10.0, 0.05),
            (11.0, -0.05),
            (12.0, 0.0),  # first wall push
            (12.5, 0.05),
            (13.5, -0.05),
            (14.5, 0.0),
        ]  # second wall push
        return _smooth_steps(t, knots, 0.15)

    def reference(self, now: float) -> Array:
        self._ref[0] = self.push_profile(now)
        for j in range(1, self.dof):
            # Starts from rest: a jump would ring the one-tick wave loop (see README, reflections).
            self._ref[j] = 0.03 * np.sin(2 * np.pi * 0.3 * j * now)
        return self._ref

    def affine(self, now: float) -> tuple[Array, Array]:
        return self.reference(now) - self.admittance.free(), self._y

    def advance(self, now: float, v: Array, f: Array) -> None:
        self.admittance.advance(f)


class ProtocolEnvironment:
    """Free space 0-5 s, foam (a damper) 5-10 s, foam plus a stiff wall on DoF 0 from 10 s.

    The wall is a unilateral spring-damper placed ``wall_gap`` ahead of where the TO is at 10 s.
    Its spring is integrated implicitly (force from the end-of-tick penetration), which is passive;
    contact is decided from the start-of-tick position, so in the tick that leaves the wall the
    force may pull slightly (at most ``k v dt``), which still absorbs energy.
    """

    def __init__(
        self,
        dof: int,
        dt: float,
        foam: float = 40.0,
        k_wall: float = 3000.0,
        c_wall: float = 20.0,
        wall_gap: float = 0.02,
    ) -> None:
        self.dt = dt
        self.foam = foam
        self.k = k_wall
        self.c = c_wall
        self.gap = wall_gap
        self.x = np.zeros(dof)
        self.wall: float | None = None
        self._f0 = np.zeros(dof)
        self._z = np.zeros(dof)

    def affine(self, now: float) -> tuple[Array, Array]:
        self._f0[:] = 0.0
        self._z[:] = self.foam if now >= 5.0 else 0.0
        if now >= 10.0:
            if self.wall is None:
                self.wall = float(self.x[0]) + self.gap
            pen = self.x[0] - self.wall
            if pen > 0:
                self._f0[0] = self.k * pen
                self._z[0] += self.k * self.dt + self.c
        return self._f0, self._z

    def advance(self, now: float, v: Array, f: Array) -> None:
        self.x += v * self.dt
