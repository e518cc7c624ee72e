"""control.rl: the SB3 adapter of the native vector env, the observation pipeline, the surrogate environment,
saving/loading policies and a short training smoke test."""
from __future__ import annotations

import json
import time

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from control.rl import available_policies, load_policy
from control.rl.pipeline import FEATURES, ObservationPipeline, PipelineConfig, PipelineVecEnv
from control.rl.vec_env import GymVectorToSB3, make_sb3_vec_env
from scr_env.envs.core import OBS_BASE

SHORT = {"cycle": "random", "random_cycle_duration_s": 20.0}  # 40 steps per episode


@pytest.fixture(scope="module")
def torch_one_thread():
    import torch

    torch.set_num_threads(1)


# ------------------------------------------------------------------------------------------------ adapter
def test_adapter_follows_sb3_vecenv_semantics():
    venv = make_sb3_vec_env(3, **SHORT, random_offsets=True)
    venv.seed(1)
    obs = venv.reset()
    assert obs.shape == (3, 5) and obs.dtype == np.float32
    assert venv.observation_space.shape == (5,) and venv.action_space.shape == (1,)
    ended = np.zeros(3, dtype=bool)
    for _ in range(60):
        obs, rewards, dones, infos = venv.step(np.zeros((3, 1), dtype=np.float32))
        assert obs.shape == (3, 5) and rewards.shape == (3,) and dones.dtype == bool and len(infos) == 3
        assert np.all(rewards <= 0)
        for i in np.flatnonzero(dones):
            info = infos[i]
            # SAME_STEP autoreset: obs is the reset observation; the last one is the terminal observation
            assert info["terminal_observation"].shape == (5,)
            assert info["TimeLimit.truncated"] is True  # cycle end = truncation, bootstrapped by SB3
            assert set(info["episode_kpis"]) >= {"tailpipe_nox_g_per_kwh", "mean_nh3_slip_ppm"}
            assert obs[i, 4] == -1.0  # a fresh episode starts with no previous dose
            assert not np.array_equal(info["terminal_observation"], obs[i])
        for i in np.flatnonzero(~dones):
            assert "terminal_observation" not in infos[i]
        ended |= dones
    assert ended.all()
    assert venv.get_attr("observation_names") == [tuple(OBS_BASE)] * 3
    assert venv.env_is_wrapped(object) == [False] * 3
    venv.close()


def test_adapter_rejects_next_step_autoreset():
    import gymnasium as gym

    venv = gym.make_vec("Pendulum-v1", num_envs=2, vectorization_mode="sync")
    with pytest.raises(ValueError, match="SAME_STEP"):
        GymVectorToSB3(venv)


def test_adapter_seeding_is_deterministic():
    def run(seed: int) -> np.ndarray:
        venv = make_sb3_vec_env(2, **SHORT)
        venv.seed(seed)
        out = [venv.reset()]
        for _ in range(10):
            out.append(venv.step(np.full((2, 1), 0.1, dtype=np.float32))[0])
        return np.concatenate(out)

    np.testing.assert_array_equal(run(3), run(3))
    assert not np.array_equal(run(3), run(4))


# ------------------------------------------------------------------------------------------------ pipeline
def test_pipeline_history_and_restart():
    cfg = PipelineConfig(n_stack=3, use_tailpipe_sensor=True)
    p = ObservationPipeline(cfg, num_envs=2)
    o0 = np.array([[500.0, 550.0, 5.0, 100.0, -1.0], [200.0, 500.0, 3.0, 50.0, -1.0]])
    p.start(o0)
    out = p.output().reshape(2, 3, cfg.n_features)
    assert np.allclose(out[:, 0], out[:, 2])  # history filled with the first observation
    o1 = o0.copy()
    o1[:, 0] += 100.0
    p.advance(o1)
    out = p.output().reshape(2, 3, cfg.n_features)
    assert np.allclose(out[:, -1, :5], o1) and np.allclose(out[:, -2, :5], o0)
    # stoichiometric AdBlue = NOx * 1e-6 * flow / 0.0108 mol/g
    assert out[0, -1, 5] == pytest.approx(600e-6 * 5.0 / 0.010822, rel=1e-3)
    p.start(o0, mask=np.array([True, False]))
    out2 = p.output().reshape(2, 3, cfg.n_features)
    assert np.allclose(out2[0, :, :5], o0[0]) and np.allclose(out2[1], out[1])
    with pytest.raises(ValueError, match="shape"):
        p.advance(np.zeros((2, 6)))
    assert len(cfg.output_names) == cfg.output_size == 3 * cfg.n_features == 3 * (len(FEATURES) - 1)


