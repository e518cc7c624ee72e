"""The identify-then-control loop, end to end (the thesis' future work, closed on the simulator).

    python -m experiments.identify_then_control [--json PATH] [--quick] [--workers N] [--ray-address ADDR]

1. Excitation experiments on the plant (open loop: feedforward dosing times seeded random steps, random cycles,
   never the held-out cycles): the grey-box model's records (:func:`control.factory.greybox_record`) and a record
   with sustained over-dosing so that NH3 slip is excited too (black-box models).
2. Identification with the thesis' methods and beyond: a linear state-space model (N4SID), RPEM (2nd-order chain
   per output, the 9-term structure of Paper III), Hammerstein-Wiener (Wiener with output saturation, one per
   output; full run only: its fit takes minutes) and the grey-box NH3-storage model; validation FIT of each
   output on held-out excitation data (the WHTC, other seed).
3. NMPC on each identified model (:func:`control.loop.loop_controller`; state by EKF from the measured signals:
   the black-box models from the tailpipe NOx sensor only, the grey-box model as ``control_benchmark``'s
   ``mpc_identified``: NOx and NH3 sensors, cycle preview), the oracle NMPC on the first-principles model
   (privileged state, cycle preview).
4. Closed loop on held-out cycles (hot WHTC and WHSC; ``--quick``: the first 600 s of the WHTC) against the
   look-up table, the PI baseline, the oracle and the shipped RL policies. ``gap_closed[model][cycle]`` is the
   fraction of the look-up-table-to-oracle gap in tailpipe NOx [g/kWh] that the NMPC on that identified model closes.

The episodes run in parallel (local processes, or Ray with ``--ray-address``). Results: JSON, a markdown report,
identification and closed-loop figures in ``runs/identify_then_control/<stamp>/`` (``--out`` to choose).
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from control.factory import available_rl, greybox_record
from control.loop import BLACK_BOX, QUICK_SEGMENT_S, SLIP_LIMIT_PPM, gap_closed, held_out, identify_black_box
from control.plots import closed_loop_figure, fit_bar_chart
from experiments._runs import run_folder, write_json, write_text
from experiments.sweep import add_arguments, from_args, run_sweep

#: A held-out output whose SD is below this [ppm] is reported without a FIT (the FIT of a flat signal is noise).
FLAT_OUTPUT_SD_PPM = 0.1
_NAN = float("nan")


def episode(name: str, trace_index: int, models: dict[str, Any], quick: bool) -> dict[str, Any]:
    """One closed-loop episode (module level, so local processes and Ray workers can run it); ``models``: the
    grey-box model file and the black-box info."""
    from control.evaluation import evaluate
    from control.loop import loop_controller
    from ident.greybox import StorageGreyBox

    trace = held_out(quick)[trace_index]
    t0 = time.perf_counter()
    try:
        greybox = StorageGreyBox.load(models["greybox"]) if name == "mpc_greybox" else None
        policy = loop_controller(name, greybox, models["black_box"], quick)
        res = evaluate(policy, cycles=(trace,), seeds=(0,), env_kwargs=getattr(policy, "env_kwargs", None), name=name,
                       record_trajectory=True)[0]
    except Exception as exc:  # noqa: BLE001  (a controller that cannot run is reported, the study goes on)
        return {"name": name, "cycle": trace.name, "error": f"{type(exc).__name__}: {exc}"}
    row = {k: v for k, v in res.row().items() if isinstance(v, (int, float, str))}
    traj = {k: np.asarray(v).tolist() for k, v in (res.trajectory or {}).items()
            if k in ("time_s", "tailpipe_nox_ppm", "tailpipe_nh3_ppm", "adblue_g_s", "inlet_temperature_k")}
    return {"name": name, "cycle": trace.name, "row": row, "trajectory": traj,
            "wall_time_s": time.perf_counter() - t0}


def _fit_cells(m: dict[str, Any]) -> tuple[list[str], bool]:
    """The FIT cells of one model's report row; "n/a (flat)" where the held-out output barely moves."""
    cells, flat = [], False
    sd = list(m.get("validation_sd_ppm", {}).values())
    for i, f in enumerate(list(m["validation_fit_percent"].values())[:3]):
        if i < len(sd) and sd[i] < FLAT_OUTPUT_SD_PPM:
            cells.append(f"n/a (flat: SD {sd[i]:.2g} ppm)")
            flat = True
        else:
            cells.append(f"{f:.1f} %")
    return cells + ["-"] * (3 - len(cells)), flat


