"""The Gymnasium wrappers the README recommends work on the environment as documented."""
from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.wrappers import DelayObservation, FrameStackObservation, RescaleAction

import scr_env


def test_rescale_action_to_grams_per_second() -> None:
    env = RescaleAction(gym.make(scr_env.ENV_ID, sensor_noise=False), np.float32(0.0), np.float32(3.0))
    env.reset(seed=0)
    _, _, _, _, info = env.step(np.array([1.2], dtype=np.float32))
    assert info["adblue_g_s"] == pytest.approx(1.2, rel=1e-6)


def test_delay_observation_delays_by_k_steps() -> None:
    plain = gym.make(scr_env.ENV_ID, sensor_noise=False)
    delayed = DelayObservation(gym.make(scr_env.ENV_ID, sensor_noise=False), delay=2)
    o_plain = [plain.reset(seed=0)[0]]
    delayed.reset(seed=0)
    o_delayed = []
    a = np.array([-0.5], dtype=np.float32)
    for _ in range(6):
        o_plain.append(plain.step(a)[0])
        o_delayed.append(delayed.step(a)[0])
    np.testing.assert_array_equal(o_delayed[2], o_plain[1])
    np.testing.assert_array_equal(o_delayed[5], o_plain[4])


def test_frame_stack_observation() -> None:
    env = FrameStackObservation(gym.make(scr_env.ENV_ID), 4)
    obs, _ = env.reset(seed=0)
    assert obs.shape == (4, 5)
    obs, *_ = env.step(np.array([0.0], dtype=np.float32))
    assert obs.shape == (4, 5)
