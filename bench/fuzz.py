"""Hostile datagrams against a live session: both processes under a blind and an on-path attacker.

A teleoperator and an operator run as two real processes on 127.0.0.1 (UDP) under one pre-shared
key; an attacker in this process sends them ``--datagrams`` hostile datagrams at ``--rate`` per
second, then the logs say what the two processes made of it (``teleop.offline.report.build``).

* **Blind**: a plain UDP socket bound to 127.0.0.1, sending from its own address.
* **On-path** (needs CAP_NET_RAW, i.e. root): an AF_PACKET socket on ``lo`` (ETH_P_ALL, with a BPF
  filter for the two session ports) sniffs the genuine datagrams, and a raw IPv4 socket
  (IPPROTO_RAW, so IP_HDRINCL) sends forgeries whose *source* is the genuine peer's address and
  port, with the learnt session id, sequence numbers and counters.  The attacker's IPv4 TTL is
  :data:`MARK_TTL`, so its sniffer never mistakes its own forgeries for the genuine traffic.  If
  either socket is refused, that part is skipped and the JSON says why.

Classes (:data:`CLASSES`), each counted per route (blind / spoofed) and target: random bytes
(0..1500), random bytes behind a plausible envelope header, truncated and bit-flipped genuine
datagrams, "re-CRC'd" forgeries (a valid ``teleop.session.wire`` packet with full-scale payload and an
energy of 1e300 or a far-future seq, correct CRC-32, sealed with a wrong key or the insecure key),
exact replays, genuine datagrams with the counter rewritten far ahead, oversized datagrams (up to
65000 bytes), handshake messages with every field wrong (sealed with a wrong or the insecure key),
and replays of datagrams recorded in an earlier session under the same key (the baseline run).

A baseline session of the same length runs first, without the attack, so the loops' period error
is compared in one invocation.  Every datagram goes to 127.0.0.1 only (:func:`_loopback`), the
attack is bounded in count and time and stops by itself.

    python -m bench.fuzz [--datagrams N] [--rate R] [--duration S] [--out FILE] [--transport udp]

Writes JSON (default ``bench/results/fuzz.json``) and prints a summary; exit status 1 if a check
failed (a crash, an unfinished session, energy played beyond what was sent, a forgery accepted).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import math
import os
import platform
import random
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import zlib
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack

from bench import write_result
from teleop.session import auth, protocol, wire
from teleop.session.protocol import PROTOCOL_VERSION, SessionParams

LOOPBACK = "127.0.0.1"
_LOOPBACK_BYTES = socket.inet_aton(LOOPBACK)
TELEOP = [sys.executable, "-m", "teleop.cli"]
ROLES = ("operator", "teleoperator")
#: Where each role's datagrams go (the target) -> the direction of the datagrams it receives.
RX_DIRECTION = {"teleoperator": wire.FORWARD, "operator": wire.BACKWARD}
ROUTES = ("blind", "spoofed")
CLASSES = (
    "random",
    "random_enveloped",
    "truncated",
    "bitflip",
    "recrc_forgery",
    "replay",
    "counter_ahead",
    "oversized",
    "bad_handshake",
    "old_session_replay",
)
#: Classes made from captured genuine datagrams: sent only when sniffing works.
CAPTURE_CLASSES = frozenset({"truncated", "bitflip", "replay", "counter_ahead"})
MAX_DATAGRAM = 1500  # random datagrams: 0..1500 bytes
MAX_OVERSIZED = 65000
#: IPv4 TTL of every spoofed datagram: the sniffer's filter drops these, so a forgery is never
#: taken for a genuine datagram (genuine loopback traffic has Linux's default, 64).
MARK_TTL = 99
ETH_P_ALL = 0x0003
ETH_HLEN = 14
SO_ATTACH_FILTER = 26
SOL_PACKET = 263
PACKET_STATISTICS = 6
PACKET_HOST = 0
DEFAULT_DATAGRAMS = 1_000_000
DEFAULT_RATE = 40_000.0
SETTLE_S = 4.0  # session seconds beyond the attack: handshake, start, and a calm end


def _loopback(host: str) -> str:
    """The only destination this module ever sends to: anything else is a bug, refused loudly."""
    if host != LOOPBACK:
        raise ValueError(f"bench.fuzz sends to {LOOPBACK} only, not {host!r}")
    return host


# --------------------------------------------------------------------------------------------
# what an on-path attacker learns
# --------------------------------------------------------------------------------------------
@dataclass
class Learned:
    """Fields of one direction's genuine traffic, read from the (authenticated, not encrypted) bodies."""

    session: int | None = None
    codec_id: int = 2
    payload_len: int = 4
    seq: int = 0
    tick: int = 0
    t_us: int = 0
    counter: dict[int, int] = field(default_factory=lambda: {auth.HANDSHAKE: 0, auth.SESSION: 0})


class Capture:
    """Genuine datagrams seen on the wire, per sender direction (thread-safe enough: appends and
    attribute stores under the GIL).  Filled by :class:`Sniffer`, or directly by a test."""

    def __init__(self, keep: int = 256, record: int = 4096) -> None:
        self.recent: dict[int, deque[bytes]] = {d: deque(maxlen=keep) for d in (0, 1)}
        self.control: dict[int, deque[bytes]] = {d: deque(maxlen=64) for d in (0, 1)}
        self.record: deque[tuple[int, bytes]] = deque(maxlen=record)  # for a later session's replay
        self.learned = {d: Learned() for d in (0, 1)}
        self.count = {0: 0, 1: 0}
        self.first_data_ns: int | None = None
        # From the hello's and the welcome's bodies (authenticated, not encrypted): what the session
        # keys are derived from, besides the pre-shared key (session id, operator's and TO's nonces).
        self.nonces: dict[int, bytes] = {}
        self.hs_session: int | None = None

    @property
    def key_context(self) -> tuple[int, bytes, bytes] | None:
        """(session, nonce_op, nonce_to) of the captured handshake, once both nonces were seen."""
        if self.hs_session is None or len(self.nonces) < 2:
            return None
        return self.hs_session, self.nonces[0], self.nonces[1]

    def add(self, direction: int, data: bytes) -> None:
        """A genuine datagram sent in ``direction`` (0: operator -> teleoperator)."""
        self.count[direction] += 1
        self.record.append((direction, data))
        hdr = auth.peek(data)
        if hdr is None:
            return
        kind, _, counter = hdr
        learned = self.learned[direction]
        learned.counter[kind] = max(learned.counter[kind], counter)
        body = data[auth.HEADER_BYTES : -auth.TAG_BYTES]
        if kind == auth.SESSION and body[:1] == b"\x9a":
            self.recent[direction].append(data)
            try:
                pkt = wire.decode(body)
            except wire.WireError:
                return
            learned.session, learned.codec_id, learned.payload_len = (
                pkt.session,
                pkt.codec_id,
                len(pkt.payload),
            )
            learned.seq, learned.tick, learned.t_us = max(learned.seq, pkt.seq), pkt.tick, pkt.t_us
            if self.first_data_ns is None:
                self.first_data_ns = time.monotonic_ns()
        else:
            self.control[direction].append(data)
            if kind == auth.HANDSHAKE:
                self._learn_handshake(direction, body)

    def _learn_handshake(self, direction: int, body: bytes) -> None:
        try:
            msg = protocol.parse(body)
        except protocol.ProtocolError:
            return
        if isinstance(msg, protocol.Hello) and direction == wire.FORWARD:
            self.nonces[0], self.hs_session = msg.nonce, msg.params.session
        elif isinstance(msg, protocol.Welcome) and direction == wire.BACKWARD:
            self.nonces[1] = msg.nonce

    def has(self, direction: int) -> bool:
        return bool(self.recent[direction] or self.control[direction])

    def pick(self, rng: random.Random, direction: int) -> bytes | None:
        """A captured genuine datagram of ``direction``: mostly data, sometimes control."""
        data, control = self.recent[direction], self.control[direction]
        pool = control if control and (not data or rng.random() < 0.2) else data
        return pool[rng.randrange(len(pool))] if pool else None


