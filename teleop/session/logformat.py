"""The log format: a session's MCAP topics and the per-tick fields each carries.

Here, beside the port whose chunks fill them, so the writer (``shell.mcaplog``) and the reader
(``teleop.offline.logfile``) import one definition and cannot drift apart.
"""

from __future__ import annotations

PER_TICK_TOPICS = ("signals", "waves", "energy", "wire", "loop")
#: The robot's own state at its own rate (``state``; only a device with a ``state()``), and its pose
#: as Foxglove's well-known messages (``pose``: foxglove.PoseInFrame, ``tf``: foxglove.FrameTransforms),
#: so a 3D panel shows the arm.
STATE_TOPICS = ("state", "pose", "tf")
TOPICS = (*PER_TICK_TOPICS, "link", "events", "session", "summary", *STATE_TOPICS)
#: The frames of the ``tf`` topic: the robot's base, and its end effector (or tool point).
BASE_FRAME, TOOL_FRAME = "base", "tool"

#: /ROLE/wire fields and the chunk arrays they come from.
WIRE_FIELDS = {
    "send_time": "send_time_s", "tx_seq": "tx_seq", "rx_seq": "rx_seq", "send_phase": "send_phase",
    "produced_payload": "produced_payload", "produced_packet": "produced_packet",
    "tx_wire": "tx_wire", "tx_payload": "tx_payload", "tx_baseline_wire": "tx_baseline_wire",
    "tx_baseline_payload": "tx_baseline_payload", "rx_wire": "rx_wire", "rx_payload": "rx_payload",
}  # fmt: skip
#: Record names whose values are whole numbers (written as JSON integers).
INT_FIELDS = frozenset({"tx_seq", "rx_seq", "send_phase", "peer_epoch", "controller_ticks"})
ENERGY_FIELDS = {
    "sent": "energy_sent", "played": "energy_played", "margin_observed": "energy_margin_observed",
    "played_epoch": "energy_played_epoch", "peer_epoch": "peer_epoch",
    # The watchdog controller's ticks so far (-1: a tick not run; absent from logs before 2026-12).
    "controller_ticks": "controller_ticks",
}  # fmt: skip
