"""A robot's description (teleop.session.fleet): sealed under its key for one nonce, refused by size
first, every field checked."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import msgpack
import pytest

from teleop.session import auth
from teleop.session import fleet as fl
from teleop.session.settings import Envelope

PSK = bytes(range(32))
KEY = auth.robot_key(PSK, "arm-1")
NONCE = bytes(16)


def desc(**kw: Any) -> fl.Description:
    base: dict[str, Any] = {
        "name": "arm-1",
        "dof": 2,
        "kind": "sim",
        "prefix": "teleop/robots/arm-1",
        "state": "free",
        "envelope": fl.envelope_fields(Envelope()),
    }
    return fl.Description(**{**base, **kw})


def test_a_sealed_description_opens_for_its_nonce_and_name() -> None:
    d = desc(state="busy", holder=0xDEADBEEF)
    assert fl.open_description(fl.seal(d, KEY, NONCE), KEY, NONCE, "arm-1") == d


@pytest.mark.parametrize(
    "what",
    ["other nonce", "other robot's key", "a stranger's key", "body changed", "tag changed", "other name"],
)
def test_anything_but_the_robots_answer_to_this_query_is_refused(what: str) -> None:
    data = fl.seal(desc(), KEY, NONCE)
    key, nonce, name = KEY, NONCE, "arm-1"
    if what == "other nonce":  # a description recorded from an earlier query, replayed
        nonce = bytes([1]) + NONCE[1:]
    elif what == "other robot's key":  # arm-2's description relayed as arm-1's
        data = fl.seal(desc(name="arm-2"), auth.robot_key(PSK, "arm-2"), NONCE)
    elif what == "a stranger's key":  # sealed by someone without the deployment key
        data = fl.seal(desc(), auth.robot_key(bytes(32 * [7]), "arm-1"), NONCE)
    elif what == "body changed":
        data = data.replace(b"free", b"busy")
    elif what == "tag changed":
        data = data[:-1] + bytes([data[-1] ^ 1])
    elif what == "other name":  # a genuine arm-1 description answered under arm-2's token
        key, name = auth.robot_key(PSK, "arm-2"), "arm-2"
    with pytest.raises(fl.DescriptionError):
        fl.open_description(data, key, nonce, name)


def test_an_authentic_description_naming_another_robot_is_refused() -> None:
    """Sealed under arm-1's key but naming arm-2: the name in the body must be the token's."""
    data = fl.seal(desc(name="arm-2"), KEY, NONCE)
    with pytest.raises(fl.DescriptionError, match="names robot 'arm-2'"):
        fl.open_description(data, KEY, NONCE, "arm-1")


def test_a_long_answer_is_refused_by_its_length_before_any_tag() -> None:
    with pytest.raises(fl.DescriptionError, match="bytes"):
        fl.open_description(bytes(fl.MAX_DESCRIPTION_BYTES + 1), KEY, NONCE, "arm-1")
    with pytest.raises(fl.DescriptionError, match="bytes"):
        fl.open_description(b"", KEY, NONCE, "arm-1")


def _sealed_raw(m: dict[str, Any]) -> bytes:
    """A body the robot's key sealed but ``seal`` would not write: the checks after the tag."""
    body = msgpack.packb(m, use_bin_type=True)
    return bytes(body) + fl._tag(KEY, NONCE, body)


@pytest.mark.parametrize(
    "change",
    [
        {"dof": 0},
        {"dof": True},
        {"state": "gone"},
        {"holder": 5},  # a free robot has no holder
        {"prefix": "teleop/**"},
        {"kind": "x" * 40},
        {"envelope": {"max_force": float("inf")}},
        {"envelope": {"min_b": 30.0, "max_b": 20.0}},
        {"envelope": {"rm_rf": 1}},
        {"v": 2},
        {"extra": 1},
    ],
)
def test_every_field_is_checked_even_when_authentic(change: dict[str, Any]) -> None:
    m = {
        "v": 1,
        "name": "arm-1",
        "dof": 2,
        "kind": "sim",
        "prefix": "teleop/robots/arm-1",
        "state": "free",
        "holder": None,
        "envelope": {},
    }
    assert fl.open_description(_sealed_raw(m), KEY, NONCE, "arm-1").state == "free"  # the base opens
    with pytest.raises(fl.DescriptionError):
        fl.open_description(_sealed_raw({**m, **change}), KEY, NONCE, "arm-1")


