"""Streamed logs in MCAP, and the live view: the real-time runner's sink for the port's record.

Why MCAP: it is what the field records into and replays (ROS 2 bags, Foxglove, PlotJuggler), it is
chunked and indexed, so a file written as a session runs is readable at any length, and a crash loses
at most the chunk in flight.  Why foxglove-sdk's writer (PyPI ``foxglove-sdk``): one library writes
the file and serves the same channels live over the Foxglove WebSocket protocol (``--live-view``);
its Rust core compresses (zstd) and writes.  Tests read files with the reference ``mcap``
library; ``teleop report`` streams them with :func:`iter_ticks` (the ``mcap`` library's record
reader and decompression, its own split of each chunk's records: three times faster).

**Who pays.** The port hands a sealed chunk (1000 ticks) to :meth:`McapLog.write`, which only puts
it on a bounded queue (an item that finds the queue full is dropped; dropped chunks are counted).
A sender thread pickles each item into the stdin of a writer *process* (``python -m
transport.mcaplog``), which turns chunks into messages, compresses and writes them, and serves the
live view.  A process, not a thread: measured with a writer thread in the same process
(bench/soak.py, first version), the loop's p99 period error was about 2x that without the log, since
encoding 5000 messages a second, and foxglove's writer, hold the interpreter lock the loop needs
when it wakes.  The writer runs under ``SCHED_IDLE`` (niced where that is refused): measured
with bench/soak.py on a quiet 2-core host, a writer at nice 10 still held a core when a loop woke
(the scheduler lets a running task finish its slice), which put the loops' p99 period error at
120-230 us against 0.3 us without a log; under ``SCHED_IDLE`` any waking task preempts it at once,
and the p99 stayed at 0.3-4 us.  The writer ignores SIGINT/SIGTERM (Ctrl-C reaches the whole
process group) and finishes the file when told, or when its stdin closes because the process it
serves died.

**Channels** (``ROLE`` is ``operator`` or ``teleoperator``; JSON messages with a JSON schema each,
log time = the session's wall-clock start + the tick's time on the session clock):

==========================  =========  ==================================================================
topic                       rate       fields
==========================  =========  ==================================================================
``/ROLE/signals``           each tick  ``k``, ``t`` (s, session clock), ``v``, ``f`` (per DoF)
``/ROLE/waves``             each tick  ``k``, ``t``, ``wave_out``, ``wave_in`` (per DoF, sqrt(W))
``/ROLE/energy``            each tick  ``k``, ``t``, ``sent``, ``played``, ``margin_observed`` (the
                                       watchdog's margin), ``played_epoch``, ``peer_epoch`` (J)
``/ROLE/wire``              each tick  ``k``, ``t``, ``send_time``, ``tx_seq``, ``rx_seq``, bytes:
                                       ``produced_payload``, ``produced_packet``, ``tx_wire``,
                                       ``tx_payload``, ``tx_baseline_wire``, ``tx_baseline_payload``,
                                       ``rx_wire``, ``rx_payload``
``/ROLE/loop``              each tick  ``k``, ``t``, ``lateness_ns`` (tick start minus its deadline)
``/ROLE/link``              1 Hz       ``t``, ``link`` (the incoming link so far: received,
                                       ``loss_so_far``, ``delay_ms_mean``, duplicates,
                                       reordered), ``sent`` and
                                       ``received`` (counters and compression so far),
                                       ``watchdog`` (violations, controller, dissipated energy)
``/ROLE/events``            as they    ``t``, ``event`` (``session_start``, ``link_lost``,
                            happen     ``link_restored``, ``peer_restarted``, ``auth_rejected``,
                                       ``replayed``, ``overrun``, ``session_end``), ``detail``
``/ROLE/session``           once       the session's parameters, role, pid, start time; ``traces``:
                                       SHA-256 and size of a ``trace FILE`` link's file
``/ROLE/summary``           once       the process's summary (what ``ROLE.json`` holds)
==========================  =========  ==================================================================

The live view serves the same topics, per-tick ones decimated to every ``live_every``-th tick (50 Hz
by default), sent from the loop through the same queue five at a time (100 ms), not a chunk later.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import pickle
import queue
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from teleop.files import create_new, open_reserved, trace_digests
from teleop.logfile import (
    ENERGY_FIELDS,
    PER_TICK_TOPICS,
    TOPICS,
    WIRE_FIELDS,
    LogError,
    iter_messages,
    iter_ticks,
    read_log,
    read_summary,
)
from teleop.port import Chunk

__all__ = [
    "PER_TICK_TOPICS",
    "TOPICS",
    "LogError",
    "McapLog",
    "iter_messages",
    "iter_ticks",
    "read_log",
    "read_summary",
]

NICE = 10  # the writer process's niceness (on top of SCHED_IDLE, or instead where refused)
LIVE_BATCH = 5  # live-view ticks per queued item
QUEUE_ITEMS = 256  # items (chunks are 1 s each at 1 kHz, live batches 10 a second) in flight
SLOW_CLOSE_S = 2.0  # a close still waiting this long for an idle writer says why, once

_NUM = {"type": "number"}
_INT = {"type": "integer"}
_VEC = {"type": "array", "items": {"type": "number"}}


def _schema(title: str, **props: Any) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": props}


SCHEMAS: dict[str, dict[str, Any]] = {
    "signals": _schema("teleop.Signals", k=_INT, t=_NUM, v=_VEC, f=_VEC),
    "waves": _schema("teleop.Waves", k=_INT, t=_NUM, wave_out=_VEC, wave_in=_VEC),
    "energy": _schema(
        "teleop.Energy",
        k=_INT,
        t=_NUM,
        sent=_NUM,
        played=_NUM,
        margin_observed=_NUM,
        played_epoch=_NUM,
        peer_epoch=_INT,
    ),
    "wire": _schema(
        "teleop.Wire",
        k=_INT,
        t=_NUM,
        send_time=_NUM,
        tx_seq=_INT,
        rx_seq=_INT,
        produced_payload=_NUM,
        produced_packet=_NUM,
        tx_wire=_NUM,
        tx_payload=_NUM,
        tx_baseline_wire=_NUM,
        tx_baseline_payload=_NUM,
        rx_wire=_NUM,
        rx_payload=_NUM,
    ),
    "loop": _schema("teleop.Loop", k=_INT, t=_NUM, lateness_ns=_INT),
    "link": _schema(
        "teleop.Link",
        t=_NUM,
        link={"type": "object"},
        sent={"type": "object"},
        received={"type": "object"},
        watchdog={"type": "object"},
    ),
    "events": _schema("teleop.Event", t=_NUM, event={"type": "string"}, detail={"type": "string"}),
    "session": _schema("teleop.Session", params={"type": "object"}),
    "summary": _schema("teleop.Summary"),
}


def _num(x: Any) -> Any:
    """JSON has no NaN: a missing value (a sample not yet sent) is null."""
    return None if isinstance(x, float) and math.isnan(x) else x


def tick_messages(a: dict[str, npt.NDArray[Any]], r: int, k: int) -> dict[str, dict[str, Any]]:
    """The per-tick messages of row ``r`` (tick ``k``) of a chunk's arrays, by topic."""
    t = float(a["play_time_s"][r])
    return {
        "signals": {"k": k, "t": t, "v": a["v"][r].tolist(), "f": a["f"][r].tolist()},
        "waves": {"k": k, "t": t, "wave_out": a["wave_out"][r].tolist(), "wave_in": a["wave_in"][r].tolist()},
        "energy": {"k": k, "t": t, **{n: _num(a[s][r].item()) for n, s in ENERGY_FIELDS.items()}},
        "wire": {"k": k, "t": t, **{n: _num(a[s][r].item()) for n, s in WIRE_FIELDS.items()}},
        "loop": {"k": k, "t": t, "lateness_ns": int(a["lateness_ns"][r])},
    }


