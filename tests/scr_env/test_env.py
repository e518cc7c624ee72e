"""The Gymnasium environment and its native vector version (issue: scr_env environment)."""
from __future__ import annotations

import re
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import scr_env
from scr_env.cycles import random_cycle
from scr_env.envs import UreaSCREnv, UreaSCRVectorEnv

ENV_ID = scr_env.ENV_ID


def _zero_dose(env: gym.Env) -> np.ndarray:
    return np.array([-1.0], dtype=np.float32)


def test_registered_and_checkers_pass_without_warnings() -> None:
    from stable_baselines3.common.env_checker import check_env as sb3_check_env

    env = gym.make(ENV_ID)
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
        sb3_check_env(gym.make(ENV_ID).unwrapped, warn=True)
    assert [str(x.message) for x in w] == []
    assert isinstance(gym.make("scr_env:scr_env/UreaSCR-v0").unwrapped, UreaSCREnv)


def _rollout(seed: int, n: int = 200, **kwargs) -> tuple[np.ndarray, np.ndarray]:
    env = gym.make(ENV_ID, **kwargs)
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(123)
    observations, rewards = [obs], []
    for _ in range(n):
        obs, r, _, _, _ = env.step(rng.uniform(-1, 1, size=1).astype(np.float32))
        observations.append(obs)
        rewards.append(r)
    return np.array(observations), np.array(rewards)


def test_determinism_same_seed_same_rollout() -> None:
    o1, r1 = _rollout(7)
    o2, r2 = _rollout(7)
    np.testing.assert_array_equal(o1, o2)
    np.testing.assert_array_equal(r1, r2)
    o3, _ = _rollout(8)
    assert not np.array_equal(o1, o3)  # sensor noise follows the seed


def test_whtc_episode_truncates_at_its_end_with_kpis_and_nitrogen_balance() -> None:
    env = gym.make(ENV_ID, cycle="whtc", dt=0.5)
    env.reset(seed=1)
    action = np.array([-0.6], dtype=np.float32)
    steps, terminated, truncated = 0, False, False
    while not (terminated or truncated):
        _, _, terminated, truncated, info = env.step(action)
        steps += 1
    assert (steps, terminated, truncated) == (3600, False, True)
    k = info["episode_kpis"]
    for key in ("nox_conversion", "engine_out_nox_g_per_kwh", "tailpipe_nox_g_per_kwh", "mean_nh3_slip_ppm",
                "peak_nh3_slip_ppm", "adblue_g", "engine_work_kwh"):
        assert np.isfinite(k[key]), key
    assert 0.0 < k["nox_conversion"] < 1.0
    assert k["tailpipe_nox_g_per_kwh"] < k["engine_out_nox_g_per_kwh"]
    expected_adblue_g = 0.5 * (float(action[0]) + 1.0) * 3.0 * 1800.0  # (a + 1) / 2 * 3 g/s over 1800 s
    assert k["adblue_g"] == pytest.approx(expected_adblue_g, rel=1e-12)
    assert abs(k["nitrogen_balance_error"]) < 1e-10  # measured 2e-13: closes to rounding by construction
    with pytest.raises(RuntimeError, match="reset"):
        env.step(action)


def test_step_before_reset_raises() -> None:
    env = UreaSCREnv()
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(1, dtype=np.float32))


@pytest.mark.parametrize("bad", [np.array([np.nan], dtype=np.float32), np.array([np.inf]), np.zeros(2),
                                 np.zeros((1, 1, 1)), "a lot"])
def test_bad_actions_raise_clear_errors(bad) -> None:
    env = UreaSCREnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match="action"):
        env.step(bad)


def test_out_of_range_actions_are_clipped_to_the_bounds() -> None:
    results = []
    for a in (5.0, 1.0, -7.0, -1.0):
        env = UreaSCREnv(sensor_noise=False)
        env.reset(seed=0)
        obs, r, _, _, info = env.step(np.array([a], dtype=np.float32))
        results.append((obs, r, info["adblue_g_s"]))
    assert results[0][2] == results[1][2] == 3.0
    assert results[2][2] == results[3][2] == 0.0
    np.testing.assert_array_equal(results[0][0], results[1][0])
    np.testing.assert_array_equal(results[2][0], results[3][0])
    assert results[0][0][4] == 1.0 and results[2][0][4] == -1.0  # the observed previous action is the clipped one


