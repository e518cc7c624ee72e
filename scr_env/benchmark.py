"""The normalised score of the benchmark tasks (:mod:`scr_env.tasks`), and its statistics over seeds.

Score of one evaluation episode (a condition and reset seed of the task's protocol), from its tailpipe NOx
``x`` [g/kWh] and mean NH3 slip ``s`` [ppm]:

* **anchors** (stored per episode in :data:`ANCHORS_PATH`, made by ``python -m experiments.rl_anchors``; never
  re-solved at evaluation): ``x_lut``, the look-up table (:class:`control.baselines.LookupTableDosing`) on the same
  episode, and ``x_ref``, the reference on the same episode: the clairvoyant optimum at the 10 ppm mean-slip budget
  solved for the episode's own plant (``control.limit.stored_limit``; the physical limit of the task, so a score of
  100 is out of reach and the scale does not move when a better controller appears). The anchors file and every
  result say which reference was used (``reference_kind``; ``experiments.rl_anchors --reference oracle`` makes
  oracle-NMPC anchors instead), and each stored episode also carries the oracle NMPC's KPIs for information;
* **raw score** ``100 (x_lut - x) / (x_lut - x_ref)``: 0 for the look-up table, 100 for the reference, more than
  100 for a policy that beats the reference; the anchors are defined on these raw figures, before any penalty, so
  they are 0 and 100 whatever their own slip (their slip is stored beside them);
* **slip penalty**: an episode whose mean slip exceeds the Euro VI limit (:data:`SLIP_LIMIT_PPM`, 10 ppm) scores
  ``min(raw, 0) - 10 (s - 10 ppm)`` (:data:`PENALTY_POINTS_PER_PPM`): no better than the look-up table, and 10
  points less per ppm over the limit.

A policy's score on a task is the mean penalised score over the protocol's episodes; :func:`evaluate` returns it
with a 95 % bootstrap interval over those episodes (:func:`bootstrap_ci`), the raw score, the chatter KPI (total
variation of the commanded dose per hour, :func:`scr_env.envs.kpis.episode_kpis`) and the KPIs per episode.
Across training seeds, :func:`aggregate` gives the interquartile mean and its 95 % percentile-bootstrap interval
(Agarwal et al. 2021, "Deep RL at the edge of the statistical precipice", the rliable recommendation; scipy's
bootstrap).
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from scr_env.constants import EURO_VI_NH3_SLIP_LIMIT_PPM
from scr_env.tasks import Task, get_task, make_eval_env

__all__ = ["ANCHORS_PATH", "PENALTY_POINTS_PER_PPM", "SLIP_LIMIT_PPM", "BenchmarkResult", "aggregate",
           "bootstrap_ci", "episode_metrics", "evaluate", "iqm", "load_anchors", "penalised_score", "raw_score",
           "run_episode"]

SLIP_LIMIT_PPM = EURO_VI_NH3_SLIP_LIMIT_PPM  # ppm, mean NH3 slip over an episode
PENALTY_POINTS_PER_PPM = 10.0  # score points per ppm of mean slip above the limit [chosen: 1 ppm over costs a tenth
#                                of the look-up-table-to-reference gap]
#: the stored anchors (package data), written by ``python -m experiments.rl_anchors``
ANCHORS_PATH = Path(__file__).resolve().parent / "data" / "benchmark" / "anchors.json"
#: KPIs kept per episode
EPISODE_KPIS = ("tailpipe_nox_g_per_kwh", "mean_nh3_slip_ppm", "peak_nh3_slip_ppm", "adblue_g",
                "command_total_variation_g_s_per_h", "adblue_total_variation_g_s_per_h", "nox_conversion")


def raw_score(nox: float, nox_lut: float, nox_ref: float) -> float:
    """100 (x_lut - x) / (x_lut - x_ref): 0 at the look-up table, 100 at the reference (ValueError if the reference
    is not better than the look-up table)."""
    gap = float(nox_lut) - float(nox_ref)
    if not gap > 0:
        raise ValueError(f"the reference ({nox_ref} g/kWh) must beat the look-up table ({nox_lut} g/kWh)")
    return 100.0 * (float(nox_lut) - float(nox)) / gap


def penalised_score(raw: float, mean_slip_ppm: float, limit_ppm: float = SLIP_LIMIT_PPM) -> float:
    """The raw score, or over the slip limit ``min(raw, 0) - PENALTY_POINTS_PER_PPM (slip - limit)``."""
    if not math.isfinite(mean_slip_ppm):
        return -math.inf
    if mean_slip_ppm <= limit_ppm:
        return float(raw)
    return min(float(raw), 0.0) - PENALTY_POINTS_PER_PPM * (float(mean_slip_ppm) - limit_ppm)


def iqm(x: Any) -> float:
    """Interquartile mean: the mean of the middle 50 % (scipy.stats.trim_mean at 25 %)."""
    from scipy.stats import trim_mean

    return float(trim_mean(np.asarray(x, dtype=float), 0.25))


def bootstrap_ci(x: Any, statistic: Any = iqm, confidence: float = 0.95, n_resamples: int = 2000,
                 seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of ``statistic`` over the samples ``x`` (scipy.stats.bootstrap); a single
    sample or identical samples give the degenerate interval."""
    from scipy.stats import bootstrap

    a = np.asarray(x, dtype=float)
    if a.size < 2 or np.all(a == a[0]):
        v = float(statistic(a)) if a.size else math.nan
        return v, v
    res = bootstrap((a,), lambda s, axis=-1: np.apply_along_axis(statistic, axis, s), confidence_level=confidence,
                    n_resamples=n_resamples, method="percentile", rng=np.random.default_rng(seed), vectorized=True)
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def aggregate(seed_scores: Any, learned: bool = True) -> dict[str, Any]:
    """One method's entry of the leaderboard from its scores per training seed: ``iqm``, ``ci`` (95 % bootstrap of
    the IQM), ``n_seeds``, ``mean``, ``scores``, ``learned``."""
    a = np.asarray(seed_scores, dtype=float)
    lo, hi = bootstrap_ci(a)
    return {"iqm": iqm(a), "ci": [lo, hi], "n_seeds": int(a.size), "mean": float(a.mean()), "scores": a.tolist(),
            "learned": bool(learned)}


