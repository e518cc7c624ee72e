"""What every part of :mod:`control.limit` shares: the result record, the score, the environment of a limit."""
from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from scr_env.constants import EURO_VI_NH3_SLIP_LIMIT_PPM
from scr_env.cycles import ExhaustTrace

#: the slip budgets of the stored Pareto front [ppm mean NH3 slip]
DEFAULT_BUDGETS_PPM: tuple[float, ...] = (1.0, 2.0, 5.0, 10.0, 20.0)
#: the budget at which controllers are scored by :func:`gap_to_limit` [ppm]: the Euro VI mean-slip limit
REFERENCE_BUDGET_PPM = float(EURO_VI_NH3_SLIP_LIMIT_PPM)
#: the cycles of the stored limit: the hot WHTC and WHSC at the 0.5 s control interval of the benchmark
STORED_CYCLES: tuple[str, ...] = ("whtc", "whsc")
#: environment arguments that define the plant of a limit (anything else, e.g. ``sensor_noise`` or ``actuator``, is
#: refused); with ``randomize`` or an ``age_h`` range the plant is the episode's drawn at ``reset(seed=seed)``
PLANT_ARGUMENTS = ("catalyst", "dt", "ageing", "age_h", "randomize", "dosing", "cold_start", "initial_coverage")


