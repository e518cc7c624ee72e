"""The simulator in the CLEERS lab configuration against the real Cu-SSZ-13 measurements (PHYSICS.md section 6).

Usage: ``python -m experiments.validate_physics [--json PATH] [--preset cu_zeolite]``.

Prints one row per validation point (case, temperature [C], quantity, measured, simulated, tolerance, ok), writes
``validation.json`` (``{"points": [{"case", "temperature_c", "quantity", "measured", "simulated", "tolerance",
"within_tolerance"}, ...]}``; also to ``--json PATH`` if given) and ``validation.png`` (conversion, NH3 slip,
NH3-oxidation outlet and storage against temperature: measured markers, simulated curves) to
``runs/validate_physics/<YYYYmmdd-HHMMSS>/``. Deterministic (no random numbers).

Points and tolerances (PHYSICS.md 6): standard SCR NOx conversion within 0.05 and NH3 slip within 25 ppm at the
five plateaus; fast SCR (NO:NO2 = 1:1) conversion within 0.07; steady NH3 outlet of the NH3-only oxidation
segments within 30 ppm at 400, 500, 550 C (the last segment at each temperature is the steady one); equilibrium
storage at 300 ppm NH3 within 20 % of the isotherm file from 150 to 450 C every 50 C.
"""
from __future__ import annotations

import argparse
import csv
from importlib import resources
from pathlib import Path

import numpy as np

from experiments._runs import run_folder, write_json
from scr_env.lab import steady_state

_CURVE_T_C = np.arange(140.0, 601.0, 5.0)  # C, simulated curves


def _rows(name: str) -> list[dict[str, str]]:
    text = resources.files("scr_env").joinpath("data", "catalyst", name).read_text(encoding="utf-8")
    return list(csv.DictReader(line for line in text.splitlines() if not line.startswith("#")))


def _point(case: str, t_c: float, quantity: str, measured: float, simulated: float, tolerance: float,
           relative: bool = False) -> dict:
    error = abs(simulated - measured) / (abs(measured) if relative else 1.0)
    return {"case": case, "temperature_c": t_c, "quantity": quantity, "measured": measured,
            "simulated": float(simulated), "tolerance": tolerance, "tolerance_kind": "relative" if relative else
            "absolute", "error": float(error), "within_tolerance": bool(error <= tolerance)}


def validation_points(preset: str = "cu_zeolite") -> list[dict]:
    """Every point of PHYSICS.md section 6 with its measurement, simulation and tolerance."""
    points = []
    for r in _rows("cleers_cu_ssz13_lowT_sweep.csv"):
        t_c, nox, nh3 = float(r["T_mid_C"]), float(r["NOx_in_ppm"]), float(r["NH3_in_ppm"])
        if r["case"] == "NOSCR":
            s = steady_state(preset, t_c, no_ppm=nox, nh3_ppm=nh3)
            points.append(_point("standard_scr", t_c, "nox_conversion", float(r["NOx_conversion"]),
                                 s["nox_conversion"], 0.05))
            points.append(_point("standard_scr", t_c, "nh3_out_ppm", float(r["NH3_out_ppm"]), s["nh3_out_ppm"], 25.0))
        elif r["case"] == "FastSCR":
            s = steady_state(preset, t_c, no_ppm=nox / 2, no2_ppm=nox / 2, nh3_ppm=nh3)
            points.append(_point("fast_scr", t_c, "nox_conversion", float(r["NOx_conversion"]),
                                 s["nox_conversion"], 0.07))
    last = {float(r["T_C"]): r for r in _rows("cleers_cu_ssz13_nh3_oxidation_steps.csv")}  # last segment per T
    for t_c in (400.0, 500.0, 550.0):
        s = steady_state(preset, t_c, nh3_ppm=float(last[t_c]["NH3_in_ppm"]))
        points.append(_point("nh3_oxidation", t_c, "nh3_out_ppm", float(last[t_c]["NH3_out_ppm"]), s["nh3_out_ppm"],
                             30.0))
    for r in _rows("cu_ssz13_nh3_storage_isotherms.csv"):
        t_c = float(r["T_C"])
        if float(r["NH3_ppm"]) == 300.0 and 150.0 <= t_c <= 450.0 and t_c % 50.0 == 0.0:
            s = steady_state(preset, t_c, nh3_ppm=300.0)
            points.append(_point("storage_300ppm", t_c, "nh3_stored_mol_per_m3", float(r["q_total_molL"]) * 1000.0,
                                 s["nh3_stored_mol_per_m3"], 0.20, relative=True))
    return points


