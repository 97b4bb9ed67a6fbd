"""Section VI's experiment: the seeded human, per-phase transparency, and `teleop experiment`."""

from __future__ import annotations

import itertools
import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from teleop.cli import main
from teleop.control import metrics
from teleop.devices import scenarios
from teleop.devices.models import ModelError, ProtocolEnvironment, ProtocolHuman, ProtocolPlan
from teleop.limits import MAX_SEED, MAX_VARIATION
from teleop.offline import experiment
from teleop.offline.sim import SimConfig, run_case
from teleop.session.protocol import ProtocolError, SessionParams

seeds = st.integers(0, MAX_SEED)
variations = st.floats(0.0, MAX_VARIATION)


# --------------------------------------------------------------------------------------------
# the seeded human
# --------------------------------------------------------------------------------------------
def test_variation_zero_is_the_scripted_run() -> None:
    for seed in (0, 1, 12345):
        assert ProtocolPlan.draw(seed, 0.0) == ProtocolPlan()
    plan = ProtocolPlan()
    assert plan.phases(15.0) == [("free", 0.0, 5.0), ("foam", 5.0, 10.0), ("wall", 10.0, 15.0)]
    want = [(5.0, 0.04), (7.0, 0.0), (7.5, -0.04), (9.5, 0.0), (10.0, 0.05), (11.0, -0.05)]
    want += [(12.0, 0.0), (12.5, 0.05), (13.5, -0.05), (14.5, 0.0)]
    assert plan.knots() == want  # the scripted profile, exactly


def test_same_seed_same_plan_and_seeds_differ() -> None:
    assert ProtocolPlan.draw(7, 1.0) == ProtocolPlan.draw(7, 1.0)
    plans = {ProtocolPlan.draw(s, 1.0) for s in range(10)}
    assert len(plans) == 10
    t_foam = [p.t_foam for p in plans]
    assert max(t_foam) - min(t_foam) > 0.1  # the phase timing does vary


def test_variation_scales_the_same_draws() -> None:
    a, b = ProtocolPlan.draw(3, 0.5), ProtocolPlan.draw(3, 1.0)
    assert b.t_wall - 10.0 == pytest.approx(2 * (a.t_wall - 10.0))
    assert b.k_grip - 2000.0 == pytest.approx(2 * (a.k_grip - 2000.0))


def test_variation_out_of_range_is_refused() -> None:
    with pytest.raises(ModelError, match=r"variation must be in 0\.\.2"):
        ProtocolPlan.draw(0, 2.5)
    with pytest.raises(ValueError, match="variation"):
        SimConfig(scenario="protocol", variation=-1.0).resolved()


@settings(max_examples=200, deadline=None)
@given(seeds, variations)
def test_every_plan_is_a_well_formed_task(seed: int, variation: float) -> None:
    """Knots in order, each phase at least 4 s, strokes ending at rest, stiffnesses positive."""
    p = ProtocolPlan.draw(seed, variation)
    times = [t for t, _ in p.knots()]
    assert all(b > a for a, b in itertools.pairwise(times))
    assert p.t_foam <= times[0] and times[3] < p.t_wall <= times[4] and times[-1] < p.t_end
    (_, _, f1), (_, f0, w0), (_, w1, _) = p.phases(15.0)
    assert f1 == f0 >= 4.0 and w0 - f0 >= 4.0 and 15.0 - w0 >= 4.5 and w1 == w0
    assert abs(math.sin(2 * math.pi * p.stroke_freq * p.t_foam)) < 1e-9
    assert abs(math.sin(2 * math.pi * p.lateral_freq * p.t_foam)) < 1e-9
    assert p.k > 0 and p.k_grip > 0 and p.stroke_amp > 0 and p.foam_depth > 0 and p.wall_depth > 0