def _report(doc: dict[str, Any], figures: list[Path], out: Path) -> Path:
    mode = f"quick (first {QUICK_SEGMENT_S:.0f} s of the WHTC, shorter horizons)" if doc["quick"] else "full cycles"
    lines = ["# Identify-then-control", "", f"Mode: {mode}; wall time {doc['wall_time_s']:.0f} s.", "",
             "## Identification (validation FIT on held-out WHTC excitation data)", "",
             "| model | tailpipe NOx | NH3 slip | NOx sensor | fit time [s] |", "|---|---|---|---|---|"]
    models = dict(doc["identification"]["black_box"]["models"])
    gb = doc["identification"]["greybox"]
    models["greybox"] = {"validation_fit_percent": gb.get("validation_fit_percent_whtc", {}),
                         "validation_sd_ppm": gb.get("validation_sd_ppm_whtc", {}),
                         "fit_seconds": gb.get("fit_seconds", _NAN)}
    flat = False
    for n, m in models.items():
        if "error" in m:
            lines.append(f"| {n} | failed: {m['error']} | | | |")
            continue
        cells, f = _fit_cells(m)
        flat |= f
        lines.append(f"| {n} | {' | '.join(cells)} | {m.get('fit_seconds', _NAN):.0f} |")
    if flat:
        lines += ["", (f"n/a: the held-out output barely moves (SD below {FLAT_OUTPUT_SD_PPM} ppm), so its FIT "
                       "(error relative to the output's own variation) says nothing about the model.")]
    lines += ["", "## Closed loop on held-out cycles", ""]
    for cycle, ctrl in doc["kpis"].items():
        lines += [f"### {cycle}", "", ("| controller | NOx conversion | tailpipe NOx [g/kWh] | mean / peak NH3 slip "
                                      "[ppm] | AdBlue [g] | solve time median / p95 [ms] | solver failures |"),
                  "|---|---|---|---|---|---|---|"]
        for n, k in ctrl.items():
            solver = (f"{k['solve_time_ms_median']:.1f} / {k.get('solve_time_ms_p95', _NAN):.1f} | "
                      f"{k.get('solver_failures', 0):.0f} |" if np.isfinite(k.get("solve_time_ms_median", np.nan))
                      else "- (no solver) | - |")
            lines.append(f"| {n} | {100 * k.get('nox_conversion', _NAN):.1f} % | "
                         f"{k.get('tailpipe_nox_g_per_kwh', _NAN):.3f} | {k.get('mean_nh3_slip_ppm', _NAN):.1f} / "
                         f"{k.get('peak_nh3_slip_ppm', _NAN):.0f} | {k.get('adblue_g', _NAN):.0f} | {solver}")
        lines.append("")
    lines += ["## Gap closed", "", ("Fraction of the look-up-table-to-oracle gap in tailpipe NOx closed by the NMPC on "
                                    "each identified model (1 = as good as the oracle, 0 = no better than the "
                                    f"look-up table), counted only within the {SLIP_LIMIT_PPM:.0f} ppm mean-slip "
                                    "limit:"), "",
              "| model | " + " | ".join(doc["kpis"]) + " |", "|---|" + "---|" * len(doc["kpis"])]
    for model, per in doc["gap_closed"].items():
        lines.append(f"| {model} | " + " | ".join(f"{per.get(c, _NAN):.2f}" for c in doc["kpis"]) + " |")
    for e in doc.get("gap_closed_excluded", []):
        lines.append(f"- not counted: {e['model']} on {e['cycle']} (raw fraction {e['raw_fraction']:.2f}): "
                     f"{e['reason']}")
    if doc.get("errors"):
        lines += ["", "Controllers that could not run: " + "; ".join(doc["errors"])]
    if doc.get("skipped"):
        lines += ["", f"Note: {doc['skipped']}"]
    lines += [""] + [f"![{p.stem}]({p.name})" for p in figures]
    return write_text(out / "report.md", "\n".join(lines) + "\n")