def _template(fields: dict[str, str]) -> str:
    """A ``%`` template of a flat per-tick message: ``k``, ``t``, then ``fields`` (ints as ints)."""
    parts = ['"k":%d', '"t":%r']
    for name, src in fields.items():
        whole = src.endswith("seq") or src == "peer_epoch"
        parts.append(f'"{name}":%{"d" if whole else "r"}')
    return "{" + ",".join(parts) + "}"


class _GuardedFile:
    """The log file as foxglove's writer sees it.  The first failed write (a full disk, a quota)
    is kept in ``error`` and said in one line, and every later write is dropped: foxglove itself
    prints a line for every message it cannot log (18 590 lines for a 5 s session, measured with
    RLIMIT_FSIZE), and the session must go on.  What was written before stays readable: the
    chunk being written is cut off, which ``teleop.logfile`` reads as the file's end."""

    def __init__(self, fd: int, role: str) -> None:
        self._f = os.fdopen(fd, "wb", buffering=0)  # unbuffered: a kill -9 loses no written chunk
        self.role = role
        self.error: str | None = None
        # The position foxglove expects (it checks it): real until a write fails, then virtual.
        self._pos = self._end = 0

    def write(self, data: bytes | bytearray) -> int:
        if self.error is None:
            try:
                view, done = memoryview(data), 0
                while done < len(view):
                    done += self._f.write(view[done:]) or 0
            except OSError as e:
                self.error = f"writing the log failed: {e.strerror or e}; later chunks are not in the log"
                print(f"teleop {self.role}: error: {self.error}", file=sys.stderr, flush=True)
        self._pos += len(data)
        self._end = max(self._end, self._pos)
        return len(data)

    def seek(self, offset: int, whence: int = 0) -> int:
        base = {os.SEEK_SET: 0, os.SEEK_CUR: self._pos, os.SEEK_END: self._end}[whence]
        self._pos = base + offset
        if self.error is None:
            self._f.seek(self._pos)
        return self._pos

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass  # unbuffered

    def close(self) -> None:
        self._f.close()


