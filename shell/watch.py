"""What the runner shows of a running port: the log's low-rate channels and the console status line.

A few integer comparisons a tick; the messages are queued by the log (``shell.mcaplog``), never
written from the loop.
"""

from __future__ import annotations

import math
import sys
from typing import Any

from teleop.session.link.phase import PHASE_MARGIN_S
from teleop.session.port import Port
from teleop.session.schedule import LoopFigures

from .mcaplog import McapLog

__all__ = ["LogWatch", "Watch", "live_messages", "status_line"]


class LogWatch:
    """Events as they happen (a peer's new energy epoch, refused and replayed datagrams, overruns),
    the live view's decimated ticks, and the link figures once a second."""

    def __init__(self) -> None:
        self._watched: tuple[int, ...] = ()

    def tick(self, log: McapLog, port: Port, k: int, t: float, overruns: int, skipped: int = 0) -> None:
        """``skipped``: ticks the loop skipped so far (a stall): said as a ``stall`` event, so that
        a hole in a log's ticks is explained in the log (a dropped chunk is ``log_dropped``)."""
        node, sec = port.node, port.security
        watched = (node.peer_restarts, sec.rejected, sec.replayed, overruns, skipped)
        if watched != self._watched:
            if self._watched:
                old = self._watched
                if watched[0] != old[0]:
                    log.event(t, "peer_restarted", f"energy epoch {watched[0]}")
                if watched[1] != old[1]:
                    log.event(t, "auth_rejected", f"{watched[1]} so far: {sec.last_rejection}")
                if watched[2] != old[2]:
                    log.event(t, "replayed", f"{watched[2]} so far")
                # The loop's figures start again when a session (re)starts: a count that went down
                # is a new baseline, not an event (a CI log read "-106 ticks skipped").
                if watched[3] > old[3]:
                    log.event(t, "overrun", f"tick {k}: {overruns} so far")
                if watched[4] > old[4]:
                    log.event(t, "stall", f"tick {k}: {watched[4] - old[4]} ticks skipped before it")
            self._watched = watched
        if k % log.live_every == 0 and log.wants_live:
            log.live(k, t, live_messages(port, k, t))
        if k % 1000 == 999:
            pv = node.passivity
            link = {"link": port.observer.quick(), "sent": port.tx.summary(), "received": port.rx.summary()}
            watchdog = {
                "violations": pv.violations,
                "controller_active_ticks": pv.controller_active_ticks,
                "energy_dissipated": pv.energy_dissipated,
                "margin": node.guard.margin,
                "link_lost": node.link_lost,
            }
            log.status("link", t, {"t": t, **link, "watchdog": watchdog})


#: Columns a status line keeps within (a terminal's 120): ``--wide`` prints everything.
STATUS_COLUMNS = 120


def status_line(
    role: str,
    port: Port,
    k: int,
    overruns: int,
    insecure: bool,
    rtt_ns: int | None = None,
    wide: bool = False,
) -> str:
    """``--live``'s line, once a second: traffic, link, watchdog, latency.

    Latency: the incoming direction's sent -> played so far (the sender's tick to the tick that
    released the payload here; the teleoperator's phase is added on its side, where it is known),
    the incoming link's transit, and on the operator the handshake's round trip and its floor
    (``rtt_ns``).  One side sees one direction: the round trip is the report's.  Within
    :data:`STATUS_COLUMNS` unless ``wide``: the watchdog as ``violations/controller ticks``, the
    latency as p50/p99, and what does not fit left to ``--wide`` and the report."""
    node = port.node
    pv = node.passivity
    link = "LINK LOST" if node.link_lost else "link ok"
    warn = ("  INSECURE (no key)" if wide else "  INSECURE") if insecure else ""
    if wide:
        return (
            f"  [{role} {(k + 1) * port.dt:5.1f} s] sent {port.tx.packets} "
            f"recv {port.rx.packets}  {link}  watchdog: "
            f"violations {pv.violations}, controller {pv.controller_active_ticks} ticks, "
            f"margin {node.guard.margin:.3e} J, overruns {overruns}{_latency(port, rtt_ns)}{warn}"
        )
    head = (
        f"  [{role} {(k + 1) * port.dt:5.1f} s] tx {port.tx.packets} rx {port.rx.packets}  {link}  "
        f"watchdog {pv.violations}/{pv.controller_active_ticks} margin {node.guard.margin:.1e} J  "
        f"overruns {overruns}"
    )
    d = port.playout.delay_ms()
    if d["p50"] is not None and d["p99"] is not None:
        shift = port.clock.phase * port.dt * 1e3
        lat = f"  latency {d['p50'] + shift:.1f}/{d['p99'] + shift:.1f} ms"
        if len(head) + len(lat) + len(warn) <= STATUS_COLUMNS:
            head += lat
    return head + warn


