"""Closed-loop benchmark of every dosing controller on the hot WHTC and WHSC.

    python -m experiments.control_benchmark [--json PATH] [--quick] [--cycles whtc whsc] [--workers 2] [--seeds 0]

Controllers: ``lookup_table`` and ``pi`` (control.baselines), ``mpc_identified`` (NMPC on a grey-box storage model
identified from open-loop excitation data on random cycles, state by EKF from the measured signals only -- the
tailpipe NOx sensor and a tailpipe NH3 sensor -- with the cycle preview of the engine-out disturbances as the
oracle has it), its variants ``mpc_identified_nox_sensor`` (EKF on the NOx sensor alone) and
``mpc_identified_no_preview`` (NOx sensor alone, the measured disturbances held over the horizon: what a truck
without an NH3 sensor or route preview can do), ``mpc_oracle`` (NMPC on the first-principles catalyst with
privileged state and the cycle preview), and the shipped RL policies ``ppo`` / ``sac`` when :mod:`control.rl` provides them (skipped otherwise, and said so). Writes the KPI
table, a JSON {"cycles": {cycle: {"controllers": {name: KPIs and timings}}}} and plots of the closed-loop
trajectories to ``runs/control_benchmark/<stamp>/``. ``--quick``: the WHTC only, shorter oracle horizon.
``--seeds``: the reset seeds (sensor noise) of every episode (default 0); with several, each controller's figures
are their means and ``per_seed`` lists NOx, slip and failed solves per seed (the plots show the first seed).

Spread over seeds (``--cycles whtc --seeds 0 1 2 3 4 5``): the baselines hardly move (look-up table 0.610-0.612
g/kWh, 6.8-7.3 ppm). The identified NMPC did, before its slip guard (below): 6.7 ppm mean slip for seed 0 but
10.8-13.0 ppm for seeds 1-5 (seed 5 also 0.540 g/kWh), and a rounding-level change of the plant moved seed 0 to
12.5 ppm. The cause: on the WHTC's heat-up at 1500-1740 s the catalyst desorbs its store, the slip bound cannot be
met, nearly every solve fails, and the look-up-table fallback dosed into the slip (seed 1: 89 of the 102 g of
AdBlue there). With the slip guard (a failed solve doses nothing while the NH3 sensor reads above 10 ppm, the
limit, not tuned; :data:`SLIP_GUARD_PPM`): WHTC 0.207-0.214 g/kWh at 3.2-4.8 ppm over seeds 0-5 (230-382 failed
solves), WHSC 0.176-0.184 g/kWh at 0.8-1.1 ppm; after the plant's fast-math compilation (scr_env/physics/backends.py)
WHTC 0.207-0.215 g/kWh at 3.2-4.6 ppm (220-440 failed solves), WHSC 0.177-0.186 g/kWh at 0.8-1.2 ppm. The guard
was added after that WHTC diagnosis; on the calibration cycles it leaves the chosen design unchanged (storage
value 50: 0.286 g/kWh at 1.42 ppm, the guard never acting; it acts at value 100: 0.546 -> 0.681 g/kWh, 16.6 ->
14.6 ppm).
"""
from __future__ import annotations

import argparse
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from control.baselines import FeedforwardPI, LookupTableDosing
from control.evaluation import EpisodeResult, comparison_table, evaluate, summarise
from experiments._runs import run_folder, save_results

