"""What one process can afford: the ranges every session parameter is checked against.

One table for the command line, ``teleop sim`` and the handshake parser, so a value that the
network proposes is held to the same bounds as one typed by the user (validate every
field against a range the local side can afford).  A real process streams its per-tick records to
disk a chunk at a time (``teleop.session.port``, ``teleop.offline.logfile``), so its memory does
not grow with the session: a session runs until stopped (duration :data:`UNTIL_STOPPED`) or for at most
:data:`MAX_DURATION_S`.  Only ``teleop sim`` keeps every tick in memory, about ``32 dof + 160``
bytes a tick, so its length is bounded by :data:`RECORD_BUDGET_BYTES`.
"""

from __future__ import annotations

MAX_DOF = 64
MIN_DT = 1e-4  # s (10 kHz)
MAX_DT = 1e-2  # s (100 Hz)
MIN_DURATION_S = 0.1  # s: shorter sessions have too few ticks to measure anything
RECORD_BUDGET_BYTES = 1 << 30  # teleop sim: its per-tick records are kept in memory
MAX_DURATION_S = 7 * 24 * 3600.0  # s: a fixed-length session of a real process (a week)
UNTIL_STOPPED = 0.0  # duration of a session that runs until a signal or the peer's bye
MAX_SESSION = 2**32 - 1  # the wire's uint32 session id (0 is never used)
MAX_SEED = 2**32 - 1
MAX_VARIATION = 2.0  # scale of the human's seeded variation (teleop.devices.models.ProtocolPlan)
MAX_B = 1e6  # N s/m
MAX_RANGE = 1e6  # sqrt(W), full scale of the raw 16-bit wave format
MIN_RANGE = 2.2250738585072014e-308  # the smallest normal float: a subnormal range is refused
MIN_LINK_TIMEOUT_S = 1e-3
MAX_LINK_TIMEOUT_S = 10.0
MAX_CODEC_SPEC_LEN = 64
MAX_NETEM_SPEC_LEN = 1024
MAX_REASON_LEN = 300  # characters of a peer's reject reason that are kept and printed
#: Largest control message body, checked before unpacking (a full hello is about 2.3 kB at most);
#: here so that ``teleop.session.wire`` can bound every datagram without importing the protocol.
MAX_CONTROL_BYTES = 4096


def record_bytes_per_tick(dof: int) -> int:
    """Bytes one process records per tick (signals, energies, times, counters, loop timing)."""
    return 32 * dof + 160


def max_duration_s(dof: int, dt: float = 1e-3) -> float:
    """The longest session whose per-tick records fit in :data:`RECORD_BUDGET_BYTES`."""
    return (RECORD_BUDGET_BYTES // record_bytes_per_tick(dof)) * dt


def check_duration(duration: float, dof: int, dt: float = 1e-3, in_memory: bool = False) -> None:
    """ValueError saying what is allowed when ``duration`` is out of range (or not finite).

    ``in_memory``: the simulation, which keeps every tick (bounded by the record budget, and it
    must end); otherwise 0 (until stopped) or up to :data:`MAX_DURATION_S`."""
    if in_memory:
        hi = max_duration_s(dof, dt)
        if not MIN_DURATION_S <= duration <= hi:
            raise ValueError(
                f"duration must be {MIN_DURATION_S:g} to {hi:g} s at {dof} DoF "
                f"(the simulation's per-tick records must fit in {RECORD_BUDGET_BYTES >> 20} MiB), "
                f"got {duration!r}"
            )
        return
    if duration != UNTIL_STOPPED and not MIN_DURATION_S <= duration <= MAX_DURATION_S:
        raise ValueError(
            f"duration must be 0 (until stopped) or {MIN_DURATION_S:g} to {MAX_DURATION_S:g} s, "
            f"got {duration!r}"
        )
