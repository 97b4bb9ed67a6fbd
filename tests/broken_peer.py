"""A deliberately broken endpoint for tests/test_conformance.py: ``python -m tests.broken_peer BREAK
ARGS...`` applies one break to this project's code, then runs ``teleop ARGS...``.  Each break
violates one rule of PROTOCOL.md that ``teleop conformance`` must catch."""

from __future__ import annotations

import dataclasses
import sys
from typing import Any


def _no_cookie() -> None:  # 4.3 step 2: a TO that welcomes a hello without a cookie
    from teleop.session import protocol

    protocol.TeleoperatorHandshake._retry = lambda self, *a: None  # type: ignore[method-assign]


def _answers_own_offers() -> None:  # 4.4 step 2: a running TO that answers its own session's hello
    from teleop.session import auth, endpoint, protocol

    def answer(self: Any, data: bytes, addr: Any, now_ns: int) -> None:
        body = self.port.open_handshake(data)
        if body is not None and (seen := protocol.peek_hello(body)) is not None:
            self._out.append((self.port.seal(protocol.Reject(seen[0], "no", seen[1])), addr))

    endpoint.Endpoint._handshake_datagram = answer  # type: ignore[method-assign]
    assert auth


def _no_bye() -> None:  # 4.6: no bye at the end
    from teleop.session import endpoint

    endpoint.BYE_COPIES = 0


def _seq_from_5() -> None:  # 3.1: seq does not start at 0
    from teleop.session import port, wire

    encode = wire.encode
    port.wire.encode = lambda p: encode(p._replace(seq=p.seq + 5))  # type: ignore[attr-defined]


def _ignores_retry() -> None:  # 4.3 step 2: an operator that never puts the cookie in its hellos
    from teleop.session import protocol

    encode = protocol.encode

    def no_cookie(msg: Any) -> bytes:
        if isinstance(msg, protocol.Hello):
            msg = dataclasses.replace(msg, cookie=None)
        return encode(msg)

    protocol.encode = no_cookie


# --- faults on the wire that an implementation written from PROTOCOL.md alone was measured to make
# (issue 35): each one once the session runs (the 20th session-key datagram), or on every packet.
FAULT_AT = 20  # the session-key datagram (of this process) that carries a one-off fault


def _on_session_datagram(fault: Any) -> None:
    """Patch ``auth.Sealer.seal`` so that ``fault(sealer, signed)`` rewrites the ``FAULT_AT``-th
    session-key datagram this process seals (``signed``: header and body, before the tag)."""
    from teleop.session import auth

    seal = auth.Sealer.seal
    count = [0]

    def sealed(self: Any, body: bytes) -> bytes:
        if (self._flags >> 1) & 1 != auth.SESSION:
            return seal(self, body)
        count[0] += 1
        if count[0] != FAULT_AT:
            return seal(self, body)
        data = seal(self, body)
        return bytes(fault(self, data))

    auth.Sealer.seal = sealed  # type: ignore[method-assign]


def _retag(sealer: Any, signed: bytes) -> bytes:
    m = sealer._mac.copy()
    m.update(signed)
    return signed + bytes(m.digest())


def _bad_mac() -> None:  # 2.1: one datagram whose tag does not verify
    _on_session_datagram(lambda s, d: d[:-1] + bytes([d[-1] ^ 0x01]))


def _wrong_direction() -> None:  # 2.1: one datagram with the other side's direction bit, tag valid
    _on_session_datagram(lambda s, d: _retag(s, d[:1] + bytes([d[1] ^ 0x01]) + d[2:-16]))


def _reserved_bits() -> None:  # 2.1: one datagram with a reserved flag bit set, tag valid
    _on_session_datagram(lambda s, d: _retag(s, d[:1] + bytes([d[1] | 0x04]) + d[2:-16]))


def _counter_jump() -> None:  # 2.3: the counter jumps by 100000 once
    from teleop.session import auth

    seal = auth.Sealer.seal
    count = [0]

    def sealed(self: Any, body: bytes) -> bytes:
        if (self._flags >> 1) & 1 == auth.SESSION:
            count[0] += 1
            if count[0] == FAULT_AT:
                self.counter += 100_000
        return seal(self, body)

    auth.Sealer.seal = sealed  # type: ignore[method-assign]


