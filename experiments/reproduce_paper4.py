"""Paper IV reproduced on the simulator: linear (M-I, M-II), Wiener (M-III) and Hammerstein-Wiener (M-IV, M-V)
models of the tailpipe NOx, beside the published Table 2. The protocol, the models, M-V's selection rule and the
results with their history are :mod:`ident.thesis.paper4`'s docstring.

    python -m experiments.reproduce_paper4 [--json PATH] [--seed 0] [--design production|excitation] [--only-design]
                                           [--no-plots] [--diagnose] [--spread-seeds S ...]

Figures (Paper IV's Figures 5 and 6: measured and simulated tailpipe NOx per model, estimation and validation
data, in ppm; the table's design) and ``results.json`` go to ``runs/reproduce_paper4/<stamp>/``.
"""
from __future__ import annotations

import os

# one BLAS thread: the fits work on small matrices, and on shared cores a multi-threaded BLAS spins and runs them
# many times slower (set before numpy is first imported, i.e. when run as a script)
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from control.plots import pyplot
from experiments._runs import run_folder, save_results, write_figure
from ident.dataset import IODataset
from ident.plant_data import PAPER4_DEFAULT_DESIGN, PAPER4_DESIGNS, PAPER4_N_ESTIMATION, PAPER4_N_SAMPLES, whtc_dataset
from ident.thesis.paper4 import MODELS, MV_HOLDOUT, PWL_SEGMENTS, diagnose_mv, fit_models, seed_spread


def plot(sims: dict[str, Any], out: Path, unit: str = "ppm", label: str = "tailpipe NOx") -> list[Path]:
    """Paper IV's Figures 5 and 6: measured vs simulated output per model (physical units)."""
    plt = pyplot()

    paths = []
    for part, key, idx in (("estimation", "y_est", 0), ("validation", "y_val", 1)):
        fig, axes = plt.subplots(len(MODELS), 1, figsize=(10, 2.0 * len(MODELS)), sharex=True)
        y = sims[key] * sims["scale"] + sims["mean"]
        n0 = 0 if part == "estimation" else len(sims["y_est"])
        k = np.arange(n0, n0 + len(y))
        for ax, name in zip(axes, MODELS, strict=True):
            if name not in sims:
                continue
            yh = sims[name][idx] * sims["scale"] + sims["mean"]
            ax.plot(k, y, "k", lw=1.2, label="simulator")
            ax.plot(k, yh, "C1", lw=1.0, label=name)
            ax.set_ylabel(f"{unit}")
            ax.legend(loc="upper right", fontsize=8)
            ax.grid(alpha=0.3)
        axes[-1].set_xlabel("sample (Ts = 0.5 s)")
        fig.suptitle(f"{label}: measured vs simulated, {part} data")
        fig.tight_layout()
        p = out / f"figure_{'5' if part == 'estimation' else '6'}_{part}.png"
        write_figure(fig, p, dpi=110)
        paths.append(p)
    return paths


def print_table(rows: list[dict[str, Any]]) -> None:
    """The table beside Paper IV's Table 2."""
    print(f"{'model':6s} {'params':>6s} | {'FIT est':>8s} {'FIT val':>8s} {'MSE est':>8s} {'MSE val':>8s} | "
          f"{'val x0*':>8s} | {'published FIT est/val, MSE est/val':s}")
    for r in rows:
        p = r["published"]
        print(f"{r['model']:6s} {r['n_params']:6d} | {r['fit_estimation']:7.2f}% {r['fit_validation']:7.2f}% "
              f"{r['mse_estimation']:8.3f} {r['mse_validation']:8.3f} | "
              f"{r['fit_validation_x0_from_validation']:7.2f}% | {p['fit_estimation']:6.2f}% "
              f"{p['fit_validation']:6.2f}%  {p['mse_estimation']:.3f} {p['mse_validation']:.3f}")
    mv_row = next((r for r in rows if r["model"] == "M-V"), None)
    if mv_row is not None:
        print(f"M-V chosen on the last {MV_HOLDOUT:.0%} of the estimation data: {mv_row['chosen']}")


