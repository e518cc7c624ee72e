"""Automatic RPEM structure choice (ident.rpem.StructureSearch) on the simulated benchmark systems of issue 21.

For every system and seed: the search fits its grid of structures (orders, polynomial degrees, output functions)
with :data:`ident.rpem.AUTO_SETTINGS` on the *estimation* record and chooses on that record's inner hold-out (its
last 20 %); the validation record is used only to score the chosen model afterwards (simulation FIT, x0 estimated).
No per-system setting: every system gets the same search.

    python -m experiments.rpem_structure_search [--systems duffing_oscillator cascaded_tanks coupled_drives]
        [--seeds 0 1 2 3 4] [--json PATH] [--quick] [--hand-chosen]

``--quick`` shortens the records and the grid (a smoke run, not a figure). ``--hand-chosen`` fits the structures
chosen by hand in tests/ident/test_rpem_auto.py (:data:`HAND_CHOSEN`) with AUTO_SETTINGS instead of searching, for
the README's comparison.
"""
from __future__ import annotations

import argparse
import time
import warnings
from typing import Any

import numpy as np

from experiments._runs import run_folder, save_results
from ident.benchmarks import simulated_benchmark
from ident.benchmarks.simulated import SIMULATED_BENCHMARKS
from ident.metrics import compare
from ident.rpem import AUTO_SETTINGS, RecursivePEM, StructureSearch

#: issue 21's validation FIT goals (percent)
GOALS = {"duffing_oscillator": 95.0, "cascaded_tanks": 85.0, "coupled_drives": 70.0}
#: the structures of tests/ident/test_rpem_auto.py (README "Simulated benchmark systems")
HAND_CHOSEN = {"duffing_oscillator": {"n_states": 2, "total_degree": 3, "output": "identity"},
               "cascaded_tanks": {"n_states": 2, "total_degree": 3, "output": "identity"},
               "coupled_drives": {"n_states": 3, "total_degree": 1, "output": "abs"}}
QUICK_LENGTHS = {"duffing_oscillator": (1200, 600), "cascaded_tanks": (400, 400), "coupled_drives": (600, 300)}


def run_one(name: str, seed: int, quick: bool, hand: bool = False) -> dict[str, Any]:
    """One search (or, with ``hand``, one fit of the hand-chosen structure) on one system and seed; the structure,
    its hold-out and validation FIT."""
    lengths = {}
    if quick:
        lengths = dict(zip(("n_estimation", "n_validation"), QUICK_LENGTHS[name], strict=True))
    b = simulated_benchmark(name, seed=seed, **lengths)
    kw: dict[str, Any] = {}
    if quick:
        kw = {"orders": (1, 2), "degrees": (1, 2), "outputs": ("identity", "abs"),
              "settings": {**AUTO_SETTINGS, "n_passes": 4}}
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        if hand:
            c = HAND_CHOSEN[name]
            est = RecursivePEM(**c, max_degrees=c["total_degree"], sampling_period=b.sampling_period,
                               **kw.get("settings", AUTO_SETTINGS)).fit(b.estimation.u, b.estimation.y)
            model, chosen, score = est, dict(c), est.holdout_fit_
        else:
            model = StructureSearch(sampling_period=b.sampling_period, **kw).fit(b.estimation.u, b.estimation.y)
            est, chosen, score = model.best_estimator_, model.best_params_, model.best_score_
    seconds = time.perf_counter() - t0
    fit = float(compare(model, b.validation.u, b.validation.y).fit)
    return {"system": name, "seed": seed, "chosen": chosen, "holdout_fit": score,
            "final_holdout_fit": est.holdout_fit_, "validation_fit": fit, "goal": GOALS.get(name),
            "half_step_input": est.half_step_input_, "pass_mode": est.pass_mode_, "R0": est.R0_,
            "refit": bool(est.refit_), "search_time_s": round(seconds, 1),
            "n_candidates": 1 if hand else len(model.results_),
            "warnings": sorted({str(w.message)[:160] for w in caught}),
            "table": "hand-chosen structure" if hand else model.table()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--systems", nargs="+", default=sorted(GOALS), choices=sorted(SIMULATED_BENCHMARKS))
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2, 3, 4])
    ap.add_argument("--json", help="write the results to this JSON file")
    ap.add_argument("--quick", action="store_true", help="short records and a small grid (smoke run)")
    ap.add_argument("--hand-chosen", action="store_true", help="fit the hand-chosen structures instead of searching")
    args = ap.parse_args(argv)
    out = run_folder("rpem_structure_search", json_path=args.json)
    rows = []
    for name in args.systems:
        for seed in args.seeds:
            row = run_one(name, seed, args.quick, args.hand_chosen)
            rows.append(row)
            c = row["chosen"]
            print(f"{name:20s} seed {seed}: n={c['n_states']} deg={c['total_degree']} {c['output']:10s} "
                  f"hold-out {row['holdout_fit']:6.1f} %  validation {row['validation_fit']:6.1f} %  "
                  f"({row['search_time_s']:.0f} s){'  WARN' if row['warnings'] else ''}", flush=True)
            save_results(out, "results.json", {"rows": rows, "quick": args.quick, "hand_chosen": args.hand_chosen},
                         args.json)
    summary = {}
    for name in args.systems:
        fits = [r["validation_fit"] for r in rows if r["system"] == name]
        summary[name] = {"mean": float(np.mean(fits)), "min": float(np.min(fits)), "max": float(np.max(fits)),
                         "fits": fits, "goal": GOALS.get(name)}
        print(f"{name:20s} validation FIT mean {np.mean(fits):.1f} % (min {np.min(fits):.1f}, "
              f"max {np.max(fits):.1f}), goal {GOALS.get(name)} %")
    save_results(out, "results.json", {"rows": rows, "summary": summary, "quick": args.quick,
                                       "hand_chosen": args.hand_chosen}, args.json)
    return 0 if all(np.isfinite(r["validation_fit"]) for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
