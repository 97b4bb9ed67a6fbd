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


def velocity_force(
    path: Path, t: Array, v_hsi: Array, v_to: Array, f_hsi: Array, f_to: Array, title: str
) -> None:
    """Two panels like the paper's Figs. 6-9, one line per DoF and side."""
    plt = _plt()
    dof = v_hsi.shape[1]
    fig, axes = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    for j in range(dof):
        sfx = f" (DoF {j})" if dof > 1 else ""
        axes[0].plot(t, v_hsi[:, j], lw=1.2, label=f"v_hsi{sfx}")
        axes[0].plot(t, v_to[:, j], lw=1.0, ls="--", label=f"v_to{sfx}")
        axes[1].plot(t, f_hsi[:, j], lw=1.2, label=f"F_hsi{sfx}")
        axes[1].plot(t, f_to[:, j], lw=1.0, ls="--", label=f"F_to{sfx}")
    axes[0].set_ylabel("velocity [m/s]")
    axes[1].set_ylabel("force [N]")
    axes[1].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    axes[0].set_title(title)
    fig.tight_layout()
    _save(fig, path, 110)
    plt.close(fig)


def bandwidth(
    path: Path, window_s: float, series: dict[str, tuple[Array, Array | None, Array | None]]
) -> None:
    """Per direction ``(t, sent, baseline)``: bytes on the wire and the uncompressed baseline over
    windows of ``window_s`` ending at ``t``, as kbit/s, and their ratio: compression over time."""
    plt = _plt()
    fig, axes = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    for name, (t, s, b) in series.items():
        if s is None or b is None:
            continue
        axes[0].plot(t, s * 8 / window_s / 1e3, label=f"{name} (sent)")
        axes[0].plot(t, b * 8 / window_s / 1e3, ls="--", lw=0.8, label=f"{name} (uncompressed baseline)")
        with np.errstate(divide="ignore", invalid="ignore"):
            axes[1].plot(t, np.where(s > 0, b / s, np.nan), label=name)
    axes[0].set_ylabel("kbit/s on the wire")
    axes[1].set_ylabel(f"compression c (per {window_s * 1e3:g} ms)")
    axes[1].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    _save(fig, path, 110)
    plt.close(fig)


def timing_histogram(path: Path, lateness_us: dict[str, tuple[Array, Array]]) -> None:
    """Histogram of each loop's tick lateness (start minus deadline), log count axis; per loop
    ``(lateness in us, ticks at it)`` (the report keeps counts, not every tick)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 4))
    hi = max((float(np.max(v)) for v, _ in lateness_us.values() if v.size), default=1.0)
    bins = np.linspace(0, max(hi, 10.0), 120)
    for name, (v, w) in lateness_us.items():
        ax.hist(v, bins=bins, weights=w, alpha=0.6, label=f"{name} ({int(w.sum())} ticks)")
    ax.set_yscale("log")
    ax.set_xlabel("tick lateness (start - deadline) [us]")
    ax.set_ylabel("ticks")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    _save(fig, path, 110)
    plt.close(fig)


def energy(path: Path, t: Array, series: dict[str, tuple[Array, Array, Array]]) -> None:
    """Per direction: wave energy sent and played (eq. 4-5), and the watchdog's observed margin."""
    plt = _plt()
    fig, axes = plt.subplots(2, 1, figsize=(8, 5.5), sharex=True)
    for name, (sent, played, margin) in series.items():
        axes[0].plot(t, sent, label=f"{name}: sent")
        axes[0].plot(t, played, ls="--", label=f"{name}: played")
        axes[1].plot(t, margin, label=f"{name}: reported sent - played")
    axes[1].axhline(0.0, color="k", lw=0.8)
    axes[0].set_ylabel("wave energy [J]")
    axes[1].set_ylabel("observed margin [J]")
    axes[1].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    _save(fig, path, 110)
    plt.close(fig)


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


