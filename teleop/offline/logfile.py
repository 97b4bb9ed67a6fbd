"""Reading the logs the runner writes (``ROLE.mcap``, format in ``shell.mcaplog``): the
summary, every message, or the per-tick record as consecutive blocks of arrays.

It lives in the core because ``teleop report`` and the tests read logs and the core imports nothing
from ``shell/``; it only reads the path it is given, and treats the file as hostile: every
size, count and tick jump is bounded before it allocates, and any damage is one :class:`LogError`.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import stat
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
import numpy.typing as npt

from teleop.errors import RemoteError
from teleop.limits import MAX_DOF
from teleop.session.logformat import ENERGY_FIELDS, INT_FIELDS, PER_TICK_TOPICS, TOPICS, WIRE_FIELDS
from teleop.session.port import fill_value
from teleop.session.protocol import ProtocolError, SessionParams

__all__ = [
    "PER_TICK_TOPICS",
    "TOPICS",
    "LogError",
    "UntrustedLog",
    "find_pair",
    "iter_messages",
    "iter_ticks",
    "log_session",
    "read_columns",
    "read_log",
    "read_session",
    "read_states",
    "read_summary",
    "topic_lines",
]

LAG_TICKS = 5000  # how far a topic may trail the signals in the file (iter_ticks)
BLOCK_TICKS = 1 << 16  # iter_ticks hands on at most this many ticks a block (a long gap: several)
MAX_GAP_TICKS = 100_000_000  # a jump in a log's ticks beyond this (28 h at 1 kHz) is not a session


def iter_messages(path: Path, topics: list[str] | None = None) -> Iterator[tuple[str, dict[str, Any]]]:
    """(topic, decoded JSON message) of an MCAP file, in log-time order (any MCAP file; for our
    per-tick channels :func:`iter_ticks` is about three times faster)."""
    from mcap.reader import make_reader

    with path.open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages(topics=topics):
            try:
                yield channel.topic, json.loads(message.data)
            except RecursionError:
                raise LogError(f"{path}: a {channel.topic} message nests deeper than JSON is read") from None


class LogError(RemoteError):
    """A file that is not a log this stack wrote, or is damaged: what is wrong, where."""


_MAGIC = b"\x89MCAP0\r\n"
_OP_FOOTER, _OP_CHANNEL, _OP_MESSAGE, _OP_CHUNK, _OP_INDEX, _OP_DATA_END = 0x02, 0x04, 0x05, 0x06, 0x07, 0x0F
_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, CRC, compression's length
MAX_CHUNK_BYTES = 8 << 20  # a chunk's records, uncompressed (the writer's are about 1 MiB)
MAX_RECORD_BYTES = MAX_CHUNK_BYTES + (1 << 20)  # any record in the data section
MAX_MESSAGE_BYTES = 1 << 20  # a summary or session message (a few kB)
MAX_TICK_MESSAGE_BYTES = 16 << 10  # a per-tick message (about 3 kB at teleop.limits.MAX_DOF)
MAX_JSON_DEPTH = 32  # levels of nesting in a summary or session message (this stack writes about 5)
#: A per-tick number beyond this (a petabyte, eleven days in ns, an energy no arm holds) is damage:
#: squared or summed it would overflow to inf in the report's figures.
MAX_TICK_VALUE = 1e15


class _Walk:
    """The records of an MCAP file's data section, each length bounded before it is read.

    A record that runs past the end of the file is where a writer was killed (foxglove's writer
    writes a chunk's length when the chunk is finished): the walk stops there and sets
    ``truncated``, so every chunk written before stays readable.  A file without the footer
    (the writer never finished) is read the same way."""

    def __init__(self, f: BinaryIO, path: Path) -> None:
        self.f, self.path = f, path
        self.size = os.fstat(f.fileno()).st_size
        self.truncated = False
        self.channels: dict[int, str] = {}

    def records(self, index: bool = False) -> Iterator[tuple[int, bytes]]:
        """Chunks and messages outside chunks (and, with ``index``, message index records)."""
        f = self.f
        if self.size == 0:
            raise LogError("empty: its writer wrote nothing (killed before the session started?)")
        if f.read(8) != _MAGIC:
            raise LogError("not a readable MCAP file (InvalidMagic: it does not start with the MCAP magic)")
        pos = 8
        while True:
            hdr = f.read(9)
            if len(hdr) < 9:  # the end, without a footer: the writer did not finish the file
                self.truncated = True
                return
            op = hdr[0]
            (n,) = _U64.unpack_from(hdr, 1)
            if op in (_OP_FOOTER, _OP_DATA_END):
                return
            if pos + 9 + n > self.size:  # unfinished: the writer was killed while writing it
                self.truncated = True
                return
            if n > MAX_RECORD_BYTES:
                raise LogError(f"a record of {n} bytes at offset {pos} (at most {MAX_RECORD_BYTES})")
            if op in (_OP_CHUNK, _OP_CHANNEL, _OP_MESSAGE) or (index and op == _OP_INDEX):
                body = f.read(n)
                if op == _OP_CHANNEL:
                    self._channel(body)
                else:
                    yield op, body
            else:
                f.seek(n, os.SEEK_CUR)
            pos += 9 + n

    def _channel(self, body: bytes) -> None:
        (cid,) = _U16.unpack_from(body, 0)
        (n,) = _U32.unpack_from(body, 4)
        if 8 + n > len(body):
            raise LogError("a channel record longer than itself")
        self.channels[cid] = body[8 : 8 + n].decode()

    def chunk_records(self, body: bytes) -> bytes:
        """A chunk's records, decompressed to at most :data:`MAX_CHUNK_BYTES` (checked before)."""
        _, _, size, _, clen = _CHUNK_HEAD.unpack_from(body, 0)
        off = _CHUNK_HEAD.size
        compression = body[off : off + clen].decode()
        (rlen,) = _U64.unpack_from(body, off + clen)
        start = off + clen + 8
        if start + rlen > len(body):
            raise LogError("a chunk longer than its record")
        if size > MAX_CHUNK_BYTES:
            raise LogError(f"a chunk of {size} bytes uncompressed (at most {MAX_CHUNK_BYTES})")
        data = body[start : start + rlen]
        if compression == "zstd":
            import zstandard

            # A stream read of at most size + 1 bytes: a frame's own size field is not trusted.
            with zstandard.ZstdDecompressor().stream_reader(data) as r:
                out = r.read(size + 1)
                while len(out) <= size and (more := r.read(size + 1 - len(out))):
                    out += more
            data = out
        elif compression != "":
            raise LogError(f"chunks compressed with {compression!r} (this stack writes zstd)")
        if len(data) != size:
            raise LogError(f"a chunk of {len(data)} bytes that says {size}")
        return data

    def payloads(self) -> Iterator[dict[str, list[bytes]]]:
        """Per MCAP chunk in file order: its message payloads by topic (a message outside any
        chunk comes alone)."""
        for op, body in self.records():
            if op == _OP_CHUNK:
                yield _chunk_payloads(self.chunk_records(body), self.channels)
            elif op == _OP_MESSAGE:
                (cid,) = _U16.unpack_from(body, 0)
                if cid in self.channels:
                    yield {self.channels[cid]: [body[22:]]}


@contextlib.contextmanager
def _walk(path: Path) -> Iterator[_Walk]:
    """``path`` open for a walk (a regular file only: never a FIFO or a device); any damage met in
    the ``with`` block becomes one :class:`LogError` naming the file."""
    from zstandard import ZstdError

    try:
        st = os.stat(path)
        if not stat.S_ISREG(st.st_mode):
            raise LogError("not a regular file (a log is one)")
        with open(path, "rb", opener=_nonblocking) as f:
            _trusted(os.fstat(f.fileno()), path)
            yield _Walk(f, path)
    except UntrustedLog as e:
        raise UntrustedLog(f"{path}: {e}") from None
    except LogError as e:
        raise LogError(f"{path}: {e}") from None
    except (ZstdError, struct.error, UnicodeDecodeError) as e:  # damaged
        raise LogError(f"{path}: not a readable MCAP file ({type(e).__name__}: {e})") from None
    except OSError as e:
        raise LogError(f"{path}: {e.strerror or e}") from None


class UntrustedLog(LogError):
    """A log that another user could have planted: owned by someone else than this user or root,
    in a folder others can write (sticky or not)."""


def _trusted(st: os.stat_result, path: Path) -> None:
    """:class:`UntrustedLog` for a file (its ``fstat``: the file opened, not a name swapped since)
    owned by another user than this one or root in a folder others can write.

    Why: a sticky folder (as /tmp) stops others from replacing our files, not from adding theirs:
    a newer ``operator-SID.mcap`` of another user's, for the same session, was taken as the
    session's log (and its figures: backward violations 0 -> 1785, measured)."""
    me = os.geteuid()
    if st.st_uid in (0, me):
        return
    folder = os.stat(path.parent)
    if folder.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        raise UntrustedLog(
            f"owned by uid {st.st_uid}, not by this user ({me}) or root, in a folder others can "
            "write: not used (another user could have planted it)"
        )


def _nonblocking(path: str, flags: int) -> int:
    return os.open(path, flags | os.O_NONBLOCK | os.O_NOFOLLOW)


def _finished(path: Path) -> bool:
    """Whether the MCAP file ends with the format's closing magic (its writer finished it)."""
    with _walk(path) as walk:
        f = walk.f
        if walk.size < 2 * len(_MAGIC):
            return False
        f.seek(walk.size - len(_MAGIC))
        return f.read(len(_MAGIC)) == _MAGIC


def _role(path: Path) -> str:
    return path.stem.split("-", 1)[0]


def _depth(m: Any) -> int:
    """How deeply ``m`` (parsed JSON) nests, walked without recursion; it stops past the bound."""
    deepest, todo = 0, [(m, 1)]
    while todo:
        x, d = todo.pop()
        if isinstance(x, dict | list):
            deepest = max(deepest, d)
            if d > MAX_JSON_DEPTH:
                break
            todo.extend((v, d + 1) for v in (x.values() if isinstance(x, dict) else x))
    return deepest


def _one(topic: str, payloads: list[bytes]) -> dict[str, Any]:
    if len(payloads[0]) > MAX_MESSAGE_BYTES:
        raise LogError(f"{topic}: a message of {len(payloads[0])} bytes (at most {MAX_MESSAGE_BYTES})")
    try:
        m = json.loads(payloads[0])
    except RecursionError:  # a C-level recursion limit, not damage the parser reports itself
        raise LogError(f"{topic}: JSON nested deeper than {MAX_JSON_DEPTH} levels") from None
    except ValueError as e:
        raise LogError(f"{topic} is not JSON ({e})") from None
    if _depth(m) > MAX_JSON_DEPTH:  # the report and report.json walk it recursively
        raise LogError(f"{topic}: JSON nested deeper than {MAX_JSON_DEPTH} levels")
    if not isinstance(m, dict):
        raise LogError(f"{topic} is not a JSON object")
    return m


def read_summary(path: Path) -> dict[str, Any]:
    """The ``/ROLE/summary`` message (empty if the process did not finish its log: killed).  It is
    logged last, so the walk decompresses only the chunks that may hold it and its channel: the
    last two, and all of them only if those do not have it.  Damage is :class:`LogError`.

    Why two: the writer declares a channel (its Channel record) in the chunk it is filling when the
    channel's first message comes, and only then closes that chunk if it is over its size and puts
    the message in the next one (``mcap``'s ``Writer::write``), so the summary's channel can sit one
    chunk before the summary.  Reading the last chunk alone missed it there, and a report then said
    the summary was missing (once in about a hundred sessions).  A file whose writer did not finish
    it (killed) and whose last two chunks do not declare the channel has no summary: read as is,
    without decompressing the rest."""
    topic = f"/{_role(path)}/summary"
    with _walk(path) as walk:
        tail: list[tuple[bytes, dict[int, bytes]]] = []  # the last two chunks, their message indexes
        for op, body in walk.records(index=True):
            if op == _OP_INDEX:
                if tail:
                    tail[-1][1][_U16.unpack_from(body, 0)[0]] = body
            elif op == _OP_CHUNK:
                tail = [*tail[-1:], (body, {})]
            elif op == _OP_MESSAGE and walk.channels.get(_U16.unpack_from(body, 0)[0]) == topic:
                return _one(topic, [body[22:]])
        # In file order, so that a channel the earlier one declares names the later one's messages.
        got = [_chunk_lines(walk, c, index, {topic}, MAX_MESSAGE_BYTES).get(topic) for c, index in tail]
        for lines in reversed(got):
            if lines and (last := lines.rstrip().rsplit(b"\n", 1)[-1].strip()):
                return _one(topic, [last])
        if walk.truncated and topic not in walk.channels.values():
            return {}
    found: list[bytes] = []
    with _walk(path) as walk:  # declared, or a finished file: in an earlier chunk, if anywhere
        for chunk in walk.payloads():
            if msgs := chunk.get(topic):
                found = msgs[-1:]  # the last one: the summary is logged last
    return _one(topic, found) if found else {}


def read_session(path: Path) -> dict[str, Any]:
    """The ``/ROLE/session`` message: the parameters of a log whose process was killed (it has no
    summary).  It is logged first: a chunk or two are read.  Empty: the file holds none (another
    role's log, or not ours)."""
    topic = f"/{_role(path)}/session"
    with _walk(path) as walk:
        for chunk in walk.payloads():
            if got := chunk.get(topic):
                return _one(topic, got)
    return {}


#: Per-tick topics: (message field, record name, kind): "vec" per DoF, "int" or "num" a scalar.
_FIELDS: dict[str, tuple[tuple[str, str, str], ...]] = {
    "signals": (("t", "play_time_s", "num"), ("v", "v", "vec"), ("f", "f", "vec")),
    "waves": (("wave_out", "wave_out", "vec"), ("wave_in", "wave_in", "vec")),
    "energy": tuple((n, s, "int" if s in INT_FIELDS else "num") for n, s in ENERGY_FIELDS.items()),
    "wire": tuple((n, s, "int" if s in INT_FIELDS else "num") for n, s in WIRE_FIELDS.items()),
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
        if body + length > end:
            raise LogError(f"a record inside a chunk runs past the chunk ({length} bytes)")
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


def _columns(topic: str, payloads: list[bytes]) -> dict[str, npt.NDArray[Any]]:
    """One topic's messages as columns: ``k`` and the record's names (JSON null: NaN); a message
    that is not the documented schema raises :class:`LogError`."""
    if (big := max(map(len, payloads))) > MAX_TICK_MESSAGE_BYTES:
        raise LogError(f"a /ROLE/{topic} message of {big} bytes (at most {MAX_TICK_MESSAGE_BYTES})")
    try:
        ms = json.loads(b"[" + b",".join(payloads) + b"]")  # one parse, not one per message
        cols: dict[str, npt.NDArray[Any]] = {"k": np.array([m["k"] for m in ms], dtype=np.int64)}
        for field, name, kind in _FIELDS[topic]:
            cols[name] = np.array([m.get(field) for m in ms], dtype=np.float64)
            if cols[name].ndim != (2 if kind == "vec" else 1):
                raise ValueError(f"{field} is not a {'list' if kind == 'vec' else 'number'} in every message")
            if kind == "vec" and cols[name].shape[1] > MAX_DOF:
                raise ValueError(f"{field} has {cols[name].shape[1]} values (at most {MAX_DOF} DoF)")
    except RecursionError:
        raise LogError(f"a /ROLE/{topic} message nests deeper than JSON is read") from None
    except (ValueError, TypeError, KeyError, OverflowError) as e:
        raise LogError(
            f"a /ROLE/{topic} message does not follow its schema: {type(e).__name__}: {e}"
        ) from None
    for field, name, _ in _FIELDS[topic]:
        if (np.abs(cols[name]) > MAX_TICK_VALUE).any():  # NaN (null) compares False: no value
            bad = float(cols[name][np.abs(cols[name]) > MAX_TICK_VALUE].flat[0])
            raise LogError(
                f"a /ROLE/{topic} message has {field} = {bad!r} (at most {MAX_TICK_VALUE:g} in size)"
            )
    k = cols["k"]
    if k.size and (k.min() < 0 or np.any(np.diff(k) <= 0)):
        raise LogError(f"/ROLE/{topic}: tick numbers must increase from 0 (got {k[:8].tolist()}...)")
    if k.size > 1 and (jump := int(np.diff(k).max())) > MAX_GAP_TICKS:
        raise LogError(f"/ROLE/{topic}: a jump of {jump} ticks (at most {MAX_GAP_TICKS}): not a session")
    return cols


def iter_ticks(
    path: Path, topics: tuple[str, ...] = PER_TICK_TOPICS, max_tick: int | None = None
) -> Iterator[tuple[int, dict[str, npt.NDArray[Any]]]]:
    """``ROLE.mcap`` as consecutive blocks of whole-session per-tick arrays: ``(k0, arrays)`` for
    ticks ``k0, k0 + 1, ...`` from tick 0 to the last tick run, by the record's names, plus ``ran``
    (the tick was run: its ``/ROLE/signals`` message is in the log).  A tick not run is filled as
    the record fills it (no value, no bytes, no sequence number).

    Streamed: a tick is handed on once every topic's messages have passed it (the writer logs a
    chunk of ticks a topic at a time), so memory holds a few MCAP chunks, not the session.  A topic
    more than ``LAG_TICKS`` behind the signals (a log cut off mid-chunk) counts as missing those
    ticks, as does a message for a tick whose signals are not in the log.

    Bounds, checked before anything is allocated: a tick beyond ``max_tick`` (the session's own
    length, when the caller knows it), a jump over more than :data:`MAX_GAP_TICKS` ticks, or more
    than :data:`MAX_GAP_TICKS` ticks skipped in all, are :class:`LogError`; so are a per-tick
    message over :data:`MAX_TICK_MESSAGE_BYTES` and a vector over ``teleop.limits.MAX_DOF``."""
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

    skipped = 0  # ticks the signals jump over after the first (the first may come late: a rejoin)
    with _walk(path) as walk:
        for chunk in walk.payloads():
            for topic, payloads in chunk.items():
                t = names.get(topic)
                if t is None:
                    continue
                cols = _columns(t, payloads)
                first, end = int(cols["k"][0]), int(cols["k"][-1])
                if first <= last[t] or first - last[t] > MAX_GAP_TICKS:
                    raise LogError(f"{topic}: tick {first} after tick {last[t]} (ticks are logged in order)")
                if max_tick is not None and end > max_tick:
                    raise LogError(f"{topic}: tick {end} beyond the session's {max_tick} ticks")
                if t == "signals":
                    k = cols["k"]
                    skipped += int(k[-1] - k[0]) + 1 - k.size + (first - last[t] - 1 if last[t] >= 0 else 0)
                    if skipped > MAX_GAP_TICKS:
                        raise LogError(f"{topic}: more than {MAX_GAP_TICKS} ticks skipped: not a session")
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


ROLES = ("operator", "teleoperator")
MAX_LOGS = 1000  # log files of one role a folder may hold for find_pair to look at


def log_session(path: Path) -> tuple[int, dict[str, Any], dict[str, Any]]:
    """(session id, summary or {}, parameters) of a log: from its summary, or, for a process that
    was killed before it wrote one, from its ``/ROLE/session`` message.  :class:`LogError` if it
    has neither (another role's log, not ours) or the parameters are not a map with a session id."""
    role = _role(path)
    summary = read_summary(path)
    params = summary.get("params") if summary else None
    if params is None:
        params = read_session(path).get("params")
        if params is None:
            if not _finished(path):  # a log cut short, not a stranger's file: say which
                raise LogError(
                    f"{path} was cut short before its session began (its writer was killed, or the "
                    f"disk filled): no /{role}/session message, so no ticks of a session to report"
                )
            raise LogError(f"{path} has no /{role}/summary or /{role}/session message: not a {role}'s log")
    sid = params.get("session") if isinstance(params, dict) else None
    if type(sid) is not int:
        raise LogError(f"{path}: its parameters name no session id")
    return sid, summary, params


def find_pair(
    log_dir: Path,
    session: int | None = None,
    seen: dict[Path, tuple[int, dict[str, Any], dict[str, Any]]] | None = None,
) -> tuple[Path, Path, list[str]]:
    """The operator's and the teleoperator's log of one session in ``log_dir`` (``ROLE.mcap``,
    ``ROLE-*.mcap``: restarts add files, never replace one), paired by session id: ``session``, or
    else the session of the newest log that has both.  Where a role has several logs of the session
    (a restarted process that rejoined, or a planted one), :class:`LogError` names them: a report
    never picks one silently; the one exception is a rejoin, where exactly one of them was finished
    (the others' processes were killed): that one is read and the others are named in the notes.
    A log another user could have planted (:class:`UntrustedLog`) is
    ignored and named in the notes.  Returns the two paths and notes on
    what else the folder holds; :class:`LogError` when no pair is found.  ``seen``: filled with what
    :func:`log_session` gave for each log read, so a caller need not read a summary twice."""
    found: dict[int, dict[str, list[tuple[int, Path, bool]]]] = {}  # (mtime, path, finished)
    errors: dict[str, str] = {}
    ignored: list[str] = []
    for role in ROLES:
        paths = sorted({*log_dir.glob(f"{role}.mcap"), *log_dir.glob(f"{role}-*.mcap")})
        if not paths:
            errors[role] = f"{log_dir} holds no {role} log ({role}.mcap): pass the folder it wrote with --log"
        for path in paths[:MAX_LOGS]:
            try:
                st = os.lstat(path)
                if not stat.S_ISREG(st.st_mode):
                    raise LogError(f"{path}: not a regular file (a log is one)")
                sid, summary, params = log_session(path)
                if seen is not None:
                    seen[path] = (sid, summary, params)
            except UntrustedLog as e:  # flagged and ignored: the figures are the genuine logs'
                ignored.append(f"ignored {e}")
                errors.setdefault(role, str(e))
                continue
            except LogError as e:
                errors.setdefault(role, str(e))
                continue
            found.setdefault(sid, {}).setdefault(role, []).append((st.st_mtime_ns, path, bool(summary)))
    both = {s: r for s, r in found.items() if all(role in r for role in ROLES)}
    if session is not None:
        if session not in both:
            have = ", ".join(str(s) for s in sorted(both)) or "none"
            raise LogError(
                f"{log_dir} holds no pair of logs of session {session} (sessions with both: {have})"
            )
        chosen = session
    elif both:
        chosen = max(both, key=lambda s: max(t for r in both[s].values() for t, _, _ in r))
    else:
        for r in ROLES:
            if r in errors and not any(r in got for got in found.values()):
                raise LogError(errors[r])
        raise LogError(f"{log_dir}: no session has both an operator and a teleoperator log")
    notes = (
        [f"{len(both) - 1} other session(s) in the folder; chose {chosen} (--session)"]
        if len(both) > 1
        else []
    )
    pick = {}
    for role in ROLES:
        logs = sorted(both[chosen][role])
        finished = [p for _, p, done in logs if done]
        if len(logs) > 1 and len(finished) == 1:
            # A process that was killed and restarted into the same session (a rejoin): the one log
            # that was finished is the session's end; the others are named, never read silently.
            others = ", ".join(p.name for _, p, done in logs if not done)
            notes.append(
                f"{role}: read {finished[0].name}, the one log of session {chosen} that was finished; "
                f"not read: {others} (an earlier process of the session, killed)"
            )
            pick[role] = finished[0]
            continue
        if len(logs) > 1:
            names = ", ".join(p.name for _, p, _ in logs[:4]) + (", ..." if len(logs) > 4 else "")
            raise LogError(
                f"{log_dir} holds {len(logs)} {role} logs of session {chosen} ({names}): a report "
                "reads one of each role; move the others out of the folder (a restarted process's)"
            )
        pick[role] = logs[0][1]
    return pick["operator"], pick["teleoperator"], notes + ignored


MAX_STATE_VALUES = 64  # numbers in one device state sample (a Franka's: 31)


def read_states(
    path: Path, max_tick: int, blocks: list[bytes] | None = None
) -> tuple[npt.NDArray[np.int64], list[str], npt.NDArray[np.float64]]:
    """The device's state samples of a log (``/ROLE/state``, ``teleop.devices``: a device's
    ``state()`` every ``state_every`` ticks): their ticks, the names of their values (``pose.0``,
    ``q.3``, ...; the first sample's fields, in its order; the others' in any) and the values, one
    row per sample.
    Empty where the log has none (a device without a state, a log before 2026-12).

    Hostile input as everywhere here: a sample beyond ``max_tick``, out of order, with other fields
    than the first, more than :data:`MAX_STATE_VALUES` numbers, or a number over
    :data:`MAX_TICK_VALUE` is :class:`LogError`; at most one sample a tick, so ``max_tick`` bounds
    the allocation.  ``blocks``: the topic's messages already read (:func:`read_columns`' ``extra``)."""
    topic = f"/{_role(path)}/state"
    blocks = topic_lines(path, [topic])[topic] if blocks is None else blocks  # a chunk's, one a line
    got = _states_arrow(blocks, max_tick)
    ks, names, values = got if got is not None else _states_python(blocks, topic, max_tick)
    if (np.abs(values) > MAX_TICK_VALUE).any():
        raise LogError(f"{topic}: a value beyond {MAX_TICK_VALUE:g}")
    return ks, names, values


def _state_layout(m: Any, topic: str) -> list[tuple[str, int]]:
    """A state sample's fields but ``k`` and ``t`` in its order, each its width (-1: a number)."""
    layout = [(n, len(v) if isinstance(v, list) else -1) for n, v in m.items() if n not in ("k", "t")]
    if sum(max(w, 1) for _, w in layout) > MAX_STATE_VALUES:
        raise LogError(f"{topic}: more than {MAX_STATE_VALUES} values a sample")
    return layout


def _state_names(layout: list[tuple[str, int]]) -> list[str]:
    return [f"{n}.{i}" if w >= 0 else n for n, w in layout for i in range(max(w, 1))]


def _json_table(data: bytes, schema: Any, unexpected: str) -> Any:
    """Newline-delimited JSON parsed by pyarrow against ``schema`` (``unexpected``: what a field
    outside it does, pyarrow's ``unexpected_field_behavior``); its ArrowInvalid/ArrowTypeError pass."""
    import pyarrow as pa
    import pyarrow.json as pj

    return pj.read_json(
        pa.py_buffer(data),
        read_options=pj.ReadOptions(block_size=max(1 << 20, 4 * MAX_TICK_MESSAGE_BYTES)),
        parse_options=pj.ParseOptions(explicit_schema=schema, unexpected_field_behavior=unexpected),
    )


def _list_values(col: Any) -> tuple[npt.NDArray[np.int64], npt.NDArray[Any]]:
    """A list column's lengths, and its values laid end to end, through its offsets rather than
    pyarrow.compute (whose import alone was 0.04 s of an export)."""
    offsets = col.offsets.to_numpy()
    values = col.values.to_numpy(zero_copy_only=False)[int(offsets[0]) : int(offsets[-1])]
    return np.diff(offsets), values


def _states_arrow(
    blocks: list[bytes], max_tick: int
) -> tuple[npt.NDArray[np.int64], list[str], npt.NDArray[np.float64]] | None:
    """:func:`read_states` parsed by pyarrow, the first sample's layout its schema (0.01 s of a
    10 s session's export, a tenth of the Python walk); None wherever it would not give exactly
    what the walk gives, which then says what is wrong."""
    import pyarrow as pa

    data = b"".join(blocks)
    first = next((ln for ln in data.split(b"\n", 64) if ln.strip()), None)
    if first is None:
        return None
    try:
        m = json.loads(first)
        layout = _state_layout(m, "")
    except (ValueError, RecursionError, AttributeError, LogError):
        return None
    if any(w == 0 for _, w in layout):  # an empty list: the walk names its fault
        return None
    fields = [(n, pa.list_(pa.float64()) if w >= 0 else pa.float64()) for n, w in layout]
    schema = pa.schema([("k", pa.int64()), ("t", pa.float64()), *fields])
    try:
        table = _json_table(data, schema, "error")
    except (pa.ArrowInvalid, pa.ArrowTypeError):
        return None
    k = table.column("k").combine_chunks()
    ks = k.to_numpy(zero_copy_only=False)
    if k.null_count or ks.size == 0 or ks[0] < 0 or ks[-1] > max_tick or (np.diff(ks) <= 0).any():
        return None
    parts = []
    for n, w in layout:
        col = table.column(n).combine_chunks()
        if col.null_count:
            return None
        if w >= 0:
            lengths, flat = _list_values(col)
            if (lengths != w).any() or col.values.null_count:
                return None
            parts.append(flat.reshape(-1, w))
        else:
            parts.append(col.to_numpy(zero_copy_only=False).reshape(-1, 1))
    names = _state_names(layout)
    values = np.hstack(parts) if parts else np.zeros((ks.size, 0))
    return ks.astype(np.int64), names, values.astype(np.float64).reshape(ks.size, len(names))


def _states_python(
    blocks: list[bytes], topic: str, max_tick: int
) -> tuple[npt.NDArray[np.int64], list[str], npt.NDArray[np.float64]]:
    """:func:`read_states` sample by sample: every fault named."""
    ks: list[int] = []
    rows: list[list[float]] = []
    layout: list[tuple[str, int]] | None = None
    for block in blocks:
        try:
            ms = json.loads(b"[" + b",".join(ln for ln in block.split(b"\n") if ln.strip()) + b"]")
        except (ValueError, RecursionError) as e:
            raise LogError(f"a {topic} message is not JSON ({type(e).__name__})") from None
        for m in ms:
            if not isinstance(m, dict) or type(m.get("k")) is not int:
                raise LogError(f"a {topic} message has no tick number k")
            k = m["k"]
            if layout is None:
                layout = _state_layout(m, topic)
            # The first sample's fields, in any order (a JSON object's is not part of its meaning).
            widths = {n: len(v) if isinstance(v, list) else -1 for n, v in m.items() if n not in ("k", "t")}
            if widths != dict(layout):
                raise LogError(f"{topic}: a sample at tick {k} has other fields than the first")
            if not 0 <= k <= max_tick or (ks and k <= ks[-1]):
                raise LogError(f"{topic}: tick {k} out of order or beyond the session's {max_tick}")
            row: list[float] = []
            for n, _ in layout:
                v = m[n]
                row.extend(v if isinstance(v, list) else [v])
            ks.append(k)
            rows.append(row)
    names = _state_names(layout or [])
    try:
        values = np.array(rows, dtype=np.float64).reshape(len(rows), len(names))
    except (ValueError, TypeError) as e:
        raise LogError(f"{topic}: a value that is not a number ({e})") from None
    return np.array(ks, dtype=np.int64), names, values


def _index_payloads(
    data: bytes, index: dict[int, bytes], channels: dict[int, str], max_bytes: int, wanted: set[str]
) -> dict[str, bytes] | None:
    """A decompressed chunk's messages by topic, one message a line, found through the chunk's
    message indexes (``index``: channel id -> its MessageIndex records) with numpy instead of a
    Python step per record: about 20 times faster than :func:`_chunk_payloads` (what a 60 s
    session's export needs, ``teleop.offline.lerobot``).

    Nothing in the index is trusted: every offset must start a message record of its channel
    inside the chunk, the records must not overlap, and what lies between them (channel and schema
    records) is walked record by record; a message the index leaves out, or any mismatch, returns
    None, and the caller walks the chunk as :func:`_chunk_payloads` does."""
    n = len(data)
    offs_parts, ids_parts = [], []
    for cid, body in index.items():
        (length,) = _U32.unpack_from(body, 2)
        if 6 + length > len(body) or length % 16:
            return None
        pairs = np.frombuffer(body, dtype="<u8", count=length // 8, offset=6).reshape(-1, 2)
        offs_parts.append(pairs[:, 1])
        ids_parts.append(np.full(pairs.shape[0], cid, dtype=np.int64))
    if not offs_parts:
        return None
    offs_u = np.concatenate(offs_parts)
    if offs_u.size == 0 or int(offs_u.max()) > n - 31:
        return None
    offs = offs_u.astype(np.int64)
    order = np.argsort(offs, kind="stable")
    offs, ids = offs[order], np.concatenate(ids_parts)[order]
    buf = np.frombuffer(data, dtype=np.uint8)
    if not (buf[offs] == _OP_MESSAGE).all():
        return None
    lens = buf[offs[:, None] + np.arange(1, 9)].copy().view("<u8").ravel()
    if int(lens.max()) > n or int(lens.min()) < 22:
        return None
    if int(lens.max()) - 22 > max_bytes:
        raise LogError(f"a message of {int(lens.max()) - 22} bytes (at most {max_bytes} on these topics)")
    ends = offs + 9 + lens.astype(np.int64)
    if int(ends[-1]) > n or (ends[:-1] > offs[1:]).any():
        return None
    cids = buf[offs[:, None] + np.array([9, 10])].copy().view("<u2").ravel()
    if not (cids == ids).all():
        return None
    # The gaps: channel and schema records (the chunk's first message's channel is declared there).
    gap_starts = np.concatenate([[0], ends])
    gap_ends = np.concatenate([offs, [n]])
    for a, b in zip(
        gap_starts[gap_starts < gap_ends].tolist(), gap_ends[gap_starts < gap_ends].tolist(), strict=True
    ):
        got = _chunk_payloads(data[a:b], channels)
        if got:  # a message the index did not list
            return None
    # Each wanted record's header (31 bytes) becomes blanks and a newline: every run of consecutive
    # messages of a topic is then newline-delimited JSON as it lies, taken with one slice.
    # A channel not declared yet is skipped, as the record walk skips it (read_summary reads the
    # last chunks alone: the others' channels were declared before them).
    # (bincount, not np.unique or np.isin: their first call imports numpy.ma, 0.02 s of an export)
    want_ids = [cid for cid in np.flatnonzero(np.bincount(ids)).tolist() if channels.get(cid) in wanted]
    mine = np.zeros(1 << 16, dtype=bool)
    mine[want_ids] = True
    mine = mine[ids]
    lined = buf.copy()
    lined[(offs[mine][:, None] + np.arange(30)).ravel()] = 0x20
    lined[offs[mine] + 30] = 0x0A
    out: dict[str, bytes] = {}
    for cid in want_ids:
        topic = channels[cid]
        sel = ids == cid
        # Runs: a message that does not directly follow one of its topic starts one.
        follows = np.concatenate([[False], sel[:-1] & sel[1:] & (ends[:-1] == offs[1:])])
        first = np.flatnonzero(sel & ~follows)
        last = np.flatnonzero(sel & ~np.concatenate([follows[1:], [False]]))
        spans = zip((offs[first] + 30).tolist(), ends[last].tolist(), strict=True)
        out[topic] = b"".join(lined[a:b].tobytes() for a, b in spans) + b"\n"
    return out


def _chunk_lines(
    walk: _Walk, chunk: bytes, index: dict[int, bytes], wanted: set[str], max_bytes: int
) -> dict[str, bytes]:
    """A chunk's messages of the ``wanted`` topics, one a line (JSON lines), through its message
    indexes (:func:`_index_payloads`), record by record where they are missing or do not hold;
    the channels it declares are learnt into ``walk``."""
    data = walk.chunk_records(chunk)
    known = dict(walk.channels)
    got = _index_payloads(data, index, known, max_bytes, wanted) if index else None
    if got is not None:
        walk.channels.update(known)
        return got
    slow = _chunk_payloads(data, walk.channels)
    if any(len(m) > max_bytes for t in wanted for m in slow.get(t, ())):
        raise LogError(f"a message of over {max_bytes} bytes on {', '.join(sorted(wanted))}")
    return {t: b"\n".join(ps) + b"\n" for t, ps in slow.items() if t in wanted}


def topic_lines(
    path: Path, topics: list[str], max_bytes: int = MAX_TICK_MESSAGE_BYTES
) -> dict[str, list[bytes]]:
    """The messages of ``topics`` (full names) of a log, as blocks of newline-separated JSON, in
    file order: each chunk's through its message indexes (:func:`_index_payloads`), a chunk
    without them (the last of a writer killed) record by record."""
    wanted = set(topics)
    out: dict[str, list[bytes]] = {t: [] for t in topics}
    with _walk(path) as walk:
        chunk: bytes | None = None
        index: dict[int, bytes] = {}

        def flush() -> None:
            if chunk is None:
                return
            for t, lines in _chunk_lines(walk, chunk, index, wanted, max_bytes).items():
                if t in wanted and lines:
                    out[t].append(lines)

        for op, body in walk.records(index=True):
            if op == _OP_INDEX:
                (cid,) = _U16.unpack_from(body, 0)
                index[cid] = body
                continue
            flush()
            chunk, index = (body, {}) if op == _OP_CHUNK else (None, {})
            if op == _OP_MESSAGE:
                (cid,) = _U16.unpack_from(body, 0)
                if walk.channels.get(cid) in wanted:
                    if len(body) - 22 > max_bytes:
                        raise LogError(f"a message of {len(body) - 22} bytes (at most {max_bytes})")
                    out[walk.channels[cid]].append(body[22:] + b"\n")
        flush()
    return out


def _arrow_column(col: Any, topic: str, f: str, kind: str, dof: int) -> npt.NDArray[Any]:
    """One field of a topic's messages as float64, held to the DoF (``dof``: 0 until the first vector
    field says it) and to :data:`MAX_TICK_VALUE`."""
    if kind == "vec":
        lengths, flat = _list_values(col)
        width = dof or (int(lengths[0]) if lengths.size else 0)
        if col.null_count or (lengths != width).any():
            raise LogError(f"{topic}: {f} must have {width} values (DoF) in every message")
        if width > MAX_DOF:
            raise LogError(f"{topic}: {f} has {width} values (at most {MAX_DOF} DoF)")
        x: npt.NDArray[Any] = flat.astype(np.float64).reshape(-1, width)
    else:
        x = col.to_numpy(zero_copy_only=False).astype(np.float64)
    if (np.abs(x) > MAX_TICK_VALUE).any():
        raise LogError(f"a {topic} message has {f} beyond {MAX_TICK_VALUE:g} in size")
    return x


def read_columns(
    path: Path,
    topics: tuple[str, ...],
    max_tick: int,
    extra: dict[str, list[bytes]] | None = None,
    names: tuple[str, ...] | None = None,
) -> dict[str, npt.NDArray[Any]]:
    """The per-tick record of ``topics`` as :func:`read_log` gives it (whole-session arrays from
    tick 0 by the record's names, ``ran``; a tick not run or a row missing filled as
    :func:`iter_ticks` fills them), read at C speed: messages through the chunks' indexes
    (:func:`topic_lines`) and parsed by pyarrow's JSON reader, where :func:`iter_ticks` steps
    through every record in Python.  For a whole session held at once (``teleop export``); every
    bound of :func:`iter_ticks` holds (ticks up to ``max_tick``, :data:`MAX_TICK_VALUE`, DoF).
    ``names``: only these of the record's names (the rest of a message is skipped unconverted:
    a sixth less time for an export, measured)."""
    import pyarrow as pa

    role = _role(path)
    wanted = ("signals", *(t for t in topics if t != "signals"))
    lines = topic_lines(path, [f"/{role}/{t}" for t in (*wanted, *(extra or {}))])
    if extra is not None:
        for t in extra:
            extra[t] = lines[f"/{role}/{t}"]
    cols: dict[str, dict[str, npt.NDArray[Any]]] = {}
    dof = 0
    fields = {t: tuple(x for x in _FIELDS[t] if names is None or x[1] in names) for t in wanted}
    for t in wanted:
        kinds = {"vec": pa.list_(pa.float64()), "int": pa.float64(), "num": pa.float64()}
        schema = pa.schema([("k", pa.int64()), *((f, kinds[kind]) for f, _, kind in fields[t])])
        data = b"".join(lines[f"/{role}/{t}"])
        c: dict[str, npt.NDArray[Any]] = {}
        if data:
            try:
                table = _json_table(data, schema, "ignore")
            except (pa.ArrowInvalid, pa.ArrowTypeError) as e:
                raise LogError(f"a /ROLE/{t} message does not follow its schema: {str(e)[:200]}") from None
            k = table.column("k")
            if k.null_count:
                raise LogError(f"a /ROLE/{t} message has no tick number k")
            c["k"] = k.to_numpy()
            for f, name, kind in fields[t]:
                c[name] = _arrow_column(table.column(f).combine_chunks(), f"/ROLE/{t}", f, kind, dof)
                dof = c[name].shape[1] if kind == "vec" else dof
            ks = c["k"]
            if ks.min() < 0 or (np.diff(ks) <= 0).any():
                raise LogError(f"/ROLE/{t}: tick numbers must increase from 0 (ticks are logged in order)")
            if int(ks[-1]) > max_tick:
                raise LogError(f"/ROLE/{t}: tick {int(ks[-1])} beyond the session's {max_tick} ticks")
        cols[t] = c
    ks = cols["signals"].get("k", np.zeros(0, dtype=np.int64))
    n = int(ks[-1]) + 1 if ks.size else 0
    ran = np.zeros(n, dtype=bool)
    ran[ks] = True
    out: dict[str, npt.NDArray[Any]] = {"ran": ran}
    for t in wanted:
        c = cols[t]
        if c:
            at = np.minimum(np.searchsorted(ks, c["k"]), max(ks.size - 1, 0))
            hit = (ks[at] == c["k"]) if ks.size else np.zeros(c["k"].size, dtype=bool)
            rows = c["k"][hit]
        for _, name, kind in fields[t]:
            full = np.full((n, dof) if kind == "vec" else n, math.nan)
            if kind != "vec":
                full[~ran] = fill_value(name)
            if c:
                full[rows] = c[name][hit]
            out[name] = np.nan_to_num(full, nan=fill_value(name)).astype(np.int64) if kind == "int" else full
    return out


def checked_params(path: Path, p: Any) -> SessionParams:
    """A log's session parameters held to what a peer's hello is held to (``SessionParams.from_msg``:
    every type, and the ranges of ``teleop.limits``), before any of them sizes an allocation or a
    loop: an edited ``dof``, ``duration`` or ``dt`` is one :class:`LogError`.  A ``trace FILE`` spec
    is kept as text; nothing here (or in the report) opens the file it names."""
    if not isinstance(p, dict):
        raise LogError(f"{path}: its session parameters are not a map")
    m = {k: v for k, v in p.items() if k != "full_scale"}
    m["range"] = p.get("full_scale")
    own = [v for k in ("netem_forward", "netem_backward") if isinstance(v := p.get(k), str)]
    try:
        return SessionParams.from_msg(m, local_netem=own)
    except ProtocolError as e:
        raise LogError(f"{path}: its session parameters: {e}") from None
