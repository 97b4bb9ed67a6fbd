"""Reading the logs the runner writes (``ROLE.mcap``, format in ``transport.mcaplog``): the
summary, every message, or the per-tick record as consecutive blocks of arrays.

It lives in the core because ``teleop report`` and the tests read logs and the core imports nothing
from ``transport/``; it only reads the path it is given, and treats the file as hostile: every
size, count and tick jump is bounded before it allocates, and any damage is one :class:`LogError`.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from teleop.port import fill_value

from .errors import RemoteError

__all__ = ["PER_TICK_TOPICS", "TOPICS", "LogError", "iter_messages", "iter_ticks", "read_log", "read_summary"]

PER_TICK_TOPICS = ("signals", "waves", "energy", "wire", "loop")
TOPICS = (*PER_TICK_TOPICS, "link", "events", "session", "summary")
LAG_TICKS = 5000  # how far a topic may trail the signals in the file (iter_ticks)
BLOCK_TICKS = 1 << 16  # iter_ticks hands on at most this many ticks a block (a long gap: several)
MAX_GAP_TICKS = 100_000_000  # a jump in a log's ticks beyond this (28 h at 1 kHz) is not a session

#: /ROLE/wire fields and the chunk arrays they come from.
WIRE_FIELDS = {
    "send_time": "send_time_s", "tx_seq": "tx_seq", "rx_seq": "rx_seq",
    "produced_payload": "produced_payload", "produced_packet": "produced_packet",
    "tx_wire": "tx_wire", "tx_payload": "tx_payload", "tx_baseline_wire": "tx_baseline_wire",
    "tx_baseline_payload": "tx_baseline_payload", "rx_wire": "rx_wire", "rx_payload": "rx_payload",
}  # fmt: skip
ENERGY_FIELDS = {
    "sent": "energy_sent", "played": "energy_played", "margin_observed": "energy_margin_observed",
    "played_epoch": "energy_played_epoch", "peer_epoch": "peer_epoch",
}  # fmt: skip


def iter_messages(path: Path, topics: list[str] | None = None) -> Iterator[tuple[str, dict[str, Any]]]:
    """(topic, decoded JSON message) of an MCAP file, in log-time order (any MCAP file; for our
    per-tick channels :func:`iter_ticks` is about three times faster)."""
    from mcap.reader import make_reader

    with path.open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=topics):
            yield channel.topic, json.loads(message.data)


class LogError(RemoteError):
    """A file that is not a log this stack wrote, or is damaged: what is wrong, where."""


def read_summary(path: Path) -> dict[str, Any]:
    """The ``/ROLE/summary`` message (empty if the process did not finish its log); through the
    file's index, so only the chunk holding it is read.  A damaged file raises :class:`LogError`."""
    from mcap.exceptions import McapError
    from zstandard import ZstdError

    role = path.stem.split("-", 1)[0]
    try:
        for _, m in iter_messages(path, topics=[f"/{role}/summary"]):
            if not isinstance(m, dict):
                raise LogError(f"{path}: its summary is not a JSON object")
            return m
    except (McapError, ZstdError, struct.error, UnicodeDecodeError, ValueError) as e:
        if isinstance(e, LogError):
            raise
        raise LogError(f"{path}: not a readable MCAP file ({type(e).__name__}: {e})") from None
    return {}


_OP_CHANNEL, _OP_MESSAGE = 0x04, 0x05
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
#: Per-tick topics: (message field, record name, kind): "vec" per DoF, "int" or "num" a scalar.
_FIELDS: dict[str, tuple[tuple[str, str, str], ...]] = {
    "signals": (("t", "play_time_s", "num"), ("v", "v", "vec"), ("f", "f", "vec")),
    "waves": (("wave_out", "wave_out", "vec"), ("wave_in", "wave_in", "vec")),
    "energy": tuple((n, s, "int" if s == "peer_epoch" else "num") for n, s in ENERGY_FIELDS.items()),
    "wire": tuple((n, s, "int" if s.endswith("seq") else "num") for n, s in WIRE_FIELDS.items()),
    "loop": (("lateness_ns", "lateness_ns", "int"),),
}


