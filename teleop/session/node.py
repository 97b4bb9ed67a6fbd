"""Operator (HSI) and teleoperator (TO) nodes: ``receive(bytes)`` and ``tick(now) -> Packet | None``.

Sans-I/O: a node never reads a clock, opens a socket or sleeps.  The same objects run in
``teleop sim`` (virtual time) and in the two real processes.

Each tick, each port solves its algebraic loop in closed form (see ``teleop.devices.models``):

* HSI: the human gives ``v = v0 - Y F``; the port renders ``F = b v - sqrt(2b) h_l`` (eq. 3)::

      v_hsi = (v0 + Y sqrt(2b) h_l) / (1 + Y b),   g_l = sqrt(2b) v_hsi - h_l

* TO: the environment gives ``F = f0 + Z v``; the port commands ``v = (sqrt(2b) g_r - F) / b``::

      v_to = (sqrt(2b) g_r - f0) / (b + Z),        h_r = g_r - sqrt(2/b) F_to

The received wave (``h_l`` or ``g_r``) is what the decoder plays this tick, after the energy guard
(``teleop.control.passivity``) has admitted it; the transmitted wave goes through the encoder.  Energies
are counted in scattering variables per direction (eq. 4-5): ``E = 1/2 sum(wave**2) dt``.

**TDPA** (``--passivity tdpa``, :class:`TdpaOperatorNode`, :class:`TdpaTeleoperatorNode`): power
variables instead of waves, velocity forward and force back, each packet carrying the sender's
input energy; the receiving side's adaptive damper keeps ``E_out <= E_in reported`` per direction
(``teleop.control.passivity``).  The HSI renders a little damping of its own and the robot follows the
commanded velocity through a PD position controller (``B = b``, ``K = 5 b``): without them no
energy enters before contact and no force ever comes back (see :data:`TDPA_HSI_DAMPING`).  The
controller's stiffness trades wall stiffness against delay: ``teleop sim --scenario protocol``
with ``none`` measured I_dc 0.083 / 0.32 / 0.59 at 0 / 50 / 200 ms and a 1.7 N wall for K = 5 b,
against 0.078 / 3.8 / 1.4 and a 4.2 N wall for K = 20 b (wave variables: 7.0 N at 0 ms), both
before the drift compensator (:data:`TDPA_DRIFT_GAIN`) existed.

**Safe state.** When nothing has been accepted for the link timeout (plus one payload interval of
the peer's codec, so a sparse codec is not mistaken for a dead link), the node fades its
coupling out over ``fade_time``: the HSI stops rendering force and the TO stops commanding
motion, and both transmit a zero wave.  When packets return it fades back in.  Fading scales the
port's coupling ``c`` in ``[0, 1]``: the HSI renders ``c F``, the TO commands ``c v``, and the
transmitted wave is scaled by ``c``, so the safe state only removes energy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from teleop.control.codecs import Array, Codec, CodecError
from teleop.control.confine import Confinement, confined
from teleop.control.passivity import (
    EnergyGuard,
    PassivityReport,
    TdpaGuard,
    parallel_damper,
    series_damper,
)
from teleop.control.ratecap import RateCap
from teleop.control.wave import WaveImpedance
from teleop.devices.models import Environment, Human
from teleop.session import auth, wire
from teleop.session.settings import DEFAULTS, Channel, Envelope, Passivity

SPARSE_MARGIN_S = 0.010  # s: how late the payload after a lost one may be before the link is lost
#: J of input energy a TDPA port may leave unreported before an event-based (deadband) encoder must
#: send: the receiver's budget lags the truth by at most this between sparse updates
#: (teleop.control.passivity).
TDPA_REPORT_QUANTUM_J = 2e-3
#: The TDPA operator's rendered damping, as a fraction of the session's impedance ``b``.  Why: with
#: the environment's direct feedthrough (Tustin's D, ``teleop.devices.models``) the robot cannot move into
#: contact without energy, and no force comes back to make the human put any in: E_in = E_out = 0
#: for ever (measured: no force at all in the protocol's foam and walls).  The work the human does
#: against this damper is real input energy, counted in E_in, so the budget starts from it and the
#: strict bound E_out <= E_in holds unchanged.  Wave variables render ``b v`` in full (eq. 3).
TDPA_HSI_DAMPING = 0.05
#: The TDPA robot's position controller: damping and stiffness per unit of ``b`` (N s/m, N/m per
#: N s/m).  The spring stores what the robot needs to push before the operator has paid for it, and
#: pulls the robot back to the commanded position (the drift the PC leaves is the command's).
TDPA_TO_DAMPING = 1.0
TDPA_TO_BANDWIDTH = 5.0
#: Drift compensation at the TO: 1/s of the lost commanded position asked back per second, and the
#: fastest it may be asked back (m/s); both inside the PC's budget (Artigas et al.'s passive drift
#: compensator in spirit: only surplus energy moves the robot back to where the operator is).
TDPA_DRIFT_GAIN = 2.0
TDPA_DRIFT_MAX_V = 0.05
#: A device's output beyond these is implausible, a fault like a non-finite value: the node holds
#: the last good output for that tick (``device_stale``).  Summed over the DoF: N, m/s; a gain (the
#: HSI's admittance ``Y``, the robot's impedance ``Z``) must be finite, >= 0 and below ``_GAIN``.
PLAUSIBLE_FORCE_N = 1e5
PLAUSIBLE_VELOCITY = 1e3
_PLAUSIBLE_GAIN = 1e12


@dataclass
class PortCounters:
    """What a node did with what it received; nothing is dropped without being counted."""

    received: int = 0
    accepted: int = 0
    malformed: int = 0
    wrong_session: int = 0
    wrong_direction: int = 0
    wrong_codec: int = 0
    stale: int = 0  # duplicate or older than one already accepted
    gaps: int = 0  # sequence numbers never seen (lost, or still in flight)
    device_stale: int = 0  # ticks the device's output was non-finite or implausible: the last good held
    saturated: int = 0  # robot: ticks its command was saturated to its envelope (settings.Envelope)

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


@dataclass(frozen=True)
class PortOptions:
    """How a node reconstructs what it receives and guards the channel's passivity.

    The channel's fields and their defaults are :class:`teleop.session.settings.Channel`'s: :meth:`of` takes
    them from a session's settings (``SessionParams``, ``SimConfig``)."""

    max_queue: int | None = None  # playout queue bound in ticks (default: one payload, newest wins)
    on_loss: str = DEFAULTS.on_loss  # what to play when nothing is queued: "conceal", "hold" or "zero"
    controller: bool = DEFAULTS.controller  # passivity controller on (never play more energy than was sent)
    link_timeout: float = DEFAULTS.link_timeout  # s of silence before the safe state
    fade_time: float = 0.1  # s to fade the coupling out (and back in)
    rate_cap: float = DEFAULTS.rate_cap  # bit/s on the wire in any 100 ms window (control.ratecap); 0: no cap
    playout: str = DEFAULTS.playout  # the receiver's playout buffer: off, auto or extra ms (session.playout)
    passivity: Passivity = DEFAULTS.passivity  # scattering waves (eq. 3-5) or TDPA on power variables

    @classmethod
    def of(cls, settings: Channel) -> PortOptions:
        """The options a session's settings (``SessionParams``, ``SimConfig``) give both ports."""
        return cls(
            on_loss=settings.on_loss,
            controller=settings.controller,
            link_timeout=settings.link_timeout,
            rate_cap=settings.rate_cap,
            playout=settings.playout,
            passivity=settings.passivity,
        )

    def __post_init__(self) -> None:
        if not self.fade_time > 0:
            raise ValueError("fade_time must be > 0 s")
        channel = Channel(
            on_loss=self.on_loss,
            link_timeout=self.link_timeout,
            rate_cap=self.rate_cap,
            playout=self.playout,
            passivity=self.passivity,
        )
        # canonical, or ValueError saying what is allowed (the same checks as every settings type)
        object.__setattr__(self, "playout", channel.check_channel(netem_files=False))
        object.__setattr__(self, "passivity", channel.passivity)


