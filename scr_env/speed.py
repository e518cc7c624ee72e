"""Throughput of the environments against Gymnasium's Pendulum-v1, measured in one process (``make bench``).

* ``env_steps_per_s``: ``gymnasium.make("scr_env/UreaSCR-v0")`` with its default wrappers, constant action,
  resetting at the end of the cycle;
* ``pendulum_steps_per_s``: ``gymnasium.make("Pendulum-v1")`` the same way (the reference for Python overhead);
* ``vector_env_steps_per_s``: env-steps per second of the native vector environment with ``num_envs`` plants;
* ``rpem_samples_per_s`` (and the full degree-2 model) from :func:`ident.speed.measure_rpem_speed`, when asked.

Everything is timed after a warm-up (JIT compilation excluded). The three figures are measured in ``rounds``
interleaved rounds of about ``seconds`` each (Pendulum, single, vector, Pendulum, ...) and each is the median of
its rounds, so a change of the machine's state during the run (other load, clock) affects the reference and the
environments alike; every round's figure is in ``rounds``.
"""
from __future__ import annotations

import os
import platform
import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

import scr_env  # noqa: F401  (registers the environment)

__all__ = ["measure"]


def _time_single(make: Callable[[], gym.Env], seconds: float) -> float:
    env = make()
    env.reset(seed=0)
    action = (0.5 * (env.action_space.low + env.action_space.high)).astype(env.action_space.dtype)
    for _ in range(200):  # warm-up
        _, _, te, tr, _ = env.step(action)
        if te or tr:
            env.reset()
    steps = 0
    start = time.perf_counter()
    deadline = start + seconds
    while True:
        for _ in range(500):
            _, _, te, tr, _ = env.step(action)
            if te or tr:
                env.reset()
        steps += 500
        now = time.perf_counter()
        if now >= deadline:
            break
    env.close()
    return steps / (now - start)


def _time_vector(num_envs: int, seconds: float) -> float:
    venv = gym.make_vec("scr_env/UreaSCR-v0", num_envs=num_envs, vectorization_mode="vector_entry_point",
                        cycle="whtc", random_offsets=True)
    venv.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, -0.3, size=(num_envs, 1)).astype(np.float32)
    for _ in range(20):
        venv.step(actions)
    steps = 0
    start = time.perf_counter()
    deadline = start + seconds
    while True:
        for _ in range(10):
            venv.step(actions)
        steps += 10 * num_envs
        now = time.perf_counter()
        if now >= deadline:
            break
    venv.close()
    return steps / (now - start)


def measure(num_envs: int = 1024, seconds: float = 2.0, rpem: bool = True, rounds: int = 3) -> dict[str, Any]:
    """All throughput figures, as a dict (see the module docstring)."""
    if rounds < 1:
        raise ValueError(f"rounds must be >= 1, got {rounds!r}")
    samples: dict[str, list[float]] = {"pendulum_steps_per_s": [], "env_steps_per_s": [],
                                       "vector_env_steps_per_s": []}
    for _ in range(rounds):
        samples["pendulum_steps_per_s"].append(_time_single(lambda: gym.make("Pendulum-v1"), seconds))
        samples["env_steps_per_s"].append(_time_single(lambda: gym.make("scr_env/UreaSCR-v0"), seconds))
        samples["vector_env_steps_per_s"].append(_time_vector(num_envs, seconds))
    result: dict[str, Any] = {key: float(np.median(v)) for key, v in samples.items()}
    result["num_envs"] = num_envs
    result["rounds"] = samples
    result["single_vs_pendulum"] = result["env_steps_per_s"] / result["pendulum_steps_per_s"]
    result["vector_vs_pendulum"] = result["vector_env_steps_per_s"] / result["pendulum_steps_per_s"]
    if rpem:
        try:
            from ident.speed import measure_rpem_speed
        except ImportError as e:  # the identification package is optional for this benchmark
            result["rpem_error"] = f"ident.speed unavailable: {e}"
        else:
            result.update(measure_rpem_speed())
    result["machine"] = {"python": platform.python_version(), "cpus": os.cpu_count(),
                         "processor": platform.processor() or platform.machine()}
    return result
