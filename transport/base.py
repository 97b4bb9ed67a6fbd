"""The one small interface the session loop needs from a transport (UDP or Zenoh)."""

from __future__ import annotations

from typing import Any, Protocol

from teleop.session.admission import Admission
from teleop.session.link import Addr

__all__ = ["Addr", "Transport"]


class Transport(Protocol):
    """Datagrams in and out; the 1 kHz loop drains the inbox once per tick.

    ``drain`` yields ``(data, sender address, receive time on the monotonic clock in ns)``.
    ``header_bytes`` is what the transport adds per message below what we count (28 for UDP/IPv4:
    the wire counters add it; 0 where the transport's own framing is not visible to us).
    """

    inbox_overflow: int
    socket_errors: int
    oversize: int  # datagrams/samples longer than ``max_datagram``, refused by length
    header_bytes: int
    #: The longest datagram taken: teleop.session.wire.MAX_DATAGRAM_BYTES until the runner narrows it to its
    #: endpoint's bound (``Endpoint.max_datagram_bytes``) when a session starts.
    max_datagram: int
    warnings: list[str]  # what the transport could not set up as asked (printed, kept in ROLE.json)

    @property
    def local_address(self) -> Addr: ...

    def send(self, data: bytes, addr: Addr) -> None: ...

    def admit(self, admission: Admission) -> None:
        """What the endpoint can take now: a transport may refuse the rest before it is read
        (UDP: a kernel socket filter); one that cannot ignores it."""

    def drain(self) -> list[tuple[bytes, Addr, int]]: ...

    async def wait(self, timeout: float) -> bool: ...

    def report(self) -> dict[str, Any]: ...

    def close(self) -> None: ...
