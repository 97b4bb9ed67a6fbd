"""PROTOCOL.md against the code: its worked examples are rebuilt byte for byte, and every message
kind, field name and constant the code uses must be in it, so the document cannot fall behind.

The examples are the fenced blocks after ``<!-- example: NAME -->`` (lines ``offset: hex | meaning``,
or JSON for ``inputs``); the constants are the block after ``<!-- constants -->`` (lines
``NAME = literal``), each mapped to the code by :func:`_code_map`.
"""

from __future__ import annotations

import ast
import contextlib
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

from teleop.control.codecs import CODECS, make_codec
from teleop.control.codecs.base import RawFormat, pack
from teleop.session import auth, protocol, wire
from teleop.session.node import PortOptions
from teleop.session.port import Port, make_node
from teleop.session.protocol import ProtocolError, SessionParams
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
    """Section 2.2's K_r, written out with hashlib alone, is the code's teleop.session.auth.robot_key."""
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
    zenoh_password = hashlib.blake2s(b"zenoh usrpwd", key=PSK, person=person, digest_size=32).hexdigest()
    assert auth.zenoh_password(PSK) == zenoh_password == INPUTS["keys"]["zenoh_password"]
    assert auth.ZENOH_USER == "teleop" and "`teleop:PASSWORD`" in DOC


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
            protocol.Start(SESSION, i["start"]["start_ns"], rtt_ns=i["start"]["rtt_ns"]),
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
    assert s["rtt_ns"] == rtt  # the start states the round trip of the exchange kept
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


def test_every_data_packet_field_is_documented() -> None:
    for name in ("magic", "version", *wire.Packet._fields):
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
        "pdr": "pdr:5",
        "dct": "dct:20:2",
    }
    assert {name for name, _ in rows} == set(specs) == set(CODECS)
    for name, codec_id in rows:
        assert make_codec(specs[name]).codec_id == int(codec_id), name
    for name, spec in specs.items():  # the table's payload sizes, at 3 DoF
        c = make_codec(spec, dof=3)
        want = {"pdp": 4 * 3, "pdr": 4 * 3, "dct": 2 * 2 * 3}.get(name, 2 * 3 if name != "cq" else 3)
        assert c.payload_bytes == want, name
        payload = c.encoder().encode(np.full(3, 0.3))
        if c.k == 1 or name in ("pd", "pdp", "pdr"):  # sent on the first tick
            assert payload is not None and len(payload) == want, name


def test_flags_table_matches_the_code() -> None:
    names = {auth.HANDSHAKE: "handshake", auth.SESSION: "session"}
    dirs = {wire.FORWARD: "forward", wire.BACKWARD: "backward"}
    for kind in (auth.HANDSHAKE, auth.SESSION):
        for direction in (wire.FORWARD, wire.BACKWARD):
            flags = auth.Sealer(bytes(32), kind, direction).seal(b"")[1]
            assert f"| `0x{flags:02x}` | {names[kind]} | {dirs[direction]} |" in DOC


def _default(callable_: object, param: str) -> object:
    """The default of ``param`` of a function or class."""
    default = inspect.signature(callable_).parameters[param].default  # type: ignore[arg-type]
    assert default is not inspect.Parameter.empty, param
    return default


