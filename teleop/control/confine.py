"""The robot's envelope on what its device is finally commanded, and the contact it cannot see.

Every element between the channel and the device (the wave solve, TDPA's position controller and
its yield, concealment, the fade, a rejoin) may ask for any velocity; :meth:`Confinement.command`
is the last step before the device and holds, per DoF:

* ``|v| <= max_velocity``, always;
* the contact force ``F = f0 + Z v`` the tick ends with within ``+-max_force``: a command that
  would push past it is slowed (never reversed), and a force already past it is **relieved**: the
  robot backs off, at up to ``max_velocity``, to the velocity that brings ``F`` back to
  ``max_force`` (``(max_force - f0) / Z``), instead of holding it.

**A robot whose force comes one tick late.**  A force-sensing arm reports the force the last tick
left and no feedthrough (``Z = 0``).  In a contact of stiffness ``K`` its force then moves by
``K v dt`` a tick that the port cannot predict: the wave solve and TDPA's yield, ``v = ... - F /
b``, feed it back with a loop gain ``K dt / b`` and oscillate at the tick rate once it passes 2
(``K = 10^4`` N/m at ``b = 5``), and the envelope cannot see the force it is about to cause.  So
:meth:`Confinement.effective` learns, per DoF where the device reports ``Z = 0``, the feedthrough
the contact has from the robot's own motion ``v`` and the force change ``dF`` the next tick
reports: least squares over the ticks spent in contact (``sum dF v / sum v^2``, forgotten with
:data:`CONTACT_MEMORY_S`), at least what a tick entering the contact showed (a lower bound: the
contact began somewhere within its motion), at most :data:`MAX_STIFFNESS` ``dt``, and held only
while in contact (faded with :data:`CONTACT_MEMORY_S` once the force is gone, so free motion is
not slowed for long).  A force below :data:`FORCE_FLOOR` of ``max_force`` is no contact (a
sensor's noise).  The node solves with it as if the device had reported it, so the loop gain
becomes ``K dt / (b + K dt) < 1``: no oscillation, under wave variables and TDPA alike, and the
envelope predicts the force.

**The overshoot.**  On a new contact (not met before, or left for about :data:`CONTACT_MEMORY_S`),
one tick at up to ``max_velocity`` reaches ``F <= max_force + K max_velocity dt``; that tick shows
the stiffness (all of it for a linear contact entered at the tick's start, less for one entered
within it), and the next one relieves the excess: at most **one tick past ``max_force``** per new
contact.  A robot that reports its ``Z`` (``Z > 0``) never overshoots where that ``Z`` is right.

**Passive by construction.**  The envelope only changes the device's velocity; what the channel
sees is chosen so that the change absorbs energy (``teleop.session.node``): under wave variables
the port's wave carries the confined force where it has the sign of the cut ``v_port - v``, so the
cut absorbs ``(v_port - v) F >= 0``, and elsewhere the wave returns as it came (nothing taken,
nothing given); under TDPA the envelope acts after the observer and its controller, on the device
side of the position controller, so the network's books (``E_out <= E_in``) are the controller's,
unchanged.  The energy a relief takes out of the contact (the spring pushes the robot back) goes
into the robot's own actuator, which brakes it: it never enters the channel.  With ``Z^ >= K dt /
2`` the port also books at least the energy the contact stores (``sum v (f0 + Z^ v) dt >= K x^2 /
2``), where a port that saw only the late force books less and makes the difference up.
"""

from __future__ import annotations

import math

import numpy as np

from teleop.control.codecs import Array

#: s: the memory of the contact's least squares, and how fast a stiffness fades once the force is
#: gone (a tick keeps ``exp(-dt / this)``): a robot that left a stiff contact is slowed in free
#: motion for a few of it, and one that comes back within it finds the contact known.
CONTACT_MEMORY_S = 0.05
#: Of ``max_force``: a reported force below it is no contact (a sensor's noise, which divided by a
#: slow motion entering a contact would read as an absurd stiffness).
FORCE_FLOOR = 0.02
#: N/m: the stiffest contact the estimate believes (stiffer readings are a fault, held to this).
MAX_STIFFNESS = 1e7


def confined(
    v: list[float], f0: list[float], z: list[float], vmax: float, fmax: float
) -> tuple[list[float], bool]:
    """Per DoF, the velocity ``v`` within the envelope for a device ``F = f0 + z v`` (the module
    docstring's rules), and whether a force past ``fmax`` was relieved (or, with ``z = 0``, held
    back from: no push further into it)."""
    out: list[float] = []
    relief = False
    for vi, fi, zi in zip(v, f0, z, strict=True):
        w = vi
        past = fi > fmax or fi < -fmax
        relief = relief or past
        if zi > 0.0:  # the force the tick ends with within +-fmax: slowed, or backed off if past it
            hi, lo = (fmax - fi) / zi, (-fmax - fi) / zi
            w = hi if w > hi else lo if w < lo else w
        elif past:  # a force it cannot predict: push no further into it
            w = min(w, 0.0) if fi > 0.0 else max(w, 0.0)
        out.append(vmax if w > vmax else -vmax if w < -vmax else w)
    return out, relief


