"""Stable-baselines3 ``VecEnv`` view of a native gymnasium vector environment (one kernel call for all plants).

:class:`UreaSCRVectorEnv` steps all plants with one call of the compiled physics; made with
``autoreset_mode="same_step"`` (as :func:`make_sb3_vec_env` does) it autoresets in ``AutoresetMode.SAME_STEP``:
when a plant's cycle ends, the step already returns its *reset* observation and puts the
last observation of the ended episode into ``infos["final_obs"][i]``. That is exactly stable-baselines3's convention,
only spelled differently, so the adapter just translates:

| gymnasium (SAME_STEP)                         | stable-baselines3                                        |
|-----------------------------------------------|----------------------------------------------------------|
| ``terminated``, ``truncated`` (bool arrays)    | ``dones = terminated | truncated``                        |
| ``infos["final_obs"][i]``                     | ``infos[i]["terminal_observation"]``                     |
| ``truncated[i] and not terminated[i]``        | ``infos[i]["TimeLimit.truncated"] = True`` (1)           |
| ``infos["final_info"]["episode_kpis"]``       | ``infos[i]["episode_kpis"]`` (dict of floats)            |
| per-step info arrays (``nox_cost``, ...)      | ``infos[i][key]`` scalars (only if ``per_step_info``)    |

(1) SB3 then bootstraps the value of the terminal observation.

The end of a drive cycle is a truncation, never a termination: the catalyst goes on, so the value of the last state
is bootstrapped.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

__all__ = ["GymVectorToSB3", "make_sb3_vec_env"]


class GymVectorToSB3(VecEnv):
    """Wrap a gymnasium ``VectorEnv`` with ``AutoresetMode.SAME_STEP`` as a stable-baselines3 ``VecEnv``.

    Parameters
    ----------
    venv : the gymnasium vector environment (e.g. ``gym.make_vec("scr_env/UreaSCR-v0", num_envs=8,
        vectorization_mode="vector_entry_point", cycle="random", random_offsets=True)``).
    per_step_info : copy the per-step info arrays into every env's info dict (costs a few microseconds per step;
        off by default since training needs none of them).
    """

    def __init__(self, venv: gym.vector.VectorEnv, per_step_info: bool = False) -> None:
        mode = venv.metadata.get("autoreset_mode")
        if mode != AutoresetMode.SAME_STEP:
            raise ValueError(f"the vector environment must autoreset in AutoresetMode.SAME_STEP, got {mode!r}: make "
                             f"it with autoreset_mode='same_step' (gym.make_vec(..., autoreset_mode='same_step')), "
                             f"or use make_sb3_vec_env, which does")
        self.venv = venv
        self.per_step_info = bool(per_step_info)
        self._actions: np.ndarray | None = None
        super().__init__(venv.num_envs, venv.single_observation_space, venv.single_action_space)

    # ------------------------------------------------------------------------------------------------ stepping
    def reset(self) -> np.ndarray:
        # A native vector env takes one seed for all plants: the first seed set by VecEnv.seed(seed) (SB3 gives
        # env i the seed seed + i; the vector env derives every plant's random stream from its one generator).
        seed = self._seeds[0]
        options = self._options[0] or None
        obs, info = self.venv.reset(seed=seed, options=options)
        self.reset_infos = [{k: v[i] for k, v in info.items() if not k.startswith("_")}
                            for i in range(self.num_envs)]
        self._reset_seeds()
        self._reset_options()
        return np.asarray(obs, dtype=np.float32)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_wait() without step_async()")
        actions = self._actions.reshape((self.num_envs, *self.action_space.shape))
        self._actions = None
        obs, rewards, terminated, truncated, info = self.venv.step(actions)
        terminated = np.asarray(terminated, dtype=bool)
        truncated = np.asarray(truncated, dtype=bool)
        dones = terminated | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if self.per_step_info:
            for key, value in info.items():
                if key.startswith("_") or key in ("final_obs", "final_info"):
                    continue
                for i in range(self.num_envs):
                    infos[i][key] = value[i]
        if dones.any():
            final_obs = info["final_obs"]
            final_info = info.get("final_info", {})
            kpis = final_info.get("episode_kpis")
            for i in np.flatnonzero(dones):
                infos[i]["terminal_observation"] = np.asarray(final_obs[i], dtype=np.float32)
                infos[i]["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
                if kpis is not None:
                    infos[i]["episode_kpis"] = {k: float(v[i]) for k, v in kpis.items() if not k.startswith("_")}
        return (np.asarray(obs, dtype=np.float32), np.asarray(rewards, dtype=np.float32), dones, infos)

    def close(self) -> None:
        self.venv.close()

    # ------------------------------------------------------------------------------------------- attributes
    def _indices(self, indices: VecEnvIndices) -> Sequence[int]:
        if indices is None:
            return range(self.num_envs)
        if isinstance(indices, int):
            return [indices]
        return list(indices)

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        # All plants share one object; an attribute of the vector env is the attribute of every plant.
        value = getattr(self.venv, attr_name)
        return [value for _ in self._indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        if indices is not None and len(self._indices(indices)) != self.num_envs:
            raise ValueError("the native vector env shares its attributes between plants; set them for all envs")
        setattr(self.venv, attr_name, value)

    def env_method(self, method_name: str, *method_args: Any, indices: VecEnvIndices = None,
                   **method_kwargs: Any) -> list[Any]:
        result = getattr(self.venv, method_name)(*method_args, **method_kwargs)
        return [result for _ in self._indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None for _ in range(self.num_envs)]

    @property
    def observation_names(self) -> tuple[str, ...]:
        """Names of the observation entries (from the wrapped environment)."""
        return tuple(self.venv.unwrapped.observation_names)


def make_sb3_vec_env(num_envs: int, env_id: str = "scr_env/UreaSCR-v0", per_step_info: bool = False,
                     **env_kwargs: Any) -> GymVectorToSB3:
    """``gym.make_vec(env_id, num_envs, vectorization_mode="vector_entry_point", autoreset_mode="same_step",
    **env_kwargs)`` as an SB3 VecEnv."""
    import scr_env  # noqa: F401  (registers the environment)

    env_kwargs.setdefault("autoreset_mode", AutoresetMode.SAME_STEP)
    venv = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", **env_kwargs)
    return GymVectorToSB3(venv, per_step_info=per_step_info)
