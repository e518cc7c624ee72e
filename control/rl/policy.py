"""Shipped RL policies: save, list and load them as :class:`~control.protocol.PolicyPredictor` objects.

A shipped policy ``<name>`` is three files in ``control/policies/`` (or any folder):

* ``<name>.zip``: the stable-baselines3 model (network weights, hyperparameters), an SB3 zip;
* ``<name>_vecnormalize.npz``: observation normalisation, ``mean`` and ``var`` of the pipeline output (numpy NPZ, no
  pickle);
* ``<name>.json``: metadata (JSON): algorithm, observation layout, env kwargs, pipeline, normaliser settings, exact
  training command, seed, timesteps, wall time, versions, evaluation.

The SB3 zip holds a JSON of the hyperparameters with a few cloudpickled entries (spaces, schedules) and the weights
as ``torch.save`` files; that is the stable-baselines3 standard. :func:`load_policy` passes the spaces and the
schedules in ``custom_objects``, so those pickled entries are never unpickled, and SB3 loads the weights with
``torch.load(weights_only=True)``. Load zips only from sources you trust all the same.

    from control.rl import load_policy
    policy = load_policy("ppo")                    # satisfies control.protocol.PolicyPredictor
    action, _ = policy.predict(obs, episode_start=np.array([True]))
"""
from __future__ import annotations

import json
import platform
from pathlib import Path
from typing import Any

import numpy as np
from gymnasium import spaces

from control.protocol import check_observation
from control.rl.pipeline import EXPECTED_OBSERVATION, ObservationPipeline, PipelineConfig
from scr_env.fileio import write_json

__all__ = ["POLICY_DIR", "RLPolicy", "available_policies", "load_policy", "save_policy", "versions"]

#: where the shipped policies live (package data: control/policies/**)
POLICY_DIR = Path(__file__).resolve().parent.parent / "policies"
FORMAT_VERSION = 1


def versions() -> dict[str, str]:
    """Versions of the packages a policy depends on (stored in its metadata)."""
    import gymnasium
    import stable_baselines3
    import torch

    return {"stable_baselines3": stable_baselines3.__version__, "torch": torch.__version__,
            "gymnasium": gymnasium.__version__, "numpy": np.__version__, "python": platform.python_version()}


def _algo_class(algo: str) -> Any:
    from stable_baselines3 import PPO, SAC, TD3

    classes = {"PPO": PPO, "SAC": SAC, "TD3": TD3}
    if algo.upper() not in classes:
        raise ValueError(f"unknown algorithm {algo!r}; one of {sorted(classes)}")
    return classes[algo.upper()]