def _curves(preset: str) -> dict[str, np.ndarray]:
    """Simulated lab curves over 140-600 C at the CLEERS feed (300 ppm NOx, ANR 1, 10 % O2)."""
    std = [steady_state(preset, t, no_ppm=300.0, nh3_ppm=300.0) for t in _CURVE_T_C]
    fast = [steady_state(preset, t, no_ppm=150.0, no2_ppm=150.0, nh3_ppm=300.0) for t in _CURVE_T_C]
    ox = [steady_state(preset, t, nh3_ppm=300.0) for t in _CURVE_T_C]
    out = {"t_c": _CURVE_T_C,
           "std_conversion": np.array([s["nox_conversion"] for s in std]),
           "std_slip": np.array([s["nh3_out_ppm"] for s in std]),
           "std_n2o": np.array([s["n2o_out_ppm"] for s in std]),
           "fast_conversion": np.array([s["nox_conversion"] for s in fast]),
           "ox_nh3_out": np.array([s["nh3_out_ppm"] for s in ox]),
           "ox_nox_out": np.array([s["nox_out_ppm"] for s in ox])}
    for ppm in (100.0, 300.0, 1000.0):
        out[f"storage_{ppm:.0f}"] = np.array([steady_state(preset, t, nh3_ppm=ppm)["nh3_stored_mol_per_m3"]
                                              for t in _CURVE_T_C])
    return out