def _data_line(ds: IODataset, design: str) -> str:
    m = ds.meta
    return (f"data ({design} design: {PAPER4_DESIGNS[design].description}): {m['cycle']} {m['start_s']:g}-"
            f"{m['start_s'] + m['duration_s']:g} s, seed {m['seed']}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the results to this JSON file")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--design", choices=sorted(PAPER4_DESIGNS), default=PAPER4_DEFAULT_DESIGN,
                    help="dosing design of the table (ident.plant_data.PAPER4_DESIGNS): production (default, the "
                         "thesis' data) or excitation (random ANR steps, beyond the thesis)")
    ap.add_argument("--only-design", action="store_true",
                    help="fit the table of --design alone (by default the other design's table follows it)")
    ap.add_argument("--no-plots", action="store_true")
    ap.add_argument("--diagnose", action="store_true",
                    help="also score every M-V candidate on the validation data and fit each on samples 0-1197, the "
                         "validation window included (about the structure's ceiling there); about 20 s more")
    ap.add_argument("--spread-seeds", type=int, nargs="+", metavar="S",
                    help="also fit the table for these seeds (each its own sensor noise, and excitation under the "
                         "excitation design; same segment) and print the validation FIT's median and range per "
                         "model; about 20 s per seed")
    args = ap.parse_args(argv)
    out = run_folder("reproduce_paper4", json_path=args.json)
    t0 = time.perf_counter()
    ds = whtc_dataset(seed=args.seed, design=args.design)[:PAPER4_N_SAMPLES]
    rows, sims = fit_models(ds)
    result = {"rows": rows, "data": ds.meta, "seed": args.seed, "design": args.design,
              "protocol": {"n_samples": PAPER4_N_SAMPLES, "n_estimation": PAPER4_N_ESTIMATION, "dt_s": ds.dt,
                           "dosing": PAPER4_DESIGNS[args.design].description,
                           "normalisation": "estimation mean/SD",
                           "fit": "simulated output; x0 estimated on the estimation data, validation: the simulation "
                                  "carried on through the validation data",
                           "output": ds.output_names[0], "pwl_segments": list(PWL_SEGMENTS),
                           "mv_selection": f"best simulated FIT on the last {MV_HOLDOUT:.0%} of the estimation data "
                                           "(fitted on the rest), refitted on all of it"},
              "runtime_s": round(time.perf_counter() - t0, 1)}
    print(_data_line(ds, args.design))
    print_table(rows)
    print("FIT val: simulated on from the estimation data into the validation data (state carried over, no "
          "validation output used); val x0*: the validation record simulated alone from an x(0) estimated on its own "
          "measured output (MATLAB compare)")
    if not args.only_design:
        result["other_designs"] = {}
        for other in (d for d in PAPER4_DESIGNS if d != args.design):
            ds_other = whtc_dataset(seed=args.seed, design=other)[:PAPER4_N_SAMPLES]
            rows_other, _ = fit_models(ds_other)
            result["other_designs"][other] = {"description": PAPER4_DESIGNS[other].description, "rows": rows_other}
            print("\nthe same segment and models, " + _data_line(ds_other, other))
            print_table(rows_other)
    if args.diagnose:
        diag = diagnose_mv(ds)
        result["mv_diagnostics"] = diag
        print(f"\nM-V candidates, {args.design} design (diagnostic, uses the validation output): FIT est / val / "
              "val when fitted on samples 0-1197")
        for d in diag:
            print(f"  nk={d['nk']} smoothness={d['smoothness']:<6g} {d['fit_estimation']:6.1f} % "
                  f"{d['fit_validation']:7.1f} % {d['fit_validation_ceiling']:6.1f} %")
    if args.spread_seeds:
        spread = seed_spread(args.spread_seeds, design=args.design)
        result["seed_spread"] = spread
        print(f"\nvalidation FIT over seeds {spread['seeds']} ({args.design} design): median [min, max] carried "
              "on; compare-style median, max")
        for m, v in spread["models"].items():
            print(f"  {m:6s} {v['median']:6.1f} [{v['min']:6.1f}, {v['max']:5.1f}] %; compare-style "
                  f"{v['median_x0_from_validation']:5.1f}, {v['max_x0_from_validation']:5.1f} %")
        if "mv_chosen" in spread:
            print("  M-V's chosen candidate per seed: " + ", ".join(spread["mv_chosen"]))
    if not args.no_plots:
        result["figures"] = [str(p) for p in plot(sims, out, label=f"tailpipe NOx ({args.design} design)")]
        print("figures:", ", ".join(result["figures"]))
    result["runtime_s"] = round(time.perf_counter() - t0, 1)
    save_results(out, "results.json", result, args.json)
    others = [r for d in result.get("other_designs", {}).values() for r in d["rows"]]
    finite = all(np.isfinite(r["fit_validation"]) for r in rows + others)
    return 0 if finite else 1


if __name__ == "__main__":
    raise SystemExit(main())
