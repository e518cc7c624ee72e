"""The shipped RL benchmark policies (control/policies/benchmark, experiments.train_baselines and make_datasets):
every dataset group has at least three learned methods with five seeds, and one policy of each method loads
(no pickle) and acts on the task's evaluation environment within its action space."""
from __future__ import annotations

import json

import numpy as np
import pytest

from control.rl.suite import policy_files
from scr_env.tasks import MAIN_TASKS, get_task

GROUPS = sorted({get_task(t).dataset_group for t in MAIN_TASKS})


@pytest.mark.parametrize("group", GROUPS)
def test_every_group_ships_three_learned_methods_over_five_seeds(group):
    methods = policy_files(group)
    assert len([m for m, paths in methods.items() if len(paths) >= 5]) >= 3, methods
    for paths in methods.values():
        meta = json.loads(paths[0].read_text())
        assert meta["format_version"] == 2


@pytest.mark.parametrize("group", GROUPS)
def test_one_policy_of_each_method_acts_on_its_task(group):
    from control.rl.policy import load_policy

    task = next(get_task(t) for t in MAIN_TASKS if get_task(t).dataset_group == group)
    env = task.make_env() if hasattr(task, "make_env") else None
    if env is None:
        from scr_env.tasks import make_eval_env

        env = make_eval_env(task)
    obs, _ = env.reset(seed=0)
    for method, paths in policy_files(group).items():
        policy = load_policy(paths[0])
        action, _ = policy.predict(obs)
        action = np.asarray(action, dtype=np.float32).reshape(env.action_space.shape)
        assert env.action_space.contains(action), (method, action)
        _, reward, *_ = env.step(action)
        assert np.isfinite(reward)
