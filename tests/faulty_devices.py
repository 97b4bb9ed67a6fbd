"""Devices that lie, for the tests: a built-in scenario's model whose output is replaced by NaN,
+-inf or an absurd value on chosen ticks (``--robot tests.faulty_devices:FaultyRobot:TICKS``,
``--hsi tests.faulty_devices:FaultyHsi:TICKS``; TICKS like ``100,200``).  On the listed ticks the
first value of ``affine``'s output cycles through NaN, +inf, -inf and 1e300."""

from __future__ import annotations

from typing import Any

import numpy as np

from teleop.devices.models import Array, ProtocolEnvironment, ProtocolHuman, ProtocolPlan

BAD = (float("nan"), float("inf"), float("-inf"), 1e300)


class _Faulty:
    def __init__(self, inner: Any, dt: float, arg: str | None) -> None:
        self.inner = inner
        self.dt = dt
        self.bad_ticks = {int(t) for t in (arg or "100").split(",")}
        self.tick = 0
        self.injected = 0

    def affine(self, now: float) -> tuple[Array, Array]:
        a, g = self.inner.affine(now)
        if self.tick in self.bad_ticks:
            a = np.array(a, dtype=float)
            a[0] = BAD[self.injected % len(BAD)]
            self.injected += 1
        self.tick += 1
        return a, g

    def advance(self, now: float, v: Array, f: Array) -> None:
        assert np.all(np.isfinite(v)) and np.all(np.isfinite(f)), "a non-finite value reached the device"
        self.inner.advance(now, v, f)


class FaultyRobot(_Faulty):
    role = "robot"
    hardware = False  # a model: teleop sim may build it

    def __init__(self, dof: int, dt: float, arg: str | None) -> None:
        super().__init__(ProtocolEnvironment(dof, dt, plan=ProtocolPlan.draw(0, 0.0)), dt, arg)


class FaultyHsi(_Faulty):
    role = "hsi"
    hardware = False

    def __init__(self, dof: int, dt: float, arg: str | None) -> None:
        super().__init__(ProtocolHuman(dof, dt, plan=ProtocolPlan.draw(0, 0.0)), dt, arg)