# --------------------------------------------------------------------------------------------
# on-path sockets: sniffing and spoofing (root only)
# --------------------------------------------------------------------------------------------
def _bpf_ports(port_a: int, port_b: int) -> bytes:
    """A classic BPF program: incoming copies (PACKET_HOST) of unfragmented IPv4/UDP datagrams
    between ``port_a`` and ``port_b`` whose TTL is not :data:`MARK_TTL` (not ours)."""
    accept, drop = 17, 18  # instruction indices below
    prog: list[tuple[int, int, int, int]] = []

    def ins(code: int, k: int, jt: int = 0, jf: int = 0) -> None:
        prog.append((code, jt, jf, k))

    def to(target: int) -> int:  # a jump offset from the next instruction
        return target - len(prog) - 1

    ins(0x20, 0xFFFFF004)  # 0 ld [SKF_AD_OFF + SKF_AD_PKTTYPE]
    ins(0x15, PACKET_HOST, 0, to(drop))  # 1 jeq PACKET_HOST (loopback shows each datagram twice)
    ins(0x28, 12)  # 2 ldh [12] ethertype
    ins(0x15, 0x0800, 0, to(drop))  # 3 IPv4
    ins(0x30, ETH_HLEN + 9)  # 4 ldb protocol
    ins(0x15, socket.IPPROTO_UDP, 0, to(drop))  # 5 UDP
    ins(0x30, ETH_HLEN + 8)  # 6 ldb ttl
    ins(0x15, MARK_TTL, to(drop), 0)  # 7 our own forgeries: drop
    ins(0x28, ETH_HLEN + 6)  # 8 ldh flags | fragment offset
    ins(0x45, 0x1FFF, to(drop), 0)  # 9 jset: a fragment
    ins(0xB1, ETH_HLEN)  # 10 ldxb 4*([14]&0xf): the IPv4 header length
    ins(0x48, ETH_HLEN)  # 11 ldh [x+14] source port
    ins(0x15, port_a, 1, 0)  # 12
    ins(0x15, port_b, 0, to(drop))  # 13
    ins(0x48, ETH_HLEN + 2)  # 14 ldh [x+16] destination port
    ins(0x15, port_a, to(accept), 0)  # 15
    ins(0x15, port_b, 0, to(drop))  # 16 falls through to accept
    assert len(prog) == accept
    ins(0x06, 0x40000)  # 17 accept (snap 256 KiB)
    ins(0x06, 0)  # 18 drop
    assert len(prog) == drop + 1
    return b"".join(struct.pack("HBBI", *p) for p in prog)


class Sniffer(threading.Thread):
    """Captures the genuine datagrams between two UDP ports on ``lo`` into a :class:`Capture`.

    ``direction_of[src_port]`` says which direction a datagram from that port travels."""

    def __init__(self, capture: Capture, direction_of: dict[int, int]) -> None:
        super().__init__(name="bench.fuzz sniffer", daemon=True)
        self.capture = capture
        self.direction_of = dict(direction_of)
        a, b = direction_of
        sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
        try:
            code = _bpf_ports(a, b)
            self._prog = ctypes.create_string_buffer(code)  # kept alive while attached
            fprog = struct.pack("HL", len(code) // 8, ctypes.addressof(self._prog))
            sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)
            sock.bind(("lo", 0))
            sock.settimeout(0.1)
        except OSError:
            sock.close()
            raise
        self.sock = sock
        self._halt = threading.Event()
        self.ignored = 0  # what got past the filter but is not a datagram between the two ports

    def run(self) -> None:
        while not self._halt.is_set():
            try:
                frame, addr = self.sock.recvfrom(1 << 17)
            except TimeoutError:
                continue
            except OSError:
                return
            got = self._parse(frame, addr[2]) if addr[0] == "lo" else None
            if got is None:
                self.ignored += 1
            else:
                self.capture.add(*got)

    def _parse(self, frame: bytes, pkttype: int) -> tuple[int, bytes] | None:
        """(direction, UDP payload) of a genuine datagram between the two ports, else None."""
        ip = frame[ETH_HLEN:]
        if pkttype != PACKET_HOST or len(ip) < 28 or ip[0] >> 4 != 4 or ip[9] != socket.IPPROTO_UDP:
            return None
        if ip[8] == MARK_TTL:
            return None
        ihl = (ip[0] & 0x0F) * 4
        src, dst, length = struct.unpack_from("!HHH", ip, ihl)
        if src not in self.direction_of or dst not in self.direction_of or src == dst:
            return None
        return self.direction_of[src], bytes(ip[ihl + 8 : ihl + length])

    def stats(self) -> dict[str, int]:
        """The kernel's count of frames this socket received and dropped (PACKET_STATISTICS)."""
        try:
            raw = self.sock.getsockopt(SOL_PACKET, PACKET_STATISTICS, 8)
            packets, drops = struct.unpack("II", raw)
        except OSError:
            return {}
        return {"frames": packets, "kernel_drops": drops}

    def stop(self) -> None:
        self._halt.set()
        self.join(timeout=2)
        self.sock.close()


