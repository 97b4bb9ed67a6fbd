"""``teleop export --to lerobot``: sessions' logs as one LeRobot v3.0 dataset, at the loop's full rate.

Why: a teleoperated session is a demonstration, and LeRobot is where robot learning reads them.
Each session (its operator's and teleoperator's logs, paired as ``teleop report`` pairs them) is an
episode; its frames come at ``fps`` (50 by default) and carry the 1 kHz signals as **windows** of
``1000 / fps`` samples per feature, e.g. ``observation.robot.force`` of shape ``[20, dof]``: nothing
is resampled, and every logged sample is in the dataset once (:func:`ticks_of` rebuilds them).

Every feature but the flags is float64, the log's own type, so the round trip is exact to the bit
(tests/test_lerobot_export.py).  The layout is LeRobot's own v3.0 (``meta/info.json``,
``meta/stats.json``, ``meta/tasks.parquet``, ``meta/episodes/...``, ``data/chunk-.../file-....parquet``),
written with pyarrow, and read by LeRobot's ``LeRobotDataset`` as is.

What each feature is, and why, is :data:`FEATURES`; docs/guides/demonstrations.md says how to drop one.
The logs are read as :mod:`teleop.offline.logfile` reads them (hostile files: bounded, one
:class:`LogError`); an episode is held in memory while it is written (the 60 s MuJoCo session's
export peaked at 0.37 GB, measured), so one is at most :data:`MAX_EPISODE_TICKS` long.
"""

from __future__ import annotations

import json
import math
import os
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from teleop.errors import LocalError
from teleop.offline.logfile import (
    MAX_LOGS,
    LogError,
    checked_params,
    find_pair,
    log_session,
    read_columns,
    read_states,
)

__all__ = ["FEATURES", "Episode", "ExportError", "export", "read_episode", "read_episodes", "ticks_of"]

CODEBASE_VERSION = "v3.0"
CHUNKS_SIZE = 1000  # files a chunk folder holds (LeRobot's default)
DATA_FILES_SIZE_IN_MB = 100  # a data file is closed once it holds about this much (LeRobot's default)
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
DEFAULT_FPS = 50
MAX_EPISODE_TICKS = 600_000  # ten minutes at 1 kHz: about 3 GB held while it is written
MAX_TASK_CHARS = 1000
#: A log an export reads at most (checked by size before it is read): ten minutes of session at
#: 2 DoF are about 140 MB (the 60 s MuJoCo session's logs: 13.9 MB each, measured).
MAX_LOG_BYTES = 1 << 30
QUANTILES = (0.01, 0.10, 0.50, 0.90, 0.99)  # the quantiles LeRobot's stats carry (q01 ... q99)

#: The per-tick columns read from each log (and nothing else: the export reads what it writes).
_TOPICS = ("signals", "energy", "wire")
_COLUMNS = ("v", "f", "play_time_s", "energy_margin_observed", "controller_ticks", "tx_seq", "rx_seq",
            "send_time_s")  # fmt: skip


class ExportError(LocalError):
    """Sessions that cannot make a dataset (too short, unlike each other), or an output refused."""


@dataclass(frozen=True)
class Feature:
    """A dataset feature: where each sample comes from, its type, unit, and why it is there."""

    name: str
    dtype: str
    unit: str
    why: str
    per: str = "dof"  # a sample's shape: "dof" (one value per DoF), "one", or "state" (the device's)