def _on_packet(change: Any) -> None:
    """Every data packet this process encodes goes through ``change(packet) -> packet`` first."""
    from teleop.session import port, wire

    encode = wire.encode
    port.wire.encode = lambda p: encode(change(p))  # type: ignore[attr-defined]


def _oversize_payload() -> None:  # 3.5, 4.5: one data packet with a 6000-byte payload
    _on_packet(lambda p: p._replace(payload=bytes(6000)) if p.seq == FAULT_AT else p)


def _energy_2x() -> None:  # 3.6: energy over-reported twice
    _on_packet(lambda p: p._replace(energy=2.0 * p.energy))


def _t_us_off() -> None:  # 3.2: t_us 500 us off its tick
    _on_packet(lambda p: p._replace(t_us=p.t_us + 500) if p.t_us < 2**63 else p)  # (not the size bound's)


def _round_nearest() -> None:  # 3.4: the 16-bit format rounds to nearest instead of toward zero
    import numpy as np

    from teleop.control.codecs import base

    def quantize(self: Any, x: Any, dtype: Any = base._I8) -> Any:
        inv, lo, hi, _ = self._constants(x.shape)
        return np.rint(np.clip(x * inv, lo, hi)).astype(dtype)

    base.RawFormat.quantize = quantize  # type: ignore[method-assign]


def _deadband_no_budget() -> None:  # 3.6: pd/pdp hold and send without the energy budget (eq. 10)
    from teleop.control.codecs import deadband

    deadband.DeadbandEncoder.power = True  # the deadband's rules 2 and 3 off, as on a power variable


def _phase_0() -> None:  # 5.1: a teleoperator that runs its ticks with the operator's (phase 0)
    from teleop.session import endpoint
    from teleop.session.link import phase

    from_to = endpoint.Endpoint._from_to_handshake
    init = phase.ClockTracker.__init__

    def pinned(self: Any, dt: float, phase: float = 0.0, moves_phase: bool = False) -> None:
        init(self, dt, phase, False)  # its phase never moves off 0 (a correct one keeps in [0.25, 0.9])

    phase.ClockTracker.__init__ = pinned  # type: ignore[method-assign]

    def zero(self: Any, hs: Any, now_ns: int) -> None:
        hs.params = dataclasses.replace(hs.params, phase=0.0)
        from_to(self, hs, now_ns)

    endpoint.Endpoint._from_to_handshake = zero  # type: ignore[method-assign]


def _late_5() -> None:  # 5.1: ticks run 5 periods late
    from teleop.session import endpoint

    begin, retime = endpoint.Endpoint._begin, endpoint.Endpoint._retime

    def late(self: Any, ev: Any, *a: Any, **kw: Any) -> None:
        begin(self, dataclasses.replace(ev, t0_ns=ev.t0_ns + 5 * round(ev.params.dt * 1e9)), *a, **kw)

    def late_again(self: Any, k: int) -> None:  # (the schedule is set again before each tick)
        retime(self, k)
        self.t0_ns += 5 * round(self.params.dt * 1e9)

    endpoint.Endpoint._begin = late  # type: ignore[method-assign]
    endpoint.Endpoint._retime = late_again  # type: ignore[method-assign]


def _start_skew() -> None:  # 4.3 step 5: an operator whose start_ns is 200 ms off S_O + offset
    from teleop.session import protocol

    encode = protocol.encode

    def skewed(msg: Any) -> bytes:
        if isinstance(msg, protocol.Start):
            msg = dataclasses.replace(msg, start_ns=msg.start_ns + 200_000_000)
        return encode(msg)

    protocol.encode = skewed


def _short_lead() -> None:  # 4.3 step 5: an operator whose start lead is 100 ms (< 3 rtt + 150 ms)
    from teleop.session import protocol

    protocol.start_lead = lambda *a, **kw: 100_000_000


def _on_hello(change: Any) -> None:
    """Every hello this process encodes has its msgpack map rewritten by ``change(m)``."""
    import msgpack

    from teleop.session import protocol

    encode = protocol.encode

    def changed(msg: Any) -> bytes:
        body = encode(msg)
        if not isinstance(msg, protocol.Hello):
            return body
        m = msgpack.unpackb(body, raw=False)
        change(m)
        return bytes(msgpack.packb(m, use_bin_type=True))

    protocol.encode = changed


def _wave_field() -> None:  # 9: an operator that sends passivity "wave" (it MUST leave it out)
    _on_hello(lambda m: m.setdefault("passivity", "wave"))


