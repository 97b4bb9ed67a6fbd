"""PROTOCOL.md against the code: its worked examples are rebuilt byte for byte, and every message
kind, field name and constant the code uses must be in it, so the document cannot fall behind.

The examples are the fenced blocks after ``<!-- example: NAME -->`` (lines ``offset: hex | meaning``,
or JSON for ``inputs``); the constants are the block after ``<!-- constants -->`` (lines
``dotted.name = literal`` or ``dotted.Callable(param) = literal`` for a default).
"""

from __future__ import annotations

import ast
import dataclasses
import hashlib
import importlib
import inspect
import json
import math
import re
import zlib
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from teleop import auth, protocol, wire
from teleop.codecs import CODECS, make_codec
from teleop.codecs.base import RawFormat, pack
from teleop.node import PortOptions
from teleop.port import Port, make_node
from teleop.protocol import SessionParams
from transport.zenoh import _keys as zenoh_keys

DOC_PATH = Path(__file__).resolve().parent.parent / "PROTOCOL.md"
DOC = DOC_PATH.read_text(encoding="utf-8")
_BLOCK = re.compile(r"<!-- (example: [\w-]+|constants) -->\n```[a-z]*\n(.*?)\n```", re.S)
BLOCKS = {m.group(1).removeprefix("example: "): m.group(2) for m in _BLOCK.finditer(DOC)}
INPUTS: dict[str, Any] = json.loads(BLOCKS["inputs"])
PSK = bytes.fromhex(INPUTS["robot_key"])  # K_r: what every key of section 2.2 derives from
SESSION: int = INPUTS["session"]
NONCE_OP = bytes.fromhex(INPUTS["nonce_op"])
NONCE_TO = bytes.fromhex(INPUTS["nonce_to"])
K_FWD, K_BWD = auth.session_keys(PSK, SESSION, NONCE_OP, NONCE_TO)
K_HS = auth.handshake_key(PSK)
DATAGRAMS = ("data", "hello", "welcome", "start", "started")


def example_bytes(name: str) -> bytes:
    """The bytes of an annotated example; each line's offset must be where its bytes start."""
    out = bytearray()
    for line in BLOCKS[name].splitlines():
        offset, rest = line.split(":", 1)
        assert int(offset) == len(out), f"{name}: line {line!r} is at offset {len(out)}"
        out += bytes.fromhex(rest.split("|", 1)[0])
    return bytes(out)


def mentioned(name: str) -> bool:
    """``name`` appears in the document as code or as a quoted string."""
    return re.search(rf'[`"]{re.escape(name)}[`"]', DOC) is not None


# --------------------------------------------------------------------------------------------
# the worked examples
# --------------------------------------------------------------------------------------------
def test_every_example_is_present() -> None:
    for name in (*DATAGRAMS, "inputs", "constants"):
        assert name in BLOCKS, f"PROTOCOL.md lost the block {name!r}"


def test_the_robot_key_example() -> None:
    """Section 2.2's K_r, written out with hashlib alone, is the code's teleop.auth.robot_key."""
    ex = INPUTS["robot_key_example"]
    psk, name = bytes.fromhex(ex["psk"]), ex["name"]
    by_hand = hashlib.blake2s(b"robot\x00" + name.encode(), key=psk, person=b"teleopv1", digest_size=32)
    assert by_hand.hexdigest() == auth.robot_key(psk, name).hex() == ex["robot_key"]
    assert auth.robot_key(psk, name + "x") != auth.robot_key(psk, name)


def test_keys_of_the_example() -> None:
    keys = INPUTS["keys"]
    assert K_HS.hex() == keys["handshake"]
    assert K_FWD.hex() == keys["forward"]
    assert K_BWD.hex() == keys["backward"]


def test_the_key_derivations_as_the_document_states_them() -> None:
    """Section 2.2 written out with hashlib alone gives the code's keys and tags."""
    person = b"teleopv1"
    assert hashlib.blake2s(b"handshake", key=PSK, person=person, digest_size=32).digest() == K_HS
    context = SESSION.to_bytes(4, "big") + NONCE_OP + NONCE_TO
    assert len(b"forward" + context) == 43 and len(b"backward" + context) == 44
    assert hashlib.blake2s(b"forward" + context, key=PSK, person=person).digest() == K_FWD
    assert hashlib.blake2s(b"backward" + context, key=PSK, person=person).digest() == K_BWD
    for name, key in (("data", K_FWD), ("welcome", K_HS), ("started", K_BWD)):
        dg = example_bytes(name)
        tag = hashlib.blake2s(dg[:-16], key=key, digest_size=16).digest()
        assert tag == dg[-16:], name
        # "not the first 16 bytes of a 32-byte digest"
        assert hashlib.blake2s(dg[:-16], key=key).digest()[:16] != tag
    key_id = hashlib.blake2s(b"key id", key=PSK, person=person, digest_size=4).hexdigest()
    assert auth.key_id(PSK) == key_id