def _chunk_payloads(data: bytes, channels: dict[int, str]) -> dict[str, list[bytes]]:
    """The message payloads of a decompressed MCAP chunk by topic, in file order (channel records
    inside the chunk are learnt on the way).  A plain loop over the records' headers: the ``mcap``
    library builds an object per record, most of the time this reading used to take."""
    out: dict[str, list[bytes]] = {}
    off, end = 0, len(data)
    while off + 9 <= end:
        op = data[off]
        (length,) = _U64.unpack_from(data, off + 1)
        body = off + 9
        if op == _OP_MESSAGE:
            (cid,) = _U16.unpack_from(data, body)
            topic = channels.get(cid)
            if topic is not None:
                out.setdefault(topic, []).append(data[body + 22 : body + length])
        elif op == _OP_CHANNEL:
            (cid,) = _U16.unpack_from(data, body)
            (n,) = _U32.unpack_from(data, body + 4)
            channels[cid] = data[body + 8 : body + 8 + n].decode()
        off = body + length
    return out


def _iter_payloads(path: Path) -> Iterator[dict[str, list[bytes]]]:
    """Per MCAP chunk in file order: its message payloads by topic (a message outside any chunk
    comes alone)."""
    from mcap.records import Channel, Chunk, Message
    from mcap.stream_reader import StreamReader, get_chunk_data_stream

    channels: dict[int, str] = {}
    with path.open("rb") as f:
        for r in StreamReader(f, emit_chunks=True).records:
            if isinstance(r, Chunk):
                stream, size = get_chunk_data_stream(r)
                yield _chunk_payloads(stream.read(size), channels)
            elif isinstance(r, Channel):
                channels[r.id] = r.topic
            elif isinstance(r, Message) and r.channel_id in channels:
                yield {channels[r.channel_id]: [r.data]}


def _columns(topic: str, payloads: list[bytes]) -> dict[str, npt.NDArray[Any]]:
    """One topic's messages as columns: ``k`` and the record's names (JSON null: NaN); a message
    that is not the documented schema raises :class:`LogError`."""
    try:
        ms = json.loads(b"[" + b",".join(payloads) + b"]")  # one parse, not one per message
        cols: dict[str, npt.NDArray[Any]] = {"k": np.array([m["k"] for m in ms], dtype=np.int64)}
        for field, name, kind in _FIELDS[topic]:
            cols[name] = np.array([m.get(field) for m in ms], dtype=np.float64)
            if cols[name].ndim != (2 if kind == "vec" else 1):
                raise ValueError(f"{field} is not a {'list' if kind == 'vec' else 'number'} in every message")
    except (ValueError, TypeError, KeyError, OverflowError) as e:
        raise LogError(
            f"a /ROLE/{topic} message does not follow its schema: {type(e).__name__}: {e}"
        ) from None
    k = cols["k"]
    if k.size and (k.min() < 0 or np.any(np.diff(k) <= 0)):
        raise LogError(f"/ROLE/{topic}: tick numbers must increase from 0 (got {k[:8].tolist()}...)")
    if k.size > 1 and (jump := int(np.diff(k).max())) > MAX_GAP_TICKS:
        raise LogError(f"/ROLE/{topic}: a jump of {jump} ticks (at most {MAX_GAP_TICKS}): not a session")
    return cols