class Spoofer:
    """Sends UDP datagrams with any 127.0.0.1 source port, through a raw IPv4 socket (IP_HDRINCL)."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_RAW)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
        self._id = 0

    def send(self, payload: bytes, src_port: int, dst_port: int) -> None:
        """IPv4 (TTL :data:`MARK_TTL`) + UDP (checksum 0: none) + payload, 127.0.0.1 to 127.0.0.1."""
        self._id = (self._id + 1) & 0xFFFF
        ip = struct.pack(
            "!BBHHHBBH4s4s",
            0x45,
            0,
            28 + len(payload),
            self._id,
            0,
            MARK_TTL,
            socket.IPPROTO_UDP,
            0,  # the kernel fills in the IPv4 checksum (raw(7))
            _LOOPBACK_BYTES,
            _LOOPBACK_BYTES,
        )
        udp = struct.pack("!HHHH", src_port, dst_port, 8 + len(payload), 0)
        self.sock.sendto(ip + udp + payload, (_loopback(LOOPBACK), 0))

    def close(self) -> None:
        self.sock.close()


def probe_on_path() -> dict[str, Any]:
    """Whether this process can sniff ``lo`` and send datagrams with a forged source, measured:
    a spoofed datagram must arrive at a socket of ours with the forged source address, and a
    plain datagram between two sockets of ours must be captured."""
    out: dict[str, Any] = {"uid": os.getuid(), "sniff": False, "spoof": False, "notes": []}
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    fake = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # holds the forged source port
    rx.bind((LOOPBACK, 0))
    fake.bind((LOOPBACK, 0))
    rx.settimeout(1.0)
    rx_port, fake_port = rx.getsockname()[1], fake.getsockname()[1]
    try:
        try:
            spoofer = Spoofer()
        except OSError as e:
            out["notes"].append(f"raw IPv4 socket refused ({e.strerror or e}): no spoofed source")
        else:
            try:
                spoofer.send(b"bench.fuzz probe", fake_port, rx_port)
                data, addr = rx.recvfrom(2048)
                out["spoof"] = data == b"bench.fuzz probe" and addr == (LOOPBACK, fake_port)
            except OSError as e:
                out["notes"].append(f"spoofed probe did not arrive ({e.strerror or e})")
            finally:
                spoofer.close()
        capture = Capture()
        try:
            sniffer = Sniffer(capture, {fake_port: 0, rx_port: 1})
        except OSError as e:
            out["notes"].append(f"AF_PACKET socket on lo refused ({e.strerror or e}): no sniffing")
        else:
            sniffer.start()
            try:
                fake.sendto(b"bench.fuzz sniff probe", (_loopback(LOOPBACK), rx_port))
                rx.recvfrom(2048)
                deadline = time.monotonic() + 1.0
                while not capture.record and time.monotonic() < deadline:
                    time.sleep(0.01)
                out["sniff"] = any(d == b"bench.fuzz sniff probe" for _, d in capture.record)
                if not out["sniff"]:
                    out["notes"].append("the sniffer saw nothing on lo")
            except OSError as e:
                out["notes"].append(f"sniff probe failed ({e.strerror or e})")
            finally:
                sniffer.stop()
    finally:
        rx.close()
        fake.close()
    return out


# --------------------------------------------------------------------------------------------
# hostile datagrams
# --------------------------------------------------------------------------------------------
_HOSTILE_VALUES: tuple[Any, ...] = (
    math.inf,
    -math.inf,
    math.nan,
    1e308,
    -1.0,
    0,
    -1,
    -(2**63),
    2**64 - 1,
    2**32,
    True,
    None,
    "",
    "x" * 5000,
    "trace /etc/shadow",
    "trace /dev/zero",
    "delay 1e309ms",
    "loss 200%",
    b"\x00" * 16,
    b"\xff" * 4097,
    [],
    [1, 2, 3],
    {},
    {"a": {"b": {"c": []}}},
)


def _hello_fields(session: int) -> dict[str, Any]:
    p = SessionParams(
        session=session, codec="eds:50", scenario="protocol", dof=2, b=20.0, full_scale=16.0, duration=30.0
    )
    return {"t": "hello", "v": PROTOCOL_VERSION, "t_ns": 1, "nonce": bytes(16), **p.to_msg()}


def hostile_control_bodies(rng: random.Random, session: int = 1, count: int = 400) -> list[bytes]:
    """Control messages (msgpack maps) with wrong fields: each field of a hello set to each hostile
    value, netem specs naming /etc/shadow, wrong versions and kinds, everything wrong at once, and
    welcomes, rejects, starts and byes with hostile values.  Deterministic for a given ``rng``."""
    base = _hello_fields(session)
    bodies: list[bytes] = []

    def add(m: dict[Any, Any]) -> None:
        body = msgpack.packb(m, use_bin_type=True)
        try:
            protocol.parse(body)
        except protocol.ProtocolError:
            bodies.append(body)  # only messages a receiver must refuse (a mutation may be valid)

    for name in base:
        for v in _HOSTILE_VALUES:
            add({**base, name: v})
    for v in (0, 2, -1, 255, 2**64 - 1, "1", 1.0, None):
        add({**base, "v": v})
    for spec in ("trace /etc/shadow", "trace /dev/zero", "trace /proc/self/mem", "trace ../../etc/passwd"):
        add({**base, "netem_forward": spec})
        add({**base, "netem_backward": spec, "v": 2})
    for kind in ("welcome", "reject", "start", "started", "bye", "HELLO", "", "x" * 300):
        m = {k: rng.choice(_HOSTILE_VALUES) for k in ("session", "t_ns", "t2", "t3", "nonce", "why")}
        add({"t": kind, "v": PROTOCOL_VERSION, **m, "start_ns": -1, "produced": 2**64 - 1})
    while len(bodies) < count:  # everything wrong at once
        add({k: rng.choice(_HOSTILE_VALUES) for k in base})
    return bodies


class Forge:
    """Makes one hostile datagram of a class for the receiver of ``direction``.

    ``capture``: what the sniffer learnt (None: a blind attacker, who knows nothing); ``recorded``:
    datagrams recorded in an earlier session under the same key, with their direction."""

    def __init__(
        self,
        rng: random.Random,
        capture: Capture | None = None,
        recorded: list[tuple[int, bytes]] | None = None,
    ) -> None:
        self.rng = rng
        self.capture = capture
        self.recorded = {d: [b for dd, b in (recorded or []) if dd == d] for d in (0, 1)}
        # Sealers with keys the attacker may have: a guessed one and the well-known insecure one.
        self._wrong_psk = [auth.generate_key() for _ in range(4)]
        self._sealers: dict[tuple[int, int, int, tuple[int, bytes, bytes]], auth.Sealer] = {}
        self._bodies = hostile_control_bodies(random.Random(rng.random()))
        self._noise = rng.randbytes(2 * MAX_OVERSIZED)  # sliced at random offsets: cheap random bytes

    def _random(self, n: int) -> bytes:
        start = self.rng.randrange(len(self._noise) - n + 1)
        return self._noise[start : start + n]

    def available(self, cls: str, direction: int) -> bool:
        """Whether this class can be made now (captured material may be missing)."""
        if cls in CAPTURE_CLASSES:
            return self.capture is not None and self.capture.has(direction)
        if cls == "old_session_replay":
            return bool(self.recorded[direction])
        return True

    def _sealer(self, which: int, kind: int, direction: int) -> auth.Sealer:
        """A sealer under pre-shared key ``which`` (0 the insecure key, 1..4 a guessed one), derived
        as the receiver would: the handshake key, or the session key of ``direction`` from the
        captured session id and nonces (so under ``--insecure`` such a forgery verifies)."""
        ctx = self.capture.key_context if self.capture is not None else None
        context = ctx or (1, bytes(auth.NONCE_BYTES), bytes(auth.NONCE_BYTES))
        key = (which, kind, direction, context)
        s = self._sealers.get(key)
        if s is None:
            psk = auth.INSECURE_KEY if which == 0 else self._wrong_psk[which - 1]
            k = (
                auth.handshake_key(psk)
                if kind == auth.HANDSHAKE
                else auth.session_keys(psk, *context)[direction]
            )
            s = self._sealers[key] = auth.Sealer(k, kind, direction)
        return s

    def _learned(self, direction: int) -> Learned:
        return self.capture.learned[direction] if self.capture is not None else Learned()

    def make(self, cls: str, direction: int) -> bytes:
        """One datagram of class ``cls`` posing as the sender of ``direction``."""
        rng = self.rng
        if cls == "random":
            return self._random(rng.randint(0, MAX_DATAGRAM))
        if cls == "random_enveloped":
            kind = rng.randrange(2)
            n = rng.randint(auth.OVERHEAD, MAX_DATAGRAM)
            header = struct.pack(
                ">cBQ", auth.MAGIC, 0x10 | kind << 1 | direction, rng.randint(1, auth.MAX_COUNTER)
            )
            return header + self._random(n - auth.HEADER_BYTES)
        if cls == "oversized":
            n = rng.randint(MAX_DATAGRAM + 1, MAX_OVERSIZED)
            if rng.random() < 0.5:
                return self._random(n)
            # A plausible header, so the receiver computes the tag over all of it (the costly path).
            counter = self._learned(direction).counter[auth.SESSION] + 1
            return struct.pack(">cBQ", auth.MAGIC, 0x12 | direction, counter) + self._random(n - 10)
        if cls == "recrc_forgery":
            return self._recrc(direction)
        if cls == "bad_handshake":
            body = self._bodies[rng.randrange(len(self._bodies))]
            kind = auth.HANDSHAKE if rng.random() < 0.8 else auth.SESSION
            s = self._sealer(rng.randrange(5), kind, direction)
            s.counter = max(1, self._learned(direction).counter[kind] + rng.randint(1, 3))
            return s.seal(body)
        if cls == "old_session_replay":
            pool = self.recorded[direction]
            return pool[rng.randrange(len(pool))]
        assert self.capture is not None, cls
        got = self.capture.pick(rng, direction)
        assert got is not None, cls
        if cls == "replay":
            return got
        if cls == "truncated":
            return got[: rng.randrange(len(got))]
        if cls == "bitflip":
            b = bytearray(got)
            for _ in range(rng.randint(1, 4)):
                b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
            return bytes(b)
        if cls == "counter_ahead":
            counter = int.from_bytes(got[2:10], "big")
            ahead = rng.choice((rng.randint(2**11, 2**40), 2**63, auth.MAX_COUNTER - counter))
            new = min(auth.MAX_COUNTER, counter + max(1, ahead))
            return got[:2] + new.to_bytes(8, "big") + got[10:]
        raise ValueError(f"unknown class {cls!r}")

    def _recrc(self, direction: int) -> bytes:
        """A well-formed data packet with a correct CRC-32, full-scale payload and an absurd energy
        or seq, sealed with a wrong or the insecure key, with the next counter if known."""
        rng, lr = self.rng, self._learned(direction)
        session = lr.session if lr.session is not None else rng.randint(1, 2**32 - 1)
        far = rng.random() < 0.5
        n = max(1, lr.payload_len // 2)
        payload = (b"\xff\x7f" if rng.random() < 0.5 else b"\x01\x80") * n
        pkt = wire.Packet(
            session=session,
            direction=direction,
            seq=2**32 - 1 if far else (lr.seq + 1) & 0xFFFFFFFF,
            tick=lr.tick + 1,
            t_us=lr.t_us + 1000,
            codec_id=lr.codec_id,
            payload=payload[: max(lr.payload_len, 1)],
            energy=1e300 if not far or rng.random() < 0.5 else 1e3,
        )
        body = wire.encode(pkt)
        assert zlib.crc32(body[:-4]) == int.from_bytes(body[-4:], "little")
        s = self._sealer(rng.randrange(5), auth.SESSION, direction)
        s.counter = max(1, lr.counter[auth.SESSION] + rng.randint(1, 3))
        return s.seal(body)


# --------------------------------------------------------------------------------------------
# the attacker
# --------------------------------------------------------------------------------------------
@dataclass
class Ports:
    teleoperator: int
    operator: int

    def of(self, role: str) -> int:
        return self.teleoperator if role == "teleoperator" else self.operator


@dataclass
class AttackStats:
    """What the attacker sent: per class, per route, per target; and how fast."""

    sent: dict[str, dict[str, int]] = field(
        default_factory=lambda: {c: dict.fromkeys(ROUTES, 0) for c in CLASSES}
    )
    to: dict[str, dict[str, int]] = field(
        default_factory=lambda: {r: dict.fromkeys(ROUTES, 0) for r in ROLES}
    )
    send_errors: dict[str, int] = field(default_factory=dict)
    bytes_sent: int = 0
    elapsed_s: float = 0.0
    cpu_s: float = 0.0
    stopped_by: str = ""
    #: Replays of captured handshake messages (hello, welcome, reject) of this or the recorded
    #: session: authentic, so no receiver counts them as refused (their tag verifies).
    handshake_replays: dict[str, int] = field(default_factory=lambda: dict.fromkeys(ROLES, 0))
    #: What came back to the attacker's own (blind) socket: an endpoint that answers a stranger.
    replies: dict[str, int] = field(default_factory=lambda: {"datagrams": 0, "bytes": 0, "handshake_kind": 0})

    @property
    def total(self) -> int:
        return sum(sum(r.values()) for r in self.sent.values())

    def as_dict(self) -> dict[str, Any]:
        return {
            "total": self.total,
            "by_class": {c: sum(r.values()) for c, r in self.sent.items()},
            "by_class_and_route": self.sent,
            "by_target": {t: {**r, "total": sum(r.values())} for t, r in self.to.items()},
            "by_route": {r: sum(c[r] for c in self.sent.values()) for r in ROUTES},
            "bytes": self.bytes_sent,
            "send_errors": self.send_errors,
            "elapsed_s": self.elapsed_s,
            "achieved_rate_per_s": self.total / self.elapsed_s if self.elapsed_s > 0 else None,
            "attacker_cpu_s": self.cpu_s,
            "stopped_by": self.stopped_by,
            "handshake_replays_by_target": self.handshake_replays,
            "replies_to_blind_socket": self.replies,
        }

    def drain_replies(self, sock: socket.socket) -> None:
        """Count what the endpoints sent back to the attacker's blind socket (non-blocking)."""
        while True:
            try:
                data = sock.recv(1 << 16)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # ICMP port unreachable reported on the socket: not a reply
                continue
            self.replies["datagrams"] += 1
            self.replies["bytes"] += len(data)
            hdr = auth.peek(data)
            if hdr is not None and hdr[0] == auth.HANDSHAKE:
                self.replies["handshake_kind"] += 1


