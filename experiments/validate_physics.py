"""The simulator in the CLEERS lab configuration against the real Cu-SSZ-13 measurements (PHYSICS.md section 6).

Usage: ``python -m experiments.validate_physics [--json PATH] [--preset cu_zeolite] [--no-transients]``.

Points (:mod:`scr_env.lab_validation`): the earlier unaged data (low-temperature sweep, NH3-oxidation steps,
isotherms) and every plateau of the five-age file (standard SCR conversion, N2O and NH3 slip, NH3 oxidation, the
NH3 storage step in 0.2 % O2, NO oxidation), each with ``age_h`` and its tolerance (None where PHYSICS.md gives
none); RMS errors per kind, temperature and age; and the transient records of all 35 runs replayed through
``scr_env.lab.run_protocol`` with RMS errors [ppm] per species and segment kind. Prints the tables and writes, to
``runs/validate_physics/<YYYYmmdd-HHMMSS>/``: ``validation.json`` (also ``--json``), ``validation.png`` (the
earlier unaged data), ``validation_ages.png`` (five ages against temperature) and ``validation_transients.png``
(standard-SCR and NH3 storage/oxidation steps at 250 and 450 C, unaged and 16 h, measured and simulated).
Deterministic (no random numbers).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from experiments._runs import run_folder, save_results, write_figure
from scr_env import catalyst_data as cd
from scr_env.lab import steady_state
from scr_env.lab_validation import SPECIES, lab_points, plateau_points, rms_summary, transient_replays

_T = np.arange(140.0, 601.0, 10.0)  # C, simulated curves
_SHOWN_RUNS = ((250.0, 0.0), (250.0, 16.0), (450.0, 0.0), (450.0, 16.0))  # transient figure


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_lab(preset: str, points: list[dict], path: Path) -> None:
    """The earlier unaged data: conversion (standard, fast SCR), slip, NH3 oxidation, storage against temperature."""
    plt = _plt()
    sim = {f: [steady_state(preset, t, **kw) for t in _T] for f, kw in (
        ("std", {"no_ppm": 300.0, "nh3_ppm": 300.0}), ("fast", {"no_ppm": 150.0, "no2_ppm": 150.0, "nh3_ppm": 300.0}),
        ("no2", {"no2_ppm": 300.0, "nh3_ppm": 300.0}), ("ox", {"nh3_ppm": 300.0}))}
    fig, axes = plt.subplots(2, 2, figsize=(12, 8.5))

    def meas(case: str, quantity: str) -> tuple[list, list]:
        sel = [p for p in points if p["case"] == case and p["quantity"] == quantity and p["age_h"] == 0.0]
        return [p["temperature_c"] for p in sel], [p["measured"] for p in sel]

    ax = axes[0, 0]
    for key, col, lab in (("std", "C0", "standard SCR"), ("fast", "C1", "fast SCR (NO:NO2 1:1)"),
                          ("no2", "C2", "NO2-SCR (prediction, no data)")):
        ax.plot(_T, [s["nox_conversion"] for s in sim[key]], "-", color=col, label=f"{lab}, simulated")
    ax.plot(*meas("standard_scr", "nox_conversion"), "C0o", label="standard SCR, measured")
    ax.plot(*meas("fast_scr", "nox_conversion"), "C1s", label="fast SCR, measured")
    ax.set(ylabel="NOx conversion [-]", ylim=(0, 1.02), title="300 ppm NOx, ANR 1, 10 % O2, unaged")
    ax = axes[0, 1]
    ax.plot(_T, [s["nh3_out_ppm"] for s in sim["std"]], "C0-", label="NH3 slip, simulated")
    ax.plot(*meas("standard_scr", "nh3_out_ppm"), "C0o", label="NH3 slip, measured")
    for key, col in (("std", "C0"), ("fast", "C1"), ("no2", "C2")):
        ax.plot(_T, [s["n2o_out_ppm"] for s in sim[key]], "--", color=col, label=f"N2O ({key}), simulated")
    ax.set(ylabel="outlet [ppm]", ylim=(0, 300), title="Slip and N2O")
    ax = axes[1, 0]
    ax.plot(_T, [s["nh3_out_ppm"] for s in sim["ox"]], "C3-", label="NH3 out, simulated")
    ax.plot(_T, [s["nox_out_ppm"] for s in sim["ox"]], "C4-", label="NOx out, simulated")
    ax.plot(*meas("nh3_oxidation", "nh3_out_ppm"), "C3o", label="NH3 out, measured")
    ax.set(xlabel="temperature [C]", ylabel="outlet [ppm]", title="NH3 oxidation, 300 ppm NH3")
    ax = axes[1, 1]
    ax.plot(_T, [steady_state(preset, t, nh3_ppm=300.0)["nh3_stored_mol_per_m3"] for t in _T], "C0-",
            label="simulated")
    ax.plot(*meas("storage_300ppm", "nh3_stored_mol_per_m3"), "C0o", label="isotherm file (derived)")
    ax.set(xlabel="temperature [C]", ylabel="NH3 stored [mol/m3]", title="Equilibrium storage, 300 ppm NH3")
    for a in axes.flat:
        a.grid(alpha=0.3), a.legend(fontsize=7), a.set_xlim(140, 600)
    fig.tight_layout()
    write_figure(fig, path, dpi=110)


def plot_ages(preset: str, points: list[dict], path: Path) -> None:
    """Five ages against temperature: standard-SCR conversion and N2O, NH3-oxidation outlet, NO2 from NO."""
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(12, 8.5))
    panels = (("standard_scr", "nox_conversion", "standard SCR NOx conversion [-]", {"no_ppm": 297.0,
                                                                                     "nh3_ppm": 299.0}),
              ("standard_scr", "n2o_out_ppm", "standard SCR N2O [ppm]", {"no_ppm": 297.0, "nh3_ppm": 299.0}),
              ("nh3_oxidation", "nh3_out_fraction", "NH3 oxidation: NH3 out / in [-]", {"nh3_ppm": 299.0}),
              ("no_only", "no2_out_ppm", "NO oxidation: NO2 out [ppm]", {"no_ppm": 297.0}))
    t_sim = np.arange(240.0, 561.0, 10.0)
    for ax, (case, q, title, feed) in zip(axes.flat, panels, strict=True):
        for i, age in enumerate(cd.AGES_H):
            sel = [p for p in points if p["case"] == case and p["quantity"] == q and p["age_h"] == age
                   and p.get("first_no_only", True)]
            ax.plot([p["temperature_c"] for p in sel], [p["measured"] for p in sel], "o", color=f"C{i}")
            sim = [steady_state(preset, t, age_h=age, **feed) for t in t_sim]
            key = "nh3_out_ppm" if q == "nh3_out_fraction" else q
            val = np.array([s[key] for s in sim]) / (feed["nh3_ppm"] if q == "nh3_out_fraction" else 1.0)
            ax.plot(t_sim, val, "-", color=f"C{i}", label=f"{age:g} h")
        ax.set(title=title, xlabel="temperature [C]")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(title="age (lines simulated,\nmarkers measured)", fontsize=8)
    fig.suptitle(f"'{preset}' against the five-age CLEERS plateaus (Cu-SSZ-13, hydrothermal ageing)")
    fig.tight_layout()
    write_figure(fig, path, dpi=110)


def plot_transients(runs: list[dict], path: Path) -> None:
    """Outlet NH3 and NOx over the kept record (NH3 storage, NH3 oxidation, NO only, standard SCR) of four runs."""
    plt = _plt()
    shown = [r for key in _SHOWN_RUNS for r in runs if (r["temperature_c"], r["age_h"]) == key]
    fig, axes = plt.subplots(len(shown), 1, figsize=(12, 3.0 * len(shown)), squeeze=False)
    for ax, r in zip(axes[:, 0], shown, strict=False):
        t = r["time_min"]
        ax.plot(t, r["inlet"]["NH3_in_ppm"], color="0.7", lw=1, label="NH3 in")
        for sp, col in (("NH3", "C3"), ("NO", "C0"), ("NO2", "C2"), ("N2O", "C4")):
            ax.plot(t, r["measured"][sp], ".", color=col, ms=2, label=f"{sp} measured")
            ax.plot(t, r["simulated"][sp], "-", color=col, lw=1.2,
                    label=f"{sp} simulated (RMS {r['rms_ppm']['all'][sp]:.1f} ppm)")
        ax.set(ylabel="ppm", title=f"{r['temperature_c']:.0f} C, {r['age_h']:g} h: NH3 storage (0.2 % O2), "
                                   "NH3 oxidation, NO only, standard SCR, NO only")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=5, loc="upper right")
    axes[-1, 0].set_xlabel("time [min]")
    fig.tight_layout()
    write_figure(fig, path, dpi=100)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", type=Path, help="also write the results to this JSON file")
    parser.add_argument("--preset", default="cu_zeolite", help="catalyst preset (default cu_zeolite)")
    parser.add_argument("--no-transients", action="store_true", help="skip the transient replays (faster)")
    args = parser.parse_args(argv)
    folder = run_folder("validate_physics", json_path=args.json)  # created and checked before the work

    points = lab_points(args.preset) + plateau_points(args.preset)
    judged = [p for p in points if p["within_tolerance"] is not None]
    for p in points:
        flag = "-" if p["within_tolerance"] is None else ("yes" if p["within_tolerance"] else "NO")
        print(f"{p['case']:15s} {p['temperature_c']:6.1f} C {p['age_h']:4g} h {p['quantity']:22s} "
              f"meas {p['measured']:9.4g} sim {p['simulated']:9.4g}  {flag}")
    n_ok = sum(p["within_tolerance"] for p in judged)
    print(f"{n_ok}/{len(judged)} judged points within tolerance "
          f"({sum(p['within_tolerance'] for p in judged if p['source'] == 'five_age_plateaus')}/"
          f"{sum(1 for p in judged if p['source'] == 'five_age_plateaus')} of the five-age plateaus)")
    rms = rms_summary(points)
    for key, v in rms.items():
        if key.count("/") == 1:
            print(f"RMS {key:40s} {v['rms']:.4g} (n = {v['n']})")
    result = {"preset": args.preset, "points": points, "rms": rms}
    if not args.no_transients:
        runs = transient_replays(args.preset)
        for r in runs:
            print(f"transient {r['temperature_c']:.0f} C {r['age_h']:4g} h: RMS [ppm] "
                  + ", ".join(f"{sp} {r['rms_ppm']['all'][sp]:.1f}" for sp in SPECIES))
        result["transients"] = [{k: r[k] for k in ("temperature_c", "age_h", "n_samples", "rms_ppm")} for r in runs]
        plot_transients(runs, folder / "validation_transients.png")
    save_results(folder, "validation.json", result, args.json)
    plot_lab(args.preset, points, folder / "validation.png")
    plot_ages(args.preset, points, folder / "validation_ages.png")
    print(f"run folder: {folder}")
    return result


if __name__ == "__main__":
    main()