@settings(max_examples=60, deadline=None)
@given(seeds, variations, st.lists(st.floats(-50.0, 50.0), min_size=50, max_size=300))
def test_every_varied_hand_is_passive(seed: int, variation: float, forces: list[float]) -> None:
    """The hand's yielding part (arm plus grip admittance, Tustin) never gives energy back:
    from rest, ``sum F * (Y F) dt >= 0`` at every tick, for any force and any plan."""
    dt = 1e-3
    h = ProtocolHuman(1, dt, plan=ProtocolPlan.draw(seed, variation))
    energy = 0.0
    for f in forces:
        y = float(h.admittance.advance(np.array([f]))[0])
        energy += f * y * dt
        assert energy >= -1e-12


def test_environment_switches_on_the_phase_boundaries() -> None:
    """The environment's foam and wall begin on the first tick of their phases (same plan)."""
    dt = 1e-3
    for seed in range(5):
        sc = scenarios.get("protocol")
        phases = sc.phases(seed, 1.0, 15.0)
        env = ProtocolEnvironment(1, dt, plan=ProtocolPlan.draw(seed, 1.0))
        ticks = metrics.phase_ticks(15000, dt, phases)
        a = ticks["foam"].start
        assert env.affine((a - 1) * dt)[1][0] == 0.0 and env.affine(a * dt)[1][0] == env.foam
        w = ticks["wall"].start
        env.affine((w - 1) * dt)
        assert env.wall is None
        env.affine(w * dt)
        assert env.wall is not None


def test_same_seed_same_run_and_the_seed_changes_the_run() -> None:
    cfg = SimConfig(codec="eds:2", scenario="protocol", duration=6.0, seed=4, variation=1.0)
    a, b = run_case(cfg).summary, run_case(cfg).summary
    assert a["phases"] == b["phases"] and a["I"] == b["I"]
    c = run_case(SimConfig(codec="eds:2", scenario="protocol", duration=6.0, seed=5, variation=1.0)).summary
    assert c["I"] != a["I"]
    assert a["passive"] and c["passive"]


# --------------------------------------------------------------------------------------------
# per-phase figures
# --------------------------------------------------------------------------------------------
def test_phase_transparency_adds_up_to_eq_7() -> None:
    rng = np.random.default_rng(0)
    v_h, v_t, f_h, f_t = (rng.normal(size=(1000, 2)) for _ in range(4))
    phases = [("free", 0.0, 0.3), ("foam", 0.3, 0.75), ("wall", 0.75, 1.0)]
    out = metrics.phase_transparency(v_h, v_t, f_h, f_t, 1e-3, phases)
    whole = metrics.transparency(v_h, v_t, f_h, f_t, 1e-3)
    assert out["all"]["I"] == pytest.approx(whole, rel=1e-12)
    assert sum(out[n]["I"] for n in ("free", "foam", "wall")) == pytest.approx(whole, rel=1e-12)
    assert [out[n]["ticks"] for n in ("free", "foam", "wall")] == [300, 450, 250]
    for n in out:
        assert sum(out[n]["I_dof"]) == pytest.approx(out[n]["I"], rel=1e-12)
    dof1 = metrics.transparency(v_h[300:750, 1], v_t[300:750, 1], f_h[300:750, 1], f_t[300:750, 1], 1e-3)
    assert out["foam"]["I_dof"][1] == pytest.approx(dof1, rel=1e-12)


def test_phase_transparency_leaves_out_unrecorded_ticks() -> None:
    v = np.ones((100, 1))
    z = np.zeros((100, 1))
    valid = np.ones(100, dtype=bool)
    valid[:10] = False
    v_bad = v.copy()
    v_bad[:10] = np.nan
    out = metrics.phase_transparency(v_bad, z, z, z, 0.01, [("a", 0.0, 0.5), ("b", 0.5, 1.0)], valid)
    assert out["a"]["I"] == pytest.approx(40 * 0.01) and out["a"]["ticks"] == 40
    assert out["b"]["I"] == pytest.approx(50 * 0.01) and out["all"]["ticks"] == 90