def attack(
    ports: Ports,
    datagrams: int,
    rate: float,
    deadline_ns: int,
    *,
    capture: Capture | None = None,
    spoofer: Spoofer | None = None,
    recorded: list[tuple[int, bytes]] | None = None,
    seed: int = 1,
) -> AttackStats:
    """Send ``datagrams`` hostile datagrams at ``rate`` per second to both ports, alternately, until
    done or ``deadline_ns`` (monotonic).  Blind from a socket of our own; with a ``spoofer``, half
    of them from the genuine peer's address.  Never sends anywhere but 127.0.0.1."""
    rng = random.Random(seed)
    forge = Forge(rng, capture, recorded)
    stats = AttackStats()
    blind = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    blind.bind((LOOPBACK, 0))
    blind.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    blind.setblocking(False)
    dest = {role: (_loopback(LOOPBACK), ports.of(role)) for role in ROLES}
    peer_port = {"teleoperator": ports.operator, "operator": ports.teleoperator}
    usable: dict[int, list[str]] = {}
    period = 1.0 / rate
    clock = time.monotonic
    cpu0 = time.thread_time()
    t0 = next_t = clock()
    sent = 0
    try:
        while sent < datagrams:
            now = clock()
            if time.monotonic_ns() >= deadline_ns:
                stats.stopped_by = "deadline"
                break
            if next_t > now:
                time.sleep(min(next_t - now, 0.01))
                continue
            next_t = max(next_t, now - 0.05) + period  # rate-limited: never catch up more than 50 ms
            role = ROLES[sent & 1]
            d = RX_DIRECTION[role]
            if sent % 1000 < 2:  # captured material arrives as the session runs: look again now and then
                usable[d] = [c for c in CLASSES if forge.available(c, d)]
                stats.drain_replies(blind)
            cls = rng.choice(usable[d])
            data = forge.make(cls, d)
            route = "spoofed" if spoofer is not None and rng.random() < 0.5 else "blind"
            try:
                if route == "spoofed":
                    assert spoofer is not None
                    spoofer.send(data, peer_port[role], ports.of(role))
                else:
                    blind.sendto(data, dest[role])
            except BlockingIOError:  # the blind socket's buffer is full: wait a little, count nothing
                time.sleep(0.0005)
                continue
            except OSError as e:
                name = type(e).__name__
                stats.send_errors[name] = stats.send_errors.get(name, 0) + 1
                continue
            if cls in ("replay", "old_session_replay") and len(data) > 1 and data[1] >> 1 & 1 == 0:
                stats.handshake_replays[role] += 1
            sent += 1
            stats.sent[cls][route] += 1
            stats.to[role][route] += 1
            stats.bytes_sent += len(data)
        else:
            stats.stopped_by = "count"
    finally:
        stats.elapsed_s = clock() - t0
        stats.cpu_s = time.thread_time() - cpu0
        time.sleep(0.05)
        stats.drain_replies(blind)
        blind.close()
    return stats


