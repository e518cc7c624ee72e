"""Figures of closed-loop episodes (matplotlib, imported when a figure is drawn; written atomically).

    from control.plots import closed_loop_figure
    closed_loop_figure([(r.name, r.kpis, r.trajectory) for r in results], "closed loop on the hot WHTC", path)
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from scr_env.fileio import atomic_path

__all__ = ["closed_loop_figure", "pyplot"]


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the non-interactive Agg backend; ``ImportError`` naming the package if missing."""
    try:
        import matplotlib
    except ImportError as exc:
        raise ImportError("figures need matplotlib (pip install matplotlib)") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def closed_loop_figure(runs: Sequence[tuple[str, Mapping[str, float], Mapping[str, Any]]], title: str,
                       path: str | Path, coverage: bool = True, slip_log: bool = False, dpi: int = 110) -> Path | None:
    """Closed-loop trajectories of several controllers on one cycle, one row of panels per signal: SCR inlet
    temperature [C] (of the first run), tailpipe NOx [ppm] (symlog; engine-out NOx in grey if recorded), NH3 slip
    [ppm] (symlog with ``slip_log``), AdBlue [g/s] and, with ``coverage``, the mean NH3 coverage [-].

    ``runs``: ``(name, kpis, trajectory)`` per controller, the trajectory's signals as recorded by
    :func:`control.evaluation.evaluate` (``record_trajectory=True``; lists or arrays). The legend quotes each run's
    tailpipe NOx [g/kWh] and mean slip [ppm]. Nothing is drawn for an empty ``runs`` (returns None)."""
    runs = [r for r in runs if r[2]]
    if not runs:
        return None
    plt = pyplot()
    rows = 5 if coverage else 4
    fig, ax = plt.subplots(rows, 1, figsize=(13 if coverage else 12, 13 if coverage else 11), sharex=True)
    tr0 = runs[0][2]
    t = np.asarray(tr0["time_s"])
    ax[0].plot(t, np.asarray(tr0["inlet_temperature_k"]) - 273.15, "k", lw=0.8)
    ax[0].set_ylabel("SCR inlet T [C]")
    if "engine_out_nox_ppm" in tr0:
        ax[1].plot(t, tr0["engine_out_nox_ppm"], color="0.7", lw=0.6, label="engine-out")
    for name, k, tr in runs:
        lab = (f"{name} ({k.get('tailpipe_nox_g_per_kwh', np.nan):.3f} g/kWh, "
               f"{k.get('mean_nh3_slip_ppm', np.nan):.1f} ppm)")
        ax[1].plot(t, tr["tailpipe_nox_ppm"], lw=0.7, label=lab)
        ax[2].plot(t, tr["tailpipe_nh3_ppm"], lw=0.7, label=name)
        ax[3].plot(t, tr["adblue_g_s"], lw=0.7, label=name)
        if coverage:
            ax[4].plot(t, tr["mean_coverage"], lw=0.9, label=name)
    ax[1].set_ylabel("tailpipe NOx [ppm]")
    ax[1].set_yscale("symlog", linthresh=10)
    ax[1].legend(fontsize=7, loc="upper right")
    ax[2].set_ylabel("NH3 slip [ppm]")
    if slip_log:
        ax[2].set_yscale("symlog", linthresh=10)
    ax[3].set_ylabel("AdBlue [g/s]")
    if coverage:
        ax[4].set_ylabel("mean NH3 coverage [-]")
        ax[4].legend(fontsize=7)
    ax[-1].set_xlabel("time [s]")
    fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)
    return path
