"""The identify-then-control loop, end to end (the thesis' future work, closed on the simulator).

    python -m experiments.identify_then_control [--json PATH] [--quick] [--workers N] [--ray-address ADDR]

1. Excitation experiments on the plant (open loop: feedforward dosing times seeded random steps, random cycles,
   never the held-out cycles): the grey-box model's records (as ``experiments.control_benchmark``) and a record
   with sustained over-dosing so that NH3 slip is excited too (black-box models).
2. Identification with the thesis' methods and beyond: a linear state-space model (N4SID), RPEM (2nd-order chain
   per output, the 9-term structure of Paper III), Hammerstein-Wiener (Wiener with output saturation, one per
   output; full run only: its fit takes minutes) and the grey-box NH3-storage model; validation FIT of each
   output on held-out excitation data (the WHTC, other seed).
3. NMPC on each identified model (:class:`control.models.IdentifiedModelAdapter`, state by EKF from the measured
   signals: the black-box models from the tailpipe NOx sensor only, the grey-box model as
   ``experiments.control_benchmark``'s ``mpc_identified``: NOx and NH3 sensors, cycle preview), the oracle NMPC on
   the first-principles model (privileged state, cycle preview).
4. Closed loop on held-out cycles (hot WHTC and WHSC; ``--quick``: the first 600 s of the WHTC) against the look-up table,
   the PI baseline, the oracle and the shipped RL policies. ``gap_closed[model][cycle]`` is the fraction of the
   look-up-table-to-oracle gap in tailpipe NOx [g/kWh] that the NMPC on that identified model closes.

The episodes run in parallel (local processes, or Ray with ``--ray-address``). Results: JSON, a markdown report,
identification and closed-loop figures in ``runs/identify_then_control/<stamp>/`` (``--out`` to choose).
"""
from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from experiments._runs import run_folder, write_json
from experiments.sweep import add_arguments, from_args, run_sweep

BLACK_BOX = ("linear", "rpem", "hammerstein_wiener")
EXCITATION_SEED = 3  # random cycle of the black-box excitation record (held-out cycles are WHTC/WHSC)
VALIDATION_SEED = 99  # sensor noise and excitation seed of the validation record (on the WHTC)
QUICK_SEGMENT_S = 600.0  # s of each held-out cycle in --quick
#: A held-out output whose SD is below this [ppm] is reported without a FIT (the FIT of a flat signal is noise).
FLAT_OUTPUT_SD_PPM = 0.1


# ---------------------------------------------------------------------------------------------------- data
def black_box_excitation(cycle: str, seed: int, duration_s: float = 3600.0) -> Any:
    """Open-loop record with sustained over-dosing phases (ANR 0.1 to 2, held 20-200 s): NH3 slip is excited."""
    from ident.excitation import RandomSteps
    from ident.plant_data import excitation_dataset

    kw = {"random_cycle_duration_s": duration_s} if cycle == "random" else {}
    return excitation_dataset(cycle, seed=seed, base_anr=1.0, excitation=RandomSteps(-0.9, 1.0, 20.0, 200.0), **kw)


def held_out(quick: bool) -> list[Any]:
    """The held-out cycles (ExhaustTraces): hot WHTC and WHSC, or the WHTC's first ``QUICK_SEGMENT_S`` seconds."""
    from scr_env.cycles import load_cycle

    traces = []
    for name in (("whtc",) if quick else ("whtc", "whsc")):
        tr = load_cycle(name, dt=0.5)
        if quick:
            n = int(QUICK_SEGMENT_S / tr.dt)
            arrays = {f.name: getattr(tr, f.name)[:n] for f in dataclasses.fields(tr)
                      if isinstance(getattr(tr, f.name), np.ndarray)}
            tr = dataclasses.replace(tr, name=f"{name}_0-{int(QUICK_SEGMENT_S)}s", **arrays)
        traces.append(tr)
    return traces


