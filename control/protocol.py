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

Observation checks (:func:`check_observation`, called by every controller's ``predict`` at entry, before any
internal state -- integrator, estimator, history, warm start -- is touched):

* not a numeric array (e.g. None) -> ``TypeError`` naming ``observation``;
* NaN or inf anywhere -> ``ValueError`` naming ``observation`` and the offending entries (one bad reading must not
  poison an integrator or an estimator for the rest of the episode; there is no silent fallback for it);
* the wrong number of entries -> ``ValueError`` stating the expected size: exactly the environment's observation
  size once the controller knows it (after ``attach(env)``, or from the observation layout it was trained on),
  otherwise at least the :data:`N_BASE_OBSERVATION` entries of the default observation;
* batches: a *stateless* controller (:class:`control.baselines.LookupTableDosing`, the RL policies) takes
  ``(B, n)`` like stable-baselines3 and returns ``(B, 1)``; a *stateful single-plant* controller
  (:class:`control.baselines.FeedforwardPI`, :class:`control.mpc.NonlinearMPC`) takes ``(n,)`` -> action ``(1,)``
  or ``(1, n)`` -> action ``(1, 1)`` and rejects ``B > 1`` with a ``ValueError`` (one controller per plant).

A rejected call changes nothing: the next valid call returns what it would have returned without it.
"""
from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np

from scr_env.envs.core import OBS_BASE

#: names of the default observation's entries (``UreaSCREnv`` without optional sensors)
BASE_OBSERVATION_NAMES: tuple[str, ...] = tuple(OBS_BASE)
#: entries of the default observation; every controller reads (some of) these, so no observation is shorter
N_BASE_OBSERVATION = len(BASE_OBSERVATION_NAMES)

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


def observation_size(env: Any) -> int:
    """Number of entries of the observation of ``env`` (an environment or its ``observation_space``)."""
    space = getattr(env, "observation_space", env)
    return int(np.prod(space.shape))


def check_observation(observation: Any, size: int | None = None, *, min_size: int = N_BASE_OBSERVATION,
                      max_batch: int | None = 1, owner: str = "controller",
                      names: tuple[str, ...] | None = None) -> tuple[np.ndarray, bool]:
    """Validate a ``predict`` observation; return it as a float64 ``(B, n)`` array and whether it was 1-D.

    Parameters
    ----------
    observation : the argument of ``predict``: shape ``(n,)`` or ``(B, n)``.
    size : the exact number of entries ``n`` expected (the environment's observation size), or None if the
        controller does not know it yet; then at least ``min_size`` entries are required.
    max_batch : the largest ``B`` accepted (1 for a stateful single-plant controller, None for no limit).
    owner : the controller's name, used in the messages.
    names : the names of the ``size`` entries, if known (quoted in the message on a wrong size).

    Raises ``TypeError`` for a non-numeric ``observation`` (e.g. None) and ``ValueError`` for a wrong shape or a
    non-finite entry (module docstring). The input is converted, never modified; float32 values convert exactly,
    so a controller computes the same numbers as on the raw observation.
    """
    if observation is None:
        raise TypeError(f"{owner}: observation must be a numeric array of shape (n,) or (B, n), got None")
    try:
        obs = np.asarray(observation, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{owner}: observation must be a numeric array of shape (n,) or (B, n), got "
                        f"{type(observation).__name__} ({exc})") from None
    single = obs.ndim == 1
    if obs.ndim not in (1, 2):
        raise ValueError(f"{owner}: observation must have shape (n,) or (B, n), got shape {obs.shape}")
    batch = obs.reshape(1, -1) if single else obs
    b, n = batch.shape
    if b == 0:
        raise ValueError(f"{owner}: observation is an empty batch (shape {obs.shape})")
    if max_batch is not None and b > max_batch:
        raise ValueError(f"{owner} controls a single plant (it keeps per-episode state): observation must have "
                         f"shape (n,) or (1, n), got a batch of shape {obs.shape}; use one controller per plant")
    if size is not None and n != size:
        what = f"[{', '.join(names)}]" if names else "the environment's observation size"
        raise ValueError(f"{owner}: observation must have {size} entries ({what}), got shape {obs.shape}")
    if size is None and n < min_size:
        raise ValueError(f"{owner}: observation must have at least {min_size} entries (the default observation is "
                         f"[{', '.join(BASE_OBSERVATION_NAMES)}]), got shape {obs.shape}")
    finite = np.isfinite(batch)
    if not finite.all():
        bad = np.argwhere(~finite)
        where = [int(j) for _, j in bad] if single else [tuple(int(v) for v in ij) for ij in bad]
        raise ValueError(f"{owner}: observation contains NaN or inf at {'entries' if single else '(row, entry)'} "
                         f"{where[:5]}{' ...' if len(where) > 5 else ''}; no internal state was changed")
    return batch, single
