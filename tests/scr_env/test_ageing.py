"""Catalyst ageing in hours (age_h) from the five-age CLEERS data: monotone losses, interpolation, bad values, and
the three ways in (scr_env.lab, the environments, domain randomisation)."""
from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import scr_env  # noqa: F401  (registers the environment)
from scr_env.catalyst_data import AGES_H
from scr_env.lab import steady_state
from scr_env.params import AGEING_TABLE, MAX_AGE_H, CatalystParams, P, aged, ageing_factors, pack
from scr_env.physics.cell import rate_constants

AGES = np.arange(0.0, MAX_AGE_H + 1e-9, 1.0)
CAT = CatalystParams()


def _k_std(age_h: float, temperature_k: float) -> float:
    p = pack(CAT.replace(age_h=age_h))
    return rate_constants(temperature_k, 0.1, *p[P["a_ads"]:P["o2_order_ox"] + 1])[3]


def test_table_covers_the_measured_ages_and_is_unaged_at_zero():
    assert tuple(sorted(AGEING_TABLE)) == AGES_H
    assert all(v == (0.0 if k.endswith("_j_mol") else 1.0) for k, v in AGEING_TABLE[0.0].items())
    assert pack(CAT.replace(age_h=0.0)).tolist() == pack(CAT).tolist()


@pytest.mark.parametrize("temperature_c", [200.0, 300.0, 400.0, 500.0])
def test_storage_is_lost_monotonically(temperature_c):
    stored = [steady_state(CAT, temperature_c, nh3_ppm=300.0, age_h=a)["nh3_stored_mol_per_m3"] for a in AGES]
    assert np.all(np.diff(stored) <= 1e-12 * stored[0])
    assert stored[-1] < 0.9 * stored[0]


@pytest.mark.parametrize("temperature_k", [450.0, 523.15, 623.15, 723.15, 823.15])
def test_scr_activity_is_lost_monotonically(temperature_k):
    k = [_k_std(a, temperature_k) for a in AGES]
    assert np.all(np.diff(k) <= 1e-12 * k[0])


@pytest.mark.parametrize("temperature_c", [250.0, 350.0, 450.0, 550.0])
def test_an_older_catalyst_converts_less_nox(temperature_c):
    conv = [steady_state(CAT, temperature_c, no_ppm=300.0, nh3_ppm=300.0, age_h=a)["nox_conversion"] for a in AGES]
    assert np.all(np.diff(conv) <= 1e-12)
    assert conv[-1] < conv[0]


def test_between_measured_ages_the_factors_interpolate_log_linearly():
    lo, hi = ageing_factors(4.0), ageing_factors(8.0)
    mid = ageing_factors(6.0)
    for key in lo:
        if key.endswith("_j_mol"):
            assert mid[key] == pytest.approx(0.5 * (lo[key] + hi[key]))
        else:
            assert mid[key] == pytest.approx(np.sqrt(lo[key] * hi[key]))
    assert ageing_factors(2.0) == AGEING_TABLE[2.0]
    # and the lab output lies between its neighbours
    at = {a: steady_state(CAT, 500.0, no_ppm=300.0, nh3_ppm=300.0, age_h=a)["nox_conversion"] for a in (4, 6, 8)}
    assert at[8] <= at[6] <= at[4]


@pytest.mark.parametrize("bad", [-0.5, 16.01, float("nan"), float("inf"), "8", None, True, [8.0]])
def test_bad_ages_are_refused_naming_age_h(bad):
    with pytest.raises(ValueError, match="age_h"):
        steady_state(CAT, 300.0, no_ppm=300.0, nh3_ppm=300.0, age_h=bad) if bad is not None else ageing_factors(bad)
    with pytest.raises(ValueError, match="age_h"):
        aged(CAT, age_h=bad) if bad is not None else CAT.replace(age_h=bad)


def test_environment_takes_age_h_and_packs_the_aged_catalyst():
    env = gym.make("scr_env/UreaSCR-v0", age_h=8.0)
    env.reset(seed=0)
    assert np.array_equal(env.unwrapped.catalyst_params_array, pack(CAT.replace(age_h=8.0)))
    venv = gym.make_vec("scr_env/UreaSCR-v0", num_envs=2, vectorization_mode="vector_entry_point", age_h=16.0)
    venv.reset(seed=0)
    assert np.array_equal(venv.unwrapped.catalyst_params_array[1], pack(CAT.replace(age_h=16.0)))
    # the older severity form maps onto hours
    env = gym.make("scr_env/UreaSCR-v0", ageing=0.5)
    env.reset(seed=0)
    assert np.array_equal(env.unwrapped.catalyst_params_array, pack(CAT.replace(age_h=8.0)))


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"age_h": 20.0}, "age_h"), ({"age_h": -1.0}, "age_h"), ({"age_h": (8.0, 2.0)}, "age_h"),
    ({"age_h": "old"}, "age_h"), ({"age_h": 4.0, "ageing": 0.5}, "not both"),
])
def test_environment_refuses_bad_ages(kwargs, match):
    with pytest.raises(ValueError, match=match):
        gym.make("scr_env/UreaSCR-v0", **kwargs)


def test_age_range_randomises_the_age_per_episode_reproducibly():
    env = gym.make("scr_env/UreaSCR-v0", age_h=(0.0, 16.0))
    capacity = []
    for seed in range(8):
        env.reset(seed=seed)
        capacity.append(env.unwrapped.catalyst_params_array[P["e_des"]])
    assert len(set(capacity)) > 4  # the age (through the desorption energy) differs between episodes
    env.reset(seed=3)
    again = env.unwrapped.catalyst_params_array[P["e_des"]]
    assert again == capacity[3]
    venv = gym.make_vec("scr_env/UreaSCR-v0", num_envs=4, vectorization_mode="vector_entry_point",
                        age_h=(2.0, 4.0))
    venv.reset(seed=1)
    e_des = venv.unwrapped.catalyst_params_array[:, P["e_des"]]
    lo = pack(CAT.replace(age_h=4.0))[P["e_des"]]
    hi = pack(CAT.replace(age_h=2.0))[P["e_des"]]
    assert np.all((e_des >= lo - 1e-9) & (e_des <= hi + 1e-9)) and len(set(e_des)) == 4
