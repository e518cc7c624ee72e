"""Calibrate the ``cu_zeolite`` kinetics and the ageing table (:mod:`scr_env.calibration`; deterministic, ~2 min).

Usage: ``python -m experiments.calibrate_catalyst [--json PATH] [--quick]``.

Start: the shipped single-site lumped set (``scr_env/data/catalyst/lumped_cu_ssz13_params.txt``) for storage,
standard SCR and NH3 oxidation, and the chosen starting guesses of :data:`START` for the reactions it lacks. Then
(1) the unaged kinetics in two rounds, the ammonium-nitrate route transferred from the cats model onto the standard
SCR between rounds, and (2) the unaged kinetics and the per-age factors jointly. Prints every fitted value, the
ageing table and the residuals beyond 1.5 of their scale; the numbers in :mod:`scr_env.params` (``CatalystParams``
defaults and ``AGEING_TABLE``) are this script's output. ``--quick`` stops after step (1) (a smoke run).
Writes ``calibration.json`` to ``runs/calibrate_catalyst/<stamp>/`` (and to ``--json``).
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from experiments._runs import run_folder, save_results
from scr_env import calibration as cal
from scr_env.params import CatalystParams

#: the lumped set of lumped_cu_ssz13_params.txt (its storage capacity replaced by the saturation of the cats
#: sites, fixed), and starting guesses for the rest [chosen: orders of magnitude of the previous calibration; the
#: fit moves them]
START = {"storage_capacity_mol_m3": cal.CATS_SATURATION_MOL_M3, "a_des_1_s": 2.984e8, "e_des_j_mol": 92.66e3,
         "temkin_gamma": 0.95,
         "a_std_m3_mol_s": 6.717e6, "e_std_j_mol": 66.95e3, "a_ox_1_s": 7.103e5, "e_ox_j_mol": 107.85e3,
         "a_n2o_m3_mol_s": 1.0e5, "a_ox_no_1_s": 2.834e13, "e_ox_no_j_mol": 225.98e3, "a_ox_n2o_1_s": 1.0e11,
         "a_no_ox_m3_mol_s": 64.0, "e_no_ox_j_mol": 45.0e3, "o2_order_ox": 0.5}
_REPORTED = ("storage_capacity_mol_m3",) + tuple(f for f, _ in cal.UNAGED_FIELDS) + (
    "a_an_m3_mol_s", "e_an_j_mol", "a_an_no_m3_mol_s", "e_an_no_j_mol", "a_an_dec_1_s", "e_an_dec_j_mol",
    "a_an_n2o_1_s")


def calibrate(quick: bool = False) -> dict:
    """Run the calibration; returns the fitted values, the ageing table and the residual summaries."""
    start = dataclasses.replace(CatalystParams(), **START)
    cat, unaged = cal.fit_unaged(start, rounds=2)
    out = {"start": START, "unaged_fit": {"rms_scaled_residual": unaged["rms_scaled_residual"]}}
    table = None
    if not quick:
        cat, table, joint = cal.fit_all(cat)
        out["joint_fit"] = {"rms_scaled_residual": joint["rms_scaled_residual"], "nfev": joint["nfev"],
                            "status": joint["status"], "residuals": joint["residuals"]}
    else:
        out["unaged_fit"]["residuals"] = unaged["residuals"]
    out["catalyst_params"] = {f: getattr(cat, f) for f in _REPORTED}
    out["nitrate_transfer"] = cal.nitrate_route(cat.a_std_m3_mol_s, cat.e_std_j_mol)
    out["ageing_table"] = {str(a): row for a, row in (table or {}).items()}
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", type=Path, help="also write the results to this JSON file")
    ap.add_argument("--quick", action="store_true", help="unaged fit only (smoke run)")
    args = ap.parse_args(argv)
    folder = run_folder("calibrate_catalyst", json_path=args.json)  # created and checked before the fit
    values = calibrate(args.quick)
    for k, v in values["catalyst_params"].items():
        print(f"{k:26s} {v:.6g}")
    for age, row in values["ageing_table"].items():
        print(f"age {age:>5s} h: " + ", ".join(f"{k} {v:.4g}" for k, v in row.items()))
    fit = values.get("joint_fit", values["unaged_fit"])
    print(f"rms scaled residual {fit['rms_scaled_residual']:.3f}; residuals beyond 1.5 of their scale:")
    for k, v in fit["residuals"].items():
        if abs(v) > 1.5:
            print(f"  {k:40s} {v:+.2f}")
    save_results(folder, "calibration.json", values, args.json)
    print(f"run folder: {folder}")
    return values


if __name__ == "__main__":
    main()
