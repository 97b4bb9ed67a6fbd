"""Soak: a long session without a fixed end, each process's memory over time, and what the log costs.

Two parts, one invocation:

1. **Log on vs off** (``--ab-rounds`` rounds of ``--ab-seconds`` each, the modes' order rotated
   each round, so a shared VM's load hits all alike): an operator and a teleoperator with no log at
   all (``off``); with ``--log`` only (``log``: ROLE.mcap streamed); with ``--log`` and
   ``--live-view`` and a Foxglove WebSocket client subscribed to every channel (a view nobody
   watches costs nothing, so the bench watches it) running at SCHED_IDLE (``on``: the viewer stands
   in for Foxglove on the user's machine); and the same with the client at normal priority
   (``on_viewer_normal``: what a viewer on the same two cores costs).  Loop figures are each
   process's own (period error percentiles, printed when it exits); the target's ratio is the
   median p99 of ``on`` over that of ``off``.
2. **Soak** (``--minutes``, an hour by default): ``teleop run --duration 0`` until this script sends
   Ctrl-C, sampling each process's resident memory (VmRSS) every ``--sample`` seconds; growth is
   the slope of a straight line fitted to the samples after the first two minutes (warm-up: imports,
   first chunks, the exact-percentile buffers filling for 65 s), in MB per hour.  Loop figures per minute
   come from the processes' own logs (``/ROLE/loop`` in ROLE.mcap).

    python -m bench.soak [--minutes M] [--ab-rounds N] [--ab-seconds S] [--out FILE]

Targets (issue 12): RSS growth under 10 MB per process per hour; loop p99 with MCAP and the live
view on within 1.2x of off, measured in one run.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import platform
import re
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from bench import write_result

TELEOP = [sys.executable, "-m", "teleop.cli"]
ROLES = ("operator", "teleoperator")
# Samples before this are left out of the growth fit: imports, the first chunks, and the loop's
# exact-percentile buffers (teleop.session.link.quantiles: the first 65536 ticks, 65 s) are
# start-up, not growth.
WARM_UP_S = 120.0
_SUMMARY = re.compile(r"period error p50/p99/max ([\d.]+)/([\d.]+)/([\d.]+) us, CPU (\d+)%")


def _free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def _children(pid: int) -> list[int]:
    try:
        return [int(x) for x in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


def _role_of(pid: int) -> str | None:
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return None
    for role in ROLES:
        if role.encode() in cmd:
            return role
    return None


def _processes(run_pid: int) -> dict[str, int]:
    """The run's processes by name: each side, and each side's log writer (``ROLE-writer``)."""
    out: dict[str, int] = {}
    for child in _children(run_pid):
        role = _role_of(child)
        if role is None:
            continue
        out[role] = child
        for grandchild in _children(child):
            with contextlib.suppress(OSError):
                if b"shell.mcaplog" in Path(f"/proc/{grandchild}/cmdline").read_bytes():
                    out[f"{role}-writer"] = grandchild
    return out


# --- part 1: log and live view on vs off --------------------------------------------------------
#: The A/B modes: what each process gets, and whether a viewer watches (and at which priority).
MODES: dict[str, tuple[bool, bool, str | None]] = {
    "off": (False, False, None),  # no log, no view
    "log": (True, False, None),  # ROLE.mcap only
    "on": (True, True, "idle"),  # log and view, a viewer subscribed at SCHED_IDLE (the target)
    "on_viewer_normal": (True, True, "normal"),  # the same viewer at normal priority
}


def _watch(port: int, stop: threading.Event, counts: dict[str, int], idle: bool) -> None:
    """A Foxglove WebSocket client subscribed to every advertised channel until ``stop``.

    ``idle``: this thread runs under SCHED_IDLE.  The viewer stands in for Foxglove on the user's
    own machine; on this bench's two cores it would otherwise take CPU from the loops, which is the
    viewer's cost, not the stack's (measured apart as ``on_viewer_normal``)."""
    import websockets

    if idle:
        with contextlib.suppress(OSError, AttributeError):
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))

    async def run() -> None:
        for _ in range(50):  # the server starts after the handshake: retry
            try:
                ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"])  # type: ignore[list-item]
                break
            except OSError:
                await asyncio.sleep(0.1)
        else:
            return
        async with ws:
            while not stop.is_set():
                try:
                    frame = await asyncio.wait_for(ws.recv(), timeout=0.2)
                except TimeoutError:
                    continue
                except websockets.ConnectionClosed:
                    return
                if isinstance(frame, str):
                    msg = json.loads(frame)
                    if msg.get("op") == "advertise":
                        subs = [{"id": c["id"], "channelId": c["id"]} for c in msg["channels"]]
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                else:
                    counts["messages"] = counts.get("messages", 0) + 1

    asyncio.run(run())


def _session(seconds: float, mode: str, log_dir: Path) -> dict[str, Any]:
    """One fixed-length session of two processes; their own loop figures (from their exit line)."""
    log, view, viewer = MODES[mode]
    port = _free_port(socket.SOCK_DGRAM)
    common = ["--insecure", "--no-rt"]
    views = {"teleoperator": _free_port(), "operator": _free_port()}
    extra = {
        r: [*(["--log", str(log_dir)] if log else []), *(["--live-view", str(views[r])] if view else [])]
        for r in ROLES
    }
    to = subprocess.Popen(
        [*TELEOP, "teleoperator", "--listen", f"127.0.0.1:{port}", *common, *extra["teleoperator"]],
        stderr=subprocess.PIPE,
        text=True,
    )
    time.sleep(0.5)
    op = subprocess.Popen(
        [*TELEOP, "operator", "--peer", f"127.0.0.1:{port}", "--duration", repr(seconds), *common]
        + extra["operator"],
        stderr=subprocess.PIPE,
        text=True,
    )
    stop = threading.Event()
    counts: dict[str, dict[str, int]] = {r: {} for r in ROLES}
    watchers = []
    if viewer is not None:
        for r in ROLES:
            args = (views[r], stop, counts[r], viewer == "idle")
            t = threading.Thread(target=_watch, args=args, daemon=True)
            t.start()
            watchers.append(t)
    errs = {
        "operator": op.communicate(timeout=seconds + 60)[1],
        "teleoperator": to.communicate(timeout=60)[1],
    }
    stop.set()
    for t in watchers:
        t.join(timeout=5)
    out: dict[str, Any] = {}
    for r in ROLES:
        m = _SUMMARY.search(errs[r])
        if m is None:
            raise SystemExit(f"{r} did not report its loop: {errs[r][-500:]}")
        out[r] = {
            "p50_us": float(m[1]),
            "p99_us": float(m[2]),
            "max_us": float(m[3]),
            "cpu_pct": int(m[4]),
            "live_messages_received": counts[r].get("messages", 0),
        }
    return out


def log_on_vs_off(rounds: int, seconds: float) -> dict[str, Any]:
    """``rounds`` rounds of every mode, the order rotated each round (so drifting load hits all)."""
    modes = list(MODES)
    runs: dict[str, list[dict[str, Any]]] = {m: [] for m in modes}
    with tempfile.TemporaryDirectory(prefix="teleop-soak-ab-") as tmp:
        for i in range(rounds):
            for mode in modes[i % len(modes) :] + modes[: i % len(modes)]:
                one = _session(seconds, mode, Path(tmp) / f"{mode}{i}")
                runs[mode].append(one)
                print(
                    f"  round {i + 1} {mode:<16}: p99 operator {one['operator']['p99_us']:7.1f} us, "
                    f"teleoperator {one['teleoperator']['p99_us']:7.1f} us",
                    flush=True,
                )
    res: dict[str, Any] = {"rounds": rounds, "seconds_each": seconds, "modes": _mode_notes(), "runs": runs}
    for r in ROLES:
        med = {m: statistics.median(x[r]["p99_us"] for x in runs[m]) for m in modes}
        off = med["off"]
        res[r] = {
            **{f"p99_us_median_{m}": v for m, v in med.items()},
            **{f"ratio_{m}_off": (v / off if off > 0 else None) for m, v in med.items() if m != "off"},
            **{f"cpu_pct_median_{m}": statistics.median(x[r]["cpu_pct"] for x in runs[m]) for m in modes},
            "target_within_1.2x": med["on"] <= 1.2 * off,
        }
    return res


def _mode_notes() -> dict[str, str]:
    return {
        "off": "no log, no live view",
        "log": "--log (ROLE.mcap streamed by the writer process)",
        "on": "--log and --live-view, a WebSocket viewer subscribed to every channel, at SCHED_IDLE "
        "(the target's comparison: the viewer is normally on the user's own machine)",
        "on_viewer_normal": "the same, the viewer at normal priority on the same two cores",
    }


# --- part 2: the soak -----------------------------------------------------------------------------
def _loop_per_minute(mcap: Path) -> list[dict[str, float]]:
    """Per minute of the session: p50, p99 and max lateness (us) of the ticks run, from the log
    (streamed a block of ticks at a time; 8 bytes a tick kept)."""
    from shell.mcaplog import iter_ticks

    by_min: dict[int, list[npt.NDArray[np.int64]]] = {}
    for _, b in iter_ticks(mcap, ("loop",)):
        minute, late = (b["play_time_s"][b["ran"]] // 60).astype(np.int64), b["lateness_ns"][b["ran"]]
        for m in np.unique(minute).tolist():
            by_min.setdefault(m, []).append(late[minute == m])
    out = []
    for m in sorted(by_min):
        a = np.abs(np.concatenate(by_min[m]).astype(np.float64)) / 1e3
        p50, p99 = np.percentile(a, [50, 99])
        out.append(
            {
                "minute": m,
                "ticks": int(a.size),
                "p50_us": float(p50),
                "p99_us": float(p99),
                "max_us": float(a.max()),
            }
        )
    return out


def _growth(samples: list[tuple[float, float]]) -> dict[str, Any]:
    """RSS figures of one process: first, last, and the slope after the warm-up, MB per hour."""
    if not samples:
        return {"rss_samples": []}
    s = np.asarray(samples)
    warm = s[s[:, 0] >= WARM_UP_S] if (s[:, 0] >= WARM_UP_S).sum() >= 3 else s
    slope = float(np.polyfit(warm[:, 0], warm[:, 1], 1)[0]) if len(warm) >= 2 else float("nan")
    return {
        "rss_mb_first": float(s[0, 1]),
        "rss_mb_after_warm_up": float(warm[0, 1]),
        "rss_mb_last": float(s[-1, 1]),
        "rss_growth_mb_whole_run": float(s[-1, 1] - s[0, 1]),
        "rss_growth_mb_per_hour": slope * 3600,
        "target_under_10_mb_per_hour": slope * 3600 < 10,
        "rss_samples": [[round(t, 1), round(m, 2)] for t, m in s.tolist()],
    }


def soak(minutes: float, sample_s: float, out_dir: Path, link_timeout_ms: float) -> dict[str, Any]:
    """``teleop run --duration 0`` for ``minutes``.  ``link_timeout_ms``: long, so that a host stall
    of some 100 ms on a busy VM does not end in the restart logic (a rejoin offer the teleoperator
    takes as a new operator: a new session, its log split) in a run that measures memory."""
    run = subprocess.Popen(
        [
            *TELEOP,
            *("run", "--duration", "0", "--out", str(out_dir), "--no-plots", "--no-sim", "--no-live"),
            *("--link-timeout", repr(link_timeout_ms)),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    t0 = time.monotonic()
    names = [n for r in ROLES for n in (r, f"{r}-writer")]
    samples: dict[str, list[tuple[float, float]]] = {n: [] for n in names}
    pids: dict[str, int] = {}
    try:
        while (elapsed := time.monotonic() - t0) < minutes * 60:
            if run.poll() is not None:
                raise SystemExit(f"teleop run ended early: {run.communicate()[1][-1000:]}")
            pids.update(_processes(run.pid))
            for role, pid in pids.items():
                rss = _rss_mb(pid)
                if rss is not None:
                    samples[role].append((elapsed, rss))
            time.sleep(sample_s)
    finally:
        os.killpg(run.pid, signal.SIGINT)  # Ctrl-C: the session's end
        # Said now, not only in the results: the report that follows reads both logs (about 3 s a
        # minute of session since it streams; before, an hour's report took over 10 minutes).
        for name, got in samples.items():
            g = _growth(got)
            if got:
                print(
                    f"{name:<20} RSS {g['rss_mb_first']:.1f} -> {g['rss_mb_last']:.1f} MB, growth after "
                    f"warm-up {g['rss_growth_mb_per_hour']:+.2f} MB/h ({len(got)} samples)",
                    flush=True,
                )
    _, err = run.communicate(timeout=600 + 60 * minutes)  # generous: the report takes ~3 s a minute
    if run.returncode not in (0, 3):  # 3: a poor session (teleop.session.verdict): it ran, measured
        raise SystemExit(f"teleop run failed ({run.returncode}): {err[-2000:]}")
    rep = json.loads((out_dir / "report.json").read_text())
    res: dict[str, Any] = {
        "minutes": minutes,
        "sample_s": sample_s,
        "session_s": rep["duration_s"],
        "link_timeout_ms": link_timeout_ms,
        # A teleoperator session replaced mid-run (the restart logic) keeps its log as ROLE-<id>.*
        "teleoperator_sessions_replaced": len(list((out_dir / "logs").glob("teleoperator-*.json"))),
    }
    for name in names:
        res[name] = _growth(samples[name])
    for role in ROLES:
        loop = rep["processes"][role]["loop"]
        mcap = out_dir / "logs" / f"{role}.mcap"
        res[role].update(
            {
                "loop": {
                    k: loop[k]
                    for k in (
                        "ticks",
                        "overruns",
                        "skipped",
                        "period_error_us",
                        "lateness_us",
                        "cpu_fraction",
                    )
                },
                "loop_per_minute": _loop_per_minute(mcap),
                "mcap_bytes": mcap.stat().st_size,
                "mcap_bytes_per_tick": mcap.stat().st_size / max(1, loop["ticks"]),
            }
        )
    res["wire"] = {
        d: {k: rep["wire"][d][k] for k in ("packets", "compression_wire", "min_instant_compression_wire")}
        for d in rep["wire"]
    }
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=60.0, help="soak length (default 60; 0: skip)")
    ap.add_argument("--sample", type=float, default=10.0, help="seconds between RSS samples (default 10)")
    ap.add_argument("--ab-rounds", type=int, default=4, help="log on/off rounds (default 4; 0: skip)")
    ap.add_argument("--ab-seconds", type=float, default=20.0, help="seconds per on/off session (default 20)")
    ap.add_argument(
        "--link-timeout", type=float, default=1000.0, help="soak's link timeout, ms (default 1000)"
    )
    ap.add_argument("--out", default="bench/results/soak.json")
    a = ap.parse_args()
    res: dict[str, Any] = {
        "what": "memory and loop timing of a long session without a fixed end; the log's cost on the loop",
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "note": "shared VM (2 cores, other work running): loop figures are noisy; compare within this run",
    }
    if a.ab_rounds > 0:
        print(f"log and live view on vs off: {a.ab_rounds} rounds of {a.ab_seconds:g} s each", flush=True)
        res["log_on_vs_off"] = log_on_vs_off(a.ab_rounds, a.ab_seconds)
    if a.minutes > 0:
        print(f"soak: teleop run --duration 0 for {a.minutes:g} min, RSS every {a.sample:g} s", flush=True)
        with tempfile.TemporaryDirectory(prefix="teleop-soak-") as tmp:
            res["soak"] = soak(a.minutes, a.sample, Path(tmp) / "run", a.link_timeout)
    out = Path(a.out)
    if out.exists():  # a part not run this time keeps its last result, marked as such
        old = json.loads(out.read_text())
        for part in ("log_on_vs_off", "soak"):
            if part not in res and part in old:
                res[part] = {**old[part], "from_an_earlier_invocation": True}
    out.parent.mkdir(parents=True, exist_ok=True)
    write_result(out, res)
    for role in ROLES if "soak" in res else ():
        w = res["soak"].get(f"{role}-writer", {})
        if w.get("rss_samples"):
            print(
                f"{role + '-writer':<13} RSS {w['rss_mb_first']:.1f} -> {w['rss_mb_last']:.1f} MB, "
                f"growth after warm-up {w['rss_growth_mb_per_hour']:+.2f} MB/h"
            )
        s = res["soak"][role]
        print(
            f"{role:<13} RSS {s['rss_mb_first']:.1f} -> {s['rss_mb_last']:.1f} MB, growth after warm-up "
            f"{s['rss_growth_mb_per_hour']:+.2f} MB/h; "
            f"loop p99 {s['loop']['period_error_us']['p99']:.1f} us; "
            f"MCAP {s['mcap_bytes'] / 1e6:.1f} MB ({s['mcap_bytes_per_tick']:.0f} B/tick)"
        )
    for role in ROLES if "log_on_vs_off" in res else ():
        x = res["log_on_vs_off"][role]
        print(
            f"{role:<13} p99 medians: off {x['p99_us_median_off']:.1f} us, log "
            f"{x['p99_us_median_log']:.1f} us, log and view {x['p99_us_median_on']:.1f} us "
            f"({x['ratio_on_off']:.2f}x off), viewer at normal priority "
            f"{x['p99_us_median_on_viewer_normal']:.1f} us"
        )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
