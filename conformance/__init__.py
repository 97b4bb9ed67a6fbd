"""``teleop conformance``: the checker that tests another implementation against PROTOCOL.md, section
by section (``checker``).  It stands above the shell and the transports and below the CLI."""
