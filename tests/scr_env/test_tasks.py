"""Benchmark tasks (registered ids, training distributions, protocols) and the normalised score."""
from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

import scr_env
from scr_env import benchmark as B
from scr_env.tasks import MAIN_TASKS, TASKS, age_kwargs, get_task, make_eval_env, training_env_kwargs


def test_every_task_is_registered_and_makes_its_evaluation_environment():
    assert set(MAIN_TASKS) <= set(TASKS) and len(MAIN_TASKS) >= 3
    for tid, task in TASKS.items():
        assert tid in gym.registry and tid == task.id and tid.startswith("scr_env/UreaSCR-")
        env = gym.make(tid)
        base = env.unwrapped
        assert base.config.actuator is not None  # every task doses through the default actuator
        assert base.observation_names == tuple(scr_env.envs.core.OBS_BASE)  # no NH3 sensor, no privileged state
        assert base.config.cycle == task.protocol.cycle
        env.close()
        assert task.protocol.n_episodes == len(task.protocol.episodes()) >= 5
        d = task.describe()
        assert d["id"] == tid and d["evaluation"]["n_episodes"] == task.protocol.n_episodes and d["hard_axis"]


def test_training_distribution_is_random_cycles_never_the_evaluation_cycle():
    for task in TASKS.values():
        kw = training_env_kwargs(task.id)
        assert kw["cycle"] == "random" and kw["actuator"] == "default"
        venv = gym.make_vec(task.id, num_envs=2, vectorization_mode="vector_entry_point",
                            **{k: v for k, v in kw.items()})
        obs, _ = venv.reset(seed=0)
        assert obs.shape == (2, 5)
        venv.close()
    assert training_env_kwargs("Randomised")["randomize"] == 0.2


def test_aged_task_evaluates_one_age_per_episode():
    task = get_task("Aged")
    ages = [c["age_h"] for c, _ in task.protocol.episodes()]
    assert sorted(set(ages)) == [0.0, 4.0, 16.0]
    env0, env16 = make_eval_env(task, {"age_h": 0.0}), make_eval_env(task, {"age_h": 16.0})
    env0.reset(seed=0)
    env16.reset(seed=0)
    p0, p16 = env0.catalyst_params_array, env16.catalyst_params_array
    assert not np.array_equal(p0, p16)  # the aged catalyst differs
    assert age_kwargs(0.0) == {}


def test_get_task_names_and_errors():
    assert get_task("WHTC") is get_task("scr_env/UreaSCR-WHTC-v0") is get_task("UreaSCR-WHTC-v0")
    with pytest.raises(ValueError, match="unknown task"):
        get_task("Pendulum-v1")


def test_score_definitions():
    assert B.raw_score(0.6, 0.6, 0.2) == 0.0 and B.raw_score(0.2, 0.6, 0.2) == pytest.approx(100.0)
    assert B.raw_score(0.4, 0.6, 0.2) == pytest.approx(50.0)
    with pytest.raises(ValueError, match="must beat"):
        B.raw_score(0.3, 0.2, 0.6)
    assert B.penalised_score(80.0, 9.9) == 80.0
    assert B.penalised_score(80.0, 15.0) == pytest.approx(-50.0)  # min(80, 0) - 10 * (15 - 10)
    assert B.penalised_score(-20.0, 11.0) == pytest.approx(-30.0)
    assert B.penalised_score(50.0, math.nan) == -math.inf
    assert B.iqm([0, 1, 2, 3, 100, 4, 5, 6]) == pytest.approx(np.mean([2, 3, 4, 5]))
    lo, hi = B.bootstrap_ci([1.0, 2.0, 3.0, 4.0, 50.0])
    assert lo <= B.iqm([1.0, 2.0, 3.0, 4.0, 50.0]) <= hi
    assert B.bootstrap_ci([7.0]) == (7.0, 7.0) and B.bootstrap_ci([2.0, 2.0]) == (2.0, 2.0)
    entry = B.aggregate([10.0, 20.0, 30.0, 40.0, 50.0])
    assert entry["n_seeds"] == 5 and entry["learned"] is True and len(entry["ci"]) == 2


def test_anchors_score_0_and_100_on_cut_episodes_and_the_reference_replays():
    """Anchors made as experiments.rl_anchors makes them (here on episodes cut at 40 steps): the look-up table
    scores 0 and the oracle NMPC, run again, 100 -- the score reproduces its anchors."""
    from control.baselines import LookupTableDosing
    from control.factory import oracle_mpc

    task = get_task("WHTC")
    lut = B.episode_metrics(LookupTableDosing(), task, max_steps=40)
    ref = B.episode_metrics(oracle_mpc(quick=True), task, max_steps=40)
    anchors = {"tasks": {task.id: {"reference_kind": "oracle_mpc quick", "partial_episodes": 40, "episodes": [
        {"condition": a["condition"], "seed": a["seed"], "lookup_table": a["kpis"], "reference": b["kpis"]}
        for a, b in zip(lut, ref, strict=True)]}}}
    res = B.evaluate(LookupTableDosing(), task, anchors, max_steps=40)
    assert res.raw_score == 0.0 and res.ci == (0.0, 0.0) and len(res.episodes) == task.protocol.n_episodes
    assert res.chatter_g_s_per_h > 0
    ref_res = B.evaluate(oracle_mpc(quick=True), task, anchors, max_steps=40)
    assert ref_res.raw_score == pytest.approx(100.0, abs=1e-9)
    with pytest.raises(ValueError, match="cut at 40 steps"):
        B.evaluate(LookupTableDosing(), task, anchors)


def test_stored_anchors_cover_every_main_task_and_the_look_up_table_scores_0():
    """The shipped anchors (experiments.rl_anchors) hold every main task's protocol; the look-up table re-run on
    the whole protocol scores exactly 0 (the anchors still hold for this plant) and the stored reference 100."""
    anchors = B.load_anchors()
    from control.baselines import LookupTableDosing

    for tid in MAIN_TASKS:
        task = get_task(tid)
        entry = anchors["tasks"][tid]
        assert entry.get("partial_episodes") is None and "reference_kind" in entry and "command" in entry
        assert [(e["condition"], e["seed"]) for e in entry["episodes"]] == task.protocol.episodes()
        rows = [{"condition": e["condition"], "seed": e["seed"], "kpis": e["reference"]} for e in entry["episodes"]]
        assert all(r["raw_score"] == pytest.approx(100.0) for r in B.score_rows(rows, task, anchors))
        res = B.evaluate(LookupTableDosing(), task, anchors)
        assert res.raw_score == pytest.approx(0.0, abs=1e-9), tid
