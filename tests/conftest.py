"""Shared by every test: Hypothesis without a per-example deadline (a timed test fails on a loaded
machine, not on a defect: speed is measured in bench/, never asserted in tests), and the ``key``
fixture (a pre-shared key file)."""

from pathlib import Path

import pytest
from hypothesis import settings

settings.register_profile("teleop", deadline=None)
settings.load_profile("teleop")


@pytest.fixture
def key(tmp_path: Path) -> str:
    """A deployment's pre-shared key, as `teleop keygen` writes it."""
    from teleop.session import auth

    path = tmp_path / "teleop.key"
    auth.write_key_file(path, auth.generate_key())
    return str(path)
