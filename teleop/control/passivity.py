"""Energy watchdog (observer) and passivity controller for one received wave, per direction.

The channel is passive when, per direction, the wave energy played out never exceeds the wave
energy put in (eq. 5): ``E_in(t) - E_out(t) >= 0`` with ``E = 1/2 int(wave^2) dt``.  The sender
carries its cumulative ``E_in`` in every packet (``teleop.session.wire``), so the receiver can check this
online under any delay, loss, duplication or reordering: the newest report is a lower bound of
what really went in, so a margin computed from it is conservative.

At every tick, before a sample is played:

* the **observer** computes ``margin = E_in_reported - (E_played + 1/2 x^2 dt)`` for the proposed
  sample ``x``; a negative value is a *violation* (what the codec or a reconstruction rule would
  have generated);
* the **controller**, when enabled, scales ``x`` so that the margin is exactly zero instead,
  counting the active tick and the energy it dissipated.  This is the network form of the
  time-domain passivity approach (observer plus controller), applied in scattering variables.

Under ``--passivity tdpa`` the same in-band reports serve the time-domain passivity approach on
power variables instead (:class:`TdpaGuard`, :func:`series_damper`, :func:`parallel_damper`, below).

Link supervision: when nothing has been accepted for ``link_timeout`` seconds the link is *lost*;
the node then goes to a safe state (see ``teleop.session.node``) and resumes when packets return.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]

ON_LOSS = ("zero", "hold", "conceal")
DEFAULT_LINK_TIMEOUT = 0.050
REPORT_BURST_S = 0.2  # s of saturated power a burst of in-band energy reports may claim at once


@dataclass
class PassivityReport:
    violations: int = 0  # ticks whose proposed sample would have made the margin negative
    controller_active_ticks: int = 0
    min_margin: float = math.inf  # J, after the controller (observed, in-band)
    energy_dissipated: float = 0.0  # J removed by the controller
    link_lost_events: int = 0
    link_lost_ticks: int = 0
    energy_reports_clamped: int = 0  # in-band reports that claimed more than the wire can carry

    def as_dict(self) -> dict[str, float | int]:
        d = dict(self.__dict__)
        if math.isinf(self.min_margin):
            d["min_margin"] = 0.0
        return d


class EnergyGuard:
    """Observer + controller for the wave one node receives.  Pure: no clock, no I/O."""

    def __init__(
        self,
        dt: float,
        controller: bool = True,
        tolerance: float = 1e-12,
        max_power: float = math.inf,
        burst_s: float = REPORT_BURST_S,
    ) -> None:
        self.half_dt = 0.5 * dt
        self.controller = controller
        self.tolerance = tolerance
        self.reported_in = 0.0  # J, newest cumulative E_in reported by the sender
        # Defence in depth: the budget is the peer's word, so bound it by physics.  A token bucket
        # fills at ``max_power`` (saturated waves: 1/2 dof RANGE^2 W, all the wire format can carry)
        # up to ``burst_s`` of it (reports bunched by jitter); a report beyond it is clamped.
        self.max_power = max_power
        self.burst_s = burst_s
        self._depth = max_power * burst_s
        self._allowance = self._depth
        self._t_allowance: float | None = None
        self.played = 0.0  # J, E_out so far
        self.report = PassivityReport()
        # Energy epochs: after a peer restarts, or when joining a session late, the account restarts
        # so that energy sent to (or played by) another incarnation is never counted as budget.
        self.reported_origin = 0.0
        self.played_origin = 0.0
        self._origin_from_next_report = False
        # Self-credit (``pdr``'s cKAPPA, eq. 1 via 4): J this side credited its own budget out of
        # energy it sent and withholds from its reports (``credit``).
        self.credited = 0.0
        self.credited_origin = 0.0

    def bound(self, max_power: float) -> None:
        """Bound the peer's reports by ``max_power`` W from now on (a robot's own limits, set as its
        session starts, before any report): the token bucket starts full at its new depth."""
        self.max_power = max_power
        self._depth = max_power * self.burst_s
        self._allowance = self._depth

    def sent(self, energy: float, now: float = 0.0) -> None:
        """A packet reported the sender's cumulative energy (reordered reports never lower it);
        ``now`` is the receiver's session time, which refills the physical allowance."""
        if not math.isfinite(energy):
            self.report.energy_reports_clamped += 1
            return
        if self._t_allowance is not None and now > self._t_allowance:
            self._allowance = min(self._depth, self._allowance + self.max_power * (now - self._t_allowance))
        self._t_allowance = now if self._t_allowance is None else max(now, self._t_allowance)
        if self._origin_from_next_report:
            # Joined late: what the sender sent before this first report was played by someone else.
            self.reported_origin = self.reported_in = energy
            self._origin_from_next_report = False
        elif energy > self.reported_in:
            growth = energy - self.reported_in
            if growth > self._allowance + self.tolerance:
                self.report.energy_reports_clamped += 1
                growth = self._allowance
            self._allowance -= growth
            self.reported_in += growth

    def new_epoch(self, joined_late: bool) -> None:
        """Restart the account: the peer restarted (its reports start again from 0), or this side
        joined a running session late (the first report it sees becomes the origin)."""
        self.reported_in = self.reported_origin = 0.0
        self.played_origin = self.played
        self.credited_origin = self.credited
        self._origin_from_next_report = joined_late

    @property
    def margin(self) -> float:
        # Plus what was self-credited (0.0 without: ``m - 0.0`` is ``m`` bit for bit).
        return (
            (self.reported_in - self.reported_origin)
            - (self.played - self.played_origin)
            - (self.credited_origin - self.credited)
        )

    def credit(self, amount: float) -> None:
        """Add ``amount`` J to this budget out of the energy this side sent and has not reported
        (``pdr``'s self-credit): the caller withholds it from its reports, so eq. (1) via (4) holds
        over both directions (``teleop.control.codecs.reflective.ReflectiveEncoder._self_credit``)."""
        if not amount >= 0.0:
            raise ValueError(f"credit must be >= 0 J, got {amount!r}")
        self.credited += amount

    @property
    def played_in_epoch(self) -> float:
        return self.played - self.played_origin

    def admit(self, x: Array) -> Array:
        """The sample to play instead of ``x``: ``x`` itself unless it would generate energy."""
        # ``x.dot(x)`` is ``np.dot(x, x)`` (the same BLAS call, same bits) without the function's
        # dispatch: this runs every tick.
        e = self.half_dt * float(x.dot(x))
        budget = self.margin
        r = self.report
        if e > budget + self.tolerance:
            r.violations += 1
            if self.controller:
                allowed = max(budget, 0.0)
                scale = math.sqrt(allowed / e) if e > 0 else 0.0
                x = x * scale
                r.controller_active_ticks += 1
                r.energy_dissipated += e - allowed
                e = allowed
        self.played += e
        m = self.margin
        if m < r.min_margin:
            r.min_margin = m
        return x


