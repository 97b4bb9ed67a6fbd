"""Operator and environment models, discretised at the loop rate.

**Discretisation.** Every linear model is a SISO transfer function per DoF, discretised with the
bilinear (Tustin) transform ``s = (2/dt)(z-1)/(z+1)`` and run in direct form II transposed.  Tustin
maps a positive-real (passive) continuous model to a positive-real discrete one, so the discrete
human and environment stay passive, which is the premise of every passivity argument here.

**Algebraic loops.** Tustin keeps a direct feedthrough ``D`` (for example ``s/(s+0.5)`` has D ~ 1),
so at each tick a model's output depends on its own input.  Each model therefore exposes its
response for the coming tick as an *affine* map of its input, ``y = y0 + D u``, computed from its
state alone (``affine``), then is advanced with the values the port actually settled on
(``advance``).  The ports (``teleop.session.node``) solve the resulting linear equations in closed form:
no iteration, no extra delay.  Piecewise models (a wall that is touched or not) pick their branch
from the state at the start of the tick.

Section V models: the human exerts a velocity step and reacts to force through the admittance
``Y_h(s) = s/(s+0.5)``: ``v_hsi = v_step - Y_h F_hsi``; the environment is the impedance
``Z_e(s) = 1/(s+1)``: ``F_to = Z_e v_to``; HSI and TO are ideal (unity) transducers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt
from numpy.polynomial import polynomial as P

# Imported with this module, not on the first draw: numpy loads numpy.random lazily, and a first
# draw happens while a teleoperator answers an operator's start.  On a cold first run (its ~10
# extension modules read from disk) that took ~180 ms of the operator's 250 ms start window, and
# the start failed ("did not confirm the start").
from numpy.random import default_rng

from teleop.errors import LocalError
from teleop.limits import MAX_VARIATION

Array = npt.NDArray[np.float64]

#: Up to this many channels a :class:`DiscreteLTI` runs on floats, channel by channel (``lanes``).
#: Where the two cost the same, third order (cachegrind, instructions an advance): floats 21 k at 2
#: channels, 33 k at 4, 50 k at 6; numpy 33-44 k at any of them.  ``bench.instructions``: the whole
#: 2-DoF tick 5 % fewer with floats, the 6-DoF one 0.5-1 % more (so 4, not 6).
FLOAT_LANES = 4


class ModelError(LocalError):
    """A model's parameters are invalid."""


