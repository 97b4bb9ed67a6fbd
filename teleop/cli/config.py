"""Sessions from a file: ``--config FILE`` (TOML) and ``--print-config``.

A session file holds a command's settings under the same names as its flags, without the dashes
(``max-velocity = 0.5``, ``robot = "franka:172.16.0.2:stiffness=300"``, ``netem = "delay 10ms"``),
each value as the flag would take it; a flag typed on the command line wins over the file.  The
file is read as the command line is parsed, so its values meet the same checks as typed flags,
with the same one-line errors.  ``--print-config`` prints the settings in effect (the file's and
the flags', then every other at its default, commented out) as such a file, and exits: feed it back
with ``--config`` to run the same session again.  Only the commands that run or study sessions take
one (:data:`COMMANDS`).
"""

from __future__ import annotations

import argparse
import difflib
import json
import math
import tomllib
from collections.abc import Sequence
from enum import Enum
from typing import Any

from teleop.cli.args import CliError

COMMANDS = ("operator", "teleoperator", "run", "sim", "experiment")
MAX_CONFIG_BYTES = 64 * 1024  # a session file is a few hundred bytes: refused by size before it is read
_OWN = {"help", "config", "print_config"}  # this module's own flags, never in a file


def add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--config",
        metavar="FILE",
        help="read the settings from a TOML file: the flags' names without the dashes "
        "(max-velocity = 0.5); a flag given here wins over the file",
    )
    p.add_argument(
        "--print-config",
        action="store_true",
        help="print the settings in effect as such a file and exit (feed it back with --config)",
    )


def _flags(parser: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    """The command's long flags by their file name (``max-velocity``)."""
    return {
        a.option_strings[-1][2:]: a
        for a in parser._actions
        if a.option_strings and a.option_strings[-1].startswith("--") and a.dest not in _OWN
    }


def _token(value: Any, key: str, path: str) -> str:
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise CliError(f"--config {path}: {key} must be a string or a number, got {value!r}")
    if isinstance(value, float) and not math.isfinite(value):
        raise CliError(f"--config {path}: {key} must be finite, got {value!r}")
    return str(value)


def expand(argv: Sequence[str], commands: dict[str, argparse.ArgumentParser]) -> list[str]:
    """``argv`` with a ``--config FILE``'s settings put before the command's own flags (so those
    win; a repeatable flag given on the line replaces the file's list).  Unknown names, wrong
    types and files that are not small regular files are a CliError in one line."""
    args = list(argv)
    if not args or args[0] not in commands or args[0] not in COMMANDS:
        return args
    rest = args[1:]
    path = None
    for i, a in enumerate(rest):
        if a == "--config" and i + 1 < len(rest):
            path = rest[i + 1]
        elif a.startswith("--config="):
            path = a.split("=", 1)[1]
    if path is None:
        return args
    from teleop.files import read_regular

    try:
        data = read_regular(path, MAX_CONFIG_BYTES, "--config")
        table = tomllib.loads(data.decode("utf-8"))
    except UnicodeDecodeError:
        raise CliError(f"--config {path}: not UTF-8 text") from None
    except tomllib.TOMLDecodeError as e:
        raise CliError(f"--config {path}: not TOML: {e}") from None
    except OSError as e:
        raise CliError(f"--config {path}: {e.strerror or e}") from None
    flags = _flags(commands[args[0]])
    given = {a.split("=", 1)[0][2:] for a in rest if a.startswith("--")}
    tokens: list[str] = []
    for key, value in table.items():
        action = flags.get(key)
        if action is None:
            near = difflib.get_close_matches(key, list(flags), n=1, cutoff=0.6)
            hint = f"; did you mean {near[0]}?" if near else f"; names are the flags of 'teleop {args[0]}'"
            raise CliError(f"--config {path}: unknown setting {key!r}{hint}")
        if key in given:
            continue  # the command line wins
        flag = f"--{key}"
        if action.nargs == 0:  # an on/off flag
            if not isinstance(value, bool):
                raise CliError(f"--config {path}: {key} is on or off: true or false, got {value!r}")
            tokens += [flag] if value else []
        elif isinstance(action, argparse._AppendAction):
            for v in value if isinstance(value, list) else [value]:
                tokens += [flag, _token(v, key, path)]
        else:
            tokens += [flag, _token(value, key, path)]
    return [args[0], *tokens, *rest]


def _toml(value: Any) -> str | None:
    """A parsed value as the flag's text in TOML, or None where it has none to print."""
    if isinstance(value, Enum):
        value = value.value
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return repr(value) if math.isfinite(value) else None
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)  # a TOML basic string
    if isinstance(value, tuple) and len(value) == 2 and isinstance(value[1], int):  # HOST:PORT
        return json.dumps(f"{value[0]}:{value[1]}")
    if isinstance(value, list) and all(isinstance(v, str) for v in value):
        return "[" + ", ".join(json.dumps(v) for v in value) + "]"
    return None


def text(command: str, parser: argparse.ArgumentParser, argv: Sequence[str]) -> str:
    """The settings in effect of ``teleop COMMAND`` as a session file: what the line and the file
    set, then every other flag at its default (a flag without one, commented out)."""
    flags = _flags(parser)
    given = {a.split("=", 1)[0][2:] for a in argv if a.startswith("--")}
    raw: dict[str, list[str]] = {}  # what was typed, per flag: its exact text, units and all
    for i, a in enumerate(argv):
        if a.startswith("--") and a[2:] in flags and flags[a[2:]].nargs != 0:
            if "=" in a:
                raw.setdefault(a[2:].split("=", 1)[0], []).append(a.split("=", 1)[1])
            elif i + 1 < len(argv):
                raw.setdefault(a[2:], []).append(argv[i + 1])
    lines = [f"# teleop {command}: the settings in effect (teleop {command} --config FILE)"]
    # Defaults stay comments: set in a file, a default would be a choice (a teleoperator pins a
    # setting it is given), and fed back the file must run the same session.
    later = ["", "# at their defaults (uncomment to set one):"]
    for key, action in flags.items():
        if key in raw:
            vals = raw[key]
            v = "[" + ", ".join(json.dumps(x) for x in vals) + "]" if len(vals) > 1 else json.dumps(vals[0])
            lines.append(f"{key} = {v}")
        elif key in given and action.nargs == 0:
            lines.append(f"{key} = true")
        else:
            shown = _toml(action.default) if action.default is not None else None
            later.append(f"# {key} = {shown}" if shown is not None else f"# {key} = (none)")
    return "\n".join(lines + later) + "\n"