class RLPolicy:
    """A trained SB3 policy with its observation pipeline and normaliser: ``predict`` takes raw env observations.

    Parameters
    ----------
    model : the SB3 model (only its ``predict`` is used).
    pipeline : the :class:`PipelineConfig` it was trained with.
    obs_mean, obs_var : VecNormalize statistics of the pipeline output, shape (pipeline.output_size,).
    clip_obs, epsilon : VecNormalize settings.
    metadata : the policy's metadata (``observation_names`` is checked by :meth:`attach`).
    name : label.

    The pipeline state (history, moving averages) is kept inside the object, restarted whenever
    ``episode_start`` is True (or at the first call); ``state`` is passed through unchanged (None).
    Observations of shape (5,) give an action of shape (1,); a batch (B, 5) gives (B, 1). An observation with NaN or
    inf, or of another size than the policy's layout, raises ``ValueError``
    (:func:`control.protocol.check_observation`) before the pipeline state is touched: one bad reading does not
    poison the history and moving averages of the rest of the episode.
    """

    def __init__(self, model: Any, pipeline: PipelineConfig, obs_mean: np.ndarray, obs_var: np.ndarray,
                 clip_obs: float = 10.0, epsilon: float = 1e-8, metadata: dict[str, Any] | None = None,
                 name: str = "rl") -> None:
        self.model = model
        self.pipeline_config = pipeline
        self.obs_mean = np.asarray(obs_mean, dtype=np.float64)
        self.obs_var = np.asarray(obs_var, dtype=np.float64)
        if self.obs_mean.shape != (pipeline.output_size,) or self.obs_var.shape != (pipeline.output_size,):
            raise ValueError(f"normaliser statistics must have shape ({pipeline.output_size},), got "
                             f"{self.obs_mean.shape} and {self.obs_var.shape}")
        self.clip_obs = float(clip_obs)
        self.epsilon = float(epsilon)
        self.metadata = dict(metadata or {})
        self.name = name
        self._pipe: ObservationPipeline | None = None
        self._scale = 1.0 / np.sqrt(self.obs_var + self.epsilon)

    @property
    def observation_names(self) -> tuple[str, ...]:
        return tuple(self.metadata.get("observation_names", EXPECTED_OBSERVATION))

    def normalize(self, x: np.ndarray) -> np.ndarray:
        """The VecNormalize transform of pipeline outputs (float32)."""
        return np.clip((x - self.obs_mean) * self._scale, -self.clip_obs, self.clip_obs).astype(np.float32)

    def attach(self, env: Any) -> None:
        """Evaluation hook: check that ``env`` has the observation layout, dt and AdBlue range of training."""
        check_observation_layout(self.observation_names, tuple(getattr(env, "observation_names", ())), self.name)
        c = self.pipeline_config
        dt = float(getattr(env, "dt", c.dt))
        rate = float(getattr(env, "max_rate_g_s", c.max_rate_g_s))
        if abs(dt - c.dt) > 1e-9 or abs(rate - c.max_rate_g_s) > 1e-9:
            raise ValueError(f"policy {self.name!r} was trained with dt = {c.dt} s and max_rate_g_s = "
                             f"{c.max_rate_g_s} g/s; the environment has dt = {dt} s, max_rate_g_s = {rate} g/s")

    def predict(self, observation: np.ndarray, state: Any = None, episode_start: np.ndarray | None = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        names = self.observation_names
        batch, single = check_observation(observation, len(names), max_batch=None, owner=f"policy {self.name!r}",
                                          names=names)
        b = batch.shape[0]
        if episode_start is None:
            starts = np.zeros(b, dtype=bool)
        else:
            starts = np.broadcast_to(np.asarray(episode_start, dtype=bool).reshape(-1), (b,)).copy()
        if self._pipe is None or self._pipe.num_envs != b:
            self._pipe = ObservationPipeline(self.pipeline_config, b)
            starts[:] = True
        if not starts.all():
            self._pipe.advance(batch)
        self._pipe.start(batch, starts)
        x = self.normalize(self._pipe.output())
        action, _ = self.model.predict(x, deterministic=deterministic)
        action = self._pipe.to_env_action(action).reshape(b, -1)
        return (action[0] if single else action), state

    def reset(self) -> None:
        """Forget the pipeline state (the next call starts an episode)."""
        self._pipe = None


def check_observation_layout(expected: tuple[str, ...], got: tuple[str, ...], name: str = "policy") -> None:
    """ValueError unless the observation names ``got`` equal ``expected`` (those of training)."""
    if tuple(got) != tuple(expected):
        raise ValueError(f"{name!r} was trained on observations {tuple(expected)} but the environment gives "
                         f"{tuple(got)}; make the environment with the policy's env_kwargs "
                         f"(see its metadata JSON) or retrain")


def save_policy(model: Any, obs_mean: np.ndarray, obs_var: np.ndarray, folder: str | Path, name: str,
                metadata: dict[str, Any], clip_obs: float = 10.0, epsilon: float = 1e-8) -> Path:
    """Write ``<name>.zip``, ``<name>_vecnormalize.npz`` and ``<name>.json`` to ``folder``; return the JSON path.

    ``metadata`` must hold ``algo``, ``observation_names``, ``env_kwargs`` and ``pipeline`` (a PipelineConfig dict);
    the file names, the normaliser settings, the format version and the package versions are added here.
    """
    for key in ("algo", "observation_names", "env_kwargs", "pipeline"):
        if key not in metadata:
            raise ValueError(f"metadata needs {key!r}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    zip_path = folder / f"{name}.zip"
    model.save(zip_path)
    npz_path = folder / f"{name}_vecnormalize.npz"
    np.savez(npz_path, mean=np.asarray(obs_mean, dtype=np.float64), var=np.asarray(obs_var, dtype=np.float64))
    meta = dict(metadata)
    meta.update({
        "name": name, "format_version": FORMAT_VERSION,
        "files": {"model": zip_path.name, "normalizer": npz_path.name},
        "normalizer": {"clip_obs": float(clip_obs), "epsilon": float(epsilon),
                       "input_names": list(PipelineConfig.from_dict(metadata["pipeline"]).output_names)},
        "versions": versions(),
    })
    json_path = folder / f"{name}.json"
    write_json(json_path, meta)
    return json_path


def available_policies(folder: str | Path | None = None) -> list[str]:
    """Names of the policies in ``folder`` (default: the shipped ones), i.e. those with a ``.json`` and a ``.zip``."""
    folder = POLICY_DIR if folder is None else Path(folder)
    if not folder.is_dir():
        return []
    return sorted(p.stem for p in folder.glob("*.json") if (folder / f"{p.stem}.zip").is_file())


def _resolve(name_or_path: str | Path) -> Path:
    p = Path(name_or_path)
    if p.suffix == ".json" and p.is_file():
        return p
    if p.suffix == ".zip" and p.with_suffix(".json").is_file():
        return p.with_suffix(".json")
    if p.with_suffix(".json").is_file() and p.parent != Path("."):
        return p.with_suffix(".json")
    shipped = POLICY_DIR / f"{name_or_path}.json"
    if shipped.is_file():
        return shipped
    raise ValueError(f"no policy {str(name_or_path)!r}: shipped policies are {available_policies()}; or give the "
                     f"path of a policy's .json")


def load_policy(name_or_path: str | Path, observation_names: tuple[str, ...] | None = None,
                device: str = "cpu") -> RLPolicy:
    """Load a shipped policy (``"ppo"``, ``"sac"``; see :func:`available_policies`) or one saved by
    :func:`save_policy` (path of its ``.json``) as an :class:`RLPolicy` satisfying the policy protocol.

    ``observation_names``: the layout of the environment it will run on (e.g. ``env.unwrapped.observation_names``);
    a layout different from the one of training raises ``ValueError`` (so does :meth:`RLPolicy.attach`).
    """
    json_path = _resolve(name_or_path)
    meta = json.loads(json_path.read_text(encoding="utf-8"))
    name = str(meta.get("name", json_path.stem))
    trained_names = tuple(meta["observation_names"])
    if trained_names != EXPECTED_OBSERVATION:
        raise ValueError(f"policy {name!r} was trained on observations {trained_names}; this version of the "
                         f"observation pipeline takes {EXPECTED_OBSERVATION}")
    if observation_names is not None:
        check_observation_layout(trained_names, tuple(observation_names), name)
    pipeline = PipelineConfig.from_dict(meta["pipeline"])
    files = meta["files"]
    with np.load(json_path.parent / files["normalizer"], allow_pickle=False) as z:
        mean, var = z["mean"], z["var"]
    if mean.shape != (pipeline.output_size,):
        raise ValueError(f"policy {name!r}: normaliser has {mean.shape} entries, the pipeline gives "
                         f"{pipeline.output_size}")
    algo = _algo_class(meta["algo"])
    obs_space = spaces.Box(-np.inf, np.inf, shape=(pipeline.output_size,), dtype=np.float32)
    act_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
    custom = {"observation_space": obs_space, "action_space": act_space, "lr_schedule": lambda _: 0.0,
              "learning_rate": 0.0, "clip_range": lambda _: 0.2, "clip_range_vf": None,
              "_last_obs": None, "_last_original_obs": None, "_last_episode_starts": None}
    model = algo.load(json_path.parent / files["model"], device=device, custom_objects=custom)
    norm = meta.get("normalizer", {})
    return RLPolicy(model, pipeline, mean, var, clip_obs=norm.get("clip_obs", 10.0),
                    epsilon=norm.get("epsilon", 1e-8), metadata=meta, name=name)