def _code_map() -> dict[str, object]:
    """Each constant PROTOCOL.md section 7 names, as the code holds it: the document names no code,
    so the map from its names to the code is here (and in the development docs' code map)."""
    from shell import options
    from teleop import limits
    from teleop.control import passivity
    from teleop.control.codecs import base, frequency
    from teleop.devices import scenarios
    from teleop.session import endpoint, rejoin, schedule

    hs = protocol.OperatorHandshake
    return {
        "KEY_BYTES": auth.KEY_BYTES,
        "NONCE_BYTES": auth.NONCE_BYTES,
        "TAG_BYTES": auth.TAG_BYTES,
        "HEADER_BYTES": auth.HEADER_BYTES,
        "OVERHEAD": auth.OVERHEAD,
        "ENVELOPE_VERSION": auth.ENVELOPE_VERSION,
        "ENVELOPE_MAGIC": auth.MAGIC,
        "HANDSHAKE": auth.HANDSHAKE,
        "SESSION": auth.SESSION,
        "INSECURE_KEY": auth.INSECURE_KEY,
        "REPLAY_WINDOW": _default(auth.Opener, "window"),
        "JUMP_BASE": _default(auth.Opener, "jump_base"),
        "JUMP_RATE": _default(auth.Opener, "jump_rate"),
        "DATA_MAGIC": wire.MAGIC,
        "DATA_VERSION": wire.VERSION,
        "FORWARD": wire.FORWARD,
        "BACKWARD": wire.BACKWARD,
        "RAW_BITS": base.RAW_BITS,
        "POWER_CODEC_BASE": wire.POWER_CODEC_BASE,
        "MAX_FRAME": frequency.MAX_FRAME,
        "PROTOCOL_VERSION": protocol.PROTOCOL_VERSION,
        "KINDS": protocol.KINDS,
        "COOKIE_BYTES": protocol.COOKIE_BYTES,
        "COOKIE_BUCKET_SHIFT": protocol.COOKIE_BUCKET_SHIFT,
        "MAX_CONTROL_BYTES": protocol.MAX_CONTROL_BYTES,
        "MAX_TIMESTAMP": protocol.MAX_TIMESTAMP,
        "MAX_COUNT": protocol.MAX_COUNT,
        "START_AHEAD_NS": protocol.START_AHEAD_NS,
        "START_SLACK_NS": protocol.START_SLACK_NS,
        "MAX_RTT_NS": protocol.MAX_RTT_NS,
        **{
            name: getattr(limits, name)
            for name in (
                "MAX_SESSION",
                "MAX_SEED",
                "MAX_VARIATION",
                "MAX_DOF",
                "MIN_DT",
                "MAX_DT",
                "MIN_DURATION_S",
                "MAX_DURATION_S",
                "UNTIL_STOPPED",
                "MAX_B",
                "MAX_RANGE",
                "MIN_LINK_TIMEOUT_S",
                "MAX_LINK_TIMEOUT_S",
                "MAX_CODEC_SPEC_LEN",
                "MAX_NETEM_SPEC_LEN",
                "MAX_REASON_LEN",
            )
        },
        "MAX_ROBOT_NAME": auth.MAX_ROBOT_NAME,
        "DEFAULT_ROBOT_NAME": auth.DEFAULT_ROBOT_NAME,
        "ON_LOSS": passivity.ON_LOSS,
        "REPORT_BURST_S": passivity.REPORT_BURST_S,
        "SCENARIOS": scenarios.SCENARIOS,
        "REFERENCE_MAX_CANDIDATES": protocol.MAX_CANDIDATES,
        "REFERENCE_CANDIDATE_ADDRS": protocol.CANDIDATE_ADDRS,
        "BUSY": protocol.BUSY,
        "REFERENCE_START_LEAD_RTTS": protocol.START_LEAD_RTTS,
        "REFERENCE_START_LEAD_SLACK_NS": protocol.START_LEAD_SLACK_NS,
        "REFERENCE_START_RESEND_DIV": protocol.START_RESEND_DIV,
        "REFERENCE_WELCOMES": _default(hs, "answers"),
        "REFERENCE_HELLO_INTERVAL_NS": _default(hs, "hello_interval_ns"),
        "REFERENCE_START_LEAD_NS": _default(hs, "start_lead_ns"),
        "REFERENCE_START_RESEND_NS": _default(hs, "start_resend_ns"),
        "REFERENCE_START_MARGIN_NS": _default(hs, "start_margin_ns"),
        **{
            f"REFERENCE_{f.upper()}": _default(SessionParams, f)
            for f in (
                "dt",
                "phase",
                "netem_forward",
                "netem_backward",
                "seed",
                "on_loss",
                "controller",
                "variation",
            )
        },
        "REFERENCE_LINK_TIMEOUT_S": _default(SessionParams, "link_timeout"),
        "REFERENCE_FADE_TIME_S": _default(PortOptions, "fade_time"),
        "REFERENCE_MAX_CATCHUP": _default(schedule.TickPolicy, "max_catchup"),
        "REFERENCE_REJOIN_OFFER_INTERVAL_NS": rejoin.REJOIN_OFFER_INTERVAL_NS,
        "REFERENCE_REJOIN_SAMPLES": rejoin.REJOIN_SAMPLES,
        "REFERENCE_REJOIN_COLLECT_NS": rejoin.REJOIN_COLLECT_NS,
        "REFERENCE_REJOIN_START_RESEND_NS": rejoin.START_RESEND_NS,
        "REFERENCE_REJOIN_START_RESENDS": rejoin.START_RESENDS,
        "REFERENCE_JOIN_AHEAD_TICKS": endpoint.JOIN_AHEAD_TICKS,
        "REFERENCE_SILENT_MIN_NS": endpoint.SILENT_MIN_NS,
        "REFERENCE_GHOST_MARGIN_NS": endpoint.GHOST_MARGIN_NS,
        "REFERENCE_LEAD_FIXED_NS": endpoint.LEAD_FIXED_NS,
        "REFERENCE_LINGER_S": _default(options.EndpointOptions, "linger"),
        "REFERENCE_GRACE_US": _default(options.EndpointOptions, "grace_us"),
        "REFERENCE_CONNECT_TIMEOUT_S": _default(options.EndpointOptions, "connect_timeout"),
    }


def test_constants_match_the_code() -> None:
    code = _code_map()
    seen = set()
    for line in BLOCKS["constants"].splitlines():
        m = re.fullmatch(r"([A-Z][A-Z0-9_]*) = (.+?)(?:\s+#.*)?", line)
        assert m, f"constants: cannot read {line!r}"
        want: object = ast.literal_eval(m.group(2)) if m.group(2) != "bytes(32)" else bytes(32)
        assert m.group(1) in code, f"constants: {m.group(1)} is in no code map entry"
        got = code[m.group(1)]
        if isinstance(got, dict):
            got = tuple(got)
        if isinstance(want, float) or isinstance(got, float):
            assert isinstance(got, int | float) and isinstance(want, int | float)
            assert math.isclose(got, want, rel_tol=1e-12), line
        else:
            assert got == want, line
        seen.add(m.group(1))
    assert seen == set(code), set(code) - seen  # every constant the map holds is in the document


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


# --------------------------------------------------------------------------------------------
# the rules issue 24's implementer had to guess, as the document now states them
# --------------------------------------------------------------------------------------------
def _section(title: str) -> str:
    """The text of the section whose heading starts with ``title`` (up to the next heading)."""
    m = re.search(rf"^#+ {re.escape(title)}.*?\n(.*?)(?=^#+ )", DOC, re.S | re.M)
    assert m, title
    return m.group(1)


