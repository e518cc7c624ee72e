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
    "command_total_variation_g_s_per_h": "g/s per h",  # chatter (scr_env.envs.kpis)
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


def _check_max_steps(max_steps: Any) -> int | None:
    """``max_steps`` as a positive int, or None; ``ValueError`` naming it otherwise (0 would run no step at all)."""
    if max_steps is None:
        return None
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"max_steps must be a positive whole number of steps or None (the whole episode), got "
                         f"{max_steps!r}")
    return int(max_steps)


def run_episode(policy: Any, env: Any, seed: int | None = 0, *, name: str | None = None,
                record_trajectory: bool = False, max_steps: int | None = None,
                reset_options: dict | None = None) -> EpisodeResult:
    """Run ``policy`` for one episode of ``env`` (reset with ``seed``) and return its :class:`EpisodeResult`.

    ``env`` is any Gymnasium environment (the SCR plant, a surrogate of it, a wrapped one): it is stepped as
    given, until it terminates or truncates, or for ``max_steps`` steps (a positive int; then ``kpis`` is empty
    unless the episode ended: environments report them at the end, in ``info["episode_kpis"]``). The policy's
    ``attach`` hook gets the unwrapped environment. The trajectory's plant signals (:data:`TRAJECTORY_SIGNALS`)
    come from the info dict, the environment's drive cycle (``trace``) and state where it has them, NaN otherwise.
    """
    max_steps = _check_max_steps(max_steps)
    base = getattr(env, "unwrapped", env)
    if not hasattr(policy, "predict"):
        raise TypeError(f"policy must have a predict(observation, state, episode_start, deterministic) method, "
                        f"got {type(policy).__name__}")
    obs, reset_info = env.reset(seed=seed, options=reset_options)
    if hasattr(policy, "attach"):
        policy.attach(base)
    trace = getattr(base, "trace", None)
    n = trace.n_steps if trace is not None else None
    if max_steps is not None:
        n = max_steps if n is None else min(max_steps, n)
    dt = float(getattr(base, "dt", 1.0))
    ms: list[float] = []
    rec: dict[str, list[float]] | None = {key: [] for key in TRAJECTORY_SIGNALS} if record_trajectory else None
    state = None
    kpis: dict[str, float] = {}
    start = np.array([True])
    not_start = np.array([False])
    k = 0
    while n is None or k < n:
        t0 = time.perf_counter()
        action, state = policy.predict(obs, state=state, episode_start=start if k == 0 else not_start,
                                       deterministic=True)
        ms.append((time.perf_counter() - t0) * 1e3)
        sensor = float(obs[3]) if np.size(obs) > 3 else math.nan
        obs, reward, terminated, truncated, info = env.step(action)
        if rec is not None:
            _record(rec, k, dt, obs, action, float(reward), info, trace, base, sensor, ms[-1])
        k += 1
        if terminated or truncated:
            kpis = dict(info.get("episode_kpis", {}))
            break
    stats = dict(policy.stats()) if hasattr(policy, "stats") else {}
    cycle = trace.name if trace is not None else str(reset_info.get("cycle", type(base).__name__))
    trajectory = None if rec is None else {key: np.asarray(v, dtype=float) for key, v in rec.items()}
    return EpisodeResult(name=name or type(policy).__name__, cycle=cycle, seed=seed, kpis=kpis,
                         timing=_timing(np.asarray(ms)), stats=stats, trajectory=trajectory)


def _record(rec: dict[str, list[float]], k: int, dt: float, obs: Any, action: Any, reward: float,
            info: dict[str, Any], trace: Any, env: Any, sensor: float, ms: float) -> None:
    """Append step ``k``'s signals to ``rec`` (NaN where the environment does not provide one)."""
    nan = math.nan
    on_trace = trace is not None and k < trace.n_steps
    state = getattr(env, "state", None)
    rec["time_s"].append(k * dt)
    rec["action"].append(float(obs[4]) if np.size(obs) > 4 else float(np.asarray(action).reshape(-1)[0]))
    rec["adblue_g_s"].append(float(info.get("adblue_g_s", nan)))
    rec["engine_out_nox_ppm"].append(float(info.get("engine_out_nox_ppm", nan)))
    rec["inlet_temperature_k"].append(float(trace.scr_inlet_temperature_k[k]) if on_trace else nan)
    rec["exhaust_flow_mol_s"].append(float(trace.exhaust_flow_mol_s[k]) if on_trace else nan)
    rec["tailpipe_nox_ppm"].append(float(info.get("tailpipe_nox_ppm", nan)))
    rec["tailpipe_nh3_ppm"].append(float(info.get("tailpipe_nh3_ppm", nan)))
    rec["nox_sensor_ppm"].append(sensor)
    rec["mean_coverage"].append(float(np.mean(state["nh3_coverage"])) if isinstance(state, dict)
                                and "nh3_coverage" in state else nan)
    rec["reward"].append(reward)
    rec["policy_time_ms"].append(ms)


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


