"""Operator (HSI) and teleoperator (TO) nodes: ``receive(bytes)`` and ``tick(now) -> Packet | None``.

Sans-I/O: a node never reads a clock, opens a socket or sleeps.  The same objects run in
``teleop sim`` (virtual time) and in the two real processes.

Each tick, each port solves its algebraic loop in closed form (see ``teleop.models``):

* HSI: the human gives ``v = v0 - Y F``; the port renders ``F = b v - sqrt(2b) h_l`` (eq. 3)::

      v_hsi = (v0 + Y sqrt(2b) h_l) / (1 + Y b),   g_l = sqrt(2b) v_hsi - h_l

* TO: the environment gives ``F = f0 + Z v``; the port commands ``v = (sqrt(2b) g_r - F) / b``::

      v_to = (sqrt(2b) g_r - f0) / (b + Z),        h_r = g_r - sqrt(2/b) F_to

The received wave (``h_l`` or ``g_r``) is what the decoder plays this tick; the transmitted wave
goes through the encoder.  Energies are counted in scattering variables per direction (eq. 4-5):
``E = 1/2 sum(wave**2) dt``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import wire
from .codecs import Array, Codec, CodecError
from .models import Environment, Human
from .wave import WaveImpedance


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
    errors: dict[str, int] = field(default_factory=dict)  # last message per kind, for logs

    def as_dict(self) -> dict[str, int]:
        return {k: v for k, v in self.__dict__.items() if k != "errors"}


class _Port:
    """What both nodes share: sequence numbers, codec ends, energy counters, inbound checks."""

    tx_direction: int

    def __init__(
        self,
        *,
        wave: WaveImpedance,
        tx: Codec,
        rx: Codec,
        session: int,
        dt: float,
        max_queue: int | None = None,
    ) -> None:
        if tx.dof != wave.dof or rx.dof != wave.dof:
            raise ValueError(f"codec DoF ({tx.dof}, {rx.dof}) must match wave DoF {wave.dof}")
        self.wave = wave
        self.tx_codec = tx
        self.rx_codec = rx
        self.encoder = tx.encoder()
        self.decoder = rx.decoder(max_queue)
        self.session = session
        self.dt = dt
        self.half_dt = 0.5 * dt
        self.rx_direction = 1 - self.tx_direction
        self.seq = 0
        self.ticks = 0
        self.last_rx_seq = -1
        self.counters = PortCounters()
        self.energy_sent = 0.0  # J carried into the channel by the transmitted wave
        self.energy_played = 0.0  # J played out of the channel by the received wave
        self.peer_energy_sent = 0.0  # latest cumulative energy the peer reported in-band
        self.last_error = ""
        dof = wave.dof
        self.v = np.zeros(dof)
        self.f = np.zeros(dof)
        self.wave_out = np.zeros(dof)
        self.wave_in = np.zeros(dof)

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
        c.gaps += pkt.seq - self.last_rx_seq - 1
        self.last_rx_seq = pkt.seq
        self.peer_energy_sent = max(self.peer_energy_sent, pkt.energy)
        c.accepted += 1
        return True

    # --- outbound ------------------------------------------------------------------------
    def _play(self) -> Array:
        x = self.decoder.next()
        self.energy_played += self.half_dt * float(np.dot(x, x))
        self.wave_in = x
        return x

    def _send(self, now: float, x: Array) -> wire.Packet | None:
        self.wave_out = x
        self.energy_sent += self.half_dt * float(np.dot(x, x))
        payload = self.encoder.encode(x)
        tick = int(now / self.dt + 0.5)  # from the session clock: stays true if the loop skips ticks
        self.ticks += 1
        if payload is None:
            return None
        pkt = wire.Packet(
            self.session,
            self.tx_direction,
            self.seq & 0xFFFFFFFF,
            tick,
            int(now * 1e6),
            self.tx_codec.codec_id,
            payload,
            self.energy_sent,
        )
        self.seq += 1
        return pkt


class OperatorNode(_Port):
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
        max_queue: int | None = None,
    ) -> None:
        super().__init__(wave=wave, tx=tx, rx=rx, session=session, dt=dt, max_queue=max_queue)
        self.human = human

    def tick(self, now: float) -> wire.Packet | None:
        w = self.wave
        h_l = self._play()
        v0, y = self.human.affine(now)
        v = (v0 + y * w.sqrt2b * h_l) / (1.0 + y * w.b)
        f = w.hsi_force(v, h_l)
        self.human.advance(now, v, f)
        self.v, self.f = v, f
        return self._send(now, w.hsi_wave_out(v, h_l))


class TeleoperatorNode(_Port):
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
        max_queue: int | None = None,
    ) -> None:
        super().__init__(wave=wave, tx=tx, rx=rx, session=session, dt=dt, max_queue=max_queue)
        self.environment = environment

    def tick(self, now: float) -> wire.Packet | None:
        w = self.wave
        g_r = self._play()
        f0, z = self.environment.affine(now)
        v = (w.sqrt2b * g_r - f0) / (w.b + z)
        f = f0 + z * v
        self.environment.advance(now, v, f)
        self.v, self.f = v, f
        return self._send(now, w.to_wave_out(g_r, f))
