"""Reflection-aware predictive deadband ``pdr:PCT[:MAXMS[:BPCT[:FR:BR]]]`` on wave variables (direct LDR,
on events).

*Why.*  In wave variables each side's outgoing wave contains the reflection of the one it receives:
by eq. (3), at the operator ``g_l = h_l + sqrt(2/b) F_hsi`` and at the teleoperator
``h_r = g_r - sqrt(2/b) F_to``.  In free space ``F_to = 0``, so the returning wave *is* the sent one,
and ``pdp``'s two linear predictors chase each other's reconstructions: every send in one direction
puts a kink into the other direction's signal, which its predictor then misses.  ``pdr`` predicts
the backward wave as the teleoperator's reflection ``rho g_r`` of the forward wave it played, plus a
linear prediction of the rest (the force term of eq. 3, zero in free space, smooth against the
foam).  Both ends know ``g_r``: the teleoperator played it, and the operator's forward sender
modelled it.  The forward wave is no reflection (the hand's grip matches ``b`` and absorbs what comes
back, so ``g_l`` does not follow ``h_l``); it is predicted as by ``pdp``, with the slope a chord
(``ReflectiveEncoder._slope_now``).

*Receiver* (:class:`ReflectiveDecoder`), backward: it plays ``value + slope * i + rho m - r0``, ``i``
counting from 0 on the first tick it plays a payload, ``m`` what its own side's forward encoder
modelled, on the previous tick, that the teleoperator plays, ``rho`` the fitted reflection
coefficient (:class:`Reflection`) and ``r0`` the ``rho m`` of the payload's first tick: the value is
absolute, as ``pdp``'s, and the reflection only carries what the forward wave did since.  So a
payload resynchronises both ends, and a reference that is off (a loss, or a round trip longer than
``teleop sim``'s one tick, which the reference assumes) costs transparency only until the next one,
never passivity.  The two ends of a node are paired (``pair``, called by ``teleop.session.node``);
unpaired (on power variables under TDPA) ``pdr`` is ``pdp`` with its own slope and reserve schedule.

*Passivity* (eqs. 5, 10, 11): as for ``pdp`` (``teleop.control.codecs.deadband``).  The receiver's energy
guard plays only within the energy reported in-band, whatever the payload says; the sender runs the
receiver's reconstruction and its budget exactly and sends before a hold would exceed it; the value
it sends is rounded toward zero (eq. 11) and scaled to the reserve like eDS (eq. 10) when that is
short.

*Reserve schedule.*  A hold of ``N`` ticks plays about ``N |x|^2`` the receiver has no report of yet,
so it needs that much *reserve* (energy sent and never played), and in free space every joule of
reserve is work the operator does against a drag the teleoperator does not feel: with ``F = a v``,
eq. (7) grows by ``W^2 / int v^2`` at least (Cauchy-Schwarz).  Building reserve is cheapest early
and slowly, so the sender shrinks each new value by ``RESERVE_SCALE * RANGE / sqrt(E_in) + RESERVE_FLOOR``
(``E_in`` its cumulative ``sum |x|^2``), at most ``RESERVE_MAX_SHRINK``, while the
reserve is below ``RESERVE_TICKS`` ticks of the current power: the reserve then grows like
``sqrt(E_in)`` (``R ~ 4 scale sqrt(E_in)``), the profile that keeps ``W^2 / int v^2`` smallest for a
given hold length over the whole run.  Measured on the protocol scenario: see the codec guide.

*Per direction* (optional ``BPCT``, ``FR``, ``BR``): the backward band in percent (default ``PCT``)
and each direction's reserve scale in percent of ``RESERVE_SCALE`` (default 100 each).  Nearly all
of ``pdr``'s cost in eq. (7) is its reserve (without the shrink, ``pdr:0.8`` gives I = 3.29e-4, the
uncoded 3.25e-4, at 596 packets/s), and the forward direction sends more; so moving reserve from
the backward to the forward direction, and widening the backward band (whose errors the reflection
model keeps small), trades the two directions' packets at about the same I.  Each encoder learns
its direction in ``pair``; unpaired it keeps the forward settings.

*Two-port accounting* (optional ``cKAPPA`` after ``BR``; PROTOCOL.md 3.6).  Eq. (5) per direction is
sufficient, not necessary: passivity is eq. (1) with (4), the two-port's energy.  ``cKAPPA`` credits a
side's guard with energy it sent and has not reported, withheld from its reports (``_self_credit``):
in free space each side then plays the returning wave on what it sends, and the budget sends nearly
vanish (the codec guide).
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from teleop.control.codecs.base import (
    BACKWARD,
    Array,
    CodecError,
    Encoder,
    PlayoutDecoder,
    RawFormat,
    pack,
    unpack,
)
from teleop.control.codecs.deadband import (
    FLOOR_FRACTION,
    SLOPE_SCALE,
    SLOPE_WINDOW,
    _norm,
    _slope_weights,
    send_reason,
)
from teleop.control.passivity import EnergyGuard

#: The reserve shrink ``RESERVE_SCALE * RANGE / sqrt(E_in) + RESERVE_FLOOR`` (module docstring), tuned
#: on the protocol scenario: more reserve in one direction moves budget sends into the other.
RESERVE_SCALE = 0.01
RESERVE_FLOOR = 0.003
RESERVE_MAX_SHRINK = 0.5
RESERVE_TICKS = 100  # reserve wanted: this many ticks of the current power
#: cKAPPA: the longest round trip (ticks) over which a sender pairs its model of the peer's credit.
CREDIT_HISTORY = 4096
CREDIT_LAGS = 16  # payloads over which the spread of the lags is taken
CREDIT_SPREAD = 256  # ticks: the widest window of models searched
#: Round trips (ticks) beyond which nobody credits: a sender does not know the peer's credits in
#: flight, so its budget sends grow with the round trip, which behind a rate limit lengthens the
#: queue and the round trip again (measured: netem rate 300kbit, 208 / 290 packets/s, I = 182).
CREDIT_MAX_RTT = 50
REFLECTION_FORGET = 1.0 - 1.0 / 125.0  # per tick: the fit of rho looks back about 125 ticks
REFLECTION_MIN_POWER = 1e-6  # sum g^2 below which rho keeps its last value (a still wave)
#: The forward slope: the chord of a parabola fitted over CHORD_WINDOW ticks, to a horizon of
#: CHORD_FRACTION of the ticks a tangent would stay in the band (``2 sqrt(band / curvature)``), at most
#: CHORD_MAX ticks (see ``_slope_now``).
CHORD_WINDOW = 16
CHORD_FRACTION = 0.15
CHORD_MAX = 50.0
#: Least-squares rows giving (value, slope, curvature) at the newest of CHORD_WINDOW ticks.
_CHORD_FIT = np.linalg.pinv(np.vander(np.arange(1 - CHORD_WINDOW, 1, dtype=np.float64), 3, increasing=True))


class Reflection:
    """The teleoperator's reflection coefficient per DoF, ``h ~ rho g``, fitted by exponentially
    weighted least squares over pairs of the forward wave it played and the backward wave the
    operator played for it.  Both ends hold both waves exactly (one played, the other modelled),
    so both compute the same ``rho`` from the same numbers in the same order: +1 in free space,
    ``(b - Z) / (b + Z)`` against an impedance ``Z`` (-1/3 in the protocol's foam, about -1 at the
    wall)."""

    def __init__(self, dof: int) -> None:
        self._gh = np.zeros(dof)
        self._gg = np.zeros(dof)
        self.rho = np.ones(dof)

    def add(self, g: Array, h: Array) -> None:
        self._gh = REFLECTION_FORGET * self._gh + g * h
        self._gg = REFLECTION_FORGET * self._gg + g * g
        ok = self._gg > REFLECTION_MIN_POWER
        self.rho = np.where(ok, np.clip(self._gh / np.where(ok, self._gg, 1.0), -1.0, 1.0), self.rho)


class ReflectiveEncoder(Encoder):
    """Sender side of ``pdr``; see the module docstring."""

    def __init__(
        self,
        raw: RawFormat,
        dof: int,
        k_pct: float,
        heartbeat: int,
        back_pct: float | None = None,
        reserve_pct: tuple[float, float] = (100.0, 100.0),
        credit: float | None = None,
    ) -> None:
        self.raw = raw
        self.slope_raw = RawFormat(raw.full_scale * SLOPE_SCALE)
        self.full_scale = raw.full_scale
        self.k = k_pct / 100.0
        self._back_k = (k_pct if back_pct is None else back_pct) / 100.0
        self._reserve_pct = reserve_pct
        # RESERVE_SCALE * 1.0 is RESERVE_SCALE bit for bit: the default schedule is unchanged.
        self.reserve_scale = RESERVE_SCALE * (reserve_pct[0] / 100.0)
        self.floor = raw.full_scale * FLOOR_FRACTION
        self.heartbeat = heartbeat
        self.dof = dof
        self._dec: ReflectiveDecoder | None = None
        self._refl = Reflection(dof)
        zero = np.zeros(dof)
        self._r0 = zero  # rho d on the last send tick: the reflection its value contains
        self._val = zero
        self._slope = zero
        self._off = zero  # x - played on the last send: the band is tested without the shrink
        self._i = 0
        self._sent_once = False
        self._e_in = 0.0  # sum x.x so far (energy / half dt), this tick included
        self._e_budget = 0.0  # e_in reported with the last payload: the receiver's budget ceiling
        self._e_played = 0.0  # what the receiver plays, as modelled here
        self._hist = np.zeros((SLOPE_WINDOW, dof))
        self._w = _slope_weights(SLOPE_WINDOW)
        self._chord = np.zeros((CHORD_WINDOW, dof))
        self._n = 0
        #: What the receiver plays for this tick's sample (its decoder's ``d`` one tick later).
        self.model = zero
        self._undo: tuple[Array, Array, Array, int, bool, float, float, Array] | None = None
        self.sends = {"band": 0, "heartbeat": 0, "budget": 0, "energy": 0}
        self.limited = 0
        #: This side's guard and decoder, armed by ``pair`` for self-credit.
        self._guard: EnergyGuard | None = None
        self._rx: ReflectiveDecoder | None = None
        #: Self-credit (``cKAPPA``; the module docstring): kappa, armed by ``pair``.
        self.credit = credit
        self._kk = (1.0 - credit) ** 2 if credit is not None else 0.0  # (1 - kappa)^2, used every tick
        self._c_own = 0.0  # e units this side credited its own guard: withheld from its reports
        self._c_peer = 0.0  # the peer's self-credit, as modelled here (e units)
        self._c_rep = (0.0, 0.0)  # (e_in, c_own) when the last report left: the invariant's origin
        self._c_undo = (0.0, 0.0)
        #: Ticks from the peer's send to the play here of its newest payload (the node sets it), and
        #: the peer's own, from its payloads: their sum is the round trip that pairs the peer's credit
        #: on its tick with this side's model it was playing then (1 tick at 0 ms in teleop.offline.sim).
        self.rx_lag: int | None = None
        self._m_hist = np.zeros(CREDIT_HISTORY)  # |model|^2 of this side's last ticks, a ring
        self._lags: deque[int] = deque(maxlen=CREDIT_LAGS)  # rx_lag of the last payloads
        self._credit_on = False  # this side credits (as its last payload announced)
        self._on_next = False  # what its next payload will announce
        self._on_undo = False
        if credit is not None:
            self.sends["credit"] = 0
            self.rx_lag = -1  # none measured yet: the payloads say so, and nothing is credited

    def pair(self, decoder: PlayoutDecoder, direction: int, guard: EnergyGuard | None = None) -> None:
        """Join this side's decoder (``teleop.session.node`` calls it; ``direction`` is the one this encoder
        sends, ``teleop.session.wire``).  Only the backward wave is predicted as a reflection: the
        teleoperator reflects what it receives (``h_r = g_r`` in free space), while the operator's
        hand, whose grip matches ``b``, absorbs it (``g_l`` does not follow ``h_l``).  Not on power
        variables, where the waves of eq. 3 do not exist.  It also sets the direction's band and
        reserve scale (``BPCT``, ``FR``, ``BR``; the module docstring)."""
        if direction == BACKWARD:
            self.k = self._back_k
            self.reserve_scale = RESERVE_SCALE * (self._reserve_pct[1] / 100.0)
        if isinstance(decoder, ReflectiveDecoder) and not self.power:
            if self.credit is not None and guard is not None:
                self._guard, self._rx = guard, decoder
            if direction == BACKWARD:
                self._dec = decoder  # the teleoperator: its wave refers to the g_r it played
            else:
                decoder.paired = self  # the operator: its decoder refers to what g_r was modelled

    def _outside_band(self, x: Array, pred: Array) -> bool:
        """Weber's test on the vector, against the prediction with its reserve offset."""
        full = pred + self._off
        return _norm(x - full) > self.k * max(_norm(full), self.floor)

    def _slope_now(self) -> Array:
        """The slope to send.  Backward: ``pdp``'s least-squares slope of the innovation.  Forward
        (and unpaired): the hand's wave curves (the arm's mode near 3 Hz in contact), and a tangent
        overshoots a concave wave, which spends the reserve on energy the wave never carried; the
        chord of the fitted parabola to a short horizon stays under it.  Measured on the protocol
        scenario (pdr:0.7, 15 s): forward 57.1 -> 49.9 packets/s, I 1.055e-3 -> 1.086e-3."""
        if self._dec is None and self._n >= CHORD_WINDOW:
            _, slope, curv = _CHORD_FIT @ self._chord
            band = self.k * max(_norm(self._chord[-1]), self.floor)
            c = _norm(curv)
            horizon = min(CHORD_FRACTION * 2.0 * math.sqrt(band / c), CHORD_MAX) if c > 0 else CHORD_MAX
            return np.asarray(slope + curv * horizon)
        n = min(self._n, SLOPE_WINDOW)
        if n < 2:
            return np.zeros(self.dof)
        if n < SLOPE_WINDOW:
            return _slope_weights(n) @ self._hist[SLOPE_WINDOW - n :]
        return self._w @ self._hist

    def encode(self, x: Array) -> bytes | None:
        d = self._dec.played if self._dec is not None else None
        # The reflection of the forward wave now, less the one in the last send's value (eq. 3).
        refl = self._refl.rho * d - self._r0 if d is not None else np.zeros(self.dof)
        xx = float(x.dot(x))
        self._e_in += xx
        self._hist[:-1] = self._hist[1:]
        self._hist[-1] = x - (self._refl.rho * d if d is not None else 0.0)
        self._chord[:-1] = self._chord[1:]
        self._chord[-1] = self._hist[-1]
        self._n += 1
        pred = self._val + self._slope * self._i + refl
        e_pred = float(pred.dot(pred))
        guard = self._guard
        ceiling = self._e_budget
        c_hold = 0.0
        if self.credit is not None and guard is not None and self._rx is not None:
            # The peer's self-credit on its last tick (what it played of this wave, as modelled
            # here, matched against what it sent as played here; none on its send ticks).
            rx = self._rx
            if rx.fresh and self.rx_lag is not None and self.rx_lag >= 0:
                self._lags.append(self.rx_lag)
            # The round trip, over the spread of the lags seen lately each way: where it varies
            # (jitter, a rate limit's queue) the smallest of the models it may pair with.
            lo = min(self._lags, default=0) + min(rx.peer_lags, default=0)
            hi = min(max(self._lags, default=0) + max(rx.peer_lags, default=0), lo + CREDIT_SPREAD)
            # Whether to credit is decided on send ticks only and announced in the payload, so the
            # peer knows from which tick on (``_credit_on``); it models this side's credits likewise.
            self._on_next = bool(self._lags) and bool(rx.peer_lags) and hi <= CREDIT_MAX_RTT
            pairing = not rx.fresh and rx.peer_on and lo >= 1 and hi <= self._n - 1
            if pairing or self._credit_on:  # both use what this side played, once a tick
                d_rx = rx.played
                p_rx = float(d_rx.dot(d_rx))
            if pairing:
                if lo == hi:
                    mm = float(self._m_hist[(self._n - 1 - lo) % CREDIT_HISTORY])
                else:
                    idx = np.arange(self._n - 1 - hi, self._n - lo) % CREDIT_HISTORY
                    mm = float(self._m_hist[idx].min())
                self._c_peer += min(self._kk * p_rx, mm)
            ceiling = self._e_budget + self._c_peer
            if self._credit_on:  # beyond CREDIT_MAX_RTT: per-direction accounting (eq. 5)
                c_hold = min(self._kk * e_pred, p_rx)
        reason = send_reason(
            not self._sent_once or self._outside_band(x, pred),
            self._i >= self.heartbeat,
            self.power,
            self.urgent,
            self._e_played + e_pred > ceiling,
        )
        if not reason and xx < c_hold:
            reason = "credit"  # the promise |x|^2 >= the credit is broken: send (no credit this tick)
        if not reason:
            self._e_played += e_pred
            self._i += 1
            self.model = pred
            if d is not None:
                self._refl.add(d, pred)
            if c_hold > 0.0 and guard is not None:
                self._self_credit(guard, c_hold)
            if self.credit is not None:
                self._m_hist[(self._n - 1) % CREDIT_HISTORY] = e_pred
            return None
        self._c_undo = self._c_rep
        self._undo = (
            self._val, self._slope, self._off, self._i, self._sent_once, self._e_budget, self._e_played, pred
        )  # fmt: skip
        self.sends[reason] += 1
        p = x
        if not self.power:
            reserve = max(self._e_in - self._e_played, 0.0)
            if guard is not None and self.credit is not None:  # the receiver's budget, self-credit in
                reserve = max(self._e_in - self._c_own + self._c_peer - self._e_played, 0.0)
            target = RESERVE_TICKS * xx
            if reserve < target:
                early = self.reserve_scale * self.full_scale / math.sqrt(self._e_in)
                shrink = min(RESERVE_MAX_SHRINK, early + RESERVE_FLOOR)
                p = x * (1.0 - shrink * (1.0 - reserve / target))
            if float(p.dot(p)) > reserve:  # eq. (10): the send tick plays at most the reserve
                self.limited += 1
                p = x * math.sqrt(reserve / xx)
        q = self.raw.quantize(p)  # toward zero: the send tick plays at most |p| per DoF (eq. 11)
        val = self.raw.dequantize(q)
        qs = self.slope_raw.quantize(self._slope_now())
        played = val
        if d is not None:
            self._r0 = self._refl.rho * d
        self._val, self._slope, self._i, self._sent_once = val, self.slope_raw.dequantize(qs), 1, True
        self._off = x - played
        self._e_budget = self._e_in - self._c_own  # what the node reports: sent less self-credit
        self._c_rep = (self._e_in, self._c_own)
        self._e_played += float(played.dot(played))
        self.model = played
        if d is not None:
            self._refl.add(d, played)
        if self.credit is not None:
            self._m_hist[(self._n - 1) % CREDIT_HISTORY] = float(played.dot(played))
            self._on_undo, self._credit_on = self._credit_on, self._on_next
            lag = (
                -1
                if self.rx_lag is None or self.rx_lag < 0
                else 2 * min(self.rx_lag, 16383) + self._credit_on
            )
            qs = np.concatenate([qs, [lag]])  # the lag seen here (echoed: the round trip) and the state
        return pack(np.concatenate([q, qs]), 16)

    def _self_credit(self, guard: EnergyGuard, c: float) -> None:
        """Credit this side's guard ``c`` (e units) of the energy it sent this tick and has not
        reported, and withhold it from its reports (``withheld`` grows by it, J).

        Why it is passive (eqs. 1, 4): with ``C`` a side's credits, its reports are ``S - C`` and its
        guard plays at most ``A_peer + C``; credits since its last report never exceed the energy it
        sent since (checked here), so ``S - A_last >= C - C_last`` and the two guards' bounds sum to
        ``E_g_out + E_h_out <= E_g_in + E_h_in`` at every tick, under any delay or loss.  Eq. (5) per
        direction need not hold."""
        e_rep, c_rep = self._c_rep
        c = min(c, (self._e_in - e_rep) - (self._c_own - c_rep))  # the invariant, whatever rounding did
        if not c > 0.0:
            return
        self._c_own += c
        withheld = self._c_own * guard.half_dt
        guard.credit(withheld - self.withheld)
        self.withheld = withheld

    def cancel(self) -> None:
        """The last payload was not sent (rate cap): the receiver goes on with the previous one."""
        if self._undo is None:
            return
        val, slope, off, i, once, budget, played, pred = self._undo
        self._val, self._slope, self._off, self._i, self._sent_once = val, slope, off, i + 1, once
        self._e_budget = budget
        self._c_rep = self._c_undo  # the report never left: the invariant keeps the older origin
        self._credit_on = self._on_undo  # nor did the state it announced
        # Without a payload so far the receiver plays zero; else the prediction it had.
        self.model = pred if once else np.zeros(self.dof)
        self._e_played = played + float(self.model.dot(self.model))
        self._undo = None