# --- the time-domain passivity approach (TDPA), network form -----------------------------------
#
# Ryu, Kwon and Hannaford (IEEE TRO 2004) observe the energy of a one-port and dissipate what it
# would generate; Artigas et al. (ICRA 2010, "time delay power networks") split the delayed channel
# into two such networks, one per direction of energy flow.  Power variables cross the channel:
# velocity forward, force back.  At each port ``P = v . F`` is the power into the network (eq. 2,
# HSI side) and its sign splits it: ``E_in`` sums ``max(P, 0) dt`` (reported to the peer in-band),
# ``E_out`` sums ``max(-P, 0) dt``.  Per direction the observer is
#
#     E_obs = E_in(peer, as reported so far) - E_out(here) >= 0
#
# and the passivity controller (PC) dissipates exactly what would make it negative: a series damper
# on the commanded velocity at the teleoperator, a parallel damper on the displayed force at the
# operator.  A report can only be older than the truth (delay, jitter, loss, reordering), never
# newer, so the bound holds for any channel.


class TdpaGuard(EnergyGuard):
    """TDPA observer + controller bookkeeping of the direction one port receives.

    ``played`` is this port's ``E_out`` (energy the network delivered to the local device),
    ``reported_in`` the peer's ``E_in`` as last reported; the epochs, the physical allowance of
    reports and :attr:`margin` are :class:`EnergyGuard`'s.  The damper itself is solved by the node
    (:func:`series_damper`, :func:`parallel_damper`) from the budget this guard gives.
    """

    def __init__(self, dt: float, controller: bool = True, max_power: float = math.inf) -> None:
        super().__init__(dt, controller=controller, max_power=max_power)
        self.dt = dt
        self.energy_in = 0.0  # J into the network at this port: what the peer is told

    def allowed_power(self) -> float:
        """W the port may let out this tick without making ``E_obs`` negative (>= 0)."""
        return max(self.margin, 0.0) / self.dt

    def account(self, power: float, removed: float, violation: bool, active: bool) -> None:
        """Book one tick: ``power`` W into the network at this port (after the PC), ``removed`` W
        the PC dissipated (the excess over the budget: ``energy_dissipated`` counts it, J)."""
        dt = self.dt
        if power > 0.0:
            self.energy_in += power * dt
        else:
            self.played -= power * dt
        r = self.report
        if violation:
            r.violations += 1
        if active:
            r.controller_active_ticks += 1
            r.energy_dissipated += removed * dt
        m = self.margin
        if m < r.min_margin:
            r.min_margin = m


def _root(a2: float, a1: float, a0: float) -> float:
    """The positive root of ``a2 x^2 + a1 x + a0`` with ``a2 >= 0 > a0`` (there is exactly one, or
    none when ``a2 == 0 and a1 <= 0``: then ``inf``); the form without cancellation."""
    den = a1 + math.sqrt(max(a1 * a1 - 4.0 * a2 * a0, 0.0))
    return -2.0 * a0 / den if den > 0.0 else math.inf


