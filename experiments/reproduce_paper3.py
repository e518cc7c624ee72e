"""Paper III reproduced on the simulator: RPEM with a 2nd-order chain model, the 9-term (linear) and 16-term
(nonlinear) regressors, Euler against midpoint, beside the published Table 2; backward term selection; the
repetition over independent segments. The protocol (data, alignment, normalisation, RPEM settings, FIT, the
repetition's verdicts) is :mod:`ident.thesis.paper3`'s docstring.

    python -m experiments.reproduce_paper3 [--json PATH] [--seed 0] [--quick] [--passes 50] [--no-plots]

Figures and ``results.json`` go to ``runs/reproduce_paper3/<stamp>/``.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from control.plots import pyplot
from experiments._runs import run_folder, save_results, write_figure
from ident.plant_data import PAPER4_BASE_ANR, PAPER4_DESIGNS, PAPER4_DT_S, PAPER4_N_SAMPLES, PAPER4_SEGMENT_START_S
from ident.thesis.paper3 import (
    ALPHA,
    EXCITATION,
    EXTRA_TERMS,
    METHODS,
    N_ESTIMATION_FRACTION,
    PUBLISHED,
    brief,
    excitation_text,
    find_segments,
    fit_methods,
    load_segment,
    normalise,
    repeat_segments,
    select_terms,
    table1,
)


def plot(d: dict[str, Any], sims: dict[str, tuple], rows: list[dict], out: Path,
         repetition: dict[str, Any] | None) -> list[Path]:
    """Measured vs simulated validation output (ppm) per method; the repetition's validation FIT per method."""
    plt = pyplot()

    mean, sd = d["y_stats"]["mean"][0], d["y_stats"]["sd"][0]
    ne = d["n_est"]
    y = d["Y"][ne:, 0] * sd + mean
    k = np.arange(ne, ne + len(y))
    fits = {r["method"]: r for r in rows}
    names = [m for m in (*METHODS, "midpoint_selected") if m in sims]
    fig, axes = plt.subplots(len(names), 1, figsize=(10, 1.9 * len(names)), sharex=True)
    for ax, name in zip(np.atleast_1d(axes), names, strict=True):
        ax.plot(k, y, "k", lw=1.2, label="simulator")
        ax.plot(k, sims[name][1] * sd + mean, "C1", lw=1.0, label=f"RPEM {name}")
        r = fits[name]
        pub = f", paper {PUBLISHED[name]:.2f} %" if name in PUBLISHED else " (terms chosen on these data)"
        ax.set_title(f"{name}: {r['n_params']} parameters, validation FIT {r['fit_validation']:.1f} %{pub}",
                     fontsize=9)
        ax.set_ylabel("NOx [ppm]")
        ax.legend(loc="upper right", fontsize=7)
        ax.grid(alpha=0.3)
    np.atleast_1d(axes)[-1].set_xlabel("sample (T = 0.5 s)")
    fig.suptitle("Paper III on the simulator: tailpipe NOx, validation data (last 25 %)")
    fig.tight_layout()
    paths = [out / "validation_output.png"]
    write_figure(fig, paths[0], dpi=110)
    if repetition and repetition["summary"]:
        ok = [s for s in repetition["segments"] if "fit_validation" in s]
        ms = list(repetition["summary"])
        fig, ax = plt.subplots(figsize=(9, 4))
        for i, m in enumerate(ms):
            v = [s["fit_validation"][m] for s in ok]
            ax.plot(np.full(len(v), i) + np.linspace(-0.15, 0.15, len(v)), v, "o", alpha=0.7)
            ax.plot([i - 0.3, i + 0.3], [np.median(v)] * 2, "k", lw=2)
            if m in PUBLISHED:
                ax.plot(i, PUBLISHED[m], "r*", ms=12, label="paper" if i == 0 else None)
        ax.set_xticks(range(len(ms)), ms, rotation=15, fontsize=8)
        ax.set_ylabel("validation FIT [%]")
        ax.set_ylim(max(-50.0, ax.get_ylim()[0]), 100)
        ax.set_title(f"{len(ok)} independent segments (dots; below -50 % not shown), median (bar), Paper III (star)",
                     fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        paths.append(out / "repetition_fit.png")
        write_figure(fig, paths[1], dpi=110)
    return paths


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the results to this JSON file")
    ap.add_argument("--seed", type=int, default=0, help="seed of the main segment (sensor noise, excitation)")
    ap.add_argument("--passes", type=int, default=50, help="largest number of RPEM passes (default 50)")
    ap.add_argument("--n-samples", type=int, default=PAPER4_N_SAMPLES, help="samples per segment (default 1200)")
    ap.add_argument("--quick", action="store_true",
                    help="3 repetition segments, a small selection candidate set and at most 10 passes")
    ap.add_argument("--segments", type=int, help="largest number of repetition segments (default 10, quick 3)")
    ap.add_argument("--no-align", action="store_true", help="pair u[k] with y[k] (see the module docstring)")
    ap.add_argument("--no-selection", action="store_true")
    ap.add_argument("--no-repetition", action="store_true")
    ap.add_argument("--no-plots", action="store_true")
    args = ap.parse_args(argv)
    out = run_folder("reproduce_paper3", json_path=args.json)
    t0 = time.perf_counter()
    passes = min(args.passes, 10) if args.quick else args.passes
    align = not args.no_align
    n = int(args.n_samples)
    n_est = round(N_ESTIMATION_FRACTION * n)

    seg = load_segment("whtc", args.seed, PAPER4_SEGMENT_START_S, n, align=align)
    d = normalise(seg["u"], seg["y"], n_est)
    rows, sims = fit_methods(d, passes)
    paper4 = {}   # the methods on the records of Paper IV's designs (ident.plant_data.PAPER4_DESIGNS)
    for name in ("excitation", "production"):
        design = PAPER4_DESIGNS[name]
        seg_d = load_segment("whtc", args.seed, PAPER4_SEGMENT_START_S, n, excitation=design.excitation,
                             base_anr=design.base_anr, align=align)
        paper4[name] = fit_methods(normalise(seg_d["u"], seg_d["y"], n_est), passes)[0]
    rows4, rows_p = paper4["excitation"], paper4["production"]
    result: dict[str, Any] = {
        "rows": [{k: v for k, v in r.items() if k not in ("theta", "theta_kalman_init")} for r in rows],
        "models": {r["method"]: {"terms": r["terms"], "theta": r["theta"], "theta_kalman_init": r["theta_kalman_init"]}
                   for r in rows},
        **{f"paper4_{name}_design": {"excitation": excitation_text(name), "rows": [brief(r) for r in rows_d]}
           for name, rows_d in paper4.items()},
        "data": {**seg["meta"], "n_estimation": n_est, "n_validation": n - n_est, "output": "tailpipe_nox_ppm",
                 "inputs": ["inlet_nox_ppm", "urea_dosing_g_min", "exp(-a/inlet_temperature_k), a = 1e4 K",
                            "exhaust_flow_mol_s"],
                 "normalisation": {"inputs": d["u_stats"], "output": d["y_stats"],
                                   "source": "estimation part (first 75 %)"},
                 "table1": table1(seg["u"], seg["y"], n_est)},
        "seed": args.seed,
        "rpem": {"n_states": 2, "alpha": ALPHA, "ts_model_s": ALPHA * PAPER4_DT_S, "R0": 100.0, "Lambda0": 0.1,
                 "stability_margin": 0.015, "max_passes": passes, "init": "kalman",
                 "kalman": {"p0": 10.0, "q_state": 50.0, "q_theta": 0.0, "r": 3.0},
                 "output_saturation": f"y >= {d['y_min']:.4f} (zero NOx, normalised)",
                 "forgetting": "0.999 -> 1 at rate 0.999 (gain ~ 1/t)", "half_step_input": "hold"},
        "quick": bool(args.quick),
    }
    print(f"data: {seg['meta']['cycle']} {seg['meta']['start_s']:g} s + {n * PAPER4_DT_S:g} s, seed {args.seed}, "
          f"{n_est}/{n - n_est} samples, ANR {PAPER4_BASE_ANR} x (1 + {EXCITATION!r}), aligned {align}")
    print(f"{'method':20s} {'params':>6s} | {'FIT est':>8s} {'FIT val':>8s} | {'paper est':>9s} {'paper val':>9s} "
          f"| {'val on Paper IV excitation / production':>40s}")
    for r, r4, rp in zip(rows, rows4, rows_p, strict=True):
        print(f"{r['method']:20s} {r['n_params']:6d} | {r['fit_estimation']:7.2f}% {r['fit_validation']:7.2f}% | "
              f"{r['published_fit_estimation']:8.2f}% {r['published_fit_validation']:8.2f}% | "
              f"{r4['fit_validation']:29.2f}% / {rp['fit_validation']:6.2f}%")
    if not args.no_selection:
        extra = EXTRA_TERMS[:2] if args.quick else EXTRA_TERMS
        sel = select_terms(d, passes, extra)
        sims["midpoint_selected"] = sel.pop("_sim")
        result["selection"] = sel
        rows.append(sel)
        print(f"backward elimination ({len(sel['candidates'])} candidates, validation FIT): {sel['n_params']} terms, "
              f"FIT est {sel['fit_estimation']:.2f} % val {sel['fit_validation']:.2f} % (optimistic): "
              f"{' '.join(sel['terms'])}")
    if not args.no_repetition:
        max_segments = args.segments if args.segments is not None else (3 if args.quick else 10)
        segments = find_segments(n_samples=n, max_segments=max_segments)
        rep = repeat_segments(segments, n, passes, align, result.get("selection", {}).get("terms"))
        result["repetition"] = rep
        print(f"repetition over {len(segments)} segments (validation FIT %: median, mean +- SD [min, max], "
              "segments below 0 %):")
        for m, s in rep["summary"].items():
            print(f"  {m:20s} {s['median']:6.1f}  {s['mean']:9.1f} +- {s['sd']:9.1f} [{s['min']:9.1f}, {s['max']:5.1f}]"
                  f"  {s['n_negative']}")
        for name, v in rep["verdicts"].items():
            parts = ", ".join(f"{k}: {x['verdict']}, {x['wins']}/{x['segments']} wins, median "
                              f"{x['median_difference']:+.1f}, Wilcoxon p {x['p_wilcoxon']:.3f}"
                              for k, x in v.items() if isinstance(x, dict))
            print(f"  {name}: {'holds' if v['holds'] else 'does not hold'} ({parts})")
    if not args.no_plots:
        result["figures"] = [str(p) for p in plot(d, sims, rows, out, result.get("repetition"))]
        print("figures:", ", ".join(result["figures"]))
    result["runtime_s"] = round(time.perf_counter() - t0, 1)
    save_results(out, "results.json", result, args.json)
    print(f"runtime {result['runtime_s']} s")
    return 0 if all(np.isfinite(r["fit_validation"]) for r in result["rows"]) else 1


if __name__ == "__main__":
    raise SystemExit(main())
