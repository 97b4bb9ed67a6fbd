"""The exit statuses of a session command that ran its session: ok (0) or poor (3,
:data:`teleop.session.verdict.POOR_EXIT`).  A test whose point is not the verdict accepts both: a
loaded host's stall can make a sound session poor (its link lost for 50 ms, its real I off the
sim's), and a test that impairs the link on purpose makes one poor by design.  The verdict itself is
held by tests/test_verdict.py and tests/test_journey.py."""

from teleop.session.verdict import POOR_EXIT

RAN = (0, POOR_EXIT)
