"""The catalyst model in the CLEERS lab configuration against the shipped Cu-SSZ-13 data (PHYSICS.md section 6)."""
from __future__ import annotations

import csv
import math
from importlib import resources

import numpy as np
import pytest

from scr_env.catalyst_data import step_records
from scr_env.lab import run_protocol, steady_state
from scr_env.params import CatalystParams


def _rows(name: str) -> list[dict[str, str]]:
    text = resources.files("scr_env").joinpath("data", "catalyst", name).read_text(encoding="utf-8")
    return list(csv.DictReader(line for line in text.splitlines() if not line.startswith("#")))


SWEEP = _rows("cleers_cu_ssz13_lowT_sweep.csv")
STANDARD = [r for r in SWEEP if r["case"] == "NOSCR"]
FAST = [r for r in SWEEP if r["case"] == "FastSCR"]
OXIDATION_LAST = {float(r["T_C"]): r for r in _rows("cleers_cu_ssz13_nh3_oxidation_steps.csv")}  # last segment
ISOTHERM_300 = [r for r in _rows("cu_ssz13_nh3_storage_isotherms.csv")
                if float(r["NH3_ppm"]) == 300.0 and 150.0 <= float(r["T_C"]) <= 450.0 and float(r["T_C"]) % 50 == 0]


def test_data_cover_the_validation_targets():
    assert len(STANDARD) == 5 and len(FAST) == 5
    assert {400.0, 500.0, 550.0} <= set(OXIDATION_LAST)
    assert [float(r["T_C"]) for r in ISOTHERM_300] == [150.0, 200.0, 250.0, 300.0, 350.0, 400.0, 450.0]


@pytest.mark.parametrize("row", STANDARD, ids=lambda r: f"{float(r['T_mid_C']):.0f}C")
def test_standard_scr_conversion_and_slip(row):
    s = steady_state("cu_zeolite", float(row["T_mid_C"]), no_ppm=float(row["NOx_in_ppm"]),
                     nh3_ppm=float(row["NH3_in_ppm"]))
    assert abs(s["nox_conversion"] - float(row["NOx_conversion"])) <= 0.05
    assert abs(s["nh3_out_ppm"] - float(row["NH3_out_ppm"])) <= 25.0


@pytest.mark.parametrize("row", FAST, ids=lambda r: f"{float(r['T_mid_C']):.0f}C")
def test_fast_scr_conversion(row):
    nox = float(row["NOx_in_ppm"])
    s = steady_state("cu_zeolite", float(row["T_mid_C"]), no_ppm=nox / 2, no2_ppm=nox / 2,
                     nh3_ppm=float(row["NH3_in_ppm"]))
    assert abs(s["nox_conversion"] - float(row["NOx_conversion"])) <= 0.07


@pytest.mark.parametrize("temperature_c", [400.0, 500.0, 550.0])
def test_nh3_oxidation_outlet(temperature_c):
    row = OXIDATION_LAST[temperature_c]
    s = steady_state("cu_zeolite", temperature_c, nh3_ppm=float(row["NH3_in_ppm"]))
    assert abs(s["nh3_out_ppm"] - float(row["NH3_out_ppm"])) <= 30.0
    assert math.isnan(s["nox_conversion"])


@pytest.mark.parametrize("row", ISOTHERM_300, ids=lambda r: f"{float(r['T_C']):.0f}C")
def test_storage_at_300_ppm_matches_isotherm(row):
    measured = float(row["q_total_molL"]) * 1000.0  # mol/L -> mol/m3
    s = steady_state("cu_zeolite", float(row["T_C"]), nh3_ppm=300.0)
    assert abs(s["nh3_stored_mol_per_m3"] - measured) <= 0.20 * measured


