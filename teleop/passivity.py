"""Energy watchdog (observer) and passivity controller for one received wave, per direction.

The channel is passive when, per direction, the wave energy played out never exceeds the wave
energy put in (eq. 5): ``E_in(t) - E_out(t) >= 0`` with ``E = 1/2 int(wave^2) dt``.  The sender
carries its cumulative ``E_in`` in every packet (``teleop.wire``), so the receiver can check this
online under any delay, loss, duplication or reordering: the newest report is a lower bound of
what really went in, so a margin computed from it is conservative.

At every tick, before a sample is played:

* the **observer** computes ``margin = E_in_reported - (E_played + 1/2 x^2 dt)`` for the proposed
  sample ``x``; a negative value is a *violation* (what the codec or a reconstruction rule would
  have generated);
* the **controller**, when enabled, scales ``x`` so that the margin is exactly zero instead,
  counting the active tick and the energy it dissipated.  This is the network form of the
  time-domain passivity approach (observer plus controller), applied in scattering variables.

Link supervision: when nothing has been accepted for ``link_timeout`` seconds the link is *lost*;
the node then goes to a safe state (see ``teleop.node``) and resumes when packets return.
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
        self._origin_from_next_report = joined_late

    @property
    def margin(self) -> float:
        return (self.reported_in - self.reported_origin) - (self.played - self.played_origin)

    @property
    def played_in_epoch(self) -> float:
        return self.played - self.played_origin

    def admit(self, x: Array) -> Array:
        """The sample to play instead of ``x``: ``x`` itself unless it would generate energy."""
        e = self.half_dt * float(np.dot(x, x))
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