def _latency(port: Port, rtt_ns: int | None) -> str:
    d = port.playout.delay_ms()
    if d["p50"] is None:
        return ""
    assert d["p99"] is not None and d["max"] is not None
    shift = port.clock.phase * port.dt * 1e3  # the teleoperator plays at its phase (0 at the operator)
    text = f"  latency in {d['p50'] + shift:.1f}/{d['p99'] + shift:.1f}/{d['max'] + shift:.1f} ms p50/p99/max"
    transit = port.clock.summary()["transit_ms"]["p50"]
    if transit is not None:
        text += f", link in {max(transit, 0.0):.2f} ms"
    if rtt_ns is not None:
        # The handshake's: its floor is the session's on a plain link; an in-process --netem shim
        # delays data only (the report's round trip and floor are measured in session, both ways).
        ms = port.dt * 1e3
        floor = max(1, math.ceil((rtt_ns / 1e6 + PHASE_MARGIN_S * 1e3) / ms - 1e-6)) * ms
        text += f", handshake round trip {rtt_ns / 1e6:.2f} ms (floor {floor:g} ms)"
    return text


def live_messages(port: Port, k: int, t: float) -> dict[str, dict[str, Any]]:
    """This tick's per-tick messages, built from the node (the record's chunk is not sealed yet)."""
    node = port.node
    return {
        "signals": {"k": k, "t": t, "v": node.v.tolist(), "f": node.f.tolist()},
        "waves": {"k": k, "t": t, "wave_out": node.wave_out.tolist(), "wave_in": node.wave_in.tolist()},
        "energy": {
            "k": k,
            "t": t,
            "sent": node.energy_sent,
            "played": node.energy_played,
            "margin_observed": node.guard.margin,
            "played_epoch": node.guard.played_in_epoch,
            "peer_epoch": node.peer_restarts,
        },
    }


class Watch:
    """The endpoint's monitor in a real process (``Endpoint(monitor=...)``), after each tick's
    datagrams left: the log's events and live view (:class:`LogWatch`) and ``--live``'s status line
    once a second of the session clock (``k`` may jump: a stall, a device that missed deadlines)."""

    def __init__(self, role: str, live: bool, insecure: bool, wide: bool = False) -> None:
        self.role, self.live, self.insecure, self.wide = role, live, insecure, wide
        self.log: McapLog | None = None  # the running session's (None: no log, no live view)
        self.rtt_ns: int | None = None  # operator: the handshake's round trip (the status line's floor)
        self.device: Any = None  # a device that paces the session adds its own figures
        self.watch = LogWatch()
        self._next_status = 999

    def start(self, log: McapLog | None, k0: int, rtt_ns: int | None, device: Any) -> None:
        self.log, self.rtt_ns, self.device = log, rtt_ns, device
        self.watch = LogWatch()  # a new session's log: its events count from its own start
        self._next_status = k0 - k0 % 1000 + 999

    def __call__(self, port: Port, k: int, t: float, loop: LoopFigures) -> None:
        if self.log is not None:
            self.watch.tick(self.log, port, k, t, loop.overruns, loop.skipped)
        if self.live and k >= self._next_status:
            self._next_status = ((k - 999) // 1000 + 1) * 1000 + 999
            line = status_line(self.role, port, k, loop.overruns, self.insecure, self.rtt_ns, self.wide)
            if loop.device_paced:
                status = getattr(self.device, "status", None)
                line += f", missed deadlines {loop.missed}" + (f", {status()}" if callable(status) else "")
            print(line, file=sys.stderr, flush=True)
