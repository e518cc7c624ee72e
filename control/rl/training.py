"""Training of PPO, SAC and TD3 on the native vector environment, with the documented hyperparameters.

The training stack, innermost first::

    UreaSCRVectorEnv (cycle="random", random_offsets=True)   one compiled call steps all plants
    -> GymVectorToSB3            SAME_STEP autoreset -> SB3 terminal_observation, TimeLimit.truncated
    -> VecMonitor                episode returns and lengths for the logs
    -> PipelineVecEnv            features + history (control.rl.pipeline), shipped with the policy; with
                                 PipelineConfig(action="anr") it also maps the policy's ANR to the AdBlue rate
    -> VecNormalize              observation and reward normalisation; observation statistics shipped as NPZ

Hyperparameters (:data:`HYPERPARAMETERS`) [chosen, not tuned beyond a couple of runs]: the discount reflects the
time scales of the plant: 0.5 s steps and NH3 storage time constants of a minute or more, so ``gamma = 0.995``
(effective horizon 1 / (1 - gamma) = 200 steps = 100 s) for PPO; SAC uses 0.99 (its bootstrapped critic is less
tolerant of long horizons and learns faster with it). PPO: 8 plants x 512 steps per update, small 64-64 networks
(the inputs are few and smooth), an initial action std of exp(-1) = 0.37 (about 0.55 g/s), which is enough to
explore a 3 g/s range. SAC: 16 plants, two gradient steps per vector step (one per 8 transitions), replay 200 k, 64-64
networks, learning rate 1e-3: on a 2-core machine shared with other jobs the gradient steps, not the simulator, set
the pace (a first run with 4 plants and one gradient step per 4 transitions managed under 100 environment steps/s).
SAC and TD3 train on the *raw* reward (observations normalised only): with VecNormalize's reward scaling the
per-step rewards were ~0.01, the entropy bonus dominated and SAC stayed at full dose for 75 k steps; the raw
reward (about -0.5 to -2 per step near ANR 1) is on the scale of the entropy term, whose weight starts at 0.1.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

from control.rl.pipeline import PipelineConfig, PipelineVecEnv
from control.rl.policy import save_policy
from control.rl.vec_env import make_sb3_vec_env

__all__ = ["ALGOS", "HYPERPARAMETERS", "TrainingResult", "make_training_env", "train"]

ALGOS = ("ppo", "sac", "td3")

#: per algorithm: constructor keyword arguments of the SB3 class, and ``num_envs``
HYPERPARAMETERS: dict[str, dict[str, Any]] = {
    "ppo": {
        "num_envs": 8,
        "kwargs": {"n_steps": 512, "batch_size": 512, "n_epochs": 10, "gamma": 0.995, "gae_lambda": 0.95,
                   "learning_rate": 3e-4, "clip_range": 0.2, "ent_coef": 0.0, "vf_coef": 0.5, "max_grad_norm": 0.5,
                   "policy_kwargs": {"net_arch": {"pi": [64, 64], "vf": [64, 64]}, "log_std_init": -1.0}},
    },
    "sac": {
        "num_envs": 16,
        "norm_reward": False,
        "kwargs": {"buffer_size": 200_000, "learning_starts": 5_000, "batch_size": 256, "gamma": 0.99,
                   "tau": 0.005, "learning_rate": 1e-3, "train_freq": 1, "gradient_steps": 2,
                   "ent_coef": "auto_0.1", "policy_kwargs": {"net_arch": [64, 64]}},
    },
    "td3": {
        "num_envs": 16,
        "norm_reward": False,
        "kwargs": {"buffer_size": 300_000, "learning_starts": 5_000, "batch_size": 256, "gamma": 0.99,
                   "tau": 0.005, "learning_rate": 1e-3, "train_freq": 1, "gradient_steps": 1,
                   "policy_kwargs": {"net_arch": [128, 128]}},
    },
}

#: arguments of the training environment (besides num_envs); the reward weights are the environment defaults
TRAIN_ENV_KWARGS: dict[str, Any] = {"cycle": "random", "random_offsets": True}
CLIP_OBS = 10.0


def make_training_env(num_envs: int, seed: int, pipeline: PipelineConfig, gamma: float,
                      env_kwargs: dict[str, Any] | None = None, norm_reward: bool = True) -> VecNormalize:
    """The training stack of the module docstring, seeded."""
    kw = dict(TRAIN_ENV_KWARGS)
    kw.update(env_kwargs or {})
    venv = make_sb3_vec_env(num_envs, **kw)
    venv.seed(seed)
    venv = VecMonitor(venv)
    venv = PipelineVecEnv(venv, pipeline)
    return VecNormalize(venv, norm_obs=True, norm_reward=norm_reward, clip_obs=CLIP_OBS, gamma=gamma)


class ProgressCallback(BaseCallback):
    """A tqdm progress bar (SB3's own needs ``rich``, which is not a dependency) and the episode KPIs in the logs."""

    def __init__(self, total_timesteps: int, show: bool = True) -> None:
        super().__init__()
        self.total = int(total_timesteps)
        self.show = show
        self._bar = None
        self._kpis: list[dict[str, float]] = []
        self._returns: list[float] = []
        #: learning curve: every 8 finished episodes, (timesteps, mean episode return, tailpipe NOx g/kWh, slip ppm)
        self.curve: dict[str, list[float]] = {"timesteps": [], "episode_return": [], "tailpipe_nox_g_per_kwh": [],
                                              "mean_nh3_slip_ppm": []}

    def _on_training_start(self) -> None:
        if self.show:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, unit="step", smoothing=0.05, mininterval=5.0)

    def _on_step(self) -> bool:
        if self._bar is not None:
            self._bar.update(self.training_env.num_envs)
        for info in self.locals.get("infos", ()):
            if "episode_kpis" in info:
                self._kpis.append(info["episode_kpis"])
            if "episode" in info:
                self._returns.append(float(info["episode"]["r"]))
        if len(self._kpis) >= 8:
            self.curve["timesteps"].append(int(self.num_timesteps))
            self.curve["episode_return"].append(float(np.mean(self._returns)) if self._returns else float("nan"))
            for key in ("tailpipe_nox_g_per_kwh", "mean_nh3_slip_ppm"):
                self.curve[key].append(float(np.nanmean([k[key] for k in self._kpis])))
            self._returns = []
            for key in ("tailpipe_nox_g_per_kwh", "mean_nh3_slip_ppm", "nox_conversion"):
                self.logger.record(f"kpi/{key}", float(np.nanmean([k[key] for k in self._kpis])))
            if self._bar is not None:
                self._bar.set_postfix(tp=f"{np.nanmean([k['tailpipe_nox_g_per_kwh'] for k in self._kpis]):.3f}",
                                      slip=f"{np.nanmean([k['mean_nh3_slip_ppm'] for k in self._kpis]):.1f}")
            self._kpis = []
        return True

    def _on_training_end(self) -> None:
        if self._bar is not None:
            self._bar.close()


