"""Validation of the environment arguments, shared by the single and the vector environment."""
from __future__ import annotations

import math
import numbers
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from scr_env.actuator import ActuatorParams, actuator_params
from scr_env.cycles import ExhaustTrace, available_cycles, load_cycle
from scr_env.envs.core import NH3_SENSOR_HIGH, OBS_BASE, OBS_BASE_HIGH, OBS_BASE_LOW, RewardWeights
from scr_env.params import (
    CatalystParams,
    DosingParams,
    SensorParams,
    aged,
    catalyst_preset,
    check_age_h,
    check_age_range,
    randomised,
)

ACTION_MODES = ("normalized", "physical")
O2_FRACTION = 0.10  # mole fraction of O2 at the SCR inlet [chosen: the lab reference; the kinetics are at most
#                     half order in O2, and the engine-out O2 (8-18 % for a lean diesel) is not modelled]
MAX_DT_S = 10.0  # s; coverage and thermal steps stay stable for any dt, but sensors and KPIs assume a fine grid


@dataclass(frozen=True)
class EnvConfig:
    """Validated arguments of a UreaSCR environment."""

    cycle: Any
    catalyst: CatalystParams
    dt: float
    ageing: float
    dosing: DosingParams
    sensors: SensorParams
    reward_weights: RewardWeights
    action_mode: str
    nh3_sensor: bool
    privileged: bool
    cold_start: bool
    randomize: float
    initial_coverage: float
    random_cycle_duration_s: float
    actuator: ActuatorParams | None = None
    age_h_range: tuple[float, float] | None = None

    @property
    def effective_catalyst(self) -> CatalystParams:
        return aged(self.catalyst, self.ageing) if self.ageing > 0 else self.catalyst

    @property
    def randomizes(self) -> bool:
        """Whether each episode draws its own catalyst (``randomize`` > 0 or an ``age_h`` range)."""
        return self.randomize > 0 or self.age_h_range is not None

    def episode_catalyst(self, rng: np.random.Generator) -> CatalystParams:
        """The catalyst of a new episode: domain-randomised by ``randomize`` and, with an ``age_h`` range, at a
        uniformly drawn age (:func:`scr_env.params.randomised`)."""
        cat = randomised(self.catalyst, rng, self.randomize, age_h_range=self.age_h_range)
        return aged(cat, self.ageing) if self.ageing > 0 else cat

    @property
    def obs_names(self) -> tuple[str, ...]:
        names = list(OBS_BASE)
        if self.nh3_sensor:
            names.append("tailpipe_nh3_sensor_ppm")
        if self.privileged:
            names += [f"nh3_coverage_cell{j}" for j in range(self.catalyst.n_cells)]
        return tuple(names)

    def obs_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        low = list(OBS_BASE_LOW)
        high = list(OBS_BASE_HIGH)
        if self.nh3_sensor:
            low.append(0.0)
            high.append(NH3_SENSOR_HIGH)
        if self.privileged:
            low += [0.0] * self.catalyst.n_cells
            high += [1.0] * self.catalyst.n_cells
        return np.array(low, dtype=np.float32), np.array(high, dtype=np.float32)

    def trace(self, cycle: Any, seed: int | None, cold_start: bool) -> ExhaustTrace:
        """Load ``cycle`` (name, path or ExhaustTrace) at this config's dt."""
        if isinstance(cycle, ExhaustTrace):
            if abs(cycle.dt - self.dt) > 1e-12:
                raise ValueError(f"cycle: the ExhaustTrace has dt = {cycle.dt} s but the environment dt = {self.dt} s")
            return cycle
        return load_cycle(cycle, dt=self.dt, cold_start=cold_start, seed=seed,
                          duration_s=self.random_cycle_duration_s)


def _number(name: str, value: Any, lo: float, hi: float, lo_open: bool = False) -> float:
    """``value`` as a float in [lo, hi] (or (lo, hi]); ValueError naming ``name`` for anything else, including
    bools and numeric strings (no silent coercion)."""
    if isinstance(value, np.ndarray) and value.ndim == 0 and value.dtype.kind in "fiu":
        value = value[()]
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        # ValueError, as every argument error of the environment (make_config's contract), also for a wrong type
        raise ValueError(f"{name} must be a number, got {value!r}")  # noqa: TRY004
    v = float(value)
    if not math.isfinite(v) or v < lo or v > hi or (lo_open and v == lo):
        interval = f"{'(' if lo_open else '['}{lo}, {hi}]"
        raise ValueError(f"{name} must be a finite number in {interval}, got {value!r}")
    return v


def flag(name: str, value: Any) -> bool:
    """``value`` as a bool: True/False or a numpy bool; ValueError naming ``name`` for anything else (a string such
    as "no" or "False", a number, None), which ``bool()`` would silently turn into True or False."""
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise ValueError(f"{name} must be True or False, got {value!r} ({type(value).__name__})")


def reset_options(options: Any, allowed: tuple[str, ...]) -> dict[str, Any]:
    """The ``options`` of ``reset`` as a dict: None or a mapping whose keys are all in ``allowed`` (ValueError
    naming ``options`` otherwise)."""
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise ValueError(f"options must be None or a dict with keys among {', '.join(allowed)}; "  # noqa: TRY004
                         f"got {type(options).__name__} {options!r}")
    unknown = [k for k in options if k not in allowed]
    if unknown:
        raise ValueError(f"options has unknown key(s) {', '.join(sorted(map(repr, unknown)))}; "
                         f"use {', '.join(allowed)}")
    return dict(options)


