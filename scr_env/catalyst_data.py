"""Readers of the shipped Cu-SSZ-13 lab data (``scr_env/data/catalyst``, provenance in its PROVENANCE.md).

Every file is CSV with ``#`` comment lines; these functions return its rows as dicts of strings
(:func:`rows`) or, for the transient records, arrays per run (:func:`step_records`). The calibration
(:mod:`experiments.calibrate_catalyst`), the validation (:mod:`experiments.validate_physics`) and the tests read the
data through here.
"""
from __future__ import annotations

import csv
from functools import cache
from importlib import resources

import numpy as np

#: sample labels of the five-age CLEERS files -> hours of hydrothermal ageing
AGE_LABELS: dict[str, float] = {"Unaged": 0.0, "2hr": 2.0, "4hr": 4.0, "8hr": 8.0, "16hr": 16.0}
#: the measured ages [h]
AGES_H: tuple[float, ...] = tuple(AGE_LABELS.values())

LOW_T_SWEEP = "cleers_cu_ssz13_lowT_sweep.csv"
NH3_OXIDATION_STEPS = "cleers_cu_ssz13_nh3_oxidation_steps.csv"
ISOTHERMS = "cu_ssz13_nh3_storage_isotherms.csv"
PLATEAUS = "cleers_cu_ssz13_standard_scr_plateaus.csv"
STEPS = "cleers_cu_ssz13_isothermal_steps.csv"


def _text(name: str) -> str:
    return resources.files("scr_env").joinpath("data", "catalyst", name).read_text(encoding="utf-8")


@cache
def _rows(name: str) -> tuple[dict[str, str], ...]:
    return tuple(csv.DictReader(line for line in _text(name).splitlines() if not line.startswith("#")))


def rows(name: str) -> list[dict[str, str]]:
    """The rows of a catalyst data file (comment lines skipped) as dicts of strings (copies)."""
    return [dict(r) for r in _rows(name)]


def plateaus(kind: str | None = None) -> list[dict]:
    """Rows of the five-age plateau file with numbers as floats and ``age_h``; ``kind`` filters (nh3_storage,
    nh3_oxidation, standard_scr, no_only). ``first_no_only`` marks the first NO-only plateau of each run (steady
    NO oxidation before any NO2 was fed)."""
    out, seen = [], set()
    for r in _rows(PLATEAUS):
        d: dict = {k: (float(v) if v not in ("", None) else float("nan")) for k, v in r.items()
                   if k not in ("age", "kind")}
        d.update(age=r["age"], kind=r["kind"], age_h=AGE_LABELS[r["age"]])
        d["first_no_only"] = False
        if r["kind"] == "no_only" and (d["T_C"], r["age"]) not in seen:
            seen.add((d["T_C"], r["age"]))
            d["first_no_only"] = True
        if kind is None or r["kind"] == kind:
            out.append(d)
    return out


@cache
def _records() -> dict[tuple[float, str], dict[str, np.ndarray]]:
    raw = _rows(STEPS)
    runs: dict[tuple[float, str], list[dict[str, str]]] = {}
    for r in raw:
        runs.setdefault((float(r["T_C"]), r["age"]), []).append(r)
    out = {}
    for key, rr in runs.items():
        cols = {name: np.array([float(r[name]) for r in rr]) for name in rr[0] if name not in ("T_C", "age")}
        out[key] = cols
    return out


def step_records(temperature_c: float, age_h: float, segment: int | None = 1) -> dict[str, np.ndarray]:
    """The transient record of one run of the isothermal step protocol (10 s samples): columns ``time_min``,
    ``segment``, the inlets ``O2_in_percent``, ``H2O_in_percent``, ``NH3_in_ppm``, ``NO_in_ppm``, ``NO2_in_ppm`` and
    the outlets ``NH3_out_ppm``, ``NO_out_ppm``, ``NO2_out_ppm``, ``N2O_out_ppm``. ``segment`` 1 is everything before
    the withheld NO2-feed block (NH3 storage, NH3 oxidation, NO only, standard SCR, NO only); None gives every kept
    sample (the time then jumps over the withheld block)."""
    label = next((k for k, v in AGE_LABELS.items() if v == float(age_h)), None)
    key = (float(temperature_c), label)
    recs = _records()
    if label is None or key not in recs:
        raise ValueError(f"no record at {temperature_c!r} C and {age_h!r} h; records exist at "
                         f"{sorted({k[0] for k in recs})} C for ages {list(AGE_LABELS.values())} h")
    cols = recs[key]
    keep = np.ones(cols["time_min"].size, dtype=bool) if segment is None else cols["segment"] == segment
    return {k: v[keep].copy() for k, v in cols.items()}


def step_record_keys() -> list[tuple[float, float]]:
    """(temperature [C], age [h]) of every run in the transient file, sorted."""
    return sorted((t, AGE_LABELS[a]) for t, a in _records())
