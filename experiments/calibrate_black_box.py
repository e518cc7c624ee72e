"""Calibrate the black-box NMPCs of the loop (issue 18) on calibration cycles, never on the WHTC or WHSC.

    python -m experiments.calibrate_black_box [--models rpem hammerstein_wiener] [--seeds 5 6] [--duration 600]
        [--ramped-seeds 5 6 7 8] [--ramped-duration 1200]
        [--configs '{"terminal_s": 0}' '{"anr_band_hi": 2.0}' ...] [--slip-target 8] [--json PATH]
        [--identified JSON] [--closed-loop-iterations N] [--hw-fit '{"multistep_horizon": 160}']
        [--rpem-fit '{"multistep_horizon": 0}']

``--identified``: reuse the models of an earlier run (its JSON, key ``identification``) instead of identifying
again, so a sweep of NMPC settings costs only the closed-loop episodes. ``--closed-loop-iterations N``: identify the
RPEM by N iterations of closed-loop identification (:func:`control.loop.closed_loop_identification`) and keep every
iteration as a model ``rpem-iter<i>`` (``--models rpem-iter0 ... rpem``: the calibration KPIs per iteration).
``--hw-fit`` / ``--rpem-fit``: options of :func:`ident.for_control.fit_hw_for_control` (the Hammerstein-Wiener
model structure) / :func:`ident.for_control.fit_rpem_for_control` (default :data:`control.loop.RPEM_FIT`).

The models are identified as in the loop (:func:`control.loop.identify_for_control`); each configuration (a JSON
dict of :func:`control.blackbox.black_box_nmpc` overrides; ``{}`` is the current default) runs in closed loop on
the seeded random cycles ``--seeds`` (``--duration`` seconds each, sensor-noise seed 0), beside the look-up table.
The rule of :mod:`experiments.calibrate_controllers` picks per model: the lowest mean tailpipe NOx among the
configurations whose mean NH3 slip stays below ``--slip-target`` on every calibration cycle. ``--hw-fit`` passes
options to :func:`ident.for_control.fit_hw_for_control` (calibrating the model structure), ``--identified`` reuses
the models of an earlier ``--json`` instead of identifying again. Each table row lists per cycle: the cycle, NOx
[g/kWh], mean NH3 slip [ppm], failed solves, AdBlue [g], peak NH3 slip [ppm], suboptimal plans applied (the
solver stopped short of convergence at a feasible iterate, :class:`control.mpc.NonlinearMPC`). The chosen values
are the defaults of :data:`control.blackbox.NMPC_SETTINGS`.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from control.loop import BLACK_BOX, identify_for_control
from experiments._runs import environment, run_folder, write_json
from experiments.sweep import add_arguments, from_args, run_sweep


def episode(model: str, config: dict[str, Any], seed: int, duration: float, black_box: dict[str, Any],
            kind: str = "transient") -> dict[str, Any]:
    """One closed-loop run of a configuration (``model`` ``"lookup_table"``: the baseline) on a random cycle.

    ``kind="transient"``: the environment's random cycle drawn at ``reset(seed=seed)`` (the calibration cycles of
    every earlier round); ``"ramped_modes"``: ``scr_env.cycles.random_cycle(duration, seed, kind="ramped_modes")``.
    """
    from control.blackbox import black_box_nmpc
    from control.evaluation import evaluate
    from control.factory import make_controller
    from control.loop import load_for_control
    from scr_env.cycles import random_cycle
    from scr_env.envs.urea_scr import UreaSCREnv

    if kind == "transient":
        env = UreaSCREnv(cycle="random", random_cycle_duration_s=duration)
        env.reset(seed=seed)
        trace = env.trace
    else:
        trace = random_cycle(duration, seed, kind=kind)
    t0 = time.perf_counter()
    if model == "lookup_table":
        policy, kw = make_controller("lookup_table"), None
    else:
        policy = black_box_nmpc(*load_for_control(model, black_box), **config)
        kw = policy.env_kwargs
    res = evaluate(policy, cycles=(trace,), seeds=(0,), env_kwargs=kw, name=model)[0]
    stats = policy.stats() if hasattr(policy, "stats") else {}
    return {"model": model, "config": config, "seed": seed, "nox": res.kpis["tailpipe_nox_g_per_kwh"],
            "slip": res.kpis["mean_nh3_slip_ppm"], "peak": res.kpis["peak_nh3_slip_ppm"],
            "adblue_g": res.kpis.get("adblue_g", float("nan")),
            "failures": stats.get("solver_failures", 0.0),
            "suboptimal": stats.get("solver_suboptimal", 0.0), "wall_s": time.perf_counter() - t0}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="+", default=["rpem", "hammerstein_wiener"])
    ap.add_argument("--seeds", type=int, nargs="*", default=[5, 6], help="random (transient) calibration cycles")
    ap.add_argument("--duration", type=float, default=600.0, help="seconds of each calibration cycle")
    ap.add_argument("--configs", nargs="+", default=["{}"], help="JSON dicts of black_box_nmpc overrides")
    ap.add_argument("--ramped-seeds", type=int, nargs="*", default=[],
                    help="ramped-mode calibration cycles (random_cycle(kind='ramped_modes'), WHSC-like) beside --seeds")
    ap.add_argument("--ramped-duration", type=float, default=1200.0, help="seconds of each ramped-mode cycle")
    ap.add_argument("--ident-ramped-seeds", type=int, nargs="*", default=None,
                    help="ramped-mode identification cycles beside the transient ones (default: the loop's)")
    ap.add_argument("--slip-target", type=float, default=8.0, help="mean NH3 slip bound on every cycle [ppm]")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--identified", type=Path, default=None,
                    help="JSON of an earlier calibrate_black_box run: reuse its identified models")
    ap.add_argument("--closed-loop-iterations", type=int, default=None,
                    help="iterations of closed-loop identification of the RPEM (models rpem-iter<i> kept)")
    ap.add_argument("--closed-loop-nmpc", default="{}", help="JSON overrides of the closed-loop experiments' NMPC")
    ap.add_argument("--hw-fit", default=None, help="JSON dict of ident.for_control.fit_hw_for_control options "
                    "(default: control.loop.HW_FIT)")
    ap.add_argument("--rpem-fit", default=None, help="JSON dict of ident.for_control.fit_rpem_for_control options")
    add_arguments(ap)
    args = ap.parse_args(argv)
    if args.workers is None:
        args.workers = 1
    if any(s in (0,) for s in args.seeds + args.ramped_seeds):
        ap.error("--seeds/--ramped-seeds: use calibration cycles (5-8), not seed 0")
    if set(args.ident_ramped_seeds or ()) & set(args.ramped_seeds):
        ap.error("--ident-ramped-seeds: identification cycles must differ from the --ramped-seeds calibration cycles")
    if not args.seeds and not args.ramped_seeds:
        ap.error("give calibration cycles: --seeds and/or --ramped-seeds")
    try:
        configs = [json.loads(c) for c in args.configs]
    except json.JSONDecodeError as exc:
        ap.error(f"--configs: not JSON ({exc})")
    try:
        hw_fit = None if args.hw_fit is None else json.loads(args.hw_fit)
        rpem_fit = None if args.rpem_fit is None else json.loads(args.rpem_fit)
    except json.JSONDecodeError as exc:
        ap.error(f"--hw-fit/--rpem-fit: not JSON ({exc})")
    out = run_folder("calibrate_black_box", json_path=args.json)
    if args.identified is not None:
        black_box = json.loads(args.identified.read_text())["identification"]
    elif args.closed_loop_iterations is None:
        black_box = identify_for_control(out, kinds=tuple(m for m in args.models if m in BLACK_BOX) or BLACK_BOX,
                                         hw_fit=hw_fit, rpem_fit=rpem_fit, ramped_seeds=args.ident_ramped_seeds)
    else:
        black_box = identify_for_control(out, closed_loop_iterations=args.closed_loop_iterations,
                                         keep_iterations=True, closed_loop_nmpc=json.loads(args.closed_loop_nmpc),
                                         hw_fit=hw_fit, rpem_fit=rpem_fit, ramped_seeds=args.ident_ramped_seeds)
    cycles = [(s, args.duration, "transient") for s in args.seeds]
    cycles += [(s, args.ramped_duration, "ramped_modes") for s in args.ramped_seeds]
    tasks = [{"model": m, "config": c, "seed": s, "duration": d, "black_box": black_box, "kind": k}
             for m, c in [("lookup_table", {})] + [(m, c) for m in args.models for c in configs]
             for s, d, k in cycles]
    rows = run_sweep(episode, tasks, description="calibration", **from_args(args))
    for r, t in zip(rows, tasks, strict=True):  # cycle label: the seed, "modes-<seed>" for a ramped-mode cycle
        r["cycle"] = r["seed"] if t["kind"] == "transient" else f"modes-{r['seed']}"
    lut = {r["cycle"]: r["nox"] for r in rows if r["model"] == "lookup_table"}
    print("lookup table per cycle (cycle, NOx, slip, AdBlue g):",
          [(r["cycle"], r["nox"], r["slip"], r["adblue_g"]) for r in rows if r["model"] == "lookup_table"])
    table, chosen = [], {}
    for m in args.models:
        best = None
        for c in configs:
            rs = [r for r in rows if r["model"] == m and r["config"] == c]
            nox, worst = float(np.mean([r["nox"] for r in rs])), max(r["slip"] for r in rs)
            table.append({"model": m, "config": c, "mean_nox_g_per_kwh": nox, "worst_mean_slip_ppm": worst,
                          "lut_mean_nox_g_per_kwh": float(np.mean([lut[r["cycle"]] for r in rs])),
                          "per_seed": [(r["cycle"], r["nox"], r["slip"], r["failures"], r["adblue_g"], r["peak"],
                                        r["suboptimal"]) for r in rs]})
            print(f"{m} {json.dumps(c)}: NOx {nox:.3f} g/kWh (LUT {table[-1]['lut_mean_nox_g_per_kwh']:.3f}), "
                  f"worst mean slip {worst:.2f} ppm, per cycle {table[-1]['per_seed']}", flush=True)
            if worst <= args.slip_target and (best is None or nox < best[0]):
                best = (nox, c)
        chosen[m] = None if best is None else best[1]
    doc = {"seeds": args.seeds, "duration_s": args.duration, "ramped_seeds": args.ramped_seeds,
           "ramped_duration_s": args.ramped_duration, "hw_fit": hw_fit, "rpem_fit": rpem_fit,
           "slip_target_ppm": args.slip_target,
           "table": table, "chosen": chosen, "identification": black_box, "environment": environment()}
    print("chosen:", json.dumps(chosen))
    write_json(out / "calibrate_black_box.json", doc)
    if args.json is not None:
        write_json(args.json, doc)
    return doc


if __name__ == "__main__":
    main()
