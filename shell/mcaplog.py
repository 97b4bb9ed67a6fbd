"""Streamed logs in MCAP, and the live view: the real-time runner's sink for the port's record.

Why MCAP: it is what the field records into and replays (ROS 2 bags, Foxglove, PlotJuggler), it is
chunked and indexed, so a file written as a session runs is readable at any length.  Why
foxglove-sdk's writer (PyPI ``foxglove-sdk``): one library writes the file and serves the same
channels live over the Foxglove WebSocket protocol (``--live-view``); its Rust core compresses
(zstd) and writes.  Tests read files with the reference ``mcap`` library; ``teleop report``
streams them with :func:`iter_ticks` (the ``mcap`` library's record
reader and decompression, its own split of each chunk's records: three times faster).

**What a kill -9 loses.** The port of a real-time session seals its record every
:data:`LOG_CHUNK_TICKS` ticks (250 ms at 1 kHz) and hands it to :meth:`McapLog.write`, which puts it
on a queue the process holds at most :data:`MAX_AHEAD_TICKS` ticks of (750 ms; a chunk beyond that
is dropped, counted, and logged as a ``log_dropped`` event).  A sender thread moves each item into a
pipe enlarged to :data:`PIPE_BYTES`, whose contents outlive the process: the writer reads them to
the end, then finishes the file.  A kill -9 of the process therefore loses at most 1 s of ticks (the
unsealed chunk and what the process held), however far behind the writer was; the writer keeps up
on a loaded host by leaving ``SCHED_IDLE`` while its pipe fills (:meth:`McapLog._keep_up`).

**Who pays.** The loop pickles each chunk, in a gap between two ticks; a sender thread writes it,
and pickles the small items, into the stdin of a writer *process* (``python -m
shell.mcaplog``), which turns chunks into messages, compresses and writes them, and serves the
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
``/ROLE/wire``              each tick  ``k``, ``t``, ``send_time``, ``tx_seq``, ``rx_seq``,
                                       ``send_phase`` (the teleoperator's, ticks; -1: none), bytes:
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
                                       ``replayed``, ``overrun``, ``stall`` (ticks
                                       skipped), ``log_dropped``, ``session_end``),
                                       ``detail``
``/ROLE/session``           once       the session's parameters, role, pid, start time; ``traces``:
                                       SHA-256 and size of a ``trace FILE`` link's file
``/ROLE/summary``           once       the process's summary (what ``ROLE.json`` holds)
``/ROLE/state``             device's   ``k``, ``t``, the device's ``state()``: ``pose`` (x, y, z,
                            own rate   qx, qy, qz, qw), a Franka's ``q``, ``dq``, ``tau``, ``setpoint``
``/ROLE/pose``, ``/ROLE/tf`` as state  the pose as ``foxglove.PoseInFrame`` and
                                       ``foxglove.FrameTransforms`` (``base`` -> ``tool``)
==========================  =========  ==================================================================

The live view serves the same topics, per-tick ones decimated to every ``live_every``-th tick (50 Hz
by default), sent from the loop through the same queue five at a time (100 ms), not a chunk later.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import pickle
import queue
import signal
import subprocess
import sys
import termios
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from teleop.files import create_new, open_reserved, trace_digests
from teleop.offline.logfile import (
    LogError,
    iter_messages,
    iter_ticks,
    read_log,
    read_summary,
)
from teleop.session.logformat import (
    BASE_FRAME,
    ENERGY_FIELDS,
    INT_FIELDS,
    PER_TICK_TOPICS,
    TOOL_FRAME,
    TOPICS,
    WIRE_FIELDS,
)
from teleop.session.port import Chunk

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
QUEUE_ITEMS = 256  # items (chunks, live batches 10 a second, events) in flight
#: Ticks a port's chunk holds in a real-time session (``shell.runner``): sealed and handed to
#: the writer four times a second, so a kill -9 of the process loses at most this much unsealed.
LOG_CHUNK_TICKS = 250
#: Ticks of sealed chunks the process itself may hold ahead of the writer's pipe (0.75 s at 1 kHz):
#: what a kill -9 loses on top of the unsealed chunk.  Beyond it a chunk is dropped and counted
#: (``log.dropped_chunks``): the writer is that far behind, and the loop never waits for it.
MAX_AHEAD_TICKS = 750
#: The pipe to the writer, enlarged so that a sealed chunk leaves the process at once: what sits in
#: the pipe survives a kill -9 of the process (the writer reads it to the end, then finishes the
#: file).  About 20 s of record at 2 DoF; where the kernel refuses it, ``pipe-max-size``.
PIPE_BYTES = 4 << 20
#: The writer runs under SCHED_IDLE until its pipe holds more than BEHIND of its size, then at its
#: process's own priority until it holds less than CAUGHT_UP (:meth:`McapLog._keep_up`).
BEHIND, CAUGHT_UP = 1 / 8, 1 / 64
SLOW_CLOSE_S = 2.0  # a close still waiting this long for an idle writer says why, once


def _f(kind: str, unit: str, what: str) -> dict[str, Any]:
    """A field of a schema: its JSON type, its unit and what it is (shown by Foxglove and mcap info)."""
    spec: dict[str, Any] = {"type": "array", "items": {"type": "number"}} if kind == "vec" else {"type": kind}
    return {**spec, "description": f"{what} [{unit}]" if unit else what}


_K = _f("integer", "tick", "the session's tick (1 kHz: ms since tick 0)")
_T = _f("number", "s", "when the tick ran, on the session clock")
_BYTES = "bytes"


def _schema(title: str, what: str = "", **props: Any) -> dict[str, Any]:
    return {"title": title, "description": what, "type": "object", "properties": props}


_XYZ = _schema("xyz", x=_f("number", "m", "x"), y=_f("number", "m", "y"), z=_f("number", "m", "z"))
_QUAT = _schema(
    "quaternion",
    "",
    x=_f("number", "", "quaternion x"),
    y=_f("number", "", "quaternion y"),
    z=_f("number", "", "quaternion z"),
    w=_f("number", "", "quaternion w"),
)
_STAMP = _schema("time", sec=_f("integer", "s", "seconds"), nsec=_f("integer", "ns", "nanoseconds"))

SCHEMAS: dict[str, dict[str, Any]] = {
    "signals": _schema(
        "teleop.Signals",
        "the port's variables each tick: the operator's hand, or the robot's command and force",
        k=_K,
        t=_T,
        v=_f("vec", "m/s", "velocity per DoF (operator: the hand's; teleoperator: the robot's command)"),
        f=_f(
            "vec", "N", "force per DoF (operator: rendered to the hand; teleoperator: the robot's measured)"
        ),
    ),
    "waves": _schema(
        "teleop.Waves",
        "the wave variables this side sent and received (eq. 3)",
        k=_K,
        t=_T,
        wave_out=_f("vec", "sqrt(W)", "wave sent, per DoF"),
        wave_in=_f("vec", "sqrt(W)", "wave received and played, per DoF"),
    ),
    "energy": _schema(
        "teleop.Energy",
        "the watchdog's energy books of this side (eqs. 5, 8)",
        k=_K,
        t=_T,
        sent=_f("number", "J", "energy sent so far"),
        played=_f("number", "J", "energy played so far"),
        margin_observed=_f("number", "J", "the watchdog's margin: reported in minus played"),
        played_epoch=_f("number", "J", "energy played since the peer's last restart"),
        peer_epoch=_f("integer", "", "the peer's restarts seen"),
        controller_ticks=_f("integer", "ticks", "ticks the passivity controller acted in so far"),
    ),
    "wire": _schema(
        "teleop.Wire",
        "what this side sent and received, counted at its socket",
        k=_K,
        t=_T,
        send_time=_f("number", "s", "when this tick's packet left (session clock; null: none)"),
        tx_seq=_f("integer", "", "sequence number sent this tick (-1: none)"),
        rx_seq=_f("integer", "", "newest sequence number accepted by this tick (-1: none)"),
        send_phase=_f("integer", "ticks", "the teleoperator's send phase (-1: the operator)"),
        produced_payload=_f("number", _BYTES, "payload the node produced"),
        produced_packet=_f("number", _BYTES, "packet the node produced, before the shim"),
        tx_wire=_f("number", _BYTES, "sent on the wire"),
        tx_payload=_f("number", _BYTES, "payload sent"),
        tx_baseline_wire=_f("number", _BYTES, "the uncompressed stream's wire bytes"),
        tx_baseline_payload=_f("number", _BYTES, "the uncompressed stream's payload bytes"),
        rx_wire=_f("number", _BYTES, "received on the wire"),
        rx_payload=_f("number", _BYTES, "payload received"),
    ),
    "loop": _schema(
        "teleop.Loop",
        "the real-time loop",
        k=_K,
        t=_T,
        lateness_ns=_f("integer", "ns", "tick start minus its deadline"),
    ),
    "link": _schema(
        "teleop.Link",
        "once a second: the incoming link, counters and the watchdog so far",
        t=_T,
        link={"type": "object"},
        sent={"type": "object"},
        received={"type": "object"},
        watchdog={"type": "object"},
    ),
    "events": _schema(
        "teleop.Event",
        "what happened, as it happened",
        t=_T,
        event={"type": "string"},
        detail={"type": "string"},
    ),
    "session": _schema("teleop.Session", "the session's parameters", params={"type": "object"}),
    "summary": _schema("teleop.Summary", "the process's summary (ROLE.json)"),
    "state": _schema(
        "teleop.RobotState",
        "the robot's own state at its own rate (the device's state(): teleop.devices)",
        k=_K,
        t=_T,
        pose=_f("vec", "m, quaternion", "the end effector's pose in the base frame: x, y, z, qx, qy, qz, qw"),
        q=_f("vec", "rad", "joint positions"),
        dq=_f("vec", "rad/s", "joint velocities"),
        tau=_f("vec", "Nm", "measured joint torques"),
        setpoint=_f("vec", "m", "the impedance set-point (the spring's rest position) per DoF"),
        position=_f("vec", "m", "the robot's position per DoF"),
    ),
    # Foxglove's well-known schemas, JSON-encoded: a 3D panel shows the pose and the tool frame.
    "pose": _schema(
        "foxglove.PoseInFrame",
        "the end effector's pose",
        timestamp=_STAMP,
        frame_id={"type": "string"},
        pose=_schema("foxglove.Pose", position=_XYZ, orientation=_QUAT),
    ),
    "tf": _schema(
        "foxglove.FrameTransforms",
        "the tool frame in the base frame",
        transforms={
            "type": "array",
            "items": _schema(
                "foxglove.FrameTransform",
                timestamp=_STAMP,
                parent_frame_id={"type": "string"},
                child_frame_id={"type": "string"},
                translation=_XYZ,
                rotation=_QUAT,
            ),
        },
    ),
}


def pose_messages(log_time_ns: int, pose: list[float]) -> dict[str, dict[str, Any]]:
    """A state's ``pose`` (x, y, z, qx, qy, qz, qw) as Foxglove's PoseInFrame and FrameTransforms."""
    x, y, z, qx, qy, qz, qw = pose
    stamp = {"sec": log_time_ns // 1_000_000_000, "nsec": log_time_ns % 1_000_000_000}
    position, rotation = {"x": x, "y": y, "z": z}, {"x": qx, "y": qy, "z": qz, "w": qw}
    return {
        "pose": {
            "timestamp": stamp,
            "frame_id": BASE_FRAME,
            "pose": {"position": position, "orientation": rotation},
        },
        "tf": {
            "transforms": [
                {
                    "timestamp": stamp,
                    "parent_frame_id": BASE_FRAME,
                    "child_frame_id": TOOL_FRAME,
                    "translation": position,
                    "rotation": rotation,
                }
            ]
        },
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
        whole = src in INT_FIELDS
        parts.append(f'"{name}":%{"d" if whole else "r"}')
    return "{" + ",".join(parts) + "}"


class _GuardedFile:
    """The log file as foxglove's writer sees it.  The first failed write (a full disk, a quota)
    is kept in ``error`` and said in one line, and every later write is dropped: foxglove itself
    prints a line for every message it cannot log (18 590 lines for a 5 s session, measured with
    RLIMIT_FSIZE), and the session must go on.  What was written before stays readable: the
    chunk being written is cut off, which ``teleop.offline.logfile`` reads as the file's end."""

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
        (``shell.logdir.reserve``): only that file is opened, never a name swapped in since;
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
        self._states(c)

    def _states(self, c: Chunk) -> None:
        """The device's state samples (``state``), and a pose as Foxglove's pose and transform."""
        t_of = c.play_time
        for k, values in c.device_state:
            t = float(t_of[k - c.k0])
            lt = self.wall0_ns + (round(t * 1e9) if math.isfinite(t) else 0)
            self._ch["state"].log(json.dumps({"k": k, "t": _num(t), **values}).encode(), log_time=lt)
            self.messages += 1
            pose = values.get("pose")
            if isinstance(pose, list) and len(pose) == 7 and all(map(math.isfinite, pose)):
                for name, m in pose_messages(lt, pose).items():
                    self._ch[name].log(json.dumps(m).encode(), log_time=lt)
                    self.messages += 1

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
    proc = subprocess.Popen(
        [sys.executable, "-m", "shell.mcaplog", str(os.getpriority(os.PRIO_PROCESS, 0))],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        process_group=0,
    )
    assert proc.stdin is not None
    _enlarge_pipe(proc.stdin.fileno())
    return proc


