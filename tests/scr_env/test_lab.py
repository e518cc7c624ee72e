"""The catalyst model in the CLEERS lab configuration against the shipped Cu-SSZ-13 data (PHYSICS.md section 6)."""
from __future__ import annotations

import csv
import math
from importlib import resources

import numpy as np
import pytest

from scr_env.lab import steady_state
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
])
def test_bad_input_raises_value_error_naming_the_argument(kwargs, name):
    with pytest.raises(ValueError, match=name):
        steady_state("cu_zeolite", **kwargs)


def test_unknown_preset_raises_value_error():
    with pytest.raises(ValueError, match="preset"):
        steady_state("platinum_unobtainium", 250.0, nh3_ppm=300.0)