#: The dataset's features besides LeRobot's own (timestamp, frame_index, episode_index, index,
#: task_index).  "operator" is the operator's process (its hand), "robot" the teleoperator's.
FEATURES: tuple[Feature, ...] = (
    Feature("action", "float64", "m/s", "the operator's velocity command as the robot received it "
            "(after the channel: delay, codec, watchdog): what a policy replaces"),
    Feature("observation.operator.velocity", "float64", "m/s", "the operator's hand velocity, as "
            "sent: the intent before the channel"),
    Feature("observation.operator.force", "float64", "N", "the force rendered to the operator's hand: "
            "what the operator felt"),
    Feature("observation.robot.force", "float64", "N", "the robot's measured contact force"),
    Feature("observation.robot.state", "float64", "", "the robot's own state at its own rate (a Franka: "
            "pose, q, dq, tau, set-point; MuJoCo: pose, position): names say which", per="state"),
    Feature("observation.time", "float64", "s", "when each sample's tick ran on the session clock: "
            "the real loop's timing, late ticks included", per="one"),
    Feature("observation.channel.forward_sent", "uint8", "", "1 where the operator sent a packet "
            "this tick: a codec sends some ticks only", per="one"),
    Feature("observation.channel.backward_sent", "uint8", "", "1 where the robot sent a packet this "
            "tick", per="one"),
    Feature("observation.channel.forward_margin", "float64", "J", "the robot's watchdog margin on the "
            "forward wave (reported in minus played): how close the channel was to active", per="one"),
    Feature("observation.channel.backward_margin", "float64", "J", "the operator's watchdog margin on "
            "the backward wave", per="one"),
    Feature("observation.channel.forward_controller", "int8", "", "1 where the robot's passivity "
            "controller acted on the forward wave (cut the command), 0 not, -1 unknown (an older "
            "log)", per="one"),
    Feature("observation.channel.backward_controller", "int8", "", "1 where the operator's controller "
            "acted on the backward wave, 0 not, -1 unknown", per="one"),
    Feature("observation.channel.forward_delay", "float64", "s", "the newest command's delay: from "
            "the operator's send to the robot's tick that first played it (NaN: none yet)", per="one"),
    Feature("observation.channel.backward_delay", "float64", "s", "the newest force's delay, robot "
            "to operator", per="one"),
)  # fmt: skip


@dataclass
class Episode:
    """One session's ticks both sides ran, cut to whole frames: per-tick arrays by feature."""

    name: str  # the log folder, for messages
    session: int
    dt: float
    dof: int
    first_tick: int  # the session tick of the episode's first sample
    ticks: dict[str, npt.NDArray[Any]]  # by feature name: (n, dof), (n,) or, the state, (n // every, m)
    state_names: list[str] = field(default_factory=list)
    state_every: int = 0
    robot: str = ""
    scenario: str = ""
    notes: list[str] = field(default_factory=list)


def _side(
    path: Path, max_tick: int, extra: dict[str, list[bytes]] | None = None
) -> dict[str, npt.NDArray[Any]]:
    """The columns the export needs of one log, from tick 0, and ``ran``."""
    got = read_columns(path, _TOPICS, max_tick, extra, names=_COLUMNS)
    if not got["ran"].size:
        raise LogError(f"{path}: no tick in the log")
    return {c: got[c] for c in (*_COLUMNS, "ran")}


def _acted(ct: npt.NDArray[np.int64]) -> npt.NDArray[np.int8]:
    """Per tick: whether the controller acted (its cumulative count rose), -1 where unknown."""
    known = np.maximum.accumulate(np.concatenate([[0], ct[:-1]]))  # the count before, carried over gaps
    out = (ct > known).astype(np.int8)
    out[ct < 0] = -1
    return out


def _delay(
    rx_seq: npt.NDArray[np.int64],
    play_time: npt.NDArray[np.float64],
    tx_seq: npt.NDArray[np.int64],
    send_time: npt.NDArray[np.float64],
) -> npt.NDArray[np.float64]:
    """Per receiver tick: the newest accepted packet's delay, from its sender's send to the
    receiver's tick that first took it (both on the session clock), held until the next."""
    n = rx_seq.size
    # The newest seq before each tick, carried over ticks not run (their rx_seq is -1: no value).
    valid = rx_seq >= 0
    last = rx_seq[np.maximum.accumulate(np.where(valid, np.arange(n), 0))] if n else rx_seq
    last = np.where(np.maximum.accumulate(valid), last, -1)
    prev = np.concatenate([[-1], last[:-1]])
    new = np.flatnonzero(valid & (rx_seq != prev))
    sent = np.flatnonzero(tx_seq >= 0)
    seqs = tx_seq[sent]
    order = np.argsort(seqs, kind="stable")
    seqs, sent = seqs[order], sent[order]
    at = np.minimum(np.searchsorted(seqs, rx_seq[new]), max(seqs.size - 1, 0))
    found = (seqs[at] == rx_seq[new]) if seqs.size else np.zeros(new.size, dtype=bool)
    d = np.full(new.size, math.nan)
    d[found] = play_time[new[found]] - send_time[sent[at[found]]]
    out = np.full(n, math.nan)
    if new.size:
        idx = np.zeros(n, dtype=np.int64)  # the index into ``new`` of the newest change at each tick
        idx[new] = np.arange(new.size)
        idx = np.maximum.accumulate(idx)
        held = np.arange(n) >= new[0]
        out[held] = d[idx[held]]
    return out