class DiscreteLTI:
    """``y = H(s) u`` per channel, Tustin-discretised, direct form II transposed.

    ``num`` and ``den`` are continuous-time coefficients, highest power first (as in
    python-control); ``H`` must be proper.
    """

    def __init__(
        self, num: Sequence[float], den: Sequence[float], dt: float, channels: int, lanes: bool | None = None
    ) -> None:
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
        # At a few channels the state is plain floats, per channel (``lanes``): the same recursion in
        # Python arithmetic costs ~1.4 us an advance at 2 channels, third order, against ~5.7 us for
        # the numpy calls on two-element arrays (issue 22); above FLOAT_LANES channels numpy's fixed
        # cost per call is the cheaper one.  The same IEEE operations in the same order, so the same bits
        # (tests/test_models.py holds the two equal).
        self.lanes = channels <= FLOAT_LANES if lanes is None else lanes
        self._zero = np.zeros(channels)
        self._zero.setflags(write=False)
        if self.lanes:  # each channel's state rows, and the coefficients, as floats
            self._bl, self._al = self.b.tolist(), self.a.tolist()
            self._zl = [[0.0] * n for _ in range(channels)]
            return
        # The state, in one of two buffers: above first order, advance builds the new state in the
        # other one and swaps (no copy back), so each buffer comes with its views made once: its
        # first row (free), its last (first order writes it), all but its first (the old state's
        # rows advance reads), all but its last (the new state's rows advance adds them to).
        bufs = (np.zeros((n, channels)), np.zeros((n, channels)))
        self._views = [(b, b[0] if n else b, b[-1] if n else b, b[1:], b[:-1]) for b in bufs]
        self._cur = 0
        self.z, self._z_first, self._z_last, self._z_tail, _ = self._views[0]
        # b[1..n], a[1..n] as columns, and a scratch row set: advance builds every new state row
        # (the products, their difference, then plus the old next row), four numpy calls whatever
        # the order.
        self._b_col, self._a_col = self.b[1:, None].copy(), self.a[1:, None].copy()
        self._t2 = np.zeros((n, channels))
        # b[0], b[n], a[n] as arrays of one value per channel for advance: an array times them gives
        # the same IEEE products as times the scalar, at about half the cost (numpy converts a scalar
        # operand on every call; measured 2.4 -> 1.7 us an advance at 2 channels).
        ends = (self.b[0], self.b[-1], self.a[-1])
        self._b0, self._bn, self._an = (np.full(channels, float(c)) for c in ends)

    @property
    def feedthrough(self) -> float:
        """D: the part of this tick's output proportional to this tick's input."""
        return float(self.b[0])

    def free(self) -> Array:
        """The part of this tick's output that the state alone determines."""
        if self.lanes:
            return np.array(self.free_lanes()) if self.order else self._zero
        return self._z_first if self.order else self._zero

    def free_lanes(self) -> list[float]:
        """:meth:`free` as floats, one per channel (``lanes`` only)."""
        return [z[0] for z in self._zl] if self.order else [0.0] * len(self._zl)

    def advance(self, u: Array) -> Array:
        """Commit this tick's input; returns the output ``D u + free``."""
        if self.lanes:
            return np.array(self.step(u.tolist()))
        y = self._b0 * u + (self._z_first if self.order else 0.0)
        if self.order > 1:
            # Every row at once, into the other buffer: z[i] <- (b[i+1] u - a[i+1] y) + z[i+1] from
            # the old z[i+1], and z[n-1] <- b[n] u - a[n] y; the same IEEE operations, in the same
            # order, as the loop over i did.
            self._cur ^= 1
            t, first, last, tail, head = self._views[self._cur]
            np.multiply(self._b_col, u, out=t)
            np.multiply(self._a_col, y, out=self._t2)
            np.subtract(t, self._t2, out=t)
            np.add(head, self._z_tail, out=head)
            self.z, self._z_first, self._z_last, self._z_tail = t, first, last, tail
        elif self.order:
            np.subtract(self._bn * u, self._an * y, out=self._z_last)  # z[-1] = b[n] u - a[n] y
        return y if type(y) is np.ndarray else np.asarray(y, dtype=float)

    def commit(self, u: Array) -> None:
        """:meth:`advance` without making its output (what the models call every tick)."""
        if self.lanes:
            self.step(u.tolist())
        else:
            self.advance(u)

    def step(self, u: list[float]) -> list[float]:
        """:meth:`advance` on floats, channel by channel (``lanes`` only): per channel
        ``y = b0 u + z0``, ``z[i] <- (b[i+1] u - a[i+1] y) + z[i+1]``, ``z[n-1] <- b[n] u - a[n] y``."""
        b, a, n = self._bl, self._al, self.order
        b0, bn, an = b[0], b[n], a[n]
        out = []
        for uc, z in zip(u, self._zl, strict=True):
            y = b0 * uc + (z[0] if n else 0.0)
            for i in range(n - 1):
                z[i] = (b[i + 1] * uc - a[i + 1] * y) + z[i + 1]
            if n:
                z[n - 1] = bn * uc - an * y
            out.append(y)
        return out


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
        self._y.setflags(write=False)  # constant: the node may reuse what it derives from it
        self._half_dt = dt / 2.0
        # The two values the reference takes, made once (read-only: returned every tick).
        self._off, self._on = np.zeros(dof), np.full(dof, float(amplitude))
        self._off.setflags(write=False)
        self._on.setflags(write=False)

    def reference(self, now: float) -> Array:
        return self._on if now + self._half_dt >= self.t_step else self._off

    def affine(self, now: float) -> tuple[Array, Array]:
        return self.reference(now) - self.admittance.free(), self._y

    def advance(self, now: float, v: Array, f: Array) -> None:
        self.admittance.commit(f)