def test_keys_and_names() -> None:
    assert fl.token_key("arm-1") == "teleop/robots/arm-1" and fl.info_key("a") == "teleop/robots/a/info"
    assert fl.name_of("teleop/robots/arm-1") == fl.name_of("teleop/robots/arm-1/info") == "arm-1"
    assert fl.name_of("teleop/robots/a/b") is None and fl.name_of("other/arm-1") is None
    assert fl.describe_key(KEY) != KEY and len(fl.describe_key(KEY)) == 32
    with pytest.raises(ValueError):
        fl.token_key("a/b")
    with pytest.raises(ValueError):
        replace(desc(), prefix="a//b")


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["robots", "--zenoh-router", "tcp/127.0.0.1:7447"], "no key: pass --key-file"),
        (["robots", "--insecure"], "needs a connect endpoint"),
        (["robots", "--insecure", "--zenoh-router", "tcp/127.0.0.1:99999"], "port must be 1..65535"),
        (["robots", "--insecure", "--zenoh-router", "x", "--name", "a/b"], "a robot name is 1 to 64"),
    ],
)
def test_teleop_robots_refuses_bad_input_in_one_line(
    argv: list[str], said: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from teleop.cli import main

    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err
    assert e.value.code == 2 and said in err and err.count("\n") == 1, err


class _Query:
    def __init__(self, payload: bytes | None) -> None:
        self.payload = None if payload is None else _Bytes(payload)
        self.replies: list[tuple[str, bytes]] = []

    def reply(self, key: str, data: bytes) -> None:
        self.replies.append((key, data))


class _Bytes:
    def __init__(self, b: bytes) -> None:
        self.b = b

    def __len__(self) -> int:
        return len(self.b)

    def to_bytes(self) -> bytes:
        return self.b


class _Session:
    """Just enough of a Zenoh session to declare an Announcer on; ``holders`` hold its token already."""

    def __init__(self, holders: int = 0) -> None:
        self.holders = holders

    def liveliness(self) -> Any:
        return self

    def get(self, key: str, timeout: float | None = None) -> list[Any]:
        return [type("Reply", (), {"ok": key})() for _ in range(self.holders)]

    def declare_token(self, key: str) -> Any:
        return self

    def declare_queryable(self, key: str, cb: Any) -> Any:
        return self

    def undeclare(self) -> None:
        pass


def test_a_robot_answers_only_a_nonce_and_at_most_its_rate() -> None:
    from transport.fleet import ANSWER_BURST, Announcer

    a = Announcer(_Session(), "arm-1", KEY, lambda: desc())
    for bad in (None, b"", bytes(15), bytes(17), bytes(4096)):
        q = _Query(bad)
        a._on_query(q)
        assert not q.replies
    assert a.refused == 5 and a.answered == 0
    queries = [_Query(bytes([i % 256]) * 16) for i in range(int(ANSWER_BURST) + 50)]
    for q in queries:  # a flood, faster than the bucket refills
        a._on_query(q)
    answered = [q for q in queries if q.replies]
    assert int(ANSWER_BURST) <= len(answered) < int(ANSWER_BURST) + 50 and a.throttled > 0
    key, data = answered[0].replies[0]
    assert key == "teleop/robots/arm-1/info"  # the concrete key, never the wildcard asked
    assert fl.open_description(data, KEY, bytes(16), "arm-1") == desc()


def test_a_second_robot_of_one_name_is_refused_in_one_line() -> None:
    from transport.fleet import Announcer
    from transport.zenoh import TransportError

    with pytest.raises(TransportError, match="a robot named arm-1 is already announced here"):
        Announcer(_Session(holders=1), "arm-1", KEY, lambda: desc())
    with pytest.raises(TransportError, match="cannot announce robot arm-1: prefix"):
        Announcer(_Session(), "arm-1", KEY, _bad_prefix)  # what it would say is checked before it says it


def _bad_prefix() -> fl.Description:
    raise ValueError("prefix must be a plain key like teleop/robots/a, got 'a b'")


def test_teleop_robots_shows_what_a_robot_sent_escaped_on_one_line() -> None:
    """A robot's name, a problem quoting what it sent, its kind and prefix reach the terminal
    escaped: no forged second line, no escape sequence (issue 49)."""
    from teleop.cli.robots import table

    evil = "arm\x1b[2J\nFAKE robot"
    rows = [
        {"name": evil, "trusted": False, "problem": f"bad field {evil!s}"},
        {"name": evil, "trusted": True, "state": "free\r", "holder": None, "dof": 2, "kind": "sim\x07",
         "prefix": "teleop/robots/\x9b31m"},
    ]  # fmt: skip
    lines = table(rows, 0.01)
    assert len(lines) == 4 and len("\n".join(lines).splitlines()) == 4, lines
    text = "\n".join(lines[2:])
    assert not any(c in text for c in "\x1b\r\x07\x9b"), lines
    assert "arm\\x1b[2J\\x0aFAKE robot" in lines[2] and "\\x9b31m" in lines[3], lines