def run_episode(policy: Any, env: Any, seed: int, max_steps: int | None = None) -> dict[str, float]:
    """One episode of ``policy`` (``predict(obs, state, episode_start, deterministic)``, optional ``attach(env)``)
    on ``env`` from ``reset(seed=seed)``: its KPIs (``env.unwrapped.episode_kpis()``)."""
    obs, _ = env.reset(seed=int(seed))
    base = getattr(env, "unwrapped", env)
    if hasattr(policy, "attach"):
        policy.attach(base)
    state, k = None, 0
    start, go = np.array([True]), np.array([False])
    while True:
        action, state = policy.predict(obs, state=state, episode_start=start if k == 0 else go, deterministic=True)
        obs, _, terminated, truncated, _ = env.step(action)
        k += 1
        if terminated or truncated or (max_steps is not None and k >= max_steps):
            break
    return base.episode_kpis()


def episode_metrics(policy: Any, task: str | Task, max_steps: int | None = None,
                    progress: bool = False) -> list[dict[str, Any]]:
    """Run ``policy`` on every episode of the task's protocol: ``[{"condition", "seed", "kpis"}]`` (the KPIs of
    :data:`EPISODE_KPIS`, plus ``wall_time_s``). ``max_steps`` cuts episodes short (tests only: the anchors are for
    whole episodes)."""
    t = get_task(task)
    rows = []
    envs: dict[str, Any] = {}
    for cond, seed in t.protocol.episodes():
        key = json.dumps(cond, sort_keys=True)
        if key not in envs:
            envs[key] = make_eval_env(t, cond)
        t0 = time.perf_counter()
        kpis = run_episode(policy, envs[key], seed, max_steps)
        row = {"condition": cond, "seed": seed, "kpis": {k: float(kpis[k]) for k in EPISODE_KPIS},
               "wall_time_s": round(time.perf_counter() - t0, 2)}
        rows.append(row)
        if progress:
            print(f"  {t.name} {cond} seed {seed}: {kpis['tailpipe_nox_g_per_kwh']:.3f} g/kWh, "
                  f"{kpis['mean_nh3_slip_ppm']:.2f} ppm ({row['wall_time_s']:.0f} s)", flush=True)
    for env in envs.values():
        env.close()
    return rows


def load_anchors(path: str | Path | None = None) -> dict[str, Any]:
    """The stored anchors (:data:`ANCHORS_PATH`): ``{"tasks": {task_id: {"reference_kind", "episodes": [...]}},
    "command", ...}``; ValueError naming the file if it is missing or damaged."""
    p = Path(path) if path is not None else ANCHORS_PATH
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise ValueError(f"{p}: no readable benchmark anchors ({exc}); make them with "
                         f"python -m experiments.rl_anchors") from None
    if not isinstance(data, dict) or not isinstance(data.get("tasks"), dict):
        raise ValueError(f"{p}: anchors must hold {{'tasks': {{task_id: ...}}}}")  # noqa: TRY004 (a file error)
    return data


