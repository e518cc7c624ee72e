"""Choosing, installing and scoring trained dosing policies (the library side of ``experiments.train_rl``).

* :func:`validate` and :func:`select`: every checkpoint of a run on the validation cycles -- hot-start random cycles
  of :data:`VALIDATION_DURATION_S` with the reset seeds :data:`VALIDATION_SEEDS`, never the held-out WHTC/WHSC --
  and the rule: the lowest mean tailpipe NOx among the candidates whose worst mean slip there is within the Euro VI
  limit; if none is, :func:`select` says so loudly (a :class:`SlipLimitWarning`) and returns the one with the lowest
  worst slip marked ``within_slip_limit: False``, which ``train_rl`` then refuses to ship;
* :func:`install`: a saved policy copied under a name into a policy folder (the shipped ``control/policies/``);
* :func:`reference_policies` and :func:`evaluate_policies`: the baselines an RL policy is compared with, and their
  KPIs on the test cycles.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from scr_env.constants import EURO_VI_NH3_SLIP_LIMIT_PPM
from scr_env.fileio import write_json

__all__ = ["VALIDATION_DURATION_S", "VALIDATION_SEEDS", "VALIDATION_SLIP_LIMIT_PPM", "SlipLimitWarning",
           "candidates_in", "evaluate_policies", "install", "reference_policies", "select", "validate"]

#: checkpoint selection (validation, never the held-out WHTC/WHSC): hot-start random cycles of this length, seeds
VALIDATION_DURATION_S = 3600.0
VALIDATION_SEEDS = (1001, 1002, 1003, 1004)
VALIDATION_SLIP_LIMIT_PPM = EURO_VI_NH3_SLIP_LIMIT_PPM


class SlipLimitWarning(UserWarning):
    """No candidate policy kept its validation mean NH3 slip within the limit."""


def validate(candidates: list[Path], seeds: tuple[int, ...] = VALIDATION_SEEDS,
             env_kwargs: dict[str, Any] | None = None,
             duration_s: float = VALIDATION_DURATION_S) -> list[dict[str, Any]]:
    """KPIs of each candidate policy on the validation cycles (long random cycles, never the WHTC/WHSC);
    ``env_kwargs``: further environment arguments (a benchmark task's training distribution: actuator, catalyst
    randomisation, age; the cycle stays random); ``duration_s``: length of each validation cycle (default
    :data:`VALIDATION_DURATION_S`; shorter only in smoke tests)."""
    from control.evaluation import evaluate
    from control.rl.policy import load_policy

    rows = []
    for path in candidates:
        kw = {k: v for k, v in (env_kwargs or {}).items() if k != "cycle"}
        kw["random_cycle_duration_s"] = float(duration_s)
        res = evaluate(load_policy(path), cycles=("random",), seeds=seeds, env_kwargs=kw, name=path.stem)
        tp = [r.kpis["tailpipe_nox_g_per_kwh"] for r in res]
        slip = [r.kpis["mean_nh3_slip_ppm"] for r in res]
        rows.append({"candidate": str(path), "timesteps": int(json.loads(path.read_text()).get("timesteps", 0)),
                     "tailpipe_nox_g_per_kwh_mean": float(np.mean(tp)), "mean_nh3_slip_ppm_max": float(np.max(slip)),
                     "tailpipe_nox_g_per_kwh": tp, "mean_nh3_slip_ppm": slip})
        print(f"validation {path.stem:16s} tailpipe {np.mean(tp):.3f} g/kWh  worst mean slip {np.max(slip):.1f} ppm",
              flush=True)
    return rows


def select(rows: list[dict[str, Any]], limit_ppm: float = VALIDATION_SLIP_LIMIT_PPM) -> dict[str, Any]:
    """The rule: the lowest mean validation tailpipe NOx among the candidates whose worst validation mean slip is at
    most ``limit_ppm`` (:data:`VALIDATION_SLIP_LIMIT_PPM`); the row returned is a copy with
    ``within_slip_limit: True``. If no candidate is within the limit, a loud :class:`SlipLimitWarning` (also printed
    to stderr, with every candidate's worst slip) and the candidate with the lowest worst slip, marked
    ``within_slip_limit: False``: never a silent choice of a policy over the limit."""
    import sys
    import warnings

    if not rows:
        raise ValueError("rows is empty: no candidate policy to select from")
    ok = [r for r in rows if r["mean_nh3_slip_ppm_max"] <= limit_ppm]
    if ok:
        return dict(min(ok, key=lambda r: r["tailpipe_nox_g_per_kwh_mean"]), within_slip_limit=True)
    best = min(rows, key=lambda r: r["mean_nh3_slip_ppm_max"])
    slips = ", ".join(f"{Path(r['candidate']).stem} {r['mean_nh3_slip_ppm_max']:.1f} ppm" for r in rows)
    msg = (f"NO CANDIDATE WITHIN THE SLIP LIMIT: every checkpoint's worst validation mean NH3 slip exceeds "
           f"{limit_ppm:g} ppm ({slips}); the least slipping one, {Path(best['candidate']).stem} "
           f"({best['mean_nh3_slip_ppm_max']:.1f} ppm), is reported but is not a compliant policy")
    print("\n" + "!" * 100 + "\n" + msg + "\n" + "!" * 100, file=sys.stderr, flush=True)
    warnings.warn(msg, SlipLimitWarning, stacklevel=2)
    return dict(best, within_slip_limit=False)


def candidates_in(folder: Path) -> list[Path]:
    """Checkpoints (``checkpoints/*.json``) and the final policy (``policy/*.json``) of a run folder."""
    found = sorted((folder / "checkpoints").glob("*.json"), key=lambda p: int(json.loads(p.read_text())["timesteps"]))
    return found + sorted((folder / "policy").glob("*.json"))[:1]


def install(src_json: Path, folder: Path, name: str, extra: dict[str, Any]) -> Path:
    """Copy a saved policy (weights NPZ, normaliser NPZ, JSON) under the name ``name`` into ``folder``, metadata
    updated by ``extra`` (the JSON written atomically, last). A policy of an older format version is converted to
    the current one (:func:`control.rl.policy.convert_policy`)."""
    from control.rl.policy import FORMAT_VERSION, convert_policy

    meta = json.loads(src_json.read_text())
    folder.mkdir(parents=True, exist_ok=True)
    if meta.get("format_version") != FORMAT_VERSION:
        src_json = convert_policy(src_json, folder, name)
        meta = json.loads(src_json.read_text())
    src = src_json.parent
    files = {"model": f"{name}_policy.npz", "normalizer": f"{name}_vecnormalize.npz"}
    for key, target in files.items():
        source = src / Path(meta["files"][key]).name
        if source.resolve() != (folder / target).resolve():
            shutil.copy2(source, folder / target)
    meta.update(extra)
    meta["name"] = name
    meta["files"] = files
    return write_json(folder / f"{name}.json", meta)


def reference_policies() -> dict[str, Any]:
    """The baselines the RL policies are compared with: the look-up table and flat feedforward at ANR 0.9 and 1.0
    (:class:`control.baselines.FeedforwardDosing`; 1.0 is where an ``"anr"``-action policy starts, action 0)."""
    from control.baselines import FeedforwardDosing, LookupTableDosing

    return {"lookup_table": LookupTableDosing(), "feedforward_anr_0.9": FeedforwardDosing(0.9),
            "feedforward_anr_1.0": FeedforwardDosing(1.0)}


def evaluate_policies(policies: dict[str, Any], cycles: tuple[str, ...],
                      seeds: tuple[int, ...]) -> tuple[dict[str, Any], list[Any]]:
    """``({cycle: {name: {kpi: mean over seeds}}}, the episode results)`` via :func:`control.evaluation.evaluate`."""
    from control.evaluation import evaluate, summarise

    results = []
    for name, policy in policies.items():
        results += evaluate(policy, cycles=cycles, seeds=seeds, name=name)
    return summarise(results), results