# ------------------------------------------------------------------------------------------------------- results
@dataclass(frozen=True)
class LimitResult:
    """The optimum of one cycle at one slip budget.

    The NLP's own figures (``tailpipe_nox_g_per_kwh``, ``mean_nh3_slip_ppm``, ``peak_nh3_slip_ppm``) and those of
    the environment when the dose is replayed open loop (``replay``: its ``episode_kpis``; empty if not replayed).
    ``dose_g_s`` has one AdBlue rate [g/s] per plant step. ``status`` is IPOPT's return status of the final
    multiple-shooting solve, ``success`` whether it reported a solution; ``iterations`` counts the IPOPT iterations
    of both stages (``reduced_iterations`` of the warm start); ``solve_time_s`` is the wall time of the solve
    (``solve_cpu_s`` its CPU time).
    """

    cycle: str
    budget_ppm: float
    tailpipe_nox_g_per_kwh: float
    mean_nh3_slip_ppm: float
    peak_nh3_slip_ppm: float
    adblue_g: float
    dose_g_s: np.ndarray
    status: str
    success: bool
    iterations: int
    solve_time_s: float
    solve_cpu_s: float = float("nan")
    reduced_iterations: int = 0
    reduced_tailpipe_nox_g_per_kwh: float = float("nan")
    peak_ppm: float | None = None
    hold_steps: int = 1
    dt: float = 0.5
    warm_start: str = ""
    replay: dict[str, float] = field(default_factory=dict)
    # the primal-dual solution of the NLP (the warm start of a neighbouring budget); not serialised
    primal_dual: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(default=None, repr=False, compare=False)

    @property
    def replay_tailpipe_nox_g_per_kwh(self) -> float:
        """The environment's tailpipe NOx of the dose replayed open loop [g/kWh] (NaN if not replayed)."""
        return float(self.replay.get("tailpipe_nox_g_per_kwh", float("nan")))

    @property
    def replay_mean_nh3_slip_ppm(self) -> float:
        """The environment's mean NH3 slip of the dose replayed open loop [ppm] (NaN if not replayed)."""
        return float(self.replay.get("mean_nh3_slip_ppm", float("nan")))

    @property
    def replay_error(self) -> float:
        """Relative difference of the replayed and the predicted tailpipe NOx [-] (NaN if not replayed)."""
        return abs(self.replay_tailpipe_nox_g_per_kwh - self.tailpipe_nox_g_per_kwh) / max(
            abs(self.tailpipe_nox_g_per_kwh), 1e-12)

    def __getitem__(self, key: str) -> Any:
        """The record's entries by name, as in the stored JSON (:meth:`to_dict`): ``result["tailpipe_nox_g_per_kwh"]``,
        ``result["replay_tailpipe_nox_g_per_kwh"]``, ``result["dose_g_s"]`` (the array); ``KeyError`` naming the
        key and the known ones otherwise."""
        if key == "dose_g_s":
            return self.dose_g_s
        rec = self.to_dict(dose=False)
        if key not in rec:
            raise KeyError(f"{key!r} is not an entry of a limit record; entries: {', '.join(rec)}, dose_g_s")
        return rec[key]

    def __float__(self) -> float:
        """The limit as one number: the environment's tailpipe NOx of the optimal dose replayed open loop [g/kWh]
        (:attr:`replay_tailpipe_nox_g_per_kwh`; the NLP's figure if it was not replayed), the figure controllers
        are compared with (``float(stored_limit("whtc", 10))``)."""
        r = self.replay_tailpipe_nox_g_per_kwh
        return r if math.isfinite(r) else float(self.tailpipe_nox_g_per_kwh)

    def to_dict(self, dose: bool = True) -> dict[str, Any]:
        """JSON-friendly record (``dose``: with the dose trajectory, rounded to 1e-7 g/s)."""
        out: dict[str, Any] = {
            "tailpipe_nox_g_per_kwh": self.tailpipe_nox_g_per_kwh, "mean_nh3_slip_ppm": self.mean_nh3_slip_ppm,
            "peak_nh3_slip_ppm": self.peak_nh3_slip_ppm, "adblue_g": self.adblue_g,
            "replay_tailpipe_nox_g_per_kwh": self.replay_tailpipe_nox_g_per_kwh,
            "replay_mean_nh3_slip_ppm": self.replay_mean_nh3_slip_ppm,
            "replay_peak_nh3_slip_ppm": float(self.replay.get("peak_nh3_slip_ppm", float("nan"))),
            "replay_adblue_g": float(self.replay.get("adblue_g", float("nan"))),
            "replay_nox_conversion": float(self.replay.get("nox_conversion", float("nan"))),
            "replay_relative_error": self.replay_error, "status": self.status, "success": self.success,
            "iterations": self.iterations, "reduced_iterations": self.reduced_iterations,
            "reduced_tailpipe_nox_g_per_kwh": self.reduced_tailpipe_nox_g_per_kwh,
            "solve_time_s": self.solve_time_s, "solve_cpu_s": self.solve_cpu_s, "budget_ppm": self.budget_ppm,
            "peak_ppm": self.peak_ppm, "hold_steps": self.hold_steps, "dt": self.dt, "warm_start": self.warm_start,
        }
        if dose:
            out["dose_g_s"] = [round(float(v), 7) for v in self.dose_g_s]
        return out

    @classmethod
    def from_dict(cls, cycle: str, record: Mapping[str, Any]) -> LimitResult:
        """The result of a stored record (:meth:`to_dict`); ``KeyError`` / ``ValueError`` if it is not one."""
        replay_kpis = {k[len("replay_"):]: float(v) for k, v in record.items()
                       if k.startswith("replay_") and k != "replay_relative_error"
                       and isinstance(v, (int, float)) and not isinstance(v, bool)}
        nan = float("nan")
        return cls(cycle=cycle, budget_ppm=float(record["budget_ppm"]),
                   tailpipe_nox_g_per_kwh=float(record["tailpipe_nox_g_per_kwh"]),
                   mean_nh3_slip_ppm=float(record["mean_nh3_slip_ppm"]),
                   peak_nh3_slip_ppm=float(record.get("peak_nh3_slip_ppm", nan)),
                   adblue_g=float(record.get("adblue_g", nan)),
                   dose_g_s=np.asarray(record.get("dose_g_s", []), dtype=np.float64),
                   status=str(record.get("status", "")), success=bool(record.get("success", False)),
                   iterations=int(record.get("iterations", 0)), solve_time_s=float(record.get("solve_time_s", nan)),
                   solve_cpu_s=float(record.get("solve_cpu_s", nan)),
                   reduced_iterations=int(record.get("reduced_iterations", 0)),
                   reduced_tailpipe_nox_g_per_kwh=float(record.get("reduced_tailpipe_nox_g_per_kwh", nan)),
                   peak_ppm=None if record.get("peak_ppm") is None else float(record["peak_ppm"]),
                   hold_steps=int(record.get("hold_steps", 1)), dt=float(record.get("dt", 0.5)),
                   warm_start=str(record.get("warm_start", "")), replay=replay_kpis)


def gap_to_limit(lut_nox: float, controller_nox: float, limit_nox: float) -> float:
    """The fraction of the look-up-table-to-limit gap in tailpipe NOx that a controller closes [-].

    ``(lut_nox - controller_nox) / (lut_nox - limit_nox)``, all three in the same unit (g/kWh): 0 is the look-up
    table, 1 the clairvoyant optimum (``stored_limit(cycle, 10).replay_tailpipe_nox_g_per_kwh``), negative worse
    than the look-up table. Above 1 the controller is below the limit: on the same plant, cycle and slip budget that
    is impossible, so the limit or the controller's figure is wrong (compare like with like: the controller's mean
    slip must be within the limit's budget). NaN when the look-up table is not above the limit (no gap to close).
    ``ValueError`` naming the argument if one is not a finite number.
    """
    vals = {}
    for name, v in (("lut_nox", lut_nox), ("controller_nox", controller_nox), ("limit_nox", limit_nox)):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)) \
                or not math.isfinite(v):
            raise ValueError(f"{name} must be a finite number (tailpipe NOx, g/kWh), got {v!r}")
        vals[name] = float(v)
    gap = vals["lut_nox"] - vals["limit_nox"]
    if not gap > 0:
        return float("nan")
    return (vals["lut_nox"] - vals["controller_nox"]) / gap


