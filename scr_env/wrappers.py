"""Wrappers of the SCR environments.

:class:`RecordEpisodeKPIs` puts the emission KPIs of an episode into ``info["episode_kpis"]`` however the episode
ends. The environment does that itself at the end of its drive cycle; an episode cut short by another wrapper --
Gymnasium's ``TimeLimit``, which ``gym.make(..., max_episode_steps=N)`` adds, or a wrapper of one's own that
terminates -- ends outside the environment, which then has no chance to. Apply it outermost::

    env = RecordEpisodeKPIs(gym.make("scr_env/UreaSCR-v0", max_episode_steps=600))

The KPIs come from the environment's ``episode_kpis()`` method (:meth:`scr_env.envs.urea_scr.UreaSCREnv.
episode_kpis`), which may also be called directly at any time. The vector environment needs no wrapper: it takes
``max_episode_steps`` itself and reports the KPIs of every episode it ends
(:class:`scr_env.envs.vector.UreaSCRVectorEnv`).
"""
from __future__ import annotations

from typing import Any, SupportsFloat

import gymnasium as gym

__all__ = ["RecordEpisodeKPIs"]


class RecordEpisodeKPIs(gym.Wrapper):
    """Adds ``info["episode_kpis"]`` (a dict of floats, :func:`scr_env.envs.kpis.episode_kpis`) at every step that
    ends an episode, terminated or truncated, where the inner environment has not put it there.

    Parameters
    ----------
    env : an environment whose ``unwrapped`` has an ``episode_kpis()`` method (``scr_env/UreaSCR-v0``, the
        surrogates of :mod:`control.rl.surrogate`), with any wrappers in between.
    """

    def __init__(self, env: gym.Env) -> None:
        if not callable(getattr(env.unwrapped, "episode_kpis", None)):
            raise TypeError(f"RecordEpisodeKPIs needs an environment with an episode_kpis() method (such as "
                             f"scr_env/UreaSCR-v0); {type(env.unwrapped).__name__} has none")
        super().__init__(env)

    def step(self, action: Any) -> tuple[Any, SupportsFloat, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        if (terminated or truncated) and "episode_kpis" not in info:
            info = {**info, "episode_kpis": self.env.unwrapped.episode_kpis()}
        return obs, reward, terminated, truncated, info
