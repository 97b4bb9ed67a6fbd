"""Authenticated datagrams: a pre-shared key, a counter in an authenticated header, a tag, a replay window.

The pattern of SRTP (RFC 3711 §3.3) and WireGuard: every datagram is wrapped in an envelope

    b"T" | flags (1) | counter (uint64, big-endian) | body | tag (16)

where ``flags`` holds the envelope version (high 4 bits), the key kind (bit 1: handshake or session
key) and the direction (bit 0: the sender's), and the tag is keyed BLAKE2s over header and body.
A receiver checks the tag in constant time before it looks at the body, then holds the counter to a
sliding replay window, so a datagram from anyone without the key, or one replayed, never reaches the
protocol.  The body is authenticated, not encrypted: haptic samples are not secret, their origin is.

Keys: one pre-shared key per deployment (:func:`generate_key`, :func:`write_key_file`), from which
:func:`handshake_key` derives the key of the handshake and :func:`session_keys` one key per session
and direction, bound to both sides' nonces, so a datagram of one session or direction is never
accepted in another and a restarted peer (new nonce) starts from fresh keys and counters.

Pure: no clock reads and no sockets; the caller passes ``now`` to :meth:`Opener.accept`.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import stat
import struct

from teleop.errors import RemoteError

KEY_BYTES = 32
TAG_BYTES = 16
NONCE_BYTES = 16
HEADER_BYTES = 10  # b"T", one flags byte, counter uint64 big-endian
OVERHEAD = HEADER_BYTES + TAG_BYTES  # 26 bytes added to every datagram
ENVELOPE_VERSION = 1
HANDSHAKE, SESSION = 0, 1  # key kinds
#: ``--insecure``: the envelope is still there, but with a key everyone knows its tag checks integrity only.
INSECURE_KEY = bytes(KEY_BYTES)

MAGIC = b"T"
MAX_COUNTER = 2**64 - 1
_PERSON = b"teleopv1"  # BLAKE2 personalization: these derivations are never confused with another use
_HEADER = struct.Struct(">cBQ")
_RESERVED = 0x0C  # flags bits 2 and 3: zero in version 1
REASONS = ("short", "header", "kind", "direction", "tag", "replay", "jump")


class AuthError(RemoteError):
    """A datagram that is not accepted; ``reason`` is one of :data:`REASONS` (to count, not to print)."""

    def __init__(self, reason: str, message: str | None = None) -> None:
        assert reason in REASONS, reason
        super().__init__(message or reason)
        self.reason = reason


def _check_key(key: bytes) -> bytes:
    if not isinstance(key, bytes | bytearray) or len(key) != KEY_BYTES:
        raise ValueError(f"a key is {KEY_BYTES} bytes")
    return bytes(key)


def _check_bit(what: str, value: int) -> int:
    if value not in (0, 1):
        raise ValueError(f"{what} must be 0 or 1, got {value!r}")
    return value


# --- keys ------------------------------------------------------------------------------------------


def key_id(psk: bytes) -> str:
    """8 hex characters naming a key (to compare two hosts' keys in logs) without revealing it."""
    if psk == INSECURE_KEY:
        return "insecure"
    return hashlib.blake2s(b"key id", key=_check_key(psk), person=_PERSON, digest_size=4).hexdigest()


def generate_key() -> bytes:
    """A new pre-shared key from the OS's cryptographic random source."""
    return secrets.token_bytes(KEY_BYTES)


def write_key_file(path: str | os.PathLike[str], key: bytes) -> None:
    """Write ``key`` as 64 hex characters and a newline to a new file readable by its owner only.

    The file is created with O_EXCL and mode 0600 in one step, so the key is never readable by
    anyone else, not even for a moment, and an existing key is never overwritten (ValueError).
    """
    key = _check_key(key)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise ValueError(f"{os.fsdecode(path)} exists; refusing to overwrite a key") from None
    except OSError as e:
        raise ValueError(f"cannot create key file {os.fsdecode(path)}: {e.strerror or e}") from None
    try:
        with os.fdopen(fd, "w") as f:
            f.write(key.hex() + "\n")
    except OSError as e:  # a disk full: leave no half-written key behind
        os.unlink(path)
        raise ValueError(f"cannot write key file {os.fsdecode(path)}: {e.strerror or e}") from None


def read_key_file(path: str | os.PathLike[str]) -> bytes:
    """The key in ``path``; ValueError (one line naming the file and the fix) if it is not a good key file.

    Like ssh with a private key, a key file that its group or others can read is refused: the key
    would no longer be secret.  So is one owned by another user than this one or root: it may have
    been planted (issue 49).
    """
    name = os.fsdecode(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # O_NONBLOCK: a FIFO must not hang us
    except FileNotFoundError:
        raise ValueError(f"key file {name} does not exist (make one with 'teleop keygen {name}')") from None
    except IsADirectoryError:
        raise ValueError(f"key file {name} is a directory, not a key file") from None
    except OSError as e:
        raise ValueError(f"cannot read key file {name}: {e.strerror or e}") from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise ValueError(f"key file {name} is a directory, not a key file")
        if not stat.S_ISREG(st.st_mode):
            raise ValueError(f"key file {name} is not a regular file")
        # Owned by this user or root, as log folders (teleop.files): another user's file, even 0600,
        # may have been planted (a sticky /tmp stops others replacing our files, not adding theirs).
        if st.st_uid not in (0, os.geteuid()):
            raise ValueError(
                f"key file {name} is owned by uid {st.st_uid}, not by this user ({os.geteuid()}) or root: "
                "not used (another user could have planted it)"
            )
        if st.st_mode & 0o077:
            raise ValueError(
                f"key file {name} is open to its group or others (mode {stat.S_IMODE(st.st_mode):o}); "
                f"it must be readable by its owner only (chmod 600 {name})"
            )
        raw = os.read(fd, 4 * KEY_BYTES)  # a key file is 65 bytes: never read a large file whole
    except OSError as e:
        raise ValueError(f"cannot read key file {name}: {e.strerror or e}") from None
    finally:
        os.close(fd)
    text = raw.strip()
    if len(text) != 2 * KEY_BYTES or any(c not in b"0123456789abcdefABCDEF" for c in text):
        raise ValueError(
            f"key file {name} does not hold a key: expected {2 * KEY_BYTES} hex characters "
            f"(make one with 'teleop keygen FILE')"
        )
    return bytes.fromhex(text.decode("ascii"))


#: A robot's name: what an operator names to reach it (``--robot-name``), bound into every key.
ROBOT_NAME_CHARS = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789._-")
MAX_ROBOT_NAME = 64
DEFAULT_ROBOT_NAME = "robot"


def check_robot_name(name: str) -> str:
    """``name`` if it is 1 to 64 of ``[A-Za-z0-9._-]``; else ValueError saying what is allowed."""
    if not isinstance(name, str) or not 1 <= len(name) <= MAX_ROBOT_NAME or not set(name) <= ROBOT_NAME_CHARS:
        raise ValueError(
            f"a robot name is 1 to {MAX_ROBOT_NAME} of the characters A-Z a-z 0-9 . _ -, got {name!r:.80}"
        )
    return name


def robot_key(psk: bytes, name: str) -> bytes:
    """The key of the robot named ``name``, derived from the deployment's pre-shared key.

    Every handshake and session key of a robot derives from this one (not from the deployment key),
    so an operator that names robot A verifies only what A's key sealed: a relay that hands A's
    handshake to robot B, which holds the same deployment key, fails at B (silent) and at the
    operator.  (Each robot holds the deployment key, so a compromised robot could derive another's:
    names guard against relays and mix-ups, not against a hostile robot.)"""
    data = b"robot\x00" + check_robot_name(name).encode("ascii")
    return hashlib.blake2s(data, key=_check_key(psk), person=_PERSON).digest()


def handshake_key(psk: bytes) -> bytes:
    """The key of the handshake's envelopes, derived so the pre-shared key itself never keys a MAC."""
    return hashlib.blake2s(b"handshake", key=_check_key(psk), person=_PERSON).digest()


ZENOH_USER = "teleop"
"""The Zenoh user of the peer-mode admission (PROTOCOL.md section 1; password :func:`zenoh_password`)."""


def zenoh_password(robot: bytes) -> str:
    """The Zenoh password (64 hex digits) for the robot key ``robot`` (:func:`robot_key`).

    In peer mode a listening endpoint admits only Zenoh peers that present it (Zenoh's user-password
    authentication), so a stranger cannot even open a Zenoh link to publish on the session's keys:
    its samples are refused in Zenoh's own threads, before our callback holds the GIL for each.
    Derived, like every key here, so the robot key itself never travels or keys another use."""
    return hashlib.blake2s(b"zenoh usrpwd", key=_check_key(robot), person=_PERSON).hexdigest()


def session_keys(psk: bytes, session: int, nonce_op: bytes, nonce_to: bytes) -> tuple[bytes, bytes]:
    """(forward key, backward key) of one session, bound to its id and both sides' fresh nonces.

    As in WireGuard, each direction has its own key, and each run its own keys: a datagram
    recorded in one session, or reflected back to its sender, is never accepted.
    """
    psk = _check_key(psk)
    if not 0 <= session <= 2**32 - 1:
        raise ValueError(f"session must be 0..{2**32 - 1}, got {session}")
    for what, n in (("nonce_op", nonce_op), ("nonce_to", nonce_to)):
        if len(n) != NONCE_BYTES:
            raise ValueError(f"{what} must be {NONCE_BYTES} bytes, got {len(n)}")
    context = session.to_bytes(4, "big") + bytes(nonce_op) + bytes(nonce_to)
    forward, backward = (
        hashlib.blake2s(label + context, key=psk, person=_PERSON).digest()
        for label in (b"forward", b"backward")
    )
    return forward, backward


def _mac(key: bytes) -> hashlib.blake2s:
    """The keyed BLAKE2s state after the key block; ``.copy()`` per datagram skips the key setup."""
    return hashlib.blake2s(key=key, digest_size=TAG_BYTES)


# --- envelopes -------------------------------------------------------------------------------------


def _flags(kind: int, direction: int) -> int:
    return (ENVELOPE_VERSION << 4) | (kind << 1) | direction


class Sealer:
    """Wraps datagrams of one kind and direction under one key, with counters 1, 2, 3, ...

    A counter is never reused under a key (it is what the receiver's replay window checks), so a
    new key (a new session) is the only way to start again from 1.
    """

    def __init__(self, key: bytes, kind: int, direction: int, counter: int = 1) -> None:
        if not 1 <= counter <= MAX_COUNTER:
            raise ValueError(f"counter must be 1..2**64-1, got {counter}")
        self._mac = _mac(_check_key(key))
        self._flags = _flags(_check_bit("kind", kind), _check_bit("direction", direction))
        self.counter = counter  # the next counter to use

    def seal(self, body: bytes) -> bytes:
        """header + body + tag; then the counter moves on."""
        if self.counter > MAX_COUNTER:
            raise ValueError("counter exhausted: a new key (session) is needed")
        header = _HEADER.pack(MAGIC, self._flags, self.counter)
        self.counter += 1
        signed = header + body
        m = self._mac.copy()
        m.update(signed)
        return signed + m.digest()


def peek(datagram: bytes) -> tuple[int, int, int] | None:
    """(kind, direction, counter) from an envelope's header, NOT verified (to pick a key); else None."""
    if len(datagram) < OVERHEAD:
        return None
    magic, flags, counter = _HEADER.unpack_from(datagram)
    if magic != MAGIC or flags >> 4 != ENVELOPE_VERSION or flags & _RESERVED or counter == 0:
        return None
    return (flags >> 1) & 1, flags & 1, counter


class Opener:
    """Checks datagrams of one kind and direction under one key, and keeps their replay window.

    Two steps, so a caller can verify, act on the body, and only then commit the counter:
    :meth:`verify` (length, header, tag; no state) and :meth:`accept` (replay window).  The window
    is RFC 3711 §3.3.2's / WireGuard's: the highest counter accepted and a bitmap of the ``window``
    counters below it.  A counter far above the highest one is refused too ("jump"): the sender
    cannot have sent more than ``jump_base + jump_rate * elapsed`` datagrams since (4 kHz is four
    times the 1 kHz rate).  An authentic datagram with such a counter can only be a recording from
    an earlier run under the same key (the handshake key is the same in every run); accepted, it
    would push the window past every counter the live sender will still use and shut it out.
    """

    def __init__(
        self,
        key: bytes,
        kind: int,
        direction: int,
        window: int = 128,
        jump_base: int = 1024,
        jump_rate: float = 4000.0,
    ) -> None:
        if window < 1:
            raise ValueError(f"window must be >= 1, got {window}")
        if jump_base < 0 or not jump_rate >= 0:
            raise ValueError("jump_base and jump_rate must be >= 0")
        self._kind = _check_bit("kind", kind)
        self._direction = _check_bit("direction", direction)
        self.window = window
        self.jump_base = jump_base
        self.jump_rate = jump_rate
        self.rekey(key)

    def rekey(self, key: bytes) -> None:
        """A new key and a fresh window (the peer restarted with new nonces: its counters restart)."""
        self._mac = _mac(_check_key(key))
        self.highest = 0  # the highest counter accepted; 0: none yet
        self._seen = 0  # bit i: counter highest - i accepted
        self._highest_at = 0.0  # ``now`` when ``highest`` was accepted

    def verify(self, datagram: bytes) -> tuple[int, bytes]:
        """(counter, body) of a datagram whose header and tag check out, else AuthError.  Changes no state."""
        if len(datagram) < OVERHEAD:
            raise AuthError("short", f"{len(datagram)} bytes, shorter than an envelope ({OVERHEAD})")
        magic, flags, counter = _HEADER.unpack_from(datagram)
        if magic != MAGIC or flags >> 4 != ENVELOPE_VERSION or flags & _RESERVED or counter == 0:
            raise AuthError("header")
        if (flags >> 1) & 1 != self._kind:
            raise AuthError("kind")
        if flags & 1 != self._direction:
            raise AuthError("direction")
        m = self._mac.copy()
        m.update(datagram[:-TAG_BYTES])  # a slice: cheaper than a memoryview at these sizes
        if not hmac.compare_digest(m.digest(), datagram[-TAG_BYTES:]):
            raise AuthError("tag")
        return counter, bytes(datagram[HEADER_BYTES:-TAG_BYTES])

    def accept(self, counter: int, now: float) -> None:
        """Mark ``counter`` seen, or AuthError("replay") / AuthError("jump") and change nothing.

        Call it only with a counter :meth:`verify` returned: a forged datagram must never move the
        window.  The first counter after a (re)key is accepted whatever it is, since a late joiner
        sees the sender's counters from wherever they are.
        """
        if not 1 <= counter <= MAX_COUNTER:
            raise AuthError("header", f"counter {counter} out of range")
        if self.highest == 0:
            self.highest, self._seen, self._highest_at = counter, 1, now
            return
        if counter > self.highest:
            ahead = counter - self.highest
            if ahead > self.jump_base + self.jump_rate * max(0.0, now - self._highest_at):
                raise AuthError("jump", f"counter {counter} is {ahead} ahead of {self.highest}")
            self._seen = ((self._seen << ahead) | 1) & ((1 << self.window) - 1) if ahead < self.window else 1
            self.highest, self._highest_at = counter, now
            return
        behind = self.highest - counter
        if behind >= self.window:
            raise AuthError("replay", f"counter {counter} is older than the window")
        if (self._seen >> behind) & 1:
            raise AuthError("replay", f"counter {counter} already seen")
        self._seen |= 1 << behind

    def open(self, datagram: bytes, now: float) -> tuple[int, bytes]:
        """:meth:`verify`, then :meth:`accept`: (counter, body) of a new, authentic datagram."""
        counter, body = self.verify(datagram)
        self.accept(counter, now)
        return counter, body


class SeenTags:
    """Drops byte-identical copies of handshake datagrams, which have no replay window.

    A genuine sender never repeats a datagram (its counter moves on), so a copy is a replay; the
    tag identifies it.  Call :meth:`check` after the tag verified and before the costly parse, so a
    flood of one recording costs a tag check per copy.  Remembers the last ``size`` tags.
    """

    def __init__(self, size: int = 1024) -> None:
        self.size = size
        self._tags: dict[bytes, None] = {}  # insertion order: oldest first

    def check(self, datagram: bytes) -> None:
        """Remember ``datagram``'s tag, or AuthError("replay") if it was seen before."""
        tag = bytes(datagram[-TAG_BYTES:])
        if tag in self._tags:
            raise AuthError("replay", "a handshake datagram seen before")
        self._tags[tag] = None
        if len(self._tags) > self.size:
            del self._tags[next(iter(self._tags))]