class ReflectiveDecoder(PlayoutDecoder):
    """Receiver side of ``pdr``: extrapolates the newest payload as ``pdp``'s and, paired (the
    operator's), adds the reflection of what its side's forward model did since the payload
    began; never runs dry once a payload has arrived."""

    def __init__(self, raw: RawFormat, dof: int, max_queue: int, on_loss: str, lag: bool = False) -> None:
        super().__init__(dof, max_queue, on_loss)
        self.lag = lag  # cKAPPA: the payload ends with the peer's rx_lag (16 bits)
        self.peer_lag = 0
        self.peer_lags: deque[int] = deque(maxlen=CREDIT_LAGS)
        self.peer_on = False  # the peer credits, as its newest payload says
        self.raw = raw
        self.slope_raw = RawFormat(raw.full_scale * SLOPE_SCALE)
        self._seg: tuple[Array, Array] | None = None
        self._i = 0
        self.paired: ReflectiveEncoder | None = None
        self._refl = Reflection(dof)
        self.played = self._zero  # d: what this side played this tick (before the energy guard)
        self._r0 = self._zero  # rho m when the playing payload started: the reflection in its value

    def parse(self, payload: bytes) -> tuple[Array, int]:  # pragma: no cover - push is overridden
        raise CodecError("pdr payloads are pushed whole")

    def push(self, payload: bytes) -> None:
        """The newest payload replaces whatever was playing; malformed raises, changes nothing."""
        q = unpack(payload, 16, 2 * self.dof + (1 if self.lag else 0))
        if self.lag:
            if q[-1] < -1:
                raise CodecError(f"pdr payload has a lag {int(q[-1])} (-1: none measured yet)")
            v = int(q[-1])
            self.peer_lag, self.peer_on = (v >> 1, bool(v & 1)) if v >= 0 else (-1, False)
            if v >= 0:
                self.peer_lags.append(self.peer_lag)
            q = q[:-1]
        seg = self.raw.dequantize(q[: self.dof]), self.slope_raw.dequantize(q[self.dof :])
        if self._seg is not None and self._i == 0:
            self.dropped_samples += 1
        self._seg, self._i = seg, 0

    def clear(self) -> None:
        self._seg = None
        self._i = 0
        self._last = self.played = self._zero

    @property
    def queued(self) -> int:
        return 0 if self._seg is None else 1

    @property
    def fresh(self) -> bool:
        """Whether the last ``next`` played the first tick of a payload (its sender's send tick)."""
        return self._seg is not None and self._i == 1

    def next(self) -> Array:
        if self._seg is None:
            self.underruns += 1
            self.played = self._zero
            return self._zero
        val, slope = self._seg
        g = self.paired.model if self.paired is not None else None
        x = val + slope * self._i
        if g is not None:
            r = self._refl.rho * g
            if self._i == 0:
                self._r0 = r
            x = x + (r - self._r0)
            self._refl.add(g, x)
        self._i += 1
        self._last = self.played = x
        return x
