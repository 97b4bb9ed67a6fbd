"""The ``teleop`` command.

One module per part, in the order a reader needs them:

- :mod:`.parser`: ``build_parser`` and ``main`` (the console script ``teleop``; ``python -m teleop.cli``).
- :mod:`.args`: the argument types, each checking a range from :mod:`teleop.limits`, and the option
  groups several commands share (model, impairment, passivity, process, transport).
- :mod:`.settings`: from parsed arguments to a session's settings, and the checks that need more
  than one option (duration against DoF, a writable output folder), all before a session starts.
- :mod:`.sim`: ``teleop sim``.  :mod:`.run`: ``teleop run``.  :mod:`.endpoints`: ``teleop operator``,
  ``teleop teleoperator`` and ``teleop router``.  :mod:`.report`: ``teleop report``.
  :mod:`.keygen`: ``teleop keygen``, the pre-shared key the endpoints authenticate with
  (:mod:`teleop.session.auth`).

A bad argument is one line, ``teleop: error: <what is wrong and what is allowed>``, exit status 2.
"""

from __future__ import annotations

from teleop.cli.args import CliError
from teleop.cli.parser import build_parser, main

__all__ = ["CliError", "build_parser", "main"]