def test_physical_action_mode() -> None:
    env = UreaSCREnv(action_mode="physical", sensor_noise=False)
    assert env.action_space.low[0] == 0.0 and env.action_space.high[0] == pytest.approx(3.0)
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([1.5], dtype=np.float32))
    assert info["adblue_g_s"] == pytest.approx(1.5)


@pytest.mark.parametrize("kwargs, name", [
    ({"catalyst": "platinum"}, "catalyst"), ({"dt": 0.0}, "dt"), ({"dt": float("nan")}, "dt"),
    ({"cycle": "ftp75"}, "cycle"), ({"ageing": 2.0}, "ageing"), ({"action_mode": "volts"}, "action_mode"),
    ({"reward_weights": {"co2": 1.0}}, "reward_weights"), ({"randomize": -0.1}, "randomize"),
])
def test_bad_arguments_name_the_argument(kwargs, name) -> None:
    with pytest.raises(ValueError, match=name):
        UreaSCREnv(**kwargs)


def test_reward_terms_in_info_sum_to_reward() -> None:
    env = UreaSCREnv()
    env.reset(seed=0)
    for _ in range(50):
        _, r, _, _, info = env.step(np.array([0.2], dtype=np.float32))
        assert r == pytest.approx(info["nox_cost"] + info["nh3_cost"] + info["adblue_cost"])
        assert info["nox_cost"] <= 0 and info["nh3_cost"] <= 0 and info["adblue_cost"] <= 0


def test_optional_observations_and_privileged_state() -> None:
    env = UreaSCREnv(nh3_sensor=True, privileged=True)
    n_cells = env.config.catalyst.n_cells
    assert env.observation_space.shape == (5 + 1 + n_cells,)
    obs, _ = env.reset(seed=0, options={"initial_coverage": 0.3})
    np.testing.assert_allclose(obs[6:], 0.3, rtol=1e-6)
    assert env.observation_names[5] == "tailpipe_nh3_sensor_ppm"
    np.testing.assert_allclose(env.state["nh3_coverage"], 0.3)


def test_cold_start_starts_at_ambient() -> None:
    env = UreaSCREnv(cold_start=True)
    env.reset(seed=0)
    np.testing.assert_allclose(env.state["temperature_k"], 298.15)
    hot = UreaSCREnv()
    hot.reset(seed=0)
    assert hot.state["temperature_k"].min() > 450.0


def test_random_cycle_is_reproducible_from_the_cycle_seed() -> None:
    env = UreaSCREnv(cycle="random", random_cycle_duration_s=60.0)
    env.reset(seed=0, options={"cycle_seed": 5})
    a = env.trace.nox_ppm.copy()
    env.reset(seed=1, options={"cycle_seed": 5})
    np.testing.assert_array_equal(a, env.trace.nox_ppm)
    env.reset(seed=1, options={"cycle_seed": 6})
    assert not np.array_equal(a, env.trace.nox_ppm)
    assert env._n == 120


def test_ramped_mode_random_cycle_in_the_single_and_the_vector_env() -> None:
    """cycle="random_modes": each reset draws a seeded ramped-mode cycle (random_cycle(kind="ramped_modes")), the
    same trace for the same cycle_seed; the vector env keeps its own pool of them beside a transient "random" pool."""
    env = UreaSCREnv(cycle="random_modes", random_cycle_duration_s=120.0)
    env.reset(seed=0, options={"cycle_seed": 5})
    ref = random_cycle(120.0, seed=5, kind="ramped_modes")
    assert env.trace.name == "random-modes-5"
    np.testing.assert_array_equal(env.trace.scr_inlet_temperature_k, ref.scr_inlet_temperature_k)
    env.reset(seed=1)
    assert env.trace.name.startswith("random-modes-") and env._n == 240
    venv = UreaSCRVectorEnv(num_envs=2, cycle="random_modes", random_cycle_duration_s=60.0, random_cycle_pool=2)
    venv.reset(seed=0)
    names = {venv._traces[i].name for i in venv._env_trace}
    assert all(n.startswith("random-modes-") for n in names)
    obs, *_ = venv.step(np.full((2, 1), -0.5, dtype=np.float32))
    assert np.all(np.isfinite(obs))