# ---------------------------------------------------------------------------------------------- identification
def identify_black_box(out: Path, include_hw: bool) -> dict[str, Any]:
    """Fit the black-box models on normalised data; save them (JSON + NPZ) to ``out``; return paths and fits."""
    from ident.hammerstein_wiener import HammersteinWiener, Saturation
    from ident.io import save_model
    from ident.linear import N4SID
    from ident.metrics import fit_percent
    from ident.preprocessing import Normalizer
    from ident.rpem import SCR_PAPER3_LINEAR_TERMS, RecursivePEM
    from ident.stack import OutputStack

    est = black_box_excitation("random", EXCITATION_SEED)
    val = black_box_excitation("whtc", VALIDATION_SEED)
    nu, ny = Normalizer().fit(est.u), Normalizer().fit(est.y)
    u, y, uv, yv = nu.transform(est.u), ny.transform(est.y), nu.transform(val.u), ny.transform(val.y)
    w_min = -ny.mean_ / ny.scale_  # zero ppm in normalised units: the output saturation of Papers III/IV
    candidates: dict[str, Any] = {
        "linear": lambda: N4SID(order=4),
        "rpem": lambda: RecursivePEM(n_states=2, terms=SCR_PAPER3_LINEAR_TERMS, sampling_period=est.dt, alpha=1.5,
                                     init="kalman", n_passes=3,
                                     output_limits=[(float(w), np.inf) for w in w_min]),
    }
    if include_hw:
        candidates["hammerstein_wiener"] = lambda: OutputStack(
            [HammersteinWiener(output_block=Saturation(lower=float(w_min[i])), max_nfev=30) for i in range(3)])
    info: dict[str, Any] = {"data": {"estimation": est.meta, "validation": val.meta},
                            "input_mean": nu.mean_.tolist(), "input_scale": nu.scale_.tolist(),
                            "output_mean": ny.mean_.tolist(), "output_scale": ny.scale_.tolist(), "models": {}}
    for name, make in candidates.items():
        t0 = time.perf_counter()
        try:
            model = make().fit(u, y)
        except Exception as exc:  # noqa: BLE001  (an identification failure is a result, reported, not a crash)
            info["models"][name] = {"error": f"{type(exc).__name__}: {exc}"}
            continue
        yp = model.predict(uv)
        fits = {n: float(fit_percent(yv[:, i], yp[:, i])) for i, n in enumerate(val.output_names)}
        entry: dict[str, Any] = {"fit_seconds": time.perf_counter() - t0, "validation_fit_percent": fits,
                                 "validation_sd_ppm": {n: float(val.y[:, i].std())
                                                       for i, n in enumerate(val.output_names)}}
        if isinstance(model, OutputStack):
            entry["paths"] = [str(save_model(m, out / f"model_{name}_{i}")) for i, m in enumerate(model.models_)]
        else:
            entry["paths"] = [str(save_model(model, out / f"model_{name}"))]
        info["models"][name] = entry
    return info


def _load_black_box(name: str, info: dict[str, Any]) -> Any:
    from ident.io import load_model
    from ident.stack import OutputStack

    paths = info["models"][name]["paths"]
    models = [load_model(p) for p in paths]
    if len(models) == 1:
        return models[0]
    stack = OutputStack([None] * len(models))
    stack.models_ = models
    return stack