def test_anr_action_doses_on_the_feedforward():
    cfg = PipelineConfig(action="anr", max_anr=2.0)
    p = ObservationPipeline(cfg, num_envs=3)
    obs = np.array([[500.0, 550.0, 5.0, 0.0, -1.0], [100.0, 500.0, 2.0, 0.0, -1.0], [3000.0, 600.0, 20.0, 0.0, -1.0]])
    p.start(obs)
    stoich = obs[:, 0] * 1e-6 * obs[:, 2] / 0.010822  # g/s AdBlue at ANR 1
    env_a = p.to_env_action(np.array([[0.0], [-1.0], [1.0]]))
    rate = (env_a[:, 0] + 1.0) / 2.0 * 3.0
    assert rate[0] == pytest.approx(stoich[0], rel=1e-3)  # action 0 = ANR 1
    assert rate[1] == pytest.approx(0.0, abs=1e-6)  # action -1 = ANR 0
    assert rate[2] == pytest.approx(3.0)  # ANR 2 on a large NOx flow: clipped to the injector limit
    assert PipelineConfig().features == tuple(f for f in FEATURES if "sensor" not in f and "long" not in f)
    assert PipelineConfig(long_surplus_time_constant_s=600.0).features[-1] == "nh3_surplus_long_ema_g_s"
    with pytest.raises(ValueError, match="action"):
        PipelineConfig(action="ppm")


def test_pipeline_vec_env_stacks_terminal_observation():
    cfg = PipelineConfig(n_stack=2)
    nf = cfg.n_features
    assert "tailpipe_nox_sensor_ppm" not in cfg.features  # the default pipeline is feed-forward with memory
    venv = PipelineVecEnv(make_sb3_vec_env(2, **SHORT), cfg)
    venv.seed(0)
    obs = venv.reset()
    assert obs.shape == (2, 2 * nf)
    for _ in range(41):
        obs, _, dones, infos = venv.step(np.zeros((2, 1), dtype=np.float32))
        if dones.any():
            i = int(np.flatnonzero(dones)[0])
            term = infos[i]["terminal_observation"].reshape(2, nf)
            new = obs[i].reshape(2, nf)
            assert np.allclose(new[0], new[1])  # restarted
            assert not np.allclose(term[1], new[1])
            return
    pytest.fail("no episode ended")


# ------------------------------------------------------------------------------------------------ training
def test_training_smoke_save_load_and_evaluate(tmp_path, torch_one_thread):
    from control.evaluation import evaluate
    from control.rl.training import train

    t0 = time.perf_counter()
    res = train("ppo", 2048, seed=0, num_envs=2, out=None, env_kwargs={"random_cycle_duration_s": 60.0},
                pipeline=PipelineConfig(action="anr"), progress_bar=False,
                hyperparameters={"n_steps": 256, "batch_size": 128, "n_epochs": 2})
    path = res.save(tmp_path, "ppo_smoke")
    assert time.perf_counter() - t0 < 60.0
    meta = json.loads(path.read_text())
    assert meta["observation_names"] == list(OBS_BASE) and meta["timesteps"] >= 2048
    assert {"stable_baselines3", "torch"} <= set(meta["versions"]) and meta["wall_time_s"] > 0
    with np.load(tmp_path / "ppo_smoke_vecnormalize.npz", allow_pickle=False) as z:
        assert z["mean"].shape == (PipelineConfig().output_size,)
    policy = load_policy(path)
    obs = np.array([500.0, 550.0, 5.0, 100.0, -1.0], dtype=np.float32)
    action, state = policy.predict(obs, episode_start=np.array([True]))
    assert action.shape == (1,) and -1.0 <= action[0] <= 1.0 and state is None
    # the loaded policy applies the normaliser itself: same action as the model on the normalised pipeline output
    pipe = ObservationPipeline(PipelineConfig(action="anr"), 1)
    pipe.start(obs[None])
    x = res.vec_normalize.normalize_obs(pipe.output())
    ref, _ = res.model.predict(x, deterministic=True)
    np.testing.assert_allclose(action, pipe.to_env_action(ref)[0], atol=1e-6)
    results = evaluate(policy, cycles=("whtc",), seeds=(0,), max_steps=20, name="ppo")
    assert results[0].timing["policy_time_ms_median"] < 20.0