class _Writer:
    """The writer process's side: foxglove contexts, channels, the MCAP file and the live server."""

    def __init__(
        self,
        path: str | None,
        role: str,
        wall0_ns: int,
        live_port: int | None,
        live_host: str,
        file_id: tuple[int, int] | None = None,
    ) -> None:
        """``file_id``: (device, inode) of the empty file the parent created at ``path``
        (``transport.logdir.reserve``): only that file is opened, never a name swapped in since;
        without it the file is created here, exclusively."""
        import foxglove
        from foxglove.mcap import MCAPCompression, MCAPWriteOptions

        self.role = role
        self.wall0_ns = wall0_ns
        self.messages = 0
        self._ctx = foxglove.Context() if path is not None else None
        self._live_ctx = foxglove.Context() if live_port is not None else None
        self._file = None
        self._fh: _GuardedFile | None = None
        if self._ctx is not None and path is not None:
            opts = MCAPWriteOptions(compression=MCAPCompression.Zstd)
            fd = open_reserved(Path(path), *file_id) if file_id is not None else create_new(Path(path))
            self._fh = _GuardedFile(fd, role)
            self._file = foxglove.open_mcap(self._fh, context=self._ctx, writer_options=opts)
        self.server = None
        if self._live_ctx is not None:
            self.server = foxglove.start_server(
                name=f"teleop {role}", host=live_host, port=live_port, context=self._live_ctx
            )
        self._ch = {n: self._channel(self._ctx, n) for n in TOPICS} if self._ctx else {}
        self._live = {n: self._channel(self._live_ctx, n) for n in TOPICS} if self._live_ctx else {}

    def _channel(self, ctx: Any, name: str) -> Any:
        import foxglove

        return foxglove.Channel(f"/{self.role}/{name}", schema=SCHEMAS[name], context=ctx)

    @property
    def live_port(self) -> int | None:
        return None if self.server is None else int(self.server.port)

    def _log(self, chans: dict[str, Any], name: str, t: float, msg: dict[str, Any]) -> None:
        log_time = self.wall0_ns + (round(t * 1e9) if math.isfinite(t) else 0)
        chans[name].log(json.dumps(msg).encode(), log_time=log_time)

    def handle(self, kind: str, item: Any) -> None:
        if kind == "chunk":
            self._chunk(item)
        elif kind == "live":
            if self._live and self._live["signals"].has_sinks():  # nobody watching: nothing encoded
                for t, msgs in item:
                    for name, m in msgs.items():
                        self._log(self._live, name, t, m)
        else:
            name, t, msg = item
            if name == "session" and isinstance(msg.get("params"), dict):
                # What identifies a trace link (its digest: a log names no file to open), read here,
                # in the writer process, not in the loop's.
                msg = {**msg, "traces": trace_digests(msg["params"])}
            for chans in (self._ch, self._live):
                if chans:
                    self._log(chans, name, t, msg)
            self.messages += bool(self._ch)

    def _chunk(self, c: Chunk) -> None:
        """A chunk's per-tick messages, formatted a topic at a time from the arrays (``%`` with a
        template is a third of what a dict and ``json.dumps`` cost; ``repr`` of a float is what
        ``json.dumps`` writes); a row holding a NaN or an infinity (JSON has neither) takes the dict path."""
        if not self._ch:
            return
        a = c.arrays()
        rows = c.ran()
        if rows.size == 0:
            return
        ks = (c.k0 + rows).astype(np.float64)
        t = a["play_time_s"][rows]
        log_times = (self.wall0_ns + np.round(t * 1e9)).astype(np.int64).tolist()
        dof = a["v"].shape[1]
        vec = "[" + ",".join(["%r"] * dof) + "]"
        for name, cols, tmpl in (
            ("signals", ("v", "f"), '{"k":%d,"t":%r,"v":' + vec + ',"f":' + vec + "}"),
            (
                "waves",
                ("wave_out", "wave_in"),
                '{"k":%d,"t":%r,"wave_out":' + vec + ',"wave_in":' + vec + "}",
            ),
            ("energy", tuple(ENERGY_FIELDS.values()), _template(ENERGY_FIELDS)),
            ("wire", tuple(WIRE_FIELDS.values()), _template(WIRE_FIELDS)),
            ("loop", ("lateness_ns",), '{"k":%d,"t":%r,"lateness_ns":%d}'),
        ):
            m = np.column_stack([ks, t, *(a[col][rows].reshape(len(rows), -1) for col in cols)])
            bad = ~np.isfinite(m).all(axis=1)
            log = self._ch[name].log
            for i, (row, lt) in enumerate(zip(m.tolist(), log_times, strict=True)):
                if bad[i]:
                    r = int(rows[i])
                    data = json.dumps(tick_messages(a, r, c.k0 + r)[name]).encode()
                else:
                    data = (tmpl % tuple(row)).encode()
                log(data, log_time=lt)
        self.messages += 5 * len(rows)

    @property
    def error(self) -> str | None:
        """Why the file is incomplete (its first failed write), or None."""
        return None if self._fh is None else self._fh.error

    def close(self) -> None:
        try:
            if self._file is not None and self._fh is not None:
                self._file.close()
                self._fh.close()
        finally:
            if self.server is not None:
                self.server.stop()


