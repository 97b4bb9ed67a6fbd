"""Run by tests/test_lerobot_export.py in the LeRobot environment (``.ci/lerobot-env``), not by pytest:
LeRobot's own loader reads a dataset ``teleop export`` wrote, and what it gives is checked against
what the test read from the logs (argv: the dataset's folder, the expectations as JSON).

Prints ``lerobot check: ok`` and exits 0, or fails on the first difference."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np


def main(root: Path, expect: dict[str, Any]) -> None:
    from lerobot.datasets.compute_stats import aggregate_stats, compute_episode_stats
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset(f"local/{root.name}", root=root)
    assert len(ds) == expect["frames"], (len(ds), expect["frames"])
    assert ds.num_episodes == len(expect["episodes"]), ds.num_episodes
    eps = ds.meta.episodes
    bounds = [
        [int(eps["dataset_from_index"][i]), int(eps["dataset_to_index"][i])] for i in range(ds.num_episodes)
    ]
    assert bounds == expect["episodes"], bounds
    for name, shape in expect["features"].items():
        assert list(ds.meta.features[name]["shape"]) == shape, (name, ds.meta.features[name]["shape"], shape)
    item = ds[0]
    for name, shape in expect["features"].items():
        got = tuple(item[name].shape)
        assert got in (tuple(shape), ()) if shape == [1] else got == tuple(shape), (name, got, shape)
    # LeRobot hands a frame's numbers as torch.tensor(list) makes them: float32 (the files hold
    # float64, read exactly through ds.hf_dataset in Arrow form; its numpy form is float32 too).
    assert str(item["action"].dtype) == "torch.float32", item["action"].dtype
    exact = ds.hf_dataset.with_format("arrow")
    for index, values in expect["values"].items():
        item = ds[int(index)]
        for name, want in values.items():
            got = item[name]
            if name == "task":
                assert got == want, (index, got, want)
            elif name == "episode_index":
                assert int(got) == want, (index, got, want)
            else:
                assert np.array_equal(got.numpy(), np.array(want, dtype=np.float32)), (index, name)
                row = np.array(exact[int(index)].column(name).to_pylist()[0], dtype=np.float64)
                assert row.tobytes() == np.array(want).tobytes(), (index, name)
    # LeRobot's own statistics of the data (its compute_episode_stats, aggregate_stats) against
    # meta/stats.json: min, max, mean, std and count (its quantiles are a histogram's estimate).
    per_episode = []
    for a, b in bounds:
        rows = exact[a:b]  # Arrow: the numpy form would round to float32
        feats = {
            k: v for k, v in ds.meta.features.items() if k in rows.column_names and v["dtype"] != "string"
        }
        per_episode.append(
            compute_episode_stats(
                {k: np.array(rows.column(k).to_pylist(), dtype=feats[k]["dtype"]) for k in feats}, feats
            )
        )
    theirs = aggregate_stats(per_episode)
    compared = 0
    for name, st in theirs.items():
        for s in ("min", "max", "mean", "std", "count"):
            mine = np.asarray(ds.meta.stats[name][s], dtype=np.float64)
            ref = np.asarray(st[s], dtype=np.float64).reshape(mine.shape)
            ok = np.isfinite(ref)  # LeRobot's NaN where a sample is NaN (a skipped tick); ours leave it out
            # LeRobot's std is sqrt(E[x^2] - E[x]^2): where the spread is far below the mean it keeps
            # only the rounding of E[x^2] (about 1e-8 of the mean), where ours is the two-pass one.
            atol: Any = 1e-12
            if s == "std":
                atol += 1e-7 * np.abs(np.asarray(st["mean"], dtype=np.float64).reshape(mine.shape))[ok]
            assert np.allclose(mine[ok], ref[ok], rtol=1e-6, atol=atol), (name, s, mine[ok], ref[ok])
            compared += int(ok.sum())
    assert compared > 300, compared  # every feature but where a skipped tick made LeRobot's NaN
    print(f"lerobot check: ok ({len(ds)} frames, {ds.num_episodes} episodes, {compared} statistics compared)")


if __name__ == "__main__":
    main(Path(sys.argv[1]), json.loads(sys.argv[2]))