def test_render_rgb_array() -> None:
    env = gym.make(ENV_ID, render_mode="rgb_array")
    env.reset(seed=0)
    for _ in range(20):
        env.step(np.array([0.0], dtype=np.float32))
    img = env.render()
    assert img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8 and img.std() > 0


# ---------------------------------------------------------------------------------------------------- vector env
def test_make_vec_uses_the_native_vector_env() -> None:
    venv = gym.make_vec(ENV_ID, num_envs=8, vectorization_mode="vector_entry_point")
    assert isinstance(venv.unwrapped, UreaSCRVectorEnv)
    obs, _ = venv.reset(seed=0)
    assert obs.shape == (8, 5)
    obs, r, te, tr, info = venv.step(np.zeros((8, 1), dtype=np.float32))
    assert obs.shape == (8, 5) and r.shape == (8,) and te.shape == (8,) and tr.shape == (8,)
    assert venv.observation_space.contains(obs)
    assert info["nox_cost"].shape == (8,)


def test_vector_env_matches_single_env_step_for_step() -> None:
    """The vector env runs the same kernel: without noise, plant i equals a single env on the same cycle."""
    n = 3
    venv = UreaSCRVectorEnv(num_envs=n, cycle=["whtc", "whsc", "whtc"], sensor_noise=False)
    venv.reset(seed=0)
    singles = [UreaSCREnv(cycle=c, sensor_noise=False) for c in ("whtc", "whsc", "whtc")]
    for e in singles:
        e.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(300):
        actions = rng.uniform(-1, 1, size=(n, 1)).astype(np.float32)
        vo, vr, _, _, _ = venv.step(actions)
        for i, e in enumerate(singles):
            so, sr, _, _, _ = e.step(actions[i])
            np.testing.assert_array_equal(vo[i], so)
            assert vr[i] == sr


def test_compiled_noise_draw_is_numpys() -> None:
    """The vector env draws its sensor noise in compiled code: same numbers and generator state as numpy."""
    from scr_env.envs.core import standard_normal_fill

    for seed in (0, 1, 12345):
        a, b = np.random.default_rng(seed), np.random.default_rng(seed)
        x, y = np.empty((97, 5)), np.empty((97, 5))
        for _ in range(20):
            a.standard_normal(out=x)
            standard_normal_fill(b, y)
            np.testing.assert_array_equal(x, y)
        assert a.bit_generator.state == b.bit_generator.state


def test_threading_chooser_runs_the_faster_variant_and_recovers_from_outliers() -> None:
    from scr_env.envs.core import _ThreadingChooser

    def run(chooser: _ThreadingChooser, seconds: dict[int, float], steps: int) -> list[int]:
        picks = []
        for _ in range(steps):
            mode = chooser.pick()
            chooser.record(mode, seconds[mode])
            picks.append(mode)
        return picks

    c = _ThreadingChooser()
    picks = run(c, {0: 2e-3, 1: 1e-3}, 4 + 2000)
    assert picks[:4] == [0, 0, 1, 1]  # each variant timed twice, serial first; the first (compilation) call ignored
    # then the faster one; the other re-timed after PROBE_EVERY steps, and after twice as many each time the choice
    # holds, up to MAX_PROBE_EVERY
    probes = [i for i, mode in enumerate(picks) if mode == 0][2:]
    assert probes[0] == 3 + c.PROBE_EVERY
    assert np.diff(probes).tolist() == [128, 256, 512, 512, 512]
    assert c.MAX_PROBE_EVERY == 512
    # one slow outlier of the threaded step: back on it at the next re-timing
    c = _ThreadingChooser()
    c.calls = [2, 2]
    c.mean_s = [2e-3, 50e-3]
    picks = run(c, {0: 2e-3, 1: 1e-3}, 2 * c.PROBE_EVERY)
    assert picks[c.PROBE_EVERY - 1:2 * c.PROBE_EVERY - 1] == [1] * c.PROBE_EVERY
    # the machine gets busy: the threaded step turns slow, the serial loop takes over within a few steps
    picks = run(c, {0: 2e-3, 1: 8e-3}, 10)
    assert picks[-5:] == [0] * 5
    # a re-timing that changes the choice starts the back-off again
    c = _ThreadingChooser()
    run(c, {0: 2e-3, 1: 1e-3}, 4 + 3 * c.PROBE_EVERY)
    assert c.probe_every == 4 * c.PROBE_EVERY
    picks = run(c, {0: 0.5e-3, 1: 1e-3}, 4 * c.PROBE_EVERY + 20)  # the serial loop turns faster: found at the next
    # re-timing (after 4 PROBE_EVERY steps), and run from then on
    assert c.best() == 0 and picks[-20:] == [0] * 20
    assert c.probe_every == c.PROBE_EVERY


