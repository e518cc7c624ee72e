"""scr_env: a first-principles SCR catalyst simulator for urea-dosing control, as a Gymnasium environment.

Importing the package registers ``scr_env/UreaSCR-v0`` (single environment, ``UreaSCREnv``) with a native vector
entry point (``UreaSCRVectorEnv``), and the benchmark tasks ``scr_env/UreaSCR-WHTC-v0``, ``-WHSC-v0``, ``-Aged-v0``,
``-Randomised-v0`` (:mod:`scr_env.tasks`, scored by :mod:`scr_env.benchmark`)::

    import gymnasium as gym
    import scr_env  # noqa: F401  (registers the environment)
    env = gym.make("scr_env/UreaSCR-v0", cycle="whtc")
    venv = gym.make_vec("scr_env/UreaSCR-v0", num_envs=64, vectorization_mode="vector_entry_point")

The submodules are available as attributes after ``import scr_env`` (imported on first use): ``scr_env.lab``
(steady states in the CLEERS lab configuration), ``scr_env.rollout`` (a policy over a cycle, as arrays),
``scr_env.casadi_model`` (the catalyst in CasADi), ``scr_env.wrappers`` (``RecordEpisodeKPIs``), ``scr_env.envs``,
``scr_env.cycles``, ``scr_env.engine``, ``scr_env.params``, ``scr_env.physics``, ``scr_env.constants``,
``scr_env.jit`` (numba and its cache), ``scr_env.startup`` (first-step times, precompiling).
"""
from __future__ import annotations

import importlib
from typing import Any

from gymnasium.envs.registration import register, registry

from scr_env.cycles import ExhaustTrace, available_cycles, load_cycle, random_cycle
from scr_env.installation import check_control_package
from scr_env.params import CatalystParams, DosingParams, SensorParams, aged, catalyst_preset

ENV_ID = "scr_env/UreaSCR-v0"

if ENV_ID not in registry:
    # No max_episode_steps: the end of the drive cycle is the truncation, whatever the cycle and dt.
    register(
        id=ENV_ID,
        entry_point="scr_env.envs.urea_scr:UreaSCREnv",
        vector_entry_point="scr_env.envs.vector:UreaSCRVectorEnv",
    )

from scr_env.tasks import MAIN_TASKS, TASKS, register_tasks

register_tasks()  # the benchmark tasks scr_env/UreaSCR-<task>-v0 (scr_env.tasks)

_SUBMODULES = ("actuator", "benchmark", "casadi_model", "constants", "cycles", "engine", "envs", "installation", "jit",
               "lab", "params", "physics", "rollout", "startup", "tasks", "wrappers")

__all__ = [
    "ENV_ID", "MAIN_TASKS", "TASKS", "CatalystParams", "DosingParams", "ExhaustTrace", "SensorParams", "aged",
    "available_cycles", "catalyst_preset", "load_cycle", "random_cycle",
]


def __getattr__(name: str) -> Any:
    """``scr_env.lab``, ``scr_env.rollout``, ...: submodules imported on first access (PEP 562)."""
    if name in _SUBMODULES:
        return importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_SUBMODULES))


check_control_package()  # warns if python-control has replaced this project's `control` (scr_env.installation)
