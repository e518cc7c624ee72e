"""The public API after ``import scr_env`` and the Gymnasium / stable-baselines3 conventions of the environments."""
from __future__ import annotations

import subprocess
import sys
import textwrap
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import scr_env
from scr_env import ENV_ID
from scr_env.envs import UreaSCREnv, UreaSCRVectorEnv
from scr_env.wrappers import RecordEpisodeKPIs

SINGLE = {"cycle": "random", "random_cycle_duration_s": 10.0}  # 20 steps per episode
SHORT = {**SINGLE, "random_cycle_pool": 3}


# ----------------------------------------------------------------------------------------------------- public API
def test_submodules_are_attributes_after_import_scr_env() -> None:
    """README calls such as scr_env.lab.steady_state(...) work after a bare `import scr_env` (fresh process)."""
    code = textwrap.dedent("""
        import scr_env
        r = scr_env.lab.steady_state("cu_zeolite", temperature_c=250.0, no_ppm=300.0, nh3_ppm=300.0)
        assert 0.8 < r["nox_conversion"] < 1.0
        assert callable(scr_env.rollout.rollout) and callable(scr_env.casadi_model.catalyst_step)
        assert scr_env.wrappers.RecordEpisodeKPIs and scr_env.envs.UreaSCRVectorEnv and scr_env.startup.precompile
        for name in ("cycles", "engine", "params", "physics", "constants", "jit", "installation"):
            getattr(scr_env, name)
        assert "lab" in dir(scr_env)
        try:
            scr_env.no_such_module
        except AttributeError as e:
            assert "no_such_module" in str(e)
        else:
            raise AssertionError("no AttributeError")
    """)
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)


# ----------------------------------------------------------------------------------------------- python-control
def test_control_package_is_ours() -> None:
    from scr_env.installation import check_control_package

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert check_control_package(strict=True)


def test_python_control_over_ours_is_named_with_the_fix(tmp_path) -> None:
    """python-control installed over this project's `control`: import scr_env warns, import experiments raises, both
    naming python-control and the fix (a stand-in `control` package first on the path)."""
    fake = tmp_path / "control"
    fake.mkdir()
    (fake / "__init__.py").write_text('"""The Python Control Systems Library."""\n__version__ = "0.10.1"\n')
    code = textwrap.dedent("""
        import warnings
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            import scr_env
        msgs = [str(x.message) for x in w if x.category.__name__ == "ControlPackageShadowedWarning"]
        assert len(msgs) == 1 and "python-control" in msgs[0] and "pip uninstall control" in msgs[0], msgs
        try:
            import experiments
        except ImportError as e:
            assert "python-control" in str(e) and "separate virtual environment" in str(e)
        else:
            raise AssertionError("import experiments did not raise")
    """)
    import os

    root = os.path.dirname(os.path.dirname(scr_env.__file__))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), root])}
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300, env=env, cwd=tmp_path)


# ------------------------------------------------------------------------------------------------ episode KPIs
def test_episode_kpis_on_truncation_by_time_limit() -> None:
    env = RecordEpisodeKPIs(gym.make(ENV_ID, cycle="whtc", max_episode_steps=50))
    env.reset(seed=0)
    for k in range(50):
        _, _, terminated, truncated, info = env.step(np.array([-0.5], dtype=np.float32))
        assert truncated == (k == 49) and not terminated
    kpis = info["episode_kpis"]
    assert kpis["duration_s"] == pytest.approx(25.0) and np.isfinite(kpis["tailpipe_nox_g_per_kwh"])
    assert abs(kpis["nitrogen_balance_error"]) < 1e-9
    np.testing.assert_equal(kpis, env.unwrapped.episode_kpis())  # the method, after the early end


def test_episode_kpis_method_equals_the_end_of_cycle_kpis() -> None:
    env = UreaSCREnv(**SINGLE)
    env.reset(seed=1)
    with pytest.raises(RuntimeError, match="reset"):
        UreaSCREnv().episode_kpis()
    assert env.episode_kpis()["duration_s"] == 0.0  # before the first step: an empty episode, no error
    truncated = False
    while not truncated:
        _, _, _, truncated, info = env.step(np.array([0.0], dtype=np.float32))
    np.testing.assert_equal(env.episode_kpis(), info["episode_kpis"])  # NaN g/kWh: no positive work
    # the wrapper leaves the environment's own KPIs alone
    wrapped = RecordEpisodeKPIs(gym.make(ENV_ID, **SINGLE))
    wrapped.reset(seed=1)
    truncated = False
    while not truncated:
        _, _, _, truncated, info2 = wrapped.step(np.array([0.0], dtype=np.float32))
    np.testing.assert_equal(info2["episode_kpis"], info["episode_kpis"])
    with pytest.raises(TypeError, match="episode_kpis"):
        RecordEpisodeKPIs(gym.make("Pendulum-v1"))


def test_vector_env_max_episode_steps_and_episode_kpis() -> None:
    venv = gym.make_vec(ENV_ID, num_envs=3, vectorization_mode="vector_entry_point", cycle="whtc",
                        max_episode_steps=30)
    venv.reset(seed=0)
    for k in range(30):
        _, _, _, truncated, info = venv.step(np.zeros((3, 1), dtype=np.float32))
        assert truncated.all() == (k == 29)
    kpis = info["episode_kpis"]
    assert info["_episode_kpis"].all() and np.allclose(kpis["duration_s"], 15.0)
    per_plant = venv.unwrapped.episode_kpis()
    assert len(per_plant) == 3 and per_plant[1]["tailpipe_nox_g"] == kpis["tailpipe_nox_g"][1]
    with pytest.raises(ValueError, match="max_episode_steps"):
        UreaSCRVectorEnv(num_envs=2, max_episode_steps=0)