def _data_inputs() -> tuple[dict[str, Any], wire.Packet]:
    d: dict[str, Any] = INPUTS["data"]
    codec = make_codec(d["codec"], d["dof"], d["range"])
    assert codec.codec_id == d["codec_id"]
    codes = codec.raw.quantize(np.array(d["wave"]))
    assert codes.tolist() == d["codes"]
    pkt = wire.Packet(
        SESSION, d["direction"], d["seq"], d["tick"], d["t_us"], codec.codec_id, pack(codes, 16), d["energy"]
    )
    return d, pkt


def test_data_example_is_what_the_code_sends() -> None:
    d, pkt = _data_inputs()
    dg = auth.Sealer(K_FWD, auth.SESSION, d["direction"], d["counter"]).seal(wire.encode(pkt))
    assert dg == example_bytes("data")
    assert d["t_us"] == round(d["tick"] * d["dt"] * 1e6)
    assert d["seq"] == d["tick"] // int(d["codec"].split(":")[1])  # eds:K sends on ticks 0, K, 2K, ...


def test_data_example_opens_and_decodes_to_the_stated_fields() -> None:
    d, pkt = _data_inputs()
    dg = example_bytes("data")
    assert dg[0:1] == b"T" and dg[1] == 0x12 and int.from_bytes(dg[2:10], "big") == d["counter"]
    counter, body = auth.Opener(K_FWD, auth.SESSION, wire.FORWARD).open(dg, now=0.0)
    assert counter == d["counter"]
    assert body[0] == 0x9A
    assert f"{zlib.crc32(body[:-4]):08x}" == d["crc32"] == body[-4:][::-1].hex()
    assert wire.decode(body) == pkt
    # What a reader in another language does: msgpack and zlib, nothing of teleop.
    fields = msgpack.unpackb(body[:-4], raw=False)
    assert fields[:8] == [b"TW", 1, SESSION, d["direction"], d["seq"], d["tick"], d["t_us"], d["codec_id"]]
    codes = np.frombuffer(fields[8], dtype="<i2").tolist()
    assert codes == d["codes"]
    assert fields[9] == d["energy"]
    played = make_codec(d["codec"], d["dof"], d["range"]).decoder()
    played.push(fields[8])
    assert played.next().tolist() == [c * (d["range"] / 32767) for c in codes]


def _params() -> SessionParams:
    m = dict(INPUTS["hello"]["params"])
    return SessionParams.from_msg(m)


def _control_examples() -> dict[str, tuple[protocol.Message, bytes, int, int, int]]:
    """name -> (message, key, key kind, direction, counter) per the inputs."""
    i = INPUTS
    return {
        "hello": (
            protocol.Hello(_params(), i["hello"]["t_ns"], nonce=NONCE_OP),
            K_HS,
            auth.HANDSHAKE,
            wire.FORWARD,
            i["hello"]["counter"],
        ),
        "welcome": (
            protocol.Welcome(SESSION, i["welcome"]["t_ns"], i["welcome"]["t2"], i["welcome"]["t3"], NONCE_TO),
            K_HS,
            auth.HANDSHAKE,
            wire.BACKWARD,
            i["welcome"]["counter"],
        ),
        "start": (
            protocol.Start(SESSION, i["start"]["start_ns"]),
            K_FWD,
            auth.SESSION,
            wire.FORWARD,
            i["start"]["counter"],
        ),
        "started": (protocol.Started(SESSION), K_BWD, auth.SESSION, wire.BACKWARD, i["started"]["counter"]),
    }


@pytest.mark.parametrize("name", ["hello", "welcome", "start", "started"])
def test_control_examples_are_what_the_code_sends(name: str) -> None:
    msg, key, kind, direction, counter = _control_examples()[name]
    dg = auth.Sealer(key, kind, direction, counter).seal(protocol.encode(msg))
    assert dg == example_bytes(name)
    assert dg[1] == 0x10 | kind << 1 | direction
    got_counter, body = auth.Opener(key, kind, direction).open(example_bytes(name), now=0.0)
    assert got_counter == counter
    assert protocol.is_control(body)
    assert protocol.parse(body) == msg