def test_vector_env_threaded_and_serial_steps_agree_bitwise() -> None:
    """Large batches run the threaded or the serial compiled step, whichever is faster right now: same bits."""
    runs = []
    for mode in (0, 1):
        venv = UreaSCRVectorEnv(num_envs=80, cycle="whtc", random_offsets=True, randomize=0.2)
        venv.reset(seed=0)
        if venv._batch._chooser is None:  # NUMBA_NUM_THREADS=1: no chooser; the threaded step still runs
            from scr_env.envs.core import _ThreadingChooser

            venv._batch._chooser = _ThreadingChooser()
        venv._batch._chooser.pick = lambda mode=mode: mode
        rng = np.random.default_rng(0)
        trajectory = []
        for _ in range(60):
            obs, r, _, _, info = venv.step(rng.uniform(-1, 1, size=(80, 1)).astype(np.float32))
            trajectory += [obs, r, info["tailpipe_nh3_ppm"], venv.state["nh3_coverage"]]
        runs.append(trajectory)
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)


def test_vector_env_same_step_autoreset_reports_final_kpis() -> None:
    venv = UreaSCRVectorEnv(num_envs=4, cycle="random", random_cycle_duration_s=10.0, random_cycle_pool=3,
                            autoreset_mode="same_step")
    venv.reset(seed=0)
    for _ in range(20):
        obs, _, _, tr, info = venv.step(np.full((4, 1), -0.5, dtype=np.float32))
    assert tr.all()
    assert info["_final_obs"].all() and info["final_obs"][0].shape == (5,)
    kpis = info["final_info"]["episode_kpis"]
    assert kpis["nox_conversion"].shape == (4,) and np.all(np.isfinite(kpis["nox_conversion"]))
    assert np.all(np.abs(kpis["nitrogen_balance_error"]) < 1e-6)
    # the returned observation is the reset one: previous action back at -1 (no dosing)
    assert np.all(obs[:, 4] == -1.0)
    obs, _, _, tr, _ = venv.step(np.full((4, 1), -0.5, dtype=np.float32))
    assert not tr.any()


def test_vector_env_bad_actions() -> None:
    venv = UreaSCRVectorEnv(num_envs=2)
    venv.reset(seed=0)
    with pytest.raises(ValueError, match="actions"):
        venv.step(np.zeros((3, 1)))
    with pytest.raises(ValueError, match="actions"):
        venv.step(np.array([[0.0], [np.nan]]))
    with pytest.raises(ValueError, match="num_envs"):
        UreaSCRVectorEnv(num_envs=0)


def test_ppo_smoke_run() -> None:
    from stable_baselines3 import PPO

    env = gym.make(ENV_ID, cycle="random", random_cycle_duration_s=120.0)
    model = PPO("MlpPolicy", env, n_steps=256, batch_size=64, n_epochs=1, seed=0, device="cpu", verbose=0)
    model.learn(total_timesteps=1024)
    action, _ = model.predict(env.reset(seed=0)[0], deterministic=True)
    assert env.action_space.contains(action)


# ------------------------------------------------------------------------------------------------ input validation
FLAGS = ("sensor_noise", "nh3_sensor", "privileged", "cold_start")
NOT_BOOLS = ["no", "False", "", 1, 0, 1.0, None, [True]]


@pytest.mark.parametrize("name", FLAGS)
@pytest.mark.parametrize("value", NOT_BOOLS)
def test_flag_arguments_must_be_bools(name, value) -> None:
    """A string such as "no" used to count as True (bool("no")); now every flag names itself in a ValueError."""
    with pytest.raises(ValueError, match=rf"^{name} must be True or False"):
        gym.make(ENV_ID, **{name: value})
    with pytest.raises(ValueError, match=rf"^{name} must be True or False"):
        gym.make_vec(ENV_ID, num_envs=2, vectorization_mode="vector_entry_point", **{name: value})


@pytest.mark.parametrize("value", NOT_BOOLS)
def test_vector_random_offsets_must_be_a_bool(value) -> None:
    with pytest.raises(ValueError, match=r"^random_offsets must be True or False"):
        UreaSCRVectorEnv(num_envs=2, random_offsets=value)


