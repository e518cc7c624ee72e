"""Named benchmark tasks: registered Gymnasium ids, each with a fixed training distribution and a fixed held-out
evaluation protocol, and one hard axis.

Importing ``scr_env`` registers them. ``gym.make(task_id)`` is the task's evaluation environment (its first
evaluation condition); :func:`make_eval_env` builds every condition, :func:`training_env_kwargs` gives the training
distribution (for ``gym.make`` or ``gym.make_vec(..., vectorization_mode="vector_entry_point")``), and
:func:`scr_env.benchmark.evaluate` scores a policy on the protocol.

* ``scr_env/UreaSCR-WHTC-v0`` -- hard axis: transient generalisation (random cycles in training, the real
  transient cycle in test). Training: hot random cycles of 1800 s, a new cycle per reset, fresh catalyst.
  Evaluation (held out): hot WHTC, reset seeds 0-4 (sensor noise), 5 episodes.
* ``scr_env/UreaSCR-WHSC-v0`` -- hard axis: high-temperature steady modes and load steps, where stored NH3 is
  released. Training: as WHTC (the same training runs serve both). Evaluation: hot WHSC, seeds 0-4, 5 episodes.
* ``scr_env/UreaSCR-Aged-v0`` -- hard axis: unobserved plant drift, the catalyst's hydrothermal age. Training: as
  WHTC, the age drawn uniformly in 0-16 h per episode. Evaluation: hot WHTC at 0, 4 and 16 h (one age per
  episode), seeds 0-1, 6 episodes.
* ``scr_env/UreaSCR-Randomised-v0`` -- hard axis: catalyst-to-catalyst spread (capacity, activity, volume +/-20 %,
  unobserved). Training: as WHTC, a randomised catalyst per episode. Evaluation: hot WHTC on 5 held-out catalysts
  drawn by reset seeds 100-104, 5 episodes.

Every task observes what most trucks measure -- upstream NOx, inlet temperature, exhaust flow, the tailpipe NOx sensor
(cross-sensitive to NH3) and the previous action; no NH3 sensor, no catalyst state (``nh3_sensor=False``,
``privileged=False``) -- and doses through the default actuator of :mod:`scr_env.actuator` (1 s lag, 1 g/s per s
slew limit), at dt = 0.5 s with sensor noise and the environment's default reward weights. A task fixes these; a
study that changes them is no longer on the task. The reward is the environment's; the task's score is not the
return but the normalised tailpipe NOx within the slip limit of :mod:`scr_env.benchmark`.

Ageing: with the ``phys`` stream's environment (``age_h`` argument) the ages are hours of hydrothermal ageing of the
CLEERS samples; before it, :func:`age_kwargs` maps them to the older severity ``ageing = age_h / 16`` and a training
range to its midpoint (with a warning), so the task runs but its training distribution is then not the stated one.
"""
from __future__ import annotations

import inspect
import warnings
from dataclasses import dataclass, field
from typing import Any

from gymnasium.envs.registration import register, registry

__all__ = ["MAIN_TASKS", "TASKS", "EvaluationProtocol", "Task", "age_kwargs", "get_task", "make_eval_env",
           "register_tasks", "training_env_kwargs"]

#: settings every task shares (see the module docstring)
COMMON_KWARGS: dict[str, Any] = {"actuator": "default", "dt": 0.5, "sensor_noise": True, "nh3_sensor": False,
                                 "privileged": False, "cold_start": False}
#: the training distribution every task starts from: hot random cycles of 1800 s, a new one per reset
TRAIN_BASE: dict[str, Any] = {"cycle": "random", "random_cycle_duration_s": 1800.0}
#: ageing range of the Aged task [h] (the CLEERS samples: 0 to 16 h hydrothermal ageing)
AGE_RANGE_H = (0.0, 16.0)


@dataclass(frozen=True)
class EvaluationProtocol:
    """The held-out evaluation of a task: ``cycle``, reset ``seeds`` and ``conditions`` (environment arguments per
    condition, e.g. one catalyst age each); one episode per condition and seed, ``len(conditions) * len(seeds)``
    in all."""

    cycle: str
    seeds: tuple[int, ...]
    conditions: tuple[dict[str, Any], ...] = ({},)

    @property
    def n_episodes(self) -> int:
        return len(self.conditions) * len(self.seeds)

    def episodes(self) -> list[tuple[dict[str, Any], int]]:
        """(condition, seed) of every episode, conditions major."""
        return [(dict(c), int(s)) for c in self.conditions for s in self.seeds]