def test_storage_falls_with_temperature_and_rises_with_concentration():
    stored = [steady_state("cu_zeolite", t, nh3_ppm=300.0)["nh3_stored_mol_per_m3"] for t in (150, 250, 350, 450)]
    assert np.all(np.diff(stored) < 0)
    assert (steady_state("cu_zeolite", 250.0, nh3_ppm=1000.0)["nh3_stored_mol_per_m3"]
            > steady_state("cu_zeolite", 250.0, nh3_ppm=100.0)["nh3_stored_mol_per_m3"])


def test_accepts_params_object_and_aged_catalyst_converts_less():
    fresh = steady_state(CatalystParams(), 200.0, no_ppm=300.0, nh3_ppm=300.0)["nox_conversion"]
    old = steady_state(CatalystParams(activity_retention=0.5), 200.0, no_ppm=300.0, nh3_ppm=300.0)["nox_conversion"]
    assert 0.0 < old < fresh < 1.0


@pytest.mark.parametrize(("kwargs", "name"), [
    ({"temperature_c": float("nan")}, "temperature_c"),
    ({"temperature_c": 50.0}, "temperature_c"),
    ({"temperature_c": 900.0}, "temperature_c"),
    ({"temperature_c": "hot"}, "temperature_c"),
    ({"temperature_c": 250.0, "no_ppm": -1.0}, "no_ppm"),
    ({"temperature_c": 250.0, "no2_ppm": -5.0}, "no2_ppm"),
    ({"temperature_c": 250.0, "nh3_ppm": float("inf")}, "nh3_ppm"),
    ({"temperature_c": 250.0, "o2_percent": 30.0}, "o2_percent"),
    ({"temperature_c": 250.0, "ghsv_per_h": 0.0}, "ghsv_per_h"),
    ({"temperature_c": 250.0, "n_cells": 2.5}, "n_cells"),
    ({"temperature_c": 250.0, "age_h": 17.0}, "age_h"),
    ({"temperature_c": 250.0, "age_h": "new"}, "age_h"),
])
def test_bad_input_raises_value_error_naming_the_argument(kwargs, name):
    with pytest.raises(ValueError, match=name):
        steady_state("cu_zeolite", **kwargs)


def test_unknown_preset_raises_value_error():
    with pytest.raises(ValueError, match="preset"):
        steady_state("platinum_unobtainium", 250.0, nh3_ppm=300.0)


# --- run_protocol: a measured inlet time series through the lab sample ------------------------------------------------


def _constant_inlet(n: int, dt_s: float, **ppm: float) -> dict[str, np.ndarray]:
    return {"time_s": np.arange(n) * dt_s, "O2_in_percent": np.full(n, ppm.pop("o2", 10.0)),
            "NH3_in_ppm": np.full(n, ppm.get("nh3", 0.0)), "NO_in_ppm": np.full(n, ppm.get("no", 0.0)),
            "NO2_in_ppm": np.full(n, ppm.get("no2", 0.0))}


@pytest.mark.parametrize(("feed", "t_c"), [({"no": 300.0, "nh3": 300.0}, 250.0), ({"nh3": 300.0}, 450.0),
                                           ({"no": 150.0, "no2": 150.0, "nh3": 300.0}, 200.0)])
def test_replay_of_a_constant_feed_ends_at_the_steady_state(feed, t_c):
    out = run_protocol(_constant_inlet(400, 10.0, **feed), t_c, age_h=4.0)
    ss = steady_state("cu_zeolite", t_c, age_h=4.0, nh3_ppm=feed.get("nh3", 0.0), no_ppm=feed.get("no", 0.0),
                      no2_ppm=feed.get("no2", 0.0))
    for col, key in (("NH3_out_ppm", "nh3_out_ppm"), ("NO_out_ppm", "no_out_ppm"), ("NO2_out_ppm", "no2_out_ppm"),
                     ("N2O_out_ppm", "n2o_out_ppm")):
        assert out[col][-1] == pytest.approx(ss[key], rel=1e-3, abs=0.05), col
    assert out["mean_coverage"][-1] == pytest.approx(ss["mean_coverage"], rel=1e-3)


