"""Scattering (wave-variable) transform of eq. (3), N-DoF, both ports.

Velocity and force are turned into waves so that a delayed or lossy channel can be made passive
(eq. 5).  With impedance ``b > 0`` per DoF::

    g = (b v + F) / sqrt(2b)     incident wave   (g_l at the HSI, g_r at the TO)
    h = (b v - F) / sqrt(2b)     reflected wave  (h_l at the HSI, h_r at the TO)

Power identity behind eq. (4): ``v F = (g**2 - h**2) / 2`` per DoF.

Each port transmits one wave and receives the other, so each port also needs the *mixed* forms
solved here: the HSI knows ``v_hsi`` and receives ``h_l``; the TO knows ``g_r`` and its force.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from teleop.errors import LocalError

Array = npt.NDArray[np.float64]


class WaveError(LocalError):
    """A wave impedance or a signal shape is invalid."""


@dataclass(frozen=True)
class WaveImpedance:
    """Wave impedance ``b`` per DoF, validated once so the 1 kHz path does no checks."""

    b: Array
    sqrt2b: Array
    #: 2 per DoF, for :meth:`to_wave_out`: ``2.0 * F`` as an array product (the same IEEE products as
    #: with the scalar, at about half the cost: numpy converts a scalar operand on every call).
    _two: Array = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        two = np.full(self.b.shape, 2.0)
        two.setflags(write=False)
        object.__setattr__(self, "_two", two)

    @classmethod
    def of(cls, b: float | npt.ArrayLike, dof: int) -> WaveImpedance:
        if not isinstance(dof, int | np.integer) or dof < 1:
            raise WaveError(f"dof must be a positive integer, got {dof!r}")
        arr = np.asarray(b, dtype=np.float64)
        if arr.ndim == 0:
            arr = np.full(dof, float(arr))
        if arr.shape != (dof,):
            raise WaveError(f"b must be a scalar or have shape ({dof},), got shape {arr.shape}")
        if not np.all(np.isfinite(arr)) or np.any(arr <= 0.0):
            raise WaveError(f"wave impedance b must be finite and > 0 per DoF, got {arr.tolist()}")
        arr = arr.copy()
        arr.setflags(write=False)
        s = np.sqrt(2.0 * arr)
        s.setflags(write=False)
        return cls(b=arr, sqrt2b=s)

    @property
    def dof(self) -> int:
        return int(self.b.shape[0])

    def _check(self, *xs: Array) -> None:
        for x in xs:
            if getattr(x, "shape", None) != self.b.shape:
                raise WaveError(f"signal shape {np.shape(x)} does not match dof {self.dof}")

    # --- eq. (3) and its inverse -------------------------------------------------------------
    def to_waves(self, v: Array, f: Array) -> tuple[Array, Array]:
        """(v, F) -> (g, h), eq. (3); the same formula at both ports."""
        self._check(v, f)
        bv = self.b * v
        return (bv + f) / self.sqrt2b, (bv - f) / self.sqrt2b

    def from_waves(self, g: Array, h: Array) -> tuple[Array, Array]:
        """(g, h) -> (v, F): inverse of eq. (3)."""
        self._check(g, h)
        return (g + h) / self.sqrt2b, (g - h) * self.sqrt2b / 2.0

    # --- mixed forms used by the two ports ---------------------------------------------------
    def hsi_force(self, v_hsi: Array, h_l: Array) -> Array:
        """Force the HSI renders from its velocity and the received wave: F = b v - sqrt(2b) h_l."""
        return self.b * v_hsi - self.sqrt2b * h_l

    def hsi_wave_out(self, v_hsi: Array, h_l: Array) -> Array:
        """Wave the HSI transmits: g_l = sqrt(2b) v - h_l (eq. 3 with F eliminated)."""
        return self.sqrt2b * v_hsi - h_l

    def to_velocity(self, g_r: Array, f_to: Array) -> Array:
        """Velocity commanded to the TO from the received wave: v = (sqrt(2b) g_r - F) / b."""
        return (self.sqrt2b * g_r - f_to) / self.b

    def to_wave_out(self, g_r: Array, f_to: Array) -> Array:
        """Wave the TO transmits: h_r = g_r - sqrt(2/b) F (eq. 3 with v eliminated)."""
        return g_r - self._two * f_to / self.sqrt2b


def power(g: Array, h: Array) -> float:
    """Power entering a port, ``sum((g**2 - h**2) / 2)`` = ``v . F`` (eq. 2-4)."""
    return float(0.5 * (np.dot(g, g) - np.dot(h, h)))
