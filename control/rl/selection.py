"""Choosing, installing and scoring trained dosing policies (the library side of ``experiments.train_rl``).

* :func:`validate` and :func:`select`: every checkpoint of a run on the validation cycles -- hot-start random cycles
  of :data:`VALIDATION_DURATION_S` with the reset seeds :data:`VALIDATION_SEEDS`, never the held-out WHTC/WHSC --
  and the rule: the lowest mean tailpipe NOx among the candidates whose worst mean slip there is within the Euro VI
  limit, else the one with the lowest worst slip;
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

__all__ = ["VALIDATION_DURATION_S", "VALIDATION_SEEDS", "VALIDATION_SLIP_LIMIT_PPM", "candidates_in",
           "evaluate_policies", "install", "reference_policies", "select", "validate"]

#: checkpoint selection (validation, never the held-out WHTC/WHSC): hot-start random cycles of this length, seeds
VALIDATION_DURATION_S = 3600.0
VALIDATION_SEEDS = (1001, 1002, 1003, 1004)
VALIDATION_SLIP_LIMIT_PPM = EURO_VI_NH3_SLIP_LIMIT_PPM


def validate(candidates: list[Path], seeds: tuple[int, ...] = VALIDATION_SEEDS) -> list[dict[str, Any]]:
    """KPIs of each candidate policy on the validation cycles (long random cycles, never the WHTC/WHSC)."""
    from control.evaluation import evaluate
    from control.rl.policy import load_policy

    rows = []
    for path in candidates:
        res = evaluate(load_policy(path), cycles=("random",), seeds=seeds,
                       env_kwargs={"random_cycle_duration_s": VALIDATION_DURATION_S}, name=path.stem)
        tp = [r.kpis["tailpipe_nox_g_per_kwh"] for r in res]
        slip = [r.kpis["mean_nh3_slip_ppm"] for r in res]
        rows.append({"candidate": str(path), "timesteps": int(json.loads(path.read_text()).get("timesteps", 0)),
                     "tailpipe_nox_g_per_kwh_mean": float(np.mean(tp)), "mean_nh3_slip_ppm_max": float(np.max(slip)),
                     "tailpipe_nox_g_per_kwh": tp, "mean_nh3_slip_ppm": slip})
        print(f"validation {path.stem:16s} tailpipe {np.mean(tp):.3f} g/kWh  worst mean slip {np.max(slip):.1f} ppm",
              flush=True)
    return rows


def select(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The rule: lowest mean validation tailpipe NOx among candidates whose worst validation mean slip is at most
    :data:`VALIDATION_SLIP_LIMIT_PPM`; if none is, the one with the lowest worst slip."""
    if not rows:
        raise ValueError("rows is empty: no candidate policy to select from")
    ok = [r for r in rows if r["mean_nh3_slip_ppm_max"] <= VALIDATION_SLIP_LIMIT_PPM]
    if ok:
        return min(ok, key=lambda r: r["tailpipe_nox_g_per_kwh_mean"])
    return min(rows, key=lambda r: r["mean_nh3_slip_ppm_max"])


def candidates_in(folder: Path) -> list[Path]:
    """Checkpoints (``checkpoints/*.json``) and the final policy (``policy/*.json``) of a run folder."""
    found = sorted((folder / "checkpoints").glob("*.json"), key=lambda p: int(json.loads(p.read_text())["timesteps"]))
    return found + sorted((folder / "policy").glob("*.json"))[:1]


def install(src_json: Path, folder: Path, name: str, extra: dict[str, Any]) -> Path:
    """Copy a saved policy (zip, NPZ, JSON) under the name ``name`` into ``folder``, metadata updated by ``extra``
    (the JSON written atomically, last)."""
    meta = json.loads(src_json.read_text())
    folder.mkdir(parents=True, exist_ok=True)
    src = src_json.parent
    if src.resolve() != folder.resolve() or meta["files"]["model"] != f"{name}.zip":
        shutil.copy2(src / meta["files"]["model"], folder / f"{name}.zip")
        shutil.copy2(src / meta["files"]["normalizer"], folder / f"{name}_vecnormalize.npz")
    meta.update(extra)
    meta["name"] = name
    meta["files"] = {"model": f"{name}.zip", "normalizer": f"{name}_vecnormalize.npz"}
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
