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
