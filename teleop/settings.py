"""One session's channel settings, and the one place each of their defaults is set.

A session's settings have three users: the command line, ``teleop sim`` (:class:`teleop.sim.SimConfig`)
and the handshake (:class:`teleop.protocol.SessionParams`, what both processes agree on); the ports
get theirs from either through :meth:`teleop.node.PortOptions.of`.  All of them are :class:`Channel`:
the fields below are declared here once, with their defaults, and checked here once
(:meth:`Channel.checked`), so a real session and its simulation cannot disagree on what an option
left out means.  What a *missing* optional field of a hello means is the protocol's business, not
a default: see :data:`teleop.protocol.WIRE_ABSENT`.

The model's settings (scenario, DoF, b, range, duration) default to the scenario's
(:mod:`teleop.scenarios`); the codec to the command's.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from .link.netem import NetemError, make_link
from .passivity import DEFAULT_LINK_TIMEOUT, ON_LOSS
from .playout import parse_playout
from .ratecap import RateCap

#: The two architectures: scattering waves (eq. 3-5) or TDPA on power variables (teleop.passivity).
PASSIVITY = ("wave", "tdpa")


@dataclass(frozen=True, kw_only=True)
class Channel:
    """How the channel between the two ports behaves: impairment, reconstruction, passivity.

    Text fields hold the canonical spelling, which is also what a hello carries; :meth:`checked`
    parses each once and says what is wrong."""

    netem_forward: str = ""  # impairment of operator -> TO (applied by the operator's shim)
    netem_backward: str = ""  # impairment of TO -> operator (applied by the TO's shim)
    seed: int = 0  # link seeds: 2 seed forward, 2 seed + 1 backward (a spec's own ``seed N`` wins)
    on_loss: str = "conceal"  # receivers' reconstruction when nothing is queued (teleop.passivity)
    controller: bool = True  # passivity controller on both receivers
    link_timeout: float = DEFAULT_LINK_TIMEOUT  # s of silence before a side goes to its safe state
    rate_cap: float = 0.0  # bit/s per direction in any 100 ms window (teleop.ratecap); 0: none
    playout: str = "auto"  # receivers' playout buffer: off, auto or extra ms (teleop.playout)
    variation: float = 0.0  # scale of the human's seeded variation (teleop.models.ProtocolPlan); 0: scripted
    passivity: str = "wave"  # "wave" (scattering, eq. 3-5) or "tdpa" (power variables + TDPA)

    def check_channel(self, *, netem_files: bool) -> str:
        """Check every channel field; return the canonical playout (ValueError says what is wrong).

        ``netem_files``: a ``trace FILE`` spec is loaded to check it (settings typed locally); a
        peer's settings never open a file (:meth:`teleop.protocol.SessionParams.from_msg` checks
        their specs without it)."""
        if self.on_loss not in ON_LOSS:
            raise ValueError(f"on_loss must be one of {', '.join(ON_LOSS)}, got {self.on_loss!r}")
        if not self.link_timeout > 0:
            raise ValueError(f"link_timeout must be > 0 s, got {self.link_timeout!r}")
        if self.rate_cap:
            RateCap(self.rate_cap, 1e-3)  # ValueError saying the allowed range
        if self.passivity not in PASSIVITY:
            raise ValueError(f"passivity must be one of {', '.join(PASSIVITY)}, got {self.passivity!r}")
        if netem_files:
            for name in ("netem_forward", "netem_backward"):
                text = getattr(self, name)
                if not text.strip():
                    continue
                try:
                    make_link(text, self.seed)  # NetemError (a ValueError) names the bad token
                except NetemError as e:  # a trace file refused (teleop.files): say for which direction
                    if text.split()[:1] == ["trace"]:
                        raise ValueError(f"{name}: {e}") from None
                    raise
        return parse_playout(self.playout)

    def channel_fields(self) -> dict[str, Any]:
        """This object's :class:`Channel` fields, to build another settings type from them."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(Channel)}

    @classmethod
    def fields_from(cls, m: Mapping[str, Any]) -> dict[str, Any]:
        """The :class:`Channel` fields present in ``m`` (the rest keep their defaults)."""
        return {f.name: m[f.name] for f in dataclasses.fields(Channel) if f.name in m}


#: Every default in one object: ``DEFAULTS.playout`` is what a left-out ``--playout`` means.
DEFAULTS = Channel()
