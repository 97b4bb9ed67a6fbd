"""Perceptual and predictive deadband on wave variables (direct LDR, Section IV.D, sent on events).

**Perceptual deadband** ``pd:K[:MAXMS]`` (Hinterseer et al., IEEE TSP 2008): a sample is sent only
when it leaves the Weber band of the last sent one, ``|x - x_sent| > k max(|x_sent|, floor)`` with
``k = K/100``; between sends the receiver holds the last sample.  **Predictive deadband**
``pdp:K[:MAXMS]`` (Sakr et al. 2009, Kammerl et al. 2010): each payload carries a value and a slope,
both sides extrapolate ``x_sent + slope * i`` linearly ``i`` ticks after it, and a sample is sent
when that prediction misses by more than the band.

*Band on the vector, not per DoF.*  ``|.|`` is the Euclidean norm over the DoF, the isotropic
(spherical) deadzone of Hinterseer's 3-D deadband: the just-noticeable difference of a force is
about its magnitude and direction, not about each axis, and a per-axis box would fire on whichever
axis crosses first and send the others along anyway.  ``floor`` (1/16 of the range) keeps the band
from shrinking to nothing near zero, where Weber's law stops holding (an absolute threshold).

*Heartbeat.*  Even a still signal is sent at least every ``MAXMS`` ms (default 100 ms): the link
supervision of ``teleop.session.node`` takes the codec's longest interval into account, so silence on a
still signal is never taken for a dead link, and a lost payload is replaced within ``MAXMS``.

*Passive reconstruction.*  Holding (or extrapolating) plays energy that was never sent: in wave
variables a held sample generates energy.  Two rules keep the channel passive:

1. The receiver plays a held sample only within the in-band budget, ``E_in reported - E_played``
   (eq. 5), enforced by its energy guard (``teleop.control.passivity``) on every tick.
2. The sender runs the receiver's reconstruction and its budget exactly (a constant delay only
   shifts both): when the next held sample would not fit in the budget the receiver knows of
   (the energy reported with the last payload), it sends *now*, which refreshes that budget with
   the energy sent since; a new sample that itself exceeds the budget is scaled down to fit (as
   eDS does, eq. 10).  So on a lossless channel the guard never has to cut a sample.
3. *Energy reserve.*  Rule 2 alone would send almost every tick: a hold plays about the energy the
   sender sends meanwhile, but the receiver only learns of it with the next payload, so a hold can
   last only as long as the *reserve* (energy sent and never played) covers it.  While that reserve
   is below ``RESERVE_TICKS`` ticks of the current power, the sender shrinks each new sample by up
   to ``RESERVE_FRACTION`` of the band (so the played value stays inside the Weber band of the true
   one), and the unplayed remainder builds the reserve.  The band is checked against the unshrunk
   value.  Measured on the Section VI protocol (``pdp:1``): budget-triggered sends fall from about
   600/s to 50/s; the reserve costs some transparency, which ``teleop sweep`` shows.

*On power variables (TDPA, ``Encoder.power``).*  Velocity and force are no energies, so rules 2
and 3 are off: the band, the heartbeat and one more trigger decide, in the manner of IEEE 1918.1.1
part II and Xu et al. (IEEE ToH 2016), where the deadband's updates carry TDPA's energy reports.
Between sparse updates the receiver's budget is the last report, so its passivity controller
damps what the sender has put in but not yet reported.  Xu et al. predict that energy at the
receiver; a prediction is a claim the sender has not made, and the bound ``E_out <= E_in
reported`` (PROTOCOL.md section 8) would then hold only approximately.  Here the sender sends
instead when its unreported input energy exceeds ``TDPA_REPORT_QUANTUM_J`` (``teleop.session.node`` sets
``Encoder.urgent``): an *energy-triggered update*, so the budget lags by at most that quantum and the
bound stays exact.  The quantum trades packets for damping.  Measured with ``teleop sim
--passivity tdpa``, quantum 2 mJ / 10 mJ / none: the step scenario (a steady 0.4 W into the
network) with ``pd:5`` at 0 ms, I_dc 0.036 / 0.089 / 0.203 at 189 / 42 / 10 packets/s forward, the
controllers removing 0.28 / 1.7 / 73 mJ; the protocol scenario, where little energy flows between
band crossings, much less (``pd:20:1000`` at 200 ms: I_dc 0.455 / 0.437 / 0.504 at 31 / 20 / 24
packets/s forward).

Guarantee (wave variables): per direction, the energy played never exceeds the energy reported
sent, at every tick, whatever the signal, the delay or the losses (rule 1; rule 2 only keeps rule 1
from costing transparency).  A hypothesis test checks both on arbitrary signals.
"""

