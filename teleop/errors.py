"""One hierarchy for every error this stack raises on purpose, in h11's manner.

``TeleopError`` is the root; ``LocalError`` says this side's own settings or call are wrong (a codec
spec, a device, a netem spec typed by the user: fix the command), ``RemoteError`` that what a peer or
a file sent is wrong (a datagram, a log: count it, drop it, say so).  Each concrete error keeps
``ValueError`` as a base, so existing ``except ValueError`` handlers still hold; callers branch on
the type (and on enums such as ``teleop.session.protocol.Failure``), never on an error's text.
"""

from __future__ import annotations

__all__ = ["DeviceError", "LocalError", "RemoteError", "TeleopError", "one_line"]


class TeleopError(Exception):
    """Every error teleop raises on purpose."""


class LocalError(TeleopError, ValueError):
    """This side's own settings or call are invalid (the text says what is allowed)."""


class RemoteError(TeleopError, ValueError):
    """What a peer or a file sent is invalid (the text says what and where)."""


class DeviceError(LocalError):
    """A device spec cannot be resolved, or its device cannot be built: one line saying why.

    Here, not in ``teleop.devices``, so the drivers it loads lazily raise it without importing the
    registry that imports them."""


#: Control characters (C0, DEL, C1) shown escaped: a file name or a log's text in an error must
#: keep it one line, and must not drive the terminal (an escape sequence in a planted file's name).
_CONTROL = {c: f"\\x{c:02x}" for c in (*range(0x20), *range(0x7F, 0xA0))}


def one_line(text: object) -> str:
    """``text`` with every control character escaped (newlines too): what an error prints.  Here,
    not in ``teleop.cli``, so that the process shell (``transport``) shows a peer's text with it."""
    return str(text).translate(_CONTROL)