def series_damper(
    v_cmd: Array, f0: Array, z: Array, allowed: float
) -> tuple[Array, Array, float, float, bool]:
    """The teleoperator's PC: ``v = v_cmd - alpha F`` with the environment ``F = f0 + Z v``.

    Returns ``(v, F, power, removed, acted)``: ``power = v . F <= allowed`` (W out of the network
    into the robot; exactly ``allowed`` when the damper acts) and ``removed``, the excess power the
    PC took away (what the tick would have let out without it, minus ``power``).  With one
    feedthrough ``Z >= 0`` for every DoF (every built-in environment) alpha is the positive root of
    ``allowed (1 + Z a)^2 + a f0.Fc - v_cmd.Fc = 0``, ``Fc = f0 + Z v_cmd``; otherwise the command
    is scaled, ``v = s v_cmd`` with the largest ``s`` in [0, 1] that fits.
    """
    fc = f0 + z * v_cmd
    p = float(np.dot(v_cmd, fc))
    if p <= allowed:
        return v_cmd, fc, p, 0.0, False
    zs = float(z[0])
    uniform = zs >= 0.0 and bool(np.all(z == zs))
    alpha = (
        _root(allowed * zs * zs, 2.0 * allowed * zs + float(np.dot(f0, fc)), allowed - p) if uniform else 0.0
    )
    if uniform and math.isinf(alpha) and zs > 0.0:  # nothing allowed: the robot yields, F = 0
        return -f0 / zs, np.zeros_like(fc), 0.0, p, True
    if uniform and not math.isinf(alpha):
        d = 1.0 + zs * alpha
        f = fc / d
        v = (v_cmd - alpha * f0) / d
    else:  # several feedthroughs, or a root lost to underflow with Z = 0
        v = _scale(float(np.dot(v_cmd, z * v_cmd)), float(np.dot(v_cmd, f0)), allowed) * v_cmd
        f = f0 + z * v
    out = float(np.dot(v, f))
    return v, f, out, p - out, True


def parallel_damper(
    v0: Array, y: Array, f_c: Array, allowed: float, beta0: float = 0.0
) -> tuple[Array, Array, float, float, bool]:
    """The operator's PC: display ``F = f_c + beta v`` to the human ``v = v0 - Y F``, ``beta >= beta0``.

    ``beta0`` is the HSI's own rendered damping (:data:`teleop.session.node.TDPA_HSI_DAMPING`): the work
    the human does against it enters the network like any other.  Returns
    ``(v, F, power, removed, acted)``: ``power = v . F >= -allowed`` (W into the network;
    ``-allowed`` when the damper acts) and ``removed``, the excess the PC took away.  With one
    feedthrough ``Y >= 0`` per DoF beta is the positive root of
    ``allowed Y^2 b^2 + (p Y + |u|^2 + 2 allowed Y) b + p + allowed = 0`` (``u = v0 - Y f_c``,
    ``p = u . f_c``), which exceeds ``beta0`` when the damper must act; otherwise the received
    force is scaled (``F = s f_c + beta0 v``).
    """
    u = v0 - y * f_c
    v = u / (1.0 + y * beta0) if beta0 else u
    f = f_c + beta0 * v if beta0 else f_c
    p0 = float(np.dot(v, f))
    if p0 >= -allowed:
        return v, f, p0, 0.0, False
    ys = float(y[0])
    uniform = ys >= 0.0 and bool(np.all(y == ys))
    beta = math.inf
    if uniform:
        p = float(np.dot(u, f_c))
        beta = _root(allowed * ys * ys, p * ys + float(np.dot(u, u)) + 2.0 * allowed * ys, p + allowed)
        if math.isinf(beta) and ys > 0.0:  # nothing allowed: the hand is held, v = 0
            return np.zeros_like(u), v0 / ys, 0.0, -p0, True
    if not math.isinf(beta):
        v = u / (1.0 + ys * beta)
        f = f_c + beta * v
    else:  # several feedthroughs, or a root lost to underflow with Y = 0
        # v = A - B s, P(s) = v . (s f_c + beta0 v) >= -allowed: the largest s in [0, 1]
        a_ = v0 / (1.0 + y * beta0)
        b_ = y * f_c / (1.0 + y * beta0)
        a = float(np.dot(b_, f_c)) - beta0 * float(np.dot(b_, b_))
        b = -float(np.dot(a_, f_c)) + 2.0 * beta0 * float(np.dot(a_, b_))
        s = _scale(a, b, allowed + beta0 * float(np.dot(a_, a_)))
        v = a_ - b_ * s
        f = s * f_c + beta0 * v
    into = float(np.dot(v, f))
    return v, f, into, into - p0, True


def _scale(a: float, b: float, c: float) -> float:
    """The largest ``s`` in ``[0, 1]`` with ``a s^2 + b s <= c`` given ``c >= 0`` and ``a + b > c``."""
    if a == 0.0:
        return c / b  # b > c >= 0
    disc = math.sqrt(max(b * b + 4.0 * a * c, 0.0))
    roots = [r for r in ((-b + disc) / (2.0 * a), (-b - disc) / (2.0 * a)) if 0.0 <= r <= 1.0]
    s = max(roots, default=0.0)
    return s if a * s * s + b * s <= c else 0.0