from __future__ import annotations

import math

import numpy as np

from teleop.control.codecs.base import Array, CodecError, Encoder, PlayoutDecoder, RawFormat, pack, unpack16

FLOOR_FRACTION = 1.0 / 16.0  # of the range: the band's absolute floor (below it Weber's law fails)
SLOPE_SCALE = 1.0 / 64.0  # slope full scale, per tick, as a fraction of the range
SLOPE_WINDOW = 8  # ticks
DEFAULT_HEARTBEAT_MS = 100
RESERVE_TICKS = 100  # the energy reserve the sender builds: this many ticks of the current power
RESERVE_FRACTION = 0.5  # of the band: how much a sample is shrunk while the reserve is short
RESERVE_MAX_SHRINK = 0.05


def _norm(x: Array) -> float:
    """``np.linalg.norm(x)`` of a 1-D float array, which is ``sqrt(x.dot(x))`` (numpy's own code for
    the 2-norm of a vector; both square roots are IEEE's, correctly rounded) without its argument
    handling, several times the cost on a few DoF and run twice a tick."""
    return math.sqrt(float(x.dot(x)))


def send_reason(band: bool, heartbeat: bool, power: bool, urgent: bool, over_budget: bool) -> str:
    """Why a deadband encoder sends this tick, in order of precedence ("": it need not): outside the
    band (or nothing sent yet), the heartbeat, under TDPA an urgent energy report, under wave
    variables a hold that would play more than the receiver's budget (eq. 10).  One rule for every
    deadband (``pd``, ``pdp``, ``pdr``)."""
    if band:
        return "band"
    if heartbeat:
        return "heartbeat"
    if power:
        return "energy" if urgent else ""
    return "budget" if over_budget else ""


def _slope_weights(n: int) -> Array:
    """Weights ``w`` with ``w @ x[-n:]`` the least-squares slope of ``x`` against the tick."""
    t = np.arange(n, dtype=np.float64) - (n - 1) / 2.0
    return t / float(np.dot(t, t))