def read_episodes(log_dir: Path, fps: int, session: int | None = None) -> list[Episode]:
    """The episodes of one session in ``log_dir`` (its newest with both logs, or ``session``),
    paired as ``teleop report`` pairs its logs (``find_pair``), in the order they ran: the session,
    and, where a process was killed and restarted into it (a rejoin), each earlier segment too: the
    killed process's log beside the other role's, over the ticks both ran."""
    seen: dict[Path, tuple[int, dict[str, Any], dict[str, Any]]] = {}  # what find_pair read of each log
    op_path, to_path, notes = find_pair(log_dir, session, seen)
    episodes = [read_episode(log_dir, fps, pair=(op_path, to_path), notes=notes, seen=seen)]
    sid = episodes[0].session
    for role, chosen in (("operator", op_path), ("teleoperator", to_path)):
        names = sorted({*log_dir.glob(f"{role}.mcap"), *log_dir.glob(f"{role}-*.mcap")})
        for path in names[:MAX_LOGS]:
            if path == chosen or not path.is_file() or path.is_symlink():
                continue
            try:
                other_sid, finished, _ = seen[path] if path in seen else log_session(path)
            except LogError:  # another user's (UntrustedLog), damaged, or not ours: find_pair said so
                continue
            if other_sid != sid or finished:
                continue
            pair = (path, to_path) if role == "operator" else (op_path, path)
            why = f"{path.name}: a rejoined session's earlier segment (its process was killed): an episode"
            episodes.append(read_episode(log_dir, fps, pair=pair, notes=[why], seen=seen))
    episodes.sort(key=lambda ep: ep.first_tick)
    return episodes


def _window(fps: int, dt: float) -> int:
    """Samples a frame: ``1/fps`` must hold a whole number of the session's samples."""
    w = 1.0 / (fps * dt)
    if abs(w - round(w)) > 1e-9 or round(w) < 1:
        rate = round(1 / dt)
        allowed = ", ".join(str(f) for f in range(1, rate + 1) if rate % f == 0)
        raise ExportError(
            f"--fps {fps}: a frame must hold a whole number of the session's {rate} Hz samples "
            f"(one of {allowed})"
        )
    return round(w)


def _features(
    op: dict[str, npt.NDArray[Any]], to: dict[str, npt.NDArray[Any]], sl: slice, n_all: int
) -> dict[str, npt.NDArray[Any]]:
    """The per-tick features over the episode's ticks ``sl``, from both sides' columns."""
    return {
        "action": to["v"][sl],
        "observation.operator.velocity": op["v"][sl],
        "observation.operator.force": op["f"][sl],
        "observation.robot.force": to["f"][sl],
        "observation.time": to["play_time_s"][sl],
        "observation.channel.forward_sent": (op["tx_seq"][sl] >= 0).astype(np.uint8),
        "observation.channel.backward_sent": (to["tx_seq"][sl] >= 0).astype(np.uint8),
        "observation.channel.forward_margin": to["energy_margin_observed"][sl],
        "observation.channel.backward_margin": op["energy_margin_observed"][sl],
        "observation.channel.forward_controller": _acted(to["controller_ticks"])[sl],
        "observation.channel.backward_controller": _acted(op["controller_ticks"])[sl],
        "observation.channel.forward_delay": _delay(
            to["rx_seq"][:n_all], to["play_time_s"][:n_all], op["tx_seq"][:n_all], op["send_time_s"][:n_all]
        )[sl],
        "observation.channel.backward_delay": _delay(
            op["rx_seq"][:n_all], op["play_time_s"][:n_all], to["tx_seq"][:n_all], to["send_time_s"][:n_all]
        )[sl],
    }