def _codec_upper() -> None:  # 4.1, 4.2: an operator that spells its hello's codec in capitals
    _on_hello(lambda m: m.update(codec=str(m["codec"]).upper()))  # EDS:50: not its canonical text


def _array16() -> None:  # 3.1: data bodies encoded as msgpack array 16 (dc 00 0a), not fixarray
    import zlib

    from teleop.session import port, wire

    encode = wire.encode

    def array16(p: Any) -> bytes:
        body = encode(p)
        arr = b"\xdc\x00\x0a" + body[1:-4]
        return arr + zlib.crc32(arr).to_bytes(4, "little")

    port.wire.encode = array16  # type: ignore[attr-defined]


def _on_fields(change: Any) -> None:
    """Every data body this process encodes has its 10 msgpack fields rewritten by ``change(fields)``
    (the CRC made anew): faults the receiver MUST refuse every packet for (3.1)."""
    import zlib

    import msgpack

    from teleop.session import port, wire

    encode = wire.encode

    def changed(p: Any) -> bytes:
        fields = msgpack.unpackb(encode(p)[:-4], raw=False)
        arr = bytes(msgpack.packb(change(fields), use_bin_type=True))
        return arr + zlib.crc32(arr).to_bytes(4, "little")

    port.wire.encode = changed  # type: ignore[attr-defined]


def _bad_crc() -> None:  # 3.1: every data body's CRC-32 is wrong
    from teleop.session import port, wire

    encode = wire.encode

    def bad(p: Any) -> bytes:
        body = encode(p)
        return body[:-4] + bytes(x ^ 0xFF for x in body[-4:])

    port.wire.encode = bad  # type: ignore[attr-defined]


def _energy_int() -> None:  # 3.1: energy sent as an integer, not a float64
    _on_fields(lambda f: [*f[:9], int(f[9] * 1e9)])


def _version_2() -> None:  # 3.1: every data packet says version 2
    _on_fields(lambda f: [f[0], 2, *f[2:]])


def _wrong_codec_id() -> None:  # 3.1: every data packet names another codec
    _on_fields(lambda f: [*f[:7], (f[7] + 1) % 256, *f[8:]])


def _magic_str() -> None:  # 3.1: magic sent as a str, not bin
    _on_fields(lambda f: [f[0].decode("latin-1"), *f[1:]])


def _wrong_session() -> None:  # 3.1: every data packet names another session
    _on_packet(lambda p: p._replace(session=p.session ^ 1))


def _wrong_direction_field() -> None:  # 3.1: every data packet names the other direction
    _on_packet(lambda p: p._replace(direction=p.direction ^ 1))


def _payload_1() -> None:  # 3.5: every payload one byte long
    _on_packet(lambda p: p._replace(payload=p.payload[:1]))


def _answers_replays() -> None:  # 2.4, 4.3 step 6: a robot whose window takes a counter twice
    from teleop.session import auth

    accept = auth.Opener.accept

    def again(self: Any, counter: int, now: float) -> None:
        try:
            accept(self, counter, now)
        except auth.AuthError as e:
            if e.reason != "replay":
                raise

    auth.Opener.accept = again  # type: ignore[method-assign]


def _keeps_ghost() -> None:  # 4.3 step 8: a TO that holds a session its operator never joined
    from teleop.session import node

    node._Node.expect_first_by = lambda self, t: None  # type: ignore[method-assign]


def _phase_097() -> None:  # 5.1: a teleoperator that ticks 0.97 of a period after the operator (<= 0.9)
    from teleop.session.link import phase

    init = phase.ClockTracker.__init__

    def pinned(self: Any, dt: float, phase: float = 0.0, moves_phase: bool = False) -> None:
        init(self, dt, 0.97 if moves_phase else phase, False)  # (the operator's keeps 0)

    phase.ClockTracker.__init__ = pinned  # type: ignore[method-assign]


def _started_counter_2() -> None:  # 2.3, 4.3 step 6: a TO whose session counter starts at 2
    from teleop.session import auth, wire

    init = auth.Sealer.__init__

    def from_2(self: Any, key: bytes, kind: int, direction: int, counter: int = 1) -> None:
        bump = kind == auth.SESSION and direction == wire.BACKWARD and counter == 1
        init(self, key, kind, direction, 2 if bump else counter)

    auth.Sealer.__init__ = from_2  # type: ignore[method-assign]


