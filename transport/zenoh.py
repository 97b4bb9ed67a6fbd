"""Zenoh pub/sub as a drop-in for :class:`transport.udp.UdpTransport` in the session loop.

Why Zenoh: it routes between hosts (through a router, over TLS/mTLS if needed) without the two
processes knowing each other's address, while the 1 kHz loop keeps the same duck-typed surface
(``send``/``drain``/``wait``).

**Keys.** With a ``prefix`` agreed by both sides, the operator publishes on ``<prefix>/forward`` and
subscribes to ``<prefix>/backward``; the teleoperator does the opposite.  Control messages (msgpack
maps) and data packets (msgpack arrays, ``teleop.session.wire``) travel on the same two keys, each in the
authenticated envelope of ``teleop.session.auth``, as the sample's payload bytes: no Zenoh encoding or
attachment is used, so any Zenoh subscriber can read them (PROTOCOL.md) and none can forge them.

**QoS.** One publisher per process: ``express=True`` (no batching: each packet leaves at once),
``CongestionControl.DROP`` (a stale haptic sample is worth less than a stalled loop; the handshake
resends control messages anyway) and ``Priority.REAL_TIME``.  DROP gives up on a packet when the
priority's transmit queue stays full for 1 ms; with Zenoh's default queue (2 batches) that lost
~0.5 % of packets at 1 kHz on loopback whenever both cores were busy (Zenoh's I/O threads starved),
so ``make_config`` sets the REAL_TIME queue to ``RT_QUEUE_BATCHES`` (16) unless the file changes it:
like a UDP socket buffer, it absorbs a starved moment instead of dropping.

**Threads.** The subscriber callback runs on a Zenoh thread.  It never blocks: it stamps
``time.monotonic_ns()``, appends to a deque bounded in count and in bytes (``INBOX_BYTES``; oldest
dropped, counted in ``inbox_overflow``) and, if the loop is waiting, schedules the wake-up with
``loop.call_soon_threadsafe``.

**Bounds.** A sample longer than ``max_datagram`` (the protocol's largest datagram,
``teleop.session.wire.MAX_DATAGRAM_BYTES``, until the runner narrows it to the session's bound) is refused
by its length alone, before its bytes are copied or hashed, and counted in ``oversize``;
``make_config`` also sets Zenoh's ``transport/link/rx/max_message_size`` to ``MAX_MESSAGE_BYTES``
(Zenoh's default is 1 GiB: six 256 MB samples froze a robot's loop for 1.4 s), so Zenoh itself
drops a longer message before reassembling it (a file may set a smaller value, not a larger one).

**Admission (peer mode).** Given the robot key, :func:`open_session` makes the session present the
Zenoh user and password derived from it (``teleop.session.auth.zenoh_password``) and admit only peers that
present them (Zenoh's user-password authentication, PROTOCOL.md section 1): a stranger's Zenoh
link is refused in Zenoh's own threads, so its samples never reach ``_on_sample`` (a stranger's 60 kB
samples at 10k/s had cost the loop 3.4x its lateness p99, GIL and all).  The password file Zenoh
reads at open lives in a private temporary folder for the duration of ``zenoh.open`` only.  A
config file that sets ``transport/auth/usrpwd`` itself keeps its own; in client mode the router
admits (give it TLS client certificates or its own user-password dictionary).

**Processes.** Open the session inside the process that uses it: Zenoh's runtime (Tokio threads)
does not survive ``fork()``.

**Discovery.** Scouting (multicast and gossip) is always off: every endpoint is explicit, so a
session never joins a stranger on the LAN and nothing depends on multicast working.

**Failure.** In client mode the router must be reachable: the connect is retried for
``CLIENT_CONNECT_TIMEOUT_MS`` (2 s; ``connect/timeout_ms``, plus ``transport/unicast/open_timeout``
for a router that accepts TCP but never answers), then :class:`TransportError` names the endpoints.
A peer whose connect target is not up yet opens anyway (after ~0.5 s) and keeps retrying in the
background, so the two peers may start in either order.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import tempfile
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from teleop.errors import TeleopError
from teleop.files import MAX_CONFIG_BYTES, create_new, read_regular
from teleop.session import auth
from teleop.session.admission import Admission
from teleop.session.wire import MAX_DATAGRAM_BYTES

Addr = tuple[str, int]
ZENOH_PEER: Addr = ("zenoh", 0)
"""The pseudo-address every received sample carries (Zenoh hides the sender's socket address)."""

ROLES = ("operator", "teleoperator")
MODES = ("peer", "client", "router")
PROTOCOLS = ("tcp", "udp", "tls", "quic")
CLIENT_CONNECT_TIMEOUT_MS = 2000
RT_QUEUE_BATCHES = 16  # Zenoh's maximum; its default of 2 dropped ~0.5 % at 1 kHz on a busy 2-core host
_RT_QUEUE = "transport/link/tx/queue/size/real_time"
_MAX_MESSAGE = "transport/link/rx/max_message_size"
_USRPWD = "transport/auth/usrpwd"
_LEASE = "transport/link/tx/lease"
#: Zenoh's shared-memory transport (on by default in 1.x): a router with it admitted 351 client
#: sessions here and timed out every later one, whatever its max_sessions; without it, up to
#: max_sessions (tests/test_fleet_zenoh.py).  teleop's datagrams are far below its 3 KiB threshold,
#: so it never carried one: a router has it off (Zenoh's config cannot tell a file's "on" from its
#: default, so a file cannot turn it back on).
_SHM = "transport/shared_memory/enabled"
_KEEP_ALIVE = "transport/link/tx/keep_alive"
#: An announcing robot's lease (Zenoh's default is 10 s): silent this long, its router drops it, and
#: its liveliness token with it.  Keep-alives go FLEET_KEEP_ALIVE times a lease (every 250 ms).
FLEET_LEASE_MS = 1000
FLEET_KEEP_ALIVE = 4
#: Files a config names that Zenoh opens itself: each must be a regular file of bounded size, checked
#: by its type before Zenoh sees it (a FIFO there hung zenoh.open past SIGTERM; /dev/zero never ends).
_NAMED_FILES = (
    f"{_USRPWD}/dictionary_file",
    *(
        f"transport/link/tls/{k}"
        for k in (
            "root_ca_certificate",
            "listen_private_key",
            "listen_certificate",
            "connect_private_key",
            "connect_certificate",
        )
    ),
)
#: Zenoh's largest message: our largest sample plus room for Zenoh's own headers.
MAX_MESSAGE_BYTES = MAX_DATAGRAM_BYTES + 4096
#: The inbox's bound in bytes (with the count, ``inbox_size``): a few tens of the largest samples.
INBOX_BYTES = 32 * MAX_DATAGRAM_BYTES

_ENDPOINT = re.compile(
    r"(?P<proto>[a-z0-9-]+)/(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+):(?P<port>\d+)([?#].*)?"
)
_KEY_FORBIDDEN = re.compile(r"[*$?#\s]")
_RUST_LOCATION = re.compile(r"\s+at /\S+\.rs:\d+\.?")


class TransportError(TeleopError, OSError):
    """The Zenoh session could not open or connect (printed as one clear line)."""


def _reason(e: BaseException) -> str:
    """A ZError's message without the Rust source location it carries."""
    return _RUST_LOCATION.sub("", str(e)).strip()


def _check_endpoint(ep: str, what: str) -> None:
    m = _ENDPOINT.fullmatch(ep)
    allowed = f"PROTO/HOST:PORT with PROTO one of {', '.join(PROTOCOLS)} (for example tcp/127.0.0.1:7447)"
    if m is None:
        raise ValueError(f"{what} endpoint must be {allowed}, got {ep!r}")
    if m["proto"] not in PROTOCOLS:
        raise ValueError(f"{what} endpoint protocol must be one of {', '.join(PROTOCOLS)}, got {ep!r}")
    if not 0 <= int(m["port"]) <= 65535 or (what == "connect" and int(m["port"]) == 0):
        lo = 1 if what == "connect" else 0
        raise ValueError(f"{what} endpoint port must be {lo}..65535, got {ep!r}")


def _get(config: Any, key: str) -> Any:
    return json.loads(config.get_json(key))


def _check_lists(listen: list[str] | None, connect: list[str] | None) -> None:
    """Each endpoint list a list of strings, each one an endpoint (ValueError says which)."""
    for what, eps in (("listen", listen), ("connect", connect)):
        if eps is not None and (not isinstance(eps, list) or not all(isinstance(e, str) for e in eps)):
            raise ValueError(f"{what} endpoints must be a list of strings, got {eps!r}")
        for ep in eps or []:
            _check_endpoint(ep, what)


def make_config(
    mode: str = "peer",
    listen: list[str] | None = None,
    connect: list[str] | None = None,
    config_file: str | None = None,
    announcing: bool = False,
) -> zenoh.Config:
    """A Zenoh config: ``config_file`` (JSON5) first if given, then these overrides.

    ``mode`` always wins; ``listen``/``connect`` replace the file's lists when given (an endpoint
    list left unset everywhere is empty, never Zenoh's all-interfaces default).  Scouting is forced
    off; the REAL_TIME transmit queue is ``RT_QUEUE_BATCHES`` unless the file changes it; a router's
    shared memory is off (``_SHM``: it capped the sessions).  In client
    mode the connect timeout is ``CLIENT_CONNECT_TIMEOUT_MS`` unless the file sets
    one.  A robot that announces itself (``announcing``, transport.fleet) gets the lease
    ``FLEET_LEASE_MS`` unless the file sets one, so a robot whose cable is pulled leaves every
    listing within it.  ValueError says what is wrong and what is allowed.
    """
    if mode not in MODES:
        raise ValueError(f"Zenoh mode must be one of {', '.join(MODES)}, got {mode!r}")
    _check_lists(listen, connect)
    default = zenoh.Config()
    if config_file is None:
        config = zenoh.Config()
    else:
        try:  # a regular file of bounded size: a FIFO or a device is refused by its type
            text = read_regular(config_file, MAX_CONFIG_BYTES, "cannot load Zenoh config").decode()
            config = zenoh.Config.from_json5(text)
        except UnicodeDecodeError:
            raise ValueError(f"Zenoh config {config_file}: not text (JSON5 expected)") from None
        except zenoh.ZError as e:
            raise ValueError(f"cannot load Zenoh config {config_file}: {_reason(e)}") from None

    def put(key: str, value: Any) -> None:
        try:
            config.insert_json5(key, json.dumps(value))
        except zenoh.ZError as e:
            raise ValueError(f"Zenoh config {key} = {value!r}: {_reason(e)}") from None

    def unset(key: str) -> bool:
        return bool(_get(config, key) == _get(default, key))

    put("mode", mode)
    put("scouting/multicast/enabled", False)
    put("scouting/gossip/enabled", False)
    for key, eps in (("listen/endpoints", listen), ("connect/endpoints", connect)):
        if eps is not None:
            put(key, eps)
        elif unset(key):
            put(key, [])
    for key in _NAMED_FILES:  # a missing one is left to Zenoh, which names it when it opens
        if isinstance(path := _get(config, key), str) and os.path.exists(path):
            read_regular(path, MAX_CONFIG_BYTES, f"Zenoh config {key}:")  # FileRefused: one line
    if announcing and unset(_LEASE):
        put(_LEASE, FLEET_LEASE_MS)
        put(_KEEP_ALIVE, FLEET_KEEP_ALIVE)
    if unset(_RT_QUEUE):
        put(_RT_QUEUE, RT_QUEUE_BATCHES)
    if mode == "router":
        put(_SHM, False)
    max_msg = _get(config, _MAX_MESSAGE)
    if not (isinstance(max_msg, int) and 0 < max_msg <= MAX_MESSAGE_BYTES):
        put(_MAX_MESSAGE, MAX_MESSAGE_BYTES)
    listen_eps = _get(config, "listen/endpoints")
    connect_eps = _get(config, "connect/endpoints")
    if mode == "client":
        if not connect_eps:
            raise ValueError(
                "Zenoh client mode needs a connect endpoint (the router's), e.g. tcp/127.0.0.1:7447"
            )
        if unset("connect/timeout_ms"):
            put("connect/timeout_ms", CLIENT_CONNECT_TIMEOUT_MS)
        if unset("transport/unicast/open_timeout"):
            put("transport/unicast/open_timeout", CLIENT_CONNECT_TIMEOUT_MS)
    elif mode == "router" and not listen_eps:
        raise ValueError("Zenoh router mode needs a listen endpoint, e.g. tcp/127.0.0.1:7447")
    elif mode == "peer" and not listen_eps and not connect_eps:
        raise ValueError("Zenoh peer mode needs a listen or connect endpoint (scouting is off)")
    return config


def _describe(config: Any) -> tuple[str, str]:
    """(mode, human-readable endpoints) for error messages."""
    mode = _get(config, "mode") or "peer"
    if mode == "client":
        return mode, ", ".join(_get(config, "connect/endpoints")) or "(none)"
    return mode, f"listen {_get(config, 'listen/endpoints')}, connect {_get(config, 'connect/endpoints')}"


def _admit_key(config: Any, key: bytes, folder: str) -> Any:
    """Set ``config``'s user-password authentication from the robot ``key`` (peer mode, when the
    config leaves it unset), the dictionary in a new file in ``folder``; return the setting to put
    back after the open (the caller's config may open again, and the file is gone by then), or
    None if nothing was changed."""
    before = _get(config, _USRPWD)
    if not _ours_to_set(config):
        return None
    password = auth.zenoh_password(key)
    path = Path(folder) / "usrpwd"
    with os.fdopen(create_new(path, 0o600), "w") as f:
        f.write(f"{auth.ZENOH_USER}:{password}\n")
    ours = {"user": auth.ZENOH_USER, "password": password, "dictionary_file": str(path)}
    config.insert_json5(_USRPWD, json.dumps(ours))
    return before


def _ours_to_set(config: Any) -> bool:
    """Whether the robot key's admission applies: peer mode, and the config sets no usrpwd of its own."""
    return bool(_get(config, "mode") == "peer" and all(v is None for v in _get(config, _USRPWD).values()))


def admission(config: Any, key: bytes | None) -> str:
    """Who may open a Zenoh link to a session opened with ``config`` and ``key`` (for ``ROLE.json``)."""
    if _get(config, "mode") != "peer":
        return "the router's"
    if not _ours_to_set(config):
        return "user-password of the config file"
    return "any peer" if key is None else "peers holding the robot key (user-password)"


def open_session(config: Any, key: bytes | None = None) -> Any:
    """``zenoh.open(config)``, in peer mode admitting only peers that hold the robot ``key``
    (module docstring, Admission); TransportError names the endpoints if it cannot open."""
    with tempfile.TemporaryDirectory(prefix="teleop-zenoh-") as folder:
        before = None if key is None else _admit_key(config, key, folder)
        try:
            return zenoh.open(config)
        except zenoh.ZError as e:
            mode, where = _describe(config)
            if mode == "client":
                raise TransportError(f"cannot reach Zenoh router at {where}: {_reason(e)}") from None
            raise TransportError(f"cannot open Zenoh {mode} session ({where}): {_reason(e)}") from None
        finally:
            if before is not None:
                config.insert_json5(_USRPWD, json.dumps(before))


async def _open_session(config: Any, key: bytes | None = None) -> Any:
    """:func:`open_session` off the event loop (a client may wait seconds for its router)."""
    fut = asyncio.get_running_loop().run_in_executor(None, open_session, config, key)
    try:
        return await asyncio.shield(fut)
    except asyncio.CancelledError:
        # Cancelled while opening: close the session once the thread has it, so nothing leaks.
        def _close(f: asyncio.Future[Any]) -> None:
            if not f.cancelled() and f.exception() is None:
                f.result().close()

        fut.add_done_callback(_close)
        raise


def _keys(role: str, prefix: str) -> tuple[str, str]:
    """(tx, rx) key expressions for a role."""
    if role not in ROLES:
        raise ValueError(f"role must be one of {', '.join(ROLES)}, got {role!r}")
    p = prefix.strip("/")
    if not p or _KEY_FORBIDDEN.search(p) or "//" in p:
        raise ValueError(
            f"Zenoh key prefix must be a plain key like teleop/lab1 (no wildcards), got {prefix!r}"
        )
    fwd, bwd = f"{p}/forward", f"{p}/backward"
    return (fwd, bwd) if role == "operator" else (bwd, fwd)


def _wake(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


class ZenohTransport:
    """A Zenoh session publishing on the role's tx key and subscribed to its rx key.

    ``drain() -> [(data, ZENOH_PEER, t_rx_ns)]`` with ``t_rx_ns`` the monotonic clock when the Zenoh
    callback got the sample.  ``send`` ignores the address: there is one peer, the other key.
    """

    header_bytes = 0  # Zenoh's framing (and TCP/TLS below it) is not visible to us: count payload only

    def __init__(self, inbox_size: int = 4096) -> None:
        if inbox_size < 1:
            raise ValueError(f"inbox_size must be >= 1, got {inbox_size}")
        self._inbox: deque[tuple[bytes, Addr, int]] = deque()
        self._inbox_size = inbox_size
        self._inbox_bytes = 0
        self._lock = threading.Lock()  # the inbox and its byte count, between Zenoh's thread and the loop
        self._waiter: asyncio.Future[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._session: Any = None
        self._publisher: Any = None
        self._subscriber: Any = None
        self._announcer: Any = None
        self._zid = "zenoh"
        self.tx_key = ""
        self.rx_key = ""
        self.inbox_overflow = 0
        self.oversize = 0
        self.max_datagram = MAX_DATAGRAM_BYTES  # narrowed by the runner when a session starts
        self.admission = "any peer"  # who may open a Zenoh link to us (open() says)
        self.warnings: list[str] = []
        self.socket_errors = 0
        self.last_socket_error = ""

    @classmethod
    async def open(
        cls,
        role: str,
        prefix: str,
        config: zenoh.Config,
        inbox_size: int = 4096,
        key: bytes | None = None,
        locate: Callable[[Any], str] | None = None,
        announce: Callable[[Any], Any] | None = None,
    ) -> ZenohTransport:
        """Open the session and declare the publisher and subscriber; TransportError if it can't.

        With the robot ``key``, a peer-mode session admits only Zenoh peers holding it
        (:func:`open_session`).  ``locate(session)``, if given, finds the prefix on the open session
        (``transport.fleet.find_robot``; run off the event loop) instead of ``prefix``; ``announce(session)``
        declares what announces this robot once the keys are declared (closed with the transport)."""
        self = cls(inbox_size)
        self._loop = asyncio.get_running_loop()
        self.admission = admission(config, key)
        self._session = await _open_session(config, key)
        try:
            if locate is not None:
                prefix = await asyncio.get_running_loop().run_in_executor(None, locate, self._session)
            tx, rx = _keys(role, prefix)
        except (TransportError, ValueError):
            self.close()
            raise
        self.tx_key, self.rx_key = tx, rx
        try:
            self._zid = str(self._session.zid())
            self._subscriber = self._session.declare_subscriber(rx, self._on_sample)
            self._publisher = self._session.declare_publisher(
                tx,
                express=True,
                congestion_control=zenoh.CongestionControl.DROP,
                priority=zenoh.Priority.REAL_TIME,
            )
        except zenoh.ZError as e:
            self.close()
            raise TransportError(
                f"cannot declare Zenoh publisher {tx} / subscriber {rx}: {_reason(e)}"
            ) from None
        if announce is not None:
            try:
                self._announcer = announce(self._session)
            except (TransportError, ValueError):
                self.close()
                raise
        return self

    @property
    def session(self) -> Any:
        """The open Zenoh session (None once closed): for a listing on the same session."""
        return self._session

    def _on_sample(self, sample: Any) -> None:
        """Zenoh thread: stamp, enqueue, wake the loop. Never blocks."""
        t_rx = time.monotonic_ns()
        if sample.kind != zenoh.SampleKind.PUT:
            return
        payload = sample.payload
        n = len(payload)
        if n > self.max_datagram:  # by length alone: never copied, hashed or queued
            self.oversize += 1
            return
        data = payload.to_bytes()
        inbox = self._inbox
        with self._lock:  # held for a few list operations only: the loop's drain never waits long
            inbox.append((data, ZENOH_PEER, t_rx))
            self._inbox_bytes += n
            while len(inbox) > self._inbox_size or self._inbox_bytes > INBOX_BYTES:
                self._inbox_bytes -= len(inbox.popleft()[0])  # latest wins
                self.inbox_overflow += 1
        w, loop = self._waiter, self._loop
        if w is not None and loop is not None:
            self._waiter = None  # claimed: one wake-up per wait()
            with contextlib.suppress(RuntimeError):  # loop already closed
                loop.call_soon_threadsafe(_wake, w)

    @property
    def local_address(self) -> Addr:
        """(Zenoh id, 0): for logs; there is no socket address to show."""
        return self._zid, 0

    def admit(self, admission: Admission) -> None:
        """Nothing to install: Zenoh's own threads receive, and ``_on_sample`` refuses by length."""

    def send(self, data: bytes, addr: Addr) -> None:
        """Publish ``data`` on the tx key (``addr`` is ignored); failures are counted, not raised."""
        if self._publisher is None:
            raise TransportError("ZenohTransport is closed")
        try:
            self._publisher.put(data)
        except zenoh.ZError as e:
            self.socket_errors += 1
            self.last_socket_error = f"ZError: {_reason(e)}"

    def drain(self) -> list[tuple[bytes, Addr, int]]:
        """Everything received so far, in arrival order (under the inbox's lock)."""
        with self._lock:
            items = list(self._inbox)
            self._inbox.clear()
            self._inbox_bytes = 0
        return items

    async def wait(self, timeout: float) -> bool:
        """Wait until a sample is in the inbox (woken by the callback, not a timer); False on timeout."""
        if self._inbox:
            return True
        fut = asyncio.get_running_loop().create_future()
        self._waiter = fut
        try:
            if self._inbox:  # arrived between the check and publishing the waiter
                return True
            await asyncio.wait_for(fut, max(timeout, 0.0))
        except TimeoutError:
            return bool(self._inbox)
        finally:
            self._waiter = None
        return True

    def report(self) -> dict[str, Any]:
        """The transport's counters for ``ROLE.json``'s ``received``."""
        return {
            "inbox_overflow": self.inbox_overflow,
            "socket_errors": self.socket_errors,
            "oversize": self.oversize,
            "admission": self.admission,
        }

    def close(self) -> None:
        """Undeclare and close the session; idempotent."""
        self._loop = None
        if self._announcer is not None:
            with contextlib.suppress(Exception):
                self._announcer.close()
            self._announcer = None
        for entity in (self._subscriber, self._publisher):
            if entity is not None:
                with contextlib.suppress(Exception):
                    entity.undeclare()
        self._subscriber = self._publisher = None
        if self._session is not None:
            with contextlib.suppress(Exception):
                self._session.close()
            self._session = None


async def run_router(listen: list[str], config_file: str | None, stop: asyncio.Event) -> None:
    """A Zenoh router (scouting off) on ``listen`` (or the file's endpoints if empty) until ``stop``."""
    session = await _open_session(make_config("router", listen or None, None, config_file))
    try:
        await stop.wait()
    finally:
        # A router's close takes ~0.4 s (measured): keep it off the event loop.
        await asyncio.get_running_loop().run_in_executor(None, session.close)