class CheckpointCallback(BaseCallback):
    """Every ``every`` environment steps, save the policy in the shipped format (zip + NPZ + JSON) to ``folder``."""

    def __init__(self, every: int, folder: Path, name: str, metadata: dict[str, Any]) -> None:
        super().__init__()
        self.every = int(every)
        self.folder = Path(folder)
        self.name = name
        self.metadata = metadata
        self._next = self.every
        self._t0 = time.perf_counter()

    def _on_training_start(self) -> None:
        self._t0 = time.perf_counter()

    def _on_step(self) -> bool:
        if self.num_timesteps >= self._next:
            self._next += self.every
            norm = self.model.get_vec_normalize_env()
            meta = dict(self.metadata, timesteps=int(self.num_timesteps),
                        wall_time_s=round(time.perf_counter() - self._t0, 1))
            save_policy(self.model, norm.obs_rms.mean, norm.obs_rms.var, self.folder,
                        f"{self.name}_{self.num_timesteps}", meta, clip_obs=norm.clip_obs, epsilon=norm.epsilon)
        return True


class TrainingResult:
    """What :func:`train` returns: the model, its VecNormalize and the wall time [s]."""

    def __init__(self, model: Any, vec_normalize: VecNormalize, wall_time_s: float, metadata: dict[str, Any]):
        self.model = model
        self.vec_normalize = vec_normalize
        self.wall_time_s = wall_time_s
        self.metadata = metadata

    def save(self, folder: str | Path, name: str) -> Path:
        """Write the policy in the shipped format; return its JSON path."""
        norm = self.vec_normalize
        return save_policy(self.model, norm.obs_rms.mean, norm.obs_rms.var, folder, name, self.metadata,
                           clip_obs=norm.clip_obs, epsilon=norm.epsilon)


