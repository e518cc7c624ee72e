"""Paper IV's comparison over many independent segments and cycles: do the thesis' conclusions hold beyond one
segment? And the NH3 slip as a second output (the thesis' stated future work). The segments, the dosing designs
(``--design``), the summaries and the verdicts are :mod:`ident.thesis.multisegment`'s docstring.

    python -m experiments.paper4_multisegment [--json PATH] [--segments 4] [--design production|excitation|slip]
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small fits: one BLAS thread (see reproduce_paper4)
os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse
import time
from typing import Any

from experiments._runs import run_folder, save_results
from ident.plant_data import PAPER4_DEFAULT_DESIGN
from ident.thesis.multisegment import (
    DESIGNS,
    SLIP_MIN_SD_PPM,
    conclusions,
    load_segment,
    mimo_summary,
    segment_list,
    study_segment,
)


def _print_summary(title: str, summary: dict[str, Any], verdicts: dict[str, Any]) -> None:
    n = next(iter(summary.values()))["n"]
    print(f"\n{title}: validation FIT over {n} segments, median [quartiles]  mean (SD)  [min, max]")
    for m, s in summary.items():
        print(f"  {m:6s} {s['median']:6.1f} [{s['q25']:6.1f}, {s['q75']:6.1f}]  {s['mean']:7.1f} ({s['sd']:5.1f})  "
              f"[{s['min']:7.1f}, {s['max']:6.1f}]")
    print("  thesis conclusions (paired differences of validation FIT):")
    for k, v in verdicts.items():
        print(f"    {k:46s} median {v['median_diff']:+6.1f}, mean {v['mean_diff']:+7.1f} (t {v['t']:5.2f}), "
              f"better in {v['wins']}/{v['n']}, Wilcoxon p {v['p_wilcoxon']:.3f}: {v['verdict']}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the results to this JSON file")
    ap.add_argument("--segments", type=int, default=4,
                    help="number of segments (default 4, about 1-2 min; 15 for the full run)")
    ap.add_argument("--design", choices=sorted(DESIGNS), default=PAPER4_DEFAULT_DESIGN,
                    help="dosing design (module docstring): production (default: the thesis' feedforward alone), "
                         "excitation (random ANR steps) or slip (over-dosing phases)")
    args = ap.parse_args(argv)
    if args.segments < 2:
        ap.error("--segments must be at least 2 (the conclusions are paired tests over segments)")
    out = run_folder("paper4_multisegment", json_path=args.json)
    t0 = time.perf_counter()
    segs = segment_list(args.segments)
    print(f"design {args.design}: {DESIGNS[args.design].description}")
    per_segment = []
    for cyc, seed, start in segs:
        ds = load_segment(cyc, seed, start, args.design)
        entry = {"cycle": cyc, "seed": seed, "start_s": start, **study_segment(ds)}
        per_segment.append(entry)
        fits = "  ".join(f"{r['model']} {r['fit_validation']:6.1f}" for r in entry["nox"])
        slip = ("slip: " + "  ".join(f"{r['model']} {r['fit_validation']:6.1f}" for r in entry["nh3_slip"])
                if isinstance(entry["nh3_slip"], list) else "slip not identifiable")
        print(f"{cyc:6s} seed {seed:3d} {start:6.0f} s | NOx val FIT {fits} | {slip}", flush=True)
    summary, verdicts = conclusions(per_segment, "nox")
    d = DESIGNS[args.design]
    result: dict[str, Any] = {
        "design": {"name": args.design, "base_anr": d.base_anr, "excitation": repr(d.excitation),
                   "description": d.description},
        "segments": per_segment, "summary_fit_validation": summary, "conclusions": verdicts,
        "nh3_slip_identified_segments": sum(isinstance(e["nh3_slip"], list) for e in per_segment),
        "n_segments": len(segs)}
    _print_summary("tailpipe NOx", summary, verdicts)
    n_slip = result["nh3_slip_identified_segments"]
    print(f"\nNH3 slip varies (SD > {SLIP_MIN_SD_PPM} ppm in both parts) in {n_slip} of {len(segs)} segments")
    if n_slip >= 2:
        s_sum, s_ver = conclusions(per_segment, "nh3_slip")
        result["nh3_slip_summary_fit_validation"], result["nh3_slip_conclusions"] = s_sum, s_ver
        _print_summary("NH3 slip", s_sum, s_ver)
        result["mimo"] = mimo_summary(per_segment)
        print("  joint NOx + slip state-space model vs M-I fitted to each output alone (validation FIT medians):")
        for k, v in result["mimo"].items():
            print(f"    {k:32s} joint {v['joint']['median']:6.1f}, alone {v['m1_alone']['median']:6.1f}, "
                  f"joint better in {v['joint_vs_alone']['wins']}/{v['joint_vs_alone']['n']}")
    result["runtime_s"] = round(time.perf_counter() - t0, 1)
    save_results(out, "results.json", result, args.json)
    print(f"\n{result['runtime_s']:.0f} s; results in {out / 'results.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