def test_numpy_bools_are_accepted_as_flags() -> None:
    env = UreaSCREnv(nh3_sensor=np.True_, privileged=np.False_, cold_start=np.bool_(False))
    assert env.config.nh3_sensor is True and env.config.privileged is False and env.config.cold_start is False
    assert env.observation_space.shape == (6,)
    assert UreaSCRVectorEnv(num_envs=2, random_offsets=np.True_).random_offsets is True


@pytest.mark.parametrize("kwargs, name", [
    ({"dt": "0.5"}, "dt"), ({"ageing": True}, "ageing"), ({"randomize": None}, "randomize"),
    ({"initial_coverage": "0.2"}, "initial_coverage"), ({"random_cycle_duration_s": "60"}, "random_cycle_duration_s"),
    ({"reward_weights": {"nox": True}}, "reward_weights.nox"),
])
def test_numeric_arguments_are_not_coerced_from_strings_or_bools(kwargs, name) -> None:
    with pytest.raises(ValueError, match=rf"^{re.escape(name)} must be"):
        UreaSCREnv(**kwargs)


def test_numeric_arguments_accept_numpy_numbers() -> None:
    env = UreaSCREnv(dt=np.float32(0.5), ageing=np.int64(0), initial_coverage=np.array(0.25))
    assert env.dt == 0.5 and env.config.initial_coverage == 0.25


@pytest.mark.parametrize("options, match", [
    ({"cold_start": "no"}, r"options\['cold_start'\] must be True or False"),
    ({"cold_start": 1}, r"options\['cold_start'\] must be True or False"),
    ({"cold_start": None}, r"options\['cold_start'\] must be True or False"),
    ({"initial_coverage": "x"}, r"options\['initial_coverage'\] must be a number"),
    ({"initial_coverage": None}, r"options\['initial_coverage'\] must be a number"),
    ({"initial_coverage": True}, r"options\['initial_coverage'\] must be a number"),
    ({"initial_coverage": 1.5}, r"options\['initial_coverage'\] must be a finite number in \[0.0, 1.0\]"),
    ({"initial_coverage": float("nan")}, r"options\['initial_coverage'\]"),
    ([1], r"^options must be None or a dict"),
    ("cold_start", r"^options must be None or a dict"),
    ({"coldstart": True}, r"^options has unknown key\(s\) 'coldstart'"),
    ({"cycle_seed": 3}, r"options\['cycle_seed'\] applies to a random cycle \('random', 'random_modes'\) only"),
])
def test_reset_options_errors_name_the_option(options, match) -> None:
    env = UreaSCREnv()
    with pytest.raises(ValueError, match=match):
        env.reset(seed=0, options=options)


def test_reset_option_cold_start_takes_bools() -> None:
    env = UreaSCREnv()
    env.reset(seed=0, options={"cold_start": np.True_})
    np.testing.assert_allclose(env.state["temperature_k"], 298.15)
    env.reset(seed=0, options={"cold_start": False})
    assert env.state["temperature_k"].min() > 450.0


@pytest.mark.parametrize("seed", ["a", 1.7, 2.0, -1, True, [3]])
def test_cycle_seed_must_be_a_non_negative_integer(seed) -> None:
    env = UreaSCREnv(cycle="random", random_cycle_duration_s=60.0)
    with pytest.raises(ValueError, match=r"options\['cycle_seed'\] must be a non-negative integer"):
        env.reset(seed=0, options={"cycle_seed": seed})


def test_cycle_seed_accepts_numpy_integers_and_none_means_drawn() -> None:
    env = UreaSCREnv(cycle="random", random_cycle_duration_s=60.0)
    env.reset(seed=0, options={"cycle_seed": np.int64(5)})
    a = env.trace.nox_ppm.copy()
    env.reset(seed=0, options={"cycle_seed": 5})
    np.testing.assert_array_equal(a, env.trace.nox_ppm)
    env.reset(seed=0, options={"cycle_seed": None})
    b = env.trace.nox_ppm.copy()
    env.reset(seed=0)
    np.testing.assert_array_equal(b, env.trace.nox_ppm)
    UreaSCREnv().reset(seed=0, options={"cycle_seed": None})  # None is "no seed" on any cycle