CORE = ("lookup_table", "pi", "mpc_identified", "mpc_oracle")
#: the identified-model NMPC and its benchmarked variants (see IDENTIFIED_STORAGE_VALUE)
IDENTIFIED_VARIANTS = ("mpc_identified", "mpc_identified_nox_sensor", "mpc_identified_no_preview")
RL_NAMES = ("ppo", "sac")
IDENT_SEEDS = (1, 2)  # random cycles of the identification experiments (never the benchmark cycles)
#: the identification experiment's ANR excitation: RandomSteps(low, high, min hold s, max hold s) multiplying the
#: feedforward dose at ANR 1 (so ANR 0.1-1.7)
IDENT_EXCITATION = (-0.9, 0.7, 10.0, 120.0)
#: the identified-model MPC's NLP is small: SQP with CasADi's qrqp meets the 20 ms target where IPOPT's
#: per-iteration overhead does not. No dual warm start (NonlinearMPC's default for non-IPOPT solvers: stale
#: multipliers made the exact-Hessian QPs indefinite, qrqp pivoted for long and produced NaN steps -- the WHSC
#: stall); the QP iterations are capped so one hard QP cannot stall an episode
IDENT_SOLVER: dict[str, Any] = {"solver": "sqpmethod", "solver_options": {
    "qpsol": "qrqp", "qpsol_options": {"print_iter": False, "print_header": False, "error_on_fail": False,
                                       "max_iter": 100},
    "print_iteration": False, "print_header": False, "print_status": False, "max_iter": 20, "error_on_fail": False}}
#: the identified-model MPC: implicit stage equations, the cycle preview of the engine-out disturbances (as the
#: oracle), an EKF reading the tailpipe NOx *and* NH3 sensors, and a terminal value of stored NH3 [g AdBlue per
#: mol], all chosen by ``python -m experiments.calibrate_controllers --controller identified_nh3 identified_preview
#: identified --seeds 5 6 7 8`` on four random calibration cycles (never the WHTC/WHSC), rule: the lowest mean
#: tailpipe NOx with mean slip < 8 ppm on each cycle, over all three designs. Mean NOx [g/kWh] at worst-cycle slip
#: [ppm] for storage values 0 / 50 / 100 / 150 / 200 g/mol:
#:   NOx + NH3 sensors, preview: 0.338 at 0.67 / 0.286 at 1.42 / 0.546 at 16.6 (150, 200 not run)  <- 50 chosen
#:   NOx sensor only, preview:   0.346 at 0.45 / 0.311 at 3.83 / 0.353 at 3.99 / 0.271 at 11.5 / 0.274 at 11.8
#:   NOx sensor only, no preview: 0.645 at 9.75 / 0.711 at 40.8 / 0.397 at 8.08 / 0.682 at 12.3 / 0.635 at 26.6
#: The NH3 sensor removes the ambiguity of the cross-sensitive NOx sensor (slip read as NOx, or NOx as slip) and
#: cut the failed solves tenfold (55 against 511 on the four cycles at 50 g/mol). The two NOx-sensor-only designs
#: are benchmarked beside it (``mpc_identified_nox_sensor``: preview, 50 g/mol; ``mpc_identified_no_preview``:
#: 100 g/mol, the closest to the rule).
#: the NH3-sensor NMPC's slip guard on failed solves [ppm of the tailpipe NH3 sensor]: the benchmark's mean-slip
#: limit, not tuned. Added after the WHTC seed study (module docstring) showed the slip episode of 1500-1740 s
#: dosed by the look-up-table fallback through runs of failed solves (seed 1: 89 of 102 g of AdBlue there).
SLIP_GUARD_PPM = 10.0
IDENTIFIED_PREVIEW = True
IDENTIFIED_NH3_SENSOR = True
IDENTIFIED_STORAGE_VALUE = 50.0
NO_PREVIEW_STORAGE_VALUE = 100.0
#: safe-coverage slip level of the oracle MPC [ppm] (the desorption slip at which its terminal storage value stops
#: counting), chosen by the same rule on the same calibration cycles: 20 / 50 / 100 ppm gave mean NOx
#: 0.233 / 0.181 / 0.141 g/kWh at worst-cycle slip 0.09 / 0.94 / 11.5 ppm (100 breaks the 8 ppm rule)
ORACLE_SAFE_SLIP_PPM = 50.0
REPORT_KEYS = ("nox_conversion", "engine_out_nox_g_per_kwh", "tailpipe_nox_g_per_kwh", "mean_nh3_slip_ppm",
               "peak_nh3_slip_ppm", "adblue_g", "nh3_slip_g", "engine_work_kwh", "policy_time_ms_median",
               "policy_time_ms_p95", "solver_failures", "solve_time_ms_median", "solve_time_ms_p95",
               "solve_time_ms_max", "solve_wall_ms_median", "solve_wall_ms_p95", "solver_iterations_mean",
               "solver_suboptimal", "slip_guarded_steps")