def _start_copies() -> None:  # 2.3, 4.3 step 5: an operator that resends its start byte for byte
    from teleop.session import auth, protocol

    seal = auth.Sealer.seal
    first: dict[int, bytes] = {}  # sealer -> its first start, sealed once

    def copied(self: Any, body: bytes) -> bytes:
        if not (protocol.is_control(body) and isinstance(protocol.parse(body), protocol.Start)):
            return seal(self, body)
        return first.setdefault(id(self), seal(self, body))

    auth.Sealer.seal = copied  # type: ignore[method-assign]


def _data_under_handshake_key() -> None:  # 2.2: one data packet sealed under K_hs (kind bit 0)
    from teleop.session import auth, protocol

    init, seal = auth.Sealer.__init__, auth.Sealer.seal
    handshake: dict[int, Any] = {}  # direction -> this process's newest handshake-key sealer
    count = [0]

    def remember(self: Any, key: bytes, kind: int, direction: int, counter: int = 1) -> None:
        init(self, key, kind, direction, counter)
        if kind == auth.HANDSHAKE:
            handshake[direction] = self

    def sealed(self: Any, body: bytes) -> bytes:
        kind, direction = (self._flags >> 1) & 1, self._flags & 1
        if kind == auth.SESSION and not protocol.is_control(body) and direction in handshake:
            count[0] += 1
            if count[0] == FAULT_AT:
                return seal(handshake[direction], body)
        return seal(self, body)

    auth.Sealer.__init__ = remember  # type: ignore[method-assign]
    auth.Sealer.seal = sealed  # type: ignore[method-assign]


def _nonces(nonce: bytes) -> None:
    """Every handshake nonce (16 bytes) this process draws is ``nonce`` (its cookie secret stays random)."""
    import secrets

    from teleop.session import endpoint

    init = endpoint.Endpoint.__init__

    def fixed(self: Any, *a: Any, **kw: Any) -> None:
        kw["rng"] = lambda n: nonce if n == len(nonce) else secrets.token_bytes(n)
        init(self, *a, **kw)

    endpoint.Endpoint.__init__ = fixed  # type: ignore[method-assign]


def _zero_nonce() -> None:  # 2.2: the nonce is all zero, not from a cryptographic random source
    _nonces(bytes(16))


def _constant_nonce() -> None:  # 2.2: one nonce for every handshake (not fresh)
    _nonces(bytes(range(1, 17)))


def _five_byes() -> None:  # 4.6: five copies of the bye, each its own counter: no fault (conforms)
    from teleop.session import endpoint

    endpoint.BYE_COPIES = 5


BREAKS = {
    "keeps-ghost": _keeps_ghost,
    "no-cookie": _no_cookie,
    "answers-own-offers": _answers_own_offers,
    "no-bye": _no_bye,
    "seq-from-5": _seq_from_5,
    "ignores-retry": _ignores_retry,
    "bad-mac": _bad_mac,
    "wrong-direction": _wrong_direction,
    "reserved-bits": _reserved_bits,
    "counter-jump": _counter_jump,
    "oversize-payload": _oversize_payload,
    "energy-2x": _energy_2x,
    "t-us-off": _t_us_off,
    "round-nearest": _round_nearest,
    "deadband-no-budget": _deadband_no_budget,
    "phase-0": _phase_0,
    "late-5": _late_5,
    "start-skew": _start_skew,
    "short-lead": _short_lead,
    "wave-field": _wave_field,
    "codec-upper": _codec_upper,
    "array16": _array16,
    "answers-replays": _answers_replays,
    "bad-crc": _bad_crc,
    "energy-int": _energy_int,
    "version-2": _version_2,
    "wrong-codec-id": _wrong_codec_id,
    "magic-str": _magic_str,
    "payload-1": _payload_1,
    "wrong-session": _wrong_session,
    "wrong-direction-field": _wrong_direction_field,
    "phase-0.97": _phase_097,
    "started-counter-2": _started_counter_2,
    "start-copies": _start_copies,
    "data-under-handshake-key": _data_under_handshake_key,
    "zero-nonce": _zero_nonce,
    "constant-nonce": _constant_nonce,
    "five-byes": _five_byes,
}

if __name__ == "__main__":
    BREAKS[sys.argv[1]]()
    from teleop.cli.parser import main

    sys.exit(main(sys.argv[2:]))
