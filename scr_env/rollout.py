"""Run a dosing policy over a drive cycle and get the whole trajectory as arrays (for identification and plots)."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from scr_env.envs.urea_scr import UreaSCREnv
from scr_env.physics import kernel as K

#: signals recorded at every step, with their units
SIGNALS: dict[str, str] = {
    "time_s": "s",
    "adblue_g_s": "g/s",
    "action": "-",
    "exhaust_flow_mol_s": "mol/s",
    "inlet_temperature_k": "K",
    "inlet_nox_ppm": "ppm",
    "inlet_no2_fraction": "-",
    "engine_power_kw": "kW",
    "tailpipe_nox_ppm": "ppm",
    "tailpipe_nh3_ppm": "ppm",
    "tailpipe_n2o_ppm": "ppm",
    "nox_sensor_ppm": "ppm",
    "nh3_sensor_ppm": "ppm",
    "mean_coverage": "-",
    "outlet_temperature_k": "K",
    "reward": "-",
}


@dataclass
class Trajectory:
    """Arrays of one episode, one row per control step (signal names and units in :data:`SIGNALS`).

    ``signals[name]`` is a float64 array of length ``n_steps``; ``observations`` is (n_steps + 1, obs_dim), the
    first row being the reset observation; ``kpis`` are the episode KPIs when the cycle was run to its end.
    """

    dt: float
    cycle: str
    signals: dict[str, np.ndarray]
    observations: np.ndarray
    observation_names: tuple[str, ...]
    kpis: dict[str, float] = field(default_factory=dict)

    def __getitem__(self, name: str) -> np.ndarray:
        return self.signals[name]

    @property
    def n_steps(self) -> int:
        return int(self.signals["time_s"].size)


def _as_policy(policy: Any) -> Callable[[np.ndarray, int], np.ndarray]:
    """Accept a callable ``f(obs) -> action``, ``f(obs, step)`` or an object with the SB3 ``predict`` method."""
    if hasattr(policy, "predict"):
        state: list[Any] = [None]

        def act(obs: np.ndarray, k: int) -> np.ndarray:
            action, state[0] = policy.predict(obs, state=state[0], episode_start=np.array([k == 0]),
                                              deterministic=True)
            return action

        return act
    if callable(policy):
        import inspect

        try:
            n_args = len(inspect.signature(policy).parameters)
        except (TypeError, ValueError):
            n_args = 1
        if n_args >= 2:
            return lambda obs, k: policy(obs, k)
        return lambda obs, k: policy(obs)
    raise ValueError("policy must be callable (obs -> action) or have a predict(obs, ...) method")


def rollout(policy: Any, cycle: Any = "whtc", seed: int | None = 0, max_steps: int | None = None,
            env: UreaSCREnv | None = None, reset_options: dict | None = None, **env_kwargs: Any) -> Trajectory:
    """Run ``policy`` over one episode of a :class:`UreaSCREnv` and return the :class:`Trajectory`.

    Parameters
    ----------
    policy : callable ``obs -> action`` or ``(obs, step) -> action``, or an object with
        ``predict(obs, state, episode_start, deterministic) -> (action, state)`` (every controller of ``control``
        and every stable-baselines3 model).
    cycle, env_kwargs : arguments of the environment (ignored when ``env`` is given).
    seed : reset seed (sensor noise, random cycle).
    max_steps : stop after this many steps (default: the whole cycle).
    env : an existing environment to use instead of creating one.
    """
    if env is None:
        env = UreaSCREnv(cycle=cycle, **env_kwargs)
    env = getattr(env, "unwrapped", env)
    if not isinstance(env, UreaSCREnv):
        raise ValueError(f"env must be a UreaSCREnv, got {type(env).__name__}")  # noqa: TRY004 (documented)
    act = _as_policy(policy)
    obs, _ = env.reset(seed=seed, options=reset_options)
    n = env._n if max_steps is None else min(int(max_steps), env._n)
    if n < 1:
        raise ValueError(f"max_steps must be >= 1, got {max_steps!r}")
    rec = {name: np.empty(n) for name in SIGNALS}
    observations = np.empty((n + 1, obs.size), dtype=np.float32)
    observations[0] = obs
    kpis: dict[str, float] = {}
    b = env._batch
    drive = env._drive
    for k in range(n):
        action = act(obs, k)
        obs, reward, _, truncated, info = env.step(action)
        out = b.out[0]
        rec["time_s"][k] = k * env.dt
        rec["adblue_g_s"][k] = info["adblue_g_s"]
        rec["action"][k] = b.action_norm[0]
        rec["exhaust_flow_mol_s"][k] = drive[k, 0]
        rec["inlet_temperature_k"][k] = drive[k, 1]
        rec["inlet_nox_ppm"][k] = drive[k, 2]
        rec["inlet_no2_fraction"][k] = drive[k, 3]
        rec["engine_power_kw"][k] = drive[k, 4]
        rec["tailpipe_nox_ppm"][k] = out[K.O_NO] + out[K.O_NO2]
        rec["tailpipe_nh3_ppm"][k] = out[K.O_NH3]
        rec["tailpipe_n2o_ppm"][k] = out[K.O_N2O]
        rec["nox_sensor_ppm"][k] = out[K.O_NOX_SENSOR]
        rec["nh3_sensor_ppm"][k] = out[K.O_NH3_SENSOR]
        rec["mean_coverage"][k] = out[K.O_COV]
        rec["outlet_temperature_k"][k] = out[K.O_TOUT]
        rec["reward"][k] = reward
        observations[k + 1] = obs
        if truncated:
            kpis = info["episode_kpis"]
    return Trajectory(dt=env.dt, cycle=env.trace.name, signals=rec, observations=observations,
                      observation_names=env.observation_names, kpis=kpis)