def identify(seeds: tuple[int, ...] = IDENT_SEEDS,
             excitation: tuple[float, float, float, float] = IDENT_EXCITATION) -> dict[str, Any]:
    """Identify the grey-box storage model from open-loop excitation data (random cycles of ``seeds``, ANR
    excitation ``RandomSteps(*excitation)``); return its numbers."""
    from ident.greybox import StorageGreyBox
    from ident.excitation import RandomSteps
    from ident.metrics import fit_percent
    from ident.plant_data import excitation_dataset

    exc = RandomSteps(*excitation)
    recs = [excitation_dataset("random", seed=s, base_anr=1.0, excitation=exc) for s in seeds]
    t0 = time.perf_counter()
    model = StorageGreyBox().fit([(r.u, r.y) for r in recs], None)
    val = excitation_dataset("whtc", seed=99, base_anr=1.0, excitation=exc)
    yp = model.predict(val.u)
    return {"params": model.params_.tolist(), "sensor_gains": model.sensor_gains_.tolist(), "n_cells": model.n_cells,
            "dt": model.dt, "fit_seconds": time.perf_counter() - t0, "data": f"excitation_dataset('random', seed in "
            f"{list(seeds)}, base_anr=1.0, RandomSteps{tuple(excitation)})",
            "validation_fit_percent_whtc": {n: float(fit_percent(val.y[:, i], yp[:, i]))
                                            for i, n in enumerate(("tailpipe_nox", "nh3", "sensor"))},
            "validation_rmse_ppm_whtc": {n: float(np.sqrt(np.mean((val.y[:, i] - yp[:, i]) ** 2)))
                                         for i, n in enumerate(("tailpipe_nox", "nh3", "sensor"))},
            "validation_mean_ppm_whtc": {n: [float(val.y[:, i].mean()), float(yp[:, i].mean())]
                                         for i, n in enumerate(("tailpipe_nox", "nh3", "sensor"))},
            "validation_sd_ppm_whtc": {n: float(val.y[:, i].std())
                                       for i, n in enumerate(("tailpipe_nox", "nh3", "sensor"))}}


