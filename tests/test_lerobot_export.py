"""Issue 46: sessions exported as a LeRobot v3.0 dataset at full rate, and the robot's pose in the logs.

The logs here are written in this process by the log writer's own class (``shell.mcaplog._Writer``,
what the writer process runs) from two ports joined as ``teleop sim`` joins them, with the MuJoCo
robot: no process is started, so these tests are in the fast suite.  The last test hands the dataset
to LeRobot's own loader, in the environment ``.ci/lerobot-env`` builds (it skips where it is absent).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest

from shell.mcaplog import _Writer
from teleop.cli import main
from teleop.offline import lerobot
from teleop.offline.logfile import iter_messages, read_log, read_states
from teleop.session.node import PortOptions
from teleop.session.port import Chunk, Port, make_node
from teleop.session.protocol import SessionParams

# Imported at collection, as tests/test_mujoco_robot.py does: importing MuJoCo runs glfw's version
# probe, a child process, which the fast suite allows only outside its tests.
pytest.importorskip("mujoco")

DT = 1e-3
DOF = 2
ROOT = Path(__file__).resolve().parents[1]


class _Sink:
    """A port's sealed chunks straight to the log writer (in this process)."""

    def __init__(self, w: _Writer) -> None:
        self.w = w

    def write(self, chunk: Chunk) -> None:
        self.w.handle("chunk", chunk)


def _session(
    folder: Path,
    ticks: int,
    session: int = 7,
    stall: range = range(0),
    robot: str | None = "mujoco",
    rejoin: range | None = None,
) -> Path:
    """Two ports over ``ticks`` (the teleoperator a half tick behind, skipping ``stall``), their logs
    written as the runner writes them: ``folder/operator.mcap`` and ``folder/teleoperator.mcap``.
    ``rejoin``: the teleoperator is killed at its start (its log has no summary) and a new one
    rejoins at its end, into ``teleoperator-SESSION.mcap``."""
    folder.mkdir(parents=True)
    params = SessionParams(
        session=session, scenario="protocol", dof=DOF, b=20.0, full_scale=2.0, duration=ticks * DT
    )
    writers, ports = [], []
    for role in ("operator", "teleoperator"):
        w = _Writer(str(folder / f"{role}.mcap"), role, 1_700_000_000 * 10**9, None, "127.0.0.1")
        w.handle("msg", ("session", 0.0, {"role": role, "params": dataclasses.asdict(params)}))
        node = make_node(
            role, scenario="protocol", dof=DOF, dt=DT, b=20.0, codec="eds:20", full_scale=2.0,
            session=session, options=PortOptions(), device=robot if role == "teleoperator" else None,
        )  # fmt: skip
        writers.append(w)
        ports.append(Port(node, sink=_Sink(w)))
    op, to = ports
    backward: list[bytes] = []
    forward: list[bytes] = []
    for n in range(ticks):
        now = n * DT
        for data in backward:
            op.receive(data, now, n)
        backward = []
        forward += op.tick(n, now)
        op.sent(n, now)
        if rejoin is not None and n == rejoin.start:  # killed: its writer finishes what it had
            to.finish()
            writers[1].close()
        if rejoin is not None and n == rejoin.stop:  # a new process rejoins the session
            w = _Writer(str(folder / f"teleoperator-{session}.mcap"), "teleoperator", 1_700_000_000 * 10**9,
                        None, "127.0.0.1")  # fmt: skip
            w.handle("msg", ("session", now, {"role": "teleoperator", "params": dataclasses.asdict(params)}))
            node = make_node(
                "teleoperator", scenario="protocol", dof=DOF, dt=DT, b=20.0, codec="eds:20", full_scale=2.0,
                session=session, options=PortOptions(), device=robot,
            )  # fmt: skip
            writers[1], ports[1] = w, Port(node, sink=_Sink(w))
            to = ports[1]
        if n in stall or (rejoin is not None and n in rejoin):
            forward = []
            continue
        for data in forward:
            to.receive(data, now + DT / 2, n)
        forward = []
        backward = to.tick(n, now + DT / 2)
        to.sent(n, now + DT / 2)
    for w, port in zip(writers, ports, strict=True):
        port.finish()
        summary = port.summary()
        summary["params"] = dataclasses.asdict(params)
        w.handle("msg", ("summary", ticks * DT, summary))
        w.close()
    return folder


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3 s session with a 30-tick stall of the robot's loop."""
    return _session(tmp_path_factory.mktemp("s") / "a", 3000, stall=range(1200, 1230))


