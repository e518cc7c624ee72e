"""Closed-loop benchmark of every dosing controller on the hot WHTC and WHSC.

    python -m experiments.control_benchmark [--json PATH] [--quick] [--cycles whtc whsc] [--workers 2] [--seeds 0]

Controllers (built by :func:`control.factory.make_controller`): ``lookup_table`` and ``pi`` (control.baselines),
``mpc_identified`` (NMPC on a grey-box storage model identified from open-loop excitation data on random cycles, state
by EKF from the measured signals only -- the tailpipe NOx sensor and a tailpipe NH3 sensor -- with the cycle preview
of the engine-out disturbances as the oracle has it), its variants ``mpc_identified_nox_sensor`` (EKF on the NOx
sensor alone) and ``mpc_identified_no_preview`` (NOx sensor alone, the measured disturbances held over the horizon:
what a truck without an NH3 sensor or route preview can do), ``mpc_oracle`` (NMPC on the first-principles catalyst
with privileged state and the cycle preview), and the shipped RL policies ``ppo`` / ``sac`` when :mod:`control.rl`
provides them (skipped otherwise, and said so). Writes the KPI table, a JSON {"cycles": {cycle: {"controllers": {name:
KPIs and timings}}}} and plots of the closed-loop trajectories to ``runs/control_benchmark/<stamp>/``. ``--quick``:
the WHTC only, shorter oracle horizon. ``--seeds``: the reset seeds (sensor noise) of every episode (default 0); with
several, each controller's figures are their means and ``per_seed`` lists NOx, slip and failed solves per seed (the
plots show the first seed).

Spread over seeds (``--cycles whtc --seeds 0 1 2 3 4 5``): the baselines hardly move (look-up table 0.610-0.612 g/kWh,
6.8-7.3 ppm). The identified NMPC did, before its slip guard (below): 6.7 ppm mean slip for seed 0 but 10.8-13.0 ppm
for seeds 1-5 (seed 5 also 0.540 g/kWh), and a rounding-level change of the plant moved seed 0 to 12.5 ppm. The cause:
on the WHTC's heat-up at 1500-1740 s the catalyst desorbs its store, the slip bound cannot be met, nearly every solve
fails, and the look-up-table fallback dosed into the slip (seed 1: 89 of the 102 g of AdBlue there). With the slip
guard (a failed solve doses nothing while the NH3 sensor reads above 10 ppm, the limit, not tuned;
:data:`control.factory.SLIP_GUARD_PPM`): WHTC 0.207-0.214 g/kWh at 3.2-4.8 ppm over seeds 0-5 (230-382 failed solves),
WHSC 0.176-0.184 g/kWh at 0.8-1.1 ppm; after the plant's fast-math compilation (scr_env/physics/backends.py) WHTC
0.207-0.215 g/kWh at 3.2-4.6 ppm (220-440 failed solves), WHSC 0.177-0.186 g/kWh at 0.8-1.2 ppm. The guard was added
after that WHTC diagnosis; on the calibration cycles it leaves the chosen design unchanged (storage value 50: 0.286
g/kWh at 1.42 ppm, the guard never acting; it acts at value 100: 0.546 -> 0.681 g/kWh, 16.6 -> 14.6 ppm).
"""
from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from control.evaluation import EpisodeResult, comparison_table, evaluate, summarise
from control.factory import IDENTIFIED_VARIANTS, available_rl, greybox_record, make_controller
from control.plots import closed_loop_figure
from experiments._runs import run_folder, save_results, write_text

CORE = ("lookup_table", "pi", "mpc_identified", "mpc_oracle")
REPORT_KEYS = ("nox_conversion", "engine_out_nox_g_per_kwh", "tailpipe_nox_g_per_kwh", "mean_nh3_slip_ppm",
               "peak_nh3_slip_ppm", "adblue_g", "nh3_slip_g", "engine_work_kwh", "policy_time_ms_median",
               "policy_time_ms_p95", "solver_failures", "solve_time_ms_median", "solve_time_ms_p95",
               "solve_time_ms_max", "solve_wall_ms_median", "solve_wall_ms_p95", "solver_iterations_mean",
               "solver_suboptimal", "slip_guarded_steps")


def _job(args: tuple[str, str, str | None, bool, int, bool]) -> EpisodeResult:
    """One episode ``(name, cycle, grey-box model file, quick, seed, record_trajectory)``, with a fresh policy."""
    from ident.greybox import StorageGreyBox

    name, cycle, model_file, quick, seed, record = args
    t0 = time.perf_counter()
    policy = make_controller(name, None if model_file is None else StorageGreyBox.load(model_file), quick)
    res = evaluate(policy, cycles=(cycle,), seeds=(seed,), env_kwargs=getattr(policy, "env_kwargs", None), name=name,
                   record_trajectory=record)[0]
    res.stats["wall_time_s"] = time.perf_counter() - t0
    return res


