"""The identify-then-control report (markdown) from the loop's JSON document
(:mod:`experiments.identify_then_control`)."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from control.loop import QUICK_SEGMENT_S, SLIP_LIMIT_PPM

_NAN = float("nan")


def _kpi_table(ctrl: dict[str, dict[str, float]]) -> list[str]:
    lines = [("| controller | NOx conversion | tailpipe NOx [g/kWh] | mean / peak NH3 slip [ppm] | AdBlue [g] | "
              "solve time median / p95 [ms] | solver failures |"), "|---|---|---|---|---|---|---|"]
    for n, k in ctrl.items():
        solver = (f"{k['solve_time_ms_median']:.1f} / {k.get('solve_time_ms_p95', _NAN):.1f} | "
                  f"{k.get('solver_failures', 0):.0f} |" if np.isfinite(k.get("solve_time_ms_median", np.nan))
                  else "- (no solver) | - |")
        lines.append(f"| {n} | {100 * k.get('nox_conversion', _NAN):.1f} % | "
                     f"{k.get('tailpipe_nox_g_per_kwh', _NAN):.3f} | {k.get('mean_nh3_slip_ppm', _NAN):.2f} / "
                     f"{k.get('peak_nh3_slip_ppm', _NAN):.0f} | {k.get('adblue_g', _NAN):.0f} | {solver}")
    return lines


def loop_report(doc: dict[str, Any], figures: Sequence[Path]) -> str:
    """The markdown report of one run of the loop."""
    mode = f"quick (first {QUICK_SEGMENT_S:.0f} s of the WHTC, shorter horizons)" if doc["quick"] else "full cycles"
    seeds = doc.get("seeds", [0])
    lines = ["# Identify-then-control", "",
             (f"Mode: {mode}; sensor-noise seeds {seeds}; oracle: {doc.get('oracle', 'control.factory.oracle_mpc')}; "
              f"wall time {doc['wall_time_s']:.0f} s."), "",
             "## Identification for control (k-step FIT on the validation record, log outputs)", "",
             "| model | NOx, 40 steps | NH3, 40 steps | NOx, 160 steps | NH3, 160 steps | fit time [s] |",
             "|---|---|---|---|---|---|"]
    for n, m in doc["identification"]["black_box"]["models"].items():
        if "error" in m:
            lines.append(f"| {n} | failed: {m['error']} | | | | |")
            continue
        kf = m["validation_kstep_fit_percent"]
        cells = [f"{np.mean([r[j] for r in kf[f'{k}_steps']]):.1f} %" for k in (40, 160) for j in (0, 1)]
        lines.append(f"| {n} | {' | '.join(cells)} | {m['fit_seconds']:.0f} |")
    gb = doc["identification"]["greybox"]
    lines += ["", "Grey-box validation FIT (WHTC excitation, simulation): " + ", ".join(
        f"{k} {v:.1f} %" for k, v in gb.get("validation_fit_percent_whtc", {}).items()), "",
        "## Closed loop on held-out cycles (seed means)", ""]
    for cycle, ctrl in doc["kpis"].items():
        lines += [f"### {cycle}", "", *_kpi_table(ctrl), ""]
    cycles = list(doc["kpis"])
    lines += ["## Gap closed", "", ("Fraction of the look-up-table-to-oracle gap in tailpipe NOx [g/kWh] closed by the "
                                    "NMPC on each identified model (1 = as the oracle, 0 = as the look-up table), the "
                                    f"mean over the seeds, counted only if every seed kept the mean NH3 slip within "
                                    f"{SLIP_LIMIT_PPM:.0f} ppm:"), "",
              "| model | " + " | ".join(cycles) + " |", "|---|" + "---|" * len(cycles)]
    for model, per in doc["gap_closed"].items():
        lines.append(f"| {model} | " + " | ".join(f"{per.get(c, _NAN):.2f}" for c in cycles) + " |")
    if doc.get("ablation"):
        lines += ["", ("Ablation rows: `<model>-no_<ingredient>` is the NMPC with that ingredient removed; "
                       "`hammerstein_wiener-no_static_blocks` is the linear model class (identity blocks on every "
                       "input and output, same features and outputs); `rpem-with_online_adaptation` adds the online "
                       "adaptation that is off by default."), ""]
    for e in doc.get("gap_closed_excluded", []):
        lines.append(f"- not counted: {e['model']} on {e['cycle']} (raw fraction {e['raw_fraction']:.2f}): "
                     f"{e['reason']}")
    to_limit = doc.get("gap_to_limit") or {}
    if to_limit:
        lines += ["", ("Fraction of the look-up-table-to-limit gap closed (the stored clairvoyant optimum at 10 ppm "
                       "mean slip, `control.limit`; 1 = the physical limit of the task), seed means; * = a seed "
                       f"above {SLIP_LIMIT_PPM:.0f} ppm mean slip:"), "",
                  "| controller | " + " | ".join(f"{c} (limit {v['limit_tailpipe_nox_g_per_kwh']:.3f} g/kWh)"
                                                 for c, v in to_limit.items()) + " |",
                  "|---|" + "---|" * len(to_limit)]
        names = list(dict.fromkeys(n for v in to_limit.values() for n in v["controllers"]))
        for n in names:
            cells = []
            for v in to_limit.values():
                r = v["controllers"].get(n)
                cells.append("-" if r is None else f"{r['gap_to_limit']:.2f}" + ("" if r["within_slip_limit"] else "*"))
            lines.append(f"| {n} | " + " | ".join(cells) + " |")
    if doc.get("errors"):
        lines += ["", "Controllers that could not run: " + "; ".join(doc["errors"])]
    if doc.get("skipped"):
        lines += ["", f"Note: {doc['skipped']}"]
    lines += [""] + [f"![{p.stem}]({p.name})" for p in figures]
    return "\n".join(lines) + "\n"
