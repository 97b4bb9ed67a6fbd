"""A deliberately broken endpoint for tests/test_conformance.py: ``python -m tests.broken_peer BREAK
ARGS...`` applies one break to this project's code, then runs ``teleop ARGS...``.  Each break
violates one rule of PROTOCOL.md that ``teleop conformance`` must catch."""

from __future__ import annotations

import dataclasses
import sys
from typing import Any


def _no_cookie() -> None:  # 4.3 step 2: a TO that welcomes a hello without a cookie
    from teleop import protocol

    protocol.TeleoperatorHandshake._retry = lambda self, *a: None  # type: ignore[method-assign]


def _answers_own_offers() -> None:  # 4.4 step 2: a running TO that answers its own session's hello
    from teleop import auth, endpoint, protocol

    def answer(self: Any, data: bytes, addr: Any, now_ns: int) -> None:
        body = self.port.open_handshake(data)
        if body is not None and (seen := protocol.peek_hello(body)) is not None:
            self._out.append((self.port.seal(protocol.Reject(seen[0], "no", seen[1])), addr))

    endpoint.Endpoint._handshake_datagram = answer  # type: ignore[method-assign]
    assert auth


def _no_bye() -> None:  # 4.6: no bye at the end
    from teleop import endpoint

    endpoint.BYE_COPIES = 0


def _seq_from_5() -> None:  # 3.1: seq does not start at 0
    from teleop import port, wire

    encode = wire.encode
    port.wire.encode = lambda p: encode(p._replace(seq=p.seq + 5))  # type: ignore[attr-defined]


def _ignores_retry() -> None:  # 4.3 step 2: an operator that never puts the cookie in its hellos
    from teleop import protocol

    encode = protocol.encode

    def no_cookie(msg: Any) -> bytes:
        if isinstance(msg, protocol.Hello):
            msg = dataclasses.replace(msg, cookie=None)
        return encode(msg)

    protocol.encode = no_cookie


BREAKS = {
    "no-cookie": _no_cookie,
    "answers-own-offers": _answers_own_offers,
    "no-bye": _no_bye,
    "seq-from-5": _seq_from_5,
    "ignores-retry": _ignores_retry,
}

if __name__ == "__main__":
    BREAKS[sys.argv[1]]()
    from teleop.cli.parser import main

    sys.exit(main(sys.argv[2:]))