def _column(dataset: Path, name: str) -> np.ndarray[Any, Any]:
    """A feature back from the data files, as (frames, ...) numpy (pyarrow: not our writer's code)."""
    import pyarrow as pa

    files = sorted((dataset / "data").glob("chunk-*/file-*.parquet"))
    col = pa.concat_arrays([c for f in files for c in pq.read_table(f, columns=[name]).column(name).chunks])
    rows = len(col)
    while pa.types.is_list(col.type):
        col = col.flatten()
    shape = _info(dataset)["features"][name]["shape"]
    out: np.ndarray[Any, Any] = col.to_numpy(zero_copy_only=False).reshape(rows, *shape)
    return out[:, 0] if shape == [1] else out


def _info(dataset: Path) -> dict[str, Any]:
    info: dict[str, Any] = json.loads((dataset / "meta/info.json").read_text())
    return info


def test_the_round_trip_rebuilds_every_1khz_signal_bit_for_bit(logs: Path, tmp_path: Path) -> None:
    """Every per-tick signal read back from the dataset equals the log's, to the bit (NaN where a
    tick was skipped), as read by the established reader (iter_ticks); the robot's state equals
    the log's state messages; an episode has length x fps frames."""
    out = tmp_path / "ds"
    assert main(["export", str(logs), "--to", "lerobot", "--out", str(out), "--task", "push"]) == 0
    _, op = read_log(logs / "operator.mcap")
    _, to = read_log(logs / "teleoperator.mcap")
    assert _info(out)["total_frames"] == 3000 * 50 // 1000 == 150
    want = {
        "action": to["v"],
        "observation.operator.velocity": op["v"],
        "observation.operator.force": op["f"],
        "observation.robot.force": to["f"],
        "observation.time": to["play_time_s"],
        "observation.channel.forward_margin": to["energy_margin_observed"],
        "observation.channel.backward_margin": op["energy_margin_observed"],
        "observation.channel.forward_sent": (op["tx_seq"] >= 0).astype(np.uint8),
        "observation.channel.backward_sent": (to["tx_seq"] >= 0).astype(np.uint8),
    }
    for name, series in want.items():
        got = lerobot.ticks_of(_column(out, name))
        assert got.dtype == series.dtype and got.shape == series.shape, name
        assert got.tobytes() == series.tobytes(), name  # bit for bit, NaN included
    assert np.isnan(lerobot.ticks_of(_column(out, "action"))[1200:1230]).all()  # the stall: no value
    # The controller's flag and the delay, rebuilt here one tick at a time from the logs.
    for direction, rx, tx in (("forward", to, op), ("backward", op, to)):
        ct = rx["controller_ticks"]
        acted = [(-1 if ct[k] < 0 else int(ct[k] > max([0, *ct[:k]]))) for k in range(ct.size)]
        assert lerobot.ticks_of(_column(out, f"observation.channel.{direction}_controller")).tolist() == acted
        sent_at = {int(s): k for k, s in enumerate(tx["tx_seq"]) if s >= 0}
        delay, newest = [], -1
        for k in range(rx["rx_seq"].size):
            if rx["rx_seq"][k] >= 0 and rx["rx_seq"][k] != newest:
                newest = int(rx["rx_seq"][k])
                d = rx["play_time_s"][k] - tx["send_time_s"][sent_at[newest]]
            delay.append(d if newest >= 0 else math.nan)
        got = lerobot.ticks_of(_column(out, f"observation.channel.{direction}_delay"))
        np.testing.assert_array_equal(got, np.array(delay))
        assert np.nanmin(got) > 0 and np.nanmax(got) < 0.05  # eds:20 holds a sample up to 20 ticks
    # The robot's own state at its own rate (every 10 ticks: 2 samples a frame).
    ks, names, values = read_states(logs / "teleoperator.mcap", 10**6)
    grid = np.arange(0, 3000, 10)
    assert ks.tolist() == [k for k in grid if not 1200 <= k < 1230]  # the stall's ticks ran no device
    assert [
        m["k"] for _, m in iter_messages(logs / "teleoperator.mcap", ["/teleoperator/state"])
    ] == ks.tolist()
    state = _column(out, "observation.robot.state")
    assert state.shape == (150, 2, len(names))
    assert _info(out)["features"]["observation.robot.state"]["names"]["value"] == names
    # The stall's grid ticks hold no sample (NaN); every other row is the log's sample.
    got = lerobot.ticks_of(state)
    ok = np.isin(grid, ks)
    assert got[ok].tobytes() == values.tobytes()
    assert np.isnan(got[~ok]).all() and (~ok).sum() == 3
    ns = _column(out, "timestamp_ns")
    assert ns.tolist() == [i * 20_000_000 for i in range(150)]
    assert _column(out, "timestamp").dtype == np.float32


