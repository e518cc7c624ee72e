"""Adaptive MPC on an ageing catalyst (issue 9): fixed identified model vs a model adapted online by RPEM.

    python -m experiments.adaptive_ageing [--json PATH] [--quick] [--cycles N] [--cycle whtc|whsc|alternate]
                                          [--end-storage-retention R] [--end-activity-retention R] [--ident PATH]

Scenario. The grey-box storage model (:class:`ident.greybox.StorageGreyBox`) is identified once on the fresh
catalyst (:func:`control.factory.greybox_record`). The plant then ages over a sequence of ``n`` hot cycles
(default 6 WHTCs) with the ageing severity rising linearly from 0 to 1: the catalyst is
``CatalystParams().replace(storage_retention=1 - (1 - R_s) s, activity_retention=1 - (1 - R_a) s)`` passed as
``catalyst=``, by default to an end of life keeping R_s = 60 % of the NH3 storage capacity and R_a = 50 % of the
activity (``--end-storage-retention`` / ``--end-activity-retention`` change it). The measured CLEERS ageing
(``age_h``, :data:`scr_env.params.AGEING_TABLE`) is milder and not a pure capacity/activity scaling, so the true
retentions the estimator tracks are these explicit ones. ``--quick``: 3 cycles of the first ``--quick-seconds``
(600 s) of the WHTC.

Controllers (both see the measured signals only, every episode a hot start with an empty catalyst):

* ``fixed``: :func:`control.factory.identified_mpc` on the fresh-catalyst model, for every cycle.
* ``adaptive``: :class:`control.adaptive.AdaptiveMPC`, the same MPC (same horizon, weights, solver, EKF noise; its
  terminal cost, if any, scaled with the capacity exp(d_cap)), whose prediction model carries two drift parameters d =
  (d_cap, d_act), log retentions relative to the identified model: capacity Omega exp(d_cap) (``p[0] + d_cap``) and
  activity exp(d_act) on both the SCR and the NH3-oxidation pre-exponentials (``p[5] + d_act``, ``p[7] + d_act``, as
  ageing scales both in the simulator). A :class:`ident.rpem.parametric.ParametricRPEM` estimates d online at every
  0.5 s step from the inputs [upstream NOx ppm, urea g/min of the applied dose (obs[4]), inlet T, flow] and the
  tailpipe NOx sensor only (model output ``a NOx + b NH3`` with the fitted sensor gains), forgetting factor
  ``--forgetting`` (0.998, a memory of about 250 s), the estimates clipped to the retention box ``--box`` (0.2 ..
  1.05: ageing only removes capacity and activity; a clip rather than the recursion's reject-the-update projection,
  which froze both estimates whenever one of them sat at a bound). The estimate is carried over from cycle to cycle
  (the recursion's model state and sensitivities restart with the empty catalyst at each reset, where the plant
  restarts too). Certainty equivalence at every step: d enters the NLP as stage parameters (and the terminal value of
  the stored NH3 scales with exp(d_cap)), so the NLP is built once and no rebuild is needed; the EKF's model is
  refreshed with the current d every ``--ekf-refresh`` steps (cheap: a CasADi function).

Outputs to ``runs/adaptive_ageing/<stamp>/``: ``adaptive_ageing.json`` {"cycles": [{"index", "cycle",
"severity", "true_retention", "fixed": KPIs, "adaptive": KPIs, "estimates": {...}}], "summary": {...}},
``table.txt``, ``kpis_vs_cycle.png`` (KPIs of both controllers vs cycle) and ``parameter_tracking.png`` (the
RPEM estimates over the sequence vs the true retentions). The fixed controller runs in a second process
alongside the (sequential) adaptive one.
"""
from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from control.adaptive import DRIFT_NAMES
from control.ageing import (
    AGED_END,
    SLIP_TARGET_PPM,
    retention,
    run_adaptive_sequence,
    run_fixed_sequence,
    schedule,
    sequence_summary,
    sequence_table,
)
from control.plots import ageing_figures
from experiments._runs import run_folder, save_results, write_text


