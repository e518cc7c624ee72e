"""The simulator against the shipped Cu-SSZ-13 lab data: every validation point and transient replay, with errors.

Used by :mod:`experiments.validate_physics` (tables, JSON, figures) and the tests. Tolerances are PHYSICS.md
section 6's; quantities PHYSICS.md gives none for carry ``tolerance`` None (reported, not judged).

* :func:`lab_points`: the earlier unaged data (low-temperature sweep, NH3-oxidation steps, isotherms);
* :func:`plateau_points`: every plateau of ``cleers_cu_ssz13_standard_scr_plateaus.csv`` (five ages);
* :func:`transient_replays`: the kept record before the withheld block of every run of
  ``cleers_cu_ssz13_isothermal_steps.csv`` replayed through :func:`scr_env.lab.run_protocol`, with the RMS error
  per outlet species and per segment kind;
* :func:`rms_summary`: RMS errors of points grouped by kind, temperature and age.
"""
from __future__ import annotations

from collections import defaultdict

import numpy as np

from scr_env import catalyst_data as cd
from scr_env.lab import run_protocol, steady_state

#: tolerance per (plateau kind, quantity) [PHYSICS.md 6]; None = reported only
PLATEAU_TOLERANCES = {("standard_scr", "nox_conversion"): 0.05, ("standard_scr", "n2o_out_ppm"): 3.0,
                      ("standard_scr", "nh3_out_ppm"): None, ("nh3_oxidation", "nh3_out_fraction"): 0.10,
                      ("nh3_oxidation", "nox_out_ppm"): None, ("nh3_storage", "nh3_out_fraction"): None,
                      ("no_only", "no2_out_ppm"): (5.0, 0.25)}
SPECIES = ("NH3", "NO", "NO2", "N2O")


def _point(case: str, t_c: float, age_h: float, quantity: str, measured: float, simulated: float,
           tolerance: float | tuple[float, float] | None, relative: bool = False, **extra: object) -> dict:
    error = abs(simulated - measured) / (abs(measured) if relative else 1.0)
    if isinstance(tolerance, tuple):  # absolute + relative part, as in the five-age check
        tol = tolerance[0] + tolerance[1] * abs(measured)
    else:
        tol = tolerance
    out = {"case": case, "temperature_c": t_c, "age_h": age_h, "quantity": quantity, "measured": float(measured),
           "simulated": float(simulated), "tolerance": tol,
           "tolerance_kind": "relative" if relative else "absolute", "error": float(error),
           "signed_error": float(simulated - measured),
           "within_tolerance": None if tol is None else bool(error <= tol)}
    out.update(extra)
    return out


def lab_points(catalyst: object = "cu_zeolite") -> list[dict]:
    """The earlier unaged points (PHYSICS.md 6): standard SCR conversion (0.05) and slip (25 ppm), fast SCR (0.07),
    steady NH3-oxidation outlet at 400-550 C (30 ppm), storage at 300 ppm vs the isotherm file (20 %)."""
    points = []
    for r in cd.rows(cd.LOW_T_SWEEP):
        t_c, nox, nh3 = float(r["T_mid_C"]), float(r["NOx_in_ppm"]), float(r["NH3_in_ppm"])
        if r["case"] == "NOSCR":
            s = steady_state(catalyst, t_c, no_ppm=nox, nh3_ppm=nh3)
            points.append(_point("standard_scr", t_c, 0.0, "nox_conversion", float(r["NOx_conversion"]),
                                 s["nox_conversion"], 0.05, source="lowT_sweep"))
            points.append(_point("standard_scr", t_c, 0.0, "nh3_out_ppm", float(r["NH3_out_ppm"]), s["nh3_out_ppm"],
                                 25.0, source="lowT_sweep"))
        else:
            s = steady_state(catalyst, t_c, no_ppm=nox / 2, no2_ppm=nox / 2, nh3_ppm=nh3)
            points.append(_point("fast_scr", t_c, 0.0, "nox_conversion", float(r["NOx_conversion"]),
                                 s["nox_conversion"], 0.07, source="lowT_sweep"))
    last = {float(r["T_C"]): r for r in cd.rows(cd.NH3_OXIDATION_STEPS)}  # last segment per T: the steady one
    for t_c in (400.0, 500.0, 550.0):
        s = steady_state(catalyst, t_c, nh3_ppm=float(last[t_c]["NH3_in_ppm"]))
        points.append(_point("nh3_oxidation", t_c, 0.0, "nh3_out_ppm", float(last[t_c]["NH3_out_ppm"]),
                             s["nh3_out_ppm"], 30.0, source="nh3_oxidation_steps"))
    for r in cd.rows(cd.ISOTHERMS):
        t_c = float(r["T_C"])
        if float(r["NH3_ppm"]) == 300.0 and 150.0 <= t_c <= 450.0 and t_c % 50.0 == 0.0:
            s = steady_state(catalyst, t_c, nh3_ppm=300.0)
            points.append(_point("storage_300ppm", t_c, 0.0, "nh3_stored_mol_per_m3",
                                 float(r["q_total_molL"]) * 1000.0, s["nh3_stored_mol_per_m3"], 0.20, relative=True,
                                 source="isotherms"))
    return points


