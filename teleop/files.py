"""Opening files safely: the one place the stack opens a file it reads as input or writes.

Why here: the trace loader (``teleop.session.link.netem``), the command line, the Zenoh config and the log
writer all need the same rules (trust nothing from the network, or from a file):

* an **input** (a netem trace, a Zenoh config) is a regular file of bounded size: its type is
  checked with ``stat`` *before* it is opened, so a FIFO, a device (``/dev/zero``) or a directory
  is refused and nothing ever blocks, then it is opened with ``O_NOFOLLOW | O_NONBLOCK`` and
  checked again with ``fstat`` (it may have been swapped in between), and at most the bound is read;
* a file the stack **writes** is created with ``O_CREAT | O_EXCL | O_NOFOLLOW``: never through a
  symlink, never over an existing file;
* a **log folder** is opened where the user named it, walked from ``/`` without following a
  symlink another user could have placed (:func:`open_dir`), and files are made relative to its
  descriptor; a folder, or a folder on the way, that another user can write (group or other
  writable without the sticky bit, or owned by someone else than this user or root) is refused:
  whoever can write it can plant names in it.

Every refusal is a :class:`FileRefused` (a ValueError) whose text is one line naming the file.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import stat
from pathlib import Path

from teleop.errors import LocalError

__all__ = [
    "MAX_CONFIG_BYTES",
    "MAX_TRACE_BYTES",
    "FileRefused",
    "check_private_dir",
    "create_new",
    "open_dir",
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


def create_new(path: str | os.PathLike[str], mode: int = 0o644, dir_fd: int | None = None) -> int:
    """A file descriptor, open for writing, of ``path`` created now: FileExistsError if any file,
    or a symlink, already has that name (``O_EXCL`` also refuses a dangling symlink).  ``dir_fd``:
    ``path`` is a name in that folder (:func:`open_dir`), not a path walked again."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    return os.open(path, flags, mode, dir_fd=dir_fd)


def open_reserved(path: Path, dev: int, ino: int) -> int:
    """Open for writing the empty file :func:`create_new` made earlier (another process's), and
    only that one: no symlink, the same device and inode, still empty; :class:`FileRefused` else."""
    dfd = open_dir(path.parent)  # walked again: never through a symlink placed since
    try:
        fd = os.open(path.name, os.O_WRONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, dir_fd=dfd)
    finally:
        os.close(dfd)
    st = os.fstat(fd)
    if (st.st_dev, st.st_ino) != (dev, ino) or st.st_size != 0 or not stat.S_ISREG(st.st_mode):
        os.close(fd)
        raise FileRefused(f"log {path}: not the file this process created (replaced?)")
    return fd


_DIR_FLAGS = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
MAX_LINKS = 40  # symlinks followed on the way to a folder (Linux's own limit)


def _others_can_write(st: os.stat_result, me: int) -> bool:
    """Whether a user other than ``me`` and root may add, remove or rename names in this folder:
    group or other write without the sticky bit, or an owner who is neither (it can chmod)."""
    if st.st_uid not in (0, me):
        return True
    return not st.st_mode & stat.S_ISVTX and bool(st.st_mode & (stat.S_IWGRP | stat.S_IWOTH))