def test_different_observation_layout_fails_clearly(tmp_path, torch_one_thread):
    from control.rl.training import train
    from scr_env.envs.urea_scr import UreaSCREnv

    res = train("ppo", 64, num_envs=1, env_kwargs={"random_cycle_duration_s": 20.0}, progress_bar=False,
                hyperparameters={"n_steps": 32, "batch_size": 32, "n_epochs": 1})
    path = res.save(tmp_path, "tiny")
    with pytest.raises(ValueError, match="trained on observations"):
        load_policy(path, observation_names=tuple(OBS_BASE) + ("tailpipe_nh3_sensor_ppm",))
    policy = load_policy(path, observation_names=tuple(OBS_BASE))
    with pytest.raises(ValueError, match="trained on observations"):
        policy.attach(UreaSCREnv(cycle="whtc", nh3_sensor=True))
    with pytest.raises(ValueError, match="observation must have 5 entries"):
        policy.predict(np.zeros(6, dtype=np.float32))
    meta = json.loads(path.read_text())
    meta["observation_names"] = meta["observation_names"] + ["nh3_coverage_cell0"]
    path.write_text(json.dumps(meta))
    with pytest.raises(ValueError, match="trained on observations"):
        load_policy(path)
    with pytest.raises(ValueError, match="no policy"):
        load_policy("no_such_policy")


@pytest.mark.parametrize("name", ["ppo", "sac"])
def test_shipped_policies_load_in_one_line(name):
    if name not in available_policies():
        pytest.skip(f"{name} not shipped yet")
    policy = load_policy(name)
    meta = policy.metadata
    assert meta["observation_names"] == list(OBS_BASE)
    for key in ("command", "seed", "timesteps", "wall_time_s", "versions", "env_kwargs", "pipeline"):
        assert key in meta
    action, _ = policy.predict(np.array([500.0, 550.0, 5.0, 100.0, -1.0], dtype=np.float32),
                               episode_start=np.array([True]))
    assert action.shape == (1,) and np.isfinite(action).all()


# ------------------------------------------------------------------------------------------------ observation checks
class _SumModel:
    """A stand-in SB3 model whose action depends on the whole (normalised) pipeline output: any change of the
    pipeline state changes the action."""

    def predict(self, x, deterministic=True):
        return np.tanh(0.01 * np.asarray(x, dtype=np.float64).sum(axis=1, keepdims=True)).astype(np.float32), None


def _toy_policy():
    from control.rl.policy import RLPolicy

    cfg = PipelineConfig(long_surplus_time_constant_s=600.0)
    return RLPolicy(_SumModel(), cfg, np.zeros(cfg.output_size), np.ones(cfg.output_size), name="toy")


def _observations(n=30, seed=0):
    rng = np.random.default_rng(seed)
    obs = np.column_stack([400 + 300 * rng.random(n), np.linspace(540, 600, n), 5 + 3 * rng.random(n),
                           80 * rng.random(n), 2 * rng.random(n) - 1])
    return obs.astype(np.float32)


def test_rl_policy_rejects_bad_observations_without_touching_the_pipeline():
    obs = _observations()
    ref, pol = _toy_policy(), _toy_policy()
    expected = [ref.predict(o, episode_start=np.array([k == 0]))[0] for k, o in enumerate(obs)]
    got = []
    for k, o in enumerate(obs):
        if k in (4, 17):
            nan = o.astype(np.float64)
            nan[1] = np.nan
            for bad, err, match in ((nan, ValueError, "observation contains NaN or inf at entries \\[1\\]"),
                                    (np.r_[o, 1.0], ValueError, "observation must have 5 entries"),
                                    (o[:3], ValueError, "observation must have 5 entries"),
                                    (np.zeros((2, 2, 5)), ValueError, "observation must have shape"),
                                    (None, TypeError, "observation")):
                with pytest.raises(err, match=match):
                    pol.predict(bad, episode_start=np.array([False]))
        got.append(pol.predict(o, episode_start=np.array([k == 0]))[0])
    assert all(np.array_equal(g, e) for g, e in zip(got, expected, strict=True))