def identified_mpc(ident: dict[str, Any], quick: bool = False,
                   storage_value_g_per_mol: float | None = None,
                   safe_slip_ppm: float = 20.0, margin_k: float = 30.0, flow_ref_mol_s: float = 0.5,
                   cap_weight: float = 2.0e4, preview: bool | None = None, implicit: bool = True,
                   nh3_sensor: bool | None = None, slip_guard: bool = True) -> Any:
    """NMPC on the identified grey-box model, EKF on the tailpipe sensors. ``storage_value_g_per_mol`` > 0 adds
    the oracle's terminal value of stored NH3 on the identified storage state, with the oracle's safe-coverage
    penalty learned from the identified model: ``cap_weight`` per (excess)^2 of each cell's identified desorption
    slip above ``safe_slip_ppm`` at its terminal temperature plus ``margin_k`` (a heat-up margin) and the reference
    flow ``flow_ref_mol_s``. ``preview``: the cycle preview of the engine-out disturbances over the horizon, as the
    oracle has it (privileged information; default :data:`IDENTIFIED_PREVIEW`; False: the measured disturbances
    held). ``implicit``: the NLP's stages are the grey-box's smooth implicit-Euler equations
    (:meth:`StorageGreyBox.implicit_stage`) instead of its clipped explicit step; on the random calibration cycles this turned most failed SQP solves into solved ones
    (seed 8, storage value 0: 695 -> 487 failures, 1.63 -> 0.23 g/kWh; seed 5, value 100: 722 -> 626, 1.24 -> 0.30
    g/kWh; median solve 9 -> 2.6 ms). ``nh3_sensor``: the EKF also corrects with a tailpipe NH3 sensor (the
    environment's optional ``nh3_sensor=True`` observation, set in the returned policy's ``env_kwargs``), so a high
    NOx-sensor reading is no longer ambiguous between NOx breakthrough and NH3 slip. ``slip_guard`` (with the NH3
    sensor): a failed solve doses nothing while that sensor reads above :data:`SLIP_GUARD_PPM` (see
    :class:`~control.mpc.NonlinearMPC`)."""
    import casadi as ca

    from ident.greybox import StorageGreyBox
    from control.models import IdentifiedModelAdapter
    from control.mpc import NonlinearMPC

    if storage_value_g_per_mol is None:
        storage_value_g_per_mol = IDENTIFIED_STORAGE_VALUE
    if preview is None:
        preview = IDENTIFIED_PREVIEW
    if nh3_sensor is None:
        nh3_sensor = IDENTIFIED_NH3_SENSOR
    from scr_env.envs.core import OBS_BASE

    nh3_obs = len(OBS_BASE)   # the optional NH3 sensor follows the base observation
    m = StorageGreyBox.from_params(ident["params"], ident["sensor_gains"], ident["n_cells"], ident["dt"])
    n = m.n_cells
    sites_per_cell = m.storage_capacity_mol / n
    adapter = IdentifiedModelAdapter(
        m, input_mean=np.zeros(4), input_scale=np.ones(4), output_mean=np.zeros(3), output_scale=np.ones(3),
        output_indices=(0, 1), measured_output=(2, 1) if nh3_sensor else 2,
        measured_obs=(3, nh3_obs) if nh3_sensor else (3,), process_noise=np.r_[np.full(n, 1e-6), 0.5],
        # variances [ppm^2] of the sensor readings: NOx sensor SD 10 ppm; NH3 sensor the same [chosen]
        measurement_noise=[100.0, 100.0] if nh3_sensor else 100.0,
        state_bounds=(np.r_[np.zeros(n), 250.0], np.r_[np.ones(n), 900.0]),
        initial_state=lambda obs: np.r_[np.zeros(n), obs[1]], model_dt=ident["dt"],
        # the grey-box parameters are continuous-time: the same model discretised at the 2 s stage length
        stage_model=StorageGreyBox.from_params(ident["params"], ident["sensor_gains"], n, ident["dt"] * 4),
        implicit_stage=m.implicit_stage if implicit else None,
        terminal_cost=lambda x: sum(-storage_value_g_per_mol * sites_per_cell * x[j] + (cap_weight * ca.fmax(
            m.desorption_ppm(x[j], x[n] + margin_k, flow_ref_mol_s) / safe_slip_ppm - 1.0, 0.0) ** 2
            if storage_value_g_per_mol > 0 else 0.0) for j in range(n)))
    mpc = NonlinearMPC(adapter, horizon=10 if quick else 20, stage_steps=4, preview=preview,
                       slip_guard=(nh3_obs, SLIP_GUARD_PPM) if nh3_sensor and slip_guard else None, **IDENT_SOLVER)
    mpc.env_kwargs = {"nh3_sensor": True} if nh3_sensor else {}  # what the policy needs of the environment
    return mpc


def oracle_mpc(quick: bool = False, safe_slip_ppm: float | None = None) -> Any:
    """NMPC on the first-principles catalyst (privileged state, cycle preview), safe coverage at
    ``safe_slip_ppm`` (default :data:`ORACLE_SAFE_SLIP_PPM`)."""
    from control.models import FirstPrinciplesModel
    from control.mpc import NonlinearMPC

    model = FirstPrinciplesModel(safe_slip_ppm=ORACLE_SAFE_SLIP_PPM if safe_slip_ppm is None else safe_slip_ppm)
    return NonlinearMPC(model, horizon=10 if quick else 20, stage_steps=4, preview=True)


