"""Catalyst, dosing and sensor parameters (scr_env.params): presets, packing, ageing, randomisation, validation."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from scr_env.params import (
    PACKED_FIELDS,
    PRESETS,
    CatalystParams,
    DosingParams,
    SensorParams,
    aged,
    catalyst_preset,
    pack,
    randomised,
)

P = {name: i for i, name in enumerate(PACKED_FIELDS)}
ACTIVITY = ("a_std", "a_an", "a_an_no", "a_an_dec", "a_an_n2o", "a_ox", "a_ox_no", "a_ox_n2o", "a_n2o", "a_no_ox")


def test_presets_resolve_and_cu_zeolite_is_the_calibrated_full_size_brick():
    assert "cu_zeolite" in PRESETS
    cat = catalyst_preset("cu_zeolite")
    assert cat is PRESETS["cu_zeolite"] and catalyst_preset(cat) is cat
    assert 0.034 <= cat.volume_m3 <= 0.054  # m3: 12-13 L engine (PHYSICS.md 2)
    assert 5 <= cat.n_cells <= 10
    assert 50.0 <= cat.storage_capacity_mol_m3 <= 300.0  # mol/m3, calibrated (experiments.calibrate_catalyst)
    assert cat.age_h == 0.0
    for name, preset in PRESETS.items():
        assert isinstance(preset, CatalystParams) and preset.name == name


def test_unknown_preset_raises_value_error():
    with pytest.raises(ValueError, match="preset"):
        catalyst_preset("unknown")


def test_pack_layout_and_derived_quantities():
    cat = CatalystParams()
    p = pack(cat)
    assert p.shape == (len(PACKED_FIELDS),) and p.dtype == np.float64
    assert p[P["n_cells"]] == cat.n_cells
    assert p[P["sites_per_cell_mol"]] * cat.n_cells == pytest.approx(cat.volume_m3 * cat.storage_capacity_mol_m3)
    assert p[P["heat_capacity_per_cell_j_k"]] * cat.n_cells == pytest.approx(
        cat.volume_m3 * (1 - cat.open_frontal_area) * cat.solid_density_kg_m3 * cat.solid_heat_capacity_j_kg_k)


def test_activity_retention_scales_every_reaction_and_storage_retention_the_sites():
    cat = CatalystParams()
    base, half = pack(cat), pack(cat.replace(activity_retention=0.5, storage_retention=0.8))
    for name in ACTIVITY:
        assert half[P[name]] == pytest.approx(0.5 * base[P[name]]), name
    assert half[P["sites_per_cell_mol"]] == pytest.approx(0.8 * base[P["sites_per_cell_mol"]])
    # adsorption/desorption kinetics (the isotherm shape) are not an activity
    assert half[P["a_des"]] == base[P["a_des"]] and half[P["e_des"]] == base[P["e_des"]]


def test_aged_maps_severity_to_hours_and_takes_exactly_one_of_them():
    cat = CatalystParams()
    assert aged(cat, 0.5).age_h == pytest.approx(8.0)
    assert aged(cat, age_h=4.0).age_h == 4.0
    assert aged(cat, 0.0) == cat
    assert aged(aged(cat, age_h=16.0), age_h=2.0).age_h == 2.0  # an age, not an increment
    with pytest.raises(ValueError, match="exactly one"):
        aged(cat)
    with pytest.raises(ValueError, match="exactly one"):
        aged(cat, 0.5, age_h=8.0)


@pytest.mark.parametrize("severity", [-0.1, 1.5, float("nan"), "half", True])
def test_ageing_rejects_bad_severity(severity):
    with pytest.raises(ValueError, match="severity"):
        aged(CatalystParams(), severity)


def test_randomised_is_reproducible_per_seed_and_bounded():
    cat = CatalystParams()
    a = randomised(cat, np.random.default_rng(3))
    b = randomised(cat, np.random.default_rng(3))
    c = randomised(cat, np.random.default_rng(4))
    assert a == b and a != c
    draws = [randomised(cat, np.random.default_rng(s), spread=0.2) for s in range(50)]
    for name in ("storage_capacity_mol_m3", "a_std_m3_mol_s", "a_an_m3_mol_s", "a_ox_1_s", "volume_m3"):
        ratios = np.array([getattr(d, name) / getattr(cat, name) for d in draws])
        assert np.all((ratios >= 0.8 - 1e-12) & (ratios <= 1.2 + 1e-12)), name
        assert ratios.std() > 0.01, name
    assert randomised(cat, np.random.default_rng(0), spread=0.0) == cat
    # ageing as a randomised quantity: uniform in the range, drawn after the factors (same factors per seed)
    ages = [randomised(cat, np.random.default_rng(s), 0.2, age_h_range=(2.0, 8.0)) for s in range(50)]
    assert all(2.0 <= d.age_h <= 8.0 for d in ages) and np.std([d.age_h for d in ages]) > 1.0
    assert all(a.replace(age_h=0.0) == d for a, d in zip(ages, draws, strict=True))


def test_randomised_rejects_bad_spread_and_age_range():
    with pytest.raises(ValueError, match="spread"):
        randomised(CatalystParams(), np.random.default_rng(0), spread=1.5)
    for bad in ((8.0, 2.0), (0.0, 20.0), (0.0,), "0-16", (float("nan"), 4.0)):
        with pytest.raises(ValueError, match="age_h_range"):
            randomised(CatalystParams(), np.random.default_rng(0), age_h_range=bad)


@pytest.mark.parametrize(("field", "value"), [
    ("volume_m3", -0.01), ("volume_m3", 0.0), ("storage_capacity_mol_m3", float("nan")), ("a_std_m3_mol_s", -1.0),
    ("e_des_j_mol", float("inf")), ("n_cells", 0), ("n_cells", 2.5), ("temkin_gamma", 1.0),
    ("open_frontal_area", 1.0), ("storage_retention", 0.0), ("activity_retention", 1.5), ("age_h", -1.0),
    ("age_h", 16.5), ("age_h", float("nan")), ("temkin_gamma", True),
])
def test_catalyst_bad_values_raise_value_error_naming_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        CatalystParams(**{field: value})


@pytest.mark.parametrize(("cls", "field", "value"), [
    (DosingParams, "max_rate_g_s", 0.0), (DosingParams, "decomposition_width_k", float("nan")),
    (SensorParams, "nox_sensor_noise_ppm", -1.0), (SensorParams, "nox_sensor_time_constant_s", float("inf")),
])
def test_dosing_and_sensor_bad_values_raise_value_error_naming_the_field(cls, field, value):
    with pytest.raises(ValueError, match=field):
        cls(**{field: value})


def test_params_are_frozen_and_replace_validates():
    cat = CatalystParams()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cat.volume_m3 = 1.0  # type: ignore[misc]
    assert cat.replace(volume_m3=0.054).volume_m3 == 0.054
    with pytest.raises(ValueError, match="volume_m3"):
        cat.replace(volume_m3=-1.0)


def test_noiseless_sensors_keep_lags():
    s = SensorParams().noiseless()
    assert s.nox_sensor_noise_ppm == 0.0 and s.temperature_noise_k == 0.0 and s.flow_noise_fraction == 0.0
    assert s.nox_sensor_time_constant_s == SensorParams().nox_sensor_time_constant_s
