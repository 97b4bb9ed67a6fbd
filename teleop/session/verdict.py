"""Whether a session's figures can be trusted: the verdict line every session command ends with, and
its exit status (issue 48: a Franka session on a loaded host lost its link 8 times, its watchdog
flagged 2571 ticks and its loop missed 3486 deadlines, and the operator still exited 0).

A session is *poor* when, on either side, the link was lost, the watchdog flagged or the passivity
controller acted on more than a share of the ticks, or the loop skipped or missed more than a share
of its deadlines; with both logs (``teleop run``, ``teleop report``) also when the real transparency
``I`` (eq. 7) is more than a factor away from ``teleop sim``'s with the same settings.  A poor
session is no failure: it ran and its records are whole, so it exits :data:`POOR_EXIT` (3), apart
from failures (1) and interruptions (130), and a script that impairs a link on purpose accepts 3 or
widens the bounds (``--poor-share``, ``--poor-i-factor``).

Pure functions of the summaries (``ROLE.json``, ``report.json``): no clock, no file.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

__all__ = ["POOR_EXIT", "Bounds", "Verdict", "judge_process", "judge_report"]

POOR_EXIT = 3  # the session ran and was recorded, but its figures are not to be trusted as they are


@dataclass(frozen=True)
class Bounds:
    """What a session may show and still be ok.  ``share``: of the session's ticks, those the
    watchdog flagged, the passivity controller acted on, or the loop skipped or missed (each
    counted alone); ``i_factor``: real I against the sim's, either way."""

    share: float = 0.01
    i_factor: float = 2.0


@dataclass(frozen=True)
class Verdict:
    """``poor``: why the session is poor, one reason each (empty: ok); ``checked``: what was judged
    (an ok line says it, so an ok from one log is never read as one from both)."""

    poor: list[str] = field(default_factory=list)
    checked: list[str] = field(default_factory=list)

    @property
    def exit_status(self) -> int:
        return POOR_EXIT if self.poor else 0

    def line(self, who: str) -> str:
        """The command's last line: ``teleop run: verdict: ok`` or ``...: verdict: poor (exit 3): ...``."""
        if not self.poor:
            return f"{who}: verdict: ok ({', '.join(self.checked) or 'nothing to judge'})"
        return f"{who}: verdict: poor (exit {POOR_EXIT}): " + "; ".join(self.poor)


def _pct(x: float) -> str:
    return f"{100 * x:.3g}%"


def _side(role: str, passivity: dict[str, Any], loop: dict[str, Any] | None, bounds: Bounds) -> list[str]:
    """One process's reasons, from its watchdog's counters and its loop's."""
    out: list[str] = []
    if loop is None:  # a process that ran no loop (sim, a log written by a test): nothing to judge
        return out
    ticks = int(loop.get("ticks", 0)) + int(loop.get("skipped", 0)) + int(loop.get("missed_deadlines", 0))
    lost = int(passivity.get("link_lost_events", 0))
    if lost:
        n = int(passivity.get("link_lost_ticks", 0))
        out.append(f"{role}: the link was lost {lost} time{'s' if lost != 1 else ''} ({n} ticks)")
    if ticks <= 0:
        return out
    flagged, acted = int(passivity.get("violations", 0)), int(passivity.get("controller_active_ticks", 0))
    if max(flagged, acted) > bounds.share * ticks:
        out.append(
            f"{role}: the watchdog flagged {_pct(max(flagged, acted) / ticks)} of ticks ({flagged} "
            f"violations, controller active {acted}; bound {_pct(bounds.share)})"
        )
    late = int(loop.get("skipped", 0)) + int(loop.get("missed_deadlines", 0))
    if late > bounds.share * ticks:
        out.append(
            f"{role}: the loop skipped or missed {_pct(late / ticks)} of its deadlines "
            f"({late} of {ticks}; bound {_pct(bounds.share)}): a loaded host, see teleop doctor"
        )
    return out


def judge_process(doc: dict[str, Any], bounds: Bounds) -> Verdict:
    """One process's verdict from its ``ROLE.json`` map (``SessionSummary.document()``)."""
    loop = doc.get("loop")
    checked = ["link kept", "watchdog", "loop deadlines"] if loop is not None else []
    return Verdict(_side(str(doc.get("role", "?")), doc.get("passivity") or {}, loop, bounds), checked)


def judge_report(rep: dict[str, Any], bounds: Bounds) -> Verdict:
    """A session's verdict from its report: both sides, and the real I against the sim's."""
    out: list[str] = []
    checked = ["link kept", "watchdog", "loop deadlines", "both sides"]
    passivity = rep.get("passivity") or {}
    for role, direction in (("operator", "backward"), ("teleoperator", "forward")):
        # Each side's watchdog guards what it receives: the operator the backward wave.
        proc = (rep.get("processes") or {}).get(role) or {}
        out += _side(role, passivity.get(direction) or {}, proc.get("loop"), bounds)
    tr = rep.get("transparency") or {}
    # Over the span the sim ran (a session cut short by Ctrl-C is compared over its own length).
    real, sim = tr.get("I_over_sim_s", tr.get("I")), tr.get("I_sim")
    if isinstance(real, (int, float)) and isinstance(sim, (int, float)) and real > 0 and sim > 0:
        factor = max(real / sim, sim / real)
        checked.append(f"I within {bounds.i_factor:g}x of the sim")
        if factor > bounds.i_factor:
            out.append(
                f"transparency I = {real:.4g} is {factor:.4g}x off teleop sim's {sim:.4g} with the same "
                f"settings (bound {bounds.i_factor:g}x)"
            )
    return Verdict(out, checked)