# --------------------------------------------------------------------------------------------
# the two processes
# --------------------------------------------------------------------------------------------
def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((LOOPBACK, 0))
        return int(s.getsockname()[1])


def udp_socket_stats(ports: list[int]) -> dict[int, dict[str, int]]:
    """Per bound 127.0.0.1 UDP port: the kernel's receive-queue bytes and datagrams dropped
    (``/proc/net/udp``: a full socket buffer drops before the process ever sees the datagram)."""
    want = {f"0100007F:{p:04X}": p for p in ports}
    out: dict[int, dict[str, int]] = {}
    with contextlib.suppress(OSError):
        for line in Path("/proc/net/udp").read_text().splitlines()[1:]:
            f = line.split()
            if len(f) >= 13 and f[1] in want:
                out[want[f[1]]] = {"rx_queue": int(f[4].split(":")[1], 16), "drops": int(f[12])}
    return out


class SocketMonitor(threading.Thread):
    """Polls the kernel's drop counters of the session's two sockets while they exist."""

    def __init__(self, ports: Ports, interval: float = 0.2) -> None:
        super().__init__(name="bench.fuzz monitor", daemon=True)
        self.ports = ports
        self.interval = interval
        self.drops = dict.fromkeys(ROLES, 0)
        self.max_rx_queue = dict.fromkeys(ROLES, 0)
        self.seen = dict.fromkeys(ROLES, False)
        self._halt = threading.Event()

    def run(self) -> None:
        while not self._halt.wait(self.interval):
            self.poll()

    def poll(self) -> None:
        stats = udp_socket_stats([self.ports.teleoperator, self.ports.operator])
        for role in ROLES:
            s = stats.get(self.ports.of(role))
            if s is not None:
                self.seen[role] = True
                self.drops[role] = max(self.drops[role], s["drops"])
                self.max_rx_queue[role] = max(self.max_rx_queue[role], s["rx_queue"])

    def stop(self) -> None:
        self._halt.set()
        self.join(timeout=2)

    def as_dict(self) -> dict[str, Any]:
        return {
            role: {
                "kernel_drops": self.drops[role] if self.seen[role] else None,
                "max_rx_queue_bytes": self.max_rx_queue[role] if self.seen[role] else None,
            }
            for role in ROLES
        }


def cpu_times() -> list[int]:
    """The machine's CPU time counters (``/proc/stat``: user nice system idle iowait irq softirq steal)."""
    with contextlib.suppress(OSError, ValueError):
        return [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:9]]
    return []


def cpu_share(before: list[int], after: list[int]) -> dict[str, Any]:
    """What the whole machine did meanwhile, as fractions of all CPU time: busy (everything but
    idle), softirq (the network stack) and steal (a hypervisor gave the CPU to someone else)."""
    if len(before) < 8 or len(after) < 8:
        return {"note": "/proc/stat not readable"}
    d = [b - a for a, b in zip(before, after, strict=True)]
    total = sum(d) or 1
    return {
        "busy": (total - d[3]) / total,
        "softirq": d[6] / total,
        "steal": d[7] / total,
        "cpus": os.cpu_count(),
    }


def lateness_in_window(log_dir: Path, window: tuple[float, float]) -> dict[str, Any]:
    """Per process: tick lateness inside the attack's window and outside it (the same session's
    calm part), from the loop's per-tick record (``/ROLE/loop`` in ROLE.mcap, with each tick's time)."""
    import numpy as np

    from shell.mcaplog import iter_messages

    out: dict[str, Any] = {}
    for role in ROLES:
        path = log_dir / f"{role}.mcap"
        if not path.exists():
            continue
        rows = [(m["t"], m["lateness_ns"]) for _, m in iter_messages(path, [f"/{role}/loop"])]
        t = np.array([r[0] for r in rows], dtype=np.float64)
        late = np.abs(np.array([r[1] for r in rows], dtype=np.float64)) / 1e3
        inside = (t >= window[0]) & (t < window[1])
        parts = {"attack_window": late[inside], "rest_of_session": late[~inside]}
        out[role] = {
            name: {
                "ticks": int(a.size),
                "p99_us": float(np.percentile(a, 99)) if a.size else None,
                "late_over_1ms": int((a > 1000).sum()),
            }
            for name, a in parts.items()
        }
    return out


def _die_with_parent() -> None:
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