def test_a_failed_reset_changes_nothing() -> None:
    env = UreaSCREnv()
    env.reset(seed=0)
    action = np.array([0.1], dtype=np.float32)
    for _ in range(5):
        env.step(action)
    rng_state = env.np_random.bit_generator.state
    state = env.state
    with pytest.raises(ValueError, match="initial_coverage"):
        env.reset(seed=123, options={"initial_coverage": "x"})
    assert env.np_random.bit_generator.state == rng_state and env.step_index == 5
    np.testing.assert_array_equal(env.state["nh3_coverage"], state["nh3_coverage"])
    env.step(action)  # the episode goes on
    assert env.step_index == 6


@pytest.mark.parametrize("bad", [None, np.array([0.5 + 1j]), 0.5 + 0j, np.array([True]), True, np.array(["0.5"]),
                                 np.array([0.5], dtype=object), "0.5"])
def test_non_real_actions_raise_naming_the_action(bad) -> None:
    env = UreaSCREnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"^action must be a real number or an array of shape \(1,\)"):
        env.step(bad)
    assert env.step_index == 0


def test_int_and_other_real_actions_step_as_their_float_value() -> None:
    runs = []
    for action in (np.array([1.0]), 1, np.array([1], dtype=np.int32), [1.0], np.float16(1.0), np.array(1.0)):
        env = UreaSCREnv(sensor_noise=False)
        env.reset(seed=0)
        runs.append(env.step(action)[0])
    for obs in runs[1:]:
        np.testing.assert_array_equal(obs, runs[0])


@pytest.mark.parametrize("horizon", [-1, 10**9, 2.0, True, "3", None])
def test_disturbance_preview_rejects_bad_horizons(horizon) -> None:
    env = UreaSCREnv()
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"^horizon must be"):
        env.disturbance_preview(horizon)


def test_disturbance_preview_horizons() -> None:
    with pytest.raises(RuntimeError, match="reset"):
        UreaSCREnv().disturbance_preview(3)
    env = UreaSCREnv(cycle="random", random_cycle_duration_s=10.0)  # 20 steps
    env.reset(seed=0)
    assert env.disturbance_preview(0).shape == (0, 4)
    prev = env.disturbance_preview(np.int64(100))  # past the end of the cycle: its last row repeated
    assert prev.shape == (100, 4)
    np.testing.assert_array_equal(prev[19:], np.repeat(prev[19:20], 81, axis=0))
    from scr_env.envs.urea_scr import MAX_PREVIEW_STEPS

    assert env.disturbance_preview(MAX_PREVIEW_STEPS).shape == (MAX_PREVIEW_STEPS, 4)
    with pytest.raises(ValueError, match="horizon"):
        env.disturbance_preview(MAX_PREVIEW_STEPS + 1)


def _trace_with_flow(flow_mol_s: float, n: int = 40) -> scr_env.ExhaustTrace:
    ones = np.ones(n)
    return scr_env.ExhaustTrace(
        name="big", dt=0.5, time_s=np.arange(n) * 0.5, engine_speed_rpm=0 * ones, engine_torque_nm=0 * ones,
        engine_power_kw=0 * ones, exhaust_mass_flow_kg_s=flow_mol_s * 0.0289 * ones,
        exhaust_flow_mol_s=flow_mol_s * ones, scr_inlet_temperature_k=550.0 * ones, nox_ppm=400.0 * ones,
        no2_fraction=0.3 * ones)


def test_flow_above_the_observation_bound_is_clipped_in_the_observation_only() -> None:
    """Documented: a reading beyond its range saturates in the observation; the physics uses the real flow."""
    assert UreaSCREnv().observation_space.high[2] == 100.0
    tailpipe = {}
    for flow in (100.0, 150.0):
        env = UreaSCREnv(cycle=_trace_with_flow(flow), sensor_noise=False)
        obs, _ = env.reset(seed=0)
        assert obs[2] == 100.0 and env.observation_space.contains(obs)
        for _ in range(10):
            obs, _, _, _, info = env.step(np.array([0.0], dtype=np.float32))
        assert obs[2] == 100.0 and env.observation_space.contains(obs)
        tailpipe[flow] = info["tailpipe_nox_ppm"]
    assert tailpipe[150.0] > tailpipe[100.0]  # less residence time at the real, higher flow: more NOx slips