def plateau_points(catalyst: object = "cu_zeolite") -> list[dict]:
    """Every plateau of the five-age file with its simulated value; ``first_no_only`` marks the steady NO oxidation
    before any NO2 was fed (the one the five-age acceptance check judges); later NO-only plateaus are reported."""
    points = []
    for r in cd.plateaus():
        t, age, kind, o2 = r["T_C"], r["age_h"], r["kind"], r["O2_in_percent"]
        nh3, no = max(r["NH3_in_ppm"], 0.0), max(r["NO_in_ppm"], 0.0)
        extra = {"source": "five_age_plateaus", "o2_percent": o2, "plateau_start_min": r["plateau_start_min"]}
        if kind == "standard_scr":
            s = steady_state(catalyst, t, no_ppm=no, nh3_ppm=nh3, o2_percent=o2, age_h=age)
            for q, meas in (("nox_conversion", r["NOx_conversion"]), ("n2o_out_ppm", r["N2O_out_ppm"]),
                            ("nh3_out_ppm", r["NH3_out_ppm"])):
                points.append(_point(kind, t, age, q, meas, s[q], PLATEAU_TOLERANCES[(kind, q)], **extra))
        elif kind in ("nh3_oxidation", "nh3_storage"):
            s = steady_state(catalyst, t, nh3_ppm=nh3, o2_percent=o2, age_h=age)
            points.append(_point(kind, t, age, "nh3_out_fraction", r["NH3_out_ppm"] / nh3, s["nh3_out_ppm"] / nh3,
                                 PLATEAU_TOLERANCES[(kind, "nh3_out_fraction")], **extra))
            if kind == "nh3_oxidation":
                points.append(_point(kind, t, age, "nox_out_ppm", r["NO_out_ppm"] + r["NO2_out_ppm"],
                                     s["nox_out_ppm"], None, **extra))
        elif kind == "no_only":
            s = steady_state(catalyst, t, no_ppm=no, o2_percent=o2, age_h=age)
            tol = PLATEAU_TOLERANCES[(kind, "no2_out_ppm")] if r["first_no_only"] else None
            points.append(_point(kind, t, age, "no2_out_ppm", r["NO2_out_ppm"], s["no2_out_ppm"], tol,
                                 first_no_only=r["first_no_only"], **extra))
    return points


def _segment_kind(o2: float, nh3: float, no: float) -> str:
    if nh3 > 10.0 and no > 10.0:
        return "standard_scr"
    if nh3 > 10.0:
        return "nh3_storage" if o2 < 1.0 else "nh3_oxidation"
    if no > 10.0:
        return "no_only"
    return "purge"


def transient_replays(catalyst: object = "cu_zeolite", keys: list[tuple[float, float]] | None = None) -> list[dict]:
    """Replay the first kept segment of every run (or of ``keys``, (temperature C, age h) pairs) and return, per run,
    the measured and simulated outlets (arrays) and the RMS errors [ppm] per species, overall and per segment kind
    (kind of each sample from its inlet: nh3_storage, nh3_oxidation, no_only, standard_scr, purge)."""
    out = []
    for t_c, age in keys or cd.step_record_keys():
        rec = cd.step_records(t_c, age, segment=1)
        sim = run_protocol(rec, t_c, catalyst=catalyst, age_h=age)
        kinds = np.array([_segment_kind(o, a, n) for o, a, n in
                          zip(rec["O2_in_percent"], rec["NH3_in_ppm"], rec["NO_in_ppm"], strict=True)])
        rms: dict[str, dict[str, float]] = {"all": {}}
        for sp in SPECIES:
            err = sim[f"{sp}_out_ppm"] - rec[f"{sp}_out_ppm"]
            rms["all"][sp] = float(np.sqrt(np.mean(err ** 2)))
            for kind in sorted(set(kinds)):
                m = kinds == kind
                rms.setdefault(kind, {})[sp] = float(np.sqrt(np.mean(err[m] ** 2)))
        out.append({"temperature_c": t_c, "age_h": age, "n_samples": int(rec["time_min"].size), "rms_ppm": rms,
                    "time_min": rec["time_min"], "kinds": kinds, "inlet": {k: rec[k] for k in
                                                                          ("NH3_in_ppm", "NO_in_ppm",
                                                                           "O2_in_percent")},
                    "measured": {sp: rec[f"{sp}_out_ppm"] for sp in SPECIES},
                    "simulated": {sp: sim[f"{sp}_out_ppm"] for sp in SPECIES}})
    return out


def rms_summary(points: list[dict]) -> dict[str, dict[str, float]]:
    """RMS of (simulated - measured) per "case/quantity", and per "case/quantity/T=..C" and ".../age=..h"."""
    groups: dict[str, list[float]] = defaultdict(list)
    for p in points:
        base = f"{p['case']}/{p['quantity']}"
        for key in (base, f"{base}/T={p['temperature_c']:.0f}C", f"{base}/age={p['age_h']:g}h"):
            groups[key].append(p["signed_error"])
    return {k: {"rms": float(np.sqrt(np.mean(np.square(v)))), "n": len(v)} for k, v in sorted(groups.items())}
