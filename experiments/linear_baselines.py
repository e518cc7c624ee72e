"""Linear baselines of Paper IV (M-I, M-II) plus ARX, subspace and multiple-model identification.

Protocol (Paper IV): 1200 samples at Ts = 0.5 s from a WHTC segment, first 900 for estimation and last 300 for
validation, every signal normalised with the estimation statistics; output: tailpipe NOx. FIT and MSE on the
simulated output in normalised units, initial state estimated from each record (as MATLAB ``compare``).

    python -m experiments.linear_baselines [--json PATH] [--seed 0] [--design production|excitation] [--synthetic]

The data come from :func:`ident.plant_data.whtc_dataset` under the dosing design ``--design`` (default: the thesis'
production feedforward dosing; ``excitation`` adds random ANR steps, and was the only design until 2026-11-24, when
the production design was added after the excitation design's Paper IV table fell short of the thesis' figure);
``--synthetic`` uses the surrogate of :func:`ident.plant_data.synthetic_scr_dataset` instead (development only; the
JSON's ``data_source`` and ``design`` say which).
"""
from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from experiments._runs import run_folder, save_results
from ident.dataset import IODataset
from ident.linear import ARX, N4SID, OutputError, StateSpacePEM
from ident.metrics import compare
from ident.multiple_model import MultipleModel, quantile_edges
from ident.plant_data import (
    PAPER4_DEFAULT_DESIGN,
    PAPER4_DESIGNS,
    PAPER4_N_ESTIMATION,
    PAPER4_N_SAMPLES,
    synthetic_scr_dataset,
    whtc_dataset,
)
from ident.preprocessing import normalize_split

#: Paper IV Table 2 (published, on the authors' simulator): estimation FIT %, MSE, validation FIT %, MSE.
PUBLISHED = {"M-I": (61.76, 0.156, 40.33, 0.245), "M-II": (68.93, 0.103, 38.92, 0.256)}


def models(est: IODataset) -> dict[str, Any]:
    """The model set; scheduling on inlet temperature and exhaust flow (input columns 2 and 3), 2 x 2 regions
    with equal sample counts in the estimation data."""
    edges = [quantile_edges(est.u[:, c], 2) for c in (2, 3)]
    return {
        "M-I": StateSpacePEM(order=2, focus="simulation"),
        "M-II": OutputError(nb=2, nf=2, nk=1),
        "N4SID": N4SID(order=2),
        "ARX": ARX(na=2, nb=2, nk=1),
        "MM-ARX": MultipleModel(scheduling=[2, 3], edges=edges, local="arx", na=2, nb=2, nk=1),
        "MM-OE": MultipleModel(scheduling=[2, 3], edges=edges, local="oe", na=2, nb=2, nk=1),
    }


def run(ds: IODataset, n_samples: int = PAPER4_N_SAMPLES, n_estimation: int = PAPER4_N_ESTIMATION
        ) -> list[dict[str, Any]]:
    """Fit every model on the estimation part and score it on both parts; one row per model."""
    ds = ds.select(outputs=[0])[:n_samples]
    split = normalize_split(*ds.split(index=n_estimation))
    est, val = split.estimation, split.validation
    rows = []
    for name, model in models(est).items():
        t0 = time.perf_counter()
        model.fit(est.u, est.y)
        fit_s = time.perf_counter() - t0
        ce, cv = compare(model, est), compare(model, val)
        row = {"model": name, "n_params": int(model.n_params_), "fit_estimation": float(ce.fit),
               "fit_validation": float(cv.fit), "mse_estimation": float(ce.mse), "mse_validation": float(cv.mse),
               "fit_validation_1step": float(compare(model, val, k=1).fit), "fit_time_s": round(fit_s, 3)}
        if name in PUBLISHED:
            p = PUBLISHED[name]
            row["published"] = {"fit_estimation": p[0], "mse_estimation": p[1], "fit_validation": p[2],
                                "mse_validation": p[3]}
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write the results to this JSON file")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--design", choices=sorted(PAPER4_DESIGNS),
                    help="dosing design of the simulator data (ident.plant_data.PAPER4_DESIGNS; default "
                         f"{PAPER4_DEFAULT_DESIGN}, the thesis')")
    ap.add_argument("--synthetic", action="store_true",
                    help="use the synthetic SCR surrogate instead of the environment (development only)")
    args = ap.parse_args(argv)
    if args.synthetic and args.design is not None:
        ap.error("--design is a dosing design of the simulator data; --synthetic uses the surrogate instead")
    design = None if args.synthetic else (args.design or PAPER4_DEFAULT_DESIGN)
    out = run_folder("linear_baselines", json_path=args.json)  # created and checked before the fits
    if args.synthetic:
        ds, source = synthetic_scr_dataset(seed=args.seed), "synthetic surrogate (ident.plant_data)"
    else:
        ds = whtc_dataset(seed=args.seed, design=design)
        source = f"scr_env WHTC rollout, {design} design ({PAPER4_DESIGNS[design].description})"
    rows = run(ds)
    result = {"rows": rows, "data_source": source, "design": design, "seed": args.seed,
              "protocol": {"n_samples": PAPER4_N_SAMPLES, "n_estimation": PAPER4_N_ESTIMATION, "dt_s": ds.dt,
                           "normalisation": "estimation mean/SD", "fit": "simulated output, x0 estimated",
                           "output": ds.output_names[0]}}
    print(f"data: {source}, seed {args.seed}")
    print(f"{'model':8s} {'params':>6s} {'FIT est':>8s} {'FIT val':>8s} {'MSE est':>8s} {'MSE val':>8s}  published")
    for r in rows:
        pub = r.get("published")
        ptxt = f"{pub['fit_estimation']:.2f} / {pub['fit_validation']:.2f} %" if pub else ""
        print(f"{r['model']:8s} {r['n_params']:6d} {r['fit_estimation']:7.2f}% {r['fit_validation']:7.2f}% "
              f"{r['mse_estimation']:8.3f} {r['mse_validation']:8.3f}  {ptxt}")
    save_results(out, "results.json", result, args.json)
    finite = all(np.isfinite(r["fit_validation"]) for r in rows)
    return 0 if finite else 1


if __name__ == "__main__":
    raise SystemExit(main())