def spawn_writer() -> subprocess.Popen[bytes]:
    """A writer process, started ahead of its session: it imports (numpy, foxglove: about a second
    of CPU) while the handshake waits, not while the 1 kHz loop starts, then waits for its
    :class:`McapLog`.  Closing its stdin unused makes it exit."""
    # The writer runs in a process group of its own, so a terminal's Ctrl-C (sent to the whole group)
    # never reaches it, not even while it imports (a signal handler installed after the imports left
    # that second open: a Ctrl-C then killed it and lost the log).  It also ignores SIGINT/SIGTERM,
    # and ends when told or when its stdin closes (its parent died), finishing the file either way.
    return subprocess.Popen(
        [sys.executable, "-m", "transport.mcaplog"],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        process_group=0,
    )


class McapLog:
    """``ROLE.mcap`` written as the session runs by a writer process, and optionally the live view.

    ``write(chunk)`` is the port's sink; ``live``/``event``/``status`` are called by the runner;
    ``close(summary)`` drains the queue, logs the summary, finishes the file and waits for the
    writer.  From the loop each call is a ``put_nowait`` on a bounded queue; a sender thread
    pickles the items into the writer's stdin (a blocking write releases the GIL), and the writer
    process (``python -m transport.mcaplog``) does all the encoding, compression and writing under
    its own interpreter lock, so none of it can hold the loop's."""

    def __init__(
        self,
        path: Path | None,
        role: str,
        wall0_ns: int,
        live_port: int | None = None,
        live_every: int = 20,
        live_host: str = "127.0.0.1",
        process: subprocess.Popen[bytes] | None = None,
        file_id: tuple[int, int] | None = None,
    ) -> None:
        """``process``: a writer from :func:`spawn_writer` (default: one started now); ``file_id``:
        (device, inode) of the empty file at ``path`` that ``transport.logdir.reserve`` created."""
        self.role = role
        self.path = path
        self.live_every = live_every
        self.dropped_chunks = 0
        self.messages = 0
        self.error: str | None = None  # the writer could not open the file or the view
        self._live_port: int | None = None
        self._wants_live = live_port is not None
        cfg = {
            "path": None if path is None else str(path),
            "role": role,
            "wall0_ns": wall0_ns,
            "live_port": live_port,
            "live_host": live_host,
            "file_id": file_id,
        }
        self._proc = process if process is not None else spawn_writer()
        self._q: queue.Queue[tuple[str, Any]] = queue.Queue(QUEUE_ITEMS)
        self._q.put(("open", cfg))
        self._thread = threading.Thread(target=self._send, name=f"teleop-{role}-log", daemon=True)
        self._thread.start()
        self._closed = False
        self._live_batch: list[tuple[float, dict[str, dict[str, Any]]]] = []

    @property
    def live_port(self) -> int | None:
        """The live view's port (waits for the writer to say, the first time)."""
        if self._wants_live and self._live_port is None and self._proc.stdout is not None:
            line = self._proc.stdout.readline()
            if line:
                d = json.loads(line)
                self._live_port, self.error = d.get("live_port"), d.get("error", self.error)
        return self._live_port

    # --- called from the loop: O(1), never blocks ----------------------------------------
    def write(self, chunk: Chunk) -> None:
        """The port's sink: a sealed chunk, queued for the writer."""
        self._put(("chunk", chunk))

    def live(self, k: int, t: float, msgs: dict[str, dict[str, Any]]) -> None:
        """Decimated per-tick messages for the live view, queued ``LIVE_BATCH`` at a time: each
        queued item wakes the sender thread, which then wants the interpreter lock the loop holds
        (50 wake-ups a second became 10; the view stays 50 Hz, 100 ms behind at most)."""
        if self._wants_live:
            self._live_batch.append((t, msgs))
            if len(self._live_batch) >= LIVE_BATCH:
                self._put(("live", self._live_batch))
                self._live_batch = []

    def event(self, t: float, event: str, detail: str = "") -> None:
        self._put(("msg", ("events", t, {"t": t, "event": event, "detail": detail})))

    def status(self, name: str, t: float, msg: dict[str, Any]) -> None:
        """A low-rate message (``link`` once a second, ``session`` once) to the file and the view."""
        self._put(("msg", (name, t, msg)))

    def _put(self, item: tuple[str, Any]) -> None:
        try:
            self._q.put_nowait(item)
        except queue.Full:
            self.dropped_chunks += item[0] == "chunk"

    # --- the sender thread ---------------------------------------------------------------
    def _send(self) -> None:
        out = self._proc.stdin
        assert out is not None
        while True:
            item = self._q.get()
            data = pickle.dumps(item, protocol=pickle.HIGHEST_PROTOCOL)
            try:
                out.write(len(data).to_bytes(4, "little") + data)
                out.flush()
            except OSError:  # the writer died: say so once; the loop goes on without a log
                self._writer_died()
                return
            if item[0] == "stop":
                return

    def _writer_died(self) -> None:
        """The writer process is gone (killed, crashed): the summary's ``log.error`` and one line."""
        try:  # (the sender thread, not the loop, waits here: the pipe may close a moment before)
            code: int | None = self._proc.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            code = None
        if code is None:
            how = "its pipe closed"
        else:
            how = f"killed by signal {-code}" if code < 0 else f"exit status {code}"
        if self.error is None:
            self.error = f"the log writer process died ({how}); later chunks are not in the log"
            print(f"teleop {self.role}: error: {self.error}", file=sys.stderr, flush=True)

    def promote(self) -> bool:
        """The writer to normal priority, once no loop ticks (:func:`promote_writer`)."""
        return promote_writer(self._proc)

    def close(
        self, summary: dict[str, Any] | None = None, timeout: float = 120.0, promote: bool = True
    ) -> None:
        """Write what is queued and the summary, finish the file, wait for the writer.

        ``promote``: no loop ticks any more (the caller says so: a replaced session's log closes
        while the next session ticks, and keeps its writer idle), so the writer's backlog is
        written at normal priority (:func:`promote_writer`)."""
        if self._closed:
            return
        self._closed = True
        # Where the promotion is refused (no CAP_SYS_NICE), an idle writer on a busy host may take
        # a while: a process that lingers after its session ended says why rather than look hung.
        slow = None
        if promote and not self.promote():
            slow = threading.Timer(SLOW_CLOSE_S, self._say_slow)
            slow.daemon = True
            slow.start()
        try:
            if summary is not None:
                self._q.put(("msg", ("summary", float(summary.get("end_t", 0.0)), summary)))
            self._q.put(("stop", None))
            self._thread.join(timeout)
            try:  # closes the writer's stdin (end of input), then waits for it
                out, _ = self._proc.communicate(timeout=timeout)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                out, _ = self._proc.communicate()
        finally:
            if slow is not None:
                slow.cancel()
        for line in out.decode(errors="replace").splitlines():
            with contextlib.suppress(ValueError):
                d = json.loads(line)
                self.error = d.get("error") or self.error
                self.messages = int(d.get("messages", self.messages))
                if d.get("live_port"):
                    self._live_port = int(d["live_port"])
        if self._proc.returncode != 0:  # died before it could say why (kill -9, a crash)
            self._writer_died()

    def _say_slow(self) -> None:
        print(
            f"teleop {self.role}: finishing the log: its writer runs at idle priority and the host is"
            " busy (with CAP_SYS_NICE it would finish at normal priority)",
            file=sys.stderr,
            flush=True,
        )