def test_stats_json_equals_a_recomputation_from_the_data(logs: Path, tmp_path: Path) -> None:
    """meta/stats.json: min, max, mean, std, count and quantiles per feature, laid out as LeRobot's
    (per element of the last axis, over every frame and sample: a [20, dof] feature per DoF),
    recomputed here from the data files (NaN samples left out), equal within float rounding."""
    out = tmp_path / "ds"
    lerobot.export([lerobot.read_episode(logs, 50)], ["t"], out, 50)
    stats = json.loads((out / "meta/stats.json").read_text())
    info = _info(out)
    assert set(stats) == set(info["features"])
    for name in info["features"]:
        x = _column(out, name).astype(np.float64)
        per = x.reshape(x.shape[0], -1, 1 if x.ndim == 1 else x.shape[-1])  # (frames, samples, last axis)
        want = {
            "min": np.nanmin(per, axis=(0, 1)),
            "max": np.nanmax(per, axis=(0, 1)),
            "mean": np.nanmean(per, axis=(0, 1)),
            "std": np.nanstd(per, axis=(0, 1)),
            "q50": np.nanmedian(per, axis=(0, 1)),
        }
        assert len(stats[name]["mean"]) == (1 if x.ndim == 1 else x.shape[-1]), name
        for s, v in want.items():
            got = np.array(stats[name][s], dtype=np.float64)
            np.testing.assert_allclose(got, v, rtol=1e-12, atol=1e-15, err_msg=f"{name} {s}")
        assert stats[name]["count"] == [150]


def test_sessions_make_one_dataset_with_their_tasks(logs: Path, tmp_path: Path) -> None:
    """Two sessions are two episodes: indexes run on, each episode's rows say where it lies, and
    each has its task (tasks.parquet: the task is the index, as pandas writes it)."""
    other = _session(tmp_path / "b", 1010, session=8)
    out = tmp_path / "ds"
    assert main(["export", str(logs), str(other), "--to", "lerobot", "--out", str(out),
                 "--task", "push the foam", "--task", "touch the wall"]) == 0  # fmt: skip
    eps = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    keys = ("episode_index", "length", "dataset_from_index", "dataset_to_index", "tasks")
    assert [tuple(e[k] for k in keys) for e in eps] == [
        (0, 150, 0, 150, ["push the foam"]),
        (1, 50, 150, 200, ["touch the wall"]),
    ]
    assert _column(out, "index").tolist() == list(range(200))
    assert _column(out, "episode_index").tolist() == [0] * 150 + [1] * 50
    assert _column(out, "task_index").tolist() == [0] * 150 + [1] * 50
    tasks = pq.read_table(out / "meta/tasks.parquet")
    assert tasks.column("task").to_pylist() == ["push the foam", "touch the wall"]
    assert json.loads(tasks.schema.metadata[b"pandas"])["index_columns"] == ["task"]
    info = _info(out)
    assert (info["codebase_version"], info["total_episodes"], info["total_frames"], info["fps"]) == (
        "v3.0", 2, 200, 50,
    )  # fmt: skip
    assert info["features"]["observation.robot.force"]["shape"] == [20, DOF]