# ------------------------------------------------------------------------------------------- vector autoreset
def _run(venv, steps: int, action: float = -0.5) -> list:
    rows = []
    n = venv.num_envs
    for _ in range(steps):
        rows.append(venv.step(np.full((n, 1), action, dtype=np.float32)))
    return rows


def test_vector_env_next_step_autoreset_is_the_default() -> None:
    venv = UreaSCRVectorEnv(num_envs=4, **SHORT)
    assert venv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    venv.reset(seed=0)
    rows = _run(venv, 21)
    obs, rew, term, trunc, info = rows[19]  # 20th step: every episode ends, the last observation returned
    assert trunc.all() and not term.any()
    assert np.all(obs[:, 4] > -1.0)  # previous action -0.5, not the reset observation's -1
    assert info["_episode_kpis"].all() and np.all(np.isfinite(info["episode_kpis"]["nox_conversion"]))
    assert "final_obs" not in info
    obs, rew, term, trunc, info = rows[20]  # next step: the reset, action ignored, reward 0
    assert np.all(obs[:, 4] == -1.0) and np.all(rew == 0.0) and not trunc.any() and not term.any()
    assert info["_cycle"].all() and not info["_nox_cost"].any()
    assert np.all(info["step_index"] == 0)
    obs, rew, _, trunc, info = _run(venv, 1)[0]  # and then the new episodes step
    assert np.all(info["step_index"] == 1) and np.all(rew < 0)


def test_vector_env_next_step_resets_only_the_ended_plants() -> None:
    venv = UreaSCRVectorEnv(num_envs=5, cycle="whtc", random_offsets=True)
    venv.reset(seed=2)
    lengths = venv._len.copy()
    first = int(lengths.min())
    rows = _run(venv, first + 1)
    _, _, _, trunc, _ = rows[first - 1]
    ended = lengths == first
    np.testing.assert_array_equal(trunc, ended)
    _, rew, _, trunc, info = rows[first]
    np.testing.assert_array_equal(rew == 0.0, ended)
    np.testing.assert_array_equal(info["_nox_cost"], ~ended)
    np.testing.assert_array_equal(info["step_index"][~ended], first + 1)


def test_same_and_next_step_modes_simulate_the_same_episodes() -> None:
    """The modes differ only in when the reset is returned: the physics of every episode is the same."""
    same = UreaSCRVectorEnv(num_envs=2, autoreset_mode="same_step", sensor_noise=False, **SHORT)
    nxt = UreaSCRVectorEnv(num_envs=2, autoreset_mode=AutoresetMode.NEXT_STEP, sensor_noise=False, **SHORT)
    same.reset(seed=4)
    nxt.reset(seed=4)
    a = _run(same, 20)
    b = _run(nxt, 20)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x[1], y[1])  # rewards of the first episodes
    np.testing.assert_array_equal(a[-1][4]["final_info"]["episode_kpis"]["tailpipe_nox_g"],
                                  b[-1][4]["episode_kpis"]["tailpipe_nox_g"])


@pytest.mark.parametrize("value", ["disabled", "sometimes", 3, None])
def test_autoreset_mode_choices(value) -> None:
    with pytest.raises(ValueError, match="autoreset_mode"):
        UreaSCRVectorEnv(num_envs=2, autoreset_mode=value)
    assert UreaSCRVectorEnv(num_envs=2, autoreset_mode="SAME_STEP").metadata["autoreset_mode"] == \
        AutoresetMode.SAME_STEP
    assert UreaSCRVectorEnv.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP  # the class default untouched


def test_gymnasium_vector_wrappers_work() -> None:
    from gymnasium.wrappers.vector import NormalizeObservation, RecordEpisodeStatistics, TransformObservation

    venv = gym.make_vec(ENV_ID, num_envs=4, vectorization_mode="vector_entry_point", **SHORT)
    venv = TransformObservation(venv, lambda o: o * np.float32(0.5), venv.observation_space)
    venv = RecordEpisodeStatistics(NormalizeObservation(venv))
    obs, _ = venv.reset(seed=0)
    episodes = 0
    for _ in range(45):
        obs, _, _, _, info = venv.step(np.zeros((4, 1), dtype=np.float32))
        assert np.all(np.isfinite(obs))
        if "episode" in info:
            episodes += int(info["_episode"].sum())
            assert np.all(info["episode"]["l"][info["_episode"]] == 20)
    assert episodes == 8


# ------------------------------------------------------------------------------------------ stable-baselines3
def test_raw_vector_env_in_sb3_names_the_adapter() -> None:
    from stable_baselines3 import PPO

    venv = gym.make_vec(ENV_ID, num_envs=2, vectorization_mode="vector_entry_point", **SHORT)
    with pytest.raises(TypeError, match="GymVectorToSB3.*make_sb3_vec_env"):
        PPO("MlpPolicy", venv, n_steps=32, batch_size=32, device="cpu")
    # the guard answers only for Gymnasium vector environments: SB3's own check of a single env is unchanged
    from stable_baselines3.common.vec_env import VecEnv

    assert not isinstance(gym.make(ENV_ID), VecEnv)


def test_sb3_adapter_takes_a_same_step_env_and_explains_next_step() -> None:
    from control.rl.vec_env import GymVectorToSB3, make_sb3_vec_env

    sb3 = make_sb3_vec_env(2, **SHORT)
    assert sb3.venv.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    sb3.reset()
    with pytest.raises(ValueError, match="autoreset_mode='same_step'"):
        GymVectorToSB3(gym.make_vec(ENV_ID, num_envs=2, vectorization_mode="vector_entry_point"))