def reset_coverage(options: dict[str, Any], default: float) -> float:
    """``options["initial_coverage"]`` (``default`` if absent) checked to be a number in [0, 1]."""
    if "initial_coverage" not in options:
        return default
    return _number("options['initial_coverage']", options["initial_coverage"], 0.0, 1.0)


def make_config(cycle: Any = "whtc", catalyst: Any = "cu_zeolite", dt: float = 0.5, ageing: float = 0.0,
                dosing: DosingParams | None = None, sensors: SensorParams | None = None,
                sensor_noise: bool = True, reward_weights: Any = None, action_mode: str = "normalized",
                nh3_sensor: bool = False, privileged: bool = False, cold_start: bool = False,
                randomize: float = 0.0, initial_coverage: float = 0.0,
                random_cycle_duration_s: float = 1800.0, actuator: Any = None, age_h: Any = 0.0) -> EnvConfig:
    """Check every environment argument and return an :class:`EnvConfig` (ValueError naming the argument).

    Numbers must be numbers (not strings or bools) and flags must be bools (``True``/``False`` or numpy bools): a
    string such as ``nh3_sensor="no"`` raises instead of counting as True.

    ``age_h`` is the catalyst's hydrothermal ageing in hours (0 to 16, the CLEERS samples:
    :data:`scr_env.params.AGEING_TABLE`), or a pair ``(lo, hi)`` to draw it uniformly per episode (domain
    randomisation of ageing). ``ageing`` is the older severity in [0, 1] (16 h at 1); give one or the other."""
    sensor_noise = flag("sensor_noise", sensor_noise)
    nh3_sensor = flag("nh3_sensor", nh3_sensor)
    privileged = flag("privileged", privileged)
    cold_start = flag("cold_start", cold_start)
    dt = _number("dt", dt, 0.0, MAX_DT_S, lo_open=True)
    if isinstance(cycle, str) and cycle.strip().lower() in available_cycles():
        cycle = cycle.strip().lower()
    elif isinstance(cycle, (str, os.PathLike)):
        if not os.path.isfile(os.fspath(cycle)):
            raise ValueError(f"cycle must be one of {', '.join(available_cycles())}, a path to a CSV file or an "
                             f"ExhaustTrace; got {cycle!r}")
    elif not isinstance(cycle, ExhaustTrace):
        raise ValueError(f"cycle must be one of {', '.join(available_cycles())}, a path to a CSV file or an "
                         f"ExhaustTrace; got {type(cycle).__name__}")
    try:
        cat = catalyst_preset(catalyst)
    except ValueError as e:
        raise ValueError(f"catalyst: {e}") from None
    ageing = _number("ageing", ageing, 0.0, 1.0)
    age_h_range = None
    if isinstance(age_h, (tuple, list)):
        age_h_range = check_age_range(tuple(age_h), "age_h")
        if ageing > 0:
            raise ValueError("give either ageing (a severity) or age_h (hours), not both")
        cat = cat.replace(age_h=age_h_range[0])
    else:
        age = check_age_h(age_h, "age_h")
        if age > 0:
            if ageing > 0:
                raise ValueError("give either ageing (a severity) or age_h (hours), not both")
            cat = cat.replace(age_h=age)
    dosing = DosingParams() if dosing is None else dosing
    if not isinstance(dosing, DosingParams):
        raise ValueError(f"dosing must be a DosingParams, got {type(dosing).__name__}")  # noqa: TRY004 (contract)
    sensors = SensorParams() if sensors is None else sensors
    if not isinstance(sensors, SensorParams):
        raise ValueError(f"sensors must be a SensorParams, got {type(sensors).__name__}")  # noqa: TRY004
    if not sensor_noise:
        sensors = sensors.noiseless()
    if reward_weights is None:
        weights = RewardWeights()
    elif isinstance(reward_weights, RewardWeights):
        weights = reward_weights
    elif isinstance(reward_weights, dict):
        unknown = set(reward_weights) - {"nox", "nh3", "adblue"}
        if unknown:
            raise ValueError(f"reward_weights has unknown keys {sorted(unknown)}; use nox, nh3, adblue")
        weights = RewardWeights(**reward_weights)
    else:
        raise ValueError("reward_weights must be a dict with keys nox, nh3, adblue or a RewardWeights")
    if action_mode not in ACTION_MODES:
        raise ValueError(f"action_mode must be one of {ACTION_MODES}, got {action_mode!r}")
    randomize = _number("randomize", randomize, 0.0, 0.9)
    initial_coverage = _number("initial_coverage", initial_coverage, 0.0, 1.0)
    duration = _number("random_cycle_duration_s", random_cycle_duration_s, 10.0, 86400.0)
    act = actuator_params(actuator)
    return EnvConfig(cycle=cycle, catalyst=cat, dt=dt, ageing=ageing, dosing=dosing, sensors=sensors,
                     reward_weights=weights, action_mode=action_mode, nh3_sensor=nh3_sensor,
                     privileged=privileged, cold_start=cold_start, randomize=randomize,
                     initial_coverage=initial_coverage, random_cycle_duration_s=duration, actuator=act,
                     age_h_range=age_h_range)
