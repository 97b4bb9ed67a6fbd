"""Node inbound handling: everything malformed, stale or foreign is dropped and counted."""

from __future__ import annotations

import numpy as np

from teleop.control.codecs import make_codec
from teleop.control.wave import WaveImpedance
from teleop.devices.models import LtiEnvironment, StepHuman
from teleop.session import wire
from teleop.session.node import OperatorNode, TeleoperatorNode

DT = 1e-3


def pair(spec: str = "none") -> tuple[OperatorNode, TeleoperatorNode]:
    w = WaveImpedance.of(1.0, 2)
    c = make_codec(spec, 2, 2.0)
    op = OperatorNode(human=StepHuman(2, DT, t_step=0.0), wave=w, tx=c, rx=c, session=5, dt=DT)
    to = TeleoperatorNode(environment=LtiEnvironment(2, DT), wave=w, tx=c, rx=c, session=5, dt=DT)
    return op, to


def test_bad_datagrams_are_counted_not_raised() -> None:
    op, to = pair()
    p = op.tick(0.0)
    assert p is not None
    good = wire.encode(p)
    assert not to.receive(b"garbage")
    assert not to.receive(good[:-3])
    assert not to.receive(wire.encode(wire.Packet(9, 0, 0, 0, 0, 0, p.payload)))  # foreign session
    assert not to.receive(wire.encode(wire.Packet(5, 1, 0, 0, 0, 0, p.payload)))  # wrong direction
    assert not to.receive(wire.encode(wire.Packet(5, 0, 0, 0, 0, 3, p.payload)))  # wrong codec
    assert not to.receive(wire.encode(wire.Packet(5, 0, 0, 0, 0, 0, b"\x01")))  # payload too short
    assert to.receive(good)
    assert not to.receive(good)  # duplicate: never replayed
    c = to.counters
    assert (
        c.received,
        c.accepted,
        c.malformed,
        c.wrong_session,
        c.wrong_direction,
        c.wrong_codec,
        c.stale,
    ) == (8, 1, 3, 1, 1, 1, 1)
    assert "payload has 1 bytes, expected 4" in to.last_error


def test_gaps_and_reordering() -> None:
    op, to = pair()
    pkts = [op.tick(k * DT) for k in range(5)]
    data = [wire.encode(p) for p in pkts if p is not None]
    assert to.receive(data[0]) and to.receive(data[3])
    assert not to.receive(data[1])  # overtaken: dropped, the played stream never goes back in time
    assert to.counters.gaps == 2 and to.counters.stale == 1


def test_nodes_report_energy_in_band() -> None:
    op, to = pair()
    for k in range(100):
        p = op.tick(k * DT)
        assert p is not None
        to.receive(wire.encode(p))
        to.tick(k * DT)
    assert to.peer_energy_sent == op.energy_sent > 0
    assert to.energy_played <= op.energy_sent
    assert np.all(np.isfinite(to.v))
