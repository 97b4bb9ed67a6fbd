"""``python -m teleop.cli``: the ``teleop`` command."""

import sys

from .parser import main

sys.exit(main())
