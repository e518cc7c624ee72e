"""Shipped RL policies: save, list and load them as :class:`~control.protocol.PolicyPredictor` objects.

A policy ``<name>`` is three files in ``control/policies/`` (or any folder), all plain data, no pickle:

* ``<name>_policy.npz``: the network weights, the ``state_dict`` of the stable-baselines3 policy as named float
  arrays (numpy NPZ, read with ``allow_pickle=False``);
* ``<name>_vecnormalize.npz``: observation normalisation, ``mean`` and ``var`` of the pipeline output;
* ``<name>.json``: metadata (JSON): algorithm, network settings (``hyperparameters.policy_kwargs``), observation
  layout, env kwargs, pipeline, normaliser settings, exact training command, seed, timesteps, wall time, versions,
  evaluation; ``format_version`` (:data:`FORMAT_VERSION`) and ``files`` (names of the two NPZ files, which must lie
  in the JSON's own folder).

:func:`load_policy` builds the SB3 policy network from the metadata (:func:`build_sb3_policy`) and loads the arrays
into it after checking their names, shapes, dtypes and finiteness; nothing is unpickled. Policies of format
version 1 (an SB3 ``.zip``) still load: only the zip's ``policy.pth`` member is read, by
``torch.load(weights_only=True)``, never the zip's pickled ``data``; :func:`convert_policy` rewrites them in
version 2. Any problem with a policy file raises :class:`PolicyFileError` (a ``ValueError``) naming the file.

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
from scr_env.fileio import atomic_path, write_json

__all__ = ["FORMAT_VERSION", "POLICY_DIR", "PolicyFileError", "RLPolicy", "available_policies", "build_sb3_policy",
           "convert_policy", "load_policy", "save_policy", "versions"]

#: where the shipped policies live (package data: control/policies/**)
POLICY_DIR = Path(__file__).resolve().parent.parent / "policies"
#: the policy file format written by :func:`save_policy` (2: weights as NPZ arrays); versions 1 and 2 are read
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)
#: keys of ``hyperparameters.policy_kwargs`` passed to the SB3 policy constructor (the rest is ignored)
_POLICY_KWARGS = ("net_arch", "log_std_init", "use_sde", "n_critics", "share_features_extractor", "ortho_init",
                  "squash_output", "full_std", "use_expln", "clip_mean", "normalize_images")


class PolicyFileError(ValueError):
    """A policy file (metadata JSON or weights) that cannot be loaded; the message names the file."""


def versions() -> dict[str, str]:
    """Versions of the packages a policy depends on (stored in its metadata)."""
    import gymnasium
    import stable_baselines3
    import torch

    return {"stable_baselines3": stable_baselines3.__version__, "torch": torch.__version__,
            "gymnasium": gymnasium.__version__, "numpy": np.__version__, "python": platform.python_version()}


def _policy_class(algo: str) -> Any:
    """The stable-baselines3 policy class of an algorithm (the network its ``MlpPolicy`` builds)."""
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.sac.policies import SACPolicy
    from stable_baselines3.td3.policies import TD3Policy

    classes = {"PPO": ActorCriticPolicy, "SAC": SACPolicy, "TD3": TD3Policy}
    if not isinstance(algo, str) or algo.upper() not in classes:
        raise ValueError(f"unknown algorithm {algo!r}; one of {sorted(classes)}")
    return classes[algo.upper()]


def build_sb3_policy(algo: str, input_size: int, policy_kwargs: dict[str, Any] | None = None) -> Any:
    """A fresh stable-baselines3 policy network (PPO's ``ActorCriticPolicy``, ``SACPolicy`` or ``TD3Policy``; for
    ``"BC"`` the behaviour-cloning MLP of :mod:`control.rl.bc`) for
    ``input_size`` normalised inputs and one action in [-1, 1], with the ``net_arch`` (and, for PPO,
    ``log_std_init``) of ``policy_kwargs``; in evaluation mode, on the CPU. The weights are SB3's initial ones:
    load a ``state_dict`` into it."""
    if isinstance(algo, str) and algo.upper() == "BC":  # behaviour cloning's MLP (control.rl.bc)
        from control.rl.bc import MLPActor

        net = MLPActor(int(input_size), list((policy_kwargs or {}).get("net_arch", (64, 64))))
        net.set_training_mode(False)
        return net
    cls = _policy_class(algo)
    kwargs = {k: v for k, v in (policy_kwargs or {}).items() if k in _POLICY_KWARGS}
    obs_space = spaces.Box(-np.inf, np.inf, shape=(int(input_size),), dtype=np.float32)
    act_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
    policy = cls(obs_space, act_space, lambda _: 0.0, **kwargs)
    policy.set_training_mode(False)
    return policy


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
    """Write ``<name>_policy.npz`` (the weights of ``model.policy`` as arrays), ``<name>_vecnormalize.npz`` and
    ``<name>.json`` to ``folder`` (each atomically, the JSON last); return the JSON path.

    ``model``: a trained SB3 model (its ``policy.state_dict()`` is saved) or a policy network itself.
    ``metadata`` must hold ``algo``, ``observation_names``, ``env_kwargs`` and ``pipeline`` (a PipelineConfig dict),
    and the network settings in ``hyperparameters.policy_kwargs`` (SB3's defaults if absent); the file names, the
    normaliser settings, the format version and the package versions are added here.
    """
    for key in ("algo", "observation_names", "env_kwargs", "pipeline"):
        if key not in metadata:
            raise ValueError(f"metadata needs {key!r}")
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    net = getattr(model, "policy", model)
    weights = {k: v.detach().cpu().numpy() for k, v in net.state_dict().items()}
    weights_path = folder / f"{name}_policy.npz"
    _write_npz(weights_path, weights)
    npz_path = folder / f"{name}_vecnormalize.npz"
    _write_npz(npz_path, {"mean": np.asarray(obs_mean, dtype=np.float64), "var": np.asarray(obs_var, dtype=np.float64)})
    meta = dict(metadata)
    meta.update({
        "name": name, "format_version": FORMAT_VERSION,
        "files": {"model": weights_path.name, "normalizer": npz_path.name},
        "normalizer": {"clip_obs": float(clip_obs), "epsilon": float(epsilon),
                       "input_names": list(PipelineConfig.from_dict(metadata["pipeline"]).output_names)},
        "versions": versions(),
    })
    json_path = folder / f"{name}.json"
    write_json(json_path, meta)
    return json_path


def _write_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def available_policies(folder: str | Path | None = None) -> list[str]:
    """Names of the policies in ``folder`` (default: the shipped ones): the ``.json`` files with a ``files.model``
    entry whose file exists beside them."""
    folder = POLICY_DIR if folder is None else Path(folder)
    if not folder.is_dir():
        return []
    names = []
    for p in sorted(folder.glob("*.json")):
        try:
            meta = json.loads(p.read_text(encoding="utf-8"))
            model = meta["files"]["model"]
        except (ValueError, KeyError, TypeError, OSError):
            continue
        if isinstance(model, str) and (folder / Path(model).name).is_file():
            names.append(p.stem)
    return names


def _resolve(name_or_path: str | Path) -> Path:
    p = Path(name_or_path)
    if p.suffix == ".json" and p.is_file():
        return p
    if p.with_suffix(".json").is_file() and p.parent != Path("."):
        return p.with_suffix(".json")
    shipped = POLICY_DIR / f"{name_or_path}.json"
    if shipped.is_file():
        return shipped
    raise ValueError(f"no policy {str(name_or_path)!r}: shipped policies are {available_policies()}; or give the "
                     f"path of a policy's .json")


def _member(json_path: Path, files: Any, key: str) -> Path:
    """The file ``files[key]`` of a policy: a plain file name, in the folder of its JSON (PolicyFileError else)."""
    if not isinstance(files, dict) or not isinstance(files.get(key), str):
        raise PolicyFileError(f"{json_path}: 'files' must map {key!r} to a file name")
    name = files[key]
    if Path(name).name != name or name in ("", ".", ".."):
        raise PolicyFileError(f"{json_path}: files.{key} = {name!r} must be a file name in the policy's own folder "
                              f"(no directories, no absolute path)")
    path = json_path.parent / name
    if not path.is_file():
        raise PolicyFileError(f"{json_path}: files.{key} = {name!r} does not exist beside it")
    return path


def _read_weights(json_path: Path, meta: dict[str, Any]) -> dict[str, np.ndarray]:
    """The policy's state dict as numpy arrays: version 2 from the NPZ (``allow_pickle=False``), version 1 from the
    ``policy.pth`` member of the SB3 zip by ``torch.load(weights_only=True)`` (the zip's pickled data is never
    read)."""
    path = _member(json_path, meta.get("files"), "model")
    version = meta.get("format_version")
    try:
        if version == 1:
            import io
            import zipfile

            import torch

            with zipfile.ZipFile(path) as z:
                raw = z.read("policy.pth")
            buffer = io.BytesIO(raw)
            state = torch.load(buffer, map_location="cpu", weights_only=True)
            if not isinstance(state, dict):
                raise PolicyFileError(f"{path}: policy.pth is not a state dict")
            return {str(k): v.detach().cpu().numpy() for k, v in state.items()}
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except PolicyFileError:
        raise
    except Exception as exc:  # noqa: BLE001  (any unreadable file: one clear error naming it)
        raise PolicyFileError(f"{path}: cannot read the policy weights ({type(exc).__name__}: {exc})") from None


def _load_network(json_path: Path, meta: dict[str, Any], input_size: int) -> Any:
    """The SB3 policy network of the metadata with the checked weights loaded."""
    import torch

    hp = meta.get("hyperparameters") or {}
    if not isinstance(hp, dict):
        raise PolicyFileError(f"{json_path}: 'hyperparameters' must be a dict")
    try:
        net = build_sb3_policy(meta["algo"], input_size, hp.get("policy_kwargs"))
    except (ValueError, TypeError, KeyError) as exc:
        raise PolicyFileError(f"{json_path}: cannot build the policy network from the metadata: {exc}") from None
    weights = _read_weights(json_path, meta)
    expected = net.state_dict()
    missing = sorted(set(expected) - set(weights))
    extra = sorted(set(weights) - set(expected))
    if missing or extra:
        raise PolicyFileError(f"{json_path}: the weights do not fit the network of the metadata (missing "
                              f"{missing[:5]}, unexpected {extra[:5]})")
    state = {}
    for key, ref in expected.items():
        arr = weights[key]
        if tuple(arr.shape) != tuple(ref.shape):
            raise PolicyFileError(f"{json_path}: weight {key!r} has shape {tuple(arr.shape)}, the network of the "
                                  f"metadata needs {tuple(ref.shape)}")
        if arr.dtype.kind not in "fiu" or (arr.dtype.kind == "f" and not np.all(np.isfinite(arr))):
            raise PolicyFileError(f"{json_path}: weight {key!r} must be finite real numbers (dtype {arr.dtype})")
        state[key] = torch.as_tensor(np.array(arr, dtype=np.dtype(str(ref.dtype).replace("torch.", ""))))
    net.load_state_dict(state, strict=True)
    net.set_training_mode(False)
    return net


def load_policy(name_or_path: str | Path, observation_names: tuple[str, ...] | None = None,
                device: str = "cpu") -> RLPolicy:
    """Load a shipped policy (``"ppo"``, ``"sac"``; see :func:`available_policies`) or one saved by
    :func:`save_policy` (path of its ``.json``) as an :class:`RLPolicy` satisfying the policy protocol.

    ``observation_names``: the layout of the environment it will run on (e.g. ``env.unwrapped.observation_names``);
    a layout different from the one of training raises ``ValueError`` (so does :meth:`RLPolicy.attach`). A damaged
    or unknown file raises :class:`PolicyFileError` naming it. Nothing is unpickled. ``device``: only ``"cpu"``.
    """
    if device != "cpu":
        raise ValueError(f"device must be 'cpu' (the policies are small MLPs), got {device!r}")
    json_path = _resolve(name_or_path)
    try:
        meta = json.loads(json_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise PolicyFileError(f"{json_path}: not a readable policy JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise PolicyFileError(f"{json_path}: a policy JSON must hold an object")
    version = meta.get("format_version")
    if isinstance(version, bool) or version not in READABLE_VERSIONS:
        raise PolicyFileError(f"{json_path}: format_version {version!r} is not one this version reads "
                              f"{READABLE_VERSIONS}; update the project or re-save the policy")
    for key in ("observation_names", "pipeline", "algo", "files"):
        if key not in meta:
            raise PolicyFileError(f"{json_path}: metadata has no {key!r}")
    name = str(meta.get("name", json_path.stem))
    trained_names = tuple(meta["observation_names"])
    if trained_names != EXPECTED_OBSERVATION:
        raise ValueError(f"policy {name!r} was trained on observations {trained_names}; this version of the "
                         f"observation pipeline takes {EXPECTED_OBSERVATION}")
    if observation_names is not None:
        check_observation_layout(trained_names, tuple(observation_names), name)
    try:
        pipeline = PipelineConfig.from_dict(meta["pipeline"])
    except (TypeError, ValueError) as exc:
        raise PolicyFileError(f"{json_path}: bad 'pipeline' ({exc})") from None
    norm_path = _member(json_path, meta["files"], "normalizer")
    try:
        with np.load(norm_path, allow_pickle=False) as z:
            mean, var = np.asarray(z["mean"], dtype=np.float64), np.asarray(z["var"], dtype=np.float64)
    except Exception as exc:  # noqa: BLE001
        raise PolicyFileError(f"{norm_path}: cannot read the normaliser ({type(exc).__name__}: {exc})") from None
    if mean.shape != (pipeline.output_size,) or var.shape != mean.shape:
        raise PolicyFileError(f"{norm_path}: normaliser has {mean.shape} / {var.shape} entries, the pipeline gives "
                              f"{pipeline.output_size}")
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(var)) and np.all(var >= 0)):
        raise PolicyFileError(f"{norm_path}: normaliser mean and var must be finite, var >= 0")
    model = _load_network(json_path, meta, pipeline.output_size)
    norm = meta.get("normalizer", {})
    return RLPolicy(model, pipeline, mean, var, clip_obs=norm.get("clip_obs", 10.0),
                    epsilon=norm.get("epsilon", 1e-8), metadata=meta, name=name)


def convert_policy(src_json: str | Path, folder: str | Path | None = None, name: str | None = None) -> Path:
    """Rewrite a policy of any readable format version as the current one (``<name>_policy.npz`` + normaliser NPZ +
    JSON) in ``folder`` (default: its own); the weights are read as :func:`load_policy` reads them. Returns the new
    JSON path; the old weights file is left in place (delete it yourself)."""
    src_json = _resolve(src_json)
    policy = load_policy(src_json)
    meta = {k: v for k, v in policy.metadata.items() if k not in ("files", "format_version", "normalizer", "name")}
    meta["converted_from"] = {"format_version": policy.metadata.get("format_version"),
                              "files": policy.metadata.get("files"), "versions": policy.metadata.get("versions")}
    norm = policy.metadata.get("normalizer", {})
    return save_policy(policy.model, policy.obs_mean, policy.obs_var, folder or src_json.parent,
                       name or policy.name, meta, clip_obs=norm.get("clip_obs", 10.0),
                       epsilon=norm.get("epsilon", 1e-8))