def test_rl_policy_batch_with_one_bad_row_is_rejected_whole():
    obs = _observations(n=6)
    pol = _toy_policy()
    batch = np.stack([obs[0], obs[1]])
    a0, _ = pol.predict(batch, episode_start=np.array([True, True]))
    assert a0.shape == (2, 1)
    bad = np.stack([obs[2], obs[3]]).astype(np.float64)
    bad[1, 4] = np.inf
    with pytest.raises(ValueError, match=r"\(row, entry\) \[\(1, 4\)\]"):
        pol.predict(bad)
    ref = _toy_policy()
    ref.predict(batch, episode_start=np.array([True, True]))
    good = np.stack([obs[2], obs[3]])
    assert np.array_equal(pol.predict(good)[0], ref.predict(good)[0])


# ------------------------------------------------------------------------------------------------ surrogate
class _FirstOrder:
    """A made-up normalised model: tailpipe NOx follows inlet NOx minus the dose, NH3 a fraction of the dose."""

    def to_casadi(self):
        import casadi as ca

        x = ca.SX.sym("x", 1)
        u = ca.SX.sym("u", 2)
        x_next = 0.9 * x + 0.1 * u[1]
        y = ca.vertcat(u[0] - 0.5 * x, 0.2 * x)
        return ca.Function("step", [x, u], [x_next, y], ["x", "u"], ["x_next", "y"])


def _surrogate():
    from control.rl.surrogate import SurrogateModel
    from ident.preprocessing import Normalizer

    nu = Normalizer.from_stats([400.0, 1.0], [200.0, 0.5])
    ny = Normalizer.from_stats([200.0, 0.0], [100.0, 10.0])
    return SurrogateModel(_FirstOrder(), ("inlet_nox_ppm", "adblue_g_s"), ("tailpipe_nox_ppm", "nh3_slip_ppm"),
                          nu, ny)


def test_surrogate_env_has_the_plant_spaces_and_reward():
    from control.rl.surrogate import SurrogateSCREnv
    from scr_env.envs.urea_scr import UreaSCREnv

    env = SurrogateSCREnv(_surrogate(), cycle="random", random_cycle_duration_s=60.0)
    plant = UreaSCREnv(cycle="whtc")
    assert env.observation_space == plant.observation_space and env.action_space == plant.action_space
    assert env.observation_names == plant.observation_names
    obs, info = env.reset(seed=0)
    assert obs.shape == (5,) and obs[4] == -1.0 and info["n_steps"] == 120
    total, n = 0.0, 0
    while True:
        obs, r, term, trunc, info = env.step(np.array([0.0], dtype=np.float32))
        assert r <= 0 and not term
        total += r
        n += 1
        if trunc:
            break
    assert n == 120 and set(info["episode_kpis"]) >= {"tailpipe_nox_g_per_kwh", "mean_nh3_slip_ppm"}
    assert info["episode_kpis"]["mean_nh3_slip_ppm"] > 0  # the dose shows up as NH3 in physical units


def test_surrogate_scaling_is_explicit():
    sur = _surrogate()
    x = np.zeros((1, 1))
    # u = (800 ppm, 2 g/s) -> normalised (2, 2); y_norm = (2 - 0, 0) -> physical (200 + 100 * 2, 0)
    x1, y = sur.step(x, np.array([[800.0, 2.0]]))
    np.testing.assert_allclose(x1, [[0.2]])
    np.testing.assert_allclose(y, [[400.0, 0.0]])


def test_surrogate_vector_env_trains_through_the_adapter():
    from control.rl.surrogate import SurrogateVectorEnv

    venv = GymVectorToSB3(SurrogateVectorEnv(_surrogate(), num_envs=2, cycle="random", random_cycle_pool=2))
    venv.seed(0)
    obs = venv.reset()
    assert obs.shape == (2, 5)
    for _ in range(5):
        obs, rew, _, _ = venv.step(np.zeros((2, 1), dtype=np.float32))
    assert rew.shape == (2,) and np.all(np.isfinite(obs))
