"""Simulated robots for fleet tests and the bench: N Zenoh client sessions in one process, each
announcing a robot exactly as ``teleop teleoperator`` does (token and sealed description, the
announcing lease), with no loop behind it.

    python -m tests.fleet_robots ROUTER KEYFILE_OR_- PREFIX N [--stranger] [--config FILE]

Robots ``PREFIX-0`` .. ``PREFIX-(N-1)``; ``-`` as the key file means the all-zero key (--insecure).
``--stranger`` seals with a key that is not the deployment's (a forger on the router); ``--config``
loads a Zenoh client config first (a user and password for a router's access control).  Prints
``ready`` once every robot is declared, then holds them until stdin closes or a signal.
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Callable

from teleop.session import auth
from teleop.session import fleet as fl
from teleop.session.settings import Envelope
from transport.fleet import Announcer
from transport.zenoh import make_config, open_session


def _const(d: fl.Description) -> Callable[[], fl.Description]:
    return lambda: d


def main(argv: list[str]) -> int:
    router, key_file, prefix, n = argv[0], argv[1], argv[2], int(argv[3])
    psk = auth.INSECURE_KEY if key_file == "-" else auth.read_key_file(key_file)
    if "--stranger" in argv:
        psk = bytes(b ^ 0x5A for b in psk)  # not the deployment key
    config_file = argv[argv.index("--config") + 1] if "--config" in argv else None
    env = fl.envelope_fields(Envelope())
    held = []
    for i in range(n):
        name = f"{prefix}-{i}"
        session = open_session(make_config("client", None, [router], config_file, announcing=True))
        d = fl.Description(name, 2, "sim", fl.default_prefix(name), "free", None, env)
        held.append((session, Announcer(session, name, auth.robot_key(psk, name), _const(d))))
    print("ready", flush=True)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
    try:
        sys.stdin.read()
    finally:
        for session, a in held:
            a.close()
            session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