def make(name: str, ident: dict[str, Any] | None, quick: bool) -> Any:
    if name == "lookup_table":
        return LookupTableDosing()
    if name == "pi":
        return FeedforwardPI()
    if name == "mpc_identified":
        return identified_mpc(ident, quick)
    if name == "mpc_identified_nox_sensor":
        return identified_mpc(ident, quick, preview=True, nh3_sensor=False)
    if name == "mpc_identified_no_preview":
        return identified_mpc(ident, quick, storage_value_g_per_mol=NO_PREVIEW_STORAGE_VALUE, preview=False,
                              nh3_sensor=False)
    if name == "mpc_oracle":
        return oracle_mpc(quick)
    from control.rl import load_policy

    return load_policy(name)


def available_rl() -> tuple[list[str], str]:
    try:
        from control.rl import available_policies
    except Exception as exc:  # noqa: BLE001  (any import problem means: no RL policies to benchmark)
        return [], f"control.rl not importable ({type(exc).__name__}: {exc})"
    names = [n for n in RL_NAMES if n in available_policies()]
    missing = [n for n in RL_NAMES if n not in names]
    return names, (f"RL policies not shipped: {', '.join(missing)}" if missing else "")


def _job(args: tuple[str, str, dict | None, bool, int, bool]) -> EpisodeResult:
    """One episode ``(name, cycle, ident, quick, seed, record_trajectory)``, with a fresh policy."""
    name, cycle, ident, quick, seed, record = args
    t0 = time.perf_counter()
    policy = make(name, ident, quick)
    res = evaluate(policy, cycles=(cycle,), seeds=(seed,), env_kwargs=getattr(policy, "env_kwargs", None), name=name,
                   record_trajectory=record)[0]
    res.stats["wall_time_s"] = time.perf_counter() - t0
    return res


