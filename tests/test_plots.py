"""Every figure is fit for a paper (issue 48): units (µs, kbit/s), a title that says what ran and over
which link, both directions legible, log axes where the data spans decades, the task's phases
shaded, no bars on a log axis.  Checked on the figure objects, before any PNG is written."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from teleop.offline import plots
from teleop.offline.report import figure_title

ROOT = Path(__file__).resolve().parent.parent
T = np.arange(0, 12.0, 0.001)


@pytest.fixture(autouse=True)
def _close() -> Any:
    yield
    plots._plt().close("all")


def test_the_signals_have_units_a_title_and_the_phases_shaded() -> None:
    v = np.column_stack([np.sin(T), np.cos(T)])
    phases = {"free": (0.0, 5.0), "foam": (5.0, 10.0), "wall": (10.0, 12.0)}
    what = "eds:50, wave variables, over udp, netem delay 10ms"
    fig = plots.velocity_force_figure(T, v, v, v, v, what, phases)
    top, bottom = fig.axes
    assert top.get_ylabel() == "velocity [m/s]" and bottom.get_ylabel() == "force [N]"
    assert bottom.get_xlabel() == "time [s]" and "netem delay 10ms" in fig._suptitle.get_text()
    assert len(top.patches) == 3  # one band a phase
    assert {t.get_text() for t in top.texts} == {"free", "foam", "wall"}


def test_bandwidth_is_on_log_axes_with_each_direction_its_own_colour() -> None:
    w = np.full(T.size // 100, 200.0, dtype=np.float64)
    base = np.full(w.size, 10_000.0, dtype=np.float64)
    t = np.arange(w.size, dtype=np.float64) * 0.1
    fig = plots.bandwidth_figure(0.1, {"forward": (t, w, base), "backward": (t, w, base)}, "x over udp")
    wire, comp = fig.axes
    assert wire.get_yscale() == "log" and comp.get_yscale() == "log"
    assert "kbit/s" in wire.get_ylabel() and "compression" in comp.get_ylabel()
    colors = {line.get_label().split(":")[0]: line.get_color() for line in wire.get_lines()}
    assert colors["forward"] != colors["backward"]
    widths = {line.get_label(): line.get_linewidth() for line in wire.get_lines()}
    assert widths["forward: sent"] > widths["backward: sent"]  # one rate: both stay visible
    assert fig._suptitle.get_text() == "x over udp"


def test_loop_timing_is_in_microseconds_on_a_log_count_axis() -> None:
    lat = {"operator": (np.array([1.0, 50.0, 900.0]), np.array([900.0, 90.0, 1.0]))}
    ax = plots.timing_figure(lat, "t").axes[0]
    assert "[µs]" in ax.get_xlabel() and "us]" not in ax.get_xlabel().replace("µs]", "")
    assert ax.get_yscale() == "log" and ax.get_title() == "t"


def test_the_energy_margin_is_drawn_as_its_band_not_a_solid_block() -> None:
    margin = 0.005 + 0.004 * np.sign(np.sin(T * 2 * np.pi * 20))  # saws every 25 ticks
    series = {"forward": (np.cumsum(np.abs(margin)), np.cumsum(np.abs(margin)) * 0.99, margin)}
    fig = plots.energy_figure(T, series, "e")
    lower = fig.axes[1]
    (line,) = [ln for ln in lower.get_lines() if ln.get_label().startswith("forward")]
    assert len(line.get_xdata()) <= 400  # one point per span of the run, its lowest value
    assert float(np.min(line.get_ydata())) == pytest.approx(0.001)
    assert lower.get_ylabel() == "observed margin [J]"


def test_fig15_has_no_bars_on_its_log_axis() -> None:
    doc = json.loads((ROOT / "docs" / "experiment" / "sim" / "experiment.json").read_text())
    fig = plots.experiment_figure(doc, plots.experiment_title(doc))
    ax = fig.axes[0]
    assert ax.get_yscale() == "log" and not ax.patches  # markers with error bars, no bar patches
    assert ax.get_axisbelow() is True  # the grid behind the data
    assert "runs per codec" in ax.get_title() and "teleop sim" in ax.get_title()
    assert "lower is better" in ax.get_ylabel()


def test_the_fronts_name_their_codecs_and_show_the_hollow_markers() -> None:
    sweep = json.loads((ROOT / "bench" / "results" / "fronts" / "sweep.json").read_text())
    fig = plots.pareto_fronts_figure(sweep["fronts"], "s")
    for ax in fig.axes:
        assert ax.get_xscale() == "log" and ax.get_yscale() == "log"
        assert ax.texts  # every front point is named
        hollow = [c for c in ax.collections if c.get_label().endswith("(delay taken out)")]
        assert hollow and all(float(np.max(c.get_linewidths())) >= 1.0 for c in hollow)
    assert "transparency error" in fig.axes[0].get_ylabel()


def test_a_reports_figures_say_codec_architecture_transport_and_impairment() -> None:
    rep: dict[str, Any] = {
        "codec": "pdp:5",
        "architecture": "tdpa",
        "transport": "zenoh",
        "link": {"forward": {"spec": "delay 50ms"}, "backward": {"spec": "delay 50ms"}},
    }
    assert figure_title(rep) == "pdp:5, TDPA, over zenoh, netem delay 50ms"
    rep["link"] = {"forward": {"spec": ""}, "backward": {"spec": None}}
    assert figure_title(rep).endswith("no impairment")