class DeadbandEncoder(Encoder):
    """Sender side of ``pd`` (``predictive`` False) and ``pdp`` (True); see the module docstring."""

    def __init__(self, raw: RawFormat, dof: int, k_pct: float, heartbeat: int, predictive: bool) -> None:
        self.raw = raw
        self.slope_raw = RawFormat(raw.full_scale * SLOPE_SCALE)
        self.k = k_pct / 100.0
        self.floor = raw.full_scale * FLOOR_FRACTION
        self.heartbeat = heartbeat
        self.predictive = predictive
        self.dof = dof
        self._ref = np.zeros(dof)  # what the receiver was last sent (dequantised)
        self._slope = np.zeros(dof)
        self._i = 0  # ticks since the last send: the receiver plays ref + slope * i now
        self._sent_once = False
        self._e_in = 0.0  # sum x.x so far (energy / half dt), this tick included
        self._e_budget = 0.0  # e_in reported with the last payload: the receiver's budget ceiling
        self._e_played = 0.0  # sum of what the receiver plays (its reconstruction, run here)
        self._hist = np.zeros((SLOPE_WINDOW, dof))
        self._w = _slope_weights(SLOPE_WINDOW)
        self._n = 0
        self._gain = 1.0
        self._undo: tuple[Array, Array, int, bool, float, float] | None = None
        self.sends = {"band": 0, "heartbeat": 0, "budget": 0, "energy": 0}
        self.limited = 0  # sends whose value the budget cut down

    def _prediction(self) -> Array:
        return self._ref + self._slope * self._i if self.predictive else self._ref

    def _outside_band(self, x: Array, pred: Array) -> bool:
        """Weber's test on the vector, against the reference before any reserve shrink."""
        # pred / 1.0 is pred bit for bit: the division is skipped at full gain (most ticks).
        d = x - (pred if self._gain == 1.0 else pred / self._gain)
        return _norm(d) > self.k * max(_norm(pred), self.floor)

    def _slope_now(self) -> Array:
        if self._n < 2:
            return np.zeros(self.dof)
        if self._n < SLOPE_WINDOW:  # not enough history yet: fit what there is
            h = self._hist[SLOPE_WINDOW - self._n :]
            return _slope_weights(self._n) @ h
        return self._w @ self._hist

    def encode(self, x: Array) -> bytes | None:
        self._e_in += float(x.dot(x))  # x.dot(x): np.dot(x, x) (same call, same bits), cheaper per tick
        if self.predictive:
            self._hist[:-1] = self._hist[1:]
            self._hist[-1] = x
            self._n += 1
        pred = self._prediction()
        e_pred = float(pred.dot(pred))
        reason = send_reason(
            not self._sent_once or self._outside_band(x, pred),
            self._i >= self.heartbeat,
            self.power,
            self.urgent,
            self._e_played + e_pred > self._e_budget,
        )
        if not reason:
            self._e_played += e_pred
            self._i += 1
            return None
        self._undo = (self._ref, self._slope, self._i, self._sent_once, self._e_budget, self._e_played)
        self.sends[reason] += 1
        budget = max(self._e_in - self._e_played, 0.0)
        p = x
        self._gain = 1.0
        target = RESERVE_TICKS * float(x.dot(x))
        if self.power:  # rules 2 and 3 are wave energy; on a power variable TDPA guards the channel
            budget = target = float("inf")
        if budget < target:
            shrink = min(self.k * RESERVE_FRACTION, RESERVE_MAX_SHRINK)
            self._gain = 1.0 - shrink * (1.0 - budget / target)
            p = x * self._gain
        if float(x.dot(x)) > budget:
            self.limited += 1
            p = x * np.sqrt(budget / float(x.dot(x)))
        ref = self.raw.dequantize(q := self.raw.quantize(p))
        parts = [q]
        slope = np.zeros(self.dof)
        if self.predictive:
            qs = self.slope_raw.quantize(self._slope_now())
            slope = self.slope_raw.dequantize(qs)
            parts.append(qs)
        self._ref, self._slope, self._i, self._sent_once = ref, slope, 1, True
        self._e_budget = self._e_in
        self._e_played += float(ref.dot(ref))
        return pack(np.concatenate(parts), 16)

    def cancel(self) -> None:
        """The last payload was not sent (rate cap): the receiver goes on with the previous one."""
        if self._undo is None:
            return
        ref, slope, i, once, budget, played = self._undo
        pred = ref + slope * i if self.predictive else ref
        self._ref, self._slope, self._i, self._sent_once, self._e_budget = ref, slope, i + 1, once, budget
        self._e_played = played + (float(pred.dot(pred)) if once else 0.0)
        self._undo = None


class DeadbandDecoder(PlayoutDecoder):
    """Receiver side: holds (``pd``) or extrapolates (``pdp``) the newest payload until the next.

    It never runs dry once a payload has arrived: the energy guard in front of it, not the decoder,
    decides how much of the held signal may be played.
    """

    def __init__(self, raw: RawFormat, dof: int, predictive: bool, max_queue: int, on_loss: str) -> None:
        super().__init__(dof, max_queue, on_loss)
        self.raw = raw
        self.slope_raw = RawFormat(raw.full_scale * SLOPE_SCALE)
        self.predictive = predictive
        self._seg: tuple[Array, Array] | None = None
        self._i = 0

    def parse(self, payload: bytes) -> tuple[Array, int]:  # pragma: no cover - push is overridden
        raise CodecError("deadband payloads are pushed whole")

    def _segment(self, payload: bytes) -> tuple[Array, Array]:
        if self.predictive:
            q = unpack16(payload, 2 * self.dof)
            return self.raw.dequantize(q[: self.dof]), self.slope_raw.dequantize(q[self.dof :])
        return self.raw.dequantize(unpack16(payload, self.dof)), np.zeros(self.dof)

    def push(self, payload: bytes) -> None:
        """The newest payload replaces whatever was being held; malformed raises, changes nothing."""
        seg = self._segment(payload)
        if self._seg is not None and self._i == 0:
            self.dropped_samples += 1  # the previous one was never played (two in one tick)
        self._seg, self._i = seg, 0

    def clear(self) -> None:
        self._seg = None
        self._i = 0
        self._last = self._zero

    @property
    def queued(self) -> int:
        return 0 if self._seg is None else 1

    def next(self) -> Array:
        if self._seg is None:
            self.underruns += 1
            return self._zero
        ref, slope = self._seg
        x = ref + slope * self._i if self.predictive else ref
        self._i += 1
        self._last = x
        return x