# ------------------------------------------------------------------------------------------------ controllers
def make_controller(name: str, ident: dict[str, Any], quick: bool) -> Any:
    """A policy by name: baselines, oracle, NMPC on an identified model, or a shipped RL policy."""
    from experiments import control_benchmark as cb

    if name in ("lookup_table", "pi", "mpc_oracle"):
        return cb.make(name, None, quick)
    if name == "mpc_greybox":
        return cb.identified_mpc(ident["greybox"], quick)
    if name.startswith("mpc_"):
        from control.models import IdentifiedModelAdapter
        from control.mpc import NonlinearMPC

        bb = ident["black_box"]
        model = _load_black_box(name[4:], bb)
        nx = int(model.to_casadi().size1_in(0))
        adapter = IdentifiedModelAdapter(
            model, input_mean=bb["input_mean"], input_scale=bb["input_scale"], output_mean=bb["output_mean"],
            output_scale=bb["output_scale"], output_indices=(0, 1), measured_output=2, process_noise=1e-3,
            measurement_noise=1e-2, state_bounds=(np.full(nx, -50.0), np.full(nx, 50.0)), model_dt=0.5)
        return NonlinearMPC(adapter, horizon=10 if quick else 20, stage_steps=4, preview=False, **cb.IDENT_SOLVER)
    from control.rl import load_policy

    return load_policy(name)


def episode(name: str, trace_index: int, ident: dict[str, Any], quick: bool) -> dict[str, Any]:
    """One closed-loop episode (module level, so local processes and Ray workers can run it)."""
    from control.evaluation import evaluate

    trace = held_out(quick)[trace_index]
    t0 = time.perf_counter()
    try:
        policy = make_controller(name, ident, quick)
        res = evaluate(policy, cycles=(trace,), seeds=(0,), env_kwargs=getattr(policy, "env_kwargs", None), name=name,
                       record_trajectory=True)[0]
    except Exception as exc:  # noqa: BLE001  (a controller that cannot run is reported, the study goes on)
        return {"name": name, "cycle": trace.name, "error": f"{type(exc).__name__}: {exc}"}
    row = {k: v for k, v in res.row().items() if isinstance(v, (int, float, str))}
    traj = {k: np.asarray(v).tolist() for k, v in (res.trajectory or {}).items()
            if k in ("time_s", "tailpipe_nox_ppm", "tailpipe_nh3_ppm", "adblue_g_s", "inlet_temperature_k")}
    return {"name": name, "cycle": trace.name, "row": row, "trajectory": traj,
            "wall_time_s": time.perf_counter() - t0}


# ---------------------------------------------------------------------------------------------------- report
SLIP_LIMIT_PPM = 10.0  # mean NH3 slip limit of Euro VI [ppm]: a gap counts as closed only within it


def gap_closed(kpis: dict[str, dict[str, dict[str, float]]]) -> tuple[dict[str, dict[str, float]], list[dict]]:
    """``{model: {cycle: (LUT - MPC_model) / (LUT - oracle)}}`` in tailpipe NOx g/kWh, and the excluded entries.

    A model/cycle pair counts only if that NMPC (and the oracle) kept the mean NH3 slip within
    :data:`SLIP_LIMIT_PPM`: closing the NOx gap by slipping ammonia is not closing it "at the same slip limit". The
    excluded pairs are returned with their raw fraction and slip, so nothing is hidden.
    """
    out: dict[str, dict[str, float]] = {}
    excluded: list[dict] = []
    for cycle, ctrl in kpis.items():
        if "lookup_table" not in ctrl or "mpc_oracle" not in ctrl:
            continue
        lut = ctrl["lookup_table"]["tailpipe_nox_g_per_kwh"]
        orc = ctrl["mpc_oracle"]["tailpipe_nox_g_per_kwh"]
        oracle_ok = ctrl["mpc_oracle"].get("mean_nh3_slip_ppm", float("inf")) <= SLIP_LIMIT_PPM
        for name, row in ctrl.items():
            if not name.startswith("mpc_") or name == "mpc_oracle":
                continue
            gap = lut - orc
            val = (lut - row["tailpipe_nox_g_per_kwh"]) / gap if gap > 0 else float("nan")
            slip = row.get("mean_nh3_slip_ppm", float("inf"))
            if oracle_ok and slip <= SLIP_LIMIT_PPM and np.isfinite(val):
                out.setdefault(name[4:], {})[cycle] = float(val)
            else:
                reason = "oracle above the slip limit" if not oracle_ok else (
                    "no gap (oracle not better than the look-up table)" if not np.isfinite(val)
                    else f"mean NH3 slip {slip:.1f} ppm > {SLIP_LIMIT_PPM:.0f} ppm")
                excluded.append({"model": name[4:], "cycle": cycle, "raw_fraction": float(val),
                                 "mean_nh3_slip_ppm": float(slip), "reason": reason})
    return out, excluded