def test_a_rejoined_session_gives_an_episode_per_segment(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A teleoperator killed at tick 1500 and a new one rejoining at 1600: two episodes, the killed
    process's segment (75 frames) and the rejoined one's (70), in the order they ran, each said."""
    logs = _session(tmp_path / "r", 3000, rejoin=range(1500, 1600))
    out = tmp_path / "ds"
    assert main(["export", str(logs), "--to", "lerobot", "--out", str(out), "--task", "rejoin"]) == 0
    said = capsys.readouterr().out
    assert "teleoperator.mcap: a rejoined session's earlier segment" in said
    assert "teleoperator: read teleoperator-7.mcap, the one log of session 7 that was finished" in said
    eps = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert [(e["length"], e["dataset_from_index"], e["tasks"]) for e in eps] == [
        (75, 0, ["rejoin"]),
        (70, 75, ["rejoin"]),
    ]
    _, first = read_log(logs / "teleoperator.mcap")
    _, second = read_log(logs / "teleoperator-7.mcap")
    action = lerobot.ticks_of(_column(out, "action"))
    assert action[:1500].tobytes() == first["v"][:1500].tobytes()
    assert action[1500:].tobytes() == second["v"][1600:3000].tobytes()


def test_robots_with_other_states_share_a_dataset_without_the_state(
    logs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A MuJoCo robot's session beside one of a robot without a state: the state feature is left
    out, and the export says why in one line per episode."""
    other = _session(tmp_path / "b", 500, session=8, robot=None)
    out = tmp_path / "ds"
    assert main(["export", str(logs), str(other), "--to", "lerobot", "--out", str(out)]) == 0
    assert "observation.robot.state is left out" in capsys.readouterr().out
    assert "observation.robot.state" not in _info(out)["features"]
    assert _info(out)["total_frames"] == 150 + 25


def test_the_robots_pose_reads_back_as_foxglove_transforms(logs: Path) -> None:
    """A 3D panel shows the arm: /teleoperator/tf holds foxglove.FrameTransforms (base -> tool) and
    /teleoperator/pose foxglove.PoseInFrame at the state's rate, equal to the state's pose."""
    from mcap.reader import make_reader

    with (logs / "teleoperator.mcap").open("rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None
    schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert schemas["/teleoperator/tf"] == "foxglove.FrameTransforms"
    assert schemas["/teleoperator/pose"] == "foxglove.PoseInFrame"
    states = {m["k"]: m for _, m in iter_messages(logs / "teleoperator.mcap", ["/teleoperator/state"])}
    tfs = [m for _, m in iter_messages(logs / "teleoperator.mcap", ["/teleoperator/tf"])]
    assert len(tfs) == len(states) == 297  # every 10 ticks, but the stall's 3
    moved = 0
    for (k, state), tf in zip(sorted(states.items()), tfs, strict=True):
        (t,) = tf["transforms"]
        assert (t["parent_frame_id"], t["child_frame_id"]) == ("base", "tool")
        tr, rot = t["translation"], t["rotation"]
        assert [tr["x"], tr["y"], tr["z"], rot["x"], rot["y"], rot["z"], rot["w"]] == state["pose"]
        assert math.isclose(sum(rot[c] ** 2 for c in "xyzw"), 1.0, rel_tol=1e-9)
        moved += tr["x"] != 0.0
        assert t["timestamp"]["sec"] * 10**9 + t["timestamp"]["nsec"] >= 1_700_000_000 * 10**9 + k * 10**6
    assert moved > 100  # the tip moves: the transforms are the robot's, not a constant


def test_the_docs_foxglove_layout_names_topics_a_session_has(logs: Path) -> None:
    """Every topic the shipped layout (docs/guides/foxglove-layout.json) plots or shows is a channel
    of a session's logs, with a field its schema has: a renamed topic breaks this test, not the layout."""
    import re

    from mcap.reader import make_reader

    layout = (ROOT / "docs/guides/foxglove-layout.json").read_text()
    json.loads(layout)
    channels: dict[str, set[str]] = {}
    for role in ("operator", "teleoperator"):
        with (logs / f"{role}.mcap").open("rb") as f:
            summary = make_reader(f).get_summary()
        assert summary is not None
        for c in summary.channels.values():
            schema = json.loads(summary.schemas[c.schema_id].data)
            channels[c.topic] = set(schema.get("properties", {}))
    paths = re.findall(r'"(/(?:operator|teleoperator)/[a-z_]+)(?:\.([a-z_]+))?', layout)
    assert len(paths) >= 8
    for topic, fieldname in paths:
        assert topic in channels, topic
        assert not fieldname or fieldname in channels[topic], (topic, fieldname)


def test_a_killed_sessions_log_gives_one_line_and_the_whole_frames(
    logs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A log cut short (its writer killed) exports the episode up to the last whole frame both logs
    hold, and says so in one line; a file that is not a log is one error line, never a traceback."""
    cut = tmp_path / "cut"
    cut.mkdir()
    (cut / "operator.mcap").write_bytes((logs / "operator.mcap").read_bytes())
    data = (logs / "teleoperator.mcap").read_bytes()
    (cut / "teleoperator.mcap").write_bytes(data[: len(data) // 3])
    out = tmp_path / "ds"
    assert main(["export", str(cut), "--to", "lerobot", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "teleoperator.mcap: its process did not finish the log (killed?)" in text
    ran = read_log(cut / "teleoperator.mcap")[1]["play_time_s"]
    n = int(np.flatnonzero(~np.isnan(ran))[-1]) + 1
    assert 0 < n < 3000
    assert _info(out)["total_frames"] == n // 20
    eps = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert eps[0]["length"] == n // 20
    (cut / "teleoperator.mcap").write_bytes(data[:5000] + b"\xff" * 3000)
    with pytest.raises(SystemExit) as e:
        main(["export", str(cut), "--to", "lerobot", "--out", str(tmp_path / "ds2")])
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith("teleop: error: ") and err.count("\n") == 1
    assert "Traceback" not in err and not (tmp_path / "ds2").exists()


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--fps", "30"], "--fps 30: a frame must hold a whole number of the session's 1000 Hz samples"),
        (["--fps", "0"], "--fps must be an integer 1..1000"),
        (["--task", "a", "--task", "b"], "2 --task for 1 log folders"),
        (["--task", "line\nbreak"], "a task is one line"),
    ],
)
def test_bad_arguments_are_one_line(
    logs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], says: str
) -> None:
    with pytest.raises(SystemExit) as e:
        main(["export", str(logs), "--to", "lerobot", "--out", str(tmp_path / "ds"), *args])
    err = capsys.readouterr().err
    assert e.value.code == 2 and says in err and err.count("\n") == 1, err


def test_a_log_too_large_is_refused_by_its_size_before_it_is_read(
    logs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(lerobot, "MAX_LOG_BYTES", 100_000)
    monkeypatch.setattr(lerobot, "read_columns", None)  # never reached: the size is checked first
    with pytest.raises(SystemExit):
        main(["export", str(logs), "--to", "lerobot", "--out", str(tmp_path / "ds")])
    err = capsys.readouterr().err
    assert "operator.mcap: a log of" in err and "an export reads at most 0 MiB a log" in err
    assert err.count("\n") == 1 and not (tmp_path / "ds").exists()


def test_a_dataset_is_never_written_over(
    logs: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An --out that holds anything is refused and left as it was; an empty one is used."""
    out = tmp_path / "ds"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(SystemExit):
        main(["export", str(logs), "--to", "lerobot", "--out", str(out)])
    assert "a dataset is never written over" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["keep.txt"]
    assert not [p for p in tmp_path.iterdir() if ".partial-" in p.name]
    (out / "keep.txt").unlink()
    assert main(["export", str(logs), "--to", "lerobot", "--out", str(out)]) == 0
    assert (out / "meta/info.json").is_file()


def _lerobot_python() -> Path | None:
    venv = Path(os.environ.get("TELEOP_LEROBOT_VENV", Path.home() / ".cache/teleop-lerobot-venv"))
    python = venv / "bin/python"
    return python if (venv / ".requirements-sha256").is_file() and python.exists() else None


@pytest.mark.integration  # LeRobot's loader runs in a process of its own environment
def test_lerobots_own_loader_reads_the_dataset(logs: Path, tmp_path: Path) -> None:
    """LeRobotDataset (lerobot 0.4.4, from a local folder) loads the export as is: its features,
    shapes, episode boundaries and tasks, and a few values equal the logs'; LeRobot's own
    statistics of the data equal stats.json."""
    python = _lerobot_python()
    if python is None:
        why = "no LeRobot environment: build it with .ci/lerobot-env (about 8 GB; .ci/run does)"
        if os.environ.get("TELEOP_LEROBOT_REQUIRED"):  # .ci/run: it was built, so it must be there
            pytest.fail(why)
        pytest.skip(why)
    other = _session(tmp_path / "b", 1010, session=8)
    out = tmp_path / "ds"
    lerobot.export(
        [lerobot.read_episode(logs, 50), lerobot.read_episode(other, 50)], ["push", "touch"], out, 50
    )
    _, to = read_log(logs / "teleoperator.mcap")
    _, op = read_log(other / "operator.mcap")
    expect = {
        "frames": 200,
        "episodes": [[0, 150], [150, 200]],
        "features": {f: v["shape"] for f, v in _info(out)["features"].items()},
        "values": {
            "10": {"action": to["v"][200:220].tolist(), "task": "push", "episode_index": 0},
            "170": {"observation.operator.velocity": op["v"][400:420].tolist(), "task": "touch",
                    "episode_index": 1},
        },
    }  # fmt: skip
    env = {**os.environ, "HF_HOME": str(tmp_path / "hf"), "HF_HUB_OFFLINE": "1"}
    done = subprocess.run(
        [str(python), str(ROOT / "tests/lerobot_check.py"), str(out), json.dumps(expect)],
        capture_output=True, text=True, env=env, timeout=600,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    assert "lerobot check: ok" in done.stdout, done.stdout


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__]))


def test_a_frankas_state_for_the_log() -> None:
    """FrankaRobot.state(): the pose (position, unit quaternion of the orientation, Foxglove's
    x, y, z, w order), q, dq, measured torques and the set-point, from the newest read; and the
    quaternion of a known rotation."""
    from teleop.devices.franka import _quaternion
    from tests.test_franka import _fake, _step

    dev, arm = _fake()
    arm.next_state.tau_J = [0.5 * i for i in range(7)]
    _step(dev, 0.0, [0.0, 0.0, 0.0])
    state = dev.state()
    assert state["pose"] == [0.5, 0.0, 0.5, 0.0, 0.0, 0.0, 1.0]
    assert state["q"] == dev._q.tolist() == [0.0] * 7 and state["tau"] == [0.5 * i for i in range(7)]
    assert len(state["dq"]) == 7 and state["setpoint"] == [0.5, 0.0, 0.5]
    assert dev.state_every == 10
    c, s = math.cos(math.pi / 3), math.sin(math.pi / 3)  # 60 degrees about z
    got = _quaternion(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]))
    np.testing.assert_allclose(got, [0.0, 0.0, math.sin(math.pi / 6), math.cos(math.pi / 6)], atol=1e-12)
