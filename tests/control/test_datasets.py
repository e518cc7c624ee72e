"""Offline datasets in Minari format: collected with Minari's DataCollector, loaded with minari.load_dataset from a
local path, returns equal to the environment's for the same policy and seed, no privileged state; behaviour cloning
on them."""
from __future__ import annotations

import json

import gymnasium as gym
import numpy as np
import pytest

minari = pytest.importorskip("minari")
pytest.importorskip("jax")
pytest.importorskip("h5py")
pytest.importorskip("stable_baselines3")

from control.rl.datasets import behaviour_policy, dataset_id, datasets_root, make_group
from scr_env.tasks import get_task

DURATION = 30.0  # s: 60 steps per episode


@pytest.fixture(scope="module")
def group(tmp_path_factory):
    root = tmp_path_factory.mktemp("datasets")
    with datasets_root(root):
        made = make_group("fresh", episodes=2, seed=7, duration_s=DURATION, quick=True)
    return root, made


def test_datasets_load_from_a_local_path_with_minari(group):
    root, _ = group
    with datasets_root(root):
        for kind in ("expert", "medium", "random", "mixed"):
            ds = minari.load_dataset(dataset_id("fresh", kind))
            assert ds.total_episodes == (6 if kind == "mixed" else 2)
            for ep in ds.iterate_episodes():
                assert ep.observations.shape == (61, 5)  # the task's observation only: no privileged state
                assert ep.actions.shape == (60, 1) and np.all(np.abs(ep.actions) <= 1.0)
                assert ep.truncations[-1] and not ep.terminations.any()
    files = [p.name for p in root.rglob("*") if p.is_file()]
    assert not [f for f in files if f.endswith((".pkl", ".pickle"))]
    meta = json.loads(next(root.rglob("expert-v0/data/metadata.json")).read_text())
    spec = json.loads(meta["env_spec"])
    assert spec["kwargs"]["privileged"] is False and spec["kwargs"]["nh3_sensor"] is False
    assert json.loads(meta["eval_env_spec"])["id"] == "scr_env/UreaSCR-WHTC-v0"


@pytest.mark.parametrize("kind", ["expert", "medium", "random"])
def test_episode_returns_match_the_environment_for_the_same_policy_and_seed(group, kind):
    root, _ = group
    task = get_task("WHTC")
    with datasets_root(root):
        ds = minari.load_dataset(dataset_id("fresh", kind))
    for i, ep in enumerate(ds.iterate_episodes()):
        policy, _ = behaviour_policy(kind, i, seed=7, quick=True)
        env = gym.make(task.id, **{**task.train_kwargs(), "random_cycle_duration_s": DURATION})
        obs, _ = env.reset(seed=7 + i)
        if hasattr(policy, "attach"):
            policy.attach(env.unwrapped)
        np.testing.assert_array_equal(obs, ep.observations[0])
        total, k, done = 0.0, 0, False
        while not done:
            action, _ = policy.predict(obs, episode_start=np.array([k == 0]))
            obs, r, term, trunc, _ = env.step(np.asarray(action, dtype=np.float32).reshape(1))
            total += r
            k += 1
            done = term or trunc
        assert total == pytest.approx(float(ep.rewards.sum()), rel=1e-9)
        env.close()


def test_behaviour_cloning_trains_in_seconds_and_saves_without_pickle(group, tmp_path):
    from control.rl.bc import train_bc
    from control.rl.policy import load_policy, save_policy

    _, made = group
    policy, meta = train_bc(made["expert"], seed=0, hyperparameters={"epochs": 5})
    assert meta["samples"] == 120 and meta["wall_time_s"] < 30.0 and len(meta["learning_curve"]["mse"]) == 5
    path = save_policy(policy.model, policy.obs_mean, policy.obs_var, tmp_path, "bc_s0", meta)
    loaded = load_policy(path)
    obs = np.array([500.0, 550.0, 5.0, 100.0, -1.0], dtype=np.float32)
    a1, _ = policy.predict(obs, episode_start=np.array([True]))
    a2, _ = loaded.predict(obs, episode_start=np.array([True]))
    np.testing.assert_allclose(a1, a2, atol=1e-7)
    assert loaded.metadata["algo"] == "BC"
