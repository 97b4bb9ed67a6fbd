"""Pure models of the link the core may use: the netem shim's link model, the wire counters, the
link observer and streaming quantiles.  They read no clock and open no socket, so ``teleop sim``,
the virtual-time tests and the real-time runner share them (``shell/`` only imports them)."""

Addr = tuple[str, int]  # a peer's address as the transports report it: (host, port)

__all__ = ["Addr"]
