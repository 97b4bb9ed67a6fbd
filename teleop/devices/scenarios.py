"""Scenarios: a human and an environment model with the defaults that suit them.

The models are the built-in devices named like the scenario (``teleop.devices``); ``--hsi`` and
``--robot`` replace either side's.

Shared by ``teleop sim`` and the two real processes, so a simulated and a real run of the same
scenario use the same models.  A scenario's models may vary with the session's ``seed`` and
``variation`` (0: the scripted run); both processes get both from the handshake, so they build
the same performance, and :meth:`Scenario.phases` gives its phase boundaries for the metrics.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from teleop import devices
from teleop.devices.models import Environment, Human, ProtocolPlan


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    dof: int  # default DoF
    b: float  # default wave impedance, N s/m: of the order of the impedances met
    full_scale: float  # default range of the raw 16-bit wave format, sqrt(W): peak waves plus headroom
    duration: float  # default length, s
    make: Callable[[int, float, int, float], tuple[Human, Environment]]  # (dof, dt, seed, variation)
    #: (seed, variation, duration) -> [(phase, start s, end s)]; none: the run is one phase
    phase_plan: Callable[[int, float, float], list[tuple[str, float, float]]] | None = None

    def phases(self, seed: int, variation: float, duration: float) -> list[tuple[str, float, float]]:
        """The run's phases, from the same seeded plan the models use (empty if it has none)."""
        return [] if self.phase_plan is None else self.phase_plan(seed, variation, duration)


def _pair(name: str, dof: int, dt: float, seed: int, variation: float) -> tuple[Human, Environment]:
    """The scenario's own HSI and robot: the built-in devices named like it (``teleop.devices``),
    built from the session's seeded plan."""
    return (
        devices.make("hsi", name, dof, dt, seed, variation),
        devices.make("robot", name, dof, dt, seed, variation),
    )


SCENARIOS: dict[str, Scenario] = {
    "step": Scenario(
        name="step",
        description="Section V: velocity step, human s/(s+0.5), environment 1/(s+1)",
        dof=1,
        b=1.0,
        full_scale=2.0,  # waves peak at 1.15 (measured with none)
        duration=5.0,
        make=lambda dof, dt, seed, variation: _pair("step", dof, dt, seed, variation),
    ),
    "protocol": Scenario(
        name="protocol",
        description="Section VI: free space 0-5 s, foam 5-10 s, two wall pushes 10-15 s",
        dof=2,
        b=20.0,
        full_scale=2.0,  # waves peak at 1.26 (measured with none)
        duration=15.0,
        make=lambda dof, dt, seed, variation: _pair("protocol", dof, dt, seed, variation),
        phase_plan=lambda seed, variation, duration: ProtocolPlan.draw(seed, variation).phases(duration),
    ),
}


def get(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; accepted: {', '.join(SCENARIOS)}") from None
