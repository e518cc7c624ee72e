"""Plot the SCR-inlet signals of the WHTC (hot and cold start), the WHSC and one seeded random cycle.

Usage: ``python -m experiments.plot_cycles [--out runs/plot_cycles] [--dt 0.5] [--seed 0]``. Writes one PNG per
cycle and ``summary.json`` (min / mean / max of each signal and the positive work) to the run folder.
"""
from __future__ import annotations

import argparse
from pathlib import Path

from control.plots import pyplot
from experiments._runs import write_figure, write_json
from scr_env.cycles import ExhaustTrace, load_cycle, random_cycle

_SIGNALS = (
    ("engine_power_kw", "power [kW]"),
    ("exhaust_flow_mol_s", "exhaust flow [mol/s]"),
    ("scr_inlet_temperature_k", "SCR inlet T [K]"),
    ("nox_ppm", "SCR inlet NOx [ppm]"),
    ("no2_fraction", "NO2/NOx [-]"),
)


def summarise(trace: ExhaustTrace) -> dict[str, float]:
    """Min, mean and max of each plotted signal and the positive work [kWh]."""
    out: dict[str, float] = {"n_steps": trace.n_steps, "positive_work_kwh": trace.positive_work_kwh}
    for name, _ in _SIGNALS:
        arr = getattr(trace, name)
        out.update({f"{name}_min": float(arr.min()), f"{name}_mean": float(arr.mean()),
                    f"{name}_max": float(arr.max())})
    return out


def plot(trace: ExhaustTrace, title: str, path: Path) -> None:
    """One figure with the engine power and the four SCR-inlet signals against time."""
    plt = pyplot()
    fig, axes = plt.subplots(len(_SIGNALS), 1, figsize=(10, 9), sharex=True)
    for ax, (name, label) in zip(axes, _SIGNALS, strict=True):
        ax.plot(trace.time_s, getattr(trace, name), lw=0.8)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    axes[0].set_title(f"{title}: positive work {trace.positive_work_kwh:.1f} kWh")
    fig.tight_layout()
    write_figure(fig, path, dpi=120)


def main(argv: list[str] | None = None) -> dict[str, dict[str, float]]:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("runs/plot_cycles"), help="run folder")
    parser.add_argument("--dt", type=float, default=0.5, help="sample interval [s]")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random cycle")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    traces = {
        "whtc_hot": load_cycle("whtc", dt=args.dt),
        "whtc_cold": load_cycle("whtc", dt=args.dt, cold_start=True),
        "whsc": load_cycle("whsc", dt=args.dt),
        f"random_seed{args.seed}": random_cycle(1800.0, seed=args.seed, dt=args.dt),
    }
    summary = {}
    for key, trace in traces.items():
        plot(trace, key, args.out / f"{key}.png")
        summary[key] = summarise(trace)
    write_json(args.out / "summary.json", summary)
    for key, s in summary.items():
        print(f"{key:>14}: flow {s['exhaust_flow_mol_s_min']:.2f}-{s['exhaust_flow_mol_s_max']:.2f} mol/s, "
              f"T {s['scr_inlet_temperature_k_min']:.0f}-{s['scr_inlet_temperature_k_max']:.0f} K, "
              f"NOx max {s['nox_ppm_max']:.0f} ppm, work {s['positive_work_kwh']:.1f} kWh")
    return summary


if __name__ == "__main__":
    main()