def test_phase_rates() -> None:
    sent = np.zeros(1000)
    sent[:500:2] = 100.0  # 500 packets/s of 100 B in the first half
    sent[500::50] = 60.0  # 20 packets/s of 60 B in the second
    r = metrics.phase_rates(sent, 1e-3, [("a", 0.0, 0.5), ("b", 0.5, 1.0), ("c", 1.0, 1.0)])
    assert r["a"] == {"packets_per_s": 500.0, "bps": 8 * 100 * 500.0}
    assert r["b"]["packets_per_s"] == pytest.approx(20.0) and r["b"]["bps"] == pytest.approx(8 * 60 * 20.0)
    assert r["c"] == {"packets_per_s": None, "bps": None}
    assert r["all"]["packets_per_s"] == pytest.approx(260.0)


@pytest.fixture(scope="module")
def six_seconds_of_ids() -> dict[str, Any]:
    """A 6 s protocol run of ids:2 (it never reaches the wall), read by two tests: run once."""
    return run_case(SimConfig(codec="ids:2", scenario="protocol", duration=6.0)).summary


def test_sim_summary_has_the_phases_and_wire_rates(six_seconds_of_ids: dict[str, Any]) -> None:
    s = six_seconds_of_ids
    assert [n for n in s["phases"]] == ["free", "foam", "wall", "all"]
    assert s["phases"]["all"]["I"] == pytest.approx(s["I"], rel=1e-12)
    assert s["phases"]["wall"]["ticks"] == 0  # a 6 s run never reaches the wall
    fwd = s["phases"]["free"]["packets_per_s"]["forward"]
    assert fwd == pytest.approx(500.0, rel=0.01)  # ids:2 sends every other tick
    wire = s["wire"]["forward"]["wire_bytes"]
    assert s["phases"]["all"]["wire_bps"]["forward"] == pytest.approx(8 * wire / 6.0, rel=1e-9)
    step = run_case(SimConfig(codec="none", duration=1.0)).summary
    assert list(step["phases"]) == ["all"]  # the step scenario has no phases


def test_a_phase_not_reached_is_shown_as_such_not_as_zero(six_seconds_of_ids: dict[str, Any]) -> None:
    """A run shorter than the scenario never reaches the wall: its I there is no figure, not 0."""
    from teleop.cli.sim import format_phases

    s = six_seconds_of_ids
    table = format_phases([{"codec": "ids:2", **s}]).splitlines()
    row = table[2].split()
    assert table[0].split()[1:] == ["I", "free", "I", "foam", "I", "wall", "I", "all"]
    assert row[3] == "-" and float(row[1]) > 0 and float(row[4]) == pytest.approx(s["I"], rel=1e-4)


# --------------------------------------------------------------------------------------------
# the handshake carries the variation
# --------------------------------------------------------------------------------------------
def _params(**kw: object) -> SessionParams:
    base = dict(session=1, codec="eds:2", scenario="protocol", dof=2, b=20.0, full_scale=2.0, duration=15.0)
    return SessionParams(**{**base, **kw}).validate()  # type: ignore[arg-type]


def test_variation_travels_in_the_hello() -> None:
    p = _params(seed=9, variation=1.25)
    msg = p.to_msg()
    assert msg["variation"] == 1.25 and msg["seed"] == 9
    assert SessionParams.from_msg(msg) == p
    scripted = _params()
    assert "variation" not in scripted.to_msg()  # 0 is left out: older hellos mean the scripted run
    assert SessionParams.from_msg(scripted.to_msg()).variation == 0.0


@pytest.mark.parametrize("bad", [2.5, -0.1, True, "1", float("nan")])
def test_a_peer_variation_out_of_range_is_refused(bad: object) -> None:
    msg = _params().to_msg()
    msg["variation"] = bad
    with pytest.raises(ProtocolError, match="variation"):
        SessionParams.from_msg(msg)


