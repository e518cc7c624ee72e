"""The identify-then-control loop, end to end (the thesis' future work, closed on the simulator; issue 18).

    python -m experiments.identify_then_control [--seeds 0 1 2 3 4 5] [--ablation] [--quick] [--json PATH]

1. Excitation experiments on the plant (random cycles, never the calibration cycles 5-8 nor the held-out
   cycles): the grey-box model's records (:func:`control.factory.greybox_record`) and control-relevant records over
   many random cycles (:func:`control.loop.identify_for_control`).
2. Identification for control: the two-output RPEM (the thesis' polynomial chain ODE) and Hammerstein-Wiener
   models (:mod:`ident.for_control`), the grey-box NH3-storage model; k-step FIT on a validation record.
3. NMPC on each identified model with the same footing (:func:`control.loop.loop_controller`: NOx and NH3 sensors
   in an offset-free estimator, cycle preview, slip guard) and the oracle NMPC (:func:`control.factory.oracle_mpc`).
4. Closed loop on the held-out hot WHTC and WHSC (``--quick``: the first 600 s of the WHTC) for every sensor-noise
   seed of ``--seeds``, against the look-up table, the PI baseline, the oracle and the shipped RL policies.
   ``gap_closed[model][cycle]``: the seed mean of the fraction of the look-up-table-to-oracle gap in tailpipe NOx
   [g/kWh] that the NMPC on that model closes (counted only within the 10 ppm mean-slip limit in every seed);
   ``gap_to_limit[cycle]``: the stored clairvoyant limit at 10 ppm (never re-solved) and every controller's seed-mean
   fraction of the look-up-table-to-limit gap (:func:`control.loop.gap_to_limit_over_seeds`);
   ``kpis_per_seed[cycle][controller]``: the per-seed KPI dicts; ``kpis``: their means. ``--ablation`` adds the
   NMPCs with one ingredient removed in turn (:func:`control.loop.ablation_controllers`).

Results: JSON, a markdown report and figures in ``runs/identify_then_control/<stamp>/`` (``--out`` to choose).

Scheduling (local worker processes, ``--workers`` >= 2): the identification runs in this process while the worker
pool already fits the grey-box model (saved to the run folder, read back from its file) and runs the episodes that
need no identified model (look-up table, PI, the oracle, the RL policies; slowest first); the NMPCs on the
identified models join the same pool as soon as their models exist. With Ray or one worker the steps run one
after the other. While identifying, the main process and the pool's workers share the cores, so the timings of
those episodes (solve times, the grey-box fit time) are measured under that load; the KPIs do not depend on it.
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from control.factory import available_rl, greybox_record, oracle_description
from control.loop import (
    BLACK_BOX,
    QUICK_SEGMENT_S,
    SENSOR_NOISE_FREE,
    ablation_controllers,
    gap_closed_over_seeds,
    gap_to_limit_over_seeds,
    held_out,
    identify_for_control,
    identify_while_running,
    replicate_over_seeds,
    slowest_first,
)
from control.loop_report import loop_report
from control.plots import closed_loop_figure
from experiments._runs import environment, run_folder, write_json, write_text
from experiments.sweep import add_arguments, from_args, run_sweep


def episode(name: str, trace_index: int, seed: int, models: dict[str, Any], quick: bool,
            record: bool = False) -> dict[str, Any]:
    """One closed-loop episode (module level, so local processes and Ray workers can run it); ``models``: the
    grey-box model file and the black-box info; ``record``: keep the trajectory (the figures' seed)."""
    from control.evaluation import evaluate
    from control.loop import loop_controller
    from ident.greybox import StorageGreyBox

    trace = held_out(quick)[trace_index]
    t0 = time.perf_counter()
    try:
        greybox = StorageGreyBox.load(models["greybox"]) if name == "mpc_greybox" else None
        policy = loop_controller(name, greybox, models["black_box"], quick)
        res = evaluate(policy, cycles=(trace,), seeds=(seed,), env_kwargs=getattr(policy, "env_kwargs", None),
                       name=name, record_trajectory=record)[0]
    except Exception as exc:  # noqa: BLE001  (a controller that cannot run is reported, the study goes on)
        return {"name": name, "cycle": trace.name, "seed": seed, "error": f"{type(exc).__name__}: {exc}"}
    row = {k: v for k, v in res.row().items() if isinstance(v, (int, float))}
    traj = {k: np.asarray(v).tolist() for k, v in (res.trajectory or {}).items()
            if k in ("time_s", "tailpipe_nox_ppm", "tailpipe_nh3_ppm", "adblue_g_s", "inlet_temperature_k")}
    return {"name": name, "cycle": trace.name, "seed": seed, "row": row, "trajectory": traj,
            "wall_time_s": time.perf_counter() - t0}


def run(quick: bool = False, out: Path | None = None, sweep_kwargs: dict[str, Any] | None = None,
        include_rl: bool = True, json_path: Path | None = None, seeds: tuple[int, ...] = (0,),
        ablation: bool = False) -> dict[str, Any]:
    """The whole loop; returns the JSON document (also written with the report into ``out``)."""
    out = run_folder("identify_then_control", json_path=json_path, folder=out)
    start = time.perf_counter()
    rl, rl_note = available_rl() if include_rl else ([], "RL policies not requested")
    names = ["lookup_table", "mpc_oracle", "mpc_greybox", *[f"mpc_{m}" for m in BLACK_BOX], "pi", *rl]
    names += ablation_controllers(quick=quick) if ablation else []
    traces = held_out(quick)
    tasks = [{"name": n, "trace_index": i, "seed": int(s), "models": None, "quick": quick, "record": s == seeds[0]}
             for s in seeds for n in names for i in range(len(traces))]
    first = [t for t in tasks if t["seed"] == seeds[0] or t["name"] not in SENSOR_NOISE_FREE]
    kw = dict(sweep_kwargs or {})
    workers = kw.get("workers")
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    workers = workers or os.cpu_count() or 1
    print(f"1-4. excitation experiments, identification and {len(tasks)} closed-loop episodes on "
          f"{', '.join(t.name for t in traces)}, seeds {list(seeds)} ...", flush=True)
    if kw.get("backend", "local") == "local" and workers >= 2:
        ident, models, done = identify_while_running(episode, out, quick, ablation, first, rl, workers)
    else:
        greybox, gb = greybox_record()
        ident = {"greybox": gb, "black_box": identify_for_control(out, quick=quick, ablation=ablation)}
        models = {"greybox": str(greybox.save(out / "model_greybox")), "black_box": ident["black_box"]}
        for t in first:
            t["models"] = models
        done = run_sweep(episode, slowest_first(first), description="closed loop", **kw)
    for t in tasks:
        t["models"] = models
    for n, m in ident["black_box"]["models"].items():
        print(f"  {n}: " + (m["error"] if "error" in m else f"k-step FIT {m['validation_kstep_fit_percent']}"))
    results, rerun = replicate_over_seeds(done, seeds)
    again = [t for t in tasks if (t["name"], traces[t["trace_index"]].name) in rerun and t["seed"] != seeds[0]]
    results += run_sweep(episode, again, description="closed loop (rerun)", **(sweep_kwargs or {})) if again else []
    results.sort(key=lambda r: (names.index(r["name"]), seeds.index(r["seed"])))
    errors = [f"{r['name']} on {r['cycle']} (seed {r['seed']}): {r['error']}" for r in results if "error" in r]
    per_seed: dict[str, dict[str, list[dict[str, float]]]] = {t.name: {} for t in traces}
    for r in (r for r in results if "error" not in r):
        per_seed[r["cycle"]].setdefault(r["name"], []).append(r["row"])
    kpis = {c: {n: {k: float(np.mean([row[k] for row in rows if k in row])) for k in rows[0]}
                for n, rows in ctrl.items()} for c, ctrl in per_seed.items()}
    gaps, excluded = gap_closed_over_seeds(per_seed)
    to_limit = gap_to_limit_over_seeds(per_seed)
    doc: dict[str, Any] = {"quick": quick, "seeds": list(seeds), "ablation": ablation,
                           "oracle": oracle_description(quick), "identification": ident, "kpis": kpis,
                           "kpis_per_seed": per_seed, "gap_closed": gaps,
                           "gap_closed_excluded": excluded, "gap_to_limit": to_limit, "errors": errors,
                           "skipped": rl_note or None, "run_folder": str(out), "environment": environment(),
                           "wall_time_s": time.perf_counter() - start}
    figures = []
    for cycle in sorted({r["cycle"] for r in results if "row" in r}):
        runs = [(r["name"], r["row"], r["trajectory"]) for r in results
                if r.get("cycle") == cycle and "row" in r and r["trajectory"] and "-no_" not in r["name"]]
        fig = closed_loop_figure(runs, f"identify-then-control: closed loop on the held-out {cycle}",
                                 out / f"closed_loop_{cycle}.png", coverage=False, slip_log=True, dpi=100)
        figures += [fig] if fig is not None else []
    report = write_text(out / "report.md", loop_report(doc, figures))
    write_json(out / "identify_then_control.json", doc)
    print(report.read_text())
    print(f"report: {report}")
    return doc


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=None, help="also write the JSON result here")
    ap.add_argument("--quick", action="store_true", help=f"first {QUICK_SEGMENT_S:.0f} s of the WHTC only, "
                    "shorter horizons, fewer identification cycles (the main job of `make demo`)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="sensor-noise seeds of the closed-loop runs")
    ap.add_argument("--ablation", action="store_true", help="also run the NMPCs with each ingredient removed in turn")
    ap.add_argument("--out", type=Path, default=None, help="report folder (default runs/identify_then_control/<stamp>)")
    ap.add_argument("--no-rl", action="store_true", help="leave out the shipped RL policies")
    add_arguments(ap)
    args = ap.parse_args(argv)
    if args.workers is None:
        args.workers = 2
    if len(set(args.seeds)) != len(args.seeds) or min(args.seeds) < 0:
        ap.error(f"--seeds must be distinct non-negative integers, got {args.seeds}")
    doc = run(quick=args.quick, out=args.out, sweep_kwargs=from_args(args), include_rl=not args.no_rl,
              json_path=args.json, seeds=tuple(args.seeds), ablation=args.ablation)
    if args.json is not None:
        write_json(args.json, doc)
    return doc


if __name__ == "__main__":
    main()
