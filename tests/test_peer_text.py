"""A peer's text reaches the terminal escaped, on one line (issue 49): a robot's reject reason with
a newline and escape sequences once forged a second line of the operator's output."""

from __future__ import annotations

import socket
import subprocess
import sys
from types import SimpleNamespace
from typing import Any, cast

import pytest

from shell import console
from teleop.session import auth, protocol, wire
from teleop.session.events import HelloRejected

FORGED = "no\n\x1b[2Kteleop operator: session 7 completed\x1b[0m\r"


def test_the_robot_shows_a_rejected_hello_on_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    """The teleoperator's line for a hello it refused: its why quotes the hello's fields."""
    opts = cast(Any, SimpleNamespace(role="teleoperator", quiet=False))
    console.say(opts, HelloRejected(f"bad hello: codec {FORGED}"))
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "\x1b" not in err and "\r" not in err, repr(err)
    assert "\\x0a\\x1b[2Kteleop operator" in err, err


@pytest.mark.integration
def test_the_operator_shows_a_robots_reject_reason_on_one_line(key: str) -> None:
    """A robot holding the key answers the operator's hello with a reject whose why forges a line."""
    psk = auth.read_key_file(key)
    k_hs = auth.handshake_key(auth.robot_key(psk, auth.DEFAULT_ROBOT_NAME))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as robot:
        robot.bind(("127.0.0.1", 0))
        robot.settimeout(30)
        port = robot.getsockname()[1]
        op = subprocess.Popen(
            [sys.executable, "-m", "teleop.cli", "operator", "--key-file", key, "--peer", f"127.0.0.1:{port}",
             "--listen", "127.0.0.1:0", "--duration", "1", "--connect-timeout", "20", "--quiet"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )  # fmt: skip
        try:
            data, addr = robot.recvfrom(wire.MAX_DATAGRAM_BYTES)
            body = auth.Opener(k_hs, auth.HANDSHAKE, wire.FORWARD).verify(data)[1]
            hello = protocol.parse(body)
            assert isinstance(hello, protocol.Hello)
            reject = protocol.Reject(hello.params.session, FORGED, t_ns=hello.t_ns)
            robot.sendto(auth.Sealer(k_hs, auth.HANDSHAKE, wire.BACKWARD).seal(protocol.encode(reject)), addr)
            _, err = op.communicate(timeout=60)
        finally:
            op.kill()
            op.wait()
    assert op.returncode == 1, err
    assert err.count("\n") == 1 and "\x1b" not in err and "\r" not in err, repr(err)
    assert "rejected the session: no\\x0a\\x1b[2Kteleop operator: session 7 completed" in err, err
