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
    fig.savefig(path, dpi=110)
    plt.close(fig)