def test_the_link_loss_table_is_what_the_node_does() -> None:
    """Section 5.3: T per codec, and the first tick the link is lost after a packet accepted just
    before tick j = 0, with dt 1 ms and link_timeout 50 ms."""
    rows = re.findall(r"^\| (\d+) \| (`.+?`) \| (\d+) ms \| `j \+ (\d+)` \|$", _section("5.3"), re.M)
    assert len(rows) >= 6
    for p, codecs, t_ms, lost_at in rows:
        for codec in re.findall(r"`([^`]+)`", codecs):
            node = make_node(
                "teleoperator", scenario="protocol", dof=2, dt=0.001, b=20.0, codec=codec, full_scale=2.0,
                session=9, options=PortOptions(link_timeout=0.05),
            )  # fmt: skip
            assert node.rx_codec.k == int(p), codec
            assert math.isclose(node.link_timeout, int(t_ms) / 1e3), codec
            enc = node.rx_codec.encoder()
            payload = None
            while payload is None:
                payload = enc.encode(np.full(2, 0.1))
            node.receive_packet(wire.Packet(9, 0, 0, 0, 0, node.rx_codec.codec_id, payload, 1.0))
            k = 0
            while not node.link_lost:
                node.tick(k * 0.001)
                k += 1
            assert k - 1 == int(lost_at), codec


@pytest.mark.parametrize(
    ("given", "canonical"),
    [("EDS:050", "eds:50"), ("cq:8:1.50", "cq:8:1.5"), ("pd:5.0", "pd:5"), ("pd:5:100", "pd:5"),
     ("dct:020:02", "dct:20:2"), ("cq:8:1.2345678", "cq:8:1.23457"), ("eds:+5", "eds:5"),
     ("eds:5_0", "eds:50"), ("pdr:0.8:100:0.8", "pdr:0.8"),
     ("pdr:0.8:100:0.8:30:30:C0.50", "pdr:0.8:100:0.8:30:30:c0.5"),
     ("pdr:0.8:100:0.8:-0:30", "pdr:0.8:100:0.8:0:30")],
)  # fmt: skip
def test_canonical_codec_specs(given: str, canonical: str) -> None:
    """Section 3.5: the canonical form both sides build their codec from."""
    assert make_codec(given, 2, 2.0).spec == canonical
    assert mentioned(given) and mentioned(canonical)
    assert make_codec(canonical, 2, 2.0).spec == canonical
    # ... and a hello that spells it otherwise is refused, naming the canonical form (issue 49)
    params = SessionParams(session=7, codec=canonical, scenario="step", dof=2, b=1, full_scale=2, duration=5)
    msg = params.to_msg()
    assert SessionParams.from_msg(msg).codec == canonical
    with pytest.raises(ProtocolError, match=re.escape(f"canonical form '{canonical}'")):
        SessionParams.from_msg({**msg, "codec": given})


def test_an_integer_energy_is_refused() -> None:
    """Section 3.1: energy is a msgpack float, never an int (not even 0)."""
    for energy, ok in ((0, False), (3, False), (0.0, True), (True, False)):
        body = msgpack.packb([b"TW", 1, 9, 0, 0, 0, 0, 0, b"\0\0", energy], use_bin_type=True)
        body += zlib.crc32(body).to_bytes(4, "little")
        if ok:
            assert wire.decode(body).energy == 0.0
        else:
            with pytest.raises(wire.WireError, match="energy"):
                wire.decode(body)


def test_optional_fields_with_their_default_values_are_accepted() -> None:
    """Section 4.1: rejoin false, playout off, variation 0 and rate_cap 0 mean their absence."""
    m = {"t": "hello", "v": 1, "t_ns": 1, "nonce": bytes(16), **_params().to_msg()}
    plain = protocol.parse(msgpack.packb(m, use_bin_type=True))
    m.update(rejoin=False, playout="off", variation=0, rate_cap=0)
    assert protocol.parse(msgpack.packb(m, use_bin_type=True)) == plain


def _answer(hello: dict[str, Any] | bytes, with_cookie: bool) -> str:
    """What a teleoperator's handshake answers to an authentic hello body (section 4.2's table)."""
    secret, addr, t = bytes(32), ("10.0.0.1", 5000), 10**12
    to = protocol.TeleoperatorHandshake({}, now_ns=t, timeout_s=10.0, psk=PSK, cookie_secret=secret)
    if isinstance(hello, dict) and with_cookie:
        hello = {**hello, "cookie": protocol.make_cookie(secret, addr, hello["nonce"], t)}
    body = msgpack.packb(hello, use_bin_type=True) if isinstance(hello, dict) else hello
    out = to.receive(auth.Sealer(K_HS, auth.HANDSHAKE, wire.FORWARD).seal(body), addr, t)
    opener = auth.Opener(K_HS, auth.HANDSHAKE, wire.BACKWARD)
    return ",".join(protocol.parse(opener.verify(d)[1]).kind for d, _ in out) or "nothing"


def test_what_a_teleoperator_answers_to_a_bad_hello() -> None:
    good: dict[str, Any] = {"t": "hello", "v": 1, "t_ns": 7, "nonce": bytes(range(16)), **_params().to_msg()}
    assert _answer(good, False) == "retry" and _answer(good, True) == "welcome"
    many = {**good, **{f"x{i}": i for i in range(65 - len(good))}}
    assert len(many) == 65 and _answer(many, True) == "nothing"
    assert _answer({**good, "pad": "x" * 4000}, True) == "nothing"  # over 4096 bytes
    assert _answer({**good, "t": "Hello"}, True) == "nothing"
    assert _answer({**good, "dof": 0}, False) == "retry"  # the cookie first, whatever else is wrong
    assert _answer({**good, "dof": 0}, True) == "reject"
    assert _answer({**good, "v": 2}, True) == "reject"
    assert _answer({**good, "nonce": b"short"}, False) == "reject"
    assert _answer({k: v for k, v in good.items() if k != "nonce"}, False) == "reject"
    table = _section("4.2")
    for row in ("more than 64 entries", "no valid `cookie`", "not a 16-byte bin", "`v` included"):
        assert row in table, row


