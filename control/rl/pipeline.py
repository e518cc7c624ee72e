"""The observation pipeline of the RL policies: physical features and a short history, the same in training and use.

The environment's observation (``UreaSCREnv``: upstream NOx ppm, inlet temperature K, exhaust flow mol/s, tailpipe
NOx sensor ppm, previous action) is turned into the policy input in three steps; the first two live here, the third
is stable-baselines3's ``VecNormalize`` (its statistics are shipped with each policy, see :mod:`control.rl.policy`):

1. **Features** (per step, ``FEATURES``): the observation itself, plus

   * ``stoichiometric_adblue_g_s`` [g/s]: AdBlue rate for ANR = 1 at the measured upstream NOx and flow (NOx ppm *
     1e-6 * flow / NH3 per g AdBlue): the feed-forward term, a product a small network would otherwise have to learn;
   * ``nh3_surplus_ema_g_s`` [g/s]: exponential moving average (``surplus_time_constant_s``, 60 s) of the previous
     dose minus the stoichiometric dose: a crude proxy of the NH3 put into storage over the last minute;
   * ``temperature_trend_k`` [K]: inlet temperature minus its moving average (``temperature_time_constant_s``,
     60 s): a rising temperature releases stored NH3;
   * ``tailpipe_sensor_ema_ppm`` [ppm]: moving average (``sensor_time_constant_s``, 10 s) of the tailpipe NOx sensor;
   * ``nh3_surplus_long_ema_g_s`` [g/s]: as ``nh3_surplus_ema_g_s`` over ``long_surplus_time_constant_s`` (e.g.
     600 s; only if > 0): the NH3 stored over the last minutes, which a later temperature rise releases.

   With ``use_tailpipe_sensor=False`` the tailpipe sensor and its average are left out: the policy is then a
   learned feed-forward with memory (inlet conditions, its own previous doses), immune to the sensor's NH3
   cross-sensitivity. The shipped policies use this (see control/policies/README.md): with the sensor, PPO learned
   to answer a high reading with more AdBlue, which on the WHTC's hot motorway part (stored NH3 desorbing) is a
   runaway: 182 ppm mean slip.

2. **History**: the last ``n_stack`` feature vectors, oldest first, flattened (``n_stack * n_features`` values).
   At the start of an episode the history is filled with copies of the first feature vector (not zeros: a zero
   temperature is not a neutral value), and the moving averages start at their first input.

Actions: with ``action="rate"`` (default) the policy outputs the environment's action (normalised AdBlue rate);
with ``action="anr"`` it outputs an NH3-to-NOx ratio, ANR = (a + 1) / 2 * ``max_anr`` (0 to 2), dosed as
ANR times the stoichiometric rate of the current observation (:meth:`ObservationPipeline.to_env_action`), the
parameterisation of industrial dosing maps: the policy learns a correction map, not the product NOx x flow.

3. **Normalisation** (outside this module): ``(x - mean) / sqrt(var + eps)`` clipped to ``+/- clip_obs``.

One :class:`ObservationPipeline` object holds the state of a batch of plants; the training wrapper
(:class:`PipelineVecEnv`) and the shipped policy (:class:`control.rl.policy.RLPolicy`) both use it, so the policy sees
in use exactly what it saw in training.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvStepReturn, VecEnvWrapper

from scr_env.constants import NH3_MOL_PER_G_ADBLUE
from scr_env.envs.core import OBS_BASE

__all__ = ["FEATURES", "ObservationPipeline", "PipelineConfig", "PipelineVecEnv"]

#: the observation the pipeline expects (names of ``UreaSCREnv.observation_names`` with the default options)
EXPECTED_OBSERVATION = tuple(OBS_BASE)
#: per-step features, in order (``tailpipe_nox_sensor_ppm`` and ``tailpipe_sensor_ema_ppm`` only with
#: ``PipelineConfig.use_tailpipe_sensor``)
FEATURES = EXPECTED_OBSERVATION + ("stoichiometric_adblue_g_s", "nh3_surplus_ema_g_s", "temperature_trend_k",
                                   "tailpipe_sensor_ema_ppm", "nh3_surplus_long_ema_g_s")
_SENSOR_FEATURES = ("tailpipe_nox_sensor_ppm", "tailpipe_sensor_ema_ppm")


@dataclass(frozen=True)
class PipelineConfig:
    """Settings of the observation pipeline (stored in each policy's metadata JSON)."""

    n_stack: int = 4
    dt: float = 0.5  # s, control interval of the environment
    max_rate_g_s: float = 3.0  # g/s, AdBlue rate of action +1
    surplus_time_constant_s: float = 60.0  # s [chosen: storage time scale of about a minute]
    sensor_time_constant_s: float = 10.0  # s [chosen: averages out sensor noise and short spikes]
    temperature_time_constant_s: float = 60.0  # s [chosen: a rise against the last minute releases stored NH3]
    use_tailpipe_sensor: bool = False
    long_surplus_time_constant_s: float = 0.0  # s; > 0 adds nh3_surplus_long_ema_g_s (0: left out)
    action: str = "rate"  # "rate": the policy outputs the env action; "anr": it outputs an NH3-to-NOx ratio
    max_anr: float = 2.0  # with action "anr": policy action -1..1 -> ANR 0..max_anr

    def __post_init__(self) -> None:
        if isinstance(self.n_stack, bool) or not isinstance(self.n_stack, int) or self.n_stack < 1:
            raise ValueError(f"n_stack must be a positive integer, got {self.n_stack!r}")
        if self.action not in ("rate", "anr"):
            raise ValueError(f"action must be 'rate' or 'anr', got {self.action!r}")
        if not (np.isfinite(self.long_surplus_time_constant_s) and self.long_surplus_time_constant_s >= 0):
            raise ValueError("long_surplus_time_constant_s must be >= 0")
        for name in ("dt", "max_rate_g_s", "surplus_time_constant_s", "sensor_time_constant_s",
                     "temperature_time_constant_s", "max_anr"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number, got {v!r}")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> PipelineConfig:
        return cls(**d)

    @property
    def features(self) -> tuple[str, ...]:
        """The per-step features of this configuration, in order."""
        out = FEATURES if self.use_tailpipe_sensor else tuple(f for f in FEATURES if f not in _SENSOR_FEATURES)
        if self.long_surplus_time_constant_s <= 0:
            out = tuple(f for f in out if f != "nh3_surplus_long_ema_g_s")
        return out

    @property
    def n_features(self) -> int:
        return len(self.features)

    @property
    def output_size(self) -> int:
        return self.n_stack * self.n_features

    @property
    def output_names(self) -> tuple[str, ...]:
        """Names of the flattened output, e.g. ``upstream_nox_ppm[t-3]`` ... ``temperature_trend_k[t]``."""
        lags = [f"t-{self.n_stack - 1 - j}" if j < self.n_stack - 1 else "t" for j in range(self.n_stack)]
        return tuple(f"{f}[{lag}]" for lag in lags for f in self.features)


class ObservationPipeline:
    """Features and history for ``num_envs`` plants (batched numpy; see the module docstring).

    ``start(obs, mask)`` begins new episodes for the plants in ``mask`` (all if None); ``advance(obs)`` takes the next
    observation of every plant; ``output()`` is the (num_envs, n_stack * n_features) float32 policy input.
    """

    def __init__(self, config: PipelineConfig, num_envs: int = 1) -> None:
        self.config = config
        self.num_envs = int(num_envs)
        c = config
        self._a_surplus = 1.0 - np.exp(-c.dt / c.surplus_time_constant_s)
        self._a_sensor = 1.0 - np.exp(-c.dt / c.sensor_time_constant_s)
        self._a_temp = 1.0 - np.exp(-c.dt / c.temperature_time_constant_s)
        tl = c.long_surplus_time_constant_s
        self._a_long = 1.0 - np.exp(-c.dt / tl) if tl > 0 else 0.0
        self._long = np.zeros(self.num_envs)
        self._history = np.zeros((self.num_envs, c.n_stack, c.n_features), dtype=np.float64)
        self._surplus = np.zeros(self.num_envs)
        self._sensor = np.zeros(self.num_envs)
        self._temp = np.zeros(self.num_envs)
        self._stoich_prev = np.zeros(self.num_envs)
        self._cols = [FEATURES.index(f) for f in c.features]

    def _check(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        if obs.ndim != 2 or obs.shape[0] != self.num_envs or obs.shape[1] != len(EXPECTED_OBSERVATION):
            raise ValueError(f"observations must have shape ({self.num_envs}, {len(EXPECTED_OBSERVATION)}) with "
                             f"entries {EXPECTED_OBSERVATION}, got shape {obs.shape}")
        return obs

    def _stoich(self, obs: np.ndarray) -> np.ndarray:
        return obs[:, 0] * 1e-6 * obs[:, 2] / NH3_MOL_PER_G_ADBLUE

    def _features(self, obs: np.ndarray, stoich: np.ndarray) -> np.ndarray:
        trend = obs[:, 1] - self._temp
        full = np.concatenate([obs, stoich[:, None], self._surplus[:, None], trend[:, None], self._sensor[:, None],
                               self._long[:, None]], axis=1)
        return full[:, self._cols]

    def start(self, obs: np.ndarray, mask: np.ndarray | None = None) -> None:
        obs = self._check(obs)
        idx = np.arange(self.num_envs) if mask is None else np.flatnonzero(np.asarray(mask, dtype=bool))
        if idx.size == 0:
            return
        stoich = self._stoich(obs)
        self._surplus[idx] = 0.0
        self._long[idx] = 0.0
        self._sensor[idx] = obs[idx, 3]
        self._temp[idx] = obs[idx, 1]
        self._stoich_prev[idx] = stoich[idx]
        feats = self._features(obs, stoich)
        self._history[idx] = feats[idx, None, :]

    def advance(self, obs: np.ndarray) -> None:
        obs = self._check(obs)
        stoich = self._stoich(obs)
        # the previous action (obs[:, 4]) was dosed against the previous step's stoichiometric rate
        dosed = 0.5 * (np.clip(obs[:, 4], -1.0, 1.0) + 1.0) * self.config.max_rate_g_s
        self._surplus += self._a_surplus * (dosed - self._stoich_prev - self._surplus)
        self._long += self._a_long * (dosed - self._stoich_prev - self._long)
        self._sensor += self._a_sensor * (obs[:, 3] - self._sensor)
        self._temp += self._a_temp * (obs[:, 1] - self._temp)
        self._stoich_prev = stoich
        self._history[:, :-1] = self._history[:, 1:]
        self._history[:, -1] = self._features(obs, stoich)

    def output(self) -> np.ndarray:
        return self._history.reshape(self.num_envs, -1).astype(np.float32)

    def to_env_action(self, policy_action: np.ndarray) -> np.ndarray:
        """The environment action (normalised AdBlue rate, (num_envs, 1)) of a policy action: itself with
        ``action="rate"``; with ``action="anr"``, ANR = (a + 1) / 2 * max_anr times the stoichiometric rate of the
        latest observation, clipped to the injector range."""
        a = np.asarray(policy_action, dtype=np.float64).reshape(self.num_envs, -1)
        c = self.config
        if c.action == "rate":
            return a.astype(np.float32)
        anr = 0.5 * (np.clip(a[:, 0], -1.0, 1.0) + 1.0) * c.max_anr
        rate = np.clip(anr * self._stoich_prev, 0.0, c.max_rate_g_s)
        return (2.0 * rate / c.max_rate_g_s - 1.0).astype(np.float32)[:, None]

    def output_for(self, i: int) -> np.ndarray:
        return self._history[i].reshape(-1).astype(np.float32)


class PipelineVecEnv(VecEnvWrapper):
    """An SB3 ``VecEnv`` wrapper that feeds the environment's observations through an :class:`ObservationPipeline`.

    Terminal observations (``infos[i]["terminal_observation"]``) are passed through the pipeline too (the history
    of the ended episode advanced by its last observation), then the plant's pipeline restarts from its reset
    observation, like stable-baselines3's ``VecFrameStack``.
    """

    def __init__(self, venv: VecEnv, config: PipelineConfig) -> None:
        self.pipeline = ObservationPipeline(config, venv.num_envs)
        n = config.output_size
        space = spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float32)
        super().__init__(venv, observation_space=space)

    def reset(self) -> np.ndarray:
        obs = self.venv.reset()
        self.pipeline.start(obs)
        return self.pipeline.output()

    def step_async(self, actions: np.ndarray) -> None:
        self.venv.step_async(self.pipeline.to_env_action(actions))

    def step_wait(self) -> VecEnvStepReturn:
        obs, rewards, dones, infos = self.venv.step_wait()
        if not dones.any():
            self.pipeline.advance(obs)
            return self.pipeline.output(), rewards, dones, infos
        last = np.array(obs, copy=True)
        for i in np.flatnonzero(dones):
            last[i] = infos[i]["terminal_observation"]
        self.pipeline.advance(last)
        for i in np.flatnonzero(dones):
            infos[i]["terminal_observation"] = self.pipeline.output_for(int(i))
        self.pipeline.start(obs, dones)
        return self.pipeline.output(), rewards, dones, infos
