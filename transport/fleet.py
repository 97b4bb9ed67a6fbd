"""Fleets over Zenoh: a robot announces itself, operators list robots and find one by name.

rmw_zenoh's pattern: a robot holds a liveliness token ``teleop/robots/<name>`` (gone when its session
closes, or when its lease runs out after a pulled cable) and beside it a queryable
``teleop/robots/<name>/info`` that answers with its description (:mod:`teleop.session.fleet`),
sealed under the robot's key for the querier's fresh nonce.  A lister does one liveliness ``get``
(who is alive) and one ``get`` on ``teleop/robots/*/info`` (what each says), both at once; a robot is
*trusted* when it is alive and its description verifies.  The router does discovery; data goes
wherever Zenoh routes it.  The handshake stays the only claim: a listing shows it, never makes it.

Every answer is refused by size first, then authenticated, then each field checked; a listing holds
at most ``MAX_ROBOTS`` robots.
"""

from __future__ import annotations

import contextlib
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh

from teleop.session import auth
from teleop.session import fleet as fl

from .zenoh import TransportError, _reason

#: The most robots a listing takes (answers beyond are ignored and counted): bounds its memory.
MAX_ROBOTS = 10_000
#: How long a listing waits for answers; a robot that has not answered by then is listed untrusted.
LIST_TIMEOUT_S = 1.0
#: A robot answers at most this many queries a second (a bucket this deep): each answer costs its
#: 1 kHz loop ~20 us of the GIL on a Zenoh thread, so a flood of queries is refused unanswered.
ANSWERS_PER_S = 200.0
ANSWER_BURST = 200.0


class Announcer:
    """A robot's token and its describing queryable on an open session; ``close()`` withdraws both.

    It answers only a query carrying a nonce of exactly ``NONCE_BYTES``, at most ``ANSWERS_PER_S``
    a second (``throttled`` counts the rest).

    ``describe`` is called on a Zenoh thread per query: it must be quick and never block (it reads
    the endpoint's state, which the GIL keeps consistent enough for free/busy)."""

    def __init__(
        self,
        session: Any,
        name: str,
        robot_key: bytes,
        describe: Callable[[], fl.Description],
        exclusive: bool = True,
    ) -> None:
        """``exclusive``: refuse to announce a name someone holds already (a test tool may share)."""
        self.name = auth.check_robot_name(name)
        self._key = robot_key
        self._describe = describe
        self._info = fl.info_key(name)
        if exclusive and _alive(
            session, fl.token_key(name)
        ):  # two robots of one name: operators could not tell them apart
            raise TransportError(
                f"a robot named {name} is already announced here: give each robot its own --name"
            )
        self.answered = self.refused = self.throttled = 0
        try:  # what it will say, checked now: a robot that cannot describe itself fails to start
            fl.seal(describe(), robot_key, bytes(fl.NONCE_BYTES))
        except ValueError as e:
            raise TransportError(f"cannot announce robot {name}: {e}") from None
        self._bucket, self._filled = ANSWER_BURST, time.monotonic()
        try:
            self._token = session.liveliness().declare_token(fl.token_key(name))
            self._queryable = session.declare_queryable(self._info, self._on_query)
        except zenoh.ZError as e:
            raise TransportError(f"cannot announce robot {name}: {_reason(e)}") from None

    def _on_query(self, query: Any) -> None:
        """Zenoh thread: a nonce of exactly NONCE_BYTES, or no answer (nothing else is read)."""
        payload = query.payload
        if payload is None or len(payload) != fl.NONCE_BYTES:
            self.refused += 1
            return
        now = time.monotonic()
        self._bucket = min(ANSWER_BURST, self._bucket + (now - self._filled) * ANSWERS_PER_S)
        self._filled = now
        if self._bucket < 1.0:
            self.throttled += 1
            return
        self._bucket -= 1.0
        try:
            data = fl.seal(self._describe(), self._key, payload.to_bytes())
            query.reply(self._info, data)  # on the concrete key: never the wildcard that was asked
            self.answered += 1
        except (zenoh.ZError, ValueError):
            self.refused += 1

    def close(self) -> None:
        for entity in (self._queryable, self._token):
            with contextlib.suppress(Exception):
                entity.undeclare()


