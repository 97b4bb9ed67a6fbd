"""A process's files in its ``--log`` folder: a new pair per session run, never an old one overwritten.

Why: a restart with the same ``--log`` (systemd's ``Restart=on-failure``) used to replace the
crashed run's ``ROLE.mcap`` and ``ROLE.json``, two robots sharing a folder wrote one file, a planted
symlink was written through, and a full disk left ``ROLE.json`` empty.  Here:

* :func:`reserve` opens the folder where the user named it, never through a symlink another user
  could have placed on the way, and refuses one another user can write (``teleop.files.open_dir``);
  it creates the run's MCAP file relative to that folder's descriptor with
  ``O_CREAT | O_EXCL | O_NOFOLLOW``: ``ROLE.mcap`` when free, else
  ``ROLE-SESSION.mcap``, else ``ROLE-SESSION-2.mcap`` ...  The writer process then opens exactly that
  file (same device and inode, still empty: ``teleop.files.open_reserved``).  Two processes of a role
  can never get one name; ``ROLE.json`` takes the MCAP file's stem.
* :func:`write_summary` writes the JSON to a fresh temporary file and links it into place, so the
  name holds either nothing or the whole summary, and never replaces a file; a full disk is one line.
* ``teleop report`` pairs the two roles' files by session id (``teleop.offline.logfile.find_pair``).
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from teleop.files import FileRefused, create_new, is_exists, open_dir

__all__ = ["MAX_RUNS", "LogFiles", "reserve", "save_summary", "write_summary"]

MAX_RUNS = 1000  # numbered files per role and session id before the folder is called full


@dataclass(frozen=True)
class LogFiles:
    """The run's two files: the MCAP log (created empty, identified by device and inode) and the
    JSON summary's name (made at the end)."""

    mcap: Path
    summary: Path
    dev: int
    ino: int


def _names(role: str, session: int) -> list[str]:
    return [role, f"{role}-{session}", *(f"{role}-{session}-{n}" for n in range(2, MAX_RUNS))]


def _lexists(name: str, dir_fd: int) -> bool:
    try:
        os.stat(name, dir_fd=dir_fd, follow_symlinks=False)
    except FileNotFoundError:
        return False
    return True


def reserve(log_dir: Path, role: str, session: int) -> LogFiles:
    """Create this run's empty MCAP file under a name no earlier run holds; :class:`FileRefused`
    (a ValueError) for a folder another user can write, OSError if the file cannot be made."""
    dfd = open_dir(log_dir, create=True)
    try:
        for stem in _names(role, session):
            if _lexists(f"{stem}.json", dfd):  # an earlier run's summary without its log: keep apart
                continue
            try:
                fd = create_new(f"{stem}.mcap", dir_fd=dfd)
            except OSError as e:
                if is_exists(e):
                    continue
                raise
            try:
                st = os.fstat(fd)
            finally:
                os.close(fd)
            return LogFiles(log_dir / f"{stem}.mcap", log_dir / f"{stem}.json", st.st_dev, st.st_ino)
    finally:
        os.close(dfd)
    raise FileRefused(f"log folder {log_dir}: {MAX_RUNS} logs of {role} session {session} already")


def write_summary(path: Path, summary: dict[str, Any]) -> str | None:
    """Write ``summary`` as JSON at ``path``, which must not exist: to a new temporary file first,
    then linked into place (never over a file, never through a symlink).  Returns None, or what went
    wrong in one line (a full disk, the name taken): the caller says so and goes on."""
    tmp = f".{path.name}.{secrets.token_hex(4)}.tmp"
    try:
        dfd = open_dir(path.parent)  # the folder the user named, not where a link points now
    except FileRefused as e:
        return str(e)
    try:
        fd = create_new(tmp, dir_fd=dfd)
    except OSError as e:
        os.close(dfd)
        return f"cannot write {path}: {e.strerror or e}"
    try:
        with os.fdopen(fd, "wb") as f:
            f.write((json.dumps(summary, indent=2) + "\n").encode())
            f.flush()
            os.fsync(f.fileno())
        os.link(tmp, path.name, src_dir_fd=dfd, dst_dir_fd=dfd)  # EEXIST rather than replace
    except OSError as e:  # ENOSPC, EDQUOT, EIO; EEXIST if another process took the name
        return f"cannot write {path}: {e.strerror or e}"
    finally:
        with contextlib.suppress(OSError):
            os.unlink(tmp, dir_fd=dfd)
        os.close(dfd)
    return None


def save_summary(log_dir: Path, role: str, summary: dict[str, Any]) -> str | None:
    """``summary`` beside its MCAP log (``ROLE.json`` for ``ROLE.mcap``, the stems match); a failure
    (a full disk) is one line on the console and the return value, never an exception."""
    name = (summary.get("log") or {}).get("mcap") or f"{role}.mcap"
    error = write_summary(log_dir / f"{Path(name).stem}.json", summary)
    if error is not None:
        print(f"teleop {role}: error: {error}", file=sys.stderr, flush=True)
    return error