def _positive(name: str, value: Any) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return float(value)


def _count(name: str, value: Any, minimum: int = 1) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


# ----------------------------------------------------------------------------------------------- the environment
def _plant_kwargs(env_kwargs: Mapping[str, Any] | None) -> dict[str, Any]:
    """The environment arguments of a plant (:data:`PLANT_ARGUMENTS`) checked; ``ValueError`` naming others."""
    if env_kwargs is not None and not isinstance(env_kwargs, Mapping):
        raise ValueError(f"env_kwargs must be a dict of environment arguments, got {type(env_kwargs).__name__}")
    kw = dict(env_kwargs or {})
    bad = sorted(k for k in kw if k not in PLANT_ARGUMENTS)
    if bad:
        raise ValueError(f"env_kwargs: {', '.join(bad)} cannot be given to the limit (it is solved for one fixed "
                         f"plant without sensor noise); allowed: {', '.join(PLANT_ARGUMENTS)}")
    return kw


def make_env(cycle: str | os.PathLike | ExhaustTrace = "whtc", env_kwargs: Mapping[str, Any] | None = None) -> Any:
    """The environment of a limit: ``UreaSCREnv(cycle, **env_kwargs)`` without sensor noise, actions in g/s."""
    from scr_env.envs.urea_scr import UreaSCREnv

    return UreaSCREnv(cycle=cycle, sensor_noise=False, action_mode="physical", **_plant_kwargs(env_kwargs))


def replay(cycle: str | os.PathLike | ExhaustTrace, dose_g_s: Sequence[float] | np.ndarray,
           env_kwargs: Mapping[str, Any] | None = None, record: bool = False, seed: int = 0) -> dict[str, Any]:
    """Run ``dose_g_s`` (one AdBlue rate [g/s] per step of the cycle) open loop through the environment (no sensor
    noise; the episode of ``reset(seed=seed)``) and return its ``episode_kpis``; with ``record`` also the per-step
    arrays ``tailpipe_nox_ppm``, ``tailpipe_nh3_ppm`` and ``nh3_coverage`` (steps x cells). ``ValueError`` if the
    dose has the wrong length or a non-finite entry."""
    env = make_env(cycle, env_kwargs)
    env.reset(seed=_count("seed", seed, 0))
    n = env.trace.n_steps
    dose = np.asarray(dose_g_s, dtype=np.float64).ravel()
    if dose.size != n:
        raise ValueError(f"dose_g_s has {dose.size} entries, the cycle {env.trace.name!r} {n} steps")
    if not np.all(np.isfinite(dose)):
        raise ValueError("dose_g_s must be finite")
    nox, nh3, cov = np.empty(n), np.empty(n), np.empty((n, env.config.catalyst.n_cells))
    act = np.zeros(1)
    info: dict[str, Any] = {}
    for k in range(n):
        act[0] = dose[k]
        _, _, _, _, info = env.step(act)
        if record:
            nox[k], nh3[k] = info["tailpipe_nox_ppm"], info["tailpipe_nh3_ppm"]
            cov[k] = env.state["nh3_coverage"]
    out: dict[str, Any] = dict(info["episode_kpis"])
    if record:
        out.update(tailpipe_nox_ppm=nox, tailpipe_nh3_ppm=nh3, nh3_coverage=cov)
    return out



def cycle_segment(cycle: str | os.PathLike | ExhaustTrace, start: int, steps: int, dt: float = 0.5) -> ExhaustTrace:
    """Steps ``start`` .. ``start + steps - 1`` of a cycle as a trace of its own (time from 0, named
    ``"<cycle>[start:end]"``), for short problems: an episode on it starts as the environment starts any (hot
    start at its first inlet temperature, empty storage)."""
    from scr_env.cycles import load_cycle

    trace = cycle if isinstance(cycle, ExhaustTrace) else load_cycle(cycle, dt=dt)
    start, steps = _count("start", start, 0), _count("steps", steps)
    if start + steps > trace.n_steps:
        raise ValueError(f"start + steps = {start + steps} is past the end of {trace.name!r} ({trace.n_steps} steps)")
    fields = {f: getattr(trace, f)[start:start + steps].copy() for f in trace.__dataclass_fields__
              if isinstance(getattr(trace, f), np.ndarray)}
    fields["time_s"] = fields["time_s"] - fields["time_s"][0]
    return replace(trace, name=f"{trace.name}[{start}:{start + steps}]", **fields)
