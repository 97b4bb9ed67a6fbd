"""teleop.session.auth: envelopes, the replay window, key derivation and key files.

No timing asserts: constant-time comparison is hmac.compare_digest's job, and speed is bench/auth.py's.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from teleop.session import auth
from teleop.session.auth import (
    HANDSHAKE,
    HEADER_BYTES,
    OVERHEAD,
    SESSION,
    TAG_BYTES,
    AuthError,
    Opener,
    Sealer,
)

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
BODY = b"forty bytes of a haptic data packet....."


def _reason(fn: Callable[..., object], *args: object) -> str:
    with pytest.raises(AuthError) as e:
        fn(*args)
    assert isinstance(e.value, ValueError)
    return e.value.reason


def _state(o: Opener) -> tuple[int, int, float]:
    """What the replay window holds: the highest counter, the bitmap, when the highest came."""
    return o.highest, o._seen, o._highest_at


# --- envelopes -------------------------------------------------------------------------------------


def test_constants() -> None:
    assert (auth.KEY_BYTES, TAG_BYTES, auth.NONCE_BYTES, HEADER_BYTES) == (32, 16, 16, 10)
    assert OVERHEAD == 26 and auth.ENVELOPE_VERSION == 1 and (HANDSHAKE, SESSION) == (0, 1)
    assert auth.INSECURE_KEY == b"\0" * 32


@pytest.mark.parametrize("body", [b"", b"x", BODY, bytes(1400)])
@pytest.mark.parametrize("kind,direction", [(0, 0), (0, 1), (1, 0), (1, 1)])
def test_round_trip(body: bytes, kind: int, direction: int) -> None:
    s, o = Sealer(KEY, kind, direction), Opener(KEY, kind, direction)
    for counter in (1, 2, 3):
        d = s.seal(body)
        assert len(d) == len(body) + OVERHEAD
        assert d[:1] == b"T" and d[1] == (1 << 4) | (kind << 1) | direction
        assert int.from_bytes(d[2:10], "big") == counter
        assert auth.peek(d) == (kind, direction, counter)
        assert o.verify(d) == (counter, body)
        assert o.open(d, 0.0) == (counter, body)
    assert s.counter == 4


def test_sealer_counters() -> None:
    s = Sealer(KEY, SESSION, 0, counter=41)
    assert auth.peek(s.seal(BODY)) == (SESSION, 0, 41) and s.counter == 42
    last = Sealer(KEY, SESSION, 0, counter=2**64 - 1)
    assert auth.peek(last.seal(BODY)) == (SESSION, 0, 2**64 - 1)
    with pytest.raises(ValueError, match="counter exhausted"):
        last.seal(BODY)
    for bad in (0, -1, 2**64):
        with pytest.raises(ValueError, match="counter must be"):
            Sealer(KEY, SESSION, 0, counter=bad)


@pytest.mark.parametrize(
    "make",
    [
        lambda: Sealer(bytes(31), 0, 0),
        lambda: Sealer(KEY, 2, 0),
        lambda: Sealer(KEY, 0, -1),
        lambda: Opener(bytes(33), 0, 0),
        lambda: Opener(KEY, 0, 0, window=0),
        lambda: auth.session_keys(KEY, 1, bytes(15), bytes(16)),
        lambda: auth.session_keys(KEY, 2**32, bytes(16), bytes(16)),
        lambda: auth.handshake_key(b"short"),
    ],
)
def test_bad_parameters(make: Callable[[], object]) -> None:
    with pytest.raises(ValueError):
        make()


_SEALED = Sealer(KEY, SESSION, 1, counter=1000).seal(BODY)


@given(st.integers(0, 8 * len(_SEALED) - 1))
def test_any_flipped_bit_is_rejected(bit: int) -> None:
    d = bytearray(_SEALED)
    d[bit // 8] ^= 1 << (bit % 8)
    o = Opener(KEY, SESSION, 1)
    assert _reason(o.verify, bytes(d)) in ("header", "kind", "direction", "tag")
    assert _reason(o.open, bytes(d), 0.0) in ("header", "kind", "direction", "tag")
    assert _state(o) == (0, 0, 0.0)  # nothing accepted


def test_where_a_flip_is_caught() -> None:
    o = Opener(KEY, SESSION, 1)

    def flip(i: int, mask: int) -> bytes:
        d = bytearray(_SEALED)
        d[i] ^= mask
        return bytes(d)

    assert _reason(o.verify, flip(0, 1)) == "header"  # magic
    assert _reason(o.verify, flip(1, 0x10)) == "header"  # version
    assert _reason(o.verify, flip(1, 0x04)) == "header"  # a reserved bit
    assert _reason(o.verify, flip(1, 0x02)) == "kind"
    assert _reason(o.verify, flip(1, 0x01)) == "direction"
    assert _reason(o.verify, flip(9, 1)) == "tag"  # counter
    assert _reason(o.verify, flip(HEADER_BYTES, 1)) == "tag"  # body
    assert _reason(o.verify, flip(len(_SEALED) - 1, 0x80)) == "tag"  # tag


def test_counter_zero_is_not_an_envelope() -> None:
    d = bytearray(Sealer(KEY, SESSION, 0).seal(BODY))
    d[2:10] = bytes(8)
    assert _reason(Opener(KEY, SESSION, 0).verify, bytes(d)) == "header"
    assert auth.peek(bytes(d)) is None
    with pytest.raises(AuthError):
        Opener(KEY, SESSION, 0).accept(0, 0.0)


def test_truncated_at_every_length_and_extended() -> None:
    o = Opener(KEY, SESSION, 1)
    for n in range(len(_SEALED)):
        reason = _reason(o.verify, _SEALED[:n])
        assert reason == ("short" if n < OVERHEAD else "tag"), n
    assert _reason(o.verify, _SEALED + b"\0") == "tag"
    assert _reason(o.verify, b"") == "short"
    assert _state(o) == (0, 0, 0.0)


def test_wrong_key_kind_direction() -> None:
    d = Sealer(KEY, SESSION, 0).seal(BODY)
    assert _reason(Opener(OTHER_KEY, SESSION, 0).verify, d) == "tag"
    assert _reason(Opener(auth.INSECURE_KEY, SESSION, 0).verify, d) == "tag"
    assert _reason(Opener(KEY, HANDSHAKE, 0).verify, d) == "kind"
    assert _reason(Opener(KEY, SESSION, 1).verify, d) == "direction"
    # --insecure: the envelope and its integrity check are the same, with a key everyone knows
    i = Sealer(auth.INSECURE_KEY, SESSION, 0).seal(BODY)
    assert Opener(auth.INSECURE_KEY, SESSION, 0).verify(i) == (1, BODY)
    assert _reason(Opener(KEY, SESSION, 0).verify, i) == "tag"


def test_peek_is_not_fooled_by_other_datagrams() -> None:
    assert auth.peek(b"") is None
    assert auth.peek(b"T\x10" + bytes(8)) is None  # too short to be an envelope
    assert auth.peek(bytes(64)) is None
    assert auth.peek(b"\x9a" + bytes(63)) is None  # a msgpack array (a bare data packet)
    assert auth.peek(b"T\x20" + (1).to_bytes(8, "big") + bytes(16)) is None  # version 2
    assert auth.peek(b"T\x1c" + (1).to_bytes(8, "big") + bytes(16)) is None  # reserved bits
    assert auth.peek(b"T\x13" + (7).to_bytes(8, "big") + bytes(16)) == (1, 1, 7)  # unverified


# --- the replay window -----------------------------------------------------------------------------


def test_replay_of_the_same_datagram() -> None:
    s, o = Sealer(KEY, SESSION, 0), Opener(KEY, SESSION, 0)
    d = s.seal(BODY)
    assert o.open(d, 0.0) == (1, BODY)
    assert _reason(o.open, d, 0.0) == "replay"
    assert _reason(o.open, d, 100.0) == "replay"
    assert o.verify(d) == (1, BODY)  # verify alone does not know about replays


def test_out_of_order_within_the_window_once_each() -> None:
    s, o = Sealer(KEY, SESSION, 0), Opener(KEY, SESSION, 0, window=128)
    ds = [s.seal(bytes([i % 256])) for i in range(1, 201)]  # counters 1..200
    assert o.open(ds[199], 0.0)[0] == 200  # the first one is free (a late joiner)
    for c in range(73, 200):  # 200 - 127 .. 199: inside the window, in any order
        assert o.open(ds[c - 1], 0.0)[0] == c
        assert _reason(o.open, ds[c - 1], 0.0) == "replay"
    for c in (72, 1, 50):  # 200 - 128 and older: beyond the window
        assert _reason(o.open, ds[c - 1], 0.0) == "replay"


def test_first_counter_is_free_then_older_is_fine_in_the_window() -> None:
    o = Opener(KEY, SESSION, 0, window=4)
    o.accept(2**64 - 1, 0.0)  # any counter first, even the last one
    o.accept(2**64 - 3, 0.0)
    assert _reason(o.accept, 2**64 - 5, 0.0) == "replay"
    assert _reason(o.accept, 2**64 - 1, 0.0) == "replay"


@given(
    window=st.integers(1, 40),
    steps=st.lists(st.tuples(st.integers(1, 400), st.floats(0.0, 0.05)), max_size=200),
)
def test_window_against_a_set_model(window: int, steps: list[tuple[int, float]]) -> None:
    base, rate = 30, 1000.0
    o = Opener(KEY, SESSION, 0, window=window, jump_base=base, jump_rate=rate)
    seen: set[int] = set()
    highest, highest_at, now = 0, 0.0, 0.0
    for counter, dt in steps:
        now += dt
        if not seen:
            expect = "ok"
        elif counter > highest:
            expect = "ok" if counter - highest <= base + rate * (now - highest_at) else "jump"
        else:
            expect = "ok" if counter not in seen and highest - counter < window else "replay"
        before = _state(o)
        try:
            o.accept(counter, now)
            got = "ok"
        except AuthError as e:
            got = e.reason
            assert _state(o) == before  # a refused counter changes nothing
        assert got == expect, (counter, now, highest, sorted(seen))
        if got == "ok":
            seen.add(counter)
            if counter > highest:
                highest, highest_at = counter, now
        assert o.highest == highest


def test_far_future_counter_is_a_jump_until_enough_time_has_passed() -> None:
    o = Opener(KEY, SESSION, 0)  # jump_base 1024, jump_rate 4000/s
    o.accept(10, 5.0)
    assert _reason(o.accept, 10 + 1025, 5.0) == "jump"
    assert _reason(o.accept, 2**64 - 1, 5.0) == "jump"
    assert _state(o) == (10, 1, 5.0)
    o.accept(10 + 1024, 5.0)  # jump_base ahead: fine at once
    assert _reason(o.accept, 1034 + 1024 + 4001, 6.0) == "jump"
    o.accept(1034 + 1024 + 4000, 6.0)  # one second later: 4000 more
    assert o.highest == 6058
    # a clock that went back counts as no time elapsed, not as negative allowance
    o.accept(6058 + 1024, 1.0)
    # an outage of 100 s at 1 kHz: the sender's counter is 100 000 ahead, and that is fine
    o.accept(7082 + 100_000, 101.0)


def test_verify_changes_no_state_and_forgeries_never_move_the_window() -> None:
    s, o = Sealer(KEY, SESSION, 0), Opener(KEY, SESSION, 0)
    d1 = s.seal(BODY)
    o.open(d1, 0.0)
    before = _state(o)
    forger = Sealer(OTHER_KEY, SESSION, 0, counter=500)
    for _ in range(5):
        assert _reason(o.open, forger.seal(BODY), 0.0) == "tag"
    tampered = bytearray(Sealer(KEY, SESSION, 0, counter=2).seal(BODY))
    tampered[2:10] = (900).to_bytes(8, "big")  # a real datagram, its counter moved far ahead
    assert _reason(o.open, bytes(tampered), 1000.0) == "tag"
    assert _state(o) == before
    ds = [s.seal(BODY) for _ in range(3)]  # counters 2..4
    for d in ds:
        assert o.verify(d)[0] in (2, 3, 4)
        assert o.verify(d)[0] in (2, 3, 4)
    assert _state(o) == before  # verified twice, accepted never
    assert [o.open(d, 0.0)[0] for d in ds] == [2, 3, 4]


def test_rekey_starts_a_fresh_window() -> None:
    o = Opener(KEY, SESSION, 0)
    o.open(Sealer(KEY, SESSION, 0, counter=100).seal(BODY), 0.0)
    o.rekey(OTHER_KEY)
    assert _state(o) == (0, 0, 0.0)
    assert _reason(o.open, Sealer(KEY, SESSION, 0, counter=101).seal(BODY), 0.0) == "tag"
    assert o.open(Sealer(OTHER_KEY, SESSION, 0).seal(BODY), 0.0) == (1, BODY)  # counter 1 again


def test_auth_error_reason() -> None:
    e = AuthError("replay", "counter 3 already seen")
    assert isinstance(e, ValueError) and e.reason == "replay" and str(e) == "counter 3 already seen"
    assert str(AuthError("tag")) == "tag"


# --- key derivation --------------------------------------------------------------------------------

N1, N2, N3 = bytes(16), bytes(range(16)), bytes(range(16, 32))


def test_session_keys_are_deterministic_and_distinct() -> None:
    fwd, bwd = auth.session_keys(KEY, 7, N1, N2)
    assert (fwd, bwd) == auth.session_keys(KEY, 7, N1, N2)
    assert len(fwd) == len(bwd) == 32 and fwd != bwd
    variants = [
        auth.session_keys(KEY, 8, N1, N2),
        auth.session_keys(KEY, 7, N3, N2),
        auth.session_keys(KEY, 7, N1, N3),
        auth.session_keys(KEY, 7, N2, N1),  # nonces swapped
        auth.session_keys(OTHER_KEY, 7, N1, N2),
    ]
    keys = {fwd, bwd, auth.handshake_key(KEY), KEY} | {k for pair in variants for k in pair}
    assert len(keys) == 4 + 2 * len(variants)  # all unrelated
    assert auth.handshake_key(KEY) == auth.handshake_key(KEY) != auth.handshake_key(OTHER_KEY)


def test_a_datagram_of_one_session_or_direction_is_refused_in_another() -> None:
    fwd, bwd = auth.session_keys(KEY, 7, N1, N2)
    d = Sealer(fwd, SESSION, 0).seal(BODY)
    assert Opener(fwd, SESSION, 0).verify(d) == (1, BODY)
    assert _reason(Opener(bwd, SESSION, 0).verify, d) == "tag"  # reflected with the direction bit kept
    assert _reason(Opener(auth.session_keys(KEY, 7, N1, N3)[0], SESSION, 0).verify, d) == "tag"
    assert _reason(Opener(auth.handshake_key(KEY), SESSION, 0).verify, d) == "tag"


def test_key_id() -> None:
    kid = auth.key_id(KEY)
    assert kid == auth.key_id(KEY) and len(kid) == 8 and int(kid, 16) >= 0
    assert kid not in KEY.hex() and kid != auth.key_id(OTHER_KEY)
    assert auth.key_id(auth.INSECURE_KEY) == "insecure"
    assert len({auth.key_id(auth.generate_key()) for _ in range(50)}) == 50


def test_generate_key() -> None:
    a, b = auth.generate_key(), auth.generate_key()
    assert len(a) == len(b) == 32 and a != b


# --- key files -------------------------------------------------------------------------------------


def test_key_file_round_trip_and_mode(tmp_path: Path) -> None:
    path = tmp_path / "teleop.key"
    key = auth.generate_key()
    auth.write_key_file(path, key)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert path.read_text() == key.hex() + "\n"
    assert auth.read_key_file(path) == key
    assert auth.read_key_file(str(path)) == key


def test_key_file_is_never_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "teleop.key"
    auth.write_key_file(path, KEY)
    with pytest.raises(ValueError, match="exists; refusing to overwrite a key"):
        auth.write_key_file(path, OTHER_KEY)
    assert auth.read_key_file(path) == KEY
    with pytest.raises(ValueError, match="cannot create key file"):
        auth.write_key_file(tmp_path / "no" / "such" / "dir", KEY)


def test_key_file_accepts_upper_case_and_no_newline(tmp_path: Path) -> None:
    path = tmp_path / "k"
    path.write_text(KEY.hex().upper())
    path.chmod(0o400)
    assert auth.read_key_file(path) == KEY


def _bad(path: Path, content: str | None, mode: int = 0o600) -> Path:
    if content is not None:
        path.write_text(content)
        path.chmod(mode)
    return path


@pytest.mark.parametrize(
    "content,mode,msg",
    [
        (None, 0o600, "does not exist (make one with 'teleop keygen "),
        ("", 0o600, "does not hold a key: expected 64 hex characters"),
        (KEY.hex()[:-2], 0o600, "does not hold a key"),
        (KEY.hex() + "00", 0o600, "does not hold a key"),
        ("g" * 64, 0o600, "does not hold a key"),
        ("0x" + KEY.hex()[2:], 0o600, "does not hold a key"),
        (KEY.hex(), 0o644, "must be readable by its owner only (chmod 600 "),
        (KEY.hex(), 0o640, "open to its group or others (mode 640)"),
        (KEY.hex(), 0o604, "must be readable by its owner only"),
        (KEY.hex(), 0o660, "must be readable by its owner only"),
    ],
)
def test_bad_key_file(tmp_path: Path, content: str | None, mode: int, msg: str) -> None:
    path = _bad(tmp_path / "k", content, mode)
    with pytest.raises(ValueError) as e:
        auth.read_key_file(path)
    text = str(e.value)
    assert msg in text and str(path) in text and "\n" not in text, text


def test_key_file_directory_fifo_unreadable(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="is a directory, not a key file"):
        auth.read_key_file(tmp_path)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo, 0o600)
    with pytest.raises(ValueError, match="is not a regular file"):
        auth.read_key_file(fifo)  # refused at once, not a hang
    if os.geteuid() != 0:  # root reads anything
        locked = tmp_path / "locked"
        auth.write_key_file(locked, KEY)
        locked.chmod(0o000)
        with pytest.raises(ValueError, match=r"cannot read key file .*: Permission denied"):
            auth.read_key_file(locked)


@pytest.mark.skipif(os.geteuid() != 0, reason="chown to another user needs root")
def test_a_key_file_of_another_user_is_refused_even_0600_in_a_sticky_folder(tmp_path: Path) -> None:
    """Issue 49: a 0600 key file another user planted in a sticky world-writable folder (as /tmp)
    was taken; it is refused in one line, as a log of another user's is."""
    folder = tmp_path / "shared"
    folder.mkdir()
    folder.chmod(0o1777)
    path = folder / "k"
    auth.write_key_file(path, KEY)
    assert auth.read_key_file(path) == KEY  # this user's (root's): taken
    os.chown(path, 4321, 4321)
    with pytest.raises(ValueError) as e:
        auth.read_key_file(path)
    text = str(e.value)
    assert "owned by uid 4321" in text and str(path) in text and "\n" not in text, text
