"""Opening files safely: the one place the stack opens a file it reads as input or writes.

Why here: the trace loader (``teleop.link.netem``), the command line, the Zenoh config and the log
writer all need the same rules (DESIGN.md, "Trust nothing from the network, or from a file"):

* an **input** (a netem trace, a Zenoh config) is a regular file of bounded size: its type is
  checked with ``stat`` *before* it is opened, so a FIFO, a device (``/dev/zero``) or a directory
  is refused and nothing ever blocks, then it is opened with ``O_NOFOLLOW | O_NONBLOCK`` and
  checked again with ``fstat`` (it may have been swapped in between), and at most the bound is read;
* a file the stack **writes** is created with ``O_CREAT | O_EXCL | O_NOFOLLOW``: never through a
  symlink, never over an existing file;
* a **log folder** that another user can write (group or other writable without the sticky bit,
  or owned by another user) is refused: whoever can write it can plant names in it.

Every refusal is a :class:`FileRefused` (a ValueError) whose text is one line naming the file.
"""

from __future__ import annotations

import errno
import hashlib
import os
import stat
from pathlib import Path

from .errors import LocalError

__all__ = [
    "MAX_CONFIG_BYTES",
    "MAX_TRACE_BYTES",
    "FileRefused",
    "check_private_dir",
    "create_new",
    "open_reserved",
    "read_regular",
    "trace_digests",
    "write_new",
]

MAX_TRACE_BYTES = 8 << 20  # a Mahimahi trace: about a million delivery opportunities
MAX_CONFIG_BYTES = 1 << 20  # a Zenoh JSON5 config

_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISLNK, "a symlink"),
)


class FileRefused(LocalError):
    """A file or folder the stack will not use (one the user named, or an output): one line saying
    which and why."""


def _kind(mode: int) -> str:
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def read_regular(path: str | os.PathLike[str], limit: int, what: str) -> bytes:
    """The bytes of ``path``, a regular file of at most ``limit`` bytes; :class:`FileRefused` else.

    The type is checked before opening (a FIFO's open would block, ``/dev/zero`` never ends); a
    symlink the user named is resolved first, and the open then refuses one swapped in later."""
    name = os.fspath(path)
    real = os.path.realpath(name)
    try:
        st = os.lstat(real)
    except OSError as e:
        raise FileRefused(f"{what} {name}: {e.strerror}") from None
    if not stat.S_ISREG(st.st_mode):
        raise FileRefused(f"{what} {name}: {_kind(st.st_mode)}, not a regular file")
    if st.st_size > limit:
        raise FileRefused(f"{what} {name}: {st.st_size} bytes, more than the {limit} accepted")
    try:
        fd = os.open(real, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as e:
        raise FileRefused(f"{what} {name}: {e.strerror}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):  # swapped between the check and the open
            raise FileRefused(f"{what} {name}: {_kind(st.st_mode)}, not a regular file")
        chunks, got = [], 0
        while got <= limit:
            b = os.read(fd, min(1 << 20, limit + 1 - got))
            if not b:
                break
            chunks.append(b)
            got += len(b)
        if got > limit:  # it grew after the check
            raise FileRefused(f"{what} {name}: more than the {limit} bytes accepted")
        return b"".join(chunks)
    except OSError as e:
        raise FileRefused(f"{what} {name}: {e.strerror}") from None
    finally:
        os.close(fd)


def create_new(path: Path, mode: int = 0o644) -> int:
    """A file descriptor, open for writing, of ``path`` created now: FileExistsError if any file,
    or a symlink, already has that name (``O_EXCL`` also refuses a dangling symlink)."""
    return os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, mode)


def open_reserved(path: Path, dev: int, ino: int) -> int:
    """Open for writing the empty file :func:`create_new` made earlier (another process's), and
    only that one: no symlink, the same device and inode, still empty; :class:`FileRefused` else."""
    fd = os.open(path, os.O_WRONLY | os.O_NOFOLLOW | os.O_CLOEXEC)
    st = os.fstat(fd)
    if (st.st_dev, st.st_ino) != (dev, ino) or st.st_size != 0 or not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise FileRefused(f"log {path}: not the file this process created (replaced?)")
    return fd


def check_private_dir(path: Path, what: str = "log folder") -> None:
    """Make ``path`` if missing; :class:`FileRefused` if another user could write in it.

    Refused: not a directory; owned by another user; group or other writable without the sticky
    bit (whoever can write it can plant a symlink or take a name)."""
    try:
        path.mkdir(parents=True, exist_ok=True, mode=0o755)
        st = os.stat(path)
    except FileExistsError:
        raise FileRefused(f"{what} {path}: exists and is not a folder") from None
    except OSError as e:
        raise FileRefused(f"{what} {path}: {e.strerror or e}") from None
    if not stat.S_ISDIR(st.st_mode):
        raise FileRefused(f"{what} {path}: not a folder")
    if st.st_uid != os.geteuid():
        raise FileRefused(
            f"{what} {path}: owned by uid {st.st_uid}, not by this user ({os.geteuid()}); "
            "use a folder of your own"
        )
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH) and not st.st_mode & stat.S_ISVTX:
        raise FileRefused(
            f"{what} {path}: writable by other users (mode {stat.S_IMODE(st.st_mode):o}); "
            "use a folder only you can write (chmod go-w)"
        )


def is_exists(e: OSError) -> bool:
    """Whether an ``O_EXCL | O_NOFOLLOW`` create failed because the name is taken (a file, or a
    symlink: Linux says EEXIST for both with O_EXCL, ELOOP for a symlink without it)."""
    return e.errno in (errno.EEXIST, errno.ELOOP)


def write_new(path: Path, data: bytes) -> None:
    """``data`` in a new file at ``path`` (:func:`create_new`); :class:`FileRefused` if the name is
    taken (an earlier output is never overwritten, a planted symlink never followed) or the write
    fails (a full disk)."""
    try:
        fd = create_new(path)
    except OSError as e:
        if is_exists(e):
            raise FileRefused(
                f"{path} exists: outputs are never overwritten (another --out, or remove it)"
            ) from None
        raise FileRefused(f"cannot write {path}: {e.strerror or e}") from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
    except OSError as e:
        raise FileRefused(f"cannot write {path}: {e.strerror or e}") from None


def trace_digests(params: dict[str, object]) -> dict[str, dict[str, object]]:
    """For each direction whose netem spec is ``trace FILE``: the file's SHA-256 and size (or why it
    could not be read), so that a log carries what identifies the trace, and ``teleop report``
    can re-run the simulation with a file the user names and the digest confirms, never the
    path a log names."""
    out: dict[str, dict[str, object]] = {}
    for direction in ("forward", "backward"):
        toks = str(params.get(f"netem_{direction}") or "").split()
        if len(toks) == 2 and toks[0] == "trace":
            try:
                data = read_regular(toks[1], MAX_TRACE_BYTES, "trace")
            except FileRefused as e:
                out[direction] = {"error": str(e)}
                continue
            out[direction] = {"sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)}
    return out
