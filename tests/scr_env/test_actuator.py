"""The optional dosing actuator (first-order lag and slew limit in the compiled plant step) and the chatter KPI."""
from __future__ import annotations

import math

import numpy as np
import pytest

from scr_env.actuator import DEFAULT_ACTUATOR, ActuatorParams, actuator_params
from scr_env.envs.urea_scr import UreaSCREnv
from scr_env.envs.vector import UreaSCRVectorEnv


def _run(env, actions, seed=0):
    env.reset(seed=seed)
    out = []
    for a in actions:
        obs, _, _, _, info = env.step(np.array([a], dtype=np.float32))
        out.append((info["adblue_g_s"], float(obs[4])))
    return np.array(out)


def test_step_response_follows_the_lag_and_the_slew_limit():
    act = ActuatorParams(time_constant_s=1.0, max_slew_g_s2=1.0)
    env = UreaSCREnv(cycle="whtc", actuator=act, action_mode="physical")
    rec = _run(env, [3.0] * 12 + [0.0] * 12)
    delivered, previous_action = rec[:, 0], rec[:, 1]
    d, expected = 0.0, []
    lag, cap = 1.0 - math.exp(-0.5), 0.5
    for c in [3.0] * 12 + [0.0] * 12:
        d += min(max(lag * (c - d), -cap), cap)
        expected.append(d)
    np.testing.assert_allclose(delivered, expected, rtol=1e-12)
    assert np.all(np.abs(np.diff(np.r_[0.0, delivered])) <= 0.5 + 1e-12)  # slew limit 1 g/s per s at dt 0.5 s
    assert delivered[2] < 3.0 and delivered[11] > 2.9  # the lag: not at once, but within a few seconds
    np.testing.assert_array_equal(previous_action[:12], 1.0)  # the observation shows the command


def test_no_actuator_delivers_the_command_and_a_transparent_one_the_same():
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, 200)
    ideal = _run(UreaSCREnv(cycle="whtc"), actions)
    np.testing.assert_allclose(ideal[:, 0], 1.5 * (actions.astype(np.float32) + 1.0), rtol=1e-6)
    clear = _run(UreaSCREnv(cycle="whtc", actuator={"time_constant_s": 0.0, "max_slew_g_s2": math.inf}), actions)
    np.testing.assert_allclose(clear, ideal, rtol=1e-12, atol=1e-12)
    lagged = _run(UreaSCREnv(cycle="whtc", actuator="default"), actions)
    assert np.abs(np.diff(lagged[:, 0])).sum() < 0.5 * np.abs(np.diff(ideal[:, 0])).sum()


def test_single_and_vector_environment_share_the_actuator():
    rng = np.random.default_rng(1)
    actions = rng.uniform(-1, 1, (300, 2)).astype(np.float32)
    venv = UreaSCRVectorEnv(num_envs=2, cycle="whsc", actuator="default")
    venv.reset(seed=4)
    v = []
    for a in actions:
        _, r, _, _, info = venv.step(a[:, None])
        v.append((info["adblue_g_s"][0], r[0]))
    env = UreaSCREnv(cycle="whsc", actuator="default")
    env.reset(seed=4)
    ref = []
    for a in actions[:, 0]:
        _, r, _, _, info = env.step(np.array([a], dtype=np.float32))
        ref.append((info["adblue_g_s"], r))
    np.testing.assert_allclose(np.array(v)[:, 0], np.array(ref)[:, 0], rtol=1e-12)
    kv = venv.episode_kpis()[0]
    ke = env.episode_kpis()
    assert kv["command_total_variation_g_s_per_h"] == pytest.approx(ke["command_total_variation_g_s_per_h"])
    assert kv["adblue_total_variation_g_s_per_h"] == pytest.approx(ke["adblue_total_variation_g_s_per_h"])


def test_chatter_kpi_is_the_total_variation_per_hour():
    env = UreaSCREnv(cycle="whtc", action_mode="physical", actuator="default")
    env.reset(seed=0)
    n = 400
    commands = np.where(np.arange(n) % 2 == 0, 0.2, 2.5)
    delivered = []
    for c in commands:
        _, _, _, _, info = env.step(np.array([c]))
        delivered.append(info["adblue_g_s"])
    k = env.episode_kpis()
    hours = n * 0.5 / 3600.0
    assert k["command_total_variation_g_s_per_h"] == pytest.approx(2.3 * (n - 1) / hours)
    assert k["adblue_total_variation_g_s_per_h"] == pytest.approx(np.abs(np.diff(delivered)).sum() / hours)
    assert k["adblue_total_variation_g_s_per_h"] < 0.5 * k["command_total_variation_g_s_per_h"]
    assert k["adblue_g"] == pytest.approx(np.sum(delivered) * 0.5)  # the KPIs count what is delivered


@pytest.mark.parametrize("bad", ["fast", 3, {"tau": 1.0}, {"time_constant_s": -1.0}, {"max_slew_g_s2": 0.0},
                                 {"time_constant_s": math.nan}])
def test_bad_actuator_settings_name_the_argument(bad):
    with pytest.raises(ValueError, match="actuator"):
        UreaSCREnv(cycle="whtc", actuator=bad)


def test_actuator_presets():
    assert actuator_params(None) is None and actuator_params(False) is None
    assert actuator_params("default") is DEFAULT_ACTUATOR and actuator_params(True) is DEFAULT_ACTUATOR
    assert actuator_params({"time_constant_s": 2.0}).time_constant_s == 2.0
    assert DEFAULT_ACTUATOR.lag_coefficient(0.5) == pytest.approx(1 - math.exp(-0.5))
    assert ActuatorParams(time_constant_s=0.0).lag_coefficient(0.5) == 1.0