def open_dir(path: str | os.PathLike[str], what: str = "log folder", create: bool = False) -> int:
    """A descriptor of the folder ``path`` names, walked from ``/`` one component at a time with
    ``O_NOFOLLOW | O_DIRECTORY``, never where a link someone else placed points.

    Why: stat-ing the folder follows a symlink planted as it (or as an ancestor) in a folder others
    can write, and ``O_NOFOLLOW`` on a file covers only its last component.  Refused, as one
    :class:`FileRefused` line: an ancestor or the folder that another user can write (group or
    other writable without the sticky bit, or owned by someone else than this user or root); a
    folder owned by anyone but this user or root; a symlink on the way that another user could have
    placed (one in a folder others can write, or owned by someone else than this user or root; a
    symlink of this user's or root's in a folder only they write, as ``/var/run``, is followed).
    ``create``: missing folders are made 0755, whatever the umask."""
    me = os.geteuid()
    name = os.fspath(path)
    todo = os.path.abspath(name)
    links = 0
    while True:  # restarted from / at each symlink followed
        fd = os.open("/", _DIR_FLAGS)
        real = "/"
        parts = [p for p in todo.split("/") if p not in ("", ".")]
        try:
            for i, part in enumerate(parts):
                here = os.path.join(real, part)
                try:
                    child = os.open(part, _DIR_FLAGS, dir_fd=fd)
                except FileNotFoundError:
                    if not create:
                        raise FileRefused(f"{what} {name}: {here} does not exist") from None
                    with contextlib.suppress(FileExistsError):
                        os.mkdir(part, 0o700, dir_fd=fd)
                        made = os.open(part, _DIR_FLAGS, dir_fd=fd)
                        try:
                            os.fchmod(made, 0o755)
                        finally:
                            os.close(made)
                    child = os.open(part, _DIR_FLAGS, dir_fd=fd)
                except OSError as e:
                    if e.errno not in (errno.ELOOP, errno.ENOTDIR):
                        raise
                    lst = os.stat(part, dir_fd=fd, follow_symlinks=False)
                    if not stat.S_ISLNK(lst.st_mode):
                        kind = "a file" if stat.S_ISREG(lst.st_mode) else _kind(lst.st_mode)
                        raise FileRefused(f"{what} {name}: {here} is {kind}, not a folder") from None
                    # Its folder passed (only this user or root may rename in it, or it is sticky): a
                    # symlink there is whoever made it's, and only this user's or root's is followed.
                    if lst.st_uid not in (0, me):
                        raise FileRefused(
                            f"{what} {name}: {here} is a symlink of uid {lst.st_uid} that another user "
                            "could have placed; nothing is written through it (name the real folder)"
                        ) from None
                    links += 1
                    if links > MAX_LINKS:
                        raise FileRefused(
                            f"{what} {name}: more than {MAX_LINKS} symlinks on the way"
                        ) from None
                    target = os.readlink(part, dir_fd=fd)
                    todo = os.path.normpath(os.path.join(real, target, *parts[i + 1 :]))
                    break
                os.close(fd)
                fd = child
                real = here
                st = os.fstat(fd)
                if _others_can_write(st, me):
                    mode = stat.S_IMODE(st.st_mode)
                    if st.st_uid not in (0, me):
                        why = f"owned by uid {st.st_uid}, not by this user ({me}) or root"
                    else:
                        why = f"writable by other users (mode {mode:o})"
                    if i == len(parts) - 1:
                        fix = (
                            "use a folder of your own"
                            if st.st_uid not in (0, me)
                            else "use a folder only you can write (chmod go-w)"
                        )
                        raise FileRefused(f"{what} {name}: {why}; {fix}")
                    raise FileRefused(
                        f"{what} {name}: the folder {here} on the way is {why}: another user could "
                        "swap what it holds for a symlink; use a path only you and root can write"
                    )
            else:
                st = os.fstat(fd)
                if st.st_uid not in (0, me):
                    raise FileRefused(
                        f"{what} {name}: owned by uid {st.st_uid}, not by this user ({me}) or root; "
                        "use a folder of your own"
                    )
                out, fd = fd, -1
                return out
        except OSError as e:
            raise FileRefused(f"{what} {name}: {e.strerror or e}") from None
        finally:
            if fd >= 0:
                os.close(fd)


def check_private_dir(path: Path, what: str = "log folder") -> None:
    """Make ``path`` if missing (0755); :class:`FileRefused` if another user could write in it or on
    the way to it, or placed a symlink as it (:func:`open_dir`)."""
    os.close(open_dir(path, what, create=True))


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