class _Node:
    """What both nodes share: sequence numbers, codec ends, energy guard, inbound checks."""

    tx_direction: int
    device_spec = ""  # the --hsi/--robot spec of this side's device (teleop.devices), for the logs

    def __init__(
        self,
        *,
        wave: WaveImpedance,
        tx: Codec,
        rx: Codec,
        session: int,
        dt: float,
        options: PortOptions | None = None,
    ) -> None:
        if tx.dof != wave.dof or rx.dof != wave.dof:
            raise ValueError(f"codec DoF ({tx.dof}, {rx.dof}) must match wave DoF {wave.dof}")
        opts = options or PortOptions()
        self.options = opts
        self.wave = wave
        self.tx_codec = tx
        self.rx_codec = rx
        self.encoder = tx.encoder()
        self.decoder = rx.decoder(opts.max_queue, opts.on_loss)
        self.rate_cap = RateCap(opts.rate_cap, dt) if opts.rate_cap else None
        # Bytes a datagram carries beyond the packet: the envelope and the transport's header, as
        # the wire counters count them (the port sets it from its transport).
        self.datagram_overhead = auth.OVERHEAD + 28
        self.guard = self._make_guard(dt, opts, wave, tx, rx)
        # A codec whose reconstruction refers to the wave this side receives (pdr, eq. 3's
        # reflection) pairs its two ends here, and a self-crediting one (pdr's cKAPPA) its guard; the others
        # have no ``pair``.
        pair = getattr(self.encoder, "pair", None)
        if pair is not None:
            pair(self.decoder, self.tx_direction, self.guard)
        # A self-crediting pdr (cKAPPA) is told how many ticks after it was sent each payload began
        # to play here: with the peer's, the round trip that pairs its model of the peer's credits.
        self._tell_lag = getattr(self.encoder, "rx_lag", None) is not None
        self._rx_tick = 0
        self._now = 0.0  # the last tick's session time: when a packet arrives, as far as this node knows
        self.session = session
        self.dt = dt
        self.half_dt = 0.5 * dt
        self.rx_direction = 1 - self.tx_direction
        self.seq = 0
        self.last_rx_seq = -1
        self.last_rx_tick = 0  # the send tick of the last payload accepted (its decoder queue's source)
        self.peer_restarts = 0  # energy epochs: the peer process was replaced this many times
        self.counters = PortCounters()
        self.energy_sent = 0.0  # J carried into the channel by the transmitted wave
        # The fraction of it the packets report: 1 in every session; a conformance probe reports less
        # (safe, PROTOCOL.md 3.7 step 7: the receiver's guard only cuts more).
        self.report_scale = 1.0
        self.last_error = ""
        # link supervision
        # The timeout runs from when the next payload was due (one payload interval after the
        # last); a sparse codec's interval may be as long as the timeout itself, so for one the
        # timeout also covers one lost payload: eds:50 with 50 ms goes lost after 110 ms of
        # silence, not 100 (exactly what one lost packet leaves).
        interval = rx.k * dt
        self.link_timeout = interval + (
            max(opts.link_timeout, interval + SPARSE_MARGIN_S) if rx.k > 1 else opts.link_timeout
        )
        self._fade_step = dt / opts.fade_time
        self.coupling = 1.0
        self.link_lost = False
        self._last_rx_at: float | None = None
        self._first_due: float | None = None  # session time by which the peer's first packet is due
        self._accepted_seen = 0
        dof = wave.dof
        self.v = np.zeros(dof)
        self.f = np.zeros(dof)
        self.wave_out = np.zeros(dof)
        self.wave_in = np.zeros(dof)
        # The device's last good output (held while it gives nonsense), and a read-only gain
        # already found sane (a built-in device's constant feedthrough: checked once).
        self._shape, self._dof = (dof,), dof
        self._device_good: tuple[Array, Array] = (np.zeros(dof), np.zeros(dof))
        self._gain_ok: Array | None = None
        # The robot's envelope (:meth:`confine`): none until a robot confines its node.
        self.confined = False
        self.max_velocity = self.max_force = math.inf
        self.confinement: Confinement | None = None  # the final command stage, once confined

    def _make_guard(
        self, dt: float, opts: PortOptions, wave: WaveImpedance, tx: Codec, rx: Codec
    ) -> EnergyGuard:
        # Saturated waves carry at most 1/2 dof RANGE^2 W: the most any genuine report can grow by.
        max_power = 0.5 * wave.dof * rx.raw.full_scale**2
        return EnergyGuard(dt, controller=opts.controller, max_power=max_power)

    def _envelope_power(self, env: Envelope) -> float:
        """W the robot's own limits let a genuine report grow by: waves at its range (eq. 5)."""
        return 0.5 * self.wave.dof * env.max_range**2

    def confine(self, env: Envelope) -> None:
        """Run this (robot's) node inside ``env``: its command saturated to ``max_velocity`` and
        ``max_force`` per DoF, and its energy guard bounded by the envelope, never by the numbers
        the operator proposed (the robot is sovereign).  Called as the session starts."""
        self.confined = True
        self.max_velocity, self.max_force = env.max_velocity, env.max_force
        self.confinement = Confinement(self._dof, self.dt, env.max_velocity, env.max_force)
        self.guard.bound(self._envelope_power(env))

    def _device(self, out: tuple[Array, Array], limit: float) -> tuple[Array, Array]:
        """The device's ``affine`` output if it is sane, else the last sane one (counted): a
        non-finite or implausible value never reaches the port's solve nor the energy books.

        On plain floats, not numpy: this runs twice a tick and a ufunc call costs more than the
        whole check (the sum of magnitudes is NaN for a NaN, inf for an inf, and beyond ``limit``
        for an absurd value: one comparison fails for all three)."""
        a, g = out
        vals = a.tolist() if type(a) is np.ndarray else None
        if (
            vals is not None
            and len(vals) == self._dof
            and sum(map(abs, vals)) <= limit
            and (g is self._gain_ok or self._gain_sane(g))
        ):
            self._device_good = out
            return out
        self.counters.device_stale += 1
        return self._device_good

    def _gain_sane(self, g: Array) -> bool:
        if type(g) is not np.ndarray or g.shape != self._shape:
            return False
        vals = g.tolist()
        ok = sum(vals) < _PLAUSIBLE_GAIN and min(vals) >= 0.0  # a NaN makes the sum NaN: refused
        if ok and not g.flags.writeable:
            self._gain_ok = g
        return bool(ok)

    @property
    def energy_played(self) -> float:
        """J played out of the channel by the received wave (after the controller)."""
        return self.guard.played

    @property
    def peer_energy_sent(self) -> float:
        """The newest cumulative energy the peer reported in-band."""
        return self.guard.reported_in

    @property
    def passivity(self) -> PassivityReport:
        return self.guard.report

    # --- inbound -------------------------------------------------------------------------
    def receive(self, data: bytes) -> bool:
        """Take one datagram.  Returns whether it was accepted; anything else is counted."""
        try:
            pkt = wire.decode(data)
        except wire.WireError as e:
            self.malformed(str(e))
            return False
        return self.receive_packet(pkt)

    def malformed(self, error: str) -> None:
        """Count a datagram that did not parse (a transport that parsed it already calls this)."""
        self.counters.received += 1
        self.counters.malformed += 1
        self.last_error = error

    def takes(self, pkt: wire.Packet) -> bool:
        """Whether ``pkt`` is this session's, from the peer, in its codec (what a playout buffer
        may hold; anything else goes to :meth:`receive_packet` at once, to be counted)."""
        return (
            pkt.session == self.session
            and pkt.direction == self.rx_direction
            and pkt.codec_id == self.rx_codec.codec_id
        )

    def receive_packet(self, pkt: wire.Packet) -> bool:
        """Take one parsed packet.  Returns whether it was accepted; anything else is counted."""
        c = self.counters
        c.received += 1
        if pkt.session != self.session:
            c.wrong_session += 1
            return False
        if pkt.direction != self.rx_direction:
            c.wrong_direction += 1
            return False
        if pkt.codec_id != self.rx_codec.codec_id:
            c.wrong_codec += 1
            return False
        if pkt.seq <= self.last_rx_seq:
            c.stale += 1  # never replay a duplicate or an overtaken packet
            return False
        try:
            self.decoder.push(pkt.payload)
        except CodecError as e:
            c.malformed += 1
            self.last_error = str(e)
            return False
        if self.last_rx_seq >= 0:  # a late joiner's first packet leaves no gap behind it
            c.gaps += pkt.seq - self.last_rx_seq - 1
        self.last_rx_seq = pkt.seq
        self._rx_tick = self.last_rx_tick = pkt.tick
        self.guard.sent(pkt.energy, self._now)
        c.accepted += 1
        return True

    def peer_restarted(self) -> None:
        """The peer process was replaced mid-session: accept its sequence numbers from 0 again,
        drop what is queued from the old one, and restart the energy account."""
        self.last_rx_seq = -1
        self.decoder.clear()
        self.guard.new_epoch(joined_late=False)
        self.peer_restarts += 1

    def expect_first_by(self, t: float) -> None:
        """Silence before the first packet is the channel's delay only until session time ``t``
        (the endpoint's bound, from the round trip): after it, a link never heard from counts as
        lost ``link_timeout`` later, as if its last packet had come at ``t`` (no ghost sessions)."""
        self._first_due = t

    def fade_within(self, fade_time: float) -> None:
        """Fade over at most ``fade_time`` s: a robot shortens its fade so that the longest it acts
        after its operator's last packet stays within its cap (``settings.acting_alone``)."""
        self._fade_step = max(self._fade_step, self.dt / fade_time)

    def joined_late(self) -> None:
        """This process joined a running session: its budget starts at the first packet it sees."""
        self.guard.new_epoch(joined_late=True)

    # --- per tick ------------------------------------------------------------------------
    def _supervise(self, now: float) -> float:
        """Update link supervision; returns this tick's coupling in [0, 1].

        Armed by the first accepted packet: before it, silence is the channel's delay, not a loss,
        until the first packet's due time (:meth:`expect_first_by`), if one was set.
        """
        self._now = now
        if self.counters.accepted == 0:
            if self._first_due is None:
                return self.coupling
            last = self._first_due
        else:
            if self._last_rx_at is None or self.counters.accepted != self._accepted_seen:
                self._last_rx_at = now
                self._accepted_seen = self.counters.accepted
            last = self._last_rx_at
        lost = now - last > self.link_timeout
        rep = self.guard.report
        if lost:
            rep.link_lost_ticks += 1
            if not self.link_lost:
                rep.link_lost_events += 1
            self.coupling = max(0.0, self.coupling - self._fade_step)
        else:
            self.coupling = min(1.0, self.coupling + self._fade_step)
        self.link_lost = lost
        return self.coupling

    def _play(self) -> Array:
        x = self.guard.admit(self.decoder.next())
        self.wave_in = x
        if self._tell_lag and getattr(self.decoder, "fresh", False):
            self.encoder.rx_lag = max(self._tick_of(self._now) - self._rx_tick, 0)  # type: ignore[attr-defined]
        return x

    def _tick_of(self, now: float) -> int:
        """The tick whose node time ``k dt`` is ``now`` (s, the session clock), rounded."""
        return int(now / self.dt + 0.5)

    def _send(self, now: float, x: Array) -> wire.Packet | None:
        self.energy_sent += self.half_dt * float(x.dot(x))  # np.dot(x, x), the method: cheaper per tick
        return self._transmit(now, x)

    def _transmit(self, now: float, x: Array) -> wire.Packet | None:
        """Encode ``x`` and build its packet, carrying :attr:`energy_sent` (None: nothing sent)."""
        self.wave_out = x
        payload = self.encoder.encode(x)
        if payload is None:
            return None
        tick = self._tick_of(now)  # from the session clock: stays true if the loop skips ticks
        pkt = wire.Packet(
            self.session,
            self.tx_direction,
            self.seq & 0xFFFFFFFF,
            tick,
            round(now * 1e6),
            self.tx_codec.codec_id,
            payload,
            # Less what this side self-credited (pdr's cKAPPA, eq. 1 via 4; 0.0 otherwise, which
            # leaves the sum bit for bit).
            self.energy_sent * self.report_scale - self.encoder.withheld,
        )
        cap = self.rate_cap
        if cap is not None:
            size = wire.encoded_size(pkt) + self.datagram_overhead
            if not cap.allows(tick, size):
                self.encoder.cancel()
                return None
            cap.sent(tick, size)
        self.seq += 1
        return pkt


