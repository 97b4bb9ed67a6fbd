"""The Zenoh transport on loopback: peer-to-peer, through a router, TLS/mTLS, failures, wire format.

Every session is opened with scouting off and explicit 127.0.0.1 endpoints, and closed.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import shutil
import socket
import subprocess
import threading
import time
import zlib
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import msgpack
import pytest
import zenoh

from teleop.session import auth, wire
from tests.waiting import await_for, pace, tcp_listening
from transport.zenoh import (
    ZENOH_PEER,
    TransportError,
    ZenohTransport,
    make_config,
    run_router,
)

DEPLOY = Path(__file__).resolve().parent.parent / "deploy" / "zenoh"


def free_port(kind: socket.SocketKind = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


async def until_listening(port: int, timeout: float = 5.0) -> None:
    """Until something listens on TCP 127.0.0.1:port (the router task opened its listener)."""
    await await_for(lambda: tcp_listening(port), timeout, f"a listener on {port}")


SYNC_END = b"sync end"


async def sync(a: ZenohTransport, b: ZenohTransport, timeout: float = 5.0) -> None:
    """Ping both ways until each side hears the other: the link is up and subscriptions are known.
    Then each sends SYNC_END and each reads up to the other's: a Zenoh publisher's samples arrive
    in order, so no ping is left in flight behind it."""
    heard = {id(a): False, id(b): False}

    def ping() -> bool:
        for tx, rx in ((a, b), (b, a)):
            if not heard[id(rx)]:
                tx.send(b"sync", ZENOH_PEER)
        for t in (a, b):
            if t.drain():
                heard[id(t)] = True
        return all(heard.values())

    await await_for(ping, timeout, "the Zenoh transports to hear each other")
    a.send(SYNC_END, ZENOH_PEER)
    b.send(SYNC_END, ZENOH_PEER)
    ended = {id(a): False, id(b): False}

    def to_the_end() -> bool:
        for t in (a, b):
            ended[id(t)] = ended[id(t)] or any(d == SYNC_END for d, _, _ in t.drain())
        return all(ended.values())

    await await_for(to_the_end, timeout, "each side's last ping")


async def exchange(op: ZenohTransport, to: ZenohTransport, n: int = 200) -> None:
    """n sequenced messages each way at about 1 kHz: all delivered, in order, sane timestamps."""
    await sync(op, to)
    t0 = time.monotonic_ns()
    got: dict[int, list[tuple[bytes, tuple[str, int], int]]] = {id(op): [], id(to): []}
    for i in range(n):
        op.send(b"f" + i.to_bytes(4, "little"), ("ignored", 1))
        to.send(b"b" + i.to_bytes(4, "little"), ("ignored", 1))
        await pace(0.001)
        for t in (op, to):
            got[id(t)] += t.drain()
    give_up = time.monotonic() + 5
    while any(len(v) < n for v in got.values()) and time.monotonic() < give_up:
        for t in (op, to):
            if await t.wait(0.05):
                got[id(t)] += t.drain()
    t1 = time.monotonic_ns()
    for t, tag in ((to, b"f"), (op, b"b")):
        items = got[id(t)]
        assert [d for d, _, _ in items] == [tag + i.to_bytes(4, "little") for i in range(n)]
        assert all(addr == ZENOH_PEER for _, addr, _ in items)
        stamps = [ts for _, _, ts in items]
        assert all(t0 <= ts <= t1 for ts in stamps) and stamps == sorted(stamps)
    assert op.inbox_overflow == to.inbox_overflow == 0
    assert op.socket_errors == to.socket_errors == 0


@contextlib.asynccontextmanager
async def pair(op_config: zenoh.Config, to_config: zenoh.Config, prefix: str) -> AsyncIterator[Any]:
    to = await ZenohTransport.open("teleoperator", prefix, to_config)
    try:
        op = await ZenohTransport.open("operator", prefix, op_config)
        try:
            yield op, to
        finally:
            op.close()
    finally:
        to.close()


@contextlib.asynccontextmanager
async def router(listen: list[str], config_file: str | None = None) -> AsyncIterator[None]:
    stop = asyncio.Event()
    task = asyncio.create_task(run_router(listen, config_file, stop))
    try:
        await until_listening(int(listen[0].rsplit(":", 1)[1]))
        yield
    finally:
        stop.set()
        await task


# --- configuration ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs,msg",
    [
        ({"mode": "broker", "listen": ["tcp/127.0.0.1:7447"]}, "mode must be one of peer, client, router"),
        ({"listen": ["127.0.0.1:7447"]}, "PROTO/HOST:PORT with PROTO one of tcp, udp, tls, quic"),
        ({"listen": ["tcp/127.0.0.1"]}, "PROTO/HOST:PORT"),
        ({"connect": ["http/127.0.0.1:80"]}, "protocol must be one of tcp, udp, tls, quic"),
        ({"listen": ["tcp/127.0.0.1:70000"]}, "port must be 0..65535"),
        ({"connect": ["tcp/127.0.0.1:0"]}, "port must be 1..65535"),
        ({"mode": "client"}, "client mode needs a connect endpoint"),
        ({"mode": "router"}, "router mode needs a listen endpoint"),
        ({"mode": "peer"}, "peer mode needs a listen or connect endpoint"),
        ({"listen": ["tcp/x:1"], "config_file": "/nonexistent.json5"}, "cannot load Zenoh config"),
    ],
)
def test_make_config_rejects_bad_input(kwargs: dict[str, Any], msg: str) -> None:
    with pytest.raises(ValueError, match=msg):
        make_config(**kwargs)


def test_make_config_scouting_off_and_explicit_endpoints(tmp_path: Path) -> None:
    def get(c: zenoh.Config, key: str) -> Any:
        return json.loads(c.get_json(key))

    # Even a file that asks for scouting gets it switched off; arguments override the file.
    f = tmp_path / "c.json5"
    f.write_text(
        '{mode: "router", scouting: {multicast: {enabled: true}, gossip: {enabled: true}},'
        ' listen: {endpoints: ["tcp/127.0.0.1:1"]}}'
    )
    c = make_config("peer", connect=["tcp/127.0.0.1:7447"], config_file=str(f))
    assert get(c, "mode") == "peer"
    assert get(c, "scouting/multicast/enabled") is False and get(c, "scouting/gossip/enabled") is False
    assert get(c, "listen/endpoints") == ["tcp/127.0.0.1:1"]
    assert get(c, "connect/endpoints") == ["tcp/127.0.0.1:7447"]
    # No listen anywhere: empty, never Zenoh's all-interfaces default.
    assert get(make_config("peer", connect=["tcp/127.0.0.1:7447"]), "listen/endpoints") == []
    cl = make_config("client", connect=["tcp/127.0.0.1:7447"])
    assert get(cl, "connect/timeout_ms") == 2000 and get(cl, "transport/unicast/open_timeout") == 2000
    assert get(cl, "transport/link/tx/queue/size/real_time") == 16


def test_a_routers_shared_memory_is_off(tmp_path: Path) -> None:
    """With it on, a router admitted 351 client sessions (tests/test_fleet_zenoh.py has the count);
    off even where its file asks (no teleop datagram reaches its threshold); endpoints keep Zenoh's
    default."""

    def shm(c: zenoh.Config) -> Any:
        return json.loads(c.get_json("transport/shared_memory/enabled"))

    assert shm(make_config("router", listen=["tcp/127.0.0.1:7447"])) is False
    f = tmp_path / "r.json5"
    f.write_text("{transport: {shared_memory: {enabled: true}}}")
    assert shm(make_config("router", listen=["tcp/127.0.0.1:7447"], config_file=str(f))) is False
    assert shm(make_config("client", connect=["tcp/127.0.0.1:7447"])) is True


@pytest.mark.parametrize(
    "name",
    ["peer", "client", "router", "tls/router-tls", "tls/client-tls", "tls/router-mtls", "tls/client-mtls"],
)
def test_deploy_configs_load(name: str) -> None:
    path = DEPLOY / f"{name}.json5"
    mode = json.loads(zenoh.Config.from_file(str(path)).get_json("mode"))
    c = make_config(mode, config_file=str(path))
    assert json.loads(c.get_json("scouting/multicast/enabled")) is False
    eps = json.loads(c.get_json("listen/endpoints")) + json.loads(c.get_json("connect/endpoints"))
    assert eps and all("127.0.0.1" in e for e in eps)


async def test_bad_role_and_prefix() -> None:
    c = make_config("peer", listen=["tcp/127.0.0.1:0"])
    with pytest.raises(ValueError, match="role must be one of operator, teleoperator"):
        await ZenohTransport.open("pilot", "teleop/t", c)
    with pytest.raises(ValueError, match="no wildcards"):
        await ZenohTransport.open("operator", "teleop/*", c)


# --- peer to peer ------------------------------------------------------------------------------


@pytest.mark.parametrize("proto", ["tcp", "udp"])
async def test_peer_exchange_and_wait(proto: str) -> None:
    ep = f"{proto}/127.0.0.1:{free_port(socket.SOCK_DGRAM if proto == 'udp' else socket.SOCK_STREAM)}"
    async with pair(make_config("peer", connect=[ep]), make_config("peer", listen=[ep]), "t/peer") as (
        op,
        to,
    ):
        assert op.tx_key == "t/peer/forward" and op.rx_key == "t/peer/backward"
        assert to.tx_key == "t/peer/backward" and to.rx_key == "t/peer/forward"
        assert op.local_address[1] == 0 and op.local_address[0] not in ("", to.local_address[0])
        assert not await to.wait(0.01)  # nothing sent: times out
        await exchange(op, to)
        # wait() is woken by the Zenoh callback, long before its 5 s timeout
        t = time.monotonic()
        asyncio.get_running_loop().call_later(0.02, op.send, b"x", ZENOH_PEER)
        assert await to.wait(5.0)
        assert time.monotonic() - t < 1.0
        assert [d for d, _, _ in to.drain()] == [b"x"]
    op.close()  # idempotent
    with pytest.raises(TransportError, match="closed"):
        op.send(b"x", ZENOH_PEER)


async def test_inbox_overflow_keeps_the_latest() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    to = await ZenohTransport.open("teleoperator", "t/ovf", make_config("peer", listen=[ep]), inbox_size=5)
    try:
        op = await ZenohTransport.open("operator", "t/ovf", make_config("peer", connect=[ep]))
        try:
            await sync(op, to)
            for i in range(30):
                op.send(i.to_bytes(2, "big"), ZENOH_PEER)
                await pace(0.001)  # Zenoh itself must not drop (congestion DROP)
            await await_for(lambda: to.inbox_overflow >= 25, 5.0, "the overflow")
            got = to.drain()
            assert len(got) == 5 and to.inbox_overflow == 25
            assert [d for d, _, _ in got] == [i.to_bytes(2, "big") for i in range(25, 30)]
        finally:
            op.close()
    finally:
        to.close()


# --- through a router --------------------------------------------------------------------------


async def test_clients_through_router() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    async with (
        router([ep]),
        pair(make_config("client", connect=[ep]), make_config("client", connect=[ep]), "t/r") as (
            op,
            to,
        ),
    ):
        await exchange(op, to, n=100)


async def test_client_without_router_fails_clearly() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"  # nothing listens here
    t = time.monotonic()
    with pytest.raises(TransportError, match=f"cannot reach Zenoh router at {ep}") as e:
        await ZenohTransport.open("operator", "t/none", make_config("client", connect=[ep]))
    assert time.monotonic() - t < 5.0
    assert isinstance(e.value, OSError) and ".rs:" not in str(e.value)


async def test_listen_port_in_use_fails_clearly() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        ep = f"tcp/127.0.0.1:{s.getsockname()[1]}"
        with pytest.raises(TransportError, match=r"cannot open Zenoh peer session.*Address already in use"):
            await ZenohTransport.open("teleoperator", "t/busy", make_config("peer", listen=[ep]))


# --- a subscriber that knows only the docs (Zenoh guide, PROTOCOL.md) -------------------------------


def readme_subscriber(
    connect: str, prefix: str, n: int, timeout: float = 5.0, mode: str = "peer"
) -> tuple[list[list[Any]], int, int]:
    """Decode ``n`` live data packets on ``<prefix>/forward`` knowing only the documented format.

    Returns (packet fields, control maps seen, data packets with a bad CRC).  Uses zenoh, msgpack
    and zlib only (no teleop import), so it also works against a real session:
    ``readme_subscriber("tcp/127.0.0.1:7447", "teleop", 10)`` (``mode="client"`` for a router).
    """
    cfg = zenoh.Config.from_json5(
        json.dumps(
            {
                "mode": mode,
                "connect": {"endpoints": [connect]},
                "listen": {"endpoints": []},
                "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
            }
        )
    )
    packets: list[list[Any]] = []
    counts = {"control": 0, "bad_crc": 0}
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        envelope = sample.payload.to_bytes()
        # The envelope: b"T", flags, uint64 counter (10 bytes) ... a 16-byte tag.  Reading needs no
        # key (there is no confidentiality); only forging would.
        if envelope[:1] != b"T" or len(envelope) < 26:
            return
        raw = envelope[10:-16]
        if raw[:1] and (raw[0] & 0xF0 == 0x80 or raw[0] in (0xDE, 0xDF)):  # msgpack map: control
            counts["control"] += 1
            return
        body, crc = raw[:-4], int.from_bytes(raw[-4:], "little")  # data: array + CRC-32 (LE)
        if zlib.crc32(body) != crc:
            counts["bad_crc"] += 1
            return
        fields = msgpack.unpackb(body, raw=False)
        if len(packets) < n:
            packets.append(fields)
            if len(packets) == n:
                done.set()

    with zenoh.open(cfg) as session:  # closing the session undeclares the subscriber
        session.declare_subscriber(f"{prefix}/forward", on_sample)
        done.wait(timeout)
    return packets, counts["control"], counts["bad_crc"]


async def test_plain_zenoh_subscriber_decodes_live_packets() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    op = await ZenohTransport.open("operator", "t/wire", make_config("peer", listen=[ep]))
    try:
        stop = threading.Event()
        sealer = auth.Sealer(auth.INSECURE_KEY, auth.SESSION, wire.FORWARD)

        async def publish() -> None:
            k = 0
            while not stop.is_set():
                p = wire.Packet(
                    session=0xC0FFEE,
                    direction=wire.FORWARD,
                    seq=k,
                    tick=100 + k,
                    t_us=time.monotonic_ns() // 1000,
                    codec_id=2,
                    payload=b"\x01\x02\x03",
                    energy=0.125 * k,
                )
                op.send(sealer.seal(wire.encode(p)), ZENOH_PEER)
                op.send(sealer.seal(msgpack.packb({"t": "hello", "session": 1})), ZENOH_PEER)  # a control map
                k += 1
                await pace(0.002)

        pub = asyncio.create_task(publish())
        try:
            packets, controls, bad_crc = await asyncio.to_thread(readme_subscriber, ep, "t/wire", 5)
        finally:
            stop.set()
            await pub
    finally:
        op.close()
    assert len(packets) == 5 and controls >= 4 and bad_crc == 0
    for f in packets:
        assert len(f) == 10
        magic, version, session, direction, seq, tick, t_us, codec_id, payload, energy = f
        assert magic == b"TW" and version == 1 and session == 0xC0FFEE and direction == 0
        assert tick == 100 + seq and t_us > 0 and codec_id == 2 and payload == b"\x01\x02\x03"
        assert energy == 0.125 * seq
    seqs = [f[4] for f in packets]
    assert seqs == sorted(seqs) and len(set(seqs)) == 5


# --- TLS and mutual TLS ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def certs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    if shutil.which("openssl") is None:
        pytest.skip("openssl not installed: deploy/zenoh/tls/make-test-certs.sh needs it")
    out = tmp_path_factory.mktemp("certs")
    subprocess.run(
        ["sh", str(DEPLOY / "tls" / "make-test-certs.sh"), str(out)],
        check=True,
        capture_output=True,
        timeout=60,
    )
    yield out


def deployed(name: str, certs: Path, dest: Path) -> str:
    """A deploy/zenoh/tls config with its /etc/teleop/tls paths pointed at the test certificates."""
    text = (DEPLOY / "tls" / f"{name}.json5").read_text().replace("/etc/teleop/tls", str(certs))
    path = dest / f"{name}.json5"
    path.write_text(text)
    return str(path)


@pytest.mark.integration  # openssl makes the certificates (the certs fixture)
@pytest.mark.parametrize("kind", ["tls", "mtls"])
async def test_tls_clients_through_tls_router(kind: str, certs: Path, tmp_path: Path) -> None:
    ep = f"tls/127.0.0.1:{free_port()}"
    client = deployed(f"client-{kind}", certs, tmp_path)
    async with router([ep], deployed(f"router-{kind}", certs, tmp_path)):
        c = make_config("client", connect=[ep], config_file=client)
        async with pair(c, c, f"t/{kind}") as (op, to):
            await exchange(op, to, n=50)


@pytest.mark.integration  # openssl makes the certificates (the certs fixture)
async def test_mtls_router_refuses_client_without_certificate(certs: Path, tmp_path: Path) -> None:
    ep = f"tls/127.0.0.1:{free_port()}"
    async with router([ep], deployed("router-mtls", certs, tmp_path)):
        c = make_config("client", connect=[ep], config_file=deployed("client-tls", certs, tmp_path))
        with pytest.raises(TransportError, match="cannot reach Zenoh router"):
            await ZenohTransport.open("operator", "t/mtls-no-cert", c)
