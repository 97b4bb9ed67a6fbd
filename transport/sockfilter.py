"""A kernel socket filter (classic BPF, ``SO_ATTACH_FILTER``) compiled from an endpoint's
:class:`teleop.session.admission.Admission`: what the endpoint cannot take is dropped by the kernel before
the process is woken, copied or charged for it.

*Why.*  Refusing a datagram in Python costs the 1 kHz loop a ``recvfrom`` and a turn of its drain,
1-3 us each however cheap the endpoint's refusal is; a flood of 50k-100k a second is then 100-300
us of every tick (issue 21, ``bench/results/flood.json``).  A filter runs in the kernel's receive
path, which on loopback is the *sender's* time, and a refused datagram never reaches the socket's
queue.  The endpoint still checks everything that passes: the filter only refuses what it would
refuse anyway (longer than any message; a stranger's datagram that is not a handshake, or any
stranger's for an operator in session) and, under a handshake flood, keeps strangers' handshake
datagrams 1 in ``Admission.sample`` (``SKF_AD_RANDOM``), as the endpoint's own rate limiter would
have dropped most of them a few microseconds later.

*Counted.*  Linux counts a datagram its filter refused in the socket's drops (``SO_MEMINFO``'s
``SK_MEMINFO_DROPS``, ``/proc/net/udp``), with those a full buffer dropped: ``kernel_drops`` in
``ROLE.json``'s ``received`` is both.

Offsets (checked by ``tests/test_sockfilter.py`` on real sockets): a UDP socket's filter sees the
datagram from its UDP header (source port at 0, payload at 8) and the IP header at ``SKF_NET_OFF``.
Only IPv4 peers are matched by address; on another family, or a peer that is not an IPv4 literal,
the filter bounds the length alone.
"""

from __future__ import annotations

import ctypes
import socket
import struct
import sys
from typing import NamedTuple

from teleop.session import auth
from teleop.session.admission import Admission, Strangers

SO_ATTACH_FILTER = 26
SO_DETACH_FILTER = 27
UDP_HEADER = 8
ACCEPT = 0xFFFF_FFFF  # keep the whole datagram
DROP = 0

# Classic BPF opcodes (linux/filter.h, linux/bpf_common.h).
_LD, _ALU, _JMP, _RET = 0x00, 0x04, 0x05, 0x06
_W, _H = 0x00, 0x08
_ABS, _LEN = 0x20, 0x80
_JEQ, _JGT = 0x10, 0x20
_AND = 0x50
_K = 0x00
_SKF_AD_OFF = -0x1000
_SKF_AD_RANDOM = 56
_SKF_NET_OFF = -0x100000
_IPV4_SRC = 12  # the source address's offset in the IPv4 header

# A handshake envelope's first two bytes (auth: b"T", then flags: version << 4 | kind << 1 | direction,
# bits 2-3 reserved zero, kind 0 for the handshake key), direction masked off.
_HANDSHAKE_MAGIC = (ord(auth.MAGIC) << 8) | (auth.ENVELOPE_VERSION << 4)
_HANDSHAKE_MASK = 0xFFFE


class Insn(NamedTuple):
    """One ``struct sock_filter``: opcode, jump-if-true, jump-if-false (relative), constant."""

    code: int
    jt: int
    jf: int
    k: int


def _ipv4(host: str) -> int | None:
    try:
        packed = socket.inet_pton(socket.AF_INET, host)
    except (OSError, ValueError):
        return None
    return int.from_bytes(packed, "big")


