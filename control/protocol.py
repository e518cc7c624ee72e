"""The one interface every dosing controller of this project has: the stable-baselines3 ``predict`` method.

A controller is any object with

    predict(observation, state=None, episode_start=None, deterministic=True) -> (action, state)

exactly like a stable-baselines3 policy (``stable_baselines3.common.type_aliases.PolicyPredictor``), so one
evaluation function (:func:`control.evaluation.evaluate`) scores look-up tables, PI loops, MPC and RL alike.

``observation`` is the environment's observation (see :class:`scr_env.envs.urea_scr.UreaSCREnv`): [upstream NOx
ppm, inlet temperature K, exhaust flow mol/s, tailpipe NOx sensor ppm, previous action, (NH3 sensor ppm),
(cell coverages)]. ``action`` is a float32 array of shape (1,), normalised to [-1, 1] (AdBlue rate
(a + 1) / 2 * max_rate_g_s). ``episode_start`` is a bool array of shape (1,), True at the first step of an episode:
a controller with memory (integrator, estimator, warm start) resets itself then.

Optional hooks, called by the evaluation harness only if the controller has them:

* ``attach(env) -> None``: called after every ``env.reset`` with the *unwrapped* :class:`UreaSCREnv`, before the
  first ``predict`` of the episode. This is the only, explicit, way a controller gets privileged information
  (the oracle MPC reads ``env.state`` -- cell coverages and temperatures --, ``env.disturbance_preview(h)`` and
  ``env.catalyst_params_array``; controllers that also need ``dt`` or ``max_rate_g_s`` read them here). A
  controller without ``attach`` sees nothing but the observation.
* ``stats() -> dict[str, float]``: counters and timings of the last episode (e.g. ``solver_failures``,
  ``solve_time_ms_median``); the harness copies them into its result.
"""
from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

#: default maximum AdBlue rate of the environment [g/s] (``DosingParams.max_rate_g_s``)
DEFAULT_MAX_RATE_G_S = 3.0


@runtime_checkable
class PolicyPredictor(Protocol):
    """Anything that maps an observation to an action the stable-baselines3 way (see the module docstring)."""

    def predict(self, observation: np.ndarray, state: tuple[np.ndarray, ...] | None = None,
                episode_start: np.ndarray | None = None,
                deterministic: bool = True) -> tuple[np.ndarray, tuple[np.ndarray, ...] | None]:
        ...


def rate_to_action(rate_g_s: float, max_rate_g_s: float = DEFAULT_MAX_RATE_G_S) -> np.ndarray:
    """Normalised action (shape (1,), float32, in [-1, 1]) for an AdBlue rate [g/s] (clipped to [0, max])."""
    r = min(max(float(rate_g_s), 0.0), max_rate_g_s)
    return np.array([2.0 * r / max_rate_g_s - 1.0], dtype=np.float32)


def action_to_rate(action: Any, max_rate_g_s: float = DEFAULT_MAX_RATE_G_S) -> float:
    """AdBlue rate [g/s] of a normalised action (clipped to [-1, 1])."""
    a = min(max(float(np.asarray(action, dtype=np.float64).reshape(-1)[0]), -1.0), 1.0)
    return 0.5 * (a + 1.0) * max_rate_g_s


def is_episode_start(episode_start: Any) -> bool:
    """True if ``episode_start`` (None, bool or a bool array of shape (1,)) marks a new episode."""
    if episode_start is None:
        return False
    return bool(np.asarray(episode_start).reshape(-1)[0])
