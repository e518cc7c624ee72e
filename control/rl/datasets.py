"""Offline datasets of the benchmark tasks in Minari format, collected locally with Minari's ``DataCollector``.

For each dataset group of the main tasks (``fresh``: WHTC and WHSC, which share their training distribution;
``aged``; ``randomised``; :data:`scr_env.tasks.Task.dataset_group`), four datasets, ids
``scr-dosing/<group>/<kind>-v0``:

* ``expert``: the oracle NMPC (:func:`control.factory.oracle_mpc`: privileged state and the cycle preview, which
  the dataset never contains);
* ``medium``: the look-up table (:class:`control.baselines.LookupTableDosing`), episodes alternating with the
  feedforward + PI baseline (:class:`control.baselines.FeedforwardPI`);
* ``random``: uniform random actions in [-1, 1] (seeded);
* ``mixed``: the union of the three (``minari.combine_datasets``).

Episodes run on the task's **training distribution** (hot random cycles, a new one per episode; the Aged group at
a random age, the randomised group on a random catalyst), never on the held-out WHTC/WHSC evaluation; episode i is
``reset(seed=seed + i)``, so the same policy and seed give the same episode again (the test checks the returns).

What a step records: the observation the task's environment gives (upstream NOx ppm, inlet temperature K, exhaust
flow mol/s, tailpipe NOx sensor ppm -- cross-sensitive to NH3 --, previous action), the action (normalised AdBlue
command in [-1, 1]), the reward (the environment's economic reward), terminations (never) and truncations (end of
the cycle). **Omitted**: the NH3 coverage and temperatures of the catalyst cells, the catalyst's parameters and age,
the tailpipe NOx/NH3 split, the cycle preview the expert used, and the info dicts -- privileged state is never in a
dataset. Storage: Minari's HDF5 format (arrays and JSON metadata; nothing pickled).

The datasets live under ``MINARI_DATASETS_PATH`` (Minari's variable; :func:`datasets_root` sets it for a block):

    MINARI_DATASETS_PATH=runs/datasets python -m experiments.make_datasets
    MINARI_DATASETS_PATH=runs/datasets python -c \
        "import minari; print(minari.load_dataset('scr-dosing/fresh/expert-v0'))"
"""
from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["DATASET_GROUPS", "KINDS", "behaviour_policy", "collect", "dataset_id", "datasets_root", "make_group"]

KINDS = ("expert", "medium", "random", "mixed")
#: dataset groups and the task whose training distribution each is collected on
DATASET_GROUPS = {"fresh": "scr_env/UreaSCR-WHTC-v0", "aged": "scr_env/UreaSCR-Aged-v0",
                  "randomised": "scr_env/UreaSCR-Randomised-v0"}


def dataset_id(group: str, kind: str) -> str:
    """``scr-dosing/<group>/<kind>-v0``."""
    if group not in DATASET_GROUPS:
        raise ValueError(f"group must be one of {sorted(DATASET_GROUPS)}, got {group!r}")
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    return f"scr-dosing/{group}/{kind}-v0"


@contextlib.contextmanager
def datasets_root(path: str | os.PathLike | None) -> Iterator[Path | None]:
    """Set ``MINARI_DATASETS_PATH`` to ``path`` inside the block (None: leave it as it is)."""
    if path is None:
        yield None
        return
    old = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(Path(path).resolve())
    try:
        yield Path(path)
    finally:
        if old is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = old


class _RandomPolicy:
    """Uniform random actions in [-1, 1] from its own seeded generator (restarted by :meth:`reseed`)."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def reseed(self, seed: int) -> None:
        self.rng = np.random.default_rng(seed)

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        return self.rng.uniform(-1.0, 1.0, size=(1,)).astype(np.float32), state


def behaviour_policy(kind: str, episode: int, seed: int = 0, quick: bool = False) -> tuple[Any, str]:
    """(policy, name) of episode ``episode`` of a dataset ``kind`` (``medium`` alternates the look-up table and
    the PI baseline; ``random`` is seeded by ``seed + episode``)."""
    from control.baselines import FeedforwardPI, LookupTableDosing
    from control.factory import oracle_mpc

    if kind == "expert":
        return oracle_mpc(quick=quick), "oracle_mpc"
    if kind == "medium":
        return (LookupTableDosing(), "lookup_table") if episode % 2 == 0 else (FeedforwardPI(), "pi")
    if kind == "random":
        return _RandomPolicy(seed + episode), "uniform_random"
    raise ValueError(f"kind must be one of expert, medium, random (mixed is combined), got {kind!r}")


def collect(group: str, kind: str, episodes: int, seed: int = 0, duration_s: float = 900.0, quick: bool = False,
            max_steps: int | None = None) -> Any:
    """Collect and write one dataset (``kind`` in expert, medium, random) under ``MINARI_DATASETS_PATH``; returns
    the :class:`minari.MinariDataset`. An existing dataset of the same id is replaced."""
    import gymnasium as gym
    import minari

    from scr_env.tasks import get_task

    task = get_task(DATASET_GROUPS[group])
    did = dataset_id(group, kind)
    with contextlib.suppress(FileNotFoundError, ValueError):
        minari.delete_dataset(did)
    env = minari.DataCollector(gym.make(task.id, **{**task.train_kwargs(), "random_cycle_duration_s": duration_s}))
    names = []
    for i in range(int(episodes)):
        policy, name = behaviour_policy(kind, i, seed, quick)
        names.append(name)
        obs, _ = env.reset(seed=seed + i)
        if hasattr(policy, "attach"):
            policy.attach(env.unwrapped)
        k, state = 0, None
        while True:
            action, state = policy.predict(obs, state=state, episode_start=np.array([k == 0]), deterministic=True)
            obs, _, terminated, truncated, _ = env.step(np.asarray(action, dtype=np.float32).reshape(1))
            k += 1
            if terminated or truncated or (max_steps is not None and k >= max_steps):
                break
    ds = env.create_dataset(
        dataset_id=did, eval_env=task.id, algorithm_name=f"{kind}: " + ", ".join(sorted(set(names))),
        author="scr-dosing", code_permalink="experiments/make_datasets.py",
        description=(f"{kind} episodes on the training distribution of {task.id} ({group}): hot random cycles of "
                     f"{duration_s:g} s, reset seeds {seed}..{seed + int(episodes) - 1}, policies {names}. "
                     f"Observations as the task's environment gives them; no privileged state (see "
                     f"control.rl.datasets)."),
        requirements=["scr-dosing"])
    env.close()
    return ds


def make_group(group: str, episodes: int = 4, seed: int = 0, duration_s: float = 900.0, quick: bool = False,
               max_steps: int | None = None, kinds: tuple[str, ...] = KINDS) -> dict[str, Any]:
    """All datasets of a group (``mixed`` = the union of the others, made last); ``{kind: MinariDataset}``."""
    import minari

    made = {k: collect(group, k, episodes, seed, duration_s, quick, max_steps) for k in kinds if k != "mixed"}
    if "mixed" in kinds:
        with contextlib.suppress(FileNotFoundError, ValueError):
            minari.delete_dataset(dataset_id(group, "mixed"))
        parts = [made.get(k) or minari.load_dataset(dataset_id(group, k)) for k in ("expert", "medium", "random")]
        made["mixed"] = minari.combine_datasets(parts, dataset_id(group, "mixed"))
    return made