# --------------------------------------------------------------------------------------------
# aggregation and the command
# --------------------------------------------------------------------------------------------
def _run(seed: int, i_free: float, passive: bool = True) -> experiment.RunResult:
    def block(i: float) -> dict[str, object]:
        return {
            "I": i,
            "I_dof": [i / 4, 3 * i / 4],
            "start": 0.0,
            "end": 1.0,
            "ticks": 1000,
            "packets_per_s": {"forward": 500.0, "backward": 250.0},
            "wire_bps": {"forward": 1e5, "backward": 5e4},
        }

    return experiment.RunResult(seed, passive, {"free": block(i_free), "all": block(2 * i_free)})


def test_aggregate_mean_and_sample_spread() -> None:
    runs = {
        "none": [_run(s, x) for s, x in enumerate((1.0, 2.0, 4.0))],
        "eds:2": [_run(s, 3.0, passive=s != 1) for s in range(3)],
    }
    doc = experiment.aggregate(runs, 3, False, {"scenario": "protocol"})
    assert doc["runs"] == 3 and doc["real"] is False and doc["scenario"] == "protocol"
    none, eds = doc["cases"]
    assert none["reference"] and not eds["reference"]
    i = none["phases"]["free"]["I"]
    assert i["mean"] == pytest.approx(7 / 3) and i["std"] == pytest.approx(np.std([1, 2, 4], ddof=1))
    assert (i["min"], i["max"]) == (1.0, 4.0)
    assert none["phases"]["free"]["I_dof"][1]["mean"] == pytest.approx(7 / 4)
    assert none["phases"]["all"]["packets_per_s"] == {"forward": 500.0, "backward": 250.0}
    assert none["passive"] and not eds["passive"]
    assert "I_over_reference" not in none["phases"]["free"]
    ratio = eds["phases"]["free"]["I_over_reference"]  # 3 over 1, 2 and 4, seed by seed
    assert ratio["mean"] == pytest.approx((3 + 1.5 + 0.75) / 3) and (ratio["min"], ratio["max"]) == (
        0.75,
        3.0,
    )
    assert [r["seed"] for r in eds["per_run"]] == [0, 1, 2]
    assert "free" in experiment.format_table(doc)
    assert "eds:2" in experiment.format_paired(doc) and "0.75..3" in experiment.format_paired(doc)


def test_experiment_command_writes_json_and_figure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["experiment", "--runs", "2", "--codec", "none", "--codec", "ids:50", "--duration", "7.5"]
    rc = main([*args, "--out", str(tmp_path)])
    assert rc == 0
    doc = json.loads((tmp_path / "experiment.json").read_text())
    assert doc["runs"] == 2 and doc["real"] is False and doc["variation"] == 1.0
    assert [c["codec"] for c in doc["cases"]] == ["none", "ids:50"]
    for c in doc["cases"]:
        assert c["passive"] is True
        assert set(c["phases"]) == {"free", "foam", "all"}  # the wall phase was never reached
        for ph in c["phases"].values():
            assert set(ph["I"]) == {"mean", "std", "min", "max"}
            assert set(ph["packets_per_s"]) == {"forward", "backward"}
            assert set(ph["wire_bps"]) == {"forward", "backward"}
        # Two different humans: a spread, and both seeds recorded.
        assert c["phases"]["free"]["I"]["std"] > 0
        assert [r["seed"] for r in c["per_run"]] == [0, 1]
    none, ids = doc["cases"]
    assert ids["phases"]["free"]["I"]["mean"] > 10 * none["phases"]["free"]["I"]["mean"]
    assert (tmp_path / "fig15.png").stat().st_size > 10_000
    assert "ids:50" in capsys.readouterr().out