def _plots(results: list[dict[str, Any]], out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    for cycle in sorted({r["cycle"] for r in results if "row" in r}):
        rs = [r for r in results if r.get("cycle") == cycle and "row" in r]
        fig, ax = plt.subplots(4, 1, figsize=(12, 11), sharex=True)
        t = np.asarray(rs[0]["trajectory"]["time_s"])
        ax[0].plot(t, np.asarray(rs[0]["trajectory"]["inlet_temperature_k"]) - 273.15, "k", lw=0.8)
        ax[0].set_ylabel("SCR inlet T [C]")
        for r in rs:
            tr, k = r["trajectory"], r["row"]
            lab = f"{r['name']} ({k.get('tailpipe_nox_g_per_kwh', np.nan):.3f} g/kWh, " \
                  f"{k.get('mean_nh3_slip_ppm', np.nan):.1f} ppm)"
            ax[1].plot(t, tr["tailpipe_nox_ppm"], lw=0.7, label=lab)
            ax[2].plot(t, tr["tailpipe_nh3_ppm"], lw=0.7)
            ax[3].plot(t, tr["adblue_g_s"], lw=0.7)
        ax[1].set_ylabel("tailpipe NOx [ppm]")
        ax[1].set_yscale("symlog", linthresh=10)
        ax[1].legend(fontsize=7, loc="upper right")
        ax[2].set_ylabel("NH3 slip [ppm]")
        ax[2].set_yscale("symlog", linthresh=10)
        ax[3].set_ylabel("AdBlue [g/s]")
        ax[3].set_xlabel("time [s]")
        fig.suptitle(f"identify-then-control: closed loop on the held-out {cycle}")
        fig.tight_layout()
        p = out / f"closed_loop_{cycle}.png"
        fig.savefig(p, dpi=100)
        plt.close(fig)
        paths.append(p)
    return paths


def _fit_plot(ident: dict[str, Any], out: Path) -> Path:
    """Validation FIT per identified model and output (bar chart)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fits = dict(ident["black_box"]["models"])
    fits["greybox"] = {"validation_fit_percent": ident["greybox"].get("validation_fit_percent_whtc", {})}
    names = [n for n, v in fits.items() if "validation_fit_percent" in v]
    outputs = ["tailpipe_nox", "nh3", "sensor"]
    fig, ax = plt.subplots(figsize=(9, 4.5))
    width = 0.8 / max(len(names), 1)
    for i, n in enumerate(names):
        vals = list(fits[n]["validation_fit_percent"].values())[:3]
        ax.bar(np.arange(len(vals)) + i * width, np.clip(vals, -50, 100), width, label=n)
    ax.set_xticks(np.arange(3) + 0.4 - width / 2, outputs)
    ax.axhline(0, color="k", lw=0.8)
    ax.set_ylabel("validation FIT [%] (clipped at -50)")
    ax.set_title("identified models: simulation FIT on held-out excitation data (WHTC)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    p = out / "identification_fit.png"
    fig.savefig(p, dpi=100)
    plt.close(fig)
    return p


def _fits_line(fits: dict[str, float], sds: dict[str, float]) -> str:
    """``name FIT %`` per output; "n/a (flat)" where the held-out output barely moves."""
    return ", ".join(f"{k} n/a (flat: SD {sd:.2g} ppm)" if sd < FLAT_OUTPUT_SD_PPM else f"{k} {v:.1f} %"
                     for (k, v), sd in zip(fits.items(), sds.values()))


def _report(doc: dict[str, Any], figures: list[Path], out: Path) -> Path:
    lines = ["# Identify-then-control", "",
             f"Mode: {f'quick (first {QUICK_SEGMENT_S:.0f} s of the WHTC, shorter horizons)' if doc['quick'] else 'full cycles'}; "
             f"wall time {doc['wall_time_s']:.0f} s.", "", "## Identification (validation FIT on held-out WHTC excitation data)", "",
             "| model | tailpipe NOx | NH3 slip | NOx sensor | fit time [s] |", "|---|---|---|---|---|"]
    models = dict(doc["identification"]["black_box"]["models"])
    gb = doc["identification"]["greybox"]
    models["greybox"] = {"validation_fit_percent": gb.get("validation_fit_percent_whtc", {}),
                         "validation_sd_ppm": gb.get("validation_sd_ppm_whtc", {}),
                         "fit_seconds": gb.get("fit_seconds", float("nan"))}
    flat = False
    for n, m in models.items():
        if "error" in m:
            lines.append(f"| {n} | failed: {m['error']} | | | |")
            continue
        cells = []
        for i, f in enumerate(list(m["validation_fit_percent"].values())[:3]):
            sd = list(m.get("validation_sd_ppm", {}).values())
            if i < len(sd) and sd[i] < FLAT_OUTPUT_SD_PPM:
                cells.append(f"n/a (flat: SD {sd[i]:.2g} ppm)")
                flat = True
            else:
                cells.append(f"{f:.1f} %")
        cells += ["-"] * (3 - len(cells))
        lines.append(f"| {n} | {' | '.join(cells)} | {m.get('fit_seconds', float('nan')):.0f} |")
    if flat:
        lines += ["", f"n/a: the held-out output barely moves (SD below {FLAT_OUTPUT_SD_PPM} ppm), so its FIT "
                      "(error relative to the output's own variation) says nothing about the model."]
    lines += ["", "## Closed loop on held-out cycles", ""]
    for cycle, ctrl in doc["kpis"].items():
        lines += [f"### {cycle}", "", "| controller | NOx conversion | tailpipe NOx [g/kWh] | mean / peak NH3 slip [ppm] | "
                  "AdBlue [g] | solve time median / p95 [ms] | solver failures |", "|---|---|---|---|---|---|---|"]
        for n, k in ctrl.items():
            lines.append(f"| {n} | {100 * k.get('nox_conversion', float('nan')):.1f} % | "
                         f"{k.get('tailpipe_nox_g_per_kwh', float('nan')):.3f} | {k.get('mean_nh3_slip_ppm', float('nan')):.1f} / "
                         f"{k.get('peak_nh3_slip_ppm', float('nan')):.0f} | {k.get('adblue_g', float('nan')):.0f} | "
                         + (f"{k['solve_time_ms_median']:.1f} / {k.get('solve_time_ms_p95', float('nan')):.1f} | "
                            f"{k.get('solver_failures', 0):.0f} |" if np.isfinite(k.get("solve_time_ms_median", np.nan)) else
                            "- (no solver) | - |"))
        lines.append("")
    lines += ["## Gap closed", "", "Fraction of the look-up-table-to-oracle gap in tailpipe NOx closed by the NMPC on each "
              "identified model (1 = as good as the oracle, 0 = no better than the look-up table), counted only "
              f"within the {SLIP_LIMIT_PPM:.0f} ppm mean-slip limit:", "",
              "| model | " + " | ".join(doc["kpis"]) + " |", "|---|" + "---|" * len(doc["kpis"])]
    for model, per in doc["gap_closed"].items():
        lines.append(f"| {model} | " + " | ".join(f"{per.get(c, float('nan')):.2f}" for c in doc["kpis"]) + " |")
    for e in doc.get("gap_closed_excluded", []):
        lines.append(f"- not counted: {e['model']} on {e['cycle']} (raw fraction {e['raw_fraction']:.2f}): {e['reason']}")
    if doc.get("errors"):
        lines += ["", "Controllers that could not run: " + "; ".join(doc["errors"])]
    if doc.get("skipped"):
        lines += ["", f"Note: {doc['skipped']}"]
    lines += [""] + [f"![{p.stem}]({p.name})" for p in figures]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


# ------------------------------------------------------------------------------------------------------ main
def run(quick: bool = False, out: Path | None = None, sweep_kwargs: dict[str, Any] | None = None,
        include_rl: bool = True) -> dict[str, Any]:
    """The whole loop; returns the JSON document (also written with the report into ``out``)."""
    from experiments import control_benchmark as cb

    out = out or run_folder("identify_then_control")
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    print("1-2. excitation experiments and identification ...", flush=True)
    ident = {"greybox": cb.identify(), "black_box": identify_black_box(out, include_hw=not quick)}
    for n, m in ident["black_box"]["models"].items():
        print(f"  {n}: " + (m["error"] if "error" in m else _fits_line(m["validation_fit_percent"],
                                                                       m["validation_sd_ppm"])
                            + f" ({m['fit_seconds']:.0f} s)"))
    gb = ident["greybox"]
    print("  greybox: " + _fits_line(gb["validation_fit_percent_whtc"], gb["validation_sd_ppm_whtc"]))
    rl, rl_note = cb.available_rl() if include_rl else ([], "RL policies not requested")
    models = ["greybox"] + [n for n in BLACK_BOX if "paths" in ident["black_box"]["models"].get(n, {})]
    names = ["mpc_oracle", *[f"mpc_{m}" for m in models], "pi", "lookup_table", *rl]
    traces = held_out(quick)
    tasks = [{"name": n, "trace_index": i, "ident": ident, "quick": quick} for n in names for i in range(len(traces))]
    print(f"3-4. {len(tasks)} closed-loop episodes on {', '.join(t.name for t in traces)} ...", flush=True)
    results = run_sweep(episode, tasks, description="closed loop", **(sweep_kwargs or {}))
    kpis: dict[str, dict[str, dict[str, float]]] = {t.name: {} for t in traces}
    errors = []
    for r in results:
        if "error" in r:
            errors.append(f"{r['name']} on {r['cycle']}: {r['error']}")
            continue
        kpis[r["cycle"]][r["name"]] = {k: v for k, v in r["row"].items() if isinstance(v, (int, float))}
    gaps, excluded = gap_closed(kpis)
    doc: dict[str, Any] = {"quick": quick, "identification": ident, "kpis": kpis, "gap_closed": gaps,
                           "gap_closed_excluded": excluded, "errors": errors, "skipped": rl_note or None,
                           "run_folder": str(out)}
    doc["wall_time_s"] = time.perf_counter() - start
    figures = [_fit_plot(ident, out), *_plots(results, out)]
    report = _report(doc, figures, out)
    write_json(out / "identify_then_control.json", doc)
    print(report.read_text())
    print(f"report: {report}")
    return doc


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path, default=None, help="also write the JSON result here")
    ap.add_argument("--quick", action="store_true", help=f"first {QUICK_SEGMENT_S:.0f} s of the WHTC only, "
                    "shorter horizons, no Hammerstein-Wiener fit (the main job of `make demo`)")
    ap.add_argument("--out", type=Path, default=None, help="report folder (default runs/identify_then_control/<stamp>)")
    ap.add_argument("--no-rl", action="store_true", help="leave out the shipped RL policies")
    add_arguments(ap)
    args = ap.parse_args(argv)
    if args.workers is None:
        args.workers = 2
    doc = run(quick=args.quick, out=args.out, sweep_kwargs=from_args(args), include_rl=not args.no_rl)
    if args.json is not None:
        write_json(args.json, doc)
    return doc


if __name__ == "__main__":
    main()