def test_replay_stores_nitrogen_exactly():
    """Without O2 nothing reacts: the NH3 taken up equals the stored NH3 (samples of 1 s, one implicit step each)."""
    n = 600
    inlet = _constant_inlet(n, 1.0, nh3=300.0, o2=0.0)
    inlet["NH3_in_ppm"][300:] = 0.0  # fill for 5 min, then purge
    out = run_protocol(inlet, 300.0)
    flow = 60000.0 / 3600.0 * 101325.0 / (8.314462618 * 273.15)  # mol/s per m3 (GHSV at 0 C)
    taken = np.sum((inlet["NH3_in_ppm"][:-1] - out["NH3_out_ppm"][1:]) * 1e-6) * flow  # mol per m3
    assert taken == pytest.approx(out["nh3_stored_mol_per_m3"][-1], rel=1e-9)
    assert out["nh3_stored_mol_per_m3"][299] > out["nh3_stored_mol_per_m3"][-1] > 0.0  # desorbs in the purge


def test_replay_of_a_measured_record_follows_storage_and_scr():
    """250 C, unaged: the NH3 step breaks through late (storage), standard SCR then removes most NO."""
    rec = step_records(250.0, 0.0)
    out = run_protocol(rec, 250.0)
    assert set(out) >= {"time_min", "NH3_out_ppm", "NO_out_ppm", "NO2_out_ppm", "N2O_out_ppm"}
    assert all(v.shape == rec["time_min"].shape and np.all(np.isfinite(v)) for v in out.values())
    step = np.argmax(rec["NH3_in_ppm"] > 150.0)
    half = np.argmax(out["NH3_out_ppm"] > 150.0)
    measured_half = np.argmax(rec["NH3_out_ppm"] > 150.0)
    assert half > step + 6  # more than a minute of uptake before half breakthrough
    assert abs(rec["time_min"][half] - rec["time_min"][measured_half]) < 3.0  # min
    scr = (rec["NH3_in_ppm"] > 150.0) & (rec["NO_in_ppm"] > 150.0)
    assert np.median(out["NO_out_ppm"][scr]) < 0.2 * np.median(rec["NO_in_ppm"][scr])


@pytest.mark.parametrize(("change", "name"), [
    ({"time_s": None}, "time"), ({"NH3_in_ppm": None}, "NH3_in_ppm"),
    ({"time_s": np.r_[0.0, 0.0, np.arange(2, 10)]}, "increasing"),
    ({"NO_in_ppm": np.r_[np.nan, np.zeros(9)]}, "NO_in_ppm"), ({"NH3_in_ppm": np.r_[-50.0, np.zeros(9)]}, "NH3_in_ppm"),
    ({"O2_in_percent": np.full(10, 30.0)}, "O2_in_percent"), ({"NO_in_ppm": np.zeros(9)}, "NO_in_ppm"),
])
def test_replay_refuses_bad_inlets_naming_the_column(change, name):
    inlet = _constant_inlet(10, 10.0, no=300.0, nh3=300.0)
    for k, v in change.items():
        if v is None:
            del inlet[k]
        else:
            inlet[k] = v
    with pytest.raises(ValueError, match=name):
        run_protocol(inlet, 250.0)


@pytest.mark.parametrize(("kwargs", "name"), [({"temperature_c": [250.0, 260.0]}, "temperature_c"),
                                              ({"temperature_c": 900.0}, "temperature_c"),
                                              ({"age_h": 40.0}, "age_h"), ({"initial_coverage": 1.5},
                                                                           "initial_coverage")])
def test_replay_refuses_bad_arguments(kwargs, name):
    with pytest.raises(ValueError, match=name):
        run_protocol(_constant_inlet(10, 10.0, no=300.0), **{"temperature_c": 250.0, **kwargs})
    with pytest.raises(ValueError, match="inlet"):
        run_protocol("protocol.csv", 250.0)