def test_the_handshake_numbers_of_the_example() -> None:
    w, s = INPUTS["welcome"], INPUTS["start"]
    assert w["t_ns"] == INPUTS["hello"]["t_ns"]  # the welcome echoes the hello's t_ns
    offset, rtt = protocol.ntp_offset(w["t_ns"], w["t2"], w["t3"], w["t4"])
    assert (offset, rtt) == (w["offset_ns"], w["rtt_ns"])
    assert s["start_ns"] == s["S_O"] + offset
    assert s["S_O"] - w["t4"] >= 0


def test_the_handshake_state_machines_produce_the_examples() -> None:
    """Drive the real state machines with the example's clocks and nonces: the same datagrams."""
    params = _params()
    t1, w = INPUTS["hello"]["t_ns"], INPUTS["welcome"]
    op = protocol.OperatorHandshake(params, now_ns=t1, timeout_s=10.0, answers=1, psk=PSK, nonce=NONCE_OP)
    to = protocol.TeleoperatorHandshake({}, now_ns=w["t2"], timeout_s=10.0, psk=PSK, nonce=NONCE_TO)
    (hello,) = op.poll(t1)
    assert hello == example_bytes("hello")
    ((welcome, _),) = to.receive(hello, ("127.0.0.1", 1), w["t2"])
    assert welcome == example_bytes("welcome")
    op.receive(welcome, w["t4"])
    assert op.answers == 1
    s_o = INPUTS["start"]["S_O"]
    (start,) = op.poll(s_o - 300_000_000)  # the start is set start_lead_ns ahead
    assert (op.offset_ns, op.rtt_ns) == (w["offset_ns"], w["rtt_ns"])
    assert op.start_ns == s_o and start == example_bytes("start")
    ((started, _),) = to.receive(start, ("127.0.0.1", 1), w["t2"] + 1_000_000)
    assert started == example_bytes("started")
    assert to.start_ns == INPUTS["start"]["start_ns"]


def test_cq_payload_example() -> None:
    c = INPUTS["cq12"]
    codec = make_codec("cq:12", len(c["wave"]), c["range"])
    assert codec.codec_id == 3
    assert codec.encoder().encode(np.array(c["wave"])) == bytes.fromhex(c["payload"])
    assert f"`{c['payload']}`" in DOC


# --------------------------------------------------------------------------------------------
# the document keeps up with the code
# --------------------------------------------------------------------------------------------
def test_every_control_message_kind_and_field_is_documented() -> None:
    for kind in protocol.KINDS:
        assert mentioned(kind), kind
    params = _params()
    msgs: list[protocol.Message] = [
        protocol.Hello(params, 1, rejoin=True, cookie=bytes(16)),
        protocol.Welcome(1, 1, 2, 3),
        protocol.Reject(1, "why", 1),
        protocol.Retry(1, 1, bytes(16)),
        protocol.Start(1, 1, rejoin=True),
        protocol.Started(1),
        protocol.Bye(1, 2, 3),
    ]
    assert sorted(m.kind for m in msgs) == sorted(protocol.KINDS)
    for m in msgs:
        for field in msgpack.unpackb(protocol.encode(m), raw=False):
            assert mentioned(field), f"{m.kind}: field {field!r} is not in PROTOCOL.md"
    for field in params.to_msg():
        assert mentioned(field), field
    for f in dataclasses.fields(SessionParams):
        assert mentioned(f.name), f.name


def test_every_data_packet_field_is_documented() -> None:
    for name in ("magic", "version", *(f.name for f in dataclasses.fields(wire.Packet))):
        assert re.search(rf"\| \d \| `{name}` \|", DOC), f"wire field {name!r} is not in the table"


def test_codec_table_matches_the_code() -> None:
    rows = re.findall(r"^\| `(\w+)[^`]*`[^|]* \| (\d) \|", DOC, re.M)
    specs = {
        "none": "none",
        "cq": "cq:8",
        "ids": "ids:5",
        "eds": "eds:5",
        "pd": "pd:5",
        "pdp": "pdp:5",
        "dct": "dct:20:2",
    }
    assert {name for name, _ in rows} == set(specs) == set(CODECS)
    for name, codec_id in rows:
        assert make_codec(specs[name]).codec_id == int(codec_id), name
    for name, spec in specs.items():  # the table's payload sizes, at 3 DoF
        c = make_codec(spec, dof=3)
        want = {"pdp": 4 * 3, "dct": 2 * 2 * 3}.get(name, 2 * 3 if name != "cq" else 3)
        assert c.payload_bytes == want, name
        payload = c.encoder().encode(np.full(3, 0.3))
        if c.k == 1 or name in ("pd", "pdp"):  # sent on the first tick
            assert payload is not None and len(payload) == want, name