def plot(preset: str, path: Path) -> None:
    """Four panels against temperature: NOx conversion, NH3 slip (standard SCR), NH3 oxidation, NH3 storage."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - matplotlib is a core dependency
        raise ImportError("validate_physics needs matplotlib (pip install matplotlib)") from exc
    c = _curves(preset)
    t = c["t_c"]
    sweep = _rows("cleers_cu_ssz13_lowT_sweep.csv")
    std = [r for r in sweep if r["case"] == "NOSCR"]
    fast = [r for r in sweep if r["case"] == "FastSCR"]
    ox = _rows("cleers_cu_ssz13_nh3_oxidation_steps.csv")
    last = {float(r["T_C"]): r for r in ox}
    iso = _rows("cu_ssz13_nh3_storage_isotherms.csv")

    def col(rows: list[dict[str, str]], key: str) -> np.ndarray:
        return np.array([float(r[key]) for r in rows])

    fig, axes = plt.subplots(2, 2, figsize=(12, 8.5))
    ax = axes[0, 0]
    ax.plot(t, c["std_conversion"], "C0-", label="standard SCR, simulated")
    ax.plot(col(std, "T_mid_C"), col(std, "NOx_conversion"), "C0o", ms=7, label="standard SCR, measured")
    ax.plot(t, c["fast_conversion"], "C1-", label="fast SCR (NO:NO2 1:1), simulated")
    ax.plot(col(fast, "T_mid_C"), col(fast, "NOx_conversion"), "C1s", ms=7, label="fast SCR, measured")
    ax.set(ylabel="NOx conversion [-]", ylim=(0, 1.02), title="NOx conversion, 300 ppm NOx, ANR 1, GHSV 60000 1/h")
    ax.legend(loc="lower right", fontsize=8)

    ax = axes[0, 1]
    ax.plot(t, c["std_slip"], "C0-", label="NH3 slip, simulated")
    ax.plot(col(std, "T_mid_C"), col(std, "NH3_out_ppm"), "C0o", ms=7, label="NH3 slip, measured (+/- 25 ppm)")
    ax.errorbar(col(std, "T_mid_C"), col(std, "NH3_out_ppm"), yerr=25.0, fmt="none", ecolor="C0", alpha=0.5)
    ax.plot(t, c["std_n2o"], "C2-", label="N2O, simulated")
    ax.plot(col(std, "T_mid_C"), col(std, "N2O_out_ppm"), "C2^", ms=7, label="N2O, measured")
    ax.set(ylabel="outlet [ppm]", ylim=(0, 300), title="Standard SCR: NH3 slip and N2O")
    ax.legend(loc="upper right", fontsize=8)

    ax = axes[1, 0]
    ax.plot(t, c["ox_nh3_out"], "C3-", label="NH3 out, simulated")
    ax.plot(col(ox, "T_C"), col(ox, "NH3_out_ppm"), "o", mfc="none", mec="C3", alpha=0.6,
            label="NH3 out, all segments\n(early ones still filling)")
    lt = np.array(sorted(last))
    ax.plot(lt, [float(last[v]["NH3_out_ppm"]) for v in lt], "C3o", ms=7, label="NH3 out, last segment")
    ax.plot(t, c["ox_nox_out"], "C4-", label="NOx out, simulated")
    ax.plot(lt, [float(last[v]["NOx_out_ppm"]) for v in lt], "C4s", ms=7, label="NOx out, last segment")
    ax.set(xlabel="temperature [C]", ylabel="outlet [ppm]", ylim=(0, 320),
           title="NH3 oxidation, 300 ppm NH3, no NOx")
    ax.legend(loc="upper right", fontsize=8)

    ax = axes[1, 1]
    for ppm, color in ((100.0, "C5"), (300.0, "C0"), (1000.0, "C1")):
        rows = [r for r in iso if float(r["NH3_ppm"]) == ppm]
        ax.plot(t, c[f"storage_{ppm:.0f}"], "-", color=color, label=f"{ppm:.0f} ppm, simulated")
        ax.plot(col(rows, "T_C"), col(rows, "q_total_molL") * 1000.0, "o", color=color, ms=5,
                label=f"{ppm:.0f} ppm, isotherm file")
    ax.set(xlabel="temperature [C]", ylabel="NH3 stored [mol / m3 catalyst]", ylim=(0, None),
           title="Equilibrium NH3 storage (isotherm: derived, not measured)")
    ax.legend(loc="upper right", fontsize=8, ncol=2)

    for a in axes.flat:
        a.set_xlim(140, 600)
        a.grid(alpha=0.3)
    fig.suptitle(f"Catalyst '{preset}' in the CLEERS lab configuration vs the Cu-SSZ-13 data", fontsize=12)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _table(points: list[dict]) -> str:
    head = f"{'case':15s} {'T [C]':>6s} {'quantity':22s} {'measured':>9s} {'simulated':>9s} {'tolerance':>10s}  ok"
    lines = [head, "-" * len(head)]
    for p in points:
        tol = f"{p['tolerance'] * 100:.0f} %" if p["tolerance_kind"] == "relative" else f"{p['tolerance']:g}"
        lines.append(f"{p['case']:15s} {p['temperature_c']:6.1f} {p['quantity']:22s} {p['measured']:9.4g} "
                     f"{p['simulated']:9.4g} {tol:>10s}  {'yes' if p['within_tolerance'] else 'NO'}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", type=Path, help="also write the points to this JSON file")
    parser.add_argument("--preset", default="cu_zeolite", help="catalyst preset (default cu_zeolite)")
    args = parser.parse_args(argv)
    folder = run_folder("validate_physics", json_path=args.json)  # created and checked before the work

    points = validation_points(args.preset)
    result = {"preset": args.preset, "points": points}
    print(_table(points))
    n_ok = sum(p["within_tolerance"] for p in points)
    worst = max(p["error"] / p["tolerance"] for p in points)
    print(f"{n_ok}/{len(points)} points within tolerance; worst error/tolerance {worst:.2f}")

    write_json(folder / "validation.json", result)
    if args.json:
        write_json(args.json, result)
    plot(args.preset, folder / "validation.png")
    print(f"run folder: {folder}")
    return result


if __name__ == "__main__":
    main()