def _wait_bound(port: int, proc: subprocess.Popen[bytes], timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and proc.poll() is None:
        if port in udp_socket_stats([port]):
            return True
        time.sleep(0.02)
    return False


@dataclass
class SessionRun:
    """One session of the two processes, with or without the attack, and what came of it."""

    label: str
    log_dir: Path
    ports: Ports
    duration: float
    exit_codes: dict[str, int | None] = field(default_factory=dict)
    stderr: dict[str, str] = field(default_factory=dict)
    attack: AttackStats | None = None
    sockets: dict[str, Any] = field(default_factory=dict)
    sniffer: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    wall_s: float = 0.0
    #: The attack's start and end on the session clock (s from the first data packet seen).
    attack_window_s: tuple[float, float] | None = None
    machine: dict[str, Any] = field(default_factory=dict)


def run_session(
    work: Path,
    label: str,
    key_file: Path,
    duration: float,
    *,
    sniff: bool,
    spoofer: Spoofer | None = None,
    datagrams: int = 0,
    rate: float = DEFAULT_RATE,
    recorded: list[tuple[int, bytes]] | None = None,
    seed: int = 1,
    extra_args: tuple[str, ...] = (),
) -> tuple[SessionRun, Capture | None]:
    """Run one session (teleoperator, then operator) on fresh ports; attack it with ``datagrams``
    hostile datagrams once its data flows (none: a baseline).  Returns the run and what the
    sniffer captured (the recording a later attack may replay)."""
    t_start = time.monotonic()
    log_dir = work / label
    log_dir.mkdir(parents=True, exist_ok=True)
    ports = Ports(teleoperator=free_udp_port(), operator=free_udp_port())
    while ports.operator == ports.teleoperator:
        ports.operator = free_udp_port()
    run = SessionRun(label, log_dir, ports, duration)
    cpu0 = cpu_times()
    capture: Capture | None = None
    sniffer: Sniffer | None = None
    if sniff:
        capture = Capture()
        try:
            sniffer = Sniffer(capture, {ports.operator: wire.FORWARD, ports.teleoperator: wire.BACKWARD})
            sniffer.start()
        except OSError as e:
            run.notes.append(f"sniffer not started: {e.strerror or e}")
            capture = None
    common = ["--key-file", str(key_file), "--log", str(log_dir), "--quiet", *extra_args]
    to_cmd = [*TELEOP, "teleoperator", "--listen", f"{LOOPBACK}:{ports.teleoperator}", *common]
    op_cmd = [
        *TELEOP,
        "operator",
        "--peer",
        f"{LOOPBACK}:{ports.teleoperator}",
        "--listen",
        f"{LOOPBACK}:{ports.operator}",
        "--duration",
        repr(duration),
        "--codec",
        "eds:50",
        *common,
    ]
    monitor = SocketMonitor(ports)
    procs: dict[str, subprocess.Popen[bytes]] = {}
    err_files = {role: (log_dir / f"{role}.stderr").open("w+b") for role in ROLES}
    try:
        procs["teleoperator"] = subprocess.Popen(
            to_cmd, stdout=subprocess.DEVNULL, stderr=err_files["teleoperator"], preexec_fn=_die_with_parent
        )
        if not _wait_bound(ports.teleoperator, procs["teleoperator"]):
            run.notes.append("the teleoperator never bound its port")
        procs["operator"] = subprocess.Popen(
            op_cmd, stdout=subprocess.DEVNULL, stderr=err_files["operator"], preexec_fn=_die_with_parent
        )
        t_operator = time.monotonic_ns()
        monitor.start()
        if datagrams > 0:
            # Attack the running session: from its first data packet (seen by the sniffer), else a
            # fixed wait that covers the handshake (hellos, welcomes, the start 300 ms ahead).
            wait_until = t_operator + 8_000_000_000
            while capture is not None and capture.first_data_ns is None and time.monotonic_ns() < wait_until:
                if any(p.poll() is not None for p in procs.values()):
                    break
                time.sleep(0.005)
            if capture is not None and capture.first_data_ns is not None:
                t_session = capture.first_data_ns
            else:
                if capture is not None:
                    run.notes.append("no data packet seen within 8 s; attacking anyway")
                t_session = t_operator + 2_000_000_000
                while time.monotonic_ns() < t_session:
                    time.sleep(0.01)
            stop_ns = t_session + round((duration - 1.0) * 1e9)  # a calm last second: bye, logs
            a0 = time.monotonic_ns()
            run.attack = attack(
                ports,
                datagrams,
                rate,
                stop_ns,
                capture=capture,
                spoofer=spoofer,
                recorded=recorded,
                seed=seed,
            )
            run.attack_window_s = ((a0 - t_session) / 1e9, (time.monotonic_ns() - t_session) / 1e9)
        limit = time.monotonic() + duration + 30
        for role, p in procs.items():
            try:
                p.wait(timeout=max(0.1, limit - time.monotonic()))
            except subprocess.TimeoutExpired:
                run.notes.append(f"the {role} did not exit in time: stopped")
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
        for p in procs.values():
            try:
                p.wait(timeout=5)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        monitor.stop()
        if sniffer is not None:
            run.sniffer = sniffer.stats()
            run.sniffer["ignored"] = sniffer.ignored
            sniffer.stop()
        for role, f in err_files.items():
            f.seek(0)
            run.stderr[role] = f.read().decode("utf-8", "replace")
            f.close()
    run.exit_codes = {role: p.returncode for role, p in procs.items()}
    run.sockets = monitor.as_dict()
    if capture is not None:
        run.sniffer["captured"] = {wire.DIRECTIONS[d]: n for d, n in capture.count.items()}
    run.wall_s = time.monotonic() - t_start
    run.machine = cpu_share(cpu0, cpu_times())
    return run, capture


# --------------------------------------------------------------------------------------------
# the verdict
# --------------------------------------------------------------------------------------------
def crashes(run: SessionRun) -> dict[str, Any]:
    """A process that exited non-zero (or never started) or printed a traceback."""
    out: dict[str, Any] = {}
    for role in ROLES:
        code = run.exit_codes.get(role)
        err = run.stderr.get(role, "")
        if code != 0 or "Traceback" in err:
            out[role] = {"exit_code": code, "stderr_tail": err[-3000:]}
    return out


_ABANDONED_KEYS = ("completed", "replaced_by_new_session", "first_tick")


def figures(run: SessionRun) -> dict[str, Any]:
    """``teleop report``-style figures of one session, from both processes' logs."""
    from teleop.offline.report import build

    out: dict[str, Any] = {
        "label": run.label,
        "duration_s": run.duration,
        "wall_s": run.wall_s,
        "machine_during_session": run.machine,
        "attack_window_s": run.attack_window_s,
        "exit_codes": run.exit_codes,
        "crashes": crashes(run),
        "stderr": {r: e[-2000:] for r, e in run.stderr.items() if e.strip()},
        "notes": list(run.notes),
        "kernel_sockets": run.sockets,
    }
    if run.sniffer:
        out["sniffer"] = run.sniffer
    if run.attack is not None:
        out["attack"] = run.attack.as_dict()
    if not all((run.log_dir / f"{r}.{x}").exists() for r in ROLES for x in ("json", "mcap")):
        out["report"] = None
        out["notes"].append("no report: a process left no log (see exit_codes and stderr)")
        return out
    rep = build(run.log_dir, "udp", compare_sim=False)
    logs = {r: json.loads((run.log_dir / f"{r}.json").read_text()) for r in ROLES}
    receiver = {"forward": "teleoperator", "backward": "operator"}
    # A teleoperator that ended its session for a new operator keeps that session's logs as
    # teleoperator-<session>.json; the report covers the last one only (a rejoin, joined late).
    earlier = sorted(p.name for p in run.log_dir.glob("*-*.json"))
    out["report"] = {
        "completed": {r: rep["processes"][r]["completed"] for r in ROLES},
        "abandoned_sessions": [
            {"log": name, **{k: json.loads((run.log_dir / name).read_text()).get(k) for k in _ABANDONED_KEYS}}
            for name in earlier
        ],
        "joined_late": logs["teleoperator"].get("joined_late"),
        "rejoin": logs["operator"].get("rejoin"),
        "peer_said_bye": {r: logs[r]["peer_said_bye"] for r in ROLES},
        "security": rep["security"],
        "energy": rep["energy"],
        "two_port_min_energy": rep["two_port_min_energy"],
        "passivity": rep["passivity"],
        "link_lost_events": {d: rep["passivity"][d]["link_lost_events"] for d in ("forward", "backward")},
        "loop": {
            r: {
                "period_error_us": rep["processes"][r]["loop"]["period_error_us"],
                "overruns": rep["processes"][r]["loop"]["overruns"],
                "skipped": rep["processes"][r]["loop"]["skipped"],
                "cpu_fraction": rep["processes"][r]["loop"]["cpu_fraction"],
            }
            for r in ROLES
        },
        # What each receiver's socket loop saw (received.* of its log) and its node's inbound counters.
        "received": {
            d: {
                "at": role,
                **{k: logs[role]["received"].get(k) for k in ("packets", "malformed", "foreign")},
                **{k: logs[role]["received"].get(k) for k in ("inbox_overflow", "socket_errors")},
                # Refused by length: by the transport (UDP: once a session runs, longer than its
                # largest datagram, by the true length) or by the endpoint (by key kind).
                "oversize": logs[role]["received"].get("oversize"),
                "oversize_refused": logs[role].get("oversize_refused"),
                "control_rejected": logs[role].get("control_rejected"),
                "node": logs[role]["node"],
            }
            for d, role in receiver.items()
        },
        "wire": {
            d: {k: rep["wire"][d][k] for k in ("packets", "received_packets", "lost", "received_malformed")}
            for d in ("forward", "backward")
        },
        # The link observer sees an authentic datagram before the replay window refuses a replay.
        "link": {
            d: {k: rep["link"][d].get(k) for k in ("received", "loss", "delay_ms", "duplicates", "reordered")}
            for d in ("forward", "backward")
        },
    }
    return out


def _num(v: Any) -> float | None:
    return float(v) if isinstance(v, int | float) and not isinstance(v, bool) else None


def verdict(attacked: dict[str, Any], baseline: dict[str, Any] | None = None) -> dict[str, Any]:
    """Checks on an attacked session's figures (and the comparison with a baseline): ``failures``
    lists what went wrong; empty means every check passed."""
    failures: list[str] = []
    checks: dict[str, Any] = {}
    runs = {"attack": attacked, **({"baseline": baseline} if baseline is not None else {})}
    for label, f in runs.items():
        for role, c in f["crashes"].items():
            failures.append(f"{label}: the {role} crashed (exit {c['exit_code']})")
    checks["crashes"] = sum(len(f["crashes"]) for f in runs.values())
    rep = attacked.get("report")
    if rep is None:
        failures.append("attack: no report (a process left no log)")
        return {"ok": False, "failures": failures, "checks": checks}
    checks["sessions_completed"] = sum(
        all(f["report"]["completed"].values()) for f in runs.values() if f.get("report")
    )
    if not all(rep["completed"].values()):
        failures.append(f"attack: session not completed {rep['completed']}")
    if rep["abandoned_sessions"] or rep["joined_late"]:
        failures.append(
            f"attack: the teleoperator abandoned its session ({len(rep['abandoned_sessions'])} log(s) of an "
            f"abandoned session; the last session joined late: {rep['joined_late']})"
        )
    energy: dict[str, Any] = {}
    for d in ("forward", "backward"):
        e = rep["energy"][d]
        sent, played, margin = _num(e["sent"]), _num(e["played"]), _num(e["min_margin"])
        ok_played = sent is not None and played is not None and played <= sent
        ok_margin = margin is not None and margin >= -1e-9
        energy[d] = {"played_le_sent": ok_played, "min_margin": margin}
        if not ok_played:
            failures.append(f"attack: {d} energy played {played} exceeds sent {sent}")
        if not ok_margin:
            failures.append(f"attack: {d} energy min_margin {margin} < -1e-9")
    checks["energy"] = energy
    # Which direction's receiver was attacked, and did it refuse?
    att = attacked.get("attack", {})
    by_target = att.get("by_target", {})
    sec = rep["security"]
    refused: dict[str, Any] = {}
    for d, role in (("forward", "teleoperator"), ("backward", "operator")):
        n = by_target.get(role, {}).get("total", 0)
        rejected = sec["rejected"][d] or 0
        refused[d] = {"target": role, "sent_to": n, "rejected": rejected, "replayed": sec["replayed"][d]}
        if n > 0 and rejected <= 0:
            failures.append(f"attack: the {role} was sent {n} hostile datagrams and rejected none")
        # With a real key no forgery verifies, so none reaches the watchdog: nothing to clamp.
        clamped = sec["energy_reports_clamped"][d]
        refused[d]["energy_reports_clamped"] = clamped
        if clamped != 0:
            failures.append(f"attack: {d} watchdog clamped {clamped} energy report(s): a forgery got through")
    checks["refused"] = refused
    checks["accounting"] = accounting(attacked)
    if baseline is not None and baseline.get("report"):
        b = baseline["report"]
        checks["baseline_security_quiet"] = all(
            (b["security"][k][d] or 0) == 0
            for k in ("rejected", "replayed", "counter_jumps")
            for d in ("forward", "backward")
        )
    return {"ok": not failures, "failures": failures, "checks": checks}


def accounting(attacked: dict[str, Any]) -> dict[str, Any]:
    """Per target: hostile datagrams sent, and where they went by the receivers' own counts.

    ``refused`` = rejected + replayed + counter_jumps (the port's security counters) + what the
    transport and the endpoint refused by length (``oversize``, ``oversize_refused``);
    ``handshake_replays`` are authentic and so not refused by the tag (see AttackStats); the inbox
    and the kernel socket drop datagrams of any origin, genuine ones and handshake replays included.
    ``unaccounted`` is what none of these explains: exact without drops; with drops it is negative by
    about the handshake replays and genuine datagrams that were dropped (counted twice here), and
    positive by replays of genuine datagrams that the kernel had dropped (those are accepted)."""
    att, rep = attacked.get("attack"), attacked.get("report")
    if att is None or rep is None:
        return {}
    sec = rep["security"]
    out: dict[str, Any] = {}
    for d, role in (("forward", "teleoperator"), ("backward", "operator")):
        sent = att["by_target"][role]["total"]
        refused = sum(sec[k][d] or 0 for k in ("rejected", "replayed", "counter_jumps"))
        refused += sum(rep["received"][d].get(k) or 0 for k in ("oversize", "oversize_refused"))
        hs = att["handshake_replays_by_target"][role]
        overflow = rep["received"][d]["inbox_overflow"] or 0
        drops = attacked["kernel_sockets"][role]["kernel_drops"] or 0
        out[role] = {
            "sent": sent,
            "refused": refused,
            "handshake_replays": hs,
            "inbox_overflow": overflow,
            "kernel_drops": drops,
            "unaccounted": sent - refused - hs - overflow - drops,
        }
    return out


def compare(attacked: dict[str, Any], baseline: dict[str, Any]) -> dict[str, Any]:
    """p99 period error and link-lost events, attack vs baseline, per process / direction."""
    a, b = attacked.get("report"), baseline.get("report")
    if a is None or b is None:
        return {"note": "a run left no report: nothing to compare"}
    loops: dict[str, Any] = {}
    for r in ROLES:
        pa = a["loop"][r]["period_error_us"]["p99"]
        pb = b["loop"][r]["period_error_us"]["p99"]
        loops[r] = {"p99_us_baseline": pb, "p99_us_attack": pa, "ratio": pa / pb if pb > 0 else None}
    lost = {
        d: {
            "baseline": b["link_lost_events"][d],
            "attack": a["link_lost_events"][d],
            "caused": a["link_lost_events"][d] - b["link_lost_events"][d],
        }
        for d in ("forward", "backward")
    }
    out: dict[str, Any] = {"period_error_p99": loops, "link_lost_events": lost}
    la, lb = attacked.get("lateness"), baseline.get("lateness")
    if la and lb:
        window: dict[str, Any] = {}
        for r in ROLES:
            if r in la and r in lb:
                wa, wb = la[r]["attack_window"], lb[r]["attack_window"]
                pa, pb = wa["p99_us"], wb["p99_us"]
                window[r] = {
                    "p99_lateness_us_baseline": pb,
                    "p99_lateness_us_attack": pa,
                    "ratio": pa / pb if pa is not None and pb else None,
                    "late_over_1ms_baseline": wb["late_over_1ms"],
                    "late_over_1ms_attack": wa["late_over_1ms"],
                }
        out["lateness_in_attack_window"] = window
    return out


# --------------------------------------------------------------------------------------------
# the benchmark
# --------------------------------------------------------------------------------------------
@contextlib.contextmanager
def key_dir() -> Iterator[Path]:
    """A private folder with a new pre-shared key file (mode 0600), removed afterwards."""
    folder = Path(tempfile.mkdtemp(prefix="bench-fuzz-"))
    try:
        auth.write_key_file(folder / "fuzz.key", auth.generate_key())
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def run_fuzz(
    datagrams: int,
    rate: float,
    duration: float | None = None,
    *,
    baseline: bool = True,
    on_path: bool = True,
    seed: int = 1,
    work: Path | None = None,
) -> dict[str, Any]:
    """Probe on-path ability, run the baseline (if asked) then the attacked session under one key;
    the figures, comparison and verdict as one JSON-able dict."""
    if datagrams < 0 or not rate > 0:
        raise ValueError("datagrams must be >= 0 and rate > 0")
    if duration is None:  # room for an attacker that falls short of ``rate`` on a loaded machine
        duration = math.ceil(1.5 * datagrams / rate) + SETTLE_S
    probe: dict[str, Any] = (
        probe_on_path() if on_path else {"sniff": False, "spoof": False, "notes": ["on-path part disabled"]}
    )
    spoofer = Spoofer() if probe["spoof"] else None
    out: dict[str, Any] = {
        "benchmark": "bench.fuzz",
        "config": {
            "datagrams_requested": datagrams,
            "rate_per_s": rate,
            "session_duration_s": duration,
            "transport": "udp",
            "codec": "eds:50",
            "seed": seed,
            "classes": list(CLASSES),
        },
        "environment": {
            "python": platform.python_version(),
            "machine": platform.machine(),
            "kernel": platform.release(),
            "cpus": os.cpu_count(),
        },
        "on_path": probe,
    }
    try:
        with contextlib.ExitStack() as stack:
            keys = stack.enter_context(key_dir())
            if work is None:
                work = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="bench-fuzz-logs-")))
            key_file = keys / "fuzz.key"
            recorded: list[tuple[int, bytes]] | None = None
            base: dict[str, Any] | None = None
            if baseline:
                b_run, b_cap = run_session(work, "baseline", key_file, duration, sniff=probe["sniff"])
                base = figures(b_run)
                recorded = list(b_cap.record) if b_cap is not None else None
                out["baseline"] = base
            a_run, _ = run_session(
                work,
                "attack",
                key_file,
                duration,
                sniff=probe["sniff"],
                spoofer=spoofer,
                datagrams=datagrams,
                rate=rate,
                recorded=recorded,
                seed=seed,
            )
            attacked = figures(a_run)
            out["attack"] = attacked
            window = a_run.attack_window_s
            if window is not None:
                # Tick lateness in the attack's window vs the rest, in both sessions (same window).
                attacked["lateness"] = lateness_in_window(a_run.log_dir, window)
                if base is not None:
                    base["lateness"] = lateness_in_window(work / "baseline", window)
            notes = []
            if not probe["sniff"]:
                notes.append(f"not sniffed: classes {sorted(CAPTURE_CLASSES)} were not sent")
            if recorded is None:
                notes.append("no recording of an earlier session: old_session_replay was not sent")
            if spoofer is None:
                notes.append("no raw socket: every datagram came from the attacker's own address")
            out["notes"] = notes
            if base is not None:
                out["comparison"] = compare(attacked, base)
            out["verdict"] = verdict(attacked, base)
    finally:
        if spoofer is not None:
            spoofer.close()
    return out


