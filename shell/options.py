"""The options of one real process (``teleop operator`` / ``teleoperator``): what the command line
resolved, handed to :func:`shell.process.run_endpoint`.  The session's own settings are
:class:`teleop.session.protocol.SessionParams` (the operator's proposal) and the teleoperator's pins."""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from pathlib import Path

from teleop.errors import TeleopError
from teleop.session import auth
from teleop.session.link import Addr
from teleop.session.settings import Envelope
from teleop.session.verdict import Bounds
from transport.udp import DEFAULT_RCVBUF_BYTES


@dataclass
class EndpointOptions:
    """One process: its role and addresses, its loop, its log, its key and its robot's name."""

    role: str
    listen: Addr
    peer: Addr | None = None
    log_dir: Path | None = None
    connect_timeout: float = 10.0
    rt_priority: int | None = 10
    use_uvloop: bool = True
    spin_us: int = 100
    # "wake": run each tick as the loop wakes before its deadline, send at the deadline (the spin's
    # time does the tick's work); "deadline": run it from the deadline (teleop.session.schedule)
    tick_at: str = "wake"
    linger: float = 0.2
    grace_us: float = 400.0
    quiet: bool = False
    bounds: Bounds = field(default_factory=Bounds)  # past these the session is poor (exit 3)
    live: bool = False  # a status line every second: traffic, link, watchdog
    wide: bool = False  # the status line in full, past 120 columns (shell.watch.status_line)
    transport: str = "udp"  # "udp" or "zenoh"
    zenoh: ZenohOptions | None = None
    psk: bytes | None = None  # the deployment's pre-shared key (teleop.session.auth); None: refuse to start
    insecure: bool = False  # --insecure: run with teleop.session.auth.INSECURE_KEY (integrity only), say so
    device: str | None = None  # --hsi/--robot spec (teleop.devices), local only; None: the scenario's
    live_view: int | None = None  # serve the Foxglove WebSocket live view on this port (0: any free)
    live_view_host: str = "127.0.0.1"
    robot_name: str = auth.DEFAULT_ROBOT_NAME  # the robot this operator names / this robot is
    local_limits: Envelope = field(default_factory=Envelope)  # teleoperator: what it affords
    udp_rcvbuf: int = DEFAULT_RCVBUF_BYTES  # the UDP socket's receive buffer asked for (transport.udp)
    show_holder: bool = False  # teleoperator over Zenoh: its description names the session holding it


@dataclass
class ZenohOptions:
    """How a process joins Zenoh (see transport.zenoh.make_config and docs/guides/zenoh.md)."""

    mode: str = "peer"  # peer | client
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    # None: a teleoperator's is teleop/robots/<name> (teleop.session.fleet); an operator finds the
    # robot it names through Zenoh and takes the prefix the robot's description gives
    prefix: str | None = None
    config_file: str | None = None
    find_timeout: float = 10.0  # s an operator waits for the robot it names to be announced


def new_session_id() -> int:
    """A random session id (PROTOCOL.md 4.1: 1..2**32-1, never reused on purpose)."""
    return random.SystemRandom().randrange(1, 2**32)


class Interrupted(TeleopError):
    """Stopped by a signal before any session ran (a robot waiting for its operator, an operator
    still in its handshake): a person's choice, said as such (exit status 130), not an error."""

    @classmethod
    def of(cls, role: str) -> Interrupted:
        if role == "teleoperator":
            return cls("stopped while waiting for an operator; no session ran")
        return cls("stopped during the handshake; no session ran")