def run(quick: bool = False, out: Path | None = None, sweep_kwargs: dict[str, Any] | None = None,
        include_rl: bool = True, json_path: Path | None = None) -> dict[str, Any]:
    """The whole loop; returns the JSON document (also written with the report into ``out``)."""
    out = run_folder("identify_then_control", json_path=json_path, folder=out)
    start = time.perf_counter()
    print("1-2. excitation experiments and identification ...", flush=True)
    greybox, gb = greybox_record()
    ident = {"greybox": gb, "black_box": identify_black_box(out, include_hw=not quick)}
    models = {"greybox": str(greybox.save(out / "model_greybox")), "black_box": ident["black_box"]}
    for n, m in [*ident["black_box"]["models"].items(), ("greybox", {
            "validation_fit_percent": gb["validation_fit_percent_whtc"],
            "validation_sd_ppm": gb["validation_sd_ppm_whtc"]})]:
        print(f"  {n}: " + (m["error"] if "error" in m else ", ".join(
            f"{k} {c}" for k, c in zip(m["validation_fit_percent"], _fit_cells(m)[0], strict=False))))
    rl, rl_note = available_rl() if include_rl else ([], "RL policies not requested")
    names = ["mpc_oracle", "mpc_greybox", *[f"mpc_{m}" for m in BLACK_BOX if "paths" in ident["black_box"]["models"]
                                            .get(m, {})], "pi", "lookup_table", *rl]
    traces = held_out(quick)
    tasks = [{"name": n, "trace_index": i, "models": models, "quick": quick} for n in names for i in range(len(traces))]
    print(f"3-4. {len(tasks)} closed-loop episodes on {', '.join(t.name for t in traces)} ...", flush=True)
    results = run_sweep(episode, tasks, description="closed loop", **(sweep_kwargs or {}))
    kpis: dict[str, dict[str, dict[str, float]]] = {t.name: {} for t in traces}
    errors = [f"{r['name']} on {r['cycle']}: {r['error']}" for r in results if "error" in r]
    for r in (r for r in results if "error" not in r):
        kpis[r["cycle"]][r["name"]] = {k: v for k, v in r["row"].items() if isinstance(v, (int, float))}
    gaps, excluded = gap_closed(kpis)
    doc: dict[str, Any] = {"quick": quick, "identification": ident, "kpis": kpis, "gap_closed": gaps,
                           "gap_closed_excluded": excluded, "errors": errors, "skipped": rl_note or None,
                           "run_folder": str(out), "wall_time_s": time.perf_counter() - start}
    fits = {n: v["validation_fit_percent"] for n, v in ident["black_box"]["models"].items()
            if "validation_fit_percent" in v}
    fits["greybox"] = gb.get("validation_fit_percent_whtc", {})
    figures = [fit_bar_chart(fits, ("tailpipe_nox", "nh3", "sensor"), "identified models: simulation FIT on held-out "
                             "excitation data (WHTC)", out / "identification_fit.png")]
    for cycle in sorted({r["cycle"] for r in results if "row" in r}):
        runs = [(r["name"], r["row"], r["trajectory"]) for r in results if r.get("cycle") == cycle and "row" in r]
        figures.append(closed_loop_figure(runs, f"identify-then-control: closed loop on the held-out {cycle}",
                                          out / f"closed_loop_{cycle}.png", coverage=False, slip_log=True, dpi=100))
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
    doc = run(quick=args.quick, out=args.out, sweep_kwargs=from_args(args), include_rl=not args.no_rl,
              json_path=args.json)
    if args.json is not None:
        write_json(args.json, doc)
    return doc


if __name__ == "__main__":
    main()
