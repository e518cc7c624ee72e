"""Behaviour cloning of an offline dataset: the benchmark's offline baseline, a small torch MLP trained in seconds.

The policy input is the same as the RL policies' (:mod:`control.rl.pipeline`: features and a 4-step history of the
observation, normalised by the dataset's statistics), the target is the dataset's action (the normalised AdBlue
command, ``PipelineConfig(action="rate")``); mean-squared error, Adam. The result is an :class:`~control.rl.policy.
RLPolicy` saved and loaded like the RL policies (``algo: "BC"``; weights as NPZ arrays, no pickle).

Why not an offline-RL library: d3rlpy (maintained, torch) runs CQL/IQL/TD3+BC, but adds its own pinned dependency
set for one baseline; on datasets of a few episodes behaviour cloning of the expert is the informative lower bound
of what the expert data contain, and it trains in seconds on a CPU.
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from control.rl.pipeline import EXPECTED_OBSERVATION, ObservationPipeline, PipelineConfig

__all__ = ["BC_HYPERPARAMETERS", "MLPActor", "dataset_arrays", "train_bc"]

#: [chosen, not tuned] two hidden layers of 64 (as the PPO/SAC policies), Adam 1e-3, batch 256, 30 epochs
BC_HYPERPARAMETERS: dict[str, Any] = {"net_arch": [64, 64], "learning_rate": 1e-3, "batch_size": 256, "epochs": 30}


def _torch_module() -> Any:
    import torch

    class MLPActor(torch.nn.Module):
        """Linear-ReLU layers and a tanh output in [-1, 1]; ``predict`` as an SB3 policy's."""

        def __init__(self, input_size: int, net_arch: list[int] | tuple[int, ...] = (64, 64)) -> None:
            super().__init__()
            layers: list[Any] = []
            n = int(input_size)
            for width in net_arch:
                layers += [torch.nn.Linear(n, int(width)), torch.nn.ReLU()]
                n = int(width)
            layers.append(torch.nn.Linear(n, 1))
            self.net = torch.nn.Sequential(*layers)

        def forward(self, x: Any) -> Any:
            return torch.tanh(self.net(x))

        def predict(self, x: Any, deterministic: bool = True) -> tuple[np.ndarray, None]:
            with torch.no_grad():
                out = self(torch.as_tensor(np.asarray(x, dtype=np.float32)).reshape(-1, self.net[0].in_features))
            return out.numpy(), None

        def set_training_mode(self, mode: bool) -> None:
            self.train(mode)

    return MLPActor


def MLPActor(input_size: int, net_arch: list[int] | tuple[int, ...] = (64, 64)) -> Any:
    """The BC network: a torch module (built lazily so that importing this module needs no torch)."""
    return _torch_module()(input_size, net_arch)


def dataset_arrays(dataset: Any, pipeline: PipelineConfig) -> tuple[np.ndarray, np.ndarray]:
    """(inputs, actions) of every step of a Minari dataset: the pipeline output before each action (the pipeline
    restarted at each episode start, as the policy sees it in use) and the action taken."""
    xs, ys = [], []
    for ep in dataset.iterate_episodes():
        obs = np.asarray(ep.observations, dtype=np.float64)
        act = np.asarray(ep.actions, dtype=np.float64).reshape(-1, 1)
        if obs.shape[1] != len(EXPECTED_OBSERVATION):
            raise ValueError(f"dataset observations have {obs.shape[1]} entries, the pipeline takes "
                             f"{EXPECTED_OBSERVATION}")
        pipe = ObservationPipeline(pipeline, 1)
        pipe.start(obs[:1])
        for k in range(act.shape[0]):
            if k > 0:
                pipe.advance(obs[k:k + 1])
            xs.append(pipe.output()[0])
            ys.append(act[k])
    return np.asarray(xs, dtype=np.float64), np.asarray(ys, dtype=np.float32)


def train_bc(dataset: Any, seed: int = 0, pipeline: PipelineConfig | None = None,
             hyperparameters: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
    """Fit the BC network to a Minari dataset; returns ``(RLPolicy, metadata)`` (save it with
    :func:`control.rl.policy.save_policy`, passing ``policy.model``, ``policy.obs_mean``, ``policy.obs_var`` and
    the metadata)."""
    import torch

    from control.rl.policy import RLPolicy

    hp = {**BC_HYPERPARAMETERS, **(hyperparameters or {})}
    pipeline = pipeline or PipelineConfig(action="rate")
    if pipeline.action != "rate":
        raise ValueError("behaviour cloning predicts the dataset's action: use PipelineConfig(action='rate')")
    t0 = time.perf_counter()
    x, y = dataset_arrays(dataset, pipeline)
    mean, var = x.mean(axis=0), x.var(axis=0)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    net = MLPActor(x.shape[1], hp["net_arch"])
    policy = RLPolicy(net, pipeline, mean, var, metadata={"observation_names": list(EXPECTED_OBSERVATION)},
                      name="bc")
    xt = torch.as_tensor(policy.normalize(x))
    yt = torch.as_tensor(y)
    opt = torch.optim.Adam(net.parameters(), lr=float(hp["learning_rate"]))
    losses = []
    net.train()
    for _ in range(int(hp["epochs"])):
        perm = rng.permutation(len(xt))
        total = 0.0
        for i in range(0, len(perm), int(hp["batch_size"])):
            idx = torch.as_tensor(perm[i:i + int(hp["batch_size"])])
            loss = torch.mean((net(xt[idx]) - yt[idx]) ** 2)
            opt.zero_grad()
            loss.backward()
            opt.step()
            total += loss.item() * len(idx)
        losses.append(total / len(perm))
    net.eval()
    meta = {"algo": "BC", "observation_names": list(EXPECTED_OBSERVATION), "pipeline": pipeline.to_dict(),
            "env_kwargs": {}, "seed": int(seed),
            "hyperparameters": {"policy_kwargs": {"net_arch": hp["net_arch"]},
                                **{k: v for k, v in hp.items() if k != "net_arch"}},
            "dataset": str(dataset.spec.dataset_id), "samples": len(x), "timesteps": len(x),
            "wall_time_s": round(time.perf_counter() - t0, 2),
            "learning_curve": {"epoch": list(range(1, len(losses) + 1)), "mse": losses}}
    policy.metadata.update(meta)
    return policy, meta