def _fixed_job(args: tuple) -> list[dict[str, float]]:
    """The fixed NMPC's sequence in a worker process: ``(model file, items, quick, end, seconds, storage value)``."""
    from ident.greybox import StorageGreyBox

    model_file, *rest = args
    return run_fixed_sequence(StorageGreyBox.load(model_file), *rest)


def run(model: Any, model_file: str | None, items: list[dict[str, Any]], quick: bool, end: tuple[float, float],
        seconds: float | None, parallel: bool = True, **kw: Any) -> tuple[dict[str, Any], np.ndarray]:
    """Both controllers over the sequence (the fixed one in a second process if ``parallel``, from the saved
    ``model_file``); the JSON document (without the run folder) and the RPEM history."""
    storage_value = kw.get("storage_value", 200.0)
    if parallel and model_file is not None:
        with ProcessPoolExecutor(max_workers=1) as ex:
            fut = ex.submit(_fixed_job, (model_file, items, quick, end, seconds, storage_value))
            ad_rows, est, hist = run_adaptive_sequence(model, items, quick, end, seconds, **kw)
            fx_rows = fut.result()
    else:
        fx_rows = run_fixed_sequence(model, items, quick, end, seconds, storage_value)
        ad_rows, est, hist = run_adaptive_sequence(model, items, quick, end, seconds, **kw)
    cycles = []
    for it, f, a, e in zip(items, fx_rows, ad_rows, est, strict=True):
        rs, ra = retention(it["severity"], end)
        cycles.append({**it, "true_retention": {"storage": rs, "activity": ra}, "fixed": f, "adaptive": a,
                       "estimates": e})
    return {"cycles": cycles, "summary": sequence_summary(cycles)}, hist