def _scaled(x: Array, c: float) -> Array:
    """``c * x`` for the link coupling ``c``: ``x`` itself when ``c`` is 1, as it is but while the
    link is lost or fading in, since ``1.0 * x == x`` bit for bit (saves a numpy call a tick)."""
    return x if c == 1.0 else c * x


class OperatorNode(_Node):
    """HSI side: the simulated human on an ideal haptic device; sends g_l, receives h_l."""

    tx_direction = wire.FORWARD

    def __init__(
        self,
        *,
        human: Human,
        wave: WaveImpedance,
        tx: Codec,
        rx: Codec,
        session: int,
        dt: float,
        options: PortOptions | None = None,
    ) -> None:
        super().__init__(wave=wave, tx=tx, rx=rx, session=session, dt=dt, options=options)
        self.human = human

    @property
    def device(self) -> Human:
        """The HSI with its human (``teleop.devices``)."""
        return self.human

    _gains_of: Array | None = None  # the read-only admittance _gains last made its arrays from
    _gains_made: tuple[Array, Array]

    def _gains(self, y: Array, c: float) -> tuple[Array, Array]:
        """``(yc sqrt(2b), 1 + yc b)`` with ``yc = c y`` (the human feels ``c F``): what the HSI's
        closed-form solve multiplies and divides by.  A read-only ``y`` cannot change, so at full
        coupling its two arrays are made once and reused (the built-in humans' feedthrough is a
        constant): three numpy operations a tick fewer, the same arrays."""
        if c == 1.0 and y is self._gains_of:
            return self._gains_made
        yc = _scaled(y, c)
        made = (yc * self.wave.sqrt2b, 1.0 + yc * self.wave.b)
        if c == 1.0 and not y.flags.writeable:
            self._gains_of, self._gains_made = y, made
        return made

    def tick(self, now: float) -> wire.Packet | None:
        w = self.wave
        c = self._supervise(now)
        h_l = self._play()
        v0, y = self._device(self.human.affine(now), PLAUSIBLE_VELOCITY)
        ys, den = self._gains(y, c)
        v = (v0 + ys * h_l) / den
        f = _scaled(w.hsi_force(v, h_l), c)
        self.human.advance(now, v, f)
        self.v, self.f = v, f
        return self._send(now, _scaled(w.hsi_wave_out(v, h_l), c))


