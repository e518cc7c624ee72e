"""Score any :class:`~control.protocol.PolicyPredictor` on drive cycles: emission KPIs, policy timing, statistics.

    from control.evaluation import evaluate, comparison_table
    results = evaluate(policy, cycles=("whtc", "whsc"), seeds=(0, 1), name="pi")
    print(comparison_table(results))

Each episode runs the single :class:`scr_env.envs.urea_scr.UreaSCREnv` (built with ``env_kwargs``) from
``reset(seed=seed)`` to the truncation at the end of the cycle. Before the first step the harness calls the
policy's optional ``attach(env)`` hook with the unwrapped environment (the explicit route to privileged
information, see :mod:`control.protocol`); after the last step it copies the policy's optional ``stats()``.
"""
from __future__ import annotations

import math
import os
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from scr_env.cycles import ExhaustTrace
from scr_env.envs.urea_scr import UreaSCREnv

#: KPIs shown by :func:`comparison_table` (all from ``info["episode_kpis"]``), with their units
TABLE_KPIS: dict[str, str] = {
    "nox_conversion": "-",
    "engine_out_nox_g_per_kwh": "g/kWh",
    "tailpipe_nox_g_per_kwh": "g/kWh",
    "mean_nh3_slip_ppm": "ppm",
    "peak_nh3_slip_ppm": "ppm",
    "adblue_g": "g",
}

#: signals recorded per step when ``record_trajectory=True``, with their units
TRAJECTORY_SIGNALS: dict[str, str] = {
    "time_s": "s",
    "action": "-",
    "adblue_g_s": "g/s",
    "engine_out_nox_ppm": "ppm",
    "inlet_temperature_k": "K",
    "exhaust_flow_mol_s": "mol/s",
    "tailpipe_nox_ppm": "ppm",
    "tailpipe_nh3_ppm": "ppm",
    "nox_sensor_ppm": "ppm",
    "mean_coverage": "-",
    "reward": "-",
    "policy_time_ms": "ms",
}


@dataclass
class EpisodeResult:
    """One policy on one cycle with one seed.

    ``kpis``: the environment's ``info["episode_kpis"]``; ``timing``: wall time of ``policy.predict`` per step
    (``policy_time_ms_median``, ``policy_time_ms_p95``, ``policy_time_ms_max``, ``policy_time_ms_mean``);
    ``stats``: the policy's ``stats()`` after the episode (empty if it has none); ``trajectory``: per-step arrays
    (see :data:`TRAJECTORY_SIGNALS`) or None.
    """

    name: str
    cycle: str
    seed: int | None
    kpis: dict[str, float]
    timing: dict[str, float]
    stats: dict[str, Any] = field(default_factory=dict)
    trajectory: dict[str, np.ndarray] | None = None

    def row(self) -> dict[str, Any]:
        """Flat dict: name, cycle, seed, then KPIs, timing and stats (JSON-friendly, no trajectory)."""
        out: dict[str, Any] = {"name": self.name, "cycle": self.cycle, "seed": self.seed}
        out.update(self.kpis)
        out.update(self.timing)
        out.update(self.stats)
        return out


def _timing(ms: np.ndarray) -> dict[str, float]:
    if ms.size == 0:
        return {}
    return {"policy_time_ms_median": float(np.median(ms)), "policy_time_ms_p95": float(np.percentile(ms, 95)),
            "policy_time_ms_max": float(ms.max()), "policy_time_ms_mean": float(ms.mean())}