def _add_state(
    ep: Episode, state: tuple[npt.NDArray[Any], list[str], npt.NDArray[Any]], win: int, a: int, end: int
) -> None:
    """The robot's own state, at its own rate, on the frames' grid (NaN where a sample is missing);
    left out, said in the notes, where a frame would not hold whole samples."""
    ks, names, values = state
    if ks.size:
        every = int(np.diff(ks).min()) if ks.size > 1 else win
        if win % every:
            ep.notes.append(f"the robot's state (every {every} ticks) is left out: a frame of {win} ticks "
                         "must hold whole samples (--fps)")  # fmt: skip
        else:
            grid = np.arange(a - a % every + (every if a % every else 0), end, every)
            full = np.full((grid.size, len(names)), math.nan)
            at = np.searchsorted(ks, grid)
            hit = at < ks.size
            hit[hit] = ks[at[hit]] == grid[hit]
            full[hit] = values[at[hit]]
            ep.ticks["observation.robot.state"] = full
            ep.state_names, ep.state_every = names, every


def read_episode(
    log_dir: Path,
    fps: int,
    session: int | None = None,
    pair: tuple[Path, Path] | None = None,
    notes: list[str] | None = None,
    seen: dict[Path, tuple[int, dict[str, Any], dict[str, Any]]] | None = None,
) -> Episode:
    """The episode of one session in ``log_dir`` (its newest with both logs, or ``session``; or
    the logs ``pair``, operator's then teleoperator's): the ticks both sides ran, from the first to
    the last, cut to whole frames of ``1/fps``."""
    if pair is None:
        op_path, to_path, notes = find_pair(log_dir, session)
    else:
        (op_path, to_path), notes = pair, list(notes or [])
    for path in (op_path, to_path):
        if (size := os.stat(path).st_size) > MAX_LOG_BYTES:
            raise ExportError(
                f"{path}: a log of {size} bytes; an export reads at most {MAX_LOG_BYTES >> 20} MiB a log "
                f"(an episode is at most {MAX_EPISODE_TICKS // 60_000} minutes)"
            )
    seen = seen if seen is not None else {}
    sid, summary, params = seen[to_path] if to_path in seen else log_session(to_path)
    op_summary = (seen[op_path] if op_path in seen else log_session(op_path))[1]
    p = checked_params(to_path, params)
    win = _window(fps, p.dt)
    for path, finished in ((op_path, op_summary), (to_path, summary)):
        if not finished:
            notes.append(f"{path.name}: its process did not finish the log (killed?): the episode ends "
                         "at its last whole frame")  # fmt: skip
    max_tick = 2 * MAX_EPISODE_TICKS  # a log's ticks, from 0: a rejoin's start, then the episode
    # Both logs at once: decompression and pyarrow's parser release the interpreter lock, and the
    # parse is most of an export's time (two cores: about 0.6 of the serial time, measured).
    # (A thread, not concurrent.futures: its import, logging's included, is 0.005 s.)
    states: dict[str, list[bytes]] = {"state": []}
    got: dict[str, Any] = {}

    def op_side() -> None:
        try:
            got["op"] = _side(op_path, max_tick)
        except BaseException as e:  # handed to the caller's thread, raised there
            got["error"] = e

    helper = threading.Thread(target=op_side, name="export-operator-log")
    helper.start()
    try:
        to = _side(to_path, max_tick, states)
    finally:
        helper.join()
    if "error" in got:
        raise got["error"]
    op = got["op"]
    n_all = min(op["ran"].size, to["ran"].size)
    both = np.flatnonzero(op["ran"][:n_all] & to["ran"][:n_all])
    if both.size == 0:
        raise ExportError(f"{log_dir}: no tick that both sides ran: no episode")
    a, b = int(both[0]), int(both[-1]) + 1
    frames = (b - a) // win
    if frames == 0:
        raise ExportError(
            f"{log_dir}: {b - a} ticks both sides ran, under one frame ({win} ticks at --fps {fps})"
        )
    if frames * win > MAX_EPISODE_TICKS:
        raise ExportError(
            f"{log_dir}: a session of {(b - a) * p.dt:.0f} s; an episode is at most "
            f"{MAX_EPISODE_TICKS * p.dt:.0f} s (it is held in memory while written)"
        )
    end = a + frames * win
    sl = slice(a, end)
    ticks = _features(op, to, sl, n_all)
    # The robot's kind (a spec's name: ``franka:HOST`` is ``franka``; its host stays out of a dataset).
    spec = (summary.get("device") or {}).get("spec") if isinstance(summary.get("device"), dict) else None
    robot = str(spec).split(":", 1)[0][:64] if spec else ""
    ep = Episode(str(log_dir), sid, p.dt, p.dof, a, ticks, robot=robot, scenario=p.scenario, notes=notes)
    _add_state(ep, read_states(to_path, max_tick, states["state"]), win, a, end)
    return ep