class TeleoperatorNode(_Node):
    """TO side: an ideal velocity-controlled robot in the environment; receives g_r, sends h_r."""

    tx_direction = wire.BACKWARD

    def __init__(
        self,
        *,
        environment: Environment,
        wave: WaveImpedance,
        tx: Codec,
        rx: Codec,
        session: int,
        dt: float,
        options: PortOptions | None = None,
    ) -> None:
        super().__init__(wave=wave, tx=tx, rx=rx, session=session, dt=dt, options=options)
        self.environment = environment

    @property
    def device(self) -> Environment:
        """The robot in its environment (``teleop.devices``)."""
        return self.environment

    _den_of: Array | None = None  # the read-only impedance _den last made its array from
    _den_made: Array

    def _den(self, z: Array, c: float) -> Array:
        """``b + c Z``, what the TO's closed-form solve divides by; for a read-only ``Z`` (a
        constant feedthrough) at full coupling made once, as :meth:`OperatorNode._gains`."""
        if c == 1.0 and z is self._den_of:
            return self._den_made
        made = self.wave.b + _scaled(z, c)
        if c == 1.0 and not z.flags.writeable:
            self._den_of, self._den_made = z, made
        return made

    def tick(self, now: float) -> wire.Packet | None:
        w = self.wave
        c = self._supervise(now)
        g_r = self._play()
        f0, z = self._device(self.environment.affine(now), PLAUSIBLE_FORCE_N)
        conf = self.confinement
        if conf is not None:
            z = conf.effective(f0, z)  # a contact the device senses a tick late, solved as one
        v = _scaled(w.sqrt2b * g_r - f0, c) / self._den(z, c)  # the robot is commanded c v
        f = f_wave = f0 + z * v
        if conf is not None and (cut := self._confined(conf, v, f0, z, f)) is not None:
            v, f, f_wave = cut
        self.environment.advance(now, v, f)
        self.v, self.f = v, f
        return self._send(now, _scaled(w.to_wave_out(g_r, f_wave), c))

    def _command(
        self, conf: Confinement, v: Array, f0: Array, z: Array, f: Array | None = None
    ) -> Array | None:
        """The envelope's cut of ``v`` (None: none), counted."""
        vs = conf.command(v, f0, z, f)
        if vs is not None:
            self.counters.saturated += 1
        return vs

    def _confined(
        self, conf: Confinement, v: Array, f0: Array, z: Array, f: Array | None = None
    ) -> tuple[Array, Array, Array] | None:
        """The envelope's cut of the solve's ``v`` (``teleop.control.confine``): ``(v', F, F_wave)``,
        ``F_wave`` being the force the outgoing wave is made from, or None when nothing was cut.

        Passive: where the confined force has the sign of the cut ``v - v'``, the channel sees the
        port it solved for and the cut absorbs ``(v_port - v') F >= 0`` (``v_port - v'`` has the
        sign of ``v - v'``); elsewhere the wave returns as it came (``F_wave = 0``: nothing taken
        from the channel, nothing given), and what the contact pushes into the robot is its
        actuator's to absorb."""
        vs = self._command(conf, v, f0, z, f)
        if vs is None:
            return None
        fs = f0 + z * vs
        return vs, fs, np.where(fs * (v - vs) >= 0.0, fs, 0.0)