def _alive(session: Any, token: str, timeout: float = LIST_TIMEOUT_S) -> bool:
    """Whether someone holds the liveliness token ``token`` (one query; done when the router answers)."""
    try:
        return any(reply.ok is not None for reply in session.liveliness().get(token, timeout=timeout))
    except zenoh.ZError as e:
        raise TransportError(f"cannot query robots: {_reason(e)}") from None


@dataclass(frozen=True)
class Listed:
    """One robot in a listing: its description if trusted, else why it is not."""

    name: str
    description: fl.Description | None
    problem: str = ""

    @property
    def trusted(self) -> bool:
        return self.description is not None


def list_robots(
    session: Any, psk: bytes, name: str | None = None, timeout: float = LIST_TIMEOUT_S
) -> list[Listed]:
    """Every robot alive under ``teleop/robots`` (or only ``name``), sorted by name.

    A robot alive whose description does not verify under its key (derived from the deployment key
    ``psk`` and its name) is listed untrusted with the reason; a description without a live token is
    not listed (a robot is what holds a token)."""
    nonce = secrets.token_bytes(fl.NONCE_BYTES)
    tokens = fl.token_key(name) if name else f"{fl.ROBOTS}/*"
    infos = fl.info_key(name) if name else f"{fl.ROBOTS}/*/{fl.INFO}"
    try:
        alive_q = session.liveliness().get(tokens, timeout=timeout)
        info_q = session.get(
            infos,
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            payload=nonce,
            timeout=timeout,
        )
    except zenoh.ZError as e:
        raise TransportError(f"cannot query robots: {_reason(e)}") from None
    alive: set[str] = set()
    for reply in alive_q:  # a session sees its own token twice (local and via the router): a set
        ok = reply.ok
        if ok is not None and (n := fl.name_of(str(ok.key_expr))) is not None and len(alive) < MAX_ROBOTS:
            alive.add(n)
    found: dict[str, Listed] = {}
    for reply in info_q:
        if reply.ok is None:
            continue
        n = fl.name_of(str(reply.ok.key_expr))
        if n is None or n not in alive or (n in found and found[n].trusted):
            continue
        payload = reply.ok.payload
        if len(payload) > fl.MAX_DESCRIPTION_BYTES:  # by size, before a copy
            found[n] = Listed(n, None, f"description of {len(payload)} bytes refused")
            continue
        try:
            d = fl.open_description(payload.to_bytes(), auth.robot_key(psk, n), nonce, n)
        except fl.DescriptionError as e:
            found[n] = Listed(n, None, str(e))
            continue
        found[n] = Listed(n, d)
    out = [found.get(n) or Listed(n, None, "no description answered") for n in sorted(alive)]
    return out


def find_robot(session: Any, psk: bytes, name: str, timeout: float) -> fl.Description:
    """The trusted description of the robot ``name``, waiting up to ``timeout`` s for it to appear
    (woken by its liveliness token, not a timer); TransportError says what was seen if it does not."""
    appeared = threading.Event()

    def on_token(sample: Any) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            appeared.set()

    try:
        sub = session.liveliness().declare_subscriber(fl.token_key(name), on_token, history=True)
    except zenoh.ZError as e:
        raise TransportError(f"cannot look for robot {name}: {_reason(e)}") from None
    deadline = time.monotonic() + timeout
    last = "not announced"
    pause = threading.Event()  # never set: paces the retries
    tried = False
    try:
        while appeared.wait(max(deadline - time.monotonic(), 0.0)):
            if tried:  # alive, no trusted answer yet (its queryable may lag its token): again shortly
                pause.wait(min(0.1, max(deadline - time.monotonic(), 0.0)))
            tried = True
            left = max(deadline - time.monotonic(), 0.1)
            for r in list_robots(session, psk, name, timeout=min(LIST_TIMEOUT_S, left)):
                if r.description is not None:
                    return r.description
                last = f"announced but not trusted ({r.problem})"
            if time.monotonic() >= deadline:
                break
        raise TransportError(f"robot {name} not found through Zenoh in {timeout:g} s: {last}")
    finally:
        with contextlib.suppress(Exception):
            sub.undeclare()