def iter_ticks(
    path: Path, topics: tuple[str, ...] = PER_TICK_TOPICS
) -> Iterator[tuple[int, dict[str, npt.NDArray[Any]]]]:
    """``ROLE.mcap`` as consecutive blocks of whole-session per-tick arrays: ``(k0, arrays)`` for
    ticks ``k0, k0 + 1, ...`` from tick 0 to the last tick run, by the record's names, plus ``ran``
    (the tick was run: its ``/ROLE/signals`` message is in the log).  A tick not run is filled as
    the record fills it (no value, no bytes, no sequence number).

    Streamed: a tick is handed on once every topic's messages have passed it (the writer logs a
    chunk of ticks a topic at a time), so memory holds a few MCAP chunks, not the session.  A topic
    more than ``LAG_TICKS`` behind the signals (a log cut off mid-chunk) counts as missing those
    ticks, as does a message for a tick whose signals are not in the log."""
    from mcap.exceptions import McapError
    from zstandard import ZstdError

    wanted = ("signals", *(t for t in topics if t != "signals"))
    role = path.stem.split("-", 1)[0]
    names = {f"/{role}/{t}": t for t in wanted}
    pending: dict[str, list[dict[str, npt.NDArray[Any]]]] = {t: [] for t in wanted}
    last = dict.fromkeys(wanted, -1)
    next_k = 0
    dof = 0

    def emit(upto: int) -> tuple[int, dict[str, npt.NDArray[Any]]] | None:
        """The block of ticks ``[next_k, upto]``, taken off the pending columns."""
        nonlocal next_k
        if upto < next_k:
            return None
        n = upto - next_k + 1
        cols: dict[str, dict[str, npt.NDArray[Any]]] = {}
        for t in wanted:
            parts = pending[t]
            if not parts:
                cols[t] = {}
                continue
            whole = {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}
            take = whole["k"] <= upto
            cols[t] = {c: v[take] for c, v in whole.items()}
            pending[t] = [{c: v[~take] for c, v in whole.items()}] if not take.all() else []
        ks = cols["signals"].get("k", np.zeros(0, dtype=np.int64))
        block: dict[str, npt.NDArray[Any]] = {}
        ran = np.zeros(n, dtype=bool)
        ran[ks - next_k] = True
        block["ran"] = ran
        for t in wanted:
            c = cols[t]
            if c:
                at = np.minimum(np.searchsorted(ks, c["k"]), max(ks.size - 1, 0))
                hit = (ks[at] == c["k"]) if ks.size else np.zeros(c["k"].size, dtype=bool)
                rows = c["k"][hit] - next_k
            for _, name, kind in _FIELDS[t]:
                # A tick run whose row is missing has no value (NaN); a tick not run has the fill.
                full = np.full((n, dof) if kind == "vec" else n, math.nan)
                if kind != "vec":
                    full[~ran] = fill_value(name)
                if c:
                    full[rows] = c[name][hit]
                if kind == "int":
                    block[name] = np.nan_to_num(full, nan=fill_value(name)).astype(np.int64)
                else:
                    block[name] = full
        k0 = next_k
        next_k = upto + 1
        return k0, block

    def blocks(upto: int) -> Iterator[tuple[int, dict[str, npt.NDArray[Any]]]]:
        while (out := emit(min(upto, next_k + BLOCK_TICKS - 1))) is not None:
            yield out

    try:
        for chunk in _iter_payloads(path):
            for topic, payloads in chunk.items():
                t = names.get(topic)
                if t is None:
                    continue
                cols = _columns(t, payloads)
                first, end = int(cols["k"][0]), int(cols["k"][-1])
                if first <= last[t] or first - last[t] > MAX_GAP_TICKS:
                    raise LogError(f"{topic}: tick {first} after tick {last[t]} (ticks are logged in order)")
                if t == "signals":
                    dof = dof or cols["v"].shape[1]
                    if cols["v"].shape[1] != dof or cols["f"].shape[1] != dof:
                        raise LogError(f"{topic}: v and f must have {dof} values (DoF) in every message")
                elif t == "waves" and cols["wave_out"].shape[1] != (dof or cols["wave_out"].shape[1]):
                    raise LogError(f"{topic}: waves must have as many values as the signals")
                pending[t].append(cols)
                last[t] = end
            ready = min(max(last[t], last["signals"] - LAG_TICKS) for t in wanted)
            yield from blocks(min(ready, last["signals"]))
        yield from blocks(last["signals"])
    except LogError as e:
        raise LogError(f"{path}: {e}") from None
    except (McapError, ZstdError, struct.error, UnicodeDecodeError) as e:  # damaged or cut off
        raise LogError(f"{path}: not a readable MCAP file ({type(e).__name__}: {e})") from None


def read_log(path: Path) -> tuple[dict[str, Any], dict[str, npt.NDArray[Any]]]:
    """``ROLE.mcap`` as (summary, whole-session per-tick arrays by the record's names, from tick 0),
    for tests and short sessions: it holds the whole session (about 300 bytes a tick at 2 DoF);
    ``teleop report`` folds :func:`iter_ticks` instead.  ``lateness_ns`` holds one entry per tick
    run, in order (as the loop's record did)."""
    blocks = [b for _, b in iter_ticks(path)]
    if not blocks:
        return read_summary(path), {}
    out = {name: np.concatenate([b[name] for b in blocks]) for name in blocks[0]}
    out["lateness_ns"] = out["lateness_ns"][out.pop("ran")]
    return read_summary(path), out
