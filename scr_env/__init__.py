"""scr_env: a first-principles SCR catalyst simulator for urea-dosing control, as a Gymnasium environment.

Importing the package registers ``scr_env/UreaSCR-v0`` (single environment, ``UreaSCREnv``) with a native vector
entry point (``UreaSCRVectorEnv``)::

    import gymnasium as gym
    import scr_env  # noqa: F401  (registers the environment)
    env = gym.make("scr_env/UreaSCR-v0", cycle="whtc")
    venv = gym.make_vec("scr_env/UreaSCR-v0", num_envs=64, vectorization_mode="vector_entry_point")
"""
from __future__ import annotations

from gymnasium.envs.registration import register, registry

from scr_env.cycles import ExhaustTrace, available_cycles, load_cycle, random_cycle
from scr_env.params import CatalystParams, DosingParams, SensorParams, aged, catalyst_preset

ENV_ID = "scr_env/UreaSCR-v0"

if ENV_ID not in registry:
    # No max_episode_steps: the end of the drive cycle is the truncation, whatever the cycle and dt.
    register(
        id=ENV_ID,
        entry_point="scr_env.envs.urea_scr:UreaSCREnv",
        vector_entry_point="scr_env.envs.vector:UreaSCRVectorEnv",
    )

__all__ = [
    "ENV_ID", "CatalystParams", "DosingParams", "ExhaustTrace", "SensorParams", "aged", "available_cycles",
    "catalyst_preset", "load_cycle", "random_cycle",
]