def test_experiment_exits_1_when_a_run_is_not_passive(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(experiment, "sim_run", lambda base, codec, seed: _run(seed, 1.0, seed != 1))
    rc = main(["experiment", "--runs", "3", "--codec", "eds:2", "--out", str(tmp_path)])
    assert rc == 1
    assert "eds:2 seed 1: NOT PASSIVE" in capsys.readouterr().out


@pytest.mark.parametrize(
    "args,msg",
    [
        (["--runs", "0"], "runs must be"),
        (["--variation", "3"], "variation must be 0 to 2"),
        (["--transport", "zenoh"], "add --real"),
        (["--real", "--delay", "5"], "--delay is for the simulation"),
        (["--seed", str(MAX_SEED), "--runs", "2"], "--seed + --runs - 1 must be at most"),
    ],
)
@pytest.mark.integration  # the CLI as a process
def test_experiment_bad_arguments(tmp_path: Path, args: list[str], msg: str) -> None:
    cmd = [sys.executable, "-m", "teleop.cli", "experiment", *args, "--out", str(tmp_path)]
    r = subprocess.run(cmd, capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.startswith("teleop: error:") and msg in r.stderr


@pytest.mark.integration  # the CLI as a process
def test_real_experiment_runs_sessions_with_the_seeded_human(tmp_path: Path) -> None:
    """Two real processes per run; the teleoperator learns seed and variation from the handshake."""
    args = ["experiment", "--real", "--runs", "1", "--seed", "6", "--variation", "1.5", "--codec", "eds:2"]
    rc = main([*args, "--duration", "1", "--keep-logs", "--out", str(tmp_path)])
    assert rc == 0
    run_dir = tmp_path / "runs" / "eds_2-seed6"
    for role in ("operator", "teleoperator"):
        params = json.loads((run_dir / "logs" / f"{role}.json").read_text())["params"]
        assert (params["seed"], params["variation"]) == (6, 1.5)
    rep = json.loads((run_dir / "report.json").read_text())
    assert rep["phases"]["all"]["I"] == pytest.approx(rep["transparency"]["I"], rel=1e-9)
    doc = json.loads((tmp_path / "experiment.json").read_text())
    (case,) = doc["cases"]
    assert doc["real"] is True and case["passive"] and case["completed"] == 1
    assert case["phases"]["free"]["packets_per_s"]["forward"] == pytest.approx(500.0, rel=0.05)
    assert set(case["per_run"][0]["host"]) == {"overruns", "late_packets_missed", "watchdog_violations"}


def test_a_real_run_a_process_joined_late_is_incomplete() -> None:
    def report(op: int, to: int, both: int) -> dict[str, object]:
        procs = {"operator": {"loop": {"ticks": op}}, "teleoperator": {"loop": {"ticks": to}}}
        return {"duration_s": 15.0, "transparency": {"ticks_compared": both}, "processes": procs}

    assert experiment.incomplete(report(14500, 14480, 14450)) is None  # a few stalled ticks
    why = experiment.incomplete(report(14873, 6241, 6241))
    assert why is not None and "only 6241 of 15000 ticks" in why


def test_a_phase_a_run_barely_entered_is_left_out_of_the_experiment() -> None:
    """A 5 s run of the protocol enters its foam for a few ticks: that I is no measure of the foam
    (3.5e-7 in one such run), and fig15 drew it; a phase under MIN_PHASE_S is left out."""
    run = _run(0, 1.0)
    brief = dict(run.phases["free"], start=5.0, end=5.0 + 0.5 * experiment.MIN_PHASE_S, ticks=500)
    run.phases["foam"] = brief
    doc = experiment.aggregate({"none": [run]}, 1, False, {"scenario": "protocol"})
    assert set(doc["cases"][0]["phases"]) == {"free", "all"}
    run.phases["foam"] = dict(brief, end=5.0 + experiment.MIN_PHASE_S)
    doc = experiment.aggregate({"none": [run]}, 1, False, {"scenario": "protocol"})
    assert set(doc["cases"][0]["phases"]) == {"free", "foam", "all"}