def promote_writer(proc: subprocess.Popen[bytes]) -> bool:
    """Every thread of the writer back to ``SCHED_OTHER`` at this process's niceness; False where
    that is refused.

    Why: the writer yields to the loops under ``SCHED_IDLE`` (:func:`_writer_main`), so on a host
    whose cores are busy with other work at normal priority it gets a fraction of a percent of a
    core, and what it has not written by the end of the session then takes tens of seconds: the
    process did not exit 20 s after SIGTERM with two busy loops on a 2-core host (measured).  Once
    no loop ticks, the backlog is the only thing left to do.  Leaving ``SCHED_IDLE`` and lowering
    the niceness need ``CAP_SYS_NICE`` (root; or a high enough ``RLIMIT_NICE``): the priority
    a real-time loop (``--rt-priority``) needs anyway.  Without it the writer stays idle and the
    close waits as before.  The threads are the writer's own (``/proc/PID/task``, a child not yet
    reaped, so the ids are its): foxglove's encoder threads compress too."""
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{proc.pid}/task")]
    except (OSError, ValueError):  # no procfs, or the writer has exited
        return False
    done, nice = True, os.getpriority(os.PRIO_PROCESS, 0)  # not above the process it serves
    for tid in tids:
        try:
            os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
            os.setpriority(os.PRIO_PROCESS, tid, nice)
        except (OSError, AttributeError):  # refused (no privilege), a thread that just ended
            done = False
    return done


