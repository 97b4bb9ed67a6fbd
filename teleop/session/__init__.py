"""The sans-I/O session: the wire format and its MACs, the handshake (protocol), one side's node and
port, the endpoint that turns datagrams and ``now`` into datagrams, events and timers, and the
scheduler beside it that decides when each of its ticks runs.

The session's path takes ``now`` and never reads a clock or a socket, so ``teleop sim``, the
virtual-time tests and the two real processes run the same code.  Two helpers read files, each
before a session and never during one: ``auth`` reads and writes key files (``teleop keygen``,
``--key-file``), and ``link.netem`` reads a ``trace FILE`` link's file when its spec is parsed.
Imports ``teleop.control`` and ``teleop.devices``.
"""