def pareto_fronts(path: Path, docs: list[dict[str, Any]], title: str) -> None:
    """One panel per impairment: each architecture's cases and its Pareto front (I against the wire
    rate of both directions), and I_dc (eq. 7 with the measured one-way delays taken out) as hollow
    markers: what is left of the error once the delay is removed."""
    plt = _plt()
    nets = list(dict.fromkeys(d["netem"]["forward"] for d in docs))
    fig, axes = plt.subplots(1, len(nets), figsize=(4.6 * len(nets), 4.4), squeeze=False)
    colors = {"wave": "tab:blue", "tdpa": "tab:red"}
    for ax, net in zip(axes[0], nets, strict=True):
        for d in (d for d in docs if d["netem"]["forward"] == net):
            arch, color = d["passivity"], colors.get(d["passivity"], "k")
            cs = d["cases"]
            x = [sum(c["wire_bps"].values()) / 1e3 for c in cs]
            ax.scatter(x, [max(c["I"], 1e-12) for c in cs], s=14, color=color, alpha=0.6, label=f"{arch}: I")
            ax.scatter(x, [max(c["I_dc"], 1e-12) for c in cs], s=14, facecolors="none", edgecolors=color,
                       alpha=0.6, label=f"{arch}: I_dc")  # fmt: skip
            front = sorted((c for c in cs if c.get("pareto")), key=lambda c: sum(c["wire_bps"].values()))
            if front:
                fx = [sum(c["wire_bps"].values()) / 1e3 for c in front]
                fy = [max(c["I"], 1e-12) for c in front]
                ax.step(fx, fy, where="post", color=color, lw=1.2, label=f"{arch}: front (I)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("wire rate, both directions [kbit/s]")
        ax.set_title(net or "no impairment", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("I (eq. 7) / I_dc, lower is better")
    axes[0][-1].legend(fontsize=7, loc="best")
    fig.suptitle(title)
    fig.tight_layout()
    _save(fig, path, 110)
    plt.close(fig)


def experiment_bars(path: Path, doc: dict[str, Any], title: str) -> None:
    """Fig. 15: per phase, one bar per codec (mean I over the runs, +-1 std), log scale; the
    no-LDR reference (``none``) drawn as a dashed line across each group instead of a bar."""
    plt = _plt()
    phases = [n for n in ("free", "foam", "wall", "all") if any(n in c["phases"] for c in doc["cases"])]
    ref = next((c for c in doc["cases"] if c["reference"]), None)
    bars = [c for c in doc["cases"] if not c["reference"]]
    fig, ax = plt.subplots(figsize=(8.5, 4.6))
    width = 0.8 / max(1, len(bars))
    x = np.arange(len(phases), dtype=np.float64)
    for i, c in enumerate(bars):
        st = [c["phases"].get(n, {}).get("I", {}) for n in phases]
        mean = np.array([s.get("mean") or np.nan for s in st])
        std = np.array([s.get("std") or 0.0 for s in st])
        lower = np.minimum(std, 0.95 * mean)  # a log axis has no room below 0
        ax.bar(x - 0.4 + (i + 0.5) * width, mean, width, yerr=[lower, std], capsize=2, label=c["codec"])
    if ref is not None:
        for k, n in enumerate(phases):
            s = ref["phases"].get(n, {}).get("I", {})
            if s.get("mean"):
                ax.hlines(s["mean"], k - 0.45, k + 0.45, colors="k", linestyles="--", lw=1.2)
        ax.plot([], [], "k--", lw=1.2, label=f"{ref['codec']} (no LDR, reference)")
    ax.set_yscale("log")
    ax.set_xticks(x, [n if n != "all" else "whole run" for n in phases])
    ax.set_ylabel("transparency I (lower is better)")
    ax.set_title(title, fontsize=10)
    ax.grid(axis="y", alpha=0.3, which="both")
    ax.legend(fontsize=8, ncol=min(7, len(bars) + 1), loc="upper center", bbox_to_anchor=(0.5, -0.09))
    fig.tight_layout()
    _save(fig, path, 90)
    plt.close(fig)