def _enlarge_pipe(fd: int) -> int:
    """The pipe's size raised to :data:`PIPE_BYTES` (or as far as the kernel allows); its size."""
    sizes = [PIPE_BYTES]
    with contextlib.suppress(OSError, ValueError):
        sizes.append(int(Path("/proc/sys/fs/pipe-max-size").read_text()))
    for size in sizes:
        with contextlib.suppress(OSError):
            return int(fcntl.fcntl(fd, fcntl.F_SETPIPE_SZ, min(size, PIPE_BYTES)))
    return int(fcntl.fcntl(fd, fcntl.F_GETPIPE_SZ))


class McapLog:
    """``ROLE.mcap`` written as the session runs by a writer process, and optionally the live view.

    ``write(chunk)`` is the port's sink; ``live``/``event``/``status`` are called by the runner;
    ``close(summary)`` drains the queue, logs the summary, finishes the file and waits for the
    writer.  From the loop each call is a ``put_nowait`` on a bounded queue (a chunk pickled first,
    see :meth:`write`); a sender thread pickles the other items and writes all of them into the
    writer's stdin (a blocking write releases the GIL), and the writer process (``python -m
    shell.mcaplog``) does all the encoding, compression and writing under its own interpreter
    lock, so none of it can hold the loop's."""

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
        max_ahead_ticks: int | None = None,
    ) -> None:
        """``process``: a writer from :func:`spawn_writer` (default: one started now); ``file_id``:
        (device, inode) of the empty file at ``path`` that ``shell.logdir.reserve`` created;
        ``max_ahead_ticks``: ticks of chunks this process may hold ahead of the pipe (a real-time
        session's :data:`MAX_AHEAD_TICKS`; None: no bound, for a writer fed in virtual time)."""
        self.max_ahead_ticks = max_ahead_ticks
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
        self._pipe_size = _pipe_size(self._proc)
        self._q: queue.Queue[tuple[str, Any]] = queue.Queue(QUEUE_ITEMS)
        self._q.put(("open", cfg))
        self._thread = threading.Thread(target=self._send, name=f"teleop-{role}-log", daemon=True)
        self._thread.start()
        self._closed = False
        self._live_batch: list[tuple[float, dict[str, dict[str, Any]]]] = []
        # Ticks of chunks queued by the loop, and written into the pipe by the sender: each counter
        # is written by one thread only, so their difference is what this process holds.
        self._queued_ticks = self._sent_ticks = 0

    @property
    def wants_live(self) -> bool:
        """A live view is served: the loop builds its per-tick messages (else it need not)."""
        return self._wants_live

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
        """The port's sink: a sealed chunk, queued for the writer, unless this process already holds
        ``max_ahead_ticks`` ticks the pipe has not taken (then it is dropped and counted)."""
        ahead = self._queued_ticks - self._sent_ticks
        if self.max_ahead_ticks is None or ahead == 0 or ahead + chunk.n <= self.max_ahead_ticks:
            # Pickled here, not by the sender thread: pickle.dumps is one C call that holds the
            # interpreter lock throughout (~50 us hot, up to 0.4 ms cold, measured), which the loop
            # would wait for if the thread ran it when the next tick is due; here it is a step of
            # the seal, in a gap between two ticks (``teleop.session.port.Recorder.settle``).
            try:
                self._q.put_nowait(("chunk", (_frame(("chunk", chunk)), chunk.n)))
            except queue.Full:
                pass
            else:
                self._queued_ticks += chunk.n
                return
        self.dropped_chunks += 1  # said in the log too: a hole in the ticks is a drop, not a stall
        t = chunk.play_time[: chunk.n]
        done = t[~np.isnan(t)]
        end = float(done[-1]) if done.size else 0.0
        self.event(end, "log_dropped", f"ticks {chunk.k0} to {chunk.k0 + chunk.n - 1}: the writer is behind")

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
            framed = item[1][0] if item[0] == "chunk" else _frame(item)
            try:
                out.write(framed)
                out.flush()
            except OSError:  # the writer died: say so once; the loop goes on without a log
                self._writer_died()
                return
            if item[0] == "chunk":
                self._sent_ticks += item[1][1]
                self._keep_up()
            if item[0] == "stop":
                return

    def _keep_up(self) -> None:
        """The writer's priority follows its backlog (the bytes its pipe holds): ``SCHED_IDLE``
        (the loops first) while it holds less than :data:`CAUGHT_UP` of the pipe, this process's
        own priority once it holds more than :data:`BEHIND`.

        Why: under SCHED_IDLE beside two CPU hogs (2 cores) the writer got next to nothing, fell
        5 s behind, and a kill -9 of the robot lost all of it.  The sender thread decides, not the
        writer: a starved idle writer cannot run to promote itself.  A real-time loop (SCHED_FIFO)
        still preempts the promoted writer at once.  Needs CAP_SYS_NICE, as the loop's priority
        does; without it the writer stays idle and a writer too far behind costs dropped chunks."""
        if self._pipe_size <= 0 or self._proc.stdin is None:
            return
        buf = bytearray(4)
        try:
            fcntl.ioctl(self._proc.stdin.fileno(), termios.FIONREAD, buf)
        except (OSError, ValueError):
            return
        pending = int.from_bytes(buf, sys.byteorder)
        try:  # read back, not remembered: the writer idles itself once it has imported
            idle = os.sched_getscheduler(self._proc.pid) == os.SCHED_IDLE
        except OSError:  # it has exited
            return
        if idle and pending > self._pipe_size * BEHIND:
            promote_writer(self._proc)
        elif not idle and pending < self._pipe_size * CAUGHT_UP:
            idle_writer(self._proc)

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