def _model(path: Path | None) -> tuple[Any, dict[str, Any]]:
    """The fresh-catalyst grey-box model: read from ``--ident`` (a JSON with params, sensor_gains, n_cells, dt, or a
    control_benchmark JSON) or identified."""
    from control.factory import greybox_record
    from ident.greybox import StorageGreyBox

    if path is None:
        print("identifying the grey-box storage model on the fresh catalyst ...", flush=True)
        model, ident = greybox_record()
        print(f"  fitted in {ident['fit_seconds']:.0f} s", flush=True)
        return model, ident
    ident = json.loads(path.read_text(encoding="utf-8"))
    ident = ident.get("identified_model", ident)
    missing = [k for k in ("params", "sensor_gains", "n_cells", "dt") if k not in ident]
    if missing:
        raise ValueError(f"--ident {path}: no {', '.join(missing)} (a JSON with params, sensor_gains, n_cells, dt or "
                         "a control_benchmark JSON is needed)")
    print(f"identified model read from {path}", flush=True)
    return StorageGreyBox.from_params(ident["params"], ident["sensor_gains"], int(ident["n_cells"]),
                                      float(ident["dt"])), ident


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=None, help="also write the JSON result here")
    ap.add_argument("--quick", action="store_true", help="2 cycles of 300 s WHTC segments, shorter MPC horizon")
    ap.add_argument("--cycles", type=int, default=None, help="cycles in the sequence (default 4; --quick 2)")
    ap.add_argument("--cycle", default="whtc", choices=("whtc", "whsc", "alternate"), help="cycle type")
    ap.add_argument("--seconds", type=float, default=None,
                    help="use the first SECONDS of each cycle (default 600; --quick 300; 0: whole cycles)")
    ap.add_argument("--storage-value", type=float, default=200.0,
                    help="identified_mpc(storage_value_g_per_mol=...): terminal value of stored NH3 [g/mol]")
    ap.add_argument("--end-storage-retention", type=float, default=AGED_END[0])
    ap.add_argument("--end-activity-retention", type=float, default=AGED_END[1])
    ap.add_argument("--forgetting", type=float, default=0.998, help="RPEM forgetting factor (per 0.5 s step)")
    ap.add_argument("--free", nargs="+", default=list(DRIFT_NAMES), choices=DRIFT_NAMES,
                    help="drift parameters the RPEM estimates (the others stay at the fresh model)")
    ap.add_argument("--box", type=float, nargs=2, default=(0.2, 1.05),
                    help="retention box of the estimates (ageing only removes capacity and activity)")
    ap.add_argument("--ident", type=Path, default=None,
                    help="reuse an identified model (JSON with params, sensor_gains, n_cells, dt; or a "
                         "control_benchmark JSON) instead of identifying")
    ap.add_argument("--serial", action="store_true", help="run the fixed controller in this process too")
    args = ap.parse_args(argv)
    n = args.cycles or (2 if args.quick else 4)
    seconds = args.seconds if args.seconds is not None else (300.0 if args.quick else 600.0)
    seconds = None if seconds <= 0 else seconds
    end = (float(args.end_storage_retention), float(args.end_activity_retention))
    out = run_folder("adaptive_ageing", json_path=args.json)
    t_start = time.perf_counter()
    model, ident = _model(args.ident)
    model_file = str(model.save(out / "greybox_model"))
    items = schedule(n, args.cycle)
    print(f"sequence: {n} x {args.cycle}{'' if seconds is None else f' (first {seconds:.0f} s)'}, severity 0 -> 1, "
          f"end of life: storage x{end[0]:.2f}, activity x{end[1]:.2f}", flush=True)
    doc, hist = run(model, model_file, items, args.quick, end, seconds, parallel=not args.serial,
                    forgetting=args.forgetting, box=tuple(args.box), free=tuple(args.free),
                    storage_value=args.storage_value)
    doc.update({"identified_model": ident, "run_folder": str(out), "quick": bool(args.quick),
                "scenario": {"storage_value_g_per_mol": args.storage_value, "n_cycles": n, "cycle": args.cycle,
                             "seconds": seconds, "end_retention": list(end),
                             "ageing_route": "CatalystParams().replace(storage_retention, activity_retention) as "
                                             "catalyst="},
                "estimator": {"method": "ParametricRPEM", "free": ["log capacity retention (p[0])",
                                                                   "log activity retention (p[5] and p[7])"],
                              "forgetting": args.forgetting, "retention_box": list(args.box),
                              "estimated": list(args.free), "measured": "tailpipe NOx sensor (obs[3])",
                              "model_update": "every step (drift as NLP parameters; EKF model every 20 steps)"},
                "history_every_s": 10.0})
    doc["wall_time_s"] = time.perf_counter() - t_start
    txt = sequence_table(doc)
    print(txt)
    s = doc["summary"]
    verdict = (f"done: the adaptive MPC keeps the mean slip <= {SLIP_TARGET_PPM:g} ppm where the fixed one exceeds it"
               if s["done_criterion_met"] else
               "criterion not met: " + (f"the fixed-model MPC does not exceed {SLIP_TARGET_PPM:g} ppm mean slip in "
                                        "this scenario" if not s["fixed_exceeds_target"] else
                                        f"the adaptive MPC exceeds {SLIP_TARGET_PPM:g} ppm mean slip too"))
    doc["summary"]["verdict"] = verdict
    print(verdict)
    write_text(out / "table.txt", txt + "\n" + verdict + "\n")
    write_text(out / "rpem_history.csv", "cycle,time_s,d_cap,d_act\n"
               + "".join(",".join(f"{v:.18e}" for v in row) + "\n" for row in hist))
    ageing_figures(doc, hist, out, SLIP_TARGET_PPM)
    save_results(out, "adaptive_ageing.json", doc, args.json)
    print(f"wrote {out} in {doc['wall_time_s']:.0f} s")
    return doc


if __name__ == "__main__":
    main()
