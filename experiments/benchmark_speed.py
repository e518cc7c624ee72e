"""Throughput of the environments (and of RPEM), measured in one process against Gymnasium's Pendulum-v1.

``python -m experiments.benchmark_speed [--json PATH] [--num-envs 1024] [--seconds 2] [--rounds 3]`` (``make bench``).

Reported:
* ``env_steps_per_s``: ``gymnasium.make("scr_env/UreaSCR-v0")`` with its default wrappers, constant action,
  resetting at the end of the cycle;
* ``pendulum_steps_per_s``: ``gymnasium.make("Pendulum-v1")`` the same way (the reference for Python overhead);
* ``vector_env_steps_per_s``: env-steps per second of the native vector environment with ``num_envs`` plants;
* ``rpem_samples_per_s`` (and the full degree-2 model) from :mod:`experiments.benchmark_rpem`, when available;
* ``hw_pwl_fit_s``: seconds to fit a piecewise-linear Hammerstein-Wiener model on 10^5 samples
  (:func:`ident.hammerstein_wiener.speed.measure_pwl_fit_speed`, goal 10 s).
Everything is timed after a warm-up (JIT compilation excluded). The three figures are measured in ``--rounds``
interleaved rounds of about ``--seconds`` each (Pendulum, single, vector, Pendulum, ...) and each is the median of
its rounds, so a change of the machine's state during the run (other load, clock) affects the reference and the
environments alike; every round's figure is in ``rounds``.
"""
from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

import scr_env  # noqa: F401  (registers the environment)
from experiments._runs import write_json


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


def measure(num_envs: int = 1024, seconds: float = 2.0, rpem: bool = True, rounds: int = 3,
            hw: bool = True) -> dict[str, Any]:
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
            from experiments.benchmark_rpem import measure_rpem_speed
        except ImportError as e:  # the RPEM package is optional for this benchmark
            result["rpem_error"] = f"experiments.benchmark_rpem unavailable: {e}"
        else:
            result.update(measure_rpem_speed())
    if hw:
        from ident.hammerstein_wiener.speed import measure_pwl_fit_speed

        result.update(measure_pwl_fit_speed())
    result["machine"] = {"python": platform.python_version(), "cpus": os.cpu_count(),
                         "processor": platform.processor() or platform.machine()}
    return result


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", help="write the figures to this JSON file")
    ap.add_argument("--num-envs", type=int, default=1024, help="plants in the vector environment (default 1024)")
    ap.add_argument("--seconds", type=float, default=2.0, help="timing window per figure and round [s] (default 2)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved measuring rounds, median reported (default 3)")
    ap.add_argument("--no-rpem", action="store_true", help="skip the RPEM figures")
    ap.add_argument("--no-hw", action="store_true", help="skip the Hammerstein-Wiener fit time")
    args = ap.parse_args(argv)
    if args.num_envs < 1 or args.seconds <= 0 or args.rounds < 1:
        ap.error("--num-envs and --rounds must be >= 1 and --seconds > 0")
    r = measure(args.num_envs, args.seconds, rpem=not args.no_rpem, rounds=args.rounds, hw=not args.no_hw)
    print(f"Pendulum-v1 (gym.make)        {r['pendulum_steps_per_s']:>12,.0f} steps/s")
    print(f"UreaSCR-v0 single (gym.make)  {r['env_steps_per_s']:>12,.0f} steps/s   "
          f"{r['single_vs_pendulum']:.2f}x Pendulum (goal 0.5x)")
    print(f"UreaSCR-v0 vector ({r['num_envs']} envs)  {r['vector_env_steps_per_s']:>12,.0f} env-steps/s   "
          f"{r['vector_vs_pendulum']:.1f}x Pendulum (goal 20x)")
    for key in ("rpem_samples_per_s", "rpem_full_degree2_samples_per_s"):
        if key in r:
            print(f"{key:30s}{r[key]:>12,.0f} samples/s")
    if "rpem_error" in r:
        print(r["rpem_error"])
    if "hw_pwl_fit_s" in r:
        print(f"Hammerstein-Wiener PWL fit, {r['hw_pwl_n_samples']:,} samples  {r['hw_pwl_fit_s']:>8.1f} s   "
              f"(goal 10 s; validation FIT {r['hw_pwl_validation_fit']:.1f} %)")
    if args.json:
        write_json(args.json, r)
    return r


if __name__ == "__main__":
    main()