def run_episode(policy: Any, env: UreaSCREnv, seed: int | None = 0, *, name: str | None = None,
                record_trajectory: bool = False, max_steps: int | None = None,
                reset_options: dict | None = None) -> EpisodeResult:
    """Run ``policy`` for one episode of ``env`` (reset with ``seed``) and return its :class:`EpisodeResult`.

    ``max_steps`` stops early (then ``kpis`` is empty: the environment reports them at truncation only).
    """
    env = getattr(env, "unwrapped", env)
    if not hasattr(policy, "predict"):
        raise TypeError(f"policy must have a predict(observation, state, episode_start, deterministic) method, "
                        f"got {type(policy).__name__}")
    obs, _ = env.reset(seed=seed, options=reset_options)
    if hasattr(policy, "attach"):
        policy.attach(env)
    trace = env.trace
    n = trace.n_steps if max_steps is None else min(int(max_steps), trace.n_steps)
    ms = np.empty(n)
    rec = {k: np.empty(n) for k in TRAJECTORY_SIGNALS} if record_trajectory else None
    state = None
    kpis: dict[str, float] = {}
    start = np.array([True])
    not_start = np.array([False])
    for k in range(n):
        t0 = time.perf_counter()
        action, state = policy.predict(obs, state=state, episode_start=start if k == 0 else not_start,
                                       deterministic=True)
        ms[k] = (time.perf_counter() - t0) * 1e3
        sensor = float(obs[3])
        obs, reward, _, truncated, info = env.step(action)
        if rec is not None:
            rec["time_s"][k] = k * env.dt
            rec["action"][k] = float(obs[4])
            rec["adblue_g_s"][k] = info["adblue_g_s"]
            rec["engine_out_nox_ppm"][k] = info["engine_out_nox_ppm"]
            rec["inlet_temperature_k"][k] = trace.scr_inlet_temperature_k[k]
            rec["exhaust_flow_mol_s"][k] = trace.exhaust_flow_mol_s[k]
            rec["tailpipe_nox_ppm"][k] = info["tailpipe_nox_ppm"]
            rec["tailpipe_nh3_ppm"][k] = info["tailpipe_nh3_ppm"]
            rec["nox_sensor_ppm"][k] = sensor
            rec["mean_coverage"][k] = float(np.mean(env.state["nh3_coverage"]))
            rec["reward"][k] = reward
            rec["policy_time_ms"][k] = ms[k]
        if truncated:
            kpis = dict(info["episode_kpis"])
            break
    stats = dict(policy.stats()) if hasattr(policy, "stats") else {}
    return EpisodeResult(name=name or type(policy).__name__, cycle=trace.name, seed=seed, kpis=kpis,
                         timing=_timing(ms[:k + 1]), stats=stats, trajectory=rec)


def _as_sequence(value: Any, name: str, single: tuple[type, ...], none_is_single: bool = False) -> list:
    """``value`` as a list: one element if it is a single item of the types ``single`` (or None, with
    ``none_is_single``), else its elements; ``TypeError`` / ``ValueError`` naming ``name`` if not iterable / empty."""
    if isinstance(value, single) or (value is None and none_is_single):
        return [value]
    try:
        out = list(value)
    except TypeError:
        raise TypeError(f"{name} must be one item or a sequence of them, got {type(value).__name__}") from None
    if not out:
        raise ValueError(f"{name} is empty: give at least one")
    return out


def evaluate(policy: Any, cycles: str | Iterable[str] = ("whtc",), seeds: int | None | Iterable[int | None] = (0,),
             env_kwargs: dict | None = None, *, name: str | None = None, record_trajectory: bool = False,
             max_steps: int | None = None, reset_options: dict | None = None) -> list[EpisodeResult]:
    """Run ``policy`` on every cycle x seed and return one :class:`EpisodeResult` each (cycle-major order).

    Parameters
    ----------
    policy : a :class:`~control.protocol.PolicyPredictor` (optionally with ``attach(env)`` and ``stats()``).
    cycles : cycle names (or anything ``UreaSCREnv(cycle=...)`` accepts); a single one (``"whtc"``, a path, an
        ``ExhaustTrace``) is taken as a one-element sequence, never as its characters.
    seeds : reset seeds (sensor noise; the random cycle); a single int (or None: unseeded) is a one-element
        sequence; numpy integers are passed on as ints.
    env_kwargs : further arguments of :class:`UreaSCREnv` (``cycle`` is set from ``cycles``).
    name : label in results and tables (default: the policy's class name).
    record_trajectory : keep the per-step signals in ``EpisodeResult.trajectory``.
    max_steps : stop each episode early (smoke tests); KPIs are then empty.
    """
    cycles = _as_sequence(cycles, "cycles", (str, os.PathLike, ExhaustTrace))
    # numpy integers as Python ints (gymnasium's reset takes only those)
    seeds = [int(s) if isinstance(s, np.integer) else s
             for s in _as_sequence(seeds, "seeds", (int, np.integer), none_is_single=True)]
    kw = dict(env_kwargs or {})
    kw.pop("cycle", None)
    results = []
    for cycle in cycles:
        env = UreaSCREnv(cycle=cycle, **kw)
        for seed in seeds:
            results.append(run_episode(policy, env, seed, name=name, record_trajectory=record_trajectory,
                                       max_steps=max_steps, reset_options=reset_options))
        env.close()
    return results