class _TdpaNode(_Node):
    """What both TDPA nodes share: the TDPA guard, and the energy report riding every packet.

    The packet's ``energy`` field carries this port's cumulative input energy ``E_in`` (J into the
    network here, ``teleop.control.passivity``); its payload is a power variable (``teleop.session.wire``).
    """

    _reported = 0.0  # E_in carried by the last packet that left

    def _make_guard(
        self, dt: float, opts: PortOptions, wave: WaveImpedance, tx: Codec, rx: Codec
    ) -> EnergyGuard:
        # The peer's port power is about |v| |F| per DoF, both within their ranges; the factor 4 is
        # headroom for a device moving beyond the velocity range (its power is real, only not sent).
        max_power = 4.0 * wave.dof * tx.raw.full_scale * rx.raw.full_scale
        return TdpaGuard(dt, controller=opts.controller, max_power=max_power)

    def _envelope_power(self, env: Envelope) -> float:
        """W the robot's own limits let a genuine report grow by: its port at full velocity and
        force, with the same headroom as :meth:`_make_guard`."""
        return 4.0 * self.wave.dof * env.max_velocity * env.max_force

    @property
    def tdpa(self) -> TdpaGuard:
        g = self.guard
        assert isinstance(g, TdpaGuard)
        return g

    def _allowed(self) -> float:
        """W the PC lets out this tick: the budget, or unbounded with the controller off."""
        g = self.tdpa
        return g.allowed_power() if g.controller else float("inf")

    def _book(self, power_in: float, removed: float, acted: bool) -> None:
        """Book one tick's power into the network at this port (``removed``: W the PC took away);
        the observer's verdict on it."""
        g = self.tdpa
        violation = acted or -power_in * self.dt > g.margin + g.tolerance
        g.account(power_in, removed, violation, acted)
        self.energy_sent = g.energy_in

    def _send_power(self, now: float, x: Array) -> wire.Packet | None:
        """Send this tick's power variable; an event-based encoder must send when the input energy
        it has not reported yet exceeds :data:`TDPA_REPORT_QUANTUM_J` (energy-triggered update)."""
        self.encoder.urgent = self.energy_sent - self._reported > TDPA_REPORT_QUANTUM_J
        pkt = self._transmit(now, x)
        if pkt is not None:
            self._reported = self.energy_sent
        return pkt


