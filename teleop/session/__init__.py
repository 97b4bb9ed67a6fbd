"""The sans-I/O session: the wire format and its MACs, the handshake (protocol), one side's node and
port, and the endpoint that turns datagrams and ``now`` into datagrams, events and timers.

Takes ``now`` and never reads a clock, a socket or a file, so ``teleop sim``, the virtual-time tests
and the two real processes run the same code. Imports ``teleop.control`` and ``teleop.devices``.
"""
