"""A process's records of its sessions: one MCAP log (and live view) per session, and its ``ROLE.json``.

The runner hands each session's port the sink :meth:`Records.open` returns; the port hands it the
per-tick record a chunk (250 ticks, ``shell.mcaplog.LOG_CHUNK_TICKS``) at a time. The sink is
``shell.mcaplog.McapLog``, whose writer process writes ``ROLE.mcap`` as the session runs (and,
with a live view, serves the same channels over the Foxglove WebSocket protocol), so memory stays
flat however long the session lasts and the loop never encodes or writes a message.
:meth:`Records.end` closes a session's log and writes its summary
(``teleop.session.summary.SessionSummary.document``) into the log and beside it; a session replaced by a
takeover is finished on a thread, beside the next one, not in its way.
"""

from __future__ import annotations

import subprocess
import threading
from pathlib import Path

from teleop.errors import TeleopError
from teleop.session.port import Chunk
from teleop.session.summary import LogFigures, SessionSummary

from . import logdir
from .mcaplog import MAX_AHEAD_TICKS, McapLog, spawn_writer, wall_clock_of


class RecordError(TeleopError):
    """The log folder or the live view cannot be opened: one line, the process stops."""


class _Discard:
    """The sink of a process that keeps no log and serves no live view: chunks are dropped."""

    def write(self, chunk: Chunk) -> None:
        pass


class Records:
    """The logs of one process's sessions (``log_dir`` and/or a live view on ``live_view``)."""

    def __init__(
        self, role: str, log_dir: Path | None, live_view: int | None, live_view_host: str = "127.0.0.1"
    ) -> None:
        self.role, self.log_dir = role, log_dir
        self.live_view, self.live_view_host = live_view, live_view_host
        self.logs: dict[int, McapLog | None] = {}  # session id -> its log (a takeover opens the next)
        self._finishing: list[tuple[threading.Thread, McapLog | None]] = []
        # The writer process starts now, so that it has imported before the loop starts.
        self._writer: subprocess.Popen[bytes] | None = spawn_writer() if self.wanted else None

    @property
    def wanted(self) -> bool:
        return self.log_dir is not None or self.live_view is not None

    def open(self, session: int, t_common_ns: int) -> McapLog | _Discard:
        """The sink of a new session: a new MCAP file in the log folder (``shell.logdir.reserve``:
        ``ROLE.mcap`` or, if an earlier run or session holds it, ``ROLE-SESSION[-N].mcap``; nothing is
        renamed or overwritten) and/or the live view, or one that drops the record."""
        if not self.wanted:
            self.logs[session] = None
            return _Discard()
        writer, self._writer = self._writer, None
        try:
            files = logdir.reserve(self.log_dir, self.role, session) if self.log_dir is not None else None
            log = McapLog(
                files.mcap if files is not None else None,
                self.role,
                wall_clock_of(t_common_ns),
                live_port=self.live_view,
                live_host=self.live_view_host,
                process=writer,
                file_id=(files.dev, files.ino) if files is not None else None,
                max_ahead_ticks=MAX_AHEAD_TICKS,
            )
        except (OSError, RuntimeError, ValueError) as e:  # a folder others can write, the port is taken
            raise RecordError(f"cannot open the log or the live view: {e}") from None
        self.logs[session] = log
        return log

    def end(self, s: SessionSummary, session: int, t_end: float, why: str, replaced: bool) -> None:
        """Session ``session`` is over after ``t_end`` s: its end event, its log closed with the
        summary, ``ROLE.json`` beside it (a full disk is one line, ``shell.logdir.save_summary``)."""
        log = self.logs.pop(session, None)
        if log is not None:
            log.event(t_end, "session_end", why)
        if replaced:  # the next session already runs: finish this one's files beside it
            done = threading.Thread(target=self._finish, args=(s, log, t_end, True), name="finish-log")
            done.start()
            self._finishing.append((done, log))
        else:
            self._finish(s, log, t_end, False)

    def _finish(self, s: SessionSummary, log: McapLog | None, t_end: float, replaced: bool) -> None:
        assert s.process is not None
        if log is not None:
            # Waits for the writer; at normal priority unless the next session ticks (replaced).
            log.close(s.document(end_t=t_end), promote=not replaced)
            s.process.log = LogFigures(
                mcap=log.path.name if log.path is not None else None,
                messages=log.messages,
                dropped_chunks=log.dropped_chunks,
                live_view_port=log.live_port,
                error=log.error,
            )
        if self.log_dir is not None:
            logdir.save_summary(self.log_dir, self.role, s.document())

    def wait_finished(self) -> None:
        """Until replaced sessions' logs are finished (blocking: run it off the event loop).  No loop
        ticks any more: their writers, kept idle while the next session ticked, finish at normal
        priority (:func:`shell.mcaplog.promote_writer`)."""
        for t, log in self._finishing:
            if log is not None and t.is_alive():
                log.promote()
            t.join()

    def close(self) -> None:
        """At exit: an unused writer (no session: it holds no log) is killed, so a process stopped
        before any session (Ctrl-C while it waits for a peer) does not wait for the writer to finish
        importing (measured: 1-3 s on a loaded host); open logs close."""
        writer, self._writer = self._writer, None
        if writer is not None and writer.poll() is None:
            writer.kill()
            writer.communicate()
        for log in self.logs.values():
            if log is not None:
                log.close()
