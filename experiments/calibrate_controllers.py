"""Calibrate each MPC's storage knob on calibration cycles, never on the benchmark cycles.

    python -m experiments.calibrate_controllers [--json PATH] [--controller identified identified_preview oracle]
        [--values V ...] [--seeds 5 6 7 8] [--noise-seeds 0 1 2] [--duration S] [--slip-target 8] [--workers 1]
        [--no-rescue]

An economic MPC fills the NH3 storage as far as its terminal cost lets it: little storage means NOx breakthrough
at load steps, a full store slips at the next heat-up. The knob per controller (:data:`KNOBS`):

* ``identified`` (grey-box NMPC, no preview), ``identified_preview`` (with the cycle preview), ``identified_nh3``
  (with the preview and an EKF that also reads the tailpipe NH3 sensor): the terminal value of stored NH3 [g/mol];
  ``identified_coverage_p0``: the benchmarked grey-box NMPC (``mpc_identified``) with its EKF's prior variance of the
  cells' coverage at the episode start (best run with ``--noise-seeds``: it is about robustness to sensor noise);
* ``lookup_table`` (:class:`control.baselines.LookupTableDosing`): the window level ``anr_scale`` of its ANR map;
* ``oracle`` (the single-rate first-principles NMPC with the cycle preview, the earlier reference,
  :func:`control.factory.single_rate_oracle_mpc`): the *safe slip* [ppm] that sets its safe coverage, the coverage
  whose desorption at the hottest temperature of the next 120 s gives that slip (terminal penalty above it);
  ``oracle_storage``: its terminal value of stored NH3 [g/mol];
* the multi-rate oracle of issue 19, the reference (:func:`control.factory.multirate_oracle_mpc`):
  ``multirate_slip_price``, its price of NH3 slip [g AdBlue equivalent per ppm s]; ``multirate_horizon``, its number
  of coarse stages after the 2 s ones; ``multirate_coarse_steps``, the length of each coarse stage [control
  intervals of 0.5 s]; ``multirate_budget_gain``, the gain of its slip-budget price update (0: a fixed price);
  ``multirate_storage`` and ``multirate_safe_slip``; each with the others at their defaults.

Each value is run in closed loop on seeded random cycles (``cycle="random"``, seeds ``--seeds``; the
identification records use seeds 1-3, the benchmarks the hot WHTC and WHSC) and the rule of the look-up table's
calibration (:mod:`control.baselines`) picks it: the lowest mean tailpipe NOx among the values whose mean NH3 slip
is at most ``--slip-target`` (8 ppm: a 20 % margin below the 10 ppm limit) and whose failed solves stay under 1 %
of the steps (:data:`MAX_FAILURE_RATE`) on *every* calibration cycle. The table also gives failed and rescued
solves and solve times (median of the episodes' medians, worst p95; CPU time of the solving thread).
``--no-rescue``: the grey-box NMPCs without their IPOPT rescue solver. ``--noise-seeds``: each cycle once per
sensor-noise seed (the same cycle, ``reset(seed=noise seed, options={"cycle_seed": ...})``). ``--duration``:
shorter random cycles (for slow controllers). Results go to ``runs/calibrate_controllers/<stamp>/``; the chosen
numbers are the defaults of :mod:`control.factory` (with the command and table). Re-run it when the plant changes.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from control.factory import (
    CALIBRATION_KNOBS,
    IDENT_EXCITATION,
    IDENT_SEEDS,
    calibration_controller,
    greybox_record,
)
from experiments._runs import run_folder, save_results
from experiments.sweep import add_arguments, from_args, run_sweep

#: the calibrated argument of each controller and the values tried by default (control.factory.CALIBRATION_KNOBS)
KNOBS = CALIBRATION_KNOBS
DEFAULT_SEEDS = (5, 6, 7, 8)
SLIP_TARGET_PPM = 8.0
#: the rule also asks for fewer failed solves than this share of the steps on every calibration cycle: a
#: controller (a reference above all) that falls back to the look-up table more often is not what it claims to be
MAX_FAILURE_RATE = 0.01


_controller = calibration_controller


def cycle_seed(seed: int) -> int:
    """The seed of the random cycle that ``UreaSCREnv(cycle="random").reset(seed=seed)`` draws (so that the cycle can
    be replayed under another sensor-noise seed with ``options={"cycle_seed": ...}``)."""
    from gymnasium.utils import seeding

    return int(seeding.np_random(seed)[0].integers(0, 2**31 - 1))


def episode(kind: str, value: float, seed: int, model_file: str | None, rescue: bool = True,
            noise_seed: int | None = None, duration_s: float | None = None) -> dict[str, Any]:
    """One closed-loop episode of ``kind`` with its knob at ``value`` on the random cycle of ``seed`` (the grey-box
    model read from ``model_file`` for the identified kinds, with or without its ``rescue`` solver); with
    ``noise_seed``, the same cycle under the sensor noise of that seed; ``duration_s``: the random cycle's length."""
    from control.evaluation import evaluate
    from ident.greybox import StorageGreyBox

    t0 = time.perf_counter()
    policy = _controller(kind, value, None if model_file is None else StorageGreyBox.load(model_file), rescue)
    run = {"seeds": (seed,)} if noise_seed is None else {"seeds": (noise_seed,),
                                                         "reset_options": {"cycle_seed": cycle_seed(seed)}}
    env_kwargs = dict(getattr(policy, "env_kwargs", None) or {})
    if duration_s is not None:
        env_kwargs["random_cycle_duration_s"] = float(duration_s)
    res = evaluate(policy, cycles=("random",), env_kwargs=env_kwargs or None, name=kind, **run)[0]
    k = res.kpis
    return {"controller": kind, "knob": KNOBS[kind][0], "value": value, "seed": seed, "noise_seed": noise_seed,
            "tailpipe_nox_g_per_kwh": k["tailpipe_nox_g_per_kwh"], "mean_nh3_slip_ppm": k["mean_nh3_slip_ppm"],
            "peak_nh3_slip_ppm": k["peak_nh3_slip_ppm"], "nox_conversion": k["nox_conversion"],
            "solver_failures": res.stats.get("solver_failures", float("nan")),
            "solver_rescued": res.stats.get("solver_rescued", 0.0), "solves": res.stats.get("solves", float("nan")),
            "solve_time_ms_median": res.stats.get("solve_time_ms_median", float("nan")),
            "solve_time_ms_p95": res.stats.get("solve_time_ms_p95", float("nan")),
            "duration_s": k.get("duration_s"), "wall_time_s": time.perf_counter() - t0}