def _controllers(results: list[EpisodeResult], cycle: str, seeds: list[int]) -> dict[str, Any]:
    """The JSON rows of one cycle: the means over seeds of :data:`REPORT_KEYS` and, with several seeds, the
    per-seed NOx, slip and failed solves."""
    ctrl = {}
    for name, agg in summarise(results).get(cycle, {}).items():
        row = {k: v for k, v in agg.items() if k in REPORT_KEYS or k == "wall_time_s"}
        if len(seeds) > 1:   # the spread over sensor-noise seeds (the row holds their means)
            rs = sorted((r for r in results if r.cycle == cycle and r.name == name), key=lambda r: r.seed)
            row["per_seed"] = {"seed": [r.seed for r in rs]} | {
                k: [r.row().get(k) for r in rs] for k in ("tailpipe_nox_g_per_kwh", "mean_nh3_slip_ppm",
                                                          "solver_failures")}
        ctrl[name] = row
    return ctrl


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=None, help="also write the JSON result here")
    ap.add_argument("--quick", action="store_true", help="WHTC only, shorter MPC horizons")
    ap.add_argument("--cycles", nargs="+", default=None, help="cycles (default: whtc whsc; --quick: whtc)")
    ap.add_argument("--workers", type=int, default=2, help="parallel episodes (processes)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0],
                    help="reset seeds (sensor noise) of each episode; KPIs are averaged over them and listed per seed "
                         "(default: 0)")
    args = ap.parse_args(argv)
    seeds = list(dict.fromkeys(args.seeds))
    cycles = args.cycles or (["whtc"] if args.quick else ["whtc", "whsc"])
    out = run_folder("control_benchmark", json_path=args.json)
    t_start = time.perf_counter()
    rl, rl_note = available_rl()
    if rl_note:
        print(f"note: {rl_note}; skipped")
    print("identifying the grey-box storage model from open-loop excitation data ...", flush=True)
    model, ident = greybox_record()
    model_file = str(model.save(out / "greybox_model"))
    print(f"  fitted in {ident['fit_seconds']:.0f} s; WHTC validation (excited dosing) RMSE [ppm]: "
          + ", ".join(f"{k} {v:.1f}" for k, v in ident["validation_rmse_ppm_whtc"].items())
          + "; mean measured/predicted [ppm]: "
          + ", ".join(f"{k} {a:.1f}/{b:.1f}" for k, (a, b) in ident["validation_mean_ppm_whtc"].items()), flush=True)
    names = ["mpc_oracle", *IDENTIFIED_VARIANTS, "pi", "lookup_table", *rl]  # slowest first
    jobs = [(n, c, model_file if n in IDENTIFIED_VARIANTS else None, args.quick, s, s == seeds[0])
            for n in names for c in cycles for s in seeds]
    results = []
    with ProcessPoolExecutor(max_workers=max(args.workers, 1)) as ex:
        for r in ex.map(_job, jobs):
            k = r.kpis
            print(f"  {r.name:15s} {r.cycle} seed {r.seed}: {k.get('tailpipe_nox_g_per_kwh', np.nan):.3f} g/kWh, "
                  f"{k.get('mean_nh3_slip_ppm', np.nan):.2f} ppm mean slip ({r.stats['wall_time_s']:.0f} s)",
                  flush=True)
            results.append(r)
    order = {n: i for i, n in enumerate([*CORE, *IDENTIFIED_VARIANTS[1:], *rl])}
    results.sort(key=lambda r: (cycles.index(r.cycle) if r.cycle in cycles else 0, order.get(r.name, 99)))
    table = comparison_table(results, extra=("solve_time_ms_median", "solve_time_ms_p95", "solver_failures"))
    print(table)
    doc: dict[str, Any] = {"cycles": {}, "identified_model": ident, "skipped": rl_note or None,
                           "run_folder": str(out), "quick": bool(args.quick), "seeds": seeds}
    for c in cycles:
        ctrl = _controllers(results, c, seeds)
        doc["cycles"][c] = {"controllers": ctrl}
        if all(n in ctrl for n in ("lookup_table", "mpc_oracle", "mpc_identified")):
            lut, orc, idm = (ctrl[n]["tailpipe_nox_g_per_kwh"]
                             for n in ("lookup_table", "mpc_oracle", "mpc_identified"))
            gap = lut - orc
            doc["cycles"][c]["gap_closed_by_mpc_identified"] = (lut - idm) / gap if gap > 0 else float("nan")
            print(f"{c}: mpc_identified closes {doc['cycles'][c]['gap_closed_by_mpc_identified']:.2f} of the "
                  "look-up-table-to-oracle tailpipe NOx gap")
        closed_loop_figure([(r.name, r.kpis, r.trajectory) for r in results if r.cycle == c and r.seed == seeds[0]],
                           f"closed loop on the hot {c.upper()}", out / f"closed_loop_{c}.png")
    doc["wall_time_s"] = time.perf_counter() - t_start
    write_text(out / "table.txt", table + "\n")
    save_results(out, "control_benchmark.json", doc, args.json)
    print(f"wrote {out} in {doc['wall_time_s']:.0f} s")
    return doc


if __name__ == "__main__":
    main()