def train(algo: str, timesteps: int, seed: int = 0, num_envs: int | None = None, out: str | Path | None = None,
          pipeline: PipelineConfig | None = None, env_kwargs: dict[str, Any] | None = None,
          hyperparameters: dict[str, Any] | None = None, progress_bar: bool = True, checkpoint_every: int = 0,
          venv: Any = None, metadata: dict[str, Any] | None = None, verbose: int = 0) -> TrainingResult:
    """Train ``algo`` ("ppo", "sac", "td3") for ``timesteps`` environment steps and return a :class:`TrainingResult`.

    ``out``: run folder for TensorBoard logs (``out/tb``) and checkpoints (``out/checkpoints``); None logs nowhere.
    ``env_kwargs``: extra arguments of the training environment (e.g. ``reward_weights``).
    ``hyperparameters``: overrides of :data:`HYPERPARAMETERS` ``[algo]["kwargs"]``.
    ``venv``: a ready SB3 VecEnv to train on instead (e.g. the surrogate, :mod:`control.rl.surrogate`), already
    wrapped by the pipeline; it gets a VecNormalize here.
    """
    import torch
    from stable_baselines3 import PPO, SAC, TD3

    algo = algo.lower()
    if algo not in ALGOS:
        raise ValueError(f"algo must be one of {ALGOS}, got {algo!r}")
    if timesteps < 1:
        raise ValueError(f"timesteps must be positive, got {timesteps!r}")
    torch.set_num_threads(1)  # the machine is shared; one thread is also the fastest for 64-128 unit MLPs
    hp = HYPERPARAMETERS[algo]
    kwargs = dict(hp["kwargs"])
    kwargs.update(hyperparameters or {})
    n_envs = int(num_envs or hp["num_envs"])
    pipeline = pipeline or PipelineConfig()
    gamma = float(kwargs["gamma"])
    norm_reward = bool(hp.get("norm_reward", True))
    if venv is None:
        env = make_training_env(n_envs, seed, pipeline, gamma, env_kwargs, norm_reward=norm_reward)
    else:
        env = VecNormalize(venv, norm_obs=True, norm_reward=norm_reward, clip_obs=CLIP_OBS, gamma=gamma)
    n_envs = env.num_envs
    if algo == "ppo":
        kwargs["n_steps"] = min(int(kwargs["n_steps"]), max(timesteps // n_envs, 8))
        kwargs["batch_size"] = min(int(kwargs["batch_size"]), kwargs["n_steps"] * n_envs)
    else:
        kwargs["learning_starts"] = min(int(kwargs["learning_starts"]), max(timesteps // 4, 100))
    cls = {"ppo": PPO, "sac": SAC, "td3": TD3}[algo]
    if algo == "td3":
        from stable_baselines3.common.noise import NormalActionNoise

        kwargs.setdefault("action_noise", NormalActionNoise(np.zeros(1), 0.1 * np.ones(1)))
    tb = str(Path(out) / "tb") if out is not None else None
    model = cls("MlpPolicy", env, seed=seed, device="cpu", tensorboard_log=tb, verbose=verbose, **kwargs)
    full_env_kwargs = dict(TRAIN_ENV_KWARGS)
    full_env_kwargs.update(env_kwargs or {})
    meta = {
        "algo": algo.upper(),
        "observation_names": list(env.get_attr("observation_names")[0]) if venv is None
        else list(getattr(venv, "observation_names", ())),
        "env_kwargs": full_env_kwargs,
        "pipeline": pipeline.to_dict(),
        "seed": seed, "num_envs": n_envs,
        "hyperparameters": {k: v for k, v in kwargs.items() if k != "action_noise"},
        "norm_reward": norm_reward,
    }
    meta.update(metadata or {})
    progress = ProgressCallback(timesteps, show=progress_bar)
    callbacks: list[BaseCallback] = [progress]
    if checkpoint_every and out is not None:
        callbacks.append(CheckpointCallback(checkpoint_every, Path(out) / "checkpoints", algo, meta))
    t0 = time.perf_counter()
    model.learn(total_timesteps=int(timesteps), callback=callbacks, tb_log_name=algo)
    wall = time.perf_counter() - t0
    meta["timesteps"] = int(model.num_timesteps)
    meta["wall_time_s"] = round(wall, 1)
    meta["steps_per_s"] = round(model.num_timesteps / max(wall, 1e-9), 1)
    meta["learning_curve"] = progress.curve
    env.training = False
    return TrainingResult(model, env, wall, meta)