class LtiEnvironment:
    """An impedance ``F = Z_e(s) v`` per DoF; Section V uses ``Z_e = 1/(s+1)``."""

    def __init__(
        self, dof: int, dt: float, num: Sequence[float] = (1.0,), den: Sequence[float] = (1.0, 1.0)
    ) -> None:
        self.impedance = DiscreteLTI(num, den, dt, dof)
        self._z = np.full(dof, self.impedance.feedthrough)
        self._z.setflags(write=False)  # constant: the node may reuse what it derives from it

    def affine(self, now: float) -> tuple[Array, Array]:
        return self.impedance.free(), self._z

    def advance(self, now: float, v: Array, f: Array) -> None:
        self.impedance.commit(v)


def _smooth_steps(
    t: float, knots: Sequence[tuple[float, float]], ramp: float, first: int = -1
) -> tuple[float, int]:
    """Piecewise-constant profile ``[(t_start, value), ...]`` with raised-cosine ramps of ``ramp`` s.

    Returns the value at ``t`` and the last knot whose ramp had ended by ``t``: a later call may pass
    it as ``first`` for any time not before ``t``.  Why: a knot whose ramp has ended sets the value to
    its target exactly, whatever came before, so the loop may start there and give the same bits;
    from the start it walks every knot, ~2.4 us a tick after 5 s of the task (issue 22)."""
    v, settled = (0.0, -1) if first < 0 else (knots[first][1], first)
    for i in range(first + 1, len(knots)):
        t0, target = knots[i]
        if t < t0:
            break
        a = min(1.0, (t - t0) / ramp)
        if a < 1.0:
            v = v + (target - v) * 0.5 * (1.0 - math.cos(math.pi * a))
        else:
            v, settled = target, i
    return v, settled


# MAX_VARIATION (teleop.limits), twice the documented spread, keeps every varied plan's knots in
# order and its phases at least 4 s long (see :class:`ProtocolPlan`).
_HUMAN_STREAM = 0x48554D414E  # "HUMAN": the human's draws never share a stream with the netem shims


