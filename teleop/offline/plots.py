"""PNG figures (matplotlib, headless Agg backend): HSI vs TO velocity and force over time."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

Array = npt.NDArray[np.float64]


def _plt() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig: Any, path: Path, dpi: int) -> None:
    """The figure as a PNG in a new file (``teleop.files.write_new``: never over a file, never
    through a symlink)."""
    import io

    from teleop.files import write_new

    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format="png")
    write_new(path, buf.getvalue())


def safe_name(spec: str) -> str:
    return spec.replace(":", "_").replace("/", "_").replace(".", "p")


#: Each direction's colour in every figure: forward (operator -> robot) and backward.
DIRECTION_COLOR = {"forward": "tab:blue", "backward": "tab:orange"}
#: The protocol task's phases, shaded behind the signals (the report's ``phases``).
PHASE_COLOR = {"free": "#ffffff", "foam": "#e8f0e0", "wall": "#f6e3d6"}


def _finish(fig: Any, path: Path, dpi: int = 110) -> None:
    fig.tight_layout()
    _save(fig, path, dpi)
    _plt().close(fig)


def _shade(ax: Any, phases: dict[str, tuple[float, float]] | None) -> None:
    """The task's phases as bands behind the data, named at the top of the panel."""
    for name, (a, b) in (phases or {}).items():
        if name in PHASE_COLOR and b > a:
            ax.axvspan(a, b, color=PHASE_COLOR[name], zorder=0, lw=0)
            ax.text((a + b) / 2, 1.0, name, transform=ax.get_xaxis_transform(), ha="center", va="bottom",
                    fontsize=7, color="0.35")  # fmt: skip


def velocity_force_figure(
    t: Array,
    v_hsi: Array,
    v_to: Array,
    f_hsi: Array,
    f_to: Array,
    title: str,
    phases: dict[str, tuple[float, float]] | None = None,
) -> Any:
    """Two panels like the paper's Figs. 6-9, one line per DoF and side, the task's phases shaded."""
    plt = _plt()
    dof = v_hsi.shape[1]
    fig, axes = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    for j in range(dof):
        sfx = f" (DoF {j})" if dof > 1 else ""
        c = f"C{j % 10}"  # one colour per DoF: the HSI solid, the robot dashed over it
        axes[0].plot(t, v_hsi[:, j], color=c, lw=1.4, alpha=0.8, label=f"v HSI{sfx}")
        axes[0].plot(t, v_to[:, j], color="k" if dof == 1 else c, lw=0.9, ls="--", label=f"v robot{sfx}")
        axes[1].plot(t, f_hsi[:, j], color=c, lw=1.4, alpha=0.8, label=f"F HSI{sfx}")
        axes[1].plot(t, f_to[:, j], color="k" if dof == 1 else c, lw=0.9, ls="--", label=f"F robot{sfx}")
    axes[0].set_ylabel("velocity [m/s]")
    axes[1].set_ylabel("force [N]")
    axes[1].set_xlabel("time [s]")
    for ax in axes:
        _shade(ax, phases)
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    fig.suptitle(title, fontsize=10)
    return fig


def velocity_force(
    path: Path,
    t: Array,
    v_hsi: Array,
    v_to: Array,
    f_hsi: Array,
    f_to: Array,
    title: str,
    phases: dict[str, tuple[float, float]] | None = None,
) -> None:
    _finish(velocity_force_figure(t, v_hsi, v_to, f_hsi, f_to, title, phases), path)