class Confinement:
    """The final command stage of one robot (per DoF ``max_velocity`` m/s, ``max_force`` N), with
    the stiffness of the contact it senses one tick late (module docstring).

    Per tick: :meth:`effective` with the device's ``(f0, Z)``, then the node's solve, then
    :meth:`command` with the velocity the solve asks for.  On plain floats: a few DoF each tick."""

    def __init__(self, dof: int, dt: float, max_velocity: float, max_force: float) -> None:
        self.max_velocity, self.max_force = max_velocity, max_force
        self.stiffness = [0.0] * dof  # Z^, N s/m: the learned feedthrough per DoF (K dt)
        self._zmax = MAX_STIFFNESS * dt
        self._keep = math.exp(-dt / CONTACT_MEMORY_S)
        self._floor = FORCE_FLOOR * max_force
        # Per DoF: the least-squares sums of the ticks spent in contact (dF v, v^2, forgotten with
        # CONTACT_MEMORY_S), the stiffness a tick entering contact showed (a lower bound: the
        # contact began somewhere within its motion), and how much of both is in force (1 in contact,
        # forgotten with CONTACT_MEMORY_S out of it, so free motion is not slowed for long).
        self._sfv, self._svv = [0.0] * dof, [0.0] * dof
        self._entry, self._held = [0.0] * dof, [0.0] * dof
        self._f0 = [0.0] * dof  # this tick's reported force (effective), for the next tick to learn from
        self._idle = True  # no stiffness held: a tick out of contact has nothing to learn
        self._last: tuple[list[float], list[float]] | None = None  # last tick's reported f0, commanded v
        self.relieved = 0  # ticks that began past max_force (backed off from it, or pushed no further)

    def effective(self, f0: Array, z: Array) -> Array:
        """``Z`` with the learned ``Z^`` where the device reports none; ``z`` itself (the same
        object) where nothing was learned, so a device's constant feedthrough stays cached."""
        fl = f0.tolist()
        floor = self._floor
        if self._idle and max(fl) <= floor and min(fl) >= -floor:
            self._f0 = fl  # no stiffness held and no contact: nothing to learn (most ticks)
            return z
        zl = z.tolist()
        last, zh, keep = self._last, self.stiffness, self._keep
        learned = False
        for i, zi in enumerate(zl):
            if zi > 0.0:
                continue
            v, f = (last[1][i], last[0][i]) if last is not None else (0.0, fl[i])
            df, touching = fl[i] - f, abs(fl[i]) > floor
            self._sfv[i] *= keep
            self._svv[i] *= keep
            if v != 0.0 and touching and abs(f) > floor:  # in contact over the whole tick: exact
                self._sfv[i] += df * v
                self._svv[i] += v * v
            elif v != 0.0 and touching and df * v > 0.0:  # entering contact within the tick
                self._entry[i] = max(self._entry[i], df / v)
            self._held[i] = 1.0 if touching else self._held[i] * keep
            ls = self._sfv[i] / self._svv[i] if self._svv[i] > 0.0 else 0.0
            h = self._held[i] * min(max(ls, self._entry[i]), self._zmax)
            zh[i] = h if h > 1e-9 else 0.0
            learned = learned or zh[i] > 0.0
        self._f0 = fl
        self._idle = not learned
        if not learned:
            return z
        return np.array([zi if zi > 0.0 else zh[i] for i, zi in enumerate(zl)])

    def command(self, v: Array, f0: Array, z: Array, f: Array | None = None) -> Array | None:
        """The velocity the device is commanded, within the envelope per DoF (module docstring),
        or None where that is ``v`` itself.  ``z``: the effective feedthrough (:meth:`effective`);
        ``f``: ``f0 + z v`` if the caller has it (a cheaper test of the common case)."""
        vl, fl = v.tolist(), f0.tolist()
        vmax, fmax = self.max_velocity, self.max_force
        if (
            max(vl) <= vmax
            and min(vl) >= -vmax
            and max(fl) <= fmax
            and min(fl) >= -fmax
            and (
                z is self._z_free
                or (f is not None and max(fe := f.tolist()) <= fmax and min(fe) >= -fmax)
                or self._free_of(z)
            )
        ):  # within every limit, and the force the tick ends with too (most ticks)
            self._last = (self._f0, vl)
            return None
        out, relief = confined(vl, fl, z.tolist(), vmax, fmax)
        self._last = (self._f0, out)
        self.relieved += relief
        return None if out == vl else np.array(out)

    _z_free: Array | None = None  # a read-only all-zero feedthrough already seen (a device's constant)

    def _free_of(self, z: Array) -> bool:
        """Whether ``z`` is all zero (remembered when read-only: a device's constant array)."""
        if any(z.tolist()):
            return False
        if not z.flags.writeable:
            self._z_free = z
        return True
