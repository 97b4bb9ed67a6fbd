"""Hypothesis for every test: no per-example deadline (a timed test fails on a loaded machine, not on a
defect: speed is measured in bench/, never asserted in tests)."""

from hypothesis import settings

settings.register_profile("teleop", deadline=None)
settings.load_profile("teleop")