def test_shipped_cycles_stay_inside_the_observed_flow_range() -> None:
    from scr_env.cycles import load_cycle, random_cycle

    traces = [load_cycle(c, cold_start=cold) for c in ("whtc", "whsc") for cold in (False, True)]
    traces += [random_cycle(1800.0, seed) for seed in range(5)]
    assert max(t.exhaust_flow_mol_s.max() for t in traces) < 25.0  # bound 100 mol/s; 2 % sensor noise


# ------------------------------------------------------------------------------------- vector env input validation
def test_vector_reset_mask_must_be_a_boolean_array_of_num_envs() -> None:
    venv = UreaSCRVectorEnv(num_envs=6)
    venv.reset(seed=0)
    for bad in ([0, 2, 5], [0, 1, 0, 1, 0, 1], np.ones(6, dtype=np.int8), np.ones(5, dtype=bool),
                np.ones((6, 1), dtype=bool), "all", [[1], [1, 2]]):
        with pytest.raises(ValueError, match=r"options\['reset_mask'\] must be a boolean array of shape \(6,\)"):
            venv.reset(options={"reset_mask": bad})


def test_vector_reset_mask_resets_exactly_the_masked_envs() -> None:
    venv = UreaSCRVectorEnv(num_envs=6)
    venv.reset(seed=0)
    for _ in range(5):
        venv.step(np.full((6, 1), 0.5, dtype=np.float32))
    mask = np.isin(np.arange(6), [0, 2, 5])
    obs, _ = venv.reset(options={"reset_mask": mask})
    np.testing.assert_array_equal(obs[:, 4], np.where(mask, -1.0, 0.5))  # previous action: -1 after a reset
    _, _, _, _, info = venv.step(np.full((6, 1), 0.5, dtype=np.float32))
    np.testing.assert_array_equal(info["step_index"], np.where(mask, 1, 6))
    obs, _ = venv.reset(options={"reset_mask": [True] * 6})  # a list of bools is a boolean array
    assert np.all(obs[:, 4] == -1.0)


def test_vector_partial_reset_mask_needs_started_envs_and_no_seed() -> None:
    partial = np.array([True, False, True])
    venv = UreaSCRVectorEnv(num_envs=3, cycle="random", random_cycle_duration_s=20.0)
    with pytest.raises(ValueError, match=r"options\['reset_mask'\] must select every env on the first reset"):
        venv.reset(seed=0, options={"reset_mask": partial})
    venv.reset(seed=0)
    with pytest.raises(ValueError, match=r"options\['reset_mask'\].*seed"):
        venv.reset(seed=1, options={"reset_mask": partial})
    venv.reset(options={"reset_mask": partial})
    venv.reset(seed=1, options={"reset_mask": np.ones(3, dtype=bool)})


@pytest.mark.parametrize("options, match", [
    ({"initial_coverage": "x"}, r"options\['initial_coverage'\] must be a number"),
    ({"initial_coverage": None}, r"options\['initial_coverage'\] must be a number"),
    ({"initial_coverage": -0.5}, r"options\['initial_coverage'\]"),
    ([1], r"^options must be None or a dict"),
    ({"cold_start": True}, r"^options has unknown key\(s\) 'cold_start'"),
])
def test_vector_reset_options_errors_name_the_option(options, match) -> None:
    venv = UreaSCRVectorEnv(num_envs=2)
    with pytest.raises(ValueError, match=match):
        venv.reset(seed=0, options=options)


@pytest.mark.parametrize("bad", [np.full((2, 1), 0.5 + 0j), np.ones((2, 1), dtype=bool), None, [["a"], ["b"]],
                                 np.array([[0.5], [None]], dtype=object)])
def test_vector_non_real_actions_raise(bad) -> None:
    venv = UreaSCRVectorEnv(num_envs=2)
    venv.reset(seed=0)
    with pytest.raises(ValueError, match=r"^actions must be real numbers"):
        venv.step(bad)


def test_vector_int_actions_step_as_floats() -> None:
    runs = []
    for actions in (np.zeros((2, 1)), np.zeros((2, 1), dtype=np.int64), [0, 0]):
        venv = UreaSCRVectorEnv(num_envs=2, sensor_noise=False)
        venv.reset(seed=0)
        runs.append(venv.step(actions)[0])
    np.testing.assert_array_equal(runs[0], runs[1])
    np.testing.assert_array_equal(runs[0], runs[2])