def summarise(results: Iterable[EpisodeResult]) -> dict[str, dict[str, dict[str, float]]]:
    """Mean over seeds of every numeric KPI, timing and stat: ``{cycle: {name: {key: value}}}``."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in results:
        groups.setdefault((r.cycle, r.name), []).append(r.row())
    out: dict[str, dict[str, dict[str, float]]] = {}
    for (cycle, name), rows in groups.items():
        keys = [k for k, v in rows[0].items() if isinstance(v, (int, float)) and not isinstance(v, bool)
                and k != "seed"]
        agg = {k: float(np.mean([float(r.get(k, math.nan)) for r in rows])) for k in keys}
        agg["n_seeds"] = len(rows)
        out.setdefault(cycle, {})[name] = agg
    return out


def comparison_table(results: Iterable[EpisodeResult] | dict, kpis: Iterable[str] | None = None,
                     extra: Iterable[str] = ("policy_time_ms_median", "policy_time_ms_p95", "solver_failures")) -> str:
    """A plain-text table, one row per (cycle, policy), seeds averaged: the KPIs of :data:`TABLE_KPIS` plus the
    ``extra`` columns that any row has. Accepts a list of :class:`EpisodeResult` or the dict of :func:`summarise`.
    """
    summary = results if isinstance(results, dict) else summarise(results)
    cols = list(kpis or TABLE_KPIS)
    present = {k for per in summary.values() for row in per.values() for k in row}
    cols += [k for k in extra if k in present and k not in cols]
    short = {"nox_conversion": "conv", "engine_out_nox_g_per_kwh": "EO g/kWh", "tailpipe_nox_g_per_kwh": "TP g/kWh",
             "mean_nh3_slip_ppm": "NH3 mean", "peak_nh3_slip_ppm": "NH3 peak", "adblue_g": "AdBlue g",
             "policy_time_ms_median": "ms med", "policy_time_ms_p95": "ms p95", "solver_failures": "fails",
             "solve_time_ms_median": "solve med", "solve_time_ms_p95": "solve p95"}
    head = ["cycle", "controller"] + [short.get(c, c) for c in cols]
    rows = []
    for cycle, per in summary.items():
        for name, row in per.items():
            vals = []
            for c in cols:
                v = row.get(c, math.nan)
                if c == "nox_conversion":
                    vals.append(f"{v:.4f}")
                elif c in ("solver_failures",):
                    vals.append("-" if math.isnan(v) else f"{v:.0f}")
                else:
                    vals.append("-" if math.isnan(v) else f"{v:.3g}" if abs(v) < 1 else f"{v:.2f}")
            rows.append([cycle, name] + vals)
    widths = [max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(head)]
    fmt = lambda r: "  ".join(s.ljust(w) if i < 2 else s.rjust(w) for i, (s, w) in enumerate(zip(r, widths)))
    lines = [fmt(head), "  ".join("-" * w for w in widths)] + [fmt(r) for r in rows]
    return "\n".join(lines)