def _pipe_size(proc: subprocess.Popen[bytes]) -> int:
    try:
        return int(fcntl.fcntl(proc.stdin.fileno(), fcntl.F_GETPIPE_SZ)) if proc.stdin else 0
    except (OSError, ValueError):
        return 0


def idle_writer(proc: subprocess.Popen[bytes]) -> bool:
    """Every thread of the writer back under ``SCHED_IDLE`` (its backlog is written: the loops
    first again); False where that failed."""
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{proc.pid}/task")]
    except (OSError, ValueError):
        return False
    done = True
    for tid in tids:
        try:
            os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
        except (OSError, AttributeError):
            done = False
    return done


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


def _frame(item: tuple[str, Any]) -> bytes:
    """An item as the writer reads it (:func:`_read`): its pickle's length (4 bytes), the pickle."""
    data = pickle.dumps(item, protocol=pickle.HIGHEST_PROTOCOL)
    return len(data).to_bytes(4, "little") + data


def _read(stdin: Any) -> tuple[str, Any] | None:
    """One framed item from the parent, or None at the end of input (a frame cut short is the end
    too: the parent was killed while writing it)."""
    hdr = stdin.read(4)
    if len(hdr) < 4:
        return None
    n = int.from_bytes(hdr, "little")
    body = stdin.read(n)
    if len(body) < n:
        return None
    kind, item = pickle.loads(body)
    return str(kind), item