def summary_text(res: dict[str, Any]) -> str:
    a = res["attack"]
    att = a.get("attack", {})
    lines = [
        f"bench.fuzz: {att.get('total', 0)} hostile datagrams in {att.get('elapsed_s', 0):.1f} s "
        f"({att.get('achieved_rate_per_s') or 0:.0f}/s; sniff {res['on_path']['sniff']}, "
        f"spoof {res['on_path']['spoof']})",
        "  by class: " + ", ".join(f"{c} {n}" for c, n in att.get("by_class", {}).items()),
    ]
    rep = a.get("report")
    if rep:
        sec = rep["security"]
        lines.append(
            "  refused (forward/backward): "
            + "  ".join(
                f"{k} {sec[k]['forward']}/{sec[k]['backward']}"
                for k in ("rejected", "replayed", "counter_jumps")
            )
            + f"  energy reports clamped {sec['energy_reports_clamped']['forward']}/"
            f"{sec['energy_reports_clamped']['backward']}"
        )
        lines.append(
            "  inbox overflow "
            + "/".join(str(rep["received"][d]["inbox_overflow"]) for d in ("forward", "backward"))
            + "  kernel drops "
            + "/".join(str(a["kernel_sockets"][r]["kernel_drops"]) for r in ("teleoperator", "operator"))
            + f"  completed {rep['completed']}  abandoned sessions {len(rep['abandoned_sessions'])}"
        )
        for d in ("forward", "backward"):
            e = rep["energy"][d]
            lines.append(
                f"  energy {d:<8} sent {e['sent']:.4g} J  played {e['played']:.4g} J  "
                f"min margin {e['min_margin']:.3g} J  link lost {rep['link_lost_events'][d]}x"
            )
    cmp_ = res.get("comparison", {}).get("period_error_p99")
    if cmp_:
        lines.append(
            "  p99 period error (baseline -> attack): "
            + "  ".join(
                f"{r} {v['p99_us_baseline']:.0f} -> {v['p99_us_attack']:.0f} us"
                + (f" (x{v['ratio']:.2f})" if v["ratio"] is not None else "")
                for r, v in cmp_.items()
            )
        )
    win = res.get("comparison", {}).get("lateness_in_attack_window")
    if win:
        lines.append(
            "  p99 tick lateness in the attack's window (baseline -> attack): "
            + "  ".join(
                f"{r} {v['p99_lateness_us_baseline']:.0f} -> {v['p99_lateness_us_attack']:.0f} us, "
                f"ticks late > 1 ms {v['late_over_1ms_baseline']} -> {v['late_over_1ms_attack']}"
                for r, v in win.items()
            )
        )
    v = res["verdict"]
    lines.append("  verdict: " + ("OK" if v["ok"] else "FAILED: " + "; ".join(v["failures"])))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.fuzz", description=__doc__.split("\n\n")[0])
    ap.add_argument("--datagrams", type=int, default=DEFAULT_DATAGRAMS, metavar="N")
    ap.add_argument("--rate", type=float, default=DEFAULT_RATE, metavar="R", help="datagrams per second")
    ap.add_argument(
        "--duration", type=float, default=None, metavar="S", help="session seconds (default 1.5 N/R + 4)"
    )
    ap.add_argument("--out", default="bench/results/fuzz.json", metavar="FILE")
    ap.add_argument("--transport", choices=["udp"], default="udp", help="udp only (the attacker speaks UDP)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-baseline", action="store_true", help="skip the baseline session")
    ap.add_argument(
        "--logs", metavar="DIR", help="keep both sessions' logs here (default: a temporary folder)"
    )
    args = ap.parse_args(argv)
    if args.duration is not None and args.duration < args.datagrams / args.rate + 2:
        ap.error("--duration must leave room for N/R seconds of attack plus 2 s")
    work = Path(args.logs) if args.logs else None
    res = run_fuzz(
        args.datagrams, args.rate, args.duration, baseline=not args.no_baseline, seed=args.seed, work=work
    )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_result(out, res)
    print(summary_text(res))
    print(f"wrote {out}")
    return 0 if res["verdict"]["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
