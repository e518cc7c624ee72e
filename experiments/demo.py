"""The main job (``make demo``): the simulator on the real cycles, then a short identify-then-control loop.

1. The simulator over the real WHTC and WHSC with a simple open-loop dosing map: KPI tables, SCR-inlet signal
   ranges against the thesis data, trajectory figures.
2. The identify-then-control loop in its quick form (``python -m experiments.identify_then_control --quick``, run
   as a program):
   control-relevant excitation experiments, identification (two-output RPEM and Hammerstein-Wiener models, the
   grey-box), the NMPC on each identified model (``mpc_rpem``, ``mpc_hammerstein_wiener``, ``mpc_greybox``), closed
   loop on the first 600 s of the held-out WHTC against the baselines, the oracle NMPC and the shipped RL policies.

Writes ``runs/demo/<stamp>/report.md`` with the tables and PNG figures, and prints where it is. The full
identify-then-control study: ``python -m experiments.identify_then_control`` (about 14 minutes on 2 cores).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from control.baselines import FeedforwardDosing
from control.plots import pyplot
from experiments._runs import run_folder, write_figure, write_json, write_text
from scr_env.rollout import Trajectory, rollout

#: A minimal open-loop dosing map: ANR 0 below 200 C, 0.9 above 250 C, linear in between (demo only; the
#: calibrated industrial baseline is ``control.baselines.LookupTableDosing``).
DEMO_DOSING = {"anr": 0.9, "ramp_start_k": 473.15, "ramp_width_k": 50.0}


def _figure(tr: Trajectory, path: Path) -> None:
    plt = pyplot()
    t = tr["time_s"]
    fig, axes = plt.subplots(4, 1, figsize=(10, 9), sharex=True)
    axes[0].plot(t, tr["inlet_nox_ppm"], color="0.6", lw=0.7, label="engine-out NOx")
    axes[0].plot(t, tr["tailpipe_nox_ppm"], color="C0", lw=0.8, label="tailpipe NOx")
    axes[0].plot(t, tr["tailpipe_nh3_ppm"], color="C3", lw=0.8, label="NH3 slip")
    axes[0].set_ylabel("ppm")
    axes[0].legend(loc="upper right", fontsize=8)
    axes[1].plot(t, tr["inlet_temperature_k"], color="C1", lw=0.8)
    axes[1].set_ylabel("SCR inlet T [K]")
    axes[2].plot(t, tr["exhaust_flow_mol_s"], color="C5", lw=0.8)
    axes[2].set_ylabel("exhaust flow [mol/s]")
    axes[3].plot(t, tr["adblue_g_s"], color="C2", lw=0.8)
    axes[3].set_ylabel("AdBlue [g/s]", color="C2")
    ax2 = axes[3].twinx()
    ax2.plot(t, tr["mean_coverage"], color="C4", lw=0.8)
    ax2.set_ylabel("mean NH3 coverage [-]", color="C4")
    axes[3].set_xlabel("time [s]")
    k = tr.kpis
    fig.suptitle(f"{tr.cycle.upper()}: NOx conversion {100 * k['nox_conversion']:.1f} %, tailpipe "
                 f"{k['tailpipe_nox_g_per_kwh']:.3f} g/kWh, mean NH3 slip {k['mean_nh3_slip_ppm']:.1f} ppm")
    fig.tight_layout()
    write_figure(fig, path, dpi=90)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--json", help="also write the results to this JSON file")
    ap.add_argument("--seed", type=int, default=0, help="sensor-noise seed (default 0)")
    ap.add_argument("--overview-only", action="store_true", help="skip the identify-then-control part (seconds)")
    args = ap.parse_args(argv)
    out = run_folder("demo", json_path=args.json)
    start = time.perf_counter()
    results: dict = {"cycles": {}}
    lines = ["# scr-dosing demo: the simulator over the real WHTC and WHSC", "",
             ("Open-loop dosing map (ANR 0.9 above 250 C, ramp from 200 C), hot start, empty catalyst, "
              f"sensor-noise seed {args.seed}."), "",
             ("| cycle | NOx conversion | engine-out NOx [g/kWh] | tailpipe NOx [g/kWh] (Euro VI limit) | "
              "mean / peak NH3 slip [ppm] | AdBlue [g] | work [kWh] |"), "|---|---|---|---|---|---|---|"]
    ranges = ["", "SCR inlet signals (min / mean / max) against the thesis' WHTC data (Paper III, Table 1):", "",
              "| cycle | inlet NOx [ppm] | exhaust flow [mol/s] | inlet temperature [K] |", "|---|---|---|---|"]
    figures = {}
    for cycle, limit in (("whtc", 0.46), ("whsc", 0.40)):
        tr = rollout(FeedforwardDosing(**DEMO_DOSING), cycle=cycle, seed=args.seed)
        k = tr.kpis
        results["cycles"][cycle] = k
        figures[out / f"{cycle}_trajectory.png"] = tr
        lines.append(f"| {cycle.upper()} | {100 * k['nox_conversion']:.1f} % | {k['engine_out_nox_g_per_kwh']:.2f} | "
                     f"{k['tailpipe_nox_g_per_kwh']:.3f} ({limit}) | {k['mean_nh3_slip_ppm']:.1f} / "
                     f"{k['peak_nh3_slip_ppm']:.0f} | {k['adblue_g']:.0f} | {k['engine_work_kwh']:.1f} |")

        def r(x: np.ndarray, fmt: str) -> str:
            return f"{x.min():{fmt}} / {x.mean():{fmt}} / {x.max():{fmt}}"

        ranges.append(f"| {cycle.upper()} | {r(tr['inlet_nox_ppm'], '.0f')} | {r(tr['exhaust_flow_mol_s'], '.1f')} | "
                      f"{r(tr['inlet_temperature_k'], '.0f')} |")
        results["cycles"][cycle]["ranges"] = {
            name: [float(tr[name].min()), float(tr[name].mean()), float(tr[name].max())]
            for name in ("inlet_nox_ppm", "exhaust_flow_mol_s", "inlet_temperature_k")}
    ranges.append("| thesis WHTC | 0 to ~2500 (mean 619) | 0 to ~12 | 450 to 700 (mean 534) |")
    lines += ranges
    lines += ["", "Figures: " + ", ".join(f"`{p.name}`" for p in sorted(figures))]
    for p in sorted(figures):
        lines += ["", f"![{p.stem}]({p.name})"]
    print("\n".join(lines))
    if not args.overview_only:
        print("\n== identify-then-control (quick) ==", flush=True)
        sub = out / "identify_then_control"
        subprocess.run([sys.executable, "-m", "experiments.identify_then_control", "--quick", "--out", str(sub),
                        "--workers", "2"], check=True)
        doc = json.loads((sub / "identify_then_control.json").read_text(encoding="utf-8"))
        results["identify_then_control"] = {"gap_closed": doc["gap_closed"], "kpis": doc["kpis"]}
        text = (sub / "report.md").read_text(encoding="utf-8")
        text = text.replace("](", "](identify_then_control/").replace("# Identify-then-control",
                                                                                        "## Identify-then-control")
        lines += ["", text]
    report = out / "report.md"
    # the report is the last thing written: everything printed first (a log of the run is older than the report)
    print(f"\nwriting the report: {report} (figures beside it; {time.perf_counter() - start:.1f} s)", flush=True)
    sys.stderr.flush()
    if args.json:
        write_json(args.json, results)
    for path, tr in figures.items():
        _figure(tr, path)
    write_text(report, "\n".join(lines) + "\n")
    return results


if __name__ == "__main__":
    main()