@dataclass(frozen=True)
class Task:
    """A benchmark task (see the module docstring)."""

    name: str  # short name, e.g. "WHTC"
    hard_axis: str
    train: dict[str, Any]  # the training distribution: env kwargs on top of COMMON_KWARGS
    protocol: EvaluationProtocol
    evaluation: dict[str, Any] = field(default_factory=dict)  # env kwargs of every evaluation episode
    main: bool = True  # on the leaderboard (trained baselines, datasets)
    dataset_group: str = "fresh"  # tasks with the same training distribution share their datasets and runs

    @property
    def id(self) -> str:
        return f"scr_env/UreaSCR-{self.name}-v0"

    def eval_kwargs(self, condition: dict[str, Any] | None = None) -> dict[str, Any]:
        """Environment kwargs of an evaluation episode under ``condition`` (default: the first)."""
        cond = self.protocol.conditions[0] if condition is None else condition
        kw = {**COMMON_KWARGS, "cycle": self.protocol.cycle, **self.evaluation}
        kw.update(age_kwargs(cond["age_h"]) if "age_h" in cond else {})
        kw.update({k: v for k, v in cond.items() if k != "age_h"})
        return kw

    def train_kwargs(self) -> dict[str, Any]:
        """Environment kwargs of the training distribution (single or vector environment)."""
        kw = {**COMMON_KWARGS, **TRAIN_BASE}
        for k, v in self.train.items():
            if k == "age_h":
                kw.update(age_kwargs(v))
            else:
                kw[k] = v
        return kw

    def describe(self) -> dict[str, Any]:
        """The task as JSON: id, hard axis, training distribution, protocol."""
        return {"id": self.id, "hard_axis": self.hard_axis, "main": self.main, "dataset_group": self.dataset_group,
                "common": dict(COMMON_KWARGS), "train": {**TRAIN_BASE, **self.train},
                "evaluation": {"cycle": self.protocol.cycle, "seeds": list(self.protocol.seeds),
                               "conditions": [dict(c) for c in self.protocol.conditions],
                               "n_episodes": self.protocol.n_episodes, **self.evaluation}}


def _env_has_age_h() -> bool:
    from scr_env.envs.config import make_config

    return "age_h" in inspect.signature(make_config).parameters


def age_kwargs(age_h: float | tuple[float, float]) -> dict[str, Any]:
    """Environment kwargs for a catalyst age [h] or an age range (lo, hi) drawn per episode: ``age_h`` itself with
    the phys stream's environment; before it, ``ageing = age_h / 16`` (a range: its midpoint, with a warning). Age
    0 is the fresh catalyst, the environment's default: no kwargs."""
    if not isinstance(age_h, (tuple, list)) and float(age_h) == 0.0:
        return {}
    if _env_has_age_h():
        return {"age_h": tuple(age_h) if isinstance(age_h, (tuple, list)) else float(age_h)}
    if isinstance(age_h, (tuple, list)):
        mid = 0.5 * (float(age_h[0]) + float(age_h[1]))
        warnings.warn(f"this environment has no age_h argument yet (the phys stream adds it): the age range {age_h} "
                      f"h is trained at its midpoint, {mid:g} h (ageing severity {mid / 16.0:g})", stacklevel=2)
        return {"ageing": mid / 16.0}
    return {"ageing": float(age_h) / 16.0}


_WHTC_SEEDS = (0, 1, 2, 3, 4)
TASKS: dict[str, Task] = {t.id: t for t in (
    Task("WHTC", "transient generalisation: trained on random cycles, tested on the real transient cycle",
         train={}, protocol=EvaluationProtocol("whtc", _WHTC_SEEDS)),
    Task("WHSC", "high-temperature steady modes and load steps, where stored NH3 is released",
         train={}, protocol=EvaluationProtocol("whsc", _WHTC_SEEDS)),
    Task("Aged", "unobserved plant drift: the catalyst's hydrothermal age (0-16 h)",
         train={"age_h": AGE_RANGE_H}, dataset_group="aged",
         protocol=EvaluationProtocol("whtc", (0, 1), ({"age_h": 0.0}, {"age_h": 4.0}, {"age_h": 16.0}))),
    Task("Randomised", "catalyst-to-catalyst spread: capacity, activity and volume +/-20 %, unobserved",
         train={"randomize": 0.2}, evaluation={"randomize": 0.2}, dataset_group="randomised",
         protocol=EvaluationProtocol("whtc", (100, 101, 102, 103, 104))),
)}
#: the tasks of the leaderboard (trained baselines, offline datasets)
MAIN_TASKS: tuple[str, ...] = tuple(t.id for t in TASKS.values() if t.main)


def get_task(task: str | Task) -> Task:
    """A task by id (``"scr_env/UreaSCR-WHTC-v0"``), short name (``"WHTC"``) or the Task itself."""
    if isinstance(task, Task):
        return task
    if isinstance(task, str):
        if task in TASKS:
            return TASKS[task]
        for t in TASKS.values():
            if task in (t.name, f"UreaSCR-{t.name}-v0"):
                return t
    raise ValueError(f"unknown task {task!r}; one of {sorted(TASKS)}")


def make_eval_env(task: str | Task, condition: dict[str, Any] | None = None, **overrides: Any) -> Any:
    """The evaluation environment of ``task`` under ``condition`` (default: the protocol's first), a
    :class:`~scr_env.envs.urea_scr.UreaSCREnv` (not wrapped)."""
    from scr_env.envs.urea_scr import UreaSCREnv

    t = get_task(task)
    return UreaSCREnv(**{**t.eval_kwargs(condition), **overrides})


def training_env_kwargs(task: str | Task) -> dict[str, Any]:
    """The training distribution's environment kwargs (``gym.make(task_id, **kw)`` or the vector env's)."""
    return get_task(task).train_kwargs()


def register_tasks() -> None:
    """Register every task id (done by ``import scr_env``): ``gym.make(task_id)`` is its evaluation environment
    under the first condition, with a native vector entry point."""
    for t in TASKS.values():
        if t.id in registry:
            continue
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            kwargs = t.eval_kwargs()
        register(id=t.id, entry_point="scr_env.envs.urea_scr:UreaSCREnv",
                 vector_entry_point="scr_env.envs.vector:UreaSCRVectorEnv", kwargs=kwargs)