@dataclass(frozen=True)
class ProtocolPlan:
    """One performance of the Section VI task: what a person varies when repeating it.

    ``ProtocolPlan.draw(seed, variation)`` draws it from ``seed`` (its own numpy stream, tagged, so
    it is independent of the netem shims' ``random.Random(2 seed + direction)``); ``variation``
    scales every spread, 0 giving exactly the scripted plan (the defaults).  Spread per unit of
    variation, each a uniform draw in +-spread:

    ========================  ============  =================================================
    stroke amplitude          +-20 %        free-space strokes, default 5 cm
    stroke frequency          +-20 %        default 0.5 Hz; rounded to whole half-periods in
                                            free space so the stroke ends at rest (no jump)
    phase boundaries          +-0.25 s      foam from 5 s, wall from 10 s
    push timing               +-0.08 s      each knot of the foam and wall pushes but the first
    push depth                +-20 %        intended push velocity, default 4 and 5 cm/s
    arm stiffness k           +-20 %        default 300 N/m
    grip stiffness k_grip     +-30 %        default 2000 N/m
    lateral sine (DoF >= 1)   +-20 %        amplitude 3 cm/s and frequency 0.3 j Hz; the
                                            frequency rounded to whole half-periods in free
                                            space too
    ========================  ============  =================================================

    Why both roundings: the foam's damping switches on for every DoF at ``t_foam``; a hand still
    moving then meets a force step, and the one-tick loop floor turns a step into an error that
    would dominate the foam phase's I (measured, seed 0: 40 times the scripted run's, from the lateral
    DoF alone).  The scripted plan has both velocities at zero at 5 s; every drawn plan keeps that.

    The grip's damping stays equal to ``b``: it is what absorbs reflections (ProtocolHuman).
    Both processes draw the same plan from the handshake's ``seed`` and ``variation``, so the
    environment switches phase exactly when the human expects it.
    """

    stroke_amp: float = 0.05  # m
    stroke_freq: float = 0.5  # Hz, whole half-periods in [0, t_foam)
    t_foam: float = 5.0  # s, free space before
    t_wall: float = 10.0  # s, foam before, foam and wall after
    t_end: float = 15.0  # s, the wall pushes are laid out up to here
    foam_depth: float = 0.04  # m/s intended into the foam
    wall_depth: float = 0.05  # m/s intended into the wall
    knot_jitter: tuple[float, ...] = (0.0,) * 10  # s, per knot of the foam then wall pushes
    k: float = 300.0  # N/m, arm
    k_grip: float = 2000.0  # N/m, grip
    lateral_amp: float = 0.03  # m/s
    lateral_freq: float = 0.3  # Hz (times the DoF index)

    @classmethod
    def draw(cls, seed: int, variation: float) -> ProtocolPlan:
        """The plan of run ``seed`` at ``variation`` (0: the scripted plan, bit for bit)."""
        if not 0.0 <= variation <= MAX_VARIATION:
            raise ModelError(f"variation must be in 0..{MAX_VARIATION:g}, got {variation!r}")
        u = default_rng([seed, _HUMAN_STREAM]).uniform(-1.0, 1.0, 20) * variation
        t_foam = 5.0 + 0.25 * u[2]
        half_periods = max(1, round(2.0 * 0.5 * (1.0 + 0.2 * u[1]) * t_foam))
        return cls(
            stroke_amp=0.05 * (1.0 + 0.2 * u[0]),
            stroke_freq=half_periods / (2.0 * t_foam),
            t_foam=t_foam,
            t_wall=10.0 + 0.25 * u[3],
            foam_depth=0.04 * (1.0 + 0.2 * u[4]),
            wall_depth=0.05 * (1.0 + 0.2 * u[5]),
            knot_jitter=tuple(float(x) for x in 0.08 * u[6:16]),
            k=300.0 * (1.0 + 0.2 * u[16]),
            k_grip=2000.0 * (1.0 + 0.3 * u[17]),
            lateral_amp=0.03 * (1.0 + 0.2 * u[18]),
            lateral_freq=max(1, round(2.0 * 0.3 * (1.0 + 0.2 * u[19]) * t_foam)) / (2.0 * t_foam),
        )

    def phases(self, duration: float) -> list[tuple[str, float, float]]:
        """``(name, start, end)`` of free space, foam and wall, clipped to ``duration`` s."""
        bounds = (
            ("free", 0.0, self.t_foam),
            ("foam", self.t_foam, self.t_wall),
            ("wall", self.t_wall, duration),
        )
        return [(n, min(a, duration), min(b, duration)) for n, a, b in bounds]

    def knots(self) -> list[tuple[float, float]]:
        """The foam and wall pushes: the scripted knots scaled to this plan's phase lengths."""
        foam = ((0.0, 1.0), (2.0, 0.0), (2.5, -1.0), (4.5, 0.0))
        wall = ((0.0, 1.0), (1.0, -1.0), (2.0, 0.0), (2.5, 1.0), (3.5, -1.0), (4.5, 0.0))
        sf = (self.t_wall - self.t_foam) / 5.0
        sw = (self.t_end - self.t_wall) / 5.0
        out = [(self.t_foam + t * sf, self.foam_depth * a) for t, a in foam]
        out += [(self.t_wall + t * sw, self.wall_depth * a) for t, a in wall]
        # The first knot of each phase stays on its boundary: a push starts when contact can.
        return [
            (t + (j if i not in (0, 4) else 0.0), a)
            for i, ((t, a), j) in enumerate(zip(out, self.knot_jitter, strict=True))
        ]


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
    DoF 0 is the pushing direction; any further DoF moves laterally (a slow sine).  ``plan`` (a
    seeded :class:`ProtocolPlan`) varies the performance; the default is the scripted one.
    """

    def __init__(
        self,
        dof: int,
        dt: float,
        m: float = 1.0,
        d: float = 20.0,
        c_grip: float = 20.0,
        plan: ProtocolPlan | None = None,
    ) -> None:
        self.dof = dof
        self.plan = plan or ProtocolPlan()
        k, k_grip = self.plan.k, self.plan.k_grip
        arm_num, arm_den = np.array([1.0, 0.0]), np.array([m, d, k])
        grip_num, grip_den = np.array([1.0, 0.0]), np.array([c_grip, k_grip])
        num = np.polyadd(np.polymul(arm_num, grip_den), np.polymul(grip_num, arm_den))
        den = np.polymul(arm_den, grip_den)
        self.admittance = DiscreteLTI(tuple(num), tuple(den), dt, dof)
        self._y = np.full(dof, self.admittance.feedthrough)
        self._y.setflags(write=False)  # constant: the node may reuse what it derives from it
        self._ref = np.zeros(dof)
        self._lateral = self._ref[1:]  # the lateral DoF's references, written in place
        # 2 pi f j of each lateral DoF j, made once: ((2 pi) f) j is what reference multiplied by
        # the time, left to right, so the products are the same bits.
        self._lateral_w = 2 * np.pi * self.plan.lateral_freq * np.arange(1, dof, dtype=np.float64)
        self._lateral_wl = self._lateral_w.tolist()
        self._knots = self.plan.knots()
        self._settled, self._settled_at = -1, -math.inf  # _smooth_steps' resume point, and its time
        self._w = 2 * np.pi * self.plan.stroke_freq

    def push_profile(self, t: float) -> float:
        if t < self.plan.t_foam:  # free space: strokes of +-amplitude, ending at rest
            w = self._w
            # math.sin, not np.sin: the same libm result for a float (tests/test_fastpath.py), without
            # numpy's scalar dispatch and a numpy float through the products (every tick).
            return self.plan.stroke_amp * w * math.sin(w * t)
        # Resumed from the last knot settled by an earlier tick, unless time went back (a caller's).
        first = self._settled if t >= self._settled_at else -1
        v, self._settled = _smooth_steps(t, self._knots, 0.15, first)
        self._settled_at = t
        return v

    def reference(self, now: float) -> Array:
        self._ref[0] = self.push_profile(now)
        if self.dof > 1:
            # Starts from rest: a jump would ring the one-tick wave loop (docs/results/sim.md, Models).
            # lateral_amp sin(w_j now) over DoF 1.. in place, three numpy calls (the same IEEE
            # operations per element as a loop of scalars, bit for bit).
            lat = self._lateral
            np.multiply(self._lateral_w, now, out=lat)
            np.sin(lat, out=lat)
            np.multiply(lat, self.plan.lateral_amp, out=lat)
        return self._ref

    def reference_lanes(self, now: float) -> list[float]:
        """:meth:`reference` as floats: ``math.sin`` gives ``np.sin``'s bits for a float64 (numpy's
        own loop is correctly rounded like libm's here; tests/test_models.py holds them equal)."""
        amp = self.plan.lateral_amp
        return [self.push_profile(now), *[math.sin(w * now) * amp for w in self._lateral_wl]]

    def affine(self, now: float) -> tuple[Array, Array]:
        lti = self.admittance
        if lti.lanes:
            ref, free = self.reference_lanes(now), lti.free_lanes()
            return np.array([r - z for r, z in zip(ref, free, strict=True)]), self._y
        return self.reference(now) - lti.free(), self._y

    def advance(self, now: float, v: Array, f: Array) -> None:
        self.admittance.commit(f)