def _pd_sender(
    pct: float, heartbeat: int, predictive: bool, xs: np.ndarray, rng: float
) -> list[bytes | None]:
    """The pd/pdp sender exactly as section 3.5 states it, with nothing of teleop but the format."""
    raw, slope_raw = RawFormat(rng), RawFormat(rng / 64)
    value, slope, i, gain, e_in, e_budget, played = np.zeros(2), np.zeros(2), 0, 1.0, 0.0, 0.0, 0.0
    hist: list[np.ndarray] = []
    out: list[bytes | None] = []
    for n, x in enumerate(xs):
        e_in += float(x @ x)
        hist = [*hist, x][-8:]
        pred = value + slope * i if predictive else value
        band = float(np.linalg.norm(x - pred / gain)) > pct / 100 * max(float(np.linalg.norm(pred)), rng / 16)
        if not (n == 0 or band or i >= heartbeat or played + float(pred @ pred) > e_budget):
            played += float(pred @ pred)
            i += 1
            out.append(None)
            continue
        r = max(e_in - played, 0.0)
        gain = 1 - min(pct / 200, 0.05) * (1 - r / (100 * float(x @ x))) if r < 100 * float(x @ x) else 1.0
        p = x * math.sqrt(r / float(x @ x)) if float(x @ x) > r else gain * x
        q = raw.quantize(p)
        value, i, e_budget = raw.dequantize(q), 1, e_in
        played += float(value @ value)
        codes = [q]
        if predictive:
            m = len(hist)
            j = np.arange(m) - (m - 1) / 2
            fit = (j / float(j @ j)) @ np.array(hist) if m >= 2 else np.zeros(2)
            qs = slope_raw.quantize(fit)
            slope = slope_raw.dequantize(qs)
            codes.append(qs)
        out.append(pack(np.concatenate(codes), 16))
    return out


@pytest.mark.parametrize("spec", ["pd:5", "pdp:5", "pdp:20:30", "pd:1:7"])
def test_the_deadband_sender_is_the_documented_one(spec: str) -> None:
    rng = np.random.default_rng(3)
    t = np.arange(3000) * 1e-3
    xs = np.stack([np.sin(2 * np.pi * 1.3 * t), 0.5 * np.cos(2 * np.pi * 0.7 * t)], axis=1)
    xs += np.cumsum(rng.normal(0, 0.01, xs.shape), axis=0)
    codec = make_codec(spec, 2, 2.0)
    enc = codec.encoder()
    name, pct, *hb = spec.split(":")
    mine = _pd_sender(float(pct), int(hb[0]) if hb else 100, name == "pdp", xs, 2.0)
    theirs = [enc.encode(x) for x in xs]
    assert mine == theirs
    assert 20 < sum(p is not None for p in theirs) < 3000