def test_flags_table_matches_the_code() -> None:
    names = {auth.HANDSHAKE: "handshake", auth.SESSION: "session"}
    dirs = {wire.FORWARD: "forward", wire.BACKWARD: "backward"}
    for kind in (auth.HANDSHAKE, auth.SESSION):
        for direction in (wire.FORWARD, wire.BACKWARD):
            flags = auth.Sealer(bytes(32), kind, direction).seal(b"")[1]
            assert f"| `0x{flags:02x}` | {names[kind]} | {dirs[direction]} |" in DOC


def _resolve(name: str) -> object:
    """``pkg.mod.NAME``, or ``pkg.mod.Callable(param)`` for a parameter's default."""
    m = re.fullmatch(r"([\w.]+?)\.(\w+)(?:\((\w+)\))?", name)
    assert m, name
    obj = getattr(importlib.import_module(m.group(1)), m.group(2))
    if m.group(3) is None:
        return obj
    default = inspect.signature(obj).parameters[m.group(3)].default
    assert default is not inspect.Parameter.empty, name
    return default


def test_constants_match_the_code() -> None:
    seen = 0
    for line in BLOCKS["constants"].splitlines():
        m = re.fullmatch(r"(\S+) = (.+?)(?:\s+#.*)?", line)
        assert m, f"constants: cannot read {line!r}"
        want: object = ast.literal_eval(m.group(2)) if m.group(2) != "bytes(32)" else bytes(32)
        got = _resolve(m.group(1))
        if isinstance(got, dict):
            got = tuple(got)
        if isinstance(want, float) or isinstance(got, float):
            assert isinstance(got, int | float) and isinstance(want, int | float)
            assert math.isclose(got, want, rel_tol=1e-12), line
        else:
            assert got == want, line
        seen += 1
    assert seen >= 50


def test_the_operator_remembers_64_hellos() -> None:
    op = protocol.OperatorHandshake(_params(), now_ns=0, timeout_s=1.0)
    assert op._hellos.maxlen == 64
    assert "last 64 hellos" in DOC


def test_zenoh_keys() -> None:
    assert zenoh_keys("operator", "p") == ("p/forward", "p/backward")
    assert zenoh_keys("teleoperator", "p") == ("p/backward", "p/forward")
    assert "`<prefix>/forward`" in DOC and "`<prefix>/backward`" in DOC


# --------------------------------------------------------------------------------------------
# the semantics the document states
# --------------------------------------------------------------------------------------------
def test_raw_format_is_the_documented_formula() -> None:
    rng = np.random.default_rng(1)
    for r in (2.0, 0.3, 16.0, 1e6):
        raw = RawFormat(r)
        x = np.concatenate([rng.uniform(-1.5 * r, 1.5 * r, 2000), [r, -r, 0.0, 2 * r, -2 * r]])
        m = 32767 / r
        want = [math.trunc(min(max(v * m, -32767.0), 32767.0)) for v in x.tolist()]
        assert raw.quantize(x).tolist() == want
        codes = np.array(want)
        assert raw.dequantize(codes).tolist() == [c * (r / 32767) for c in want]


@pytest.mark.parametrize(
    ("codec", "ticks"),
    [("none", [0, 1, 2, 3]), ("cq:8", [0, 1, 2, 3]), ("ids:5", [4, 9, 14]), ("eds:5", [0, 5, 10, 15])],
)
@pytest.mark.parametrize("role", ["operator", "teleoperator"])
def test_send_ticks_tick_t_us_and_energy(codec: str, ticks: list[int], role: str) -> None:
    """Section 3: send ticks, ``tick`` = k, ``t_us`` = round(k dt 1e6), ``seq`` from 0, and
    ``energy`` = sum over every tick so far of 0.5 dt |x|^2, x the wave before the codec."""
    dt = 0.001
    node = make_node(
        role, scenario="protocol", dof=2, dt=dt, b=20.0, codec=codec, full_scale=2.0, session=9,
        options=PortOptions(),
    )  # fmt: skip
    port = Port(node, ticks=40)
    sent: list[wire.Packet] = []
    energy = 0.0
    for k in range(ticks[-1] + 1):
        datagrams = port.tick(k, k * dt)
        energy += 0.5 * dt * float(np.dot(node.wave_out, node.wave_out))
        for dg in datagrams:
            pkt = wire.decode(dg[auth.HEADER_BYTES : -auth.TAG_BYTES])
            assert pkt.energy == pytest.approx(energy, rel=1e-12, abs=0.0)
            sent.append(pkt)
    assert [p.tick for p in sent] == ticks
    assert [p.t_us for p in sent] == [round(k * dt * 1e6) for k in ticks]
    assert [p.seq for p in sent] == list(range(len(ticks)))
    assert {p.direction for p in sent} == {node.tx_direction}