class TdpaOperatorNode(_TdpaNode, OperatorNode):
    """HSI side under TDPA: sends ``v_hsi``, displays the received ``F_to`` through the adaptive
    parallel damper (``teleop.control.passivity.parallel_damper``) over its own rendered damping."""

    @property
    def hsi_damping(self) -> float:
        """N s/m the HSI renders under TDPA (:data:`TDPA_HSI_DAMPING` of the mean ``b``)."""
        return TDPA_HSI_DAMPING * float(np.mean(self.wave.b))

    def tick(self, now: float) -> wire.Packet | None:
        c = self._supervise(now)
        f_r = self.decoder.next()
        self.wave_in = f_r
        v0, y = self._device(self.human.affine(now), PLAUSIBLE_VELOCITY)
        beta0 = self.hsi_damping * c
        v, f, p, removed, acted = parallel_damper(v0, y, c * f_r, self._allowed(), beta0)
        self.human.advance(now, v, f)
        self.v, self.f = v, f
        self._book(p, removed, acted)  # eq. (2): v_hsi . F_hsi enters the network here
        return self._send_power(now, c * v)


class TdpaTeleoperatorNode(_TdpaNode, TeleoperatorNode):
    """TO side under TDPA: commands the received ``v_hsi`` through the adaptive series damper
    (``teleop.control.passivity.series_damper``), sends its force ``F_to``."""

    coupling_error: Array  # m: commanded minus robot position, per DoF (the controller's spring)

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.coupling_error = np.zeros(self.wave.dof)
        b = float(np.mean(self.wave.b))
        self.to_damping = TDPA_TO_DAMPING * b  # N s/m
        self.to_stiffness = TDPA_TO_BANDWIDTH * b  # N/m
        self.drift = np.zeros(self.wave.dof)  # m: received minus commanded position (the PC's lost motion)

    def tick(self, now: float) -> wire.Packet | None:
        c = self._supervise(now)
        v_r = self.decoder.next()
        self.wave_in = v_r
        f_dev, z_dev = self._device(self.environment.affine(now), PLAUSIBLE_FORCE_N)
        conf = self.confinement
        if conf is not None:
            z_dev = conf.effective(f_dev, z_dev)  # a contact the device senses a tick late, solved as one
        # The robot behind its position controller, massless: F = K e' + B (v_d - v) = f0 + Z v with
        # e' = e + (v_d - v) dt, so F = K e + G (v_d - v), G = K dt + B; seen from the network it is
        # again an impedance F = f0' + Z' v_d (f0' = (G f0 + Z K e) / (G + Z), Z' = G Z / (G + Z)).
        k, g = self.to_stiffness, self.to_damping + self.to_stiffness * self.dt
        if c < 1.0:  # safe state: the spring lets go with the coupling (only removes its stored energy)
            self.coupling_error *= c
        ke = k * self.coupling_error
        f0, z = (g * f_dev + z_dev * ke) / (g + z_dev), g * z_dev / (g + z_dev)
        v_ref = c * v_r
        if c < 1.0:
            self.drift *= c
        # Passive drift compensation: ask for the motion the PC took away, at a bounded rate; the
        # PC below lets it through only from the energy budget, so it can never make energy.
        corr = TDPA_DRIFT_GAIN * self.drift
        n = float(np.sqrt(np.dot(corr, corr)))
        if n > TDPA_DRIFT_MAX_V:
            corr *= TDPA_DRIFT_MAX_V / n
        cmd = v_ref + corr
        if conf is not None:
            # The envelope on the impedance seen from the network (F = f0' + Z' v_d), so that the
            # controller's books hold the robot's limited motion; a slower command only removes
            # energy, and the drift compensator asks the rest back within the budget.
            cl = cmd.tolist()
            cut, _ = confined(cl, f0.tolist(), z.tolist(), self.max_velocity, self.max_force)
            if cut != cl:
                self.counters.saturated += 1
                cmd = np.array(cut)
        v_d, f, p, removed, acted = series_damper(cmd, f0, z, self._allowed())
        self.drift += (v_ref - v_d) * self.dt
        v = v_d - (f - ke) / g  # the position controller's yield
        # Its spring winds up with its own yield only: what the envelope below refuses is not asked
        # back by the spring (no wind-up against a limit).
        self.coupling_error += (v_d - v) * self.dt
        f_out = f
        if conf is not None and (vs := self._command(conf, v, f_dev, z_dev)) is not None:
            # The last step before the device: the envelope acts on the device's side of the
            # controller, after the observer, so the network's books (-v_d . F below) are the
            # controller's, unchanged; what a relief takes out of the contact is the actuator's.
            v, f = vs, f_dev + z_dev * vs
        self.environment.advance(now, v, f)
        self.v, self.f = v, f
        self._book(-p, removed, acted)  # eq. (2): -v_d . F_pc enters the network here
        return self._send_power(now, c * f_out)