def compile_filter(adm: Admission, family: int = socket.AF_INET) -> list[Insn]:
    """The program for ``adm`` on a socket of ``family`` (see the module docstring)."""
    # Built with symbolic targets ("drop", "accept", "stranger"), resolved to relative jumps below.
    prog: list[tuple[int, int | str, int | str, int]] = []

    def op(code: int, k: int = 0, jt: int | str = 0, jf: int | str = 0) -> None:
        prog.append((code, jt, jf, k & 0xFFFF_FFFF))

    op(_LD | _W | _LEN)  # A = UDP header + payload
    op(_JMP | _JGT | _K, UDP_HEADER + adm.max_bytes, "drop", 0)
    peer = adm.peer
    ip = _ipv4(peer[0]) if peer is not None and family == socket.AF_INET else None
    if peer is not None and ip is not None and adm.strangers != Strangers.ALL:
        op(_LD | _W | _ABS, _SKF_NET_OFF + _IPV4_SRC)
        op(_JMP | _JEQ | _K, ip, 0, "stranger")
        op(_LD | _H | _ABS, 0)  # the source port
        op(_JMP | _JEQ | _K, peer[1], "accept", "stranger")
        prog.append((-1, "stranger", 0, 0))  # label
        if adm.strangers == Strangers.HANDSHAKE:
            op(_LD | _W | _LEN)
            op(_JMP | _JGT | _K, UDP_HEADER + adm.max_handshake_bytes, "drop", 0)
            op(_LD | _H | _ABS, UDP_HEADER)  # magic and flags
            op(_ALU | _AND | _K, _HANDSHAKE_MASK)
            op(_JMP | _JEQ | _K, _HANDSHAKE_MAGIC, 0, "drop")
            if adm.sample > 1:
                if adm.sample & (adm.sample - 1):
                    raise ValueError(f"sample must be a power of two, got {adm.sample}")
                op(_LD | _W | _ABS, _SKF_AD_OFF + _SKF_AD_RANDOM)
                op(_ALU | _AND | _K, adm.sample - 1)
                op(_JMP | _JEQ | _K, 0, "accept", "drop")
            else:
                prog.append((_JMP, "accept", 0, 0))  # BPF_JA
        else:
            prog.append((_JMP, "drop", 0, 0))
    prog.append((-1, "accept", 0, 0))
    op(_RET | _K, ACCEPT)
    prog.append((-1, "drop", 0, 0))
    op(_RET | _K, DROP)
    return _resolve(prog)


def _resolve(prog: list[tuple[int, int | str, int | str, int]]) -> list[Insn]:
    """Labels (code -1) out, symbolic jumps to relative offsets; an unconditional jump's target goes
    in ``k`` (``BPF_JA``), a conditional's in ``jt``/``jf`` (at most 255 ahead)."""
    where: dict[str, int] = {}
    n = 0
    for code, name, _, _ in prog:
        if code == -1:
            assert isinstance(name, str)
            where[name] = n
        else:
            n += 1
    out: list[Insn] = []
    for code, jt, jf, k in prog:
        if code == -1:
            continue
        i = len(out)
        tr, fr = (_rel(t, where, i) for t in (jt, jf))
        out.append(Insn(code, 0, 0, tr) if code == _JMP else Insn(code, tr, fr, k))  # BPF_JA: offset in k
    return out


def _rel(t: int | str, where: dict[str, int], i: int) -> int:
    if isinstance(t, int):
        return t
    off = where[t] - i - 1
    if not 0 <= off <= 255:
        raise ValueError(f"jump to {t!r} out of range ({off})")
    return off


def attach(sock: socket.socket, prog: list[Insn]) -> None:
    """Install ``prog`` on ``sock`` (replacing any filter); OSError where not supported."""
    if sys.platform != "linux":
        raise OSError("socket filters are Linux's (SO_ATTACH_FILTER)")
    code = b"".join(struct.pack("HBBI", *ins) for ins in prog)
    buf = ctypes.create_string_buffer(code, len(code))
    fprog = struct.pack("HL", len(prog), ctypes.addressof(buf))  # struct sock_fprog
    sock.setsockopt(socket.SOL_SOCKET, SO_ATTACH_FILTER, fprog)


def detach(sock: socket.socket) -> None:
    sock.setsockopt(socket.SOL_SOCKET, SO_DETACH_FILTER, 0)