def _rate(row: dict[str, Any]) -> float:
    """The episode's failed solves per solve (0 for a controller without solves)."""
    fails, solves = row.get("solver_failures", 0.0), row.get("solves", 0.0)
    return float(fails) / float(solves) if solves and np.isfinite(fails) and np.isfinite(solves) else 0.0


def _times(rows: list[dict[str, Any]]) -> dict[str, float]:
    """The episodes' solve times [ms]: the median of their medians and the worst p95 (NaN without solves)."""
    med = [r.get("solve_time_ms_median", float("nan")) for r in rows]
    p95 = [r.get("solve_time_ms_p95", float("nan")) for r in rows]
    finite = [v for v in p95 if np.isfinite(v)]
    return {"solve_time_ms_median": float(np.nanmedian(med)) if finite else float("nan"),
            "solve_time_ms_p95": float(max(finite)) if finite else float("nan")}


def choose(rows: list[dict[str, Any]], slip_target_ppm: float = SLIP_TARGET_PPM,
           max_failure_rate: float = MAX_FAILURE_RATE) -> dict[str, Any]:
    """The calibration rule (module docstring) on the episode rows of one controller: ``{"value", "table"}``;
    ``value`` is None when no value keeps the slip below the target on every cycle."""
    table = []
    for v in sorted({r["value"] for r in rows}):
        rs = [r for r in rows if r["value"] == v]
        table.append({"value": v,
                      "mean_tailpipe_nox_g_per_kwh": float(np.mean([r["tailpipe_nox_g_per_kwh"] for r in rs])),
                      "max_mean_nh3_slip_ppm": float(max(r["mean_nh3_slip_ppm"] for r in rs)),
                      "solver_failures": float(sum(r["solver_failures"] for r in rs)),
                      "max_failure_rate": float(max(_rate(r) for r in rs)),
                      "solver_rescued": float(sum(r.get("solver_rescued", 0.0) for r in rs)),
                      "solves": float(sum(r.get("solves", 0.0) for r in rs)), **_times(rs)})
    ok = [t for t in table if t["max_mean_nh3_slip_ppm"] <= slip_target_ppm
          and t["max_failure_rate"] <= max_failure_rate]
    best = min(ok, key=lambda t: t["mean_tailpipe_nox_g_per_kwh"]) if ok else None
    return {"value": None if best is None else best["value"], "table": table}


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=None, help="also write the JSON result here")
    ap.add_argument("--controller", nargs="+", default=["identified"], choices=sorted(KNOBS))
    ap.add_argument("--values", nargs="+", type=float, default=None,
                    help="knob values to try (default: KNOBS per controller)")
    ap.add_argument("--seeds", nargs="+", type=int, default=list(DEFAULT_SEEDS), help="random calibration cycles")
    ap.add_argument("--noise-seeds", nargs="+", type=int, default=None,
                    help="run each calibration cycle under these sensor-noise seeds (default: the cycle's own seed)")
    ap.add_argument("--duration", type=float, default=None,
                    help="length of each random calibration cycle [s] (default: the environment's 1800 s)")
    ap.add_argument("--slip-target", type=float, default=SLIP_TARGET_PPM, help="mean slip bound per cycle [ppm]")
    ap.add_argument("--ident-seeds", nargs="+", type=int, default=None,
                    help="random cycles of the grey-box identification (default: control.factory.IDENT_SEEDS)")
    ap.add_argument("--excitation", nargs=4, type=float, default=None, metavar=("LOW", "HIGH", "HOLD_MIN", "HOLD_MAX"),
                    help="RandomSteps ANR excitation of the identification (default: control.factory's)")
    ap.add_argument("--no-rescue", action="store_true",
                    help="grey-box NMPCs without their IPOPT rescue solver (control.factory.IDENT_SOLVER)")
    add_arguments(ap)
    args = ap.parse_args(argv)
    if args.workers is None:
        args.workers = 2
    if set(args.ident_seeds or IDENT_SEEDS) & set(args.seeds):
        ap.error("--ident-seeds and --seeds must differ: calibration cycles are not identification data")
    out = run_folder("calibrate_controllers", json_path=args.json)
    t0 = time.perf_counter()
    ident, model_file = None, None
    if any(c.startswith("identified") for c in args.controller):
        seeds = tuple(args.ident_seeds or IDENT_SEEDS)
        excitation = tuple(args.excitation or IDENT_EXCITATION)
        print(f"identifying the grey-box storage model (random cycles {seeds}, RandomSteps{excitation}) ...",
              flush=True)
        model, ident = greybox_record(seeds, excitation)
        model_file = str(model.save(out / "greybox_model"))
    tasks = [{"kind": c, "value": v, "seed": s, "model_file": model_file if c.startswith("identified") else None,
              "rescue": not args.no_rescue, "noise_seed": n, "duration_s": args.duration} for c in args.controller
             for v in (args.values or KNOBS[c][1]) for s in args.seeds for n in (args.noise_seeds or [None])]
    rows = run_sweep(episode, tasks, description="calibration episodes", **from_args(args))
    doc: dict[str, Any] = {"slip_target_ppm": args.slip_target, "seeds": args.seeds, "rows": rows, "chosen": {},
                           "noise_seeds": args.noise_seeds, "duration_s": args.duration, "rescue": not args.no_rescue,
                           "identification": None if ident is None else ident["data"]}
    for c in args.controller:
        res = choose([r for r in rows if r["controller"] == c], args.slip_target)
        doc["chosen"][c] = res
        print(f"\n{c}: {KNOBS[c][0]} -> mean tailpipe NOx [g/kWh], worst mean slip [ppm], failed / rescued / all "
              "solves, solve time median / worst p95 [ms]")
        for t in res["table"]:
            print(f"  {t['value']:7.4g}  {t['mean_tailpipe_nox_g_per_kwh']:.3f}  {t['max_mean_nh3_slip_ppm']:6.2f}  "
                  f"{t['solver_failures']:5.0f} / {t['solver_rescued']:4.0f} / {t['solves']:6.0f}  "
                  f"{t['solve_time_ms_median']:6.1f} / {t['solve_time_ms_p95']:6.1f}")
        print(f"  rule (lowest mean NOx with worst-cycle mean slip <= {args.slip_target:g} ppm and failed solves "
              f"<= {MAX_FAILURE_RATE:.0%} of the steps on every cycle) chooses: {res['value']}")
    doc["wall_time_s"] = time.perf_counter() - t0
    save_results(out, "calibrate_controllers.json", doc, args.json)
    print(f"wrote {out} in {doc['wall_time_s']:.0f} s")
    return doc


if __name__ == "__main__":
    main()