class ProtocolEnvironment:
    """Free space 0-5 s, foam (a damper) 5-10 s, foam plus a stiff wall on DoF 0 from 10 s.

    The phase times are the ``plan``'s (the same seeded plan as the human's), 5 and 10 s by default.

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
        plan: ProtocolPlan | None = None,
    ) -> None:
        plan = plan or ProtocolPlan()
        self.t_foam, self.t_wall = plan.t_foam, plan.t_wall
        self.dt = dt
        self.foam = foam
        self.k = k_wall
        self.c = c_wall
        self.gap = wall_gap
        self.x = np.zeros(dof)
        self.wall: float | None = None
        # Out of contact the map is one of two constants, returned as the same read-only arrays
        # every tick: no writes, and the node makes what it derives from Z once per phase
        # (TeleoperatorNode._den).  In contact, fresh arrays each tick.
        self._free, self._z_free, self._z_foam = np.zeros(dof), np.zeros(dof), np.full(dof, float(foam))
        for a in (self._free, self._z_free, self._z_foam):
            a.setflags(write=False)

    def affine(self, now: float) -> tuple[Array, Array]:
        z = self._z_foam if now >= self.t_foam else self._z_free
        if now >= self.t_wall:
            if self.wall is None:
                self.wall = float(self.x[0]) + self.gap
            pen = self.x[0] - self.wall
            if pen > 0:
                f0, z = np.zeros_like(self._free), z.copy()
                f0[0] = self.k * pen
                z[0] += self.k * self.dt + self.c
                return f0, z
        return self._free, z

    def advance(self, now: float, v: Array, f: Array) -> None:
        self.x += v * self.dt
