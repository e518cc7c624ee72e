"""Paper IV's comparison over many independent segments and cycles: do the thesis' conclusions hold beyond one
segment?

Each segment is 600 s (1200 samples at 0.5 s) of a WHTC, WHSC or seeded random cycle (non-overlapping windows,
hot start), with the dosing design of :func:`ident.plant_data.whtc_dataset` (feedforward at ANR 0.5 times
``1 + e``, e random steps in [-1, 1] held 4-60 s, seeded per segment); M-I..M-V exactly as
:mod:`experiments.reproduce_paper4` (900/300 split, estimation statistics, M-V's candidate chosen on the last 25 %
of the estimation data; validation FIT of the output simulated on from the estimation data). Per model: mean, SD,
min and max of the validation FIT over segments. Per thesis conclusion, the paired difference of validation FIT over
segments:

* nonlinear beats linear: M-III, M-IV, M-V against the better linear model of each segment (max of M-I, M-II),
* the exp(-a/T) temperature input helps: M-IV against M-III,
* the piecewise-linear inputs help: M-V against M-IV.

A conclusion "holds" when the mean paired difference is positive with a paired t statistic above 2, "not
significant" when positive below that, and "does not hold" when negative.

NH3 slip as a second output: every model here is fitted per output (M-III..M-V are MISO), so the slip is a separate
single-output fit of the same five structures, done when the slip varies (SD > 0.1 ppm in the estimation part);
otherwise it is recorded as not identifiable from that segment.

    python -m experiments.paper4_multisegment [--json PATH] [--segments 4]
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small fits: one BLAS thread (see reproduce_paper4)
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import time
from typing import Any

import numpy as np

from experiments._runs import run_folder, write_json
from experiments.reproduce_paper4 import MODELS, fit_models
from ident.plant_data import PAPER4_BASE_ANR, PAPER4_EXCITATION, PAPER4_N_SAMPLES, excitation_dataset

SEGMENT_S = PAPER4_N_SAMPLES * 0.5
SLIP_MIN_SD_PPM = 0.1


def segment_list(n: int) -> list[tuple[str, int, float]]:
    """(cycle, seed, start_s) of ``n`` non-overlapping segments, cycling through WHTC, WHSC and random cycles."""
    fixed = {"whtc": [0.0, 600.0, 1200.0], "whsc": [0.0, 600.0, 1200.0]}
    out: list[tuple[str, int, float]] = []
    k = 0
    while len(out) < n:
        for cyc in ("whtc", "whsc"):
            if k < len(fixed[cyc]):
                out.append((cyc, 100 + len(out), fixed[cyc][k]))
        rnd_seed, part = divmod(k, 2)
        out.append(("random", 1 + rnd_seed, 300.0 + 600.0 * part))
        k += 1
    return out[:n]


def verdict(diff: np.ndarray) -> dict[str, Any]:
    d = np.asarray(diff, dtype=float)
    mean = float(d.mean())
    se = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else float("inf")
    t = mean / se if se > 0 else float("inf")
    word = "holds" if mean > 0 and t > 2 else ("not significant" if mean > 0 else "does not hold")
    return {"mean_diff": mean, "se": se, "t": t, "wins": int(np.sum(d > 0)), "n": int(d.size), "verdict": word}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the results to this JSON file")
    ap.add_argument("--segments", type=int, default=4,
                    help="number of segments (default 4, about 3 min; 15 for the full run)")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    segs = segment_list(args.segments)
    per_segment = []
    for cyc, seed, start in segs:
        ds = excitation_dataset(cyc, seed=seed, base_anr=PAPER4_BASE_ANR, excitation=PAPER4_EXCITATION,
                                start_s=start, duration_s=SEGMENT_S)
        rows, _ = fit_models(ds)
        entry: dict[str, Any] = {"cycle": cyc, "seed": seed, "start_s": start, "nox": rows,
                                 "inlet_temperature_k": [float(ds.u[:, 2].mean()), float(ds.u[:, 2].std())]}
        slip_sd = float(ds.y[:900, 1].std())
        entry["nh3_slip_sd_ppm"] = slip_sd
        if slip_sd > SLIP_MIN_SD_PPM and ds.y[900:, 1].std() > 0:
            entry["nh3_slip"], _ = fit_models(ds, output=1)
        else:
            entry["nh3_slip"] = f"not identifiable: slip SD {slip_sd:.2g} ppm <= {SLIP_MIN_SD_PPM} ppm"
        per_segment.append(entry)
        fits = "  ".join(f"{r['model']} {r['fit_validation']:6.1f}" for r in rows)
        print(f"{cyc:6s} seed {seed:3d} {start:6.0f} s | val FIT {fits} | slip SD {slip_sd:.2g} ppm", flush=True)
    fit = {m: np.array([next(r for r in e["nox"] if r["model"] == m)["fit_validation"] for e in per_segment])
           for m in MODELS}
    summary = {m: {"mean": float(v.mean()), "sd": float(v.std(ddof=1)) if v.size > 1 else 0.0,
                   "min": float(v.min()), "max": float(v.max()), "median": float(np.median(v))}
               for m, v in fit.items()}
    best_linear = np.maximum(fit["M-I"], fit["M-II"])
    conclusions = {
        "nonlinear beats linear (M-III vs best linear)": verdict(fit["M-III"] - best_linear),
        "nonlinear beats linear (M-IV vs best linear)": verdict(fit["M-IV"] - best_linear),
        "nonlinear beats linear (M-V vs best linear)": verdict(fit["M-V"] - best_linear),
        "exp(-a/T) input helps (M-IV vs M-III)": verdict(fit["M-IV"] - fit["M-III"]),
        "piecewise-linear inputs help (M-V vs M-IV)": verdict(fit["M-V"] - fit["M-IV"]),
    }
    slip_rows = [e["nh3_slip"] for e in per_segment if isinstance(e["nh3_slip"], list)]
    result = {"segments": per_segment, "summary_fit_validation": summary, "conclusions": conclusions,
              "nh3_slip_identified_segments": len(slip_rows), "n_segments": len(segs),
              "runtime_s": round(time.perf_counter() - t0, 1)}
    print(f"\nvalidation FIT over {len(segs)} segments: mean (SD) [min, max]")
    for m, s in summary.items():
        print(f"  {m:6s} {s['mean']:7.1f} ({s['sd']:5.1f}) [{s['min']:7.1f}, {s['max']:6.1f}]")
    print("thesis conclusions (paired differences of validation FIT):")
    for k, v in conclusions.items():
        print(f"  {k:48s} {v['mean_diff']:+7.1f} (t = {v['t']:5.2f}, better in {v['wins']}/{v['n']}): {v['verdict']}")
    print(f"NH3 slip identifiable (SD > {SLIP_MIN_SD_PPM} ppm) in {len(slip_rows)} of {len(segs)} segments")
    if slip_rows:
        for m in MODELS:
            v = [next(r for r in rows if r["model"] == m)["fit_validation"] for rows in slip_rows]
            print(f"  NH3 slip {m:6s} validation FIT mean {np.mean(v):7.1f}")
    out = run_folder("paper4_multisegment")
    write_json(out / "results.json", result)
    if args.json:
        write_json(args.json, result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
