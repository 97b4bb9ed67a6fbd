"""The per-side sans-I/O port: everything one side does between its socket and its device.

A :class:`Port` owns the node, the outgoing impairment shim, the wire counters of both directions
as this side sees them, the link observer of the incoming direction, the per-tick recorder and the
summary.  Its surface is ``receive(datagram, t, k)``, ``tick(k, t) -> datagrams``, ``next_due()``,
``flush(t, k)`` and ``summary()``; it never reads a clock or a socket.  ``teleop sim`` joins two
ports with virtual links (``teleop.offline.sim``); the real-time runner (``shell.runner``)
puts one, inside its endpoint, between the clock and the transport.  So the counters, the link
figures and the summary of a simulated and a real run come from the same code, and their ``wire``
blocks compare key by key.

Time: ``k`` is the tick index (the node runs at ``k dt``, the session clock of eq. 7); ``t`` is when
this happens on the common session clock in seconds (``k dt`` in the simulation, the measured
monotonic clock minus the session's tick 0 in a real process).  The shim and the link observer
use ``t``; the node and the counters use ``k``.

Authentication (``teleop.session.auth``): every datagram the port sends is sealed and every datagram it
takes is verified first; nothing unauthenticated reaches the node, the sequence tracking, the link
observer or the energy budget.  Data and in-session control use the session keys the handshake
derived; the replay window is updated only after the tag verifies (and after the link observer
saw the packet, so a duplicate the network made is measured as one, then dropped).  Hellos of other
operators and welcomes on a rejoin come under the handshake key.

Baseline: the uncompressed stream (every tick's raw 16-bit sample in a packet of the same
format) is not encoded per tick: its size is a closed-form function of the tick
(``teleop.session.wire.packet_size``), computed for every tick of the session from this side's first to
its last (a stalled loop's skipped ticks included) when the summary is asked for.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from typing import Any, Protocol

import numpy as np
import numpy.typing as npt

from teleop import devices
from teleop.control.codecs import CodecSpec, make_codec
from teleop.control.codecs.base import RAW_BITS, packed_size
from teleop.control.wave import WaveImpedance
from teleop.devices import scenarios
from teleop.session import auth, protocol, wire
from teleop.session.link.counters import UDP_IPV4_HEADER, DirectionCounters
from teleop.session.link.linkstats import LinkObserver
from teleop.session.link.netem import Link, NetemStats, make_link
from teleop.session.link.phase import ClockTracker
from teleop.session.node import (
    OperatorNode,
    PortOptions,
    TdpaOperatorNode,
    TdpaTeleoperatorNode,
    TeleoperatorNode,
)
from teleop.session.playout import PlayoutBuffer
from teleop.session.settings import MIN_FADE_S, Envelope, Passivity

Array = npt.NDArray[np.float64]
Node = OperatorNode | TeleoperatorNode

#: The ``wire.{forward,backward}`` keys of ``report.json`` and of ``results.json`` cases.
WIRE_KEYS = (
    "packets",
    "payload_bytes",
    "wire_bytes",
    "baseline_packets",
    "baseline_payload_bytes",
    "baseline_wire_bytes",
    "compression_payload",
    "compression_wire",
    "min_instant_compression_payload",
    "min_instant_compression_wire",
    "received_packets",
    "received_wire_bytes",
    "received_payload_bytes",
    "received_malformed",
    "lost",
)


NOT_AN_ENVELOPE = "not a teleop envelope"
FOREIGN_SESSION_DATAGRAM = "a session datagram from another address"


class ConstantDelayLink:
    """A lossless link with constant delay: ``send(now, data)``, ``due(now) -> [data]``.

    Same interface as the netem shim's link model (``teleop.session.link.netem.Link``), so a port does not
    care which it has.
    """

    def __init__(self, delay: float) -> None:
        if delay < 0:
            raise ValueError(f"delay must be >= 0 s, got {delay}")
        self.delay = delay
        self.stats = NetemStats()
        self._heap: list[tuple[float, int, bytes]] = []
        self._n = 0

    def send(self, now: float, data: bytes) -> None:
        heapq.heappush(self._heap, (now + self.delay, self._n, data))
        self._n += 1
        self.stats.sent += 1

    def due(self, now: float) -> list[bytes]:
        out = []
        limit = now + 1e-9
        while self._heap and self._heap[0][0] <= limit:
            out.append(heapq.heappop(self._heap)[2])
        self.stats.delivered += len(out)
        return out

    def next_due(self) -> float | None:
        return self._heap[0][0] if self._heap else None


def make_shim(spec: str, seed: int, direction: int, delay: float = 0.0) -> Link | None:
    """The outgoing shim of one direction: the netem spec if given (seeded ``2 seed + direction``,
    so both directions and neighbouring seeds draw independent streams), else a constant delay,
    else none (packets go straight to the socket)."""
    if spec.strip():
        return make_link(spec, 2 * seed + direction)
    return ConstantDelayLink(delay) if delay > 0 else None


def make_node(
    role: str,
    *,
    scenario: str,
    dof: int,
    dt: float,
    b: float,
    codec: str,  # a CodecSpec (parsed already) or a spec to parse
    full_scale: float,
    session: int,
    options: PortOptions,
    device: str | None = None,
    seed: int = 0,
    variation: float = 0.0,
) -> Node:
    """The operator's or the teleoperator's node for a scenario: one construction for both runners.

    ``device``: this side's ``--hsi``/``--robot`` spec (``teleop.devices``; a local choice, never
    from the network); default the scenario's own model.  Only this side's device is built.
    ``seed`` and ``variation`` vary the scenario's human (0: the scripted run); both sides must
    pass the session's, so their built-in models agree on the phase timing.
    """
    if role not in ("operator", "teleoperator"):
        raise ValueError(f"role must be operator or teleoperator, got {role!r}")
    spec = device or scenarios.get(scenario).name
    side = "hsi" if role == "operator" else "robot"
    dev = devices.make(side, spec, dof, dt, seed=seed, variation=variation)
    wave = WaveImpedance.of(b, dof)
    node: Node
    codec_spec = CodecSpec.parse(codec)
    if options.passivity == Passivity.TDPA:
        v_codec, f_codec = (make_codec(codec_spec, dof, r, power=True) for r in power_ranges(full_scale, b))
        if role == "operator":
            node = TdpaOperatorNode(
                human=dev, wave=wave, tx=v_codec, rx=f_codec, session=session, dt=dt, options=options
            )
        else:
            node = TdpaTeleoperatorNode(
                environment=dev, wave=wave, tx=f_codec, rx=v_codec, session=session, dt=dt, options=options
            )
        node.device_spec = spec
        return node
    c = make_codec(codec_spec, dof, full_scale)
    if role == "operator":
        node = OperatorNode(human=dev, wave=wave, tx=c, rx=c, session=session, dt=dt, options=options)
    else:
        node = TeleoperatorNode(
            environment=dev, wave=wave, tx=c, rx=c, session=session, dt=dt, options=options
        )
    node.device_spec = spec
    return node


def session_node(role: str, params: protocol.SessionParams, device: str | None = None) -> Node:
    """This side's node of a session of ``params``: what :func:`teleop.session.endpoint.session_port`
    builds, and what :func:`build_refusal` builds to vet a proposal (one construction, so the two
    cannot disagree)."""
    return make_node(
        role,
        scenario=params.scenario,
        dof=params.dof,
        dt=params.dt,
        b=params.b,
        codec=params.codec,
        full_scale=params.full_scale,
        session=params.session,
        options=params.port_options(),
        device=device,
        seed=params.seed,
        variation=params.variation,
    )


#: Ticks :func:`build_refusal` runs both nodes for: every codec's first payload goes out at tick 0.
PROBE_TICKS = 2


def build_refusal(params: protocol.SessionParams, envelope: Envelope | None = None) -> str | None:
    """Why a session of ``params`` cannot run, in one line, or None: a welcome is a promise.

    Builds both sides' nodes as a session does (:func:`session_node` with the scenario's built-in
    devices: the codecs for the ranges the architecture derives from ``range`` and ``b``, their
    encoders and decoders, the energy guards), confines the robot's to ``envelope``, and runs
    their first :data:`PROBE_TICKS` ticks with each packet handed to the other.  A range
    that underflows a codec's format (a subnormal one, or a deadband's slope range under TDPA)
    raises here, before the welcome, instead of at the session's start (issue 45).  About a
    millisecond: only an authentic hello with a valid cookie gets this far."""
    try:
        op, to = (session_node(role, params) for role in ("operator", "teleoperator"))
        if envelope is not None:
            to.confine(envelope)
        for k in range(PROBE_TICKS):
            for a, b in ((op, to), (to, op)):
                pkt = a.tick(k * params.dt)
                if pkt is not None:  # (the wire's encode never raises; a peer's decode only counts)
                    b.receive_packet(pkt)
    except (ValueError, ArithmeticError) as e:  # CodecError, ModelError, ... are ValueErrors
        what = f"codec {params.codec}, {params.passivity}, range {params.full_scale:g}, b {params.b:g}"
        said = str(e).splitlines()[0] if str(e) else type(e).__name__
        return f"this session ({what}) cannot be built: {said}"
    return None


def power_ranges(full_scale: float, b: float) -> tuple[float, float]:
    """The ranges of velocity and force on the wire under TDPA, from the session's wave range ``W``
    and impedance ``b``: what waves within ``+-W`` carry by eq. (3), ``v = (g + h) / sqrt(2b)`` and
    ``F = (g - h) sqrt(b / 2)``, so ``|v| <= W sqrt(2 / b)`` and ``|F| <= W sqrt(2 b)``; one
    ``--range`` sizes both architectures alike."""
    return full_scale * math.sqrt(2.0 / b), full_scale * math.sqrt(2.0 * b)


@dataclass
class PortKeys:
    """This side's end of the authenticated channel: sealers for what it sends, openers (with
    their replay windows) for what it takes, and what it needs to re-key after a peer restart."""

    tx: auth.Sealer  # session key, this side's direction: data, bye, started, a rejoin's start
    rx: auth.Opener  # session key, the peer's direction
    hs_tx: auth.Sealer  # handshake key, this side's direction: a rejoin hello, a busy reject
    hs_rx: auth.Opener  # handshake key, the peer's direction: other operators' hellos, welcomes
    psk: bytes
    nonce: bytes  # this side's handshake nonce


def port_keys(
    psk: bytes, tx_direction: int, session: int, nonce_op: bytes, nonce_to: bytes, counter: int = 1
) -> PortKeys:
    """Fresh keys for one side (the simulation, or tests): what a handshake would have left."""
    fwd, bwd = auth.session_keys(psk, session, nonce_op, nonce_to)
    k_hs = auth.handshake_key(psk)
    rx_dir = 1 - tx_direction
    tx_key, rx_key = (fwd, bwd) if tx_direction == wire.FORWARD else (bwd, fwd)
    return PortKeys(
        tx=auth.Sealer(tx_key, auth.SESSION, tx_direction, counter),
        rx=auth.Opener(rx_key, auth.SESSION, rx_dir),
        hs_tx=auth.Sealer(k_hs, auth.HANDSHAKE, tx_direction, counter),
        hs_rx=auth.Opener(k_hs, auth.HANDSHAKE, rx_dir),
        psk=psk,
        nonce=nonce_op if tx_direction == wire.FORWARD else nonce_to,
    )


@dataclass
class SecurityCounters:
    """What this side refused, per reason, counted at its receiver (``report.json``'s ``security``)."""

    rejected: int = 0  # not an envelope, wrong key, kind or direction, bad tag: forged or corrupted
    replayed: int = 0  # authentic, but a counter already seen or older than the window
    counter_jumps: int = 0  # authentic, but a counter further ahead than the elapsed time allows
    last_rejection: str = ""


#: Ticks per chunk of the per-tick record: about 200 kB at 1 DoF, handed on once a second at 1 kHz.
CHUNK_TICKS = 1000

SIGNALS = ("v", "f", "wave_out", "wave_in")  # (ticks, dof) each
ENERGIES = ("energy_sent", "energy_played", "energy_margin_observed", "energy_played_epoch")
#: The per-tick byte counts of a chunk: what this side sent (``tx_*``, with the uncompressed
#: baseline) and received (``rx_*``), counted at the socket.
BYTES = ("tx_wire", "tx_payload", "tx_baseline_wire", "tx_baseline_payload", "rx_wire", "rx_payload")


class Chunk:
    """Per-tick records of ticks ``[k0, k0 + n)`` of one side, in arrays allocated once per chunk.

    Rows of ticks the side did not run (a late joiner's first ticks, a stall's skipped ones) keep
    ``play_time`` NaN; :meth:`ran` lists the others."""

    def __init__(self, k0: int, size: int, dof: int) -> None:
        self.k0 = k0
        self.size = size
        self.n = 0  # rows in use: up to the last tick recorded or counted
        self.signals = {name: np.full((size, dof), np.nan) for name in SIGNALS}
        self.energy = {name: np.full(size, np.nan) for name in ENERGIES}
        self.play_time = np.full(size, np.nan)  # s, session clock: when tick k played its sample
        self.send_time = np.full(size, np.nan)  # s, session clock: when tick k's packet left
        self.produced_payload = np.zeros(size)  # bytes of the payload the node produced at tick k
        self.produced_packet = np.zeros(size)  # bytes of that packet, before the shim
        # Sequence numbers, so the report can check the energy played against the sender's own log
        # without trusting either clock: the seq sent at tick k, and the newest seq accepted by then.
        self.tx_seq = np.full(size, -1, dtype=np.int64)
        self.rx_seq = np.full(size, -1, dtype=np.int64)
        # The teleoperator's send phase at tick k (ticks; -1: none, the operator): its playout target,
        # which iDS/eDS sample after; recorded so a replay of the run sends when the run did.
        self.send_phase = np.full(size, -1, dtype=np.int64)
        self.peer_epoch = np.zeros(size, dtype=np.int64)
        # The watchdog controller's ticks so far (cumulative), so a tick it acted in is exact in the log
        # (an export's per-sample flag: teleop.offline.lerobot); -1: a tick not run.
        self.controller_ticks = np.full(size, -1, dtype=np.int64)
        # The device's own state, at its own rate (``state_every`` ticks; teleop.devices): (tick, values).
        self.device_state: list[tuple[int, dict[str, list[float]]]] = []
        self.lateness_ns = np.zeros(size, dtype=np.int64)  # the real-time loop's, when it says
        self.bytes = {name: np.zeros(size) for name in BYTES}

    def row(self, k: int) -> int:
        r = k - self.k0
        self.n = max(self.n, r + 1)
        return r

    def ran(self) -> npt.NDArray[np.intp]:
        """Rows of the ticks this side ran."""
        return np.flatnonzero(~np.isnan(self.play_time[: self.n]))

    def arrays(self) -> dict[str, npt.NDArray[Any]]:
        """The rows in use, by the names of the log (``teleop.offline.logfile``)."""
        n = self.n
        return {
            **{k: v[:n] for k, v in self.signals.items()},
            **{k: v[:n] for k, v in self.energy.items()},
            "play_time_s": self.play_time[:n],
            "send_time_s": self.send_time[:n],
            "produced_payload": self.produced_payload[:n],
            "produced_packet": self.produced_packet[:n],
            "tx_seq": self.tx_seq[:n],
            "rx_seq": self.rx_seq[:n],
            "send_phase": self.send_phase[:n],
            "peer_epoch": self.peer_epoch[:n],
            "controller_ticks": self.controller_ticks[:n],
            "lateness_ns": self.lateness_ns[:n],
            **{k: v[:n] for k, v in self.bytes.items()},
        }


class ChunkSink(Protocol):
    """Where a port's sealed chunks go: the runner's file writer, or memory (``teleop sim``)."""

    def write(self, chunk: Chunk) -> None: ...


class MemorySink:
    """Keeps every chunk: the simulation's record, whole-session arrays on demand."""

    def __init__(self) -> None:
        self.chunks: list[Chunk] = []

    def write(self, chunk: Chunk) -> None:
        self.chunks.append(chunk)

    def arrays(self, ticks: int | None = None) -> dict[str, npt.NDArray[Any]]:
        """Every field over ticks ``[0, ticks)`` (default: through the last chunk), gaps filled as
        a chunk fills rows it did not run (NaN signals, zero bytes, seq -1)."""
        return concat_chunks([c.k0 for c in self.chunks], [c.arrays() for c in self.chunks], ticks)


def fill_value(name: str) -> float:
    """A record field's value at a tick not run: no sequence number (-1), no bytes, no epoch
    change and no lateness (0), otherwise no value (NaN)."""
    if name in ("tx_seq", "rx_seq", "send_phase", "controller_ticks"):
        return -1
    if name in BYTES or name.startswith("produced") or name in ("peer_epoch", "lateness_ns"):
        return 0
    return math.nan


def concat_chunks(
    starts: list[int], parts: list[dict[str, npt.NDArray[Any]]], ticks: int | None = None
) -> dict[str, npt.NDArray[Any]]:
    """Chunk arrays (``parts[i]`` starting at tick ``starts[i]``) as whole-session arrays from tick 0."""
    if not parts:
        return {}
    end = max(k0 + len(a["play_time_s"]) for k0, a in zip(starts, parts, strict=True))
    n = end if ticks is None else ticks
    out: dict[str, npt.NDArray[Any]] = {}
    for name, a in parts[0].items():
        out[name] = np.full((n, *a.shape[1:]), fill_value(name), dtype=a.dtype)
    for k0, part in zip(starts, parts, strict=True):
        m = max(0, min(len(part["play_time_s"]), n - k0))
        for name, v in part.items():
            out[name][k0 : k0 + m] = v[:m]
    return out


#: The per-datagram byte columns: added to (not set) for each datagram, in lists while their chunk
#: is open (a list element is added to several times faster than a numpy one), into the chunk's
#: arrays when it is sealed (the sums are integers, exact either way).
_DATAGRAM_BYTES = ("tx_wire", "tx_payload", "rx_wire", "rx_payload")


class _Columns:
    """The open chunk's per-tick columns as attributes: the recorder writes a row of each every
    tick, and an attribute is found faster than a key of a dict of a dict."""

    def __init__(self, c: Chunk) -> None:
        self.v, self.f = c.signals["v"], c.signals["f"]
        self.wave_out, self.wave_in = c.signals["wave_out"], c.signals["wave_in"]
        e = c.energy
        self.energy_sent, self.energy_played = e["energy_sent"], e["energy_played"]
        self.energy_margin_observed = e["energy_margin_observed"]
        self.energy_played_epoch = e["energy_played_epoch"]
        self.tx_wire, self.tx_payload, self.rx_wire, self.rx_payload = ([0] * c.size for _ in range(4))

    def store_bytes(self, c: Chunk) -> None:
        """The byte columns into the chunk's arrays (at its seal)."""
        for name in _DATAGRAM_BYTES:
            c.bytes[name][:] = getattr(self, name)


class Recorder:
    """The per-tick record of one side, a chunk at a time: ``CHUNK_TICKS`` ticks are kept in
    arrays allocated for the chunk, and a chunk is handed to the sink once a tick beyond it comes
    (or at :meth:`seal`), so memory does not grow with the session and the port does no I/O.

    ``baseline(ks)``: the uncompressed stream's datagram sizes at ticks ``ks`` (closed form), so a
    sealed chunk carries the baseline of every tick from this side's first to its last, skipped
    ones included: the uncompressed stream runs at 1 kHz whether or not a stalled loop ran each tick.
    """

    def __init__(
        self,
        dof: int,
        sink: ChunkSink,
        tx: DirectionCounters,
        rx: DirectionCounters,
        baseline: Callable[[npt.NDArray[np.int64]], npt.NDArray[np.int64]],
        raw_payload_len: int,
        chunk_ticks: int = CHUNK_TICKS,
    ) -> None:
        self.dof = dof
        self.sink = sink
        self.tx, self.rx = tx, rx
        self._baseline = baseline
        self.raw_payload_len = raw_payload_len
        self.chunk_ticks = chunk_ticks
        self.chunk: Chunk | None = None
        self.first = -1  # first tick run, -1 none yet
        self.last = -1  # last tick run
        self.ticks_run = 0
        self._end = 0  # the open chunk's end (exclusive)
        self._cols: _Columns  # the open chunk's columns, made with it in _at
        # ``defer`` (the real-time runner's): a chunk a tick closes is sealed by settle(), called
        # once the tick's datagrams left, a step per call (the bytes and the baseline's closed form,
        # the compression window, the sink), and the next chunk is made there too, not in the
        # tick: a seal costs ~0.4-0.5 ms cold and the sink's pickle up to as much again, which in
        # the tick delayed one send a second by that much, and in one gap between ticks started
        # the next tick late enough (0.4-1.5 ms, measured) for the peer to miss its payload.  Off
        # (teleop sim), a chunk is sealed in the tick that closes it; the chunks and figures are
        # the same either way.
        self.defer = False
        self._pending: Iterator[None] | None = None  # a closed chunk's seal, a step per settle()
        self._next: tuple[Chunk, _Columns] | None = None  # made ahead by settle()
        tx.on_tick = self._tx_bytes
        rx.on_tick = self._rx_bytes
        self._state_every = 0  # ticks between two samples of the device's state; 0: it has none
        self._state: Callable[[], dict[str, list[float]]] = dict

    def watch(self, device: object) -> None:
        """Record ``device``'s state beside the channel's signals, if it has one: ``state()`` (a
        map of named lists of numbers, cheap: it is called in the tick) every ``state_every``
        ticks, its own rate (``teleop.devices``).  Why here: the robot's joints and pose are what a
        learner or a 3D view needs, and the recorder is the one place that sees every tick."""
        every, state = getattr(device, "state_every", 0), getattr(device, "state", None)
        if callable(state) and isinstance(every, int) and every > 0:
            self._state_every, self._state = every, state

    def _at(self, k: int) -> tuple[Chunk, int]:
        """The chunk and row of tick ``k``: a tick past the chunk seals it and opens the next one
        (aligned on multiples of the chunk size); an earlier one counts in the chunk's first row.
        Called several times a tick: the common case (``k`` in the open chunk) is :meth:`Chunk.row`
        inlined, with the chunk's end kept in ``_end``."""
        c = self.chunk
        if c is None or k >= self._end:
            c = self._open(k)
        r = k - c.k0 if k > c.k0 else 0
        if r >= c.n:
            c.n = r + 1
        return c, r

    def _open(self, k: int) -> Chunk:
        """Close the open chunk (sealed now, or by :meth:`settle` if ``defer``) and open tick ``k``'s."""
        c, k0 = self.chunk, k - k % self.chunk_ticks
        if c is not None:
            self._finish_pending()  # settle() was not called enough since the last close
            if self.defer:
                self._pending = self._seal_steps(c, self._cols, k)
            else:
                self._seal(c, self._cols, k)
        made, self._next = self._next, None
        if made is not None and made[0].k0 == k0:
            c, self._cols = made
            self.chunk = c
        else:
            c = self.chunk = Chunk(k0, self.chunk_ticks, self.dof)
            self._cols = _Columns(c)
        self._end = c.k0 + c.size
        return c

    def settle(self) -> None:
        """Work that can wait until the tick's datagrams left (``defer``): the next step of the seal
        of the chunk a tick closed, else make the next chunk ahead of the tick that opens it."""
        if self._pending is not None:
            if next(self._pending, StopIteration) is StopIteration:
                self._pending = None
            else:
                return
        c = self.chunk
        if self.defer and self._next is None and c is not None:
            nxt = Chunk(c.k0 + c.size, self.chunk_ticks, self.dof)
            self._next = (nxt, _Columns(nxt))

    def _tx_bytes(self, k: int, wire: int, payload: int) -> None:
        r = self._at(k)[1]
        cols = self._cols
        cols.tx_wire[r] += wire
        cols.tx_payload[r] += payload

    def _rx_bytes(self, k: int, wire: int, payload: int) -> None:
        r = self._at(k)[1]
        cols = self._cols
        cols.rx_wire[r] += wire
        cols.rx_payload[r] += payload

    def record(
        self, k: int, t: float, node: Node, produced: tuple[int, int, int] | None = None, send_phase: int = -1
    ) -> None:
        """Tick ``k`` ran at ``t``: the node's signals and energies; ``produced`` is ``(payload
        bytes, packet bytes, seq)`` of the packet the node made in it, if any (one call a tick);
        ``send_phase``: the teleoperator's (-1: none)."""
        c, r = self._at(k)
        if produced is not None:
            c.produced_payload[r], c.produced_packet[r], c.tx_seq[r] = produced
        cols = self._cols
        cols.v[r] = node.v
        cols.f[r] = node.f
        cols.wave_out[r] = node.wave_out
        cols.wave_in[r] = node.wave_in
        cols.energy_sent[r] = node.energy_sent
        cols.energy_played[r] = node.energy_played
        cols.energy_margin_observed[r] = node.guard.margin
        cols.energy_played_epoch[r] = node.guard.played_in_epoch
        c.play_time[r] = t
        c.rx_seq[r] = node.last_rx_seq
        c.send_phase[r] = send_phase
        c.peer_epoch[r] = node.peer_restarts
        c.controller_ticks[r] = node.guard.report.controller_active_ticks
        if self._state_every and k % self._state_every == 0:
            c.device_state.append((k, self._state()))
        if self.first < 0:
            self.first = k
        self.last = max(self.last, k)
        self.ticks_run += 1

    def sent(self, k: int, t: float) -> None:
        c, r = self._at(k)
        c.send_time[r] = t

    def lateness(self, k: int, late_ns: int) -> None:
        c, r = self._at(k)
        c.lateness_ns[r] = late_ns

    def _finish_pending(self) -> None:
        if self._pending is not None:
            for _ in self._pending:
                pass
            self._pending = None

    def _seal(self, c: Chunk, cols: _Columns, next_k: int | None) -> None:
        for _ in self._seal_steps(c, cols, next_k):
            pass

    def _seal_steps(self, c: Chunk, cols: _Columns, next_k: int | None) -> Iterator[None]:
        """Baseline of the chunk's ticks (and of ticks skipped before ``next_k``), the sliding
        compression window, then the chunk (its byte columns from ``cols``) to the sink: three
        steps, a ``yield`` between two (:meth:`settle` runs one at a time)."""
        cols.store_bytes(c)
        if self.first >= 0:
            # The session goes on (next_k): every tick to the chunk's end counts; else to the last run.
            hi = c.k0 + c.size - 1 if next_k is not None else self.last
            lo = max(self.first, c.k0)
            if hi >= lo:
                ks = np.arange(lo, hi + 1)
                wire = self.tx.baseline_bulk(self._baseline(ks), self.raw_payload_len)
                c.n = max(c.n, hi - c.k0 + 1)
                c.bytes["tx_baseline_wire"][lo - c.k0 : hi - c.k0 + 1] = wire
                c.bytes["tx_baseline_payload"][lo - c.k0 : hi - c.k0 + 1] = self.raw_payload_len
            gap_end = (next_k - next_k % self.chunk_ticks) if next_k is not None else 0
            for a in range(c.k0 + c.size, gap_end, 1 << 20):  # whole chunks a stall skipped: totals only
                ks = np.arange(a, min(a + (1 << 20), gap_end))
                self.tx.baseline_bulk(self._baseline(ks), self.raw_payload_len)
        yield
        # The sliding window starts at this side's first tick: rows before it (a late joiner, or a
        # loop whose first ticks a stall skipped) carry neither baseline nor traffic.
        b, n = c.bytes, c.n
        r0 = min(max(self.first - c.k0, 0), n) if self.first >= 0 else n
        self.tx.window(
            b["tx_baseline_wire"][r0:n],
            b["tx_wire"][r0:n],
            b["tx_baseline_payload"][r0:n],
            b["tx_payload"][r0:n],
        )
        yield
        self.sink.write(c)

    def seal(self) -> None:
        """The session is over: the current chunk to the sink (once)."""
        self._finish_pending()
        if self.chunk is not None:
            self._seal(self.chunk, self._cols, None)
            self.chunk = None
        self._next = None


class Port:
    """One side of a session, sans-I/O: node, shim, counters, link observer, recorder, summary.

    ``sink`` takes the per-tick record a chunk at a time (default: kept in memory, a
    :class:`MemorySink`); ``window_ticks`` is the sliding window of the minimum instantaneous
    compression.  ``shim`` sits between the node and the socket: what it drops never reaches the
    socket (and is not counted as sent); what it duplicates is sent and counted twice.  ``peer_spec`` is the
    impairment configured for the incoming direction, echoed in the link figures.
    """

    def __init__(
        self,
        node: Node,
        *,
        ticks: int | None = None,
        shim: Link | None = None,
        peer_spec: str = "",
        header_bytes: int = UDP_IPV4_HEADER,
        first_tick: int = 0,
        keys: PortKeys | None = None,
        playout_floor: int = 0,
        playout_hold: bool = True,
        sink: ChunkSink | None = None,
        window_ticks: int = 100,
        phase: float = 0.5,
    ) -> None:
        self.node = node
        node.datagram_overhead = auth.OVERHEAD + header_bytes
        if keys is None:  # the simulation: the insecure key, fixed nonces (same bytes as a real run)
            nonce = bytes(auth.NONCE_BYTES)
            keys = port_keys(auth.INSECURE_KEY, node.tx_direction, node.session, nonce, nonce)
        self.keys = keys
        self.security = SecurityCounters()
        self._seen = auth.SeenTags(protocol.SEEN_TAGS)  # handshake datagrams have no replay window
        self.ticks = ticks  # the session's length when fixed (informative: nothing is sized by it)
        self.dt = node.dt
        self.shim = shim
        self.tx = DirectionCounters(header_bytes, window_ticks)
        self.rx = DirectionCounters(header_bytes, window_ticks)
        self.observer = LinkObserver(peer_spec, joined_late=first_tick > 0)
        self.raw_payload_len = packed_size(node.wave.dof, RAW_BITS)
        # ``auto`` keeps at least ``playout_floor`` ticks of allowance: the real-time runner asks for
        # one (its loops and transport jitter by a fraction of a tick; the simulation by none).
        # ``playout_hold=False``: a replay, whose deliveries are the run's plays (PlayoutBuffer).
        self.playout = PlayoutBuffer(
            node.options.playout, node.dt, auto_floor=playout_floor, hold=playout_hold
        )
        # A replay's send phase per tick (a real run's record, ``send_phase``; -1: the buffer's target).
        self.replay_phases: npt.NDArray[np.int64] | None = None
        # Where the peer's packets land on our tick grid: the teleoperator's phase follows it (it
        # ticks when the operator's packet is due), and either side's tick 0 moves if it lies.
        teleoperator = node.tx_direction == wire.BACKWARD
        self.clock = ClockTracker(node.dt, phase if teleoperator else 0.0, moves_phase=teleoperator)
        self.sink: ChunkSink = sink if sink is not None else MemorySink()
        self.rec = Recorder(node.wave.dof, self.sink, self.tx, self.rx, self._baseline, self.raw_payload_len)
        self.rec.watch(node.device)
        self.control_rejected = 0  # control messages that did not parse (counted, dropped)
        self.last_control_error = ""
        self._last_k = 0

    def confine(self, env: Envelope) -> None:
        """Run this (robot's) port inside ``env``: its node's saturation and guard
        (:meth:`teleop.session.node._Node.confine`), and the longest it acts after its operator's
        last packet within ``env.max_act_alone_ms``: playout + silence + fade
        (:func:`teleop.session.settings.acting_alone`; the silence is the node's own).  The fade is
        shortened to fit, and ``auto``'s allowance capped at what is left; a fixed playout the
        envelope check already held within the cap."""
        node = self.node
        node.confine(env)
        cap = env.max_act_alone_ms * 1e-3
        playout = self.playout.fixed * node.dt
        fade = min(node.options.fade_time, cap - playout - node.link_timeout)
        node.fade_within(max(fade, MIN_FADE_S))
        if self.playout.mode == "auto":
            left = cap - node.link_timeout - max(fade, MIN_FADE_S)
            self.playout.max_extra = min(self.playout.max_extra, max(0, math.floor(left / node.dt + 1e-9)))

    # --- inbound -------------------------------------------------------------------------
    def receive(
        self,
        data: bytes,
        t: float,
        k: int,
        play: bool = True,
        from_peer: bool = True,
        clock: float | None = None,
    ) -> protocol.Message | None:
        """Take one datagram that arrived at session time ``t`` during tick ``k``.

        Authenticate it first; then data packets are counted, shown to the link observer, checked
        against the replay window and (with ``play``) handed to the node; a control message is
        parsed and returned for the session logic.  Anything else is counted and dropped.  A
        datagram from another address (``from_peer`` False) may only be a handshake message.
        ``clock``: the arrival on the receiver's monotonic clock (s), which the replay window's jump
        bound runs on (PROTOCOL.md 2.4: the handshake's clock, not the session's, whose tick 0 may
        move); ``t`` if not given (one clock throughout, as in ``teleop sim``).  Never raises.
        """
        mono = t if clock is None else clock
        sec = self.security
        hdr = auth.peek(data)
        if hdr is not None and hdr[0] == auth.HANDSHAKE:
            body = self.open_handshake(data)
            return None if body is None else self._control(body, auth.HANDSHAKE)
        try:
            if hdr is None:
                raise auth.AuthError("header", NOT_AN_ENVELOPE)
            if not from_peer:
                raise auth.AuthError("kind", FOREIGN_SESSION_DATAGRAM)
            counter, body = self.keys.rx.verify(data)
        except auth.AuthError as e:
            if e.reason == "replay":
                sec.replayed += 1
            else:
                sec.rejected += 1
                sec.last_rejection = str(e)
            return None
        k = max(k, 0)
        if body[:1] != b"\x9a":  # not a 10-element msgpack array: a control message
            return self._control(body, auth.SESSION) if self._accept(counter, mono) else None
        node = self.node
        try:
            pkt = wire.decode(body)
        except wire.WireError as e:  # authentic but malformed: a bug at the peer, counted
            self.rx.packet(k, len(data), None)
            node.malformed(str(e))
            return None
        self.rx.packet(k, len(data), len(pkt.payload))
        ours = pkt.session == node.session and pkt.direction == node.rx_direction
        if ours:
            self.observer.observe(t, pkt.seq, pkt.t_us / 1e6, len(data))
        if not self._accept(counter, mono):
            return None
        if ours:
            self.clock.observe(k, t - pkt.tick * self.dt)
        if play:
            for p in self.playout.add(pkt, k) if node.takes(pkt) else [pkt]:
                node.receive_packet(p)
        return None

    def open_handshake(self, data: bytes) -> bytes | None:
        """The body of an authentic handshake-key datagram not seen before, or None (counted)."""
        try:
            body = self.keys.hs_rx.verify(data)[1]
            self._seen.check(data)  # a byte-identical copy is a replay: dropped before parsing
        except auth.AuthError as e:
            if e.reason == "replay":
                self.security.replayed += 1
            else:
                self.security.rejected += 1
                self.security.last_rejection = str(e)
            return None
        return body

    def control(self, body: bytes) -> protocol.Message | None:
        """An authentic handshake-key body parsed (:meth:`open_handshake`'s), or None (counted)."""
        return self._control(body, auth.HANDSHAKE)

    def refuse_foreign(self, envelope: bool) -> None:
        """Count a datagram from another address that is not a handshake datagram (``envelope``:
        it has an envelope's header) as :meth:`receive` would, without raising: the endpoint's
        cheap path for a flood of junk (``Endpoint._session_datagram``)."""
        sec = self.security
        sec.rejected += 1
        sec.last_rejection = FOREIGN_SESSION_DATAGRAM if envelope else NOT_AN_ENVELOPE

    def verifies(self, data: bytes) -> bool:
        """Whether ``data`` is an authentic session datagram of this session's peer (no state change)."""
        try:
            self.keys.rx.verify(data)
        except auth.AuthError:
            return False
        return True

    def _accept(self, counter: int, t: float) -> bool:
        """The replay window's verdict on an authentic datagram (RFC 3711 3.3.2), counted."""
        try:
            self.keys.rx.accept(counter, t)
        except auth.AuthError as e:
            if e.reason == "jump":
                self.security.counter_jumps += 1
            else:
                self.security.replayed += 1
            return False
        return True

    def _control(self, body: bytes, key_kind: int) -> protocol.Message | None:
        """Parse an authentic control message; one under the wrong key is refused."""
        try:
            msg = protocol.parse(body)
        except protocol.ProtocolError as e:
            self.control_rejected += 1
            self.last_control_error = str(e)
            return None
        handshake_msg = isinstance(msg, protocol.HANDSHAKE_KINDS)
        if handshake_msg != (key_kind == auth.HANDSHAKE):
            self.control_rejected += 1
            self.last_control_error = f"a {msg.kind} under the wrong key"
            return None
        return msg

    def seal(self, msg: protocol.Message) -> bytes:
        """A control message as a datagram, under the key its kind travels with."""
        handshake_msg = isinstance(msg, protocol.HANDSHAKE_KINDS)
        return (self.keys.hs_tx if handshake_msg else self.keys.tx).seal(protocol.encode(msg))

    def peer_restarted(self, peer_nonce: bytes) -> None:
        """The peer process was replaced mid-session: session keys from its new nonce (a fresh
        replay window; our counter goes on), a new energy epoch and fresh link figures (they cover
        the current peer; its sequence numbers start again from 0)."""
        keys, node = self.keys, self.node
        nonces = (keys.nonce, peer_nonce) if node.tx_direction == wire.FORWARD else (peer_nonce, keys.nonce)
        new = port_keys(keys.psk, node.tx_direction, node.session, *nonces, counter=keys.tx.counter)
        keys.tx, keys.rx = new.tx, new.rx
        self.playout.clear()
        self.clock = ClockTracker(self.dt, self.clock.phase, self.clock.moves_phase)  # another peer's
        node.peer_restarted()
        self.observer = LinkObserver(self.observer.spec)

    # --- per tick ------------------------------------------------------------------------
    def tick(self, k: int, t: float) -> list[bytes]:
        """Run tick ``k`` (node time ``k dt``) at session time ``t``; the datagrams to send now."""
        node = self.node
        for p in self.playout.due(k):  # the payloads whose playout time has come
            node.receive_packet(p)
        phase = -1
        if node.tx_direction == wire.BACKWARD:
            d = self.playout.target()
            if (rp := self.replay_phases) is not None and 0 <= k < len(rp) and rp[k] >= 0:
                d = int(rp[k])  # a replay: the phase the run's teleoperator sent at
            if d is not None:
                node.encoder.phase = phase = d  # send phase: sample right after the operator's payload plays
        pkt = node.tick(k * self.dt)
        out: list[bytes] = []
        produced = None
        if pkt is not None:
            data = self.keys.tx.seal(wire.encode(pkt))
            produced = (len(pkt.payload), len(data), pkt.seq)
            if self.shim is None:
                self.tx.packet(k, len(data), len(pkt.payload))
                out.append(data)
            else:
                self.shim.send(t, data)
        if self.shim is not None:
            out += self.flush(t, k)
        self.rec.record(k, t, node, produced, phase)
        self._last_k = k
        return out

    def sent(self, k: int, t: float) -> None:
        """Tick ``k``'s sample was produced by session time ``t``, before its datagrams left (for the
        true energy margin of ``teleop.offline.report``)."""
        self.rec.sent(k, t)

    def settle(self) -> None:
        """What may wait until the tick's datagrams left: the real-time runner calls it after each
        send (the record's chunk seal, :attr:`Recorder.defer`)."""
        self.rec.settle()

    def loop_timing(self, k: int, lateness_ns: int) -> None:
        """How late the real-time loop started tick ``k`` (recorded with the tick)."""
        self.rec.lateness(k, lateness_ns)

    # --- the node's link, for the endpoint (it never reaches into the node) ---------------------
    @property
    def link_lost(self) -> bool:
        """The peer's packets stopped for the link timeout (or never came by their due time)."""
        return self.node.link_lost

    @property
    def heard_from_peer(self) -> bool:
        """At least one of the peer's packets was accepted in this session."""
        return self.node.counters.accepted > 0

    def joined_late(self) -> None:
        """This side joined a running session: its energy budget starts at the first packet."""
        self.node.joined_late()

    def expect_first_by(self, t: float, *, lost_at: bool = False) -> None:
        """The peer's first packet is due by session time ``t``; ``lost_at``: rather, the link is
        lost at ``t`` if none came (the node counts its link timeout from when it was due)."""
        self.node.expect_first_by(t - self.node.link_timeout if lost_at else t)

    def paced_device(self) -> Any:
        """The device that paces the ticks (a real arm: ``paced`` and a ``wait``), or None."""
        dev = getattr(self.node, "device", None)
        return dev if getattr(dev, "paced", False) is True and callable(getattr(dev, "wait", None)) else None

    def payload_ready(self, k: int) -> bool:
        """Whether tick ``k``'s payload is here: due from the playout buffer or queued in the decoder,
        from a payload whose ticks ``tick + d .. tick + d + P - 1`` reach ``k``.  A payload taken late
        (all its ticks before ``k``: held for release at once, or what is left of it) is not: taken
        as ready, it let the loop run tick ``k`` before the payload due at ``k`` came, which then
        came late too, and so on: a slip of one tick for good (measured: most of a real session at
        one tick more).  Grace waits for it instead (PROTOCOL.md 5.2)."""
        node, playout = self.node, self.playout
        if not playout.pending(k) and node.decoder.queued == 0:
            return False
        d = playout.target()
        if d is None:
            return True
        return k < max(node.last_rx_tick, playout.newest_tick) + d + node.rx_codec.k

    def next_due(self) -> float | None:
        """Session time at which the shim next has a datagram due (None: nothing held)."""
        return self.shim.next_due() if self.shim is not None else None

    def flush(self, t: float, k: int) -> list[bytes]:
        """What the shim says is due at ``t``, counted as sent during tick ``k``."""
        if self.shim is None:
            return []
        out = self.shim.due(t)
        k = max(k, 0)
        for data in out:
            try:
                payload_len: int | None = len(wire.decode(data[auth.HEADER_BYTES : -auth.TAG_BYTES]).payload)
            except wire.WireError:  # corrupted by the shim on purpose
                payload_len = None
            self.tx.packet(k, len(data), payload_len)
        return out

    # --- results -------------------------------------------------------------------------
    def _baseline(self, ks: npt.NDArray[np.int64]) -> npt.NDArray[np.int64]:
        """Datagram sizes of the uncompressed stream at ticks ``ks`` (closed form, never encoded)."""
        us = round(self.dt * 1e6)
        sizes: npt.NDArray[np.int64] = (
            wire.packet_size(self.node.session, ks, ks, ks * us, self.raw_payload_len) + auth.OVERHEAD
        )
        return sizes

    def finish(self) -> None:
        """The session is over: the last chunk of the record goes to the sink (idempotent)."""
        self.rec.seal()

    def produced(self) -> int:
        """Packets the node produced (before the shim): what the peer's loss is counted against."""
        return self.node.seq

    def shim_stats(self) -> dict[str, Any] | None:
        return asdict(self.shim.stats) if self.shim is not None else None

    def summary(self, peer_produced: int | None = None, peer_dropped_by_limit: int = 0) -> dict[str, Any]:
        """This side's figures: what it sent and received, the link it observed, its watchdog.

        ``peer_produced``: the peer's packet count, when known (its bye, or the sim's other port),
        so the loss covers packets lost after the last one that arrived.
        """
        self.finish()
        node = self.node
        tx_dir = node.tx_direction
        return {
            "sent": {"direction": wire.DIRECTIONS[tx_dir], **self.tx.summary()},
            "received": {"direction": wire.DIRECTIONS[1 - tx_dir], **self.rx.summary()},
            "link_received": self.observer.summary(
                sent=peer_produced, dropped_by_limit=peer_dropped_by_limit
            ),
            "rate_cap": self._rate_cap_summary(),
            "playout": self.playout.summary(),
            "clock": self.clock.summary(),
            "control_rejected": self.control_rejected,
            "security": {
                **asdict(self.security),
                "energy_reports_clamped": node.passivity.energy_reports_clamped,
            },
            "node": {
                **node.counters.as_dict(),
                "last_error": node.last_error,
                "decoder_underruns": node.decoder.underruns,
                "decoder_dropped_samples": node.decoder.dropped_samples,
            },
            "passivity": {"direction": wire.DIRECTIONS[1 - tx_dir], **node.passivity.as_dict()},
            "energy": {
                "sent": node.energy_sent,
                "played": node.energy_played,
                "peer_reported_sent": node.peer_energy_sent,
            },
            "device": devices.summary_of(node.device, node.device_spec),
        }

    def _rate_cap_summary(self) -> dict[str, Any] | None:
        """The cap on what this side sends, and whether it held on the wire (``teleop.control.ratecap``)."""
        cap = self.node.rate_cap
        if cap is None:
            return None
        peak = self.tx.peak_window_wire_bytes
        same_window = self.tx.window_ticks == cap.window  # else the counters' window is another
        return {
            "bps": cap.rate_bps,
            "window_ms": cap.window * self.dt * 1e3,
            "limit_bytes_per_window": cap.limit_bytes,
            "peak_bytes_per_window": peak,
            "held_back": cap.held_back,
            "held": bool(peak <= cap.limit_bytes + 1e-9) if same_window else None,
        }


def wire_block(sent: dict[str, Any], received: dict[str, Any]) -> dict[str, Any]:
    """One direction's wire figures: the sender's ``sent`` summary and the receiver's ``received``."""
    out = {k: sent[k] for k in WIRE_KEYS[:10]}
    out.update(
        received_packets=received["packets"],
        received_wire_bytes=received["wire_bytes"],
        received_payload_bytes=received["payload_bytes"],
        received_malformed=received["malformed"],
        lost=sent["packets"] - received["packets"],
    )
    return out
