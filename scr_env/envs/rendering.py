"""Matplotlib plots of an episode (imported only when rendering)."""
from __future__ import annotations

from typing import Any

import numpy as np


def _pyplot() -> Any:
    try:
        import matplotlib

        if matplotlib.get_backend().lower() not in ("agg",) and not _has_display():
            matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover - matplotlib is a core dependency
        raise ImportError("rendering needs matplotlib: pip install matplotlib") from e
    return plt


def _has_display() -> bool:
    import os

    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def episode_figure(history: np.ndarray, fig: Any = None) -> Any:
    """Plot (time, NOx in, NOx out, NH3 out, AdBlue g/s, inlet temperature K, mean coverage) rows."""
    plt = _pyplot()
    if fig is None:
        fig = plt.figure(figsize=(8, 6), dpi=80)
    fig.clf()
    axes = fig.subplots(3, 1, sharex=True)
    if history.size == 0:
        history = np.zeros((1, 7))
    t = history[:, 0]
    axes[0].plot(t, history[:, 1], color="0.6", lw=0.8, label="engine-out NOx")
    axes[0].plot(t, history[:, 2], color="C0", lw=0.9, label="tailpipe NOx")
    axes[0].plot(t, history[:, 3], color="C3", lw=0.9, label="NH3 slip")
    axes[0].set_ylabel("ppm")
    axes[0].legend(loc="upper right", fontsize=7)
    axes[1].plot(t, history[:, 5], color="C1", lw=0.9)
    axes[1].set_ylabel("SCR inlet T [K]")
    axes[2].plot(t, history[:, 4], color="C2", lw=0.9, label="AdBlue [g/s]")
    ax2 = axes[2].twinx()
    ax2.plot(t, history[:, 6], color="C4", lw=0.9, label="mean NH3 coverage")
    ax2.set_ylabel("coverage [-]", color="C4")
    ax2.set_ylim(0, 1)
    axes[2].set_ylabel("AdBlue [g/s]", color="C2")
    axes[2].set_xlabel("time [s]")
    fig.tight_layout()
    return fig


def figure_to_rgb(fig: Any) -> np.ndarray:
    """(H, W, 3) uint8 image of a figure."""
    fig.canvas.draw()
    rgba = np.asarray(fig.canvas.buffer_rgba())
    return np.ascontiguousarray(rgba[..., :3])
