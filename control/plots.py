"""Figures of closed-loop episodes (matplotlib, imported when a figure is drawn; written atomically).

    from control.plots import closed_loop_figure
    closed_loop_figure([(r.name, r.kpis, r.trajectory) for r in results], "closed loop on the hot WHTC", path)
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from scr_env.constants import EURO_VI_NH3_SLIP_LIMIT_PPM
from scr_env.fileio import atomic_path

__all__ = ["ageing_figures", "closed_loop_figure", "fit_bar_chart", "pyplot"]


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


def fit_bar_chart(fits: Mapping[str, Mapping[str, float]], outputs: Sequence[str], title: str,
                  path: str | Path, ylabel: str = "validation FIT [%] (clipped at -50)") -> Path:
    """Grouped bars of a FIT [%] per model (``fits``: model -> {output: FIT}, in the order of ``outputs``),
    clipped at -50 % so that one diverging model does not flatten the others."""
    plt = pyplot()
    names = list(fits)
    fig, ax = plt.subplots(figsize=(9, 4.5))
    width = 0.8 / max(len(names), 1)
    for i, n in enumerate(names):
        vals = list(fits[n].values())[:len(outputs)]
        ax.bar(np.arange(len(vals)) + i * width, np.clip(vals, -50, 100), width, label=n)
    ax.set_xticks(np.arange(len(outputs)) + 0.4 - width / 2, list(outputs))
    ax.axhline(0, color="k", lw=0.8)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    return path


def ageing_figures(doc: Mapping[str, Any], history: np.ndarray, out: str | Path,
                   slip_target_ppm: float = EURO_VI_NH3_SLIP_LIMIT_PPM) -> list[Path]:
    """The ageing study's figures in ``out``: ``kpis_vs_cycle.png`` (mean and peak slip, tailpipe NOx and AdBlue of
    the fixed and the adaptive NMPC per cycle) and, if the adaptive run logged any, ``parameter_tracking.png`` (the
    RPEM's retention estimates over the sequence, episodes back to back, against the true retentions).
    ``doc``: the study's JSON (``cycles`` with ``fixed``, ``adaptive`` and ``estimates``); ``history``: rows
    (episode, t s, d_cap, d_act)."""
    plt = pyplot()
    out = Path(out)
    cyc = doc["cycles"]
    idx = [c["index"] for c in cyc]
    sev = [c["severity"] for c in cyc]
    fig, ax = plt.subplots(2, 2, figsize=(12, 8))
    for key, a, lab in (("mean_nh3_slip_ppm", ax[0, 0], "mean NH3 slip [ppm]"),
                        ("peak_nh3_slip_ppm", ax[0, 1], "peak NH3 slip [ppm]"),
                        ("tailpipe_nox_g_per_kwh", ax[1, 0], "tailpipe NOx [g/kWh]"),
                        ("adblue_g", ax[1, 1], "AdBlue [g]")):
        for who, st in (("fixed", "o-"), ("adaptive", "s-")):
            a.plot(idx, [c[who].get(key, np.nan) for c in cyc], st, label=f"{who} MPC")
        a.set_ylabel(lab)
        a.set_xlabel("cycle (severity " + ", ".join(f"{s:.2f}" for s in sev) + ")")
        a.grid(alpha=0.3)
    ax[0, 0].axhline(slip_target_ppm, color="r", ls="--", lw=0.8, label=f"{slip_target_ppm:g} ppm target")
    ax[0, 0].legend()
    fig.suptitle("closed loop over the ageing sequence: fixed vs RPEM-adapted grey-box MPC")
    fig.tight_layout()
    paths = [out / "kpis_vs_cycle.png"]
    with atomic_path(paths[0]) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    history = np.asarray(history)
    if history.size == 0:
        return paths
    fig, ax = plt.subplots(2, 1, figsize=(12, 7), sharex=True)
    # a continuous time axis over the sequence
    t = np.zeros(len(history))
    offset, last_c, last_t = 0.0, history[0, 0], 0.0
    for i, (c, tt, _, _) in enumerate(history):
        if c != last_c:
            offset += last_t + 0.5
            last_c = c
        t[i] = offset + tt
        last_t = tt
    bounds_t = [t[np.argmax(history[:, 0] == c["index"])] for c in cyc]
    ends = [*bounds_t[1:], t[-1]]
    for j, (name, key) in enumerate((("storage capacity", "true_capacity_retention"),
                                     ("SCR/oxidation activity", "true_activity_retention"))):
        ax[j].plot(t, np.exp(history[:, 2 + j]), lw=1.0, label="RPEM estimate (relative to the fresh model)")
        for c, t0, t1 in zip(cyc, bounds_t, ends, strict=True):
            ax[j].hlines(c["estimates"][key], t0, t1, colors="k", lw=1.5)
        ax[j].plot([], [], "k", label="true retention (plant)")
        ax[j].set_ylabel(f"{name} retention [-]")
        ax[j].legend(fontsize=8)
        ax[j].grid(alpha=0.3)
    ax[1].set_xlabel("time over the sequence [s] (episodes back to back)")
    fig.suptitle("online parameter tracking (RPEM, tailpipe NOx sensor only)")
    fig.tight_layout()
    paths.append(out / "parameter_tracking.png")
    with atomic_path(paths[1]) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)
    return paths


def learning_curve_figure(curves: Mapping[str, Sequence[Mapping[str, Any]]], title: str) -> Any:
    """Learning curves of benchmark baselines: per method (key), the metadata of its seeds' policies. RL methods
    (``learning_curve`` with ``timesteps``): the training episodes' tailpipe NOx and mean slip against environment
    steps, one line per seed, and the validated checkpoints (``selection.candidates``) as markers; BC (``epoch``,
    ``mse``): its training loss. Returns the matplotlib figure (three panels)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, (method, metas) in enumerate(sorted(curves.items())):
        c = colours[i % len(colours)]
        for j, meta in enumerate(metas):
            curve = meta.get("learning_curve") or {}
            label = method if j == 0 else None
            rows = (meta.get("selection") or {}).get("candidates") or []
            if rows:
                axes[0].plot([r["timesteps"] for r in rows], [r["tailpipe_nox_g_per_kwh_mean"] for r in rows], "o",
                             color=c, ms=4, label=label if not curve.get("timesteps") else None)
                axes[1].plot([r["timesteps"] for r in rows], [r["mean_nh3_slip_ppm_max"] for r in rows], "o",
                             color=c, ms=4)
            if curve.get("timesteps"):
                axes[0].plot(curve["timesteps"], curve["tailpipe_nox_g_per_kwh"], color=c, alpha=0.6, label=label)
                axes[1].plot(curve["timesteps"], curve["mean_nh3_slip_ppm"], color=c, alpha=0.6, label=label)
            elif "epoch" in curve:
                axes[2].plot(curve["epoch"], curve["mse"], color=c, alpha=0.6, label=label)
    axes[0].set(xlabel="environment steps", ylabel="tailpipe NOx [g/kWh]",
                title="training episodes (lines), validation (dots)")
    axes[1].axhline(EURO_VI_NH3_SLIP_LIMIT_PPM, color="k", ls="--", lw=0.8)
    axes[1].set(xlabel="environment steps", ylabel="mean NH3 slip [ppm]", yscale="symlog",
                title="slip (validation: worst cycle)")
    axes[2].set(xlabel="epoch", ylabel="MSE of the action", yscale="log", title="behaviour cloning")
    for ax in axes:
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    return fig