@pytest.mark.parametrize("name", ["eds", "ids"])
def test_the_send_phase_is_the_documented_one(name: str) -> None:
    """Section 3.5: sends on calls c with c - p (eDS) or c - p - (K-1) (iDS) a multiple of K, and a
    change of p moves only the next send, by the wrapped difference, never before the current call."""
    k = 10
    phases = [0] * 25 + [3] * 30 + [9] * 40 + [2] * 30 + [7] * 25
    enc = make_codec(f"{name}:{k}", 1, 2.0).encoder()
    sent = []
    for c, p in enumerate(phases):
        enc.phase = p
        if enc.encode(np.array([0.1])) is not None:
            sent.append(c)
    want, nxt, p_old = [], 0 if name == "eds" else k - 1, 0
    for c, p in enumerate(phases):
        if p != p_old:
            nxt = max(nxt + ((p - p_old + k // 2) % k) - k // 2, c)
            p_old = p
        if c == nxt:
            want.append(c)
            nxt = c + k
    assert sent == want
    assert [c % k for c in sent[:2]] == [0 if name == "eds" else k - 1] * 2  # before the first change


@pytest.mark.parametrize(("spec", "interval"), [("none", 1), ("eds:5", 5), ("ids:4", 4), ("dct:6:2", 6)])
def test_conceal_holds_one_payload_interval_then_fades(spec: str, interval: int) -> None:
    """Section 3.7 step 6: `last` while g <= P, then last * 0.95^(g - P)."""
    codec = make_codec(spec, 1, 2.0)
    dec = codec.decoder(None, "conceal")
    payload = None
    enc = codec.encoder()
    while payload is None:
        payload = enc.encode(np.array([0.5]))
    dec.push(payload)
    played = [float(dec.next()[0]) for _ in range(codec.k)]
    last = played[-1]
    for g in range(1, 3 * interval + 5):
        want = last if g <= interval else last * 0.95 ** (g - interval)
        assert float(dec.next()[0]) == pytest.approx(want, rel=1e-12), g


def test_the_energy_guard_as_documented() -> None:
    """Section 3.7 step 7: the bucket starts full at 0.2 s of P_max (the codec's RANGE), a late
    joiner's first report is its origin (zero budget), and the tolerance is 1e-12 J."""
    cq = make_codec("cq:8:0.5", 2, 2.0)
    node = make_node(
        "operator", scenario="protocol", dof=2, dt=0.001, b=20.0, codec="cq:8:0.5", full_scale=2.0,
        session=9, options=PortOptions(),
    )  # fmt: skip
    p_max = 0.5 * 2 * 0.5**2
    assert node.guard.max_power == p_max and cq.raw.full_scale == 0.5
    node.guard.sent(0.2 * p_max * 0.999)
    assert node.guard.report.energy_reports_clamped == 0
    node.guard.sent(0.2 * p_max * 1.5)
    assert node.guard.report.energy_reports_clamped == 1
    late = make_node(
        "teleoperator", scenario="protocol", dof=2, dt=0.001, b=20.0, codec="none", full_scale=2.0,
        session=9, options=PortOptions(),
    )  # fmt: skip
    late.joined_late()
    late.guard.sent(5.0)
    assert late.guard.margin == 0.0
    assert late.guard.admit(np.array([0.3, 0.3])).tolist() == [0.0, 0.0]
    assert late.guard.report.violations == 1 and late.guard.tolerance == 1e-12
    assert "1e-12" in _section("3.7") and "-1e-9" in _section("3.7")


# --- numbers PROTOCOL.md states for implementers (issue 35) -------------------------------------
def _smallest_hello() -> bytes:
    """The smallest hello body the full parse accepts: every number an integer but ``dt`` (a float32:
    no integer is in its range), the shortest codec and scenario names, no optional field."""
    m = {
        "t": "hello", "v": 1, "t_ns": 0, "nonce": bytes(16), "session": 1, "codec": "none",
        "scenario": "step", "dof": 1, "b": 1, "range": 1, "duration": 0, "dt": 0.001, "phase": 0,
        "netem_forward": "", "netem_backward": "", "seed": 0, "on_loss": "zero", "controller": True,
        "link_timeout": 1,
    }  # fmt: skip
    body: bytes = msgpack.packb(m, use_bin_type=True, use_single_float=True)
    return body


def test_the_smallest_valid_hello_and_the_retries_are_as_stated() -> None:
    body = _smallest_hello()
    assert isinstance(protocol.parse(body), protocol.Hello)
    smallest = len(body) + auth.OVERHEAD
    p = SessionParams(session=1, codec="none", scenario="step", dof=1, b=1.0, full_scale=1.0,
                      duration=0.0, phase=0.0, link_timeout=1.0, on_loss="zero")  # fmt: skip
    ours = len(protocol.encode(protocol.Hello(p, 0, nonce=bytes(16)))) + auth.OVERHEAD
    retries = [
        len(protocol.encode(protocol.Retry(s, t, bytes(16)))) + auth.OVERHEAD
        for s, t in ((None, 0), (2**32 - 1, 2**63 - 1))
    ]
    bare = len(msgpack.packb({"t": "hello", "nonce": bytes(16)}, use_bin_type=True)) + auth.OVERHEAD
    text = " ".join(DOC.split())
    assert f"the smallest hello the full parse accepts is **{smallest}** bytes" in text
    assert f"the reference operator's are at least {ours} bytes" in text
    assert f"retries are {min(retries)} to {max(retries)} bytes" in text
    assert f"and a `nonce`, {bare} bytes, also gets a retry" in text
    assert max(retries) < smallest


def test_the_session_length_bound_is_the_stated_formula() -> None:
    text = " ".join(DOC.split())
    assert "`max(2000 n + 53, 4096) + 26` bytes at `n` DoF up to 32," in text
    assert "`max(2000 n + 55, 4096) + 26` from 33" in text
    for n in range(1, 65):
        extra = 53 if n <= 32 else 55
        assert wire.max_session_datagram_bytes(n) == max(2000 * n + extra, 4096) + auth.OVERHEAD
    assert f"{wire.max_session_datagram_bytes(2)} bytes at 1 or 2 DoF" in text
    assert wire.max_session_datagram_bytes(1) == wire.max_session_datagram_bytes(2)


def test_the_personalisation_words_as_stated() -> None:
    """The note for implementers without BLAKE2s personalisation states the parameter block's words
    6 and 7 (RFC 7693 2.5) of the person the code uses."""
    text = " ".join(DOC.split())
    person = auth._PERSON
    w6, w7 = (int.from_bytes(person[i : i + 4], "little") for i in (0, 4))
    assert f"`{person.decode()}`: `p[6]" in text
    assert f"`p[6] = 0x{w6:08x}`, `p[7] = 0x{w7:08x}`" in text


def test_the_zenoh_credential_keys_are_the_transports() -> None:
    from transport import zenoh

    for key in ("user", "password", "dictionary_file"):
        assert f"`{zenoh._USRPWD}/{key}`" in DOC
    assert auth.ZENOH_USER == "teleop"


# --------------------------------------------------------------------------------------------
# the document is a specification: it names no code (the code map is in the development docs)
# --------------------------------------------------------------------------------------------
def _package_names() -> set[str]:
    """Every public class and function defined in the package's modules (``teleop``, ``transport``)."""
    import pkgutil

    import teleop
    import transport

    names: set[str] = set()
    for pkg in (teleop, transport):
        for info in pkgutil.walk_packages(pkg.__path__, f"{pkg.__name__}."):
            if info.name.split(".")[-1].startswith("_"):
                continue
            try:
                mod = importlib.import_module(info.name)
            except ImportError:  # an optional dependency (a robot driver) is not installed
                continue
            for name, obj in vars(mod).items():
                if name.startswith("_") or getattr(obj, "__module__", None) != mod.__name__:
                    continue
                if inspect.isclass(obj) or inspect.isfunction(obj):
                    names.add(name)
    return names


def _protocol_terms() -> set[str]:
    """Words a code span of the document may hold although a class or function of the package has
    that name: the protocol's own terms (message kinds, hello keys, data fields, the test vectors'
    keys) and the counters of the reference's summary the text cites, not references to the code."""
    keys: set[str] = set()

    def walk(x: object) -> None:
        if isinstance(x, dict):
            keys.update(x)
            for v in x.values():
                walk(v)

    from teleop.session.settings import SETTINGS

    walk(INPUTS)
    return {*protocol.KINDS, *(x.key for x in SETTINGS), *wire.Packet._fields, *keys, "kernel_drops"}


def test_the_document_names_no_code() -> None:
    """No module path, source file, test file, or class or function of the package: an implementer
    reads the protocol, not the reference's code (which the development docs map to its sections)."""
    assert not re.findall(r"\b(?:teleop|transport|tests)\.[a-z_]+\.?\w*", DOC), "a module path"
    assert not re.findall(r"\b(?:teleop|transport|tests|tools|bench)/[\w/]*\.py\b", DOC), "a source file"
    assert not re.findall(r"\w\.py\b", DOC), "a Python file"
    assert not re.search(r"\bPython\b|the code is right", DOC)
    spans = re.findall(r"`([^`\n]+)`", DOC)
    code = _package_names() - _protocol_terms()
    named = sorted({w for span in spans for w in re.findall(r"[A-Za-z_]\w*", span) if w in code})
    assert not named, f"PROTOCOL.md names the package's classes or functions: {named}"


def test_the_contents_list_every_section() -> None:
    contents = DOC.split("## 1. Overview", 1)[0]
    for number, title in re.findall(r"^## (\d+)\. (.+)$", DOC, re.M):
        assert f"[{number} " in contents, f"section {number} ({title}) is not in the contents"


# --- issue 49: the gaps an outside implementation had to guess at ----------------------------------
def test_every_message_kind_travels_under_the_key_the_document_gives_it() -> None:
    """Section 2.2 (MUST): hello, welcome, retry and reject under K_hs; start, started and bye under
    the session key; and a message under the other kind's key is refused after parsing."""
    assert {c.kind for c in protocol.HANDSHAKE_KINDS} == {"hello", "welcome", "retry", "reject"}
    assert set(protocol.KINDS) - {c.kind for c in protocol.HANDSHAKE_KINDS} == {"start", "started", "bye"}
    text = " ".join(_section("2.2").split())
    assert "**The key of each message kind** (MUST, both sides)" in text
    assert "`hello`, `welcome`, `retry` and `reject` travel under the handshake key only" in text
    assert "`start`, `started`, `bye` and data under the session key of the sender's direction only" in text


def test_the_jump_bound_runs_on_the_receivers_monotonic_clock_across_tick_0() -> None:
    """Section 2.4: ``elapsed`` counts from the start's acceptance on the handshake's clock.  An
    operator whose first data packet is 2000 counters past its start, 0.3 s later, is within the
    bound (1024 + 4000 * 0.3 = 2224); on a session clock that starts again at tick 0 the robot
    counted no time since the start and refused it as a jump (bound 1024)."""
    from teleop.session.endpoint import State

    from .vnet import VirtualNet, params

    net = VirtualNet(0.1)
    to = net.teleoperator()
    op = net.operator(params(duration=1.0))
    net.seconds(5.0, stop=lambda: op.ep.port is not None)
    assert op.ep.state == State.STARTING and op.ep.port is not None
    op.ep.port.keys.tx.counter += 2000  # its next datagram, its first data packet, skips 2000
    net.seconds(5.0, stop=lambda: (port := to.ep.port) is not None and port.node.counters.accepted > 0)
    assert to.ep.port is not None
    assert to.ep.port.security.counter_jumps == 0 and to.ep.port.node.counters.accepted > 0
    assert "the same clock before tick 0 (a `start`, a `started`) and after it" in " ".join(DOC.split())


def test_a_candidate_keeps_four_addresses_in_all_the_first_for_good() -> None:
    """Section 4.3 step 3: 4 addresses in all, the first and the 3 latest others: a start from the
    first address, or from one of the 3 latest, is answered; from one evicted, not."""
    secret, t = bytes(32), 10**12
    addrs = [(f"10.0.0.{i}", 5000 + i) for i in range(1, 7)]

    def handshake(start_from: tuple[str, int]) -> str:
        to = protocol.TeleoperatorHandshake({}, now_ns=t, timeout_s=10.0, psk=PSK, cookie_secret=secret)
        hello: dict[str, Any] = {"t": "hello", "v": 1, "t_ns": 7, "nonce": NONCE_OP, **_params().to_msg()}
        sealer, opener = (
            auth.Sealer(K_HS, auth.HANDSHAKE, wire.FORWARD),
            auth.Opener(K_HS, auth.HANDSHAKE, wire.BACKWARD),
        )
        nonce_to = b""
        for a in addrs:  # the same operator's hello (one nonce) from six addresses, in this order
            body = msgpack.packb(
                {**hello, "cookie": protocol.make_cookie(secret, a, NONCE_OP, t)}, use_bin_type=True
            )
            (welcome,) = [protocol.parse(opener.verify(d)[1]) for d, _ in to.receive(sealer.seal(body), a, t)]
            assert isinstance(welcome, protocol.Welcome)
            nonce_to = welcome.nonce
        k_fwd, _ = auth.session_keys(PSK, SESSION, NONCE_OP, nonce_to)
        start = protocol.encode(protocol.Start(SESSION, t + 300_000_000, rtt_ns=100_000))
        out = to.receive(auth.Sealer(k_fwd, auth.SESSION, wire.FORWARD).seal(start), start_from, t)
        return "started" if out else "nothing"

    assert handshake(addrs[0]) == "started"  # the first, kept for good
    assert [handshake(a) for a in addrs[3:]] == ["started"] * 3  # the 3 latest
    assert [handshake(a) for a in addrs[1:3]] == ["nothing"] * 2  # evicted by the 5th and 6th
    assert protocol.CANDIDATE_ADDRS == 4
    assert "**4** addresses in all, the first kept for good and the **3** latest others" in " ".join(
        DOC.split()
    )


def _byes_of(session: int, out: list[tuple[Any, bytes]]) -> list[Any]:
    """The session-key byes of ``session`` among the datagrams ``out`` (the body is not encrypted)."""
    found = []
    for _, data in out:
        hdr = auth.peek(data)
        body = data[auth.HEADER_BYTES : -auth.TAG_BYTES]
        if hdr is None or hdr[0] != auth.SESSION or not protocol.is_control(body):
            continue
        with contextlib.suppress(ProtocolError):
            msg = protocol.parse(body)
            if isinstance(msg, protocol.Bye) and msg.session == session:
                found.append(msg)
    return found


def _recorder(sent: list[tuple[Any, bytes]]) -> Any:
    """A tap that keeps (source, datagram) of everything sent and delivers it unchanged."""

    def tap(now: int, src: Any, dst: Any, data: bytes) -> list[tuple[Any, Any, bytes]]:
        sent.append((src, data))
        return [(src, dst, data)]

    return tap


def test_a_ghost_ends_with_no_bye() -> None:
    """Sections 4.3 step 8 and 4.6: a teleoperator ends a session its operator never joined at once,
    with no linger and no bye; it waits for an operator again."""
    from teleop.session.endpoint import State
    from teleop.session.events import EndReason, SessionEnded

    from .vnet import TO, VirtualNet, params

    net = VirtualNet(0.1)
    to = net.teleoperator()
    op = net.operator(params(duration=0.0))
    sent: list[tuple[Any, bytes]] = []
    net.tap = _recorder(sent)
    net.seconds(20.0, stop=lambda: op.ep.state != State.HANDSHAKE)
    net.kill(op.addr)  # dies once its start was confirmed: the robot's session is a ghost
    net.seconds(30.0, stop=lambda: bool(to.of(SessionEnded)))
    net.seconds(1.0)
    (ev,) = to.of(SessionEnded)
    assert ev.reason == EndReason.PEER_SILENT and to.ep.state == State.HANDSHAKE
    assert not _byes_of(7, [(s, d) for s, d in sent if s == TO])
    assert "no linger and **no `bye`**" in " ".join(_section("4.3").split())


def test_a_takeover_sends_the_old_operator_no_bye_and_runs_the_new_session_from_its_tick_0() -> None:
    """Sections 4.5 and 4.6: the replaced session ends at once with no bye; the new session is run
    as any the robot commits to, from its own tick 0 when its start came ahead of it."""
    from teleop.session.endpoint import State
    from teleop.session.events import EndReason, Replaced, SessionEnded

    from .vnet import OP, TO, VirtualNet, params

    net = VirtualNet(0.5)
    to = net.teleoperator()
    op = net.operator(params(duration=8.0))
    net.seconds(5.0, stop=lambda: op.ep.state == to.ep.state == State.RUNNING)
    net.seconds(1.0)
    sent: list[tuple[Any, bytes]] = []
    net.tap = _recorder(sent)
    net.kill(OP)
    net.seconds(0.3)
    op2 = net.operator(params(session=8, duration=2.0), addr=("10.0.0.4", 5000), offset_ns=3 * 10**9)
    net.seconds(5.0, stop=lambda: op2.ep.state == State.RUNNING)
    (rp,) = to.of(Replaced)
    assert (rp.old_session, rp.new_session) == (7, 8)
    assert [e.reason for e in to.of(SessionEnded)] == [EndReason.REPLACED]
    assert not _byes_of(7, [(s, d) for s, d in sent if s == TO])
    new = to.started()[-1]
    assert new.params.session == 8 and new.k0 == 0  # its own tick 0, not the old session's count
    assert "its first tick is tick 0 when the start came ahead of it" in " ".join(_section("4.5").split())


def test_the_robot_starts_within_its_phase_range_whatever_the_hello_says() -> None:
    """Section 5.1: the hello's ``phase`` only caps where the robot starts; the start is the stated
    formula, in [0.25, max(0.25, min(phase, 0.9))], and a hello below 0.25 or above 0.9 is valid."""
    from teleop.session.link.phase import ClockTracker

    for dt in (1e-3, 1e-4, 1e-2):
        for phase in (0.0, 0.1, 0.25, 0.5, 0.95, 0.999):
            p = ClockTracker(dt, phase, moves_phase=True).phase
            assert p == max(0.25, min(phase, 150e-6 / dt, 0.9)), (dt, phase)
            assert 0.25 <= p <= max(0.25, min(phase, 0.9))
            params = SessionParams(session=7, codec="none", scenario="step", dof=1, b=1, full_scale=2,
                                   duration=1, dt=dt, phase=phase)  # fmt: skip
            assert SessionParams.from_msg(params.to_msg()).phase == phase
    assert "`p = max(0.25, min(phase, 150 us / dt, 0.9))`" in " ".join(_section("5.1").split())


def test_conceal_repeats_the_payloads_value_not_what_the_guard_let_through() -> None:
    """Section 3.7 step 6: ``last`` is the payload's value as decoded, before the guard of step 7."""
    node = make_node(
        "teleoperator", scenario="step", dof=1, dt=0.001, b=1.0, codec="none", full_scale=2.0,
        session=9, options=PortOptions(on_loss="conceal"),
    )  # fmt: skip
    codec = make_codec("none", 1, 2.0)
    payload = codec.encoder().encode(np.array([1.0]))
    assert payload is not None
    value = float(codec.raw.dequantize(codec.raw.quantize(np.array([1.0])))[0])
    tiny = 0.25 * 0.5e-3 * value**2  # a quarter of the sample's energy: the guard cuts it to half
    node.receive_packet(wire.Packet(9, wire.FORWARD, 0, 0, 0, codec.codec_id, payload, tiny))
    node.tick(0.0)
    assert float(node.wave_in[0]) == pytest.approx(0.5 * value)  # what the guard let through
    assert float(node.decoder.next()[0]) == value  # what conceal plays next: the payload's value


def test_the_report_bucket_is_refilled_to_the_last_tick_run() -> None:
    """Section 3.7 step 7: ``t`` is the session time of the last tick the node ran before it took
    the report (here tick 99 of 100 ran: 0.099 s), not of the tick about to run (0.1 s)."""
    dt = 0.001
    node = make_node(
        "teleoperator", scenario="step", dof=1, dt=dt, b=1.0, codec="none", full_scale=2.0,
        session=9, options=PortOptions(),
    )  # fmt: skip
    p_max = node.guard.max_power
    depth = 0.2 * p_max
    payload = make_codec("none", 1, 2.0).encoder().encode(np.array([0.0]))
    assert payload is not None

    def report(seq: int, energy: float) -> None:
        node.receive_packet(wire.Packet(9, wire.FORWARD, seq, seq, 0, 0, payload, energy))

    node.tick(0.0)
    report(0, depth)  # the first report empties the bucket (t_prev = 0, tick 0's time)
    for k in range(1, 100):
        node.tick(k * dt)
    before = node.guard.report.energy_reports_clamped
    report(1, depth + p_max * 99.5 * dt)  # half a tick more than 99 ticks' refill
    assert node.guard.report.energy_reports_clamped == before + 1
    text = " ".join(_section("3.7").split())
    assert "the session time `j dt` of the last tick the receiving node ran before it accepted" in text


def test_integers_in_any_msgpack_format_and_never_negative() -> None:
    """Sections 3.1 and 4.1: any msgpack integer format that holds the value; a negative integer is
    out of every int field's range and refused."""
    body = (
        b"\x9a" + msgpack.packb(b"TW", use_bin_type=True) + b"\x01" + b"\xd0\x09" + b"\x00"
        + b"\xd0\x05" + b"\x00\x00\x00" + msgpack.packb(b"\0\0", use_bin_type=True) + msgpack.packb(0.0)
    )  # fmt: skip
    body += zlib.crc32(body).to_bytes(4, "little")
    pkt = wire.decode(body)
    assert (pkt.session, pkt.seq) == (9, 5)  # int 8 (d0) holds them as well as a fixint
    neg = msgpack.packb([b"TW", 1, 9, 0, -1, 0, 0, 0, b"\0\0", 0.0], use_bin_type=True)
    with pytest.raises(wire.WireError, match="field seq must be an unsigned integer <= 4294967295, got -1"):
        wire.decode(neg + zlib.crc32(neg).to_bytes(4, "little"))
    text = " ".join(DOC.split())
    assert "`field seq must be an unsigned integer <= 4294967295, got -1`" in text
    msg = _params().to_msg()
    with pytest.raises(ProtocolError, match=re.escape("seed must be an integer in 0..4294967295, got -1")):
        SessionParams.from_msg({**msg, "seed": -1})
    assert "`seed must be an integer in 0..4294967295, got -1`" in " ".join(_section("4.1").split())


@pytest.mark.parametrize(
    ("sent", "canonical"),
    [("2ms", None), (" 2", "2"), ("02", "2"), ("2.0", "2"), (".5", "0.5"), ("1e1", "10"), ("1_0", "10"),
     ("-0", "0"), ("OFF", "off"), ("\u0662", "2")],
)  # fmt: skip
def test_a_robot_refuses_every_spelling_of_playout_but_the_canonical_one(
    sent: str, canonical: str | None
) -> None:
    """Section 4.2: the robot names no normalisation; each spelling the table lists is refused in one
    line naming the field (and its canonical form, when the spelling names a valid one)."""
    msg = _params().to_msg()
    with pytest.raises(ProtocolError, match="playout") as e:
        SessionParams.from_msg({**msg, "playout": sent})
    assert "\n" not in str(e.value)
    if canonical is not None:
        assert f"canonical form '{canonical}'" in str(e.value)
        assert SessionParams.from_msg({**msg, "playout": canonical}).playout == canonical
    listed = f'`"{sent}"`' if sent != "\u0662" else "a non-ASCII digit"
    assert listed in DOC