def plot(results: list[EpisodeResult], cycle: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rs = [r for r in results if r.cycle == cycle and r.trajectory is not None]
    if not rs:
        return
    fig, ax = plt.subplots(5, 1, figsize=(13, 13), sharex=True)
    tr0 = rs[0].trajectory
    t = tr0["time_s"]
    ax[0].plot(t, tr0["inlet_temperature_k"] - 273.15, "k", lw=0.8)
    ax[0].set_ylabel("SCR inlet T [C]")
    ax[1].plot(t, tr0["engine_out_nox_ppm"], color="0.7", lw=0.6, label="engine-out")
    for r in rs:
        tr = r.trajectory
        k = r.kpis
        lab = f"{r.name} ({k.get('tailpipe_nox_g_per_kwh', np.nan):.3f} g/kWh, {k.get('mean_nh3_slip_ppm', np.nan):.1f} ppm)"
        ax[1].plot(t, tr["tailpipe_nox_ppm"], lw=0.7, label=lab)
        ax[2].plot(t, tr["tailpipe_nh3_ppm"], lw=0.7, label=r.name)
        ax[3].plot(t, tr["adblue_g_s"], lw=0.7, label=r.name)
        ax[4].plot(t, tr["mean_coverage"], lw=0.9, label=r.name)
    ax[1].set_ylabel("tailpipe NOx [ppm]")
    ax[1].set_yscale("symlog", linthresh=10)
    ax[1].legend(fontsize=7, loc="upper right")
    ax[2].set_ylabel("NH3 slip [ppm]")
    ax[3].set_ylabel("AdBlue [g/s]")
    ax[4].set_ylabel("mean NH3 coverage [-]")
    ax[4].set_xlabel("time [s]")
    ax[4].legend(fontsize=7)
    fig.suptitle(f"closed loop on the hot {cycle.upper()}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=None, help="also write the JSON result here")
    ap.add_argument("--quick", action="store_true", help="WHTC only, shorter MPC horizons")
    ap.add_argument("--cycles", nargs="+", default=None, help="cycles (default: whtc whsc; --quick: whtc)")
    ap.add_argument("--workers", type=int, default=2, help="parallel episodes (processes)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0],
                    help="reset seeds (sensor noise) of each episode; KPIs are averaged over them and listed per seed "
                         "(default: 0)")
    args = ap.parse_args(argv)
    seeds = list(dict.fromkeys(args.seeds))
    cycles = args.cycles or (["whtc"] if args.quick else ["whtc", "whsc"])
    out = run_folder("control_benchmark")
    t_start = time.perf_counter()
    rl, rl_note = available_rl()
    if rl_note:
        print(f"note: {rl_note}; skipped")
    print("identifying the grey-box storage model from open-loop excitation data ...", flush=True)
    ident = identify()
    print(f"  fitted in {ident['fit_seconds']:.0f} s; WHTC validation (excited dosing) RMSE [ppm]: "
          + ", ".join(f"{k} {v:.1f}" for k, v in ident["validation_rmse_ppm_whtc"].items())
          + "; mean measured/predicted [ppm]: "
          + ", ".join(f"{k} {a:.1f}/{b:.1f}" for k, (a, b) in ident["validation_mean_ppm_whtc"].items()), flush=True)
    names = ["mpc_oracle", *IDENTIFIED_VARIANTS, "pi", "lookup_table", *rl]  # slowest first
    jobs = [(n, c, ident if n.startswith("mpc_identified") else None, args.quick, s, s == seeds[0])
            for n in names for c in cycles for s in seeds]
    results = []
    with ProcessPoolExecutor(max_workers=max(args.workers, 1)) as ex:
        for r in ex.map(_job, jobs):
            k = r.kpis
            print(f"  {r.name:15s} {r.cycle} seed {r.seed}: {k.get('tailpipe_nox_g_per_kwh', np.nan):.3f} g/kWh, "
                  f"{k.get('mean_nh3_slip_ppm', np.nan):.2f} ppm mean slip ({r.stats['wall_time_s']:.0f} s)", flush=True)
            results.append(r)
    order = {n: i for i, n in enumerate([*CORE, *IDENTIFIED_VARIANTS[1:], *rl])}
    results.sort(key=lambda r: (cycles.index(r.cycle) if r.cycle in cycles else 0, order.get(r.name, 99)))
    table = comparison_table(results, extra=("solve_time_ms_median", "solve_time_ms_p95", "solver_failures"))
    print(table)
    doc: dict[str, Any] = {"cycles": {}, "identified_model": ident, "skipped": rl_note or None,
                           "run_folder": str(out), "quick": bool(args.quick), "seeds": seeds}
    means = summarise(results)
    for c in cycles:
        ctrl = {}
        for name, agg in means.get(c, {}).items():
            row = {k: v for k, v in agg.items() if k in REPORT_KEYS or k == "wall_time_s"}
            if len(seeds) > 1:   # the spread over sensor-noise seeds (the row holds their means)
                rs = sorted((r for r in results if r.cycle == c and r.name == name), key=lambda r: r.seed)
                row["per_seed"] = {"seed": [r.seed for r in rs]} | {
                    k: [r.row().get(k) for r in rs] for k in ("tailpipe_nox_g_per_kwh", "mean_nh3_slip_ppm",
                                                              "solver_failures")}
            ctrl[name] = row
        doc["cycles"][c] = {"controllers": ctrl}
        if all(n in ctrl for n in ("lookup_table", "mpc_oracle", "mpc_identified")):
            lut, orc, idm = (ctrl[n]["tailpipe_nox_g_per_kwh"] for n in ("lookup_table", "mpc_oracle", "mpc_identified"))
            gap = lut - orc
            doc["cycles"][c]["gap_closed_by_mpc_identified"] = (lut - idm) / gap if gap > 0 else float("nan")
            print(f"{c}: mpc_identified closes {doc['cycles'][c]['gap_closed_by_mpc_identified']:.2f} of the "
                  "look-up-table-to-oracle tailpipe NOx gap")
        plot([r for r in results if r.seed == seeds[0]], c, out / f"closed_loop_{c}.png")
    doc["wall_time_s"] = time.perf_counter() - t_start
    (out / "table.txt").write_text(table + "\n", encoding="utf-8")
    save_results(out, "control_benchmark.json", doc, args.json)
    print(f"wrote {out} in {doc['wall_time_s']:.0f} s")
    return doc


if __name__ == "__main__":
    main()