def _episode_anchor(anchors: dict[str, Any], task: Task, cond: dict[str, Any], seed: int) -> dict[str, Any]:
    entry = anchors["tasks"].get(task.id)
    if entry is None:
        raise ValueError(f"no stored anchors for {task.id}; run python -m experiments.rl_anchors --tasks {task.name}")
    for e in entry["episodes"]:
        if e["seed"] == seed and e["condition"] == cond:
            return e
    raise ValueError(f"no stored anchor for {task.id} condition {cond} seed {seed}: the task's protocol changed "
                     f"since the anchors were made; rerun python -m experiments.rl_anchors --tasks {task.name}")


def score_rows(rows: list[dict[str, Any]], task: str | Task, anchors: dict[str, Any] | None = None) -> list[dict]:
    """Add ``raw_score`` and ``score`` (penalised) to each row of :func:`episode_metrics`."""
    t = get_task(task)
    anchors = load_anchors() if anchors is None else anchors
    out = []
    for r in rows:
        a = _episode_anchor(anchors, t, r["condition"], r["seed"])
        raw = raw_score(r["kpis"]["tailpipe_nox_g_per_kwh"], a["lookup_table"]["tailpipe_nox_g_per_kwh"],
                        a["reference"]["tailpipe_nox_g_per_kwh"])
        out.append({**r, "raw_score": raw, "score": penalised_score(raw, r["kpis"]["mean_nh3_slip_ppm"])})
    return out


@dataclass
class BenchmarkResult:
    """A policy on a task: ``score`` (mean penalised score over the protocol's episodes) with its 95 % bootstrap
    interval ``ci`` over them, ``raw_score`` (before the slip penalty), ``chatter_g_s_per_h`` (mean total variation
    of the commanded dose per hour), ``over_limit`` (episodes above the slip limit) and the ``episodes``."""

    task_id: str
    score: float
    ci: tuple[float, float]
    raw_score: float
    chatter_g_s_per_h: float
    over_limit: int
    reference_kind: str
    episodes: list[dict[str, Any]] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"task_id": self.task_id, "score": self.score, "ci": list(self.ci), "raw_score": self.raw_score,
                "chatter_g_s_per_h": self.chatter_g_s_per_h, "over_limit": self.over_limit,
                "reference_kind": self.reference_kind, "episodes": self.episodes}


def evaluate(policy: Any, task: str | Task, anchors: dict[str, Any] | str | Path | None = None,
             progress: bool = False, max_steps: int | None = None) -> BenchmarkResult:
    """Score ``policy`` on ``task``'s evaluation protocol against the stored anchors (see the module docstring).

        from scr_env.benchmark import evaluate
        from control.baselines import LookupTableDosing
        evaluate(LookupTableDosing(), "scr_env/UreaSCR-WHTC-v0").score   # 0.0

    ``max_steps``: episodes cut short, for smoke tests with anchors made the same way (``experiments.rl_anchors
    --max-steps``); it must equal the anchors' ``partial_episodes`` (ValueError otherwise).
    """
    t = get_task(task)
    anchors = anchors if isinstance(anchors, dict) else load_anchors(anchors)
    stored = (anchors["tasks"].get(t.id) or {}).get("partial_episodes")
    if stored != max_steps:
        raise ValueError(f"the anchors of {t.id} are for episodes cut at {stored} steps, the evaluation asks for "
                         f"{max_steps}: make anchors and evaluation alike (None: whole episodes)")
    rows = score_rows(episode_metrics(policy, t, max_steps, progress=progress), t, anchors)
    scores = [r["score"] for r in rows]
    return BenchmarkResult(
        task_id=t.id, score=float(np.mean(scores)), ci=bootstrap_ci(scores, statistic=np.mean),
        raw_score=float(np.mean([r["raw_score"] for r in rows])),
        chatter_g_s_per_h=float(np.mean([r["kpis"]["command_total_variation_g_s_per_h"] for r in rows])),
        over_limit=sum(r["kpis"]["mean_nh3_slip_ppm"] > SLIP_LIMIT_PPM for r in rows),
        reference_kind=str(anchors["tasks"][t.id].get("reference_kind", "")), episodes=rows)
