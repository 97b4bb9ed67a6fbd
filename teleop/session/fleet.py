"""A robot's description for fleets: what it is, what it affords, free or busy, sealed under its key.

Why a MAC and not only the router's access control: the router's ACL decides who may *declare* a
key, but an operator that reaches a robot through someone else's router (or a misconfigured one)
would have to trust that router.  A description sealed under the robot's key
(:func:`teleop.session.auth.robot_key`) is verified end to end by any holder of the deployment key,
whatever carried it, exactly as every datagram of the session is; the router's ACL is defence in
depth (it keeps strangers from announcing or listing at all).

**Freshness.** Each query carries a fresh random ``nonce`` (the querier's); the tag covers it, so a
description recorded from a robot and replayed after the robot died (or from another query) does not
verify.  No clock is read on either side, and no clocks need agree.

Layout (PROTOCOL.md section 9): ``body | tag(16)`` with ``body`` a msgpack map and
``tag = BLAKE2s-128(key=K_d, message=nonce || body)``, ``K_d`` derived from the robot key.
Pure: no clock, no socket.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import re
from dataclasses import asdict, dataclass, field, fields
from typing import Any

import msgpack

from teleop.session import auth
from teleop.session.settings import Envelope

VERSION = 1
#: The key under which robots announce: a liveliness token ``ROBOTS/<name>`` and a queryable
#: ``ROBOTS/<name>/info``; a robot's data keys default to ``ROBOTS/<name>/forward|backward``.
ROBOTS = "teleop/robots"
INFO = "info"
NONCE_BYTES = 16
TAG_BYTES = 16
#: A description is refused by its length first: a robot's fits in well under 1 kB.
MAX_DESCRIPTION_BYTES = 2048
STATES = ("free", "busy")
MAX_KIND = 32
MAX_PREFIX = 200
_PERSON = b"teleopv1"  # section 2.2's: "describe" is a message no other derivation uses
_PREFIX = re.compile(r"[A-Za-z0-9._-]+(/[A-Za-z0-9._-]+)*")
_ENVELOPE_FIELDS = {f.name for f in fields(Envelope)}


class DescriptionError(ValueError):
    """A description that is not trusted: wrong size, bad tag, or a field out of bounds (one line)."""


def _check_key(key: bytes) -> bytes:
    if not isinstance(key, bytes) or len(key) != auth.KEY_BYTES:
        raise ValueError(f"a key is {auth.KEY_BYTES} bytes")
    return key


def describe_key(robot: bytes) -> bytes:
    """The key that seals descriptions, derived from the robot key so it keys nothing else."""
    return hashlib.blake2s(b"describe", key=_check_key(robot), person=_PERSON).digest()


def token_key(name: str) -> str:
    """The liveliness token of the robot ``name``."""
    return f"{ROBOTS}/{auth.check_robot_name(name)}"


def info_key(name: str) -> str:
    """The queryable that describes the robot ``name``."""
    return f"{token_key(name)}/{INFO}"


def default_prefix(name: str) -> str:
    """The data prefix of an announced robot that was given none: its own key."""
    return token_key(name)


def name_of(key: str) -> str | None:
    """The robot name in a token key ``teleop/robots/<name>`` (or ``.../info``), or None."""
    head = ROBOTS + "/"
    if not key.startswith(head):
        return None
    rest = key[len(head) :]
    if rest.endswith("/" + INFO):
        rest = rest[: -len(INFO) - 1]
    try:
        return auth.check_robot_name(rest)
    except ValueError:
        return None


@dataclass(frozen=True)
class Description:
    """What a robot says about itself; ``holder`` is the session id holding it, if it shows it."""

    name: str
    dof: int
    kind: str  # the robot device's kind ("sim", "mujoco", "franka", ...), never its address
    prefix: str  # its data keys: prefix/forward, prefix/backward
    state: str  # "free" or "busy"
    holder: int | None = None
    envelope: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        auth.check_robot_name(self.name)
        if not (type(self.dof) is int and 1 <= self.dof <= 64):  # a bool is not a DoF
            raise ValueError(f"dof must be 1..64, got {self.dof!r:.40}")
        if not (isinstance(self.kind, str) and 1 <= len(self.kind) <= MAX_KIND and self.kind.isprintable()):
            raise ValueError(f"kind must be 1..{MAX_KIND} printable characters, got {self.kind!r:.40}")
        if not (
            isinstance(self.prefix, str) and len(self.prefix) <= MAX_PREFIX and _PREFIX.fullmatch(self.prefix)
        ):
            raise ValueError(f"prefix must be a plain key like teleop/robots/a, got {self.prefix!r:.80}")
        if self.state not in STATES:
            raise ValueError(f"state must be one of {', '.join(STATES)}, got {self.state!r:.40}")
        if self.holder is not None and not (type(self.holder) is int and 0 <= self.holder < 2**32):
            raise ValueError(f"holder must be a session id 0..2**32-1, got {self.holder!r:.40}")
        if self.holder is not None and self.state != "busy":
            raise ValueError("a free robot has no holder")
        _check_envelope(self.envelope)


def envelope_fields(env: Envelope) -> dict[str, Any]:
    """An envelope as the description carries it: numbers and lists of names."""
    out: dict[str, Any] = {}
    for k, v in asdict(env).items():
        out[k] = [str(x) for x in v] if isinstance(v, tuple) else v
    return out


def _check_envelope(env: Any) -> None:
    """Known fields only, each a finite number or a short list of short names, and a valid Envelope."""
    if not isinstance(env, dict) or len(env) > len(_ENVELOPE_FIELDS):
        raise ValueError("envelope must be a map of the envelope's fields")
    for k, v in env.items():
        if k not in _ENVELOPE_FIELDS:
            raise ValueError(f"envelope has an unknown field {k!r:.40}")
        if isinstance(v, list):
            if len(v) > 8 or not all(isinstance(x, str) and len(x) <= 16 for x in v):
                raise ValueError(f"envelope {k} must be a short list of names")
        elif isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise ValueError(f"envelope {k} must be a finite number, got {v!r:.40}")
    try:
        given: dict[str, Any] = {k: tuple(v) if isinstance(v, list) else v for k, v in env.items()}
        Envelope(**given)
    except (TypeError, ValueError) as e:
        raise ValueError(f"envelope: {e}") from None


def _tag(robot: bytes, nonce: bytes, body: bytes) -> bytes:
    return hashlib.blake2s(nonce + body, key=describe_key(robot), digest_size=TAG_BYTES).digest()


def _check_nonce(nonce: bytes) -> bytes:
    if not isinstance(nonce, bytes) or len(nonce) != NONCE_BYTES:
        raise DescriptionError(f"a query nonce is {NONCE_BYTES} bytes")
    return nonce


def seal(d: Description, robot: bytes, nonce: bytes) -> bytes:
    """``d`` as sent to the querier that asked with ``nonce``: msgpack body and its tag."""
    body = msgpack.packb(
        {
            "v": VERSION,
            "name": d.name,
            "dof": d.dof,
            "kind": d.kind,
            "prefix": d.prefix,
            "state": d.state,
            "holder": d.holder,
            "envelope": d.envelope,
        },
        use_bin_type=True,
    )
    assert len(body) + TAG_BYTES <= MAX_DESCRIPTION_BYTES, len(body)
    return bytes(body) + _tag(robot, _check_nonce(nonce), body)


def open_description(data: bytes, robot: bytes, nonce: bytes, name: str) -> Description:
    """The description in ``data`` if it is the robot ``name``'s answer to ``nonce``; else
    DescriptionError.  Refused by size first, then the tag, then every field."""
    if not isinstance(data, bytes | bytearray) or not TAG_BYTES < len(data) <= MAX_DESCRIPTION_BYTES:
        raise DescriptionError(f"not a description: {len(data)} bytes (at most {MAX_DESCRIPTION_BYTES})")
    body, tag = bytes(data[:-TAG_BYTES]), bytes(data[-TAG_BYTES:])
    if not hmac.compare_digest(_tag(robot, _check_nonce(nonce), body), tag):
        raise DescriptionError("bad tag: not sealed by this robot's key for this query")
    try:
        m = msgpack.unpackb(body, raw=False, strict_map_key=True)  # bounded: the body is <= 2 kB
    except (
        ValueError,
        TypeError,
        msgpack.UnpackException,
    ) as e:  # authentic but malformed: a bug, not an attack
        raise DescriptionError(f"malformed description: {e}") from None
    if not isinstance(m, dict) or m.get("v") != VERSION:
        raise DescriptionError(f"description version must be {VERSION}")
    keys = {"v", "name", "dof", "kind", "prefix", "state", "holder", "envelope"}
    if set(m) != keys:
        raise DescriptionError(f"description fields must be {', '.join(sorted(keys))}")
    try:
        d = Description(
            name=m["name"],
            dof=m["dof"],
            kind=m["kind"],
            prefix=m["prefix"],
            state=m["state"],
            holder=m["holder"],
            envelope=m["envelope"],
        )
    except ValueError as e:
        raise DescriptionError(str(e)) from None
    if d.name != name:
        raise DescriptionError(f"description names robot {d.name!r}, announced as {name!r}")
    return d