def _set_priority(idle: bool, nice: int) -> bool:
    """Every thread of this process (foxglove's encoder threads compress too) under SCHED_IDLE, or
    back to SCHED_OTHER at ``nice``; False where that is refused (no CAP_SYS_NICE)."""
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    except (OSError, ValueError):
        tids = [0]
    done = True
    for tid in tids:
        try:
            if idle:
                os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
            else:
                os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
                os.setpriority(os.PRIO_PROCESS, tid, nice)
        except (OSError, AttributeError):
            done = False
    return done


def _on_parent_death(nice: int) -> None:
    """SIGUSR1 when the process this writer serves dies (``PR_SET_PDEATHSIG``): every thread back
    to ``nice`` under SCHED_OTHER, so that what the pipe still holds is written now, not when a
    busy host next leaves an idle moment (nothing ticks for it any more)."""
    import ctypes

    signal.signal(signal.SIGUSR1, lambda signum, frame: _set_priority(False, nice))
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGUSR1)  # PR_SET_PDEATHSIG
    if os.getppid() == 1:  # it died before the prctl
        _set_priority(False, nice)


def _say(line: str, stream: Any) -> None:
    """One line to the parent (stdout) or the console (stderr); nothing if nobody reads it any more
    (the parent was killed): the writer ends quietly, never with a BrokenPipeError traceback."""
    try:
        print(line, file=stream, flush=True)
    except (BrokenPipeError, ValueError):
        with contextlib.suppress(OSError):  # so that the exit's own flush does not fail again
            os.dup2(os.open(os.devnull, os.O_WRONLY), stream.fileno())


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
    base_nice = int(sys.argv[1]) if len(sys.argv) > 1 else os.getpriority(os.PRIO_PROCESS, 0)
    with contextlib.suppress(OSError, AttributeError):
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    with contextlib.suppress(OSError):
        os.nice(NICE)
    stdin = sys.stdin.buffer
    _on_parent_death(base_nice)
    first = _read(stdin)
    if first is None or first[0] != "open":  # never used (its session did not start)
        return
    cfg = first[1]
    try:
        w = _Writer(
            cfg["path"], cfg["role"], cfg["wall0_ns"], cfg["live_port"], cfg["live_host"], cfg.get("file_id")
        )
    except Exception as e:  # a file that cannot be made, a port taken: say so; the session goes on
        _say(f"teleop {cfg['role']}: error: no log and no live view: {e}", sys.stderr)
        _say(json.dumps({"error": str(e)}), sys.stdout)
        while _read(stdin) is not None:  # let the parent's sender finish
            pass
        return
    if w.server is not None:
        _say(json.dumps({"live_port": w.live_port}), sys.stdout)
        _say(f"teleop {cfg['role']}: live view on ws://{cfg['live_host']}:{w.live_port}", sys.stderr)
    port = w.live_port  # (the server says 0 once stopped)
    error = None
    got: tuple[str, Any] | None = None
    try:
        while (got := _read(stdin)) is not None and got[0] != "stop":
            w.handle(*got)
    except Exception as e:  # a full disk, an I/O error: say so; the parent's session goes on
        error = f"writing the log failed: {e}"
        _say(f"teleop {cfg['role']}: error: {error}", sys.stderr)
        while _read(stdin) is not None:  # let the parent's sender finish
            pass
    finally:
        if got is None and error is None:  # the input ended without "stop": the process died
            _set_priority(False, base_nice)  # nothing ticks for it any more: finish now
            _say(
                f"teleop {cfg['role']}: the process ended without closing its log (killed?); "
                f"the log writer finished {cfg['path']} with what reached it",
                sys.stderr,
            )
        try:
            w.close()
        except Exception as e:
            error = error or f"finishing the log failed: {e}"
    error = w.error or error  # a failed write: the first failure, said once already
    _say(json.dumps({"messages": w.messages, "live_port": port, "error": error}), sys.stdout)


def wall_clock_of(t_common_ns: int) -> int:
    """Wall-clock ns of a monotonic-clock instant (the session's tick 0), for MCAP log times."""
    return time.time_ns() - (time.monotonic_ns() - t_common_ns)


if __name__ == "__main__":
    _writer_main()