def bandwidth_figure(
    window_s: float, series: dict[str, tuple[Array, Array | None, Array | None]], title: str = ""
) -> Any:
    """Per direction ``(t, sent, baseline)``: bytes on the wire and the uncompressed baseline over
    windows of ``window_s`` ending at ``t``, as kbit/s, and their ratio: compression over time.
    Log axes: a 20 kbit/s codec beside a 780 kbit/s baseline, and compressions from 1 to 100s."""
    plt = _plt()
    fig, axes = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    for name, (t, s, b) in series.items():
        if s is None or b is None:
            continue
        color = DIRECTION_COLOR.get(name)
        # Forward wide and pale under backward thin: two directions at one rate both stay visible.
        wide = {"lw": 3.0, "alpha": 0.45} if name == "forward" else {"lw": 1.0}
        with np.errstate(divide="ignore", invalid="ignore"):
            axes[0].plot(t, np.where(s > 0, s * 8 / window_s / 1e3, np.nan), color=color,
                         label=f"{name}: sent", **wide)  # fmt: skip
            axes[0].plot(t, b * 8 / window_s / 1e3, color=color, ls=":",
                         label=f"{name}: uncompressed (1 kHz)", **wide)  # fmt: skip
            axes[1].plot(t, np.where(s > 0, b / s, np.nan), color=color, label=name, **wide)
    from matplotlib.ticker import LogFormatter

    for ax in axes:
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(LogFormatter(labelOnlyBase=False, minor_thresholds=(2, 0.5)))
        ax.yaxis.set_minor_formatter(LogFormatter(labelOnlyBase=False, minor_thresholds=(2, 0.5)))
    axes[0].set_ylabel("on the wire [kbit/s]")
    axes[1].set_ylabel(f"compression c:1 (per {window_s * 1e3:g} ms)")
    axes[1].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3, which="both")
        ax.legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def bandwidth(
    path: Path, window_s: float, series: dict[str, tuple[Array, Array | None, Array | None]], title: str = ""
) -> None:
    _finish(bandwidth_figure(window_s, series, title), path)


def timing_figure(lateness_us: dict[str, tuple[Array, Array]], title: str = "") -> Any:
    """Histogram of each loop's tick lateness (start minus deadline), log count axis; per loop
    ``(lateness in µs, ticks at it)`` (the report keeps counts, not every tick)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4))
    hi = max((float(np.max(v)) for v, _ in lateness_us.values() if v.size), default=1.0)
    bins = np.linspace(0, max(hi, 10.0), 120)
    for name, (v, w) in lateness_us.items():
        ax.hist(v, bins=bins, weights=w, alpha=0.6, label=f"{name} ({int(w.sum())} ticks)")
    ax.set_yscale("log")
    ax.set_xlabel("tick lateness, start - deadline [µs]")
    ax.set_ylabel("ticks")
    ax.grid(alpha=0.3)
    ax.legend()
    ax.set_title(title or "the two loops' tick lateness", fontsize=10)
    return fig


def timing_histogram(path: Path, lateness_us: dict[str, tuple[Array, Array]], title: str = "") -> None:
    _finish(timing_figure(lateness_us, title), path)


def _envelope(t: Array, y: Array, bins: int = 400) -> tuple[Array, Array, Array]:
    """``y``'s lowest and highest value in each of ``bins`` spans of ``t``: a margin that saws up
    and down every few ticks is drawn as its band, not as a solid block of lines."""
    n = len(t)
    if n <= bins:
        return t, y, y
    edges = np.linspace(0, n, bins + 1).astype(int)
    lo = np.minimum.reduceat(y, edges[:-1])
    hi = np.maximum.reduceat(y, edges[:-1])
    return t[edges[:-1]], lo, hi


def energy_figure(t: Array, series: dict[str, tuple[Array, Array, Array]], title: str = "") -> Any:
    """Per direction: wave energy sent and played (eq. 4-5), and the watchdog's observed margin
    (its low edge is what passivity needs: never below 0)."""
    plt = _plt()
    fig, axes = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    for name, (sent, played, margin) in series.items():
        color = DIRECTION_COLOR.get(name)
        axes[0].plot(t, sent, color=color, label=f"{name}: sent")
        axes[0].plot(t, played, color=color, ls="--", label=f"{name}: played")
        tb, lo, hi = _envelope(t, np.asarray(margin, dtype=np.float64))
        axes[1].fill_between(tb, lo, hi, color=color, alpha=0.25, lw=0)
        axes[1].plot(tb, lo, color=color, lw=1.0, label=f"{name}: reported sent - played (lowest)")
    axes[1].axhline(0.0, color="k", lw=0.8)
    axes[0].set_ylabel("wave energy [J]")
    axes[1].set_ylabel("observed margin [J]")
    axes[1].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title, fontsize=10)
    return fig


def energy(path: Path, t: Array, series: dict[str, tuple[Array, Array, Array]], title: str = "") -> None:
    _finish(energy_figure(t, series, title), path)


def pareto(path: Path, cases: list[dict[str, Any]], title: str) -> None:
    """Transparency I against total wire rate, log scales, every case labelled, the front drawn."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(9, 6))
    families: dict[str, list[dict[str, Any]]] = {}
    for c in cases:
        families.setdefault(c["codec"].split(":")[0], []).append(c)
    for fam, cs in families.items():
        x = [sum(c["wire_bps"].values()) / 1e3 for c in cs]
        y = [max(c["I"], 1e-12) for c in cs]
        ax.scatter(x, y, s=28, label=fam, zorder=3)
        for c, xi, yi in zip(cs, x, y, strict=True):
            ax.annotate(c["codec"], (xi, yi), fontsize=7, xytext=(3, 3), textcoords="offset points")
    front = sorted((c for c in cases if c.get("pareto")), key=lambda c: sum(c["wire_bps"].values()))
    if front:
        ax.step(
            [sum(c["wire_bps"].values()) / 1e3 for c in front],
            [max(c["I"], 1e-12) for c in front],
            where="post",
            color="k",
            lw=1.0,
            ls="--",
            label="Pareto front",
            zorder=2,
        )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("wire rate, both directions [kbit/s]")
    ax.set_ylabel("transparency I (eq. 7), lower is better")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, path, 110)
    plt.close(fig)