def _read(stdin: Any) -> tuple[str, Any] | None:
    """One framed item from the parent, or None at the end of input."""
    hdr = stdin.read(4)
    if len(hdr) < 4:
        return None
    kind, item = pickle.loads(stdin.read(int.from_bytes(hdr, "little")))
    return str(kind), item


def _writer_main() -> None:
    """The writer process: framed pickles on stdin (from our own parent) to the file and the view;
    the first item says what to open."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    # Yield the CPU to the 1 kHz loops: on a busy host the writer, not the loop, should wait (it
    # has a queue; the loop has a deadline).  SCHED_IDLE: any waking task preempts it at once (a
    # niced task may keep the CPU for the rest of its slice); lowering one's own policy needs no
    # privilege, and it also undoes a SCHED_FIFO inherited from a real-time parent.  Threads the
    # writer starts (foxglove's server, its zstd encoder) inherit it.
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    with contextlib.suppress(OSError):
        os.nice(NICE)
    stdin = sys.stdin.buffer
    first = _read(stdin)
    if first is None or first[0] != "open":  # never used (its session did not start)
        return
    cfg = first[1]
    try:
        w = _Writer(
            cfg["path"], cfg["role"], cfg["wall0_ns"], cfg["live_port"], cfg["live_host"], cfg.get("file_id")
        )
    except Exception as e:  # a file that cannot be made, a port taken: say so; the session goes on
        print(f"teleop {cfg['role']}: error: no log and no live view: {e}", file=sys.stderr, flush=True)
        print(json.dumps({"error": str(e)}), flush=True)
        while _read(stdin) is not None:  # let the parent's sender finish
            pass
        return
    if w.server is not None:
        print(json.dumps({"live_port": w.live_port}), flush=True)
        print(
            f"teleop {cfg['role']}: live view on ws://{cfg['live_host']}:{w.live_port}",
            file=sys.stderr,
            flush=True,
        )
    port = w.live_port  # (the server says 0 once stopped)
    error = None
    try:
        while (got := _read(stdin)) is not None and got[0] != "stop":
            w.handle(*got)
    except Exception as e:  # a full disk, an I/O error: say so; the parent's session goes on
        error = f"writing the log failed: {e}"
        print(f"teleop {cfg['role']}: error: {error}", file=sys.stderr, flush=True)
        while _read(stdin) is not None:  # let the parent's sender finish
            pass
    finally:
        try:
            w.close()
        except Exception as e:
            error = error or f"finishing the log failed: {e}"
    error = w.error or error  # a failed write: the first failure, said once already
    print(json.dumps({"messages": w.messages, "live_port": port, "error": error}), flush=True)


def wall_clock_of(t_common_ns: int) -> int:
    """Wall-clock ns of a monotonic-clock instant (the session's tick 0), for MCAP log times."""
    return time.time_ns() - (time.monotonic_ns() - t_common_ns)


if __name__ == "__main__":
    _writer_main()
