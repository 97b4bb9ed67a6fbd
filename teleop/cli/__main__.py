"""``python -m teleop.cli``: the ``teleop`` command."""

import sys

from teleop.cli.parser import main

sys.exit(main())