def _shape(f: Feature, ep: Episode, win: int) -> list[int]:
    if f.per == "dof":
        return [win, ep.dof]
    if f.per == "state":
        return [win // ep.state_every, len(ep.state_names)]
    return [win]


def _names(f: Feature, ep: Episode) -> list[str] | dict[str, list[str]]:
    """Axis names, LeRobot's way for a multi-dimensional feature (as images' height/width/channels)."""
    if f.per == "dof":
        return {"axes": ["sample", "dof"], "dof": [f"dof{i}" for i in range(ep.dof)]}
    if f.per == "state":
        return {"axes": ["sample", "value"], "value": list(ep.state_names)}
    return {"axes": ["sample"]}


def _frames(x: npt.NDArray[Any], frames: int) -> npt.NDArray[Any]:
    """Per-tick samples as one window a frame: (frames, samples a frame, ...)."""
    return x.reshape(frames, x.shape[0] // frames, *x.shape[1:])


def _stats(x: npt.NDArray[Any]) -> dict[str, npt.NDArray[Any]]:
    """LeRobot's per-feature statistics of an episode's frames, laid out as its own
    ``compute_stats.get_feature_stats`` lays them out: per element of the last axis, over every
    frame and every sample of a window (a ``[20, dof]`` feature: per DoF; ``[20]``: per position
    in the window; a scalar: shape ``[1]``), ``count`` the frames.  A sample without a value (NaN:
    a tick the loop skipped) is left out, where LeRobot's would be NaN; quantiles are exact, where
    LeRobot's are a 5000-bin histogram's estimate.

    One sort a feature gives min, max and every quantile (numpy's linear method and its ``_lerp``,
    as ``np.nanquantile``): numpy's nan* reductions took a tenth of an export (issue 46)."""
    v = x.astype(np.float64)
    # One row an element (contiguous): numpy reduces along a row several times faster than down a column.
    v = np.ascontiguousarray(v.reshape(1, -1) if v.ndim == 1 else v.reshape(-1, v.shape[-1]).T)
    s = np.sort(v, axis=1)  # NaN sorts last
    have = ~np.isnan(v)
    n = have.sum(axis=1)
    rows = np.arange(v.shape[0])
    top = np.maximum(n - 1, 0)
    with np.errstate(invalid="ignore", divide="ignore"):  # an element without any value: NaN (null)
        none = np.where(n > 0, 0.0, math.nan)
        mean = np.where(have, v, 0.0).sum(axis=1) / n
        dev = np.where(have, v - mean[:, None], 0.0)
        st = {
            "min": s[:, 0] + none,
            "max": s[rows, top] + none,
            "mean": mean,
            "std": np.sqrt((dev * dev).sum(axis=1) / n),
            "count": np.array([x.shape[0]]),
        }
        at = np.array(QUANTILES)[:, None] * (n - 1)  # (quantile, element): numpy's linear method
        i = np.clip(np.floor(at).astype(np.int64), 0, top)
        g = at - i
        lo, hi = s[rows, i], s[rows, np.minimum(i + 1, top)]
        d = hi - lo
        qs = np.where(g >= 0.5, hi - d * (1 - g), lo + d * g) + none
    for j, q in enumerate(QUANTILES):
        st[f"q{round(q * 100):02d}"] = qs[j]
    return st


def _aggregate(per_episode: list[dict[str, npt.NDArray[Any]]]) -> dict[str, npt.NDArray[Any]]:
    """Episodes' statistics as one (LeRobot's ``aggregate_feature_stats``: min of mins, max of
    maxes, the count-weighted mean, the pooled variance, count-weighted quantiles); an element an
    episode has no value of (NaN) counts in the others only."""
    counts = np.array([float(s["count"][0]) for s in per_episode])
    shape = (-1,) + (1,) * per_episode[0]["mean"].ndim
    means = np.stack([s["mean"] for s in per_episode])
    w = np.where(np.isfinite(means), counts.reshape(shape), 0.0)
    total = w.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        w = w / total  # NaN where no episode has a value: the statistic is null in stats.json
        mean = np.nansum(means * w, axis=0) / (total > 0)
        spread = np.stack([s["std"] for s in per_episode]) ** 2 + (means - mean) ** 2
        out = {
            "min": np.fmin.reduce(np.stack([s["min"] for s in per_episode]), axis=0),
            "max": np.fmax.reduce(np.stack([s["max"] for s in per_episode]), axis=0),
            "mean": mean,
            "std": np.sqrt(np.nansum(spread * w, axis=0) / (total > 0)),
            "count": np.array([int(counts.sum())]),
        }
        for key in per_episode[0]:
            if key.startswith("q"):
                out[key] = np.nansum(np.stack([s[key] for s in per_episode]) * w, axis=0) / (total > 0)
    return out


def _list_array(x: npt.NDArray[Any]) -> Any:
    """A (rows, ...) array as nested Arrow lists, without a Python loop (LeRobot's Array2D and
    Sequence features are lists of lists / lists)."""
    import pyarrow as pa

    arr: Any = _flat_array(x)
    for size in reversed(x.shape[1:]):
        arr = pa.ListArray.from_arrays(_flat_array(np.arange(0, len(arr) + 1, size, dtype=np.int32)), arr)
    return arr


def _flat_array(x: npt.NDArray[Any]) -> Any:
    """A numeric array's values as one Arrow array over its buffer: ``pa.array`` of a numpy array
    imports numpy.ma (0.02 s of a 10 s session's export) to ask whether it is masked."""
    import pyarrow as pa

    if x.dtype.kind not in "iuf":  # a bool's Arrow layout is bits, not numpy's bytes
        raise TypeError(f"not a numeric array: {x.dtype}")
    flat = np.ascontiguousarray(x).reshape(-1)
    return pa.Array.from_buffers(pa.from_numpy_dtype(flat.dtype), flat.size, [None, pa.py_buffer(flat)])


def _json(path: Path, obj: Any, lines: bool = False) -> None:
    """``obj`` as indented JSON; ``lines``: its keys one a line, each value compact (stats.json:
    json's indenting encoder is pure Python, 0.01 s of a 10 s session's export)."""
    from teleop.files import write_new

    if lines:
        text = (
            "{\n"
            + ",\n".join(f"    {json.dumps(k)}: {json.dumps(v, allow_nan=False)}" for k, v in obj.items())
            + "\n}"
        )
    else:
        text = json.dumps(obj, indent=4, allow_nan=False)
    write_new(path, (text + "\n").encode())


def _jsonable(stats: dict[str, dict[str, npt.NDArray[Any]]]) -> dict[str, dict[str, Any]]:
    """Statistics as JSON: a value no sample had (a feature all NaN) is null."""

    def clean(a: npt.NDArray[Any]) -> Any:
        a = np.asarray(a, dtype=np.float64) if a.dtype.kind == "f" else a
        x = a.tolist()
        if a.dtype.kind != "f":
            return x
        if a.ndim == 0:
            return x if math.isfinite(x) else None
        if a.ndim == 1:
            return [v if math.isfinite(v) else None for v in x]
        return [clean(row) for row in a]

    return {k: {s: clean(np.asarray(v)) for s, v in st.items()} for k, st in stats.items()}


def _tasks_table(tasks: list[str]) -> Any:
    """``meta/tasks.parquet`` as LeRobot writes it with pandas: the task text is the index, with
    pandas' metadata saying so (LeRobot reads it with ``pandas.read_parquet``)."""
    import pyarrow as pa

    table = pa.table(
        {"task_index": pa.array(range(len(tasks)), pa.int64()), "task": pa.array(tasks, pa.string())}
    )
    meta = {
        "index_columns": ["task"],
        "column_indexes": [],
        "columns": [
            {"name": "task_index", "field_name": "task_index", "pandas_type": "int64",
             "numpy_type": "int64", "metadata": None},
            {"name": None, "field_name": "task", "pandas_type": "unicode", "numpy_type": "object",
             "metadata": None},
        ],
        "creator": {"library": "pyarrow", "version": pa.__version__},
        "pandas_version": "2.2.3",
    }  # fmt: skip
    return table.replace_schema_metadata({b"pandas": json.dumps(meta).encode()})


def _one_kind(episodes: list[Episode], notes: list[str]) -> None:
    """One dataset holds sessions of one kind (DoF, rate); robots with other states lose that one
    feature, said in ``notes``."""
    first = episodes[0]
    for ep in episodes[1:]:
        if (ep.dof, ep.dt) != (first.dof, first.dt):
            raise ExportError(
                f"{ep.name} has {ep.dof} DoF at {1 / ep.dt:g} Hz, {first.name} {first.dof} DoF at "
                f"{1 / first.dt:g} Hz: one dataset holds sessions of one kind (export them separately, "
                "or record them with the same --dof)"
            )
    layouts = {(tuple(ep.state_names), ep.state_every) for ep in episodes}
    if len(layouts) > 1:  # robots with other states (a MuJoCo robot and a Franka): no common feature
        notes.append(
            "observation.robot.state is left out: the episodes' robots log different states "
            "(export each robot's sessions apart to keep it)"
        )
        for ep in episodes:
            ep.state_names, ep.state_every = [], 0
            ep.ticks.pop("observation.robot.state", None)


def _info_features(feats: list[Feature], first: Episode, win: int) -> dict[str, Any]:
    """info.json's ``features``: ours with their units and reasons, then LeRobot's own columns."""
    out: dict[str, Any] = {}
    for f in feats:
        out[f.name] = {
            "dtype": f.dtype, "shape": _shape(f, first, win), "names": _names(f, first),
            "unit": f.unit, "description": f.why,
        }  # fmt: skip
    out["timestamp_ns"] = {
        "dtype": "int64", "shape": [1], "names": None, "unit": "ns",
        "description": "the frame's first sample, exactly: ns since the episode's first tick (timestamp "
        "is float32 and rounds)",
    }  # fmt: skip
    for name, dtype in (("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"),
                        ("index", "int64"), ("task_index", "int64")):  # fmt: skip
        out[name] = {"dtype": dtype, "shape": [1], "names": None}
    return out


def _episode_table(
    ep: Episode, e_i: int, index: int, task_index: int, feats: list[Feature], win: int, fps: int
) -> tuple[Any, dict[str, dict[str, npt.NDArray[Any]]]]:
    """One episode's frames as a pyarrow table, and each column's stats."""
    import pyarrow as pa

    frames = next(iter(ep.ticks.values())).shape[0] // win
    cols: dict[str, Any] = {}
    stats: dict[str, dict[str, npt.NDArray[Any]]] = {}
    for f in feats:
        x = _frames(ep.ticks[f.name], frames)
        cols[f.name] = _list_array(x)
        stats[f.name] = _stats(x)
    fi = np.arange(frames, dtype=np.int64)
    own = {
        "timestamp_ns": fi * win * round(ep.dt * 1e9),
        "timestamp": (fi / fps).astype(np.float32),
        "frame_index": fi,
        "episode_index": np.full(frames, e_i, dtype=np.int64),
        "index": index + fi,
        "task_index": np.full(frames, task_index, dtype=np.int64),
    }
    for name, a in own.items():
        cols[name] = _flat_array(a)
        stats[name] = _stats(a)
    return pa.table(cols), stats


class _DataFiles:
    """LeRobot's data files: a new file past DATA_FILES_SIZE_IN_MB, a new chunk past CHUNKS_SIZE."""

    def __init__(self, root: Path) -> None:
        self.root, self.chunk, self.file, self.size = root, 0, 0, 0
        self.writer: Any = None

    def write(self, table: Any) -> tuple[int, int]:
        """Append ``table``; returns the (chunk, file) it went into."""
        import pyarrow.parquet as pq

        if self.writer is not None and self.size + table.nbytes > DATA_FILES_SIZE_IN_MB << 20:
            self.close()
            self.file += 1
            if self.file == CHUNKS_SIZE:
                self.chunk, self.file = self.chunk + 1, 0
        if self.writer is None:
            path = self.root / DATA_PATH.format(chunk_index=self.chunk, file_index=self.file)
            path.parent.mkdir(parents=True, exist_ok=True)
            # No dictionary encoding: the columns are measured floats, few repeat; trying it took
            # half the write, and the file is a fifth smaller without (10 s session: 17 -> 9 ms).
            self.writer = pq.ParquetWriter(path, table.schema, compression="zstd", use_dictionary=False)
        self.writer.write_table(table)
        self.size += table.nbytes
        return self.chunk, self.file

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.writer, self.size = None, 0


def _write(tmp: Path, episodes: list[Episode], tasks: list[str], fps: int) -> dict[str, Any]:
    """The dataset's files into ``tmp``; returns info.json's content."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    first = episodes[0]
    win = round(1.0 / (fps * first.dt))
    feats = [f for f in FEATURES if f.per != "state" or first.state_names]
    task_list = list(dict.fromkeys(tasks))
    for d in ("meta", "meta/episodes/chunk-000", "data/chunk-000"):
        os.makedirs(tmp / d, 0o755, exist_ok=True)
    ep_rows: list[dict[str, Any]] = []
    all_stats: dict[str, list[dict[str, npt.NDArray[Any]]]] = {}
    index = 0
    files = _DataFiles(tmp)
    for e_i, ep in enumerate(episodes):
        table, ep_stats = _episode_table(ep, e_i, index, task_list.index(tasks[e_i]), feats, win, fps)
        chunk_i, file_i = files.write(table)
        frames = table.num_rows
        row: dict[str, Any] = {
            "episode_index": e_i,
            "tasks": [tasks[e_i]],
            "length": frames,
            "data/chunk_index": chunk_i,
            "data/file_index": file_i,
            "dataset_from_index": index,
            "dataset_to_index": index + frames,
            "meta/episodes/chunk_index": 0,
            "meta/episodes/file_index": 0,
        }
        for name, st in ep_stats.items():
            for s, v in st.items():
                row[f"stats/{name}/{s}"] = v.tolist()
            all_stats.setdefault(name, []).append(st)
        ep_rows.append(row)
        index += frames
    files.close()
    pq.write_table(pa.Table.from_pylist(ep_rows), tmp / EPISODES_PATH.format(chunk_index=0, file_index=0))
    pq.write_table(_tasks_table(task_list), tmp / "meta/tasks.parquet")
    _json(tmp / "meta/stats.json", _jsonable({k: _aggregate(v) for k, v in all_stats.items()}), lines=True)
    info = {
        "codebase_version": CODEBASE_VERSION,
        "robot_type": ", ".join(dict.fromkeys(ep.robot for ep in episodes if ep.robot)) or None,
        "total_episodes": len(episodes),
        "total_frames": index,
        "total_tasks": len(task_list),
        "chunks_size": CHUNKS_SIZE,
        "data_files_size_in_mb": DATA_FILES_SIZE_IN_MB,
        "video_files_size_in_mb": 500,
        "fps": fps,
        "splits": {"train": f"0:{len(episodes)}"},
        "data_path": DATA_PATH,
        "video_path": None,
        "features": _info_features(feats, first, win),
    }
    _json(tmp / "meta/info.json", info)
    return info


def export(
    episodes: list[Episode], tasks: list[str], out: Path, fps: int, notes: list[str] | None = None
) -> dict[str, Any]:
    """Write ``episodes`` (``tasks[i]`` the task of episode ``i``) as a LeRobot v3.0 dataset into
    the new folder ``out`` (it must not exist, or be empty: a dataset is never written over).
    Written into a fresh folder beside it, renamed into place whole: a failed export leaves none.
    Returns info.json's content; what the caller should be told is added to ``notes``."""
    _one_kind(episodes, notes if notes is not None else [])
    out = out.absolute()
    if out.is_symlink() or (out.exists() and (not out.is_dir() or any(out.iterdir()))):
        raise ExportError(f"--out {out}: already there and not an empty folder: a dataset is never "
                          "written over (name a new folder)")  # fmt: skip
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    os.mkdir(tmp, 0o755)
    try:
        info = _write(tmp, episodes, tasks, fps)
        if out.exists():
            os.rmdir(out)  # empty (checked above): the rename needs it gone or empty
        os.rename(tmp, out)
    except BaseException:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return info


def ticks_of(column: npt.NDArray[Any]) -> npt.NDArray[Any]:
    """A feature's column (frames, samples a frame, ...) back as its per-sample series."""
    return column.reshape(-1, *column.shape[2:])