def pareto_fronts_figure(docs: list[dict[str, Any]], title: str) -> Any:
    """One panel per impairment: each architecture's cases and its Pareto front (I against the wire
    rate of both directions), every front point named by its codec, and I_dc (eq. 7 with the
    measured one-way delays taken out) as hollow markers: what is left once the delay is removed."""
    plt = _plt()
    nets = list(dict.fromkeys(d["netem"]["forward"] for d in docs))
    fig, axes = plt.subplots(1, len(nets), figsize=(4.8 * len(nets), 4.8), squeeze=False)
    colors = {"wave": "tab:blue", "tdpa": "tab:red"}
    for ax, net in zip(axes[0], nets, strict=True):
        for d in (d for d in docs if d["netem"]["forward"] == net):
            arch, color = d["passivity"], colors.get(d["passivity"], "k")
            cs = d["cases"]
            x = [sum(c["wire_bps"].values()) / 1e3 for c in cs]
            ax.scatter(x, [max(c["I"], 1e-12) for c in cs], s=16, color=color, alpha=0.8, label=f"{arch}: I",
                       zorder=3)  # fmt: skip
            ax.scatter(x, [max(c["I_dc"], 1e-12) for c in cs], s=22, facecolors="none", edgecolors=color,
                       linewidths=1.1, label=f"{arch}: I_dc (delay taken out)", zorder=3)  # fmt: skip
            front = sorted((c for c in cs if c.get("pareto")), key=lambda c: sum(c["wire_bps"].values()))
            if front:
                fx = [sum(c["wire_bps"].values()) / 1e3 for c in front]
                fy = [max(c["I"], 1e-12) for c in front]
                ax.step(fx, fy, where="post", color=color, lw=1.2, label=f"{arch}: front of I", zorder=2)
                for c, xi, yi in zip(front, fx, fy, strict=True):
                    ax.annotate(c["codec"], (xi, yi), fontsize=6, color=color, xytext=(3, 2),
                                textcoords="offset points")  # fmt: skip
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wire rate, both directions [kbit/s]")
        ax.set_title(net or "no impairment", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
        ax.set_axisbelow(True)
    axes[0][0].set_ylabel("transparency error (eq. 7), lower is better")
    axes[0][-1].legend(fontsize=7, loc="best")
    fig.suptitle(title)
    return fig


def pareto_fronts(path: Path, docs: list[dict[str, Any]], title: str) -> None:
    _finish(pareto_fronts_figure(docs, title), path)


def experiment_figure(doc: dict[str, Any], title: str) -> Any:
    """Fig. 15 as a dot plot: per phase, one marker per codec (mean I over the runs, a bar of +-1
    std), log scale; the no-LDR reference (``none``) as a dashed line across each group.  Markers,
    not bars: a bar on a log axis starts from an arbitrary floor, and its height means nothing."""
    plt = _plt()
    phases = [n for n in ("free", "foam", "wall", "all") if any(n in c["phases"] for c in doc["cases"])]
    ref = next((c for c in doc["cases"] if c["reference"]), None)
    dots = [c for c in doc["cases"] if not c["reference"]]
    fig, ax = plt.subplots(figsize=(8.5, 4.6))
    width = 0.8 / max(1, len(dots))
    x = np.arange(len(phases), dtype=np.float64)
    for i, c in enumerate(dots):
        st = [c["phases"].get(n, {}).get("I", {}) for n in phases]
        mean = np.array([s.get("mean") or np.nan for s in st])
        std = np.array([s.get("std") or 0.0 for s in st])
        lower = np.minimum(std, 0.95 * mean)  # a log axis has no room below 0
        ax.errorbar(x - 0.4 + (i + 0.5) * width, mean, yerr=[lower, std], fmt="o", ms=5, capsize=2,
                    label=c["codec"], zorder=3)  # fmt: skip
    if ref is not None:
        for k, n in enumerate(phases):
            s = ref["phases"].get(n, {}).get("I", {})
            if s.get("mean"):
                ax.hlines(s["mean"], k - 0.45, k + 0.45, colors="k", linestyles="--", lw=1.2, zorder=2)
        ax.plot([], [], "k--", lw=1.2, label=f"{ref['codec']} (no LDR, reference)")
    for k in range(1, len(phases)):
        ax.axvline(k - 0.5, color="0.8", lw=0.8, zorder=1)
    ax.set_yscale("log")
    ax.set_xticks(x, [n if n != "all" else "whole run" for n in phases])
    ax.set_ylabel("transparency error I (eq. 7), lower is better")
    ax.set_title(title, fontsize=10)
    ax.grid(axis="y", alpha=0.3, which="both")
    ax.set_axisbelow(True)
    ax.legend(fontsize=8, ncol=min(7, len(dots) + 1), loc="upper center", bbox_to_anchor=(0.5, -0.09))
    return fig


def experiment_bars(path: Path, doc: dict[str, Any], title: str) -> None:
    """Fig. 15 (:func:`experiment_figure`) as a PNG."""
    _finish(experiment_figure(doc, title), path, 90)


def experiment_title(doc: dict[str, Any]) -> str:
    """Fig. 15's title from an experiment's own record: what ran, where, over which links."""
    net = doc.get("netem") or {}
    fwd, bwd = net.get("forward") or "", net.get("backward") or ""
    links = "no impairment" if not fwd and not bwd else f"netem {fwd or 'none'} / {bwd or 'none'}"
    where = f"real sessions over {doc.get('transport')}" if doc.get("real") else "teleop sim"
    arch = "TDPA" if doc.get("passivity") == "tdpa" else "wave variables"
    return (
        f"{doc.get('scenario')}: {doc.get('runs')} runs per codec (variation {doc.get('variation', 0):g}), "
        f"mean ± std; {arch}, {where}, {links}"
    )