def evaluate(policy: Any, cycles: str | Iterable[str] | None = None,
             seeds: int | None | Iterable[int | None] = (0,), env_kwargs: dict | None = None, *,
             env: Any = None, name: str | None = None, record_trajectory: bool = False,
             max_steps: int | None = None, reset_options: dict | None = None) -> list[EpisodeResult]:
    """Run ``policy`` on every cycle x seed and return one :class:`EpisodeResult` each (cycle-major order).

    Parameters
    ----------
    policy : a :class:`~control.protocol.PolicyPredictor` (optionally with ``attach(env)`` and ``stats()``).
    cycles : cycle names (or anything ``UreaSCREnv(cycle=...)`` accepts), default ``("whtc",)``; a single one
        (``"whtc"``, a path, an ``ExhaustTrace``) is taken as a one-element sequence, never as its characters.
    seeds : reset seeds (sensor noise; the random cycle); a single int (or None: unseeded) is a one-element
        sequence; numpy integers are passed on as ints.
    env_kwargs : further arguments of :class:`UreaSCREnv` (``cycle`` is set from ``cycles``).
    env : any Gymnasium environment to run instead of building :class:`UreaSCREnv` per cycle -- a surrogate
        (:class:`control.rl.surrogate.SurrogateSCREnv`), a wrapped or an aged plant; one episode per seed, the
        environment is neither built nor closed here. ``cycles`` and ``env_kwargs`` must then be left out.
    name : label in results and tables (default: the policy's class name).
    record_trajectory : keep the per-step signals in ``EpisodeResult.trajectory``.
    max_steps : stop each episode after this many steps (a positive int; smoke tests); KPIs are then empty.
        ``ValueError`` for 0, negative or non-integer values.
    """
    max_steps = _check_max_steps(max_steps)
    # numpy integers as Python ints (gymnasium's reset takes only those)
    seeds = [int(s) if isinstance(s, np.integer) else s
             for s in _as_sequence(seeds, "seeds", (int, np.integer), none_is_single=True)]
    run = {"name": name, "record_trajectory": record_trajectory, "max_steps": max_steps, "reset_options": reset_options}
    if env is not None:
        if cycles is not None or env_kwargs:
            raise ValueError("evaluate: give either env or cycles/env_kwargs, not both")
        if not (hasattr(env, "reset") and hasattr(env, "step")):
            raise TypeError(f"env must be a Gymnasium environment (reset and step), got {type(env).__name__}")
        return [run_episode(policy, env, seed, **run) for seed in seeds]
    cycles = _as_sequence(("whtc",) if cycles is None else cycles, "cycles", (str, os.PathLike, ExhaustTrace))
    kw = dict(env_kwargs or {})
    kw.pop("cycle", None)
    results = []
    for cycle in cycles:
        plant = UreaSCREnv(cycle=cycle, **kw)
        for seed in seeds:
            results.append(run_episode(policy, plant, seed, **run))
        plant.close()
    return results


def cycle_segment(cycle: str | os.PathLike | ExhaustTrace, seconds: float, name: str | None = None,
                  dt: float = 0.5) -> ExhaustTrace:
    """The first ``seconds`` of a hot drive cycle (a name or path loaded at ``dt``, or an :class:`ExhaustTrace`)
    as an :class:`ExhaustTrace` named ``name`` (default the cycle's own name): every per-step signal cut to
    ``round(seconds / dt)`` steps (at most the whole cycle)."""
    import dataclasses

    from scr_env.cycles import load_cycle

    tr = cycle if isinstance(cycle, ExhaustTrace) else load_cycle(cycle, dt=dt)
    if not (np.isfinite(seconds) and seconds > 0):
        raise ValueError(f"seconds must be a positive duration [s], got {seconds!r}")
    n = min(round(seconds / tr.dt), tr.n_steps)
    changes: dict[str, Any] = {f.name: getattr(tr, f.name)[:n].copy() for f in dataclasses.fields(tr)
                               if isinstance(getattr(tr, f.name), np.ndarray) and getattr(tr, f.name).ndim >= 1
                               and getattr(tr, f.name).shape[0] == tr.n_steps}
    if name is not None:
        changes["name"] = name
    return dataclasses.replace(tr, **changes)


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
             "command_total_variation_g_s_per_h": "chatter",
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
    def fmt(r: list[str]) -> str:
        return "  ".join(s.ljust(w) if i < 2 else s.rjust(w) for i, (s, w) in enumerate(zip(r, widths, strict=True)))

    lines = [fmt(head), "  ".join("-" * w for w in widths)] + [fmt(r) for r in rows]
    return "\n".join(lines)
