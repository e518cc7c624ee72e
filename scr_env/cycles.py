"""Drive cycles as SCR-inlet disturbance traces: WHTC, WHSC, seeded random cycles and user-measured CSV data.

Every source ends as an :class:`ExhaustTrace`: the SCR-inlet conditions (exhaust flow, temperature, NOx, NO2/NOx)
and the engine operating point, sampled every ``dt`` seconds from ``t = 0``.

Sources
-------
``"whtc"``, ``"whsc"``
    The real UN GTR No. 4 schedules shipped in ``scr_env/data/cycles`` (see PROVENANCE.md there). The 1 Hz table rows
    ``t = 1..N s`` are mapped to ``t = 0..N-1 s``, denormalised with :func:`denormalise` at the 1 Hz points, linearly
    interpolated in between and the last value held, giving ``floor(N / dt)`` samples (WHTC at 0.5 s: 3600; WHSC:
    3790). Then the engine-out model and the DOC/DPF thermal path of :mod:`scr_env.engine` give the SCR inlet.
``"random"``
    :func:`random_cycle`: a seeded Markov chain of idle, launch, cruise, urban stop-and-go, stationary and motoring
    segments in normalised speed/torque, rate limited, then through the same engine model. Same seed, same trace.
``"random_modes"``
    :func:`random_cycle` with ``kind="ramped_modes"``: seeded WHSC-like loaded steady modes joined by 20 s ramps.
a path to a CSV file
    :func:`from_csv`, measured SCR-inlet data replayed as is (format below).

Hot and cold start
------------------
``cold_start=True`` starts DOC and DPF at ambient (298.15 K), as the cold WHTC. Otherwise (hot start) they start at
``max(EngineParams.hot_start_temperature_k, steady state of the first operating point)``: 500 K by default, the
warm state of the aftertreatment after the 10 min soak that precedes the hot WHTC. It keeps the hot-WHTC SCR inlet in
the 450-700 K band of the thesis data (PHYSICS.md section 1).

User CSV format (:func:`from_csv`)
----------------------------------
Plain comma-separated UTF-8 text (a byte-order mark, as spreadsheets write it, is accepted). Lines starting with
``#`` are comments; the first other line is the header, each column named once. Columns (any order, extra columns
ignored):

==========================  ========  ==========================================================================
column                      unit      notes
==========================  ========  ==========================================================================
time_s                      s         required, strictly increasing (shifted so that the trace starts at 0)
exhaust_flow_mol_s          mol/s     required unless exhaust_mass_flow_kg_s is given (M = 28.9 g/mol)
exhaust_mass_flow_kg_s      kg/s      alternative to exhaust_flow_mol_s
scr_inlet_temperature_k     K         required, in kelvin, 200 to 1500 K: a value below 200 K raises (degC
                                      data), above 1500 K raises; a record below 273.15 K throughout, or with a
                                      median below 373.15 K that is no warm-up, warns (likely degC data)
nox_ppm                     ppm       required, SCR-inlet NOx (mole ppm)
no2_fraction                -         optional NO2/NOx in [0, 1], default 0.3 (a DOC in its active window)
engine_power_kw             kW        optional, default 0: then ``positive_work_kwh`` is 0 and g/kWh figures are
                                      unavailable (the environment reports them as NaN)
engine_speed_rpm            rpm       optional, default 0 (unknown)
engine_torque_nm            Nm        optional, default 0 (unknown)
==========================  ========  ==========================================================================

The data are linearly interpolated to ``t = 0, dt, 2 dt, ... <= t_end - t_start``, at most
:data:`MAX_TRACE_SAMPLES` samples. :meth:`ExhaustTrace.to_csv` writes this format. The engine model and
``cold_start`` play no role for measured data.

Validation
----------
Every trace, whatever its source, is checked when it is built (:class:`ExhaustTrace`): finite values, flows >= 0,
NOx in [0, 1e6] ppm, NO2/NOx in [0, 1], SCR-inlet temperature in [200, 1500] K, engine speed >= 0, ``time_s``
advancing by exactly ``dt`` per sample, ``dt`` finite and positive, and at most :data:`MAX_TRACE_SAMPLES` samples
(the drive cycles and CSV replay check that bound before allocating anything). A violation raises ValueError
naming the field, its unit and the first offending sample.
"""
from __future__ import annotations

import functools
import math
import os
import warnings
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from scr_env.constants import EXHAUST_MOLAR_MASS_KG_MOL
from scr_env.engine import (
    EngineParams,
    aftertreatment_temperatures,
    doc_no2_fraction,
    engine_out,
    full_load_torque_nm,
    motoring_torque_nm,
    steady_state_solid_temperatures,
)

__all__ = [
    "MAX_TEMPERATURE_K",
    "MAX_TRACE_SAMPLES",
    "MIN_TEMPERATURE_K",
    "RANDOM_CYCLES",
    "RANDOM_CYCLE_KINDS",
    "ExhaustTrace",
    "available_cycles",
    "denormalise",
    "from_csv",
    "is_random_cycle",
    "load_cycle",
    "random_cycle",
]

_MAX_DT_S = 10.0  # s; coarser sampling would alias the cycles' 1 Hz content [chosen]
_RANDOM_DEFAULT_DURATION_S = 1800.0  # s, as long as the WHTC [chosen]
# Below this an SCR-inlet temperature is taken for degC (or another unit), not kelvin: -73 degC, colder than the
# coldest air a truck starts in (record lows of inhabited places are about -68 degC, 205 K), so no measured cold
# start is rejected, while degC data with idle, motoring or a cold start (values of 20-200) are [chosen]
_MIN_PLAUSIBLE_TEMPERATURE_K = 200.0
#: K, the hottest SCR-inlet gas accepted: diesel exhaust after the turbine stays below about 1000 K, cordierite
#: bricks melt near 1700 K, and the observation space ends at 1500 K [chosen]
MAX_TEMPERATURE_K = 1500.0
MIN_TEMPERATURE_K = _MIN_PLAUSIBLE_TEMPERATURE_K  # K (see above)
#: the most samples one trace may have: 5 million (58 days at 1 s, the WHTC at dt = 0.36 ms). Its nine float64
#: arrays then take 360 MB, and an environment holds about as much again (drive table, sensor noise); a finer dt or
#: a longer record raises ValueError before anything is allocated [chosen: fits a laptop, far above any use]
MAX_TRACE_SAMPLES = 5_000_000
# A CSV whose median temperature is below this, and which is not a warm-up, is probably in degC: a running diesel's
# SCR inlet is hotter than boiling water except in the first minutes after a cold start [chosen]
_DEGC_MEDIAN_K = 373.15
_WARM_UP_RISE_K = 100.0  # K: last tenth of a record this much warmer than its first tenth: a warm-up [chosen]
_DEFAULT_NO2_FRACTION = 0.3  # - , user CSV without NO2/NOx: a DOC in its active window [chosen, PHYSICS.md 4]
_TABLES = {"whtc": "whtc_normalized.csv", "whsc": "whsc_normalized_1hz.csv"}
_CSV_COLUMNS = (
    "time_s", "exhaust_flow_mol_s", "exhaust_mass_flow_kg_s", "scr_inlet_temperature_k", "nox_ppm", "no2_fraction",
    "engine_power_kw", "engine_speed_rpm", "engine_torque_nm",
)
_ARRAY_FIELDS = (
    "time_s", "engine_speed_rpm", "engine_torque_nm", "engine_power_kw", "exhaust_mass_flow_kg_s",
    "exhaust_flow_mol_s", "scr_inlet_temperature_k", "nox_ppm", "no2_fraction",
)


@dataclass(frozen=True, eq=False)
class ExhaustTrace:
    """SCR-inlet conditions and engine operating point, sampled every ``dt`` seconds from ``t = 0``.

    Every array field is float64 with length ``n_steps``. The constructor validates every field (module docstring,
    "Validation") and raises ValueError naming the first violation.

    Attributes
    ----------
    name : str
        Cycle name (``"whtc"``, ``"whsc"``, ``"random-<seed>"`` or the CSV file stem).
    dt : float
        Sample interval [s].
    time_s : numpy.ndarray
        Sample times [s], ``k * dt``.
    engine_speed_rpm, engine_torque_nm : numpy.ndarray
        Engine speed [rpm] and brake torque [Nm] (negative when motored; 0 if unknown for measured data).
    engine_power_kw : numpy.ndarray
        Brake power [kW], negative when motored.
    exhaust_mass_flow_kg_s, exhaust_flow_mol_s : numpy.ndarray
        Exhaust flow [kg/s] and [mol/s] (M = 28.9 g/mol).
    scr_inlet_temperature_k : numpy.ndarray
        Gas temperature at the SCR inlet [K].
    nox_ppm : numpy.ndarray
        NOx (NO + NO2) at the SCR inlet [mole ppm].
    no2_fraction : numpy.ndarray
        NO2/NOx at the SCR inlet, after the DOC [-].
    """

    name: str
    dt: float
    time_s: np.ndarray
    engine_speed_rpm: np.ndarray
    engine_torque_nm: np.ndarray
    engine_power_kw: np.ndarray
    exhaust_mass_flow_kg_s: np.ndarray
    exhaust_flow_mol_s: np.ndarray
    scr_inlet_temperature_k: np.ndarray
    nox_ppm: np.ndarray
    no2_fraction: np.ndarray

    def __post_init__(self) -> None:
        if not isinstance(self.name, str):
            raise ValueError(f"ExhaustTrace.name must be a string, got {type(self.name).__name__}")  # noqa: TRY004
        try:
            dt = float(self.dt)
        except (TypeError, ValueError):
            raise ValueError(f"ExhaustTrace.dt must be a number of seconds, got {self.dt!r}") from None
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"ExhaustTrace.dt must be a finite positive number of seconds, got {self.dt!r}")
        object.__setattr__(self, "dt", dt)
        n = None
        for name in _ARRAY_FIELDS:
            try:
                arr = np.ascontiguousarray(getattr(self, name), dtype=np.float64)
            except (TypeError, ValueError):
                raise ValueError(f"ExhaustTrace.{name} must be an array of real numbers") from None
            if arr.ndim != 1:
                raise ValueError(f"{name} must be one-dimensional")
            if n is None:
                n = arr.size
            elif arr.size != n:
                raise ValueError(f"{name} has length {arr.size}, expected {n}")
            bad = np.flatnonzero(~np.isfinite(arr))
            if bad.size:
                raise ValueError(f"ExhaustTrace.{name} must be finite; {arr[bad[0]]} at sample {bad[0]}")
            object.__setattr__(self, name, arr)
        if n == 0:
            raise ValueError("ExhaustTrace needs at least one sample")
        _check_samples(n, f"ExhaustTrace {self.name!r}")
        for name, lo, hi, unit in _RANGES:
            arr = getattr(self, name)
            out = np.flatnonzero((arr < lo) | (arr > hi))
            if out.size:
                raise ValueError(f"ExhaustTrace.{name} must lie in [{lo:g}, {hi:g}] {unit}; {arr[out[0]]:g} {unit} at "
                                 f"sample {out[0]} (t = {self.time_s[out[0]]:g} s)")
        if n > 1:
            step = np.diff(self.time_s)
            if not np.all(np.abs(step - dt) <= 1e-6 * dt):
                k = int(np.argmax(np.abs(step - dt)))
                raise ValueError(f"ExhaustTrace.time_s must increase by dt = {dt:g} s per sample (unique, monotonic, "
                                 f"evenly spaced); it goes from {self.time_s[k]:g} s to {self.time_s[k + 1]:g} s at "
                                 f"sample {k}. Resample uneven data with from_csv")

    @property
    def n_steps(self) -> int:
        """Number of samples."""
        return int(self.time_s.size)

    @property
    def duration_s(self) -> float:
        """Duration covered by the samples [s], ``n_steps * dt``."""
        return self.n_steps * self.dt

    @property
    def positive_work_kwh(self) -> float:
        """Positive engine work [kWh]: sum of max(power, 0) dt / 3600 (the basis of g/kWh figures)."""
        return float(np.sum(np.maximum(self.engine_power_kw, 0.0)) * self.dt / 3600.0)

    def copy(self) -> ExhaustTrace:
        """A deep copy (fresh, writable arrays)."""
        return replace(self, **{name: getattr(self, name).copy() for name in _ARRAY_FIELDS})

    def to_csv(self, path: str | os.PathLike) -> None:
        """Write the trace in the :func:`from_csv` format (full float precision)."""
        header = ",".join(_CSV_COLUMNS)
        data = np.column_stack([getattr(self, c) for c in _CSV_COLUMNS])
        np.savetxt(path, data, delimiter=",", fmt="%.17g", header=f"# scr_env ExhaustTrace '{self.name}', "
                   f"dt = {self.dt} s\n{header}", comments="")


def available_cycles() -> tuple[str, ...]:
    """Names accepted by :func:`load_cycle` (besides a path to a CSV file)."""
    return ("whtc", "whsc", *RANDOM_CYCLES)


def is_random_cycle(cycle: object) -> bool:
    """Whether ``cycle`` names a seeded random cycle (:data:`RANDOM_CYCLES`): a new trace per seed."""
    return isinstance(cycle, str) and cycle in RANDOM_CYCLES


# the physical range of each field of a trace (field, low, high, unit)
_RANGES = (
    ("exhaust_flow_mol_s", 0.0, math.inf, "mol/s"),
    ("exhaust_mass_flow_kg_s", 0.0, math.inf, "kg/s"),
    ("scr_inlet_temperature_k", MIN_TEMPERATURE_K, MAX_TEMPERATURE_K, "K"),
    ("nox_ppm", 0.0, 1.0e6, "ppm"),
    ("no2_fraction", 0.0, 1.0, "(NO2/NOx)"),
    ("engine_speed_rpm", 0.0, math.inf, "rpm"),
)


# ----------------------------------------------------------------------------------------------------------- helpers
def _check_samples(n: float, what: str, dt: float | None = None) -> None:
    """ValueError if a trace of ``n`` samples would exceed :data:`MAX_TRACE_SAMPLES` (checked before allocating)."""
    if not n <= MAX_TRACE_SAMPLES:  # also NaN and inf (a denormal dt)
        hint = f" at dt = {dt:g} s" if dt is not None else ""
        raise ValueError(f"{what}{hint} would have {n:,.0f} samples, more than MAX_TRACE_SAMPLES = "
                         f"{MAX_TRACE_SAMPLES:,} (about {MAX_TRACE_SAMPLES * 9 * 8 / 1e6:.0f} MB per trace); use a "
                         f"larger dt or a shorter record")


def _check_dt(dt: float) -> float:
    try:
        value = float(dt)
    except (TypeError, ValueError):
        raise ValueError(f"dt must be a number of seconds, got {dt!r}") from None
    if not (math.isfinite(value) and 0.0 < value <= _MAX_DT_S):
        raise ValueError(f"dt must be finite and in (0, {_MAX_DT_S}] s, got {dt!r}")
    return value


def _check_flag(name: str, value: object) -> bool:
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    raise ValueError(f"{name} must be True or False, got {value!r} ({type(value).__name__})")


def _read_csv(text: str, source: str) -> dict[str, np.ndarray]:
    """Parse comma-separated text with '#' comment lines and one header line; empty fields become NaN."""
    lines = [ln.strip() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln and not ln.startswith("#")]
    if not lines:
        raise ValueError(f"{source}: no header line")
    header = [h.strip() for h in lines[0].split(",")]
    seen: set[str] = set()
    for h in header:
        if h in seen:
            raise ValueError(f"{source}: column {h!r} appears twice in the header; which one holds the data is "
                             f"ambiguous")
        seen.add(h)
    rows = []
    for i, line in enumerate(lines[1:], start=2):
        parts = line.split(",")
        if len(parts) != len(header):
            raise ValueError(f"{source}: data line {i} has {len(parts)} fields, header has {len(header)}")
        try:
            rows.append([float(p) if p.strip() else math.nan for p in parts])
        except ValueError:
            raise ValueError(f"{source}: data line {i} is not numeric: {line!r}") from None
    data = np.asarray(rows, dtype=np.float64).reshape(len(rows), len(header))
    return {name: data[:, j] for j, name in enumerate(header)}


@functools.cache
def _normalised_table(name: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The shipped 1 Hz table as (n_norm_pct, t_norm_pct, motoring_mask), read once."""
    text = resources.files("scr_env").joinpath("data", "cycles", _TABLES[name]).read_text(encoding="utf-8")
    cols = _read_csv(text, _TABLES[name])
    n_norm = cols["n_norm_pct"]
    t_norm = cols["T_norm_pct"]
    motoring = cols["motoring"] > 0.5 if "motoring" in cols else np.zeros(n_norm.size, dtype=bool)
    for arr in (n_norm, t_norm, motoring):
        arr.setflags(write=False)
    return n_norm, t_norm, motoring


def _denormalise_speed(n_norm_pct: np.ndarray, engine: EngineParams) -> np.ndarray:
    span = 0.45 * engine.n_lo_rpm + 0.45 * engine.n_pref_rpm + 0.1 * engine.n_hi_rpm - engine.idle_speed_rpm
    return n_norm_pct / 100.0 * span * 2.0327 + engine.idle_speed_rpm  # GTR No. 4, Annex 1 / PROVENANCE.md


def denormalise(
    n_norm_pct: ArrayLike, t_norm_pct: ArrayLike, motoring_mask: ArrayLike, engine: EngineParams | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """GTR No. 4 denormalisation of a normalised speed/torque schedule.

    ``n_ref = n_norm/100 (0.45 n_lo + 0.45 n_pref + 0.1 n_hi - n_idle) 2.0327 + n_idle`` and
    ``M_ref = T_norm/100 M_max(n_ref)``; at motoring points ``M_ref = M_drag(n_ref)`` (negative).

    Parameters
    ----------
    n_norm_pct : array_like
        Normalised speed [%].
    t_norm_pct : array_like
        Normalised torque [%]; ignored (may be NaN) where ``motoring_mask`` is true.
    motoring_mask : array_like of bool
        True where the engine is motored.
    engine : EngineParams, optional
        Engine (reference speeds and torque curves); the default engine if None.

    Returns
    -------
    speed_rpm, torque_nm : numpy.ndarray
        Reference speed [rpm] and torque [Nm].
    """
    engine = EngineParams() if engine is None else engine
    n_norm = np.asarray(n_norm_pct, dtype=np.float64)
    t_norm = np.asarray(t_norm_pct, dtype=np.float64)
    mask = np.asarray(motoring_mask, dtype=bool)
    if not (n_norm.shape == t_norm.shape == mask.shape):
        raise ValueError("n_norm_pct, t_norm_pct and motoring_mask must have the same shape")
    if not np.all(np.isfinite(n_norm)):
        raise ValueError("n_norm_pct must be finite")
    if not np.all(np.isfinite(t_norm[~mask])):
        raise ValueError("t_norm_pct must be finite where motoring_mask is false")
    speed = _denormalise_speed(n_norm, engine)
    torque = np.where(mask, motoring_torque_nm(engine, speed),
                      np.where(mask, 0.0, t_norm) / 100.0 * full_load_torque_nm(engine, speed))
    return speed, torque


def _trace_from_operating_points(
    name: str, dt: float, speed_1hz: np.ndarray, torque_1hz: np.ndarray, engine: EngineParams, cold_start: bool
) -> ExhaustTrace:
    """1 Hz operating points (row k at t = k s) -> sampled engine-out model -> DOC/DPF -> SCR-inlet trace."""
    _check_samples(speed_1hz.size / dt, f"the {name} cycle ({speed_1hz.size} s)", dt)
    n_steps = math.floor(speed_1hz.size / dt + 1e-9)
    time = np.arange(n_steps, dtype=np.float64) * dt
    grid = np.arange(speed_1hz.size, dtype=np.float64)
    speed = np.interp(time, grid, speed_1hz)
    torque = np.interp(time, grid, torque_1hz)
    eo = engine_out(engine, speed, torque)
    if cold_start:
        initial = (engine.ambient_temperature_k, engine.ambient_temperature_k)
    else:
        ss_doc, ss_dpf = steady_state_solid_temperatures(
            engine, float(eo["engine_out_temperature_k"][0]), float(eo["exhaust_mass_flow_kg_s"][0]))
        initial = (max(engine.hot_start_temperature_k, ss_doc), max(engine.hot_start_temperature_k, ss_dpf))
    doc_out, scr_in = aftertreatment_temperatures(
        engine, time, eo["engine_out_temperature_k"], eo["exhaust_mass_flow_kg_s"], initial)
    no2 = doc_no2_fraction(engine, doc_out, eo["exhaust_flow_mol_s"], eo["no2_fraction_engine_out"])
    return ExhaustTrace(
        name=name, dt=dt, time_s=time, engine_speed_rpm=speed, engine_torque_nm=torque,
        engine_power_kw=eo["power_kw"], exhaust_mass_flow_kg_s=eo["exhaust_mass_flow_kg_s"],
        exhaust_flow_mol_s=eo["exhaust_flow_mol_s"], scr_inlet_temperature_k=scr_in, nox_ppm=eo["nox_ppm"],
        no2_fraction=no2,
    )


def _frozen(trace: ExhaustTrace) -> ExhaustTrace:
    for name in _ARRAY_FIELDS:
        getattr(trace, name).setflags(write=False)
    return trace


@functools.lru_cache(maxsize=32)
def _regulatory_trace(name: str, dt: float, engine: EngineParams, cold_start: bool) -> ExhaustTrace:
    n_norm, t_norm, motoring = _normalised_table(name)
    speed, torque = denormalise(n_norm, t_norm, motoring, engine)
    return _frozen(_trace_from_operating_points(name, dt, speed, torque, engine, cold_start))


# ------------------------------------------------------------------------------------------------------ random cycles
# Segment kinds of the generator and their transition weights (rows: from, columns: to) [chosen: a mix that resembles
# the WHTC's urban / rural / motorway parts, with motoring about 20 % and idle about 15 % of the time like the WHTC].
#: the generators of :func:`random_cycle`
RANDOM_CYCLE_KINDS = ("transient", "ramped_modes")
#: cycle names of :func:`load_cycle` that draw a seeded random cycle, and their generator (``kind``)
RANDOM_CYCLES: dict[str, str] = {"random": "transient", "random_modes": "ramped_modes"}
_KINDS = ("idle", "launch", "cruise", "urban", "stationary", "motoring")
_TRANSITIONS = np.array([
    # idle launch cruise urban stat  motor
    [0.00, 0.60, 0.00, 0.40, 0.00, 0.00],  # from idle
    [0.00, 0.00, 0.45, 0.10, 0.10, 0.35],  # from launch
    [0.00, 0.15, 0.15, 0.10, 0.05, 0.55],  # from cruise
    [0.40, 0.15, 0.15, 0.00, 0.00, 0.30],  # from urban
    [0.00, 0.15, 0.25, 0.00, 0.05, 0.55],  # from stationary
    [0.45, 0.20, 0.20, 0.15, 0.00, 0.00],  # from motoring
])
_SPEED_RATE_PCT_S = 8.0  # %/s, max normalised speed change [chosen: WHTC 99th percentile ~15 %/s, median 1 %/s]
_TORQUE_RATE_PCT_S = 50.0  # %/s, max normalised torque change [chosen: WHTC 99th percentile ~52 %/s]


def _random_targets(n_seconds: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Per-second setpoints of normalised speed [%] and signed torque [%] (negative: fraction of the drag curve)."""
    n_set = np.zeros(n_seconds)
    tau_set = np.zeros(n_seconds)
    k = 0
    kind = 0  # engine start: idle
    n_now = 0.0
    while k < n_seconds:
        name = _KINDS[kind]
        if name == "idle":
            length = int(rng.integers(5, 91))
            n_seg = np.zeros(length)
            tau_seg = np.zeros(length)
        elif name == "launch":
            target = rng.uniform(max(n_now + 10.0, 25.0), 100.0) if n_now < 90.0 else rng.uniform(90.0, 100.0)
            length = math.ceil(abs(target - n_now) / _SPEED_RATE_PCT_S) + int(rng.integers(2, 8))
            n_seg = np.full(length, target)
            tau_seg = np.full(length, rng.uniform(60.0, 100.0))
        elif name == "cruise":
            length = int(rng.integers(20, 201))
            n_seg = np.full(length, rng.uniform(25.0, 100.0))
            # AR(1) load fluctuation around a mean (gradients, traffic), 1 s steps, coefficient 0.9 [chosen]
            mean, sd = rng.uniform(5.0, 60.0), rng.uniform(2.0, 12.0)
            noise = np.empty(length)
            x = 0.0
            for i in range(length):
                x = 0.9 * x + math.sqrt(1.0 - 0.81) * sd * rng.standard_normal()
                noise[i] = x
            tau_seg = np.clip(mean + noise, 0.0, 100.0)
        elif name == "urban":
            parts_n, parts_t = [], []
            total = int(rng.integers(30, 121))
            while sum(len(p) for p in parts_n) < total:
                hold = int(rng.integers(3, 11))
                parts_n.append(np.full(hold, rng.uniform(0.0, 50.0)))
                # 40 % of the short holds are overrun (motoring), the rest light to heavy load [chosen]
                parts_t.append(np.full(hold, -100.0 if rng.random() < 0.4 else rng.uniform(0.0, 70.0)))
            n_seg = np.concatenate(parts_n)
            tau_seg = np.concatenate(parts_t)
        elif name == "stationary":
            length = int(rng.integers(60, 241))
            n_seg = np.full(length, rng.uniform(25.0, 80.0))
            tau_seg = np.full(length, rng.uniform(25.0, 100.0))
        else:  # motoring: overrun deceleration on the drag curve
            target = rng.uniform(0.0, max(n_now - 10.0, 0.0))
            length = math.ceil(abs(n_now - target) / rng.uniform(1.5, 4.0)) + int(rng.integers(3, 16))
            n_seg = np.full(length, target)
            tau_seg = np.full(length, -100.0)
        m = min(n_seg.size, n_seconds - k)
        n_set[k:k + m] = n_seg[:m]
        tau_set[k:k + m] = tau_seg[:m]
        k += m
        n_now = float(n_seg[-1])
        kind = int(rng.choice(len(_KINDS), p=_TRANSITIONS[kind]))
    return n_set, tau_set


# Ramped-mode cycles (``random_cycle(kind="ramped_modes")``): WHSC-like loaded steady modes joined by linear ramps,
# so the catalyst stays hot for long stretches with heat-ups and cool-downs between load levels. The ranges span the
# WHSC's own modes (GTR No. 4 Annex 1: speed 25-75 %, torque 25-100 %, modes of 30-230 s after 20 s ramps) without
# being the WHSC [chosen].
_MODE_SPEED_PCT = (25.0, 80.0)  # % normalised speed of a loaded mode
_MODE_TORQUE_PCT = (25.0, 100.0)  # % normalised torque of a loaded mode
_MODE_LENGTH_S = (30, 300)  # s, hold of a mode (integer bounds, the upper one exclusive)
_MODE_RAMP_S = 20  # s, linear ramp into each mode, as in the WHSC
_MODE_IDLE_PROBABILITY = 0.1  # a mode is an idle of the same length instead (cool-down, then a heat-up)
_MODE_START_IDLE_S = (30, 211)  # s, idle at the start, as the WHSC's first 210 s (integer bounds)


def _ramped_mode_targets(n_seconds: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Per-second normalised speed [%] and torque [%] of a random ramped-mode cycle (no motoring)."""
    n_parts = [np.zeros(int(rng.integers(*_MODE_START_IDLE_S)))]
    t_parts = [np.zeros(n_parts[0].size)]
    n_now = t_now = 0.0
    while sum(p.size for p in n_parts) < n_seconds:
        hold = int(rng.integers(*_MODE_LENGTH_S))
        if rng.random() < _MODE_IDLE_PROBABILITY:
            n_mode = t_mode = 0.0
        else:
            n_mode, t_mode = rng.uniform(*_MODE_SPEED_PCT), rng.uniform(*_MODE_TORQUE_PCT)
        ramp = np.arange(1, _MODE_RAMP_S + 1) / _MODE_RAMP_S
        n_parts += [n_now + (n_mode - n_now) * ramp, np.full(hold, n_mode)]
        t_parts += [t_now + (t_mode - t_now) * ramp, np.full(hold, t_mode)]
        n_now, t_now = n_mode, t_mode
    return np.concatenate(n_parts)[:n_seconds], np.concatenate(t_parts)[:n_seconds]


def _rate_limit(setpoint: np.ndarray, rate_per_step: float) -> np.ndarray:
    out = setpoint.tolist()
    y = out[0]
    for i, s in enumerate(out):
        y += min(max(s - y, -rate_per_step), rate_per_step)
        out[i] = y
    return np.asarray(out)


@functools.lru_cache(maxsize=32)
def _random_trace(duration_s: float, seed: int, dt: float, engine: EngineParams, cold_start: bool,
                  kind: str = "transient") -> ExhaustTrace:
    _check_samples(duration_s / dt, f"a random cycle of {duration_s:g} s", dt)
    rng = np.random.default_rng(seed)
    n_seconds = math.ceil(duration_s)
    targets = _random_targets if kind == "transient" else _ramped_mode_targets
    n_set, tau_set = targets(n_seconds + 1, rng)
    n_norm = np.clip(_rate_limit(n_set, _SPEED_RATE_PCT_S), 0.0, 100.0)
    tau = np.clip(_rate_limit(tau_set, _TORQUE_RATE_PCT_S), -100.0, 100.0)
    speed = _denormalise_speed(n_norm, engine)
    torque = np.where(tau >= 0.0, tau / 100.0 * full_load_torque_nm(engine, speed),
                      -tau / 100.0 * motoring_torque_nm(engine, speed))
    name = f"random-{seed}" if kind == "transient" else f"random-modes-{seed}"
    trace = _trace_from_operating_points(name, dt, speed, torque, engine, cold_start)
    # The 1 Hz profile has n_seconds + 1 points; keep floor(duration / dt) samples.
    n_keep = math.floor(duration_s / dt + 1e-9)
    return _frozen(replace(trace, **{f: getattr(trace, f)[:n_keep] for f in _ARRAY_FIELDS}))


def random_cycle(
    duration_s: float,
    seed: int,
    dt: float = 0.5,
    engine: EngineParams | None = None,
    cold_start: bool = False,
    kind: str = "transient",
) -> ExhaustTrace:
    """A seeded random drive cycle through the engine-out model (for training and held-out testing).

    ``kind="transient"`` (the default, WHTC-like): a Markov chain of segments in normalised speed and torque (idle;
    launch at 60-100 % torque; cruise with AR(1) load fluctuation; urban stop-and-go with short holds and overrun;
    WHSC-like stationary modes; motoring decelerations on the drag curve).

    ``kind="ramped_modes"`` (WHSC-like): 30-210 s of idle, then loaded steady modes (25-80 % speed, 25-100 % torque,
    held 30-299 s) joined by 20 s linear ramps, one mode in ten an idle instead; no motoring, so the catalyst stays
    hot for long stretches with heat-ups and cool-downs between load levels. A calibration family for controllers
    meant for the WHSC that is not the WHSC.

    Either is rate limited to 8 %/s speed and 50 %/s torque, denormalised as in GTR No. 4 and put through the same
    engine-out and DOC/DPF models as the WHTC.

    Parameters
    ----------
    duration_s : float
        Cycle length [s], > 0 and >= dt; ``floor(duration_s / dt)`` samples.
    seed : int
        Seed of ``numpy.random.default_rng``; the same seed gives an identical trace.
    dt : float
        Sample interval [s], in (0, 10].
    engine : EngineParams, optional
        Engine; the default engine if None.
    cold_start : bool
        Start the aftertreatment at ambient temperature (else hot start, see module docstring).
    kind : {"transient", "ramped_modes"}
        The generator (above). The trace is named ``random-<seed>`` or ``random-modes-<seed>``.

    Returns
    -------
    ExhaustTrace
    """
    if kind not in RANDOM_CYCLE_KINDS:
        raise ValueError(f"kind must be one of {RANDOM_CYCLE_KINDS}, got {kind!r}")
    dt = _check_dt(dt)
    try:
        duration = float(duration_s)
    except (TypeError, ValueError):
        raise ValueError(f"duration_s must be a number of seconds, got {duration_s!r}") from None
    if not (math.isfinite(duration) and dt <= duration <= 1.0e6):
        raise ValueError(f"duration_s must be finite and in [dt, 1e6] s, got {duration_s!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    engine = EngineParams() if engine is None else engine
    return _random_trace(duration, int(seed), dt, engine, _check_flag("cold_start", cold_start), kind).copy()


# ------------------------------------------------------------------------------------------------------------ CSV
_REQUIRED = ("time_s", "scr_inlet_temperature_k", "nox_ppm")


def _from_csv_uncached(path: Path, dt: float) -> ExhaustTrace:
    try:
        text = path.read_text(encoding="utf-8-sig")  # -sig: a byte-order mark (spreadsheet exports) is dropped
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"path: cannot read {str(path)!r} as UTF-8 text: {exc}") from None
    cols = _read_csv(text, str(path))
    missing = [c for c in _REQUIRED if c not in cols]
    if "exhaust_flow_mol_s" not in cols and "exhaust_mass_flow_kg_s" not in cols:
        missing.append("exhaust_flow_mol_s (or exhaust_mass_flow_kg_s)")
    if missing:
        raise ValueError(f"{path}: missing column(s) {', '.join(missing)}; found {', '.join(cols)}")
    used = [c for c in ("time_s", "exhaust_flow_mol_s", "exhaust_mass_flow_kg_s", "scr_inlet_temperature_k",
                        "nox_ppm", "no2_fraction", "engine_power_kw", "engine_speed_rpm", "engine_torque_nm")
            if c in cols]
    for c in used:
        bad = np.nonzero(~np.isfinite(cols[c]))[0]
        if bad.size:
            raise ValueError(f"{path}: column {c} has NaN/empty or infinite values (first at data row {bad[0] + 1})")
    time = cols["time_s"]
    if time.size < 2:
        raise ValueError(f"{path}: need at least two data rows")
    if np.any(np.diff(time) <= 0.0):
        raise ValueError(f"{path}: column time_s must be strictly increasing")
    checks = [("exhaust_flow_mol_s", 0.0, math.inf), ("exhaust_mass_flow_kg_s", 0.0, math.inf),
              ("nox_ppm", 0.0, 1.0e6), ("no2_fraction", 0.0, 1.0), ("engine_speed_rpm", 0.0, math.inf)]
    for c, lo, hi in checks:
        if c in cols and (np.any(cols[c] < lo) or np.any(cols[c] > hi)):
            raise ValueError(f"{path}: column {c} must lie in [{lo}, {hi}] (negative flows/concentrations are invalid)")
    if np.any(cols["scr_inlet_temperature_k"] <= 0.0):
        raise ValueError(f"{path}: column scr_inlet_temperature_k must be positive (kelvin)")
    temps = cols["scr_inlet_temperature_k"]
    if np.any(temps > MAX_TEMPERATURE_K):
        row = int(np.argmax(temps)) + 1
        raise ValueError(f"{path}: column scr_inlet_temperature_k reaches {temps.max():g} K (data row {row}), above "
                         f"{MAX_TEMPERATURE_K:g} K, hotter than any diesel exhaust: the column must be in kelvin "
                         f"(a value in degF, or a sensor fault?)")
    t_min = float(cols["scr_inlet_temperature_k"].min())
    if t_min < _MIN_PLAUSIBLE_TEMPERATURE_K:
        row = int(np.argmin(cols["scr_inlet_temperature_k"])) + 1
        raise ValueError(
            f"{path}: column scr_inlet_temperature_k goes down to {t_min:g} K ({t_min - 273.15:.1f} degC, data row "
            f"{row}), colder than any exhaust can be (the limit is {_MIN_PLAUSIBLE_TEMPERATURE_K:g} K); the column "
            f"must be in kelvin: if the data are in degC, convert them with T[K] = T[degC] + 273.15")
    t_max = float(cols["scr_inlet_temperature_k"].max())
    t_median = float(np.median(temps))
    tenth = max(temps.size // 10, 1)
    warm_up = float(np.mean(temps[-tenth:]) - np.mean(temps[:tenth])) >= _WARM_UP_RISE_K
    if t_max < 273.15:
        warnings.warn(
            f"{path}: column scr_inlet_temperature_k never reaches 273.15 K (max {t_max:g} K = {t_max - 273.15:.1f} "
            f"degC): are the temperatures in degC? They are read as kelvin (T[K] = T[degC] + 273.15); a sub-zero "
            f"cold-start segment would be right as it is", UserWarning, stacklevel=4)
    elif t_median < _DEGC_MEDIAN_K and not warm_up:
        warnings.warn(
            f"{path}: column scr_inlet_temperature_k has a median of {t_median:g} K ({t_median - 273.15:.1f} degC), "
            f"colder than boiling water, and the record is no warm-up: a running diesel's SCR inlet is hotter. Are "
            f"the temperatures in degC (a hot log in degC reads as {t_median:g} K)? They are read as kelvin; convert "
            f"with T[K] = T[degC] + 273.15", UserWarning, stacklevel=4)
    t_rel = time - time[0]
    _check_samples(t_rel[-1] / dt + 1.0, f"{path} (spanning {t_rel[-1]:g} s)", dt)
    n_steps = math.floor(t_rel[-1] / dt + 1e-9) + 1
    grid = np.arange(n_steps, dtype=np.float64) * dt

    def resample(c: str, default: float) -> np.ndarray:
        return np.interp(grid, t_rel, cols[c]) if c in cols else np.full(n_steps, default)

    if "exhaust_flow_mol_s" in cols:
        flow_mol = resample("exhaust_flow_mol_s", 0.0)
        mass = resample("exhaust_mass_flow_kg_s", 0.0) if "exhaust_mass_flow_kg_s" in cols else \
            flow_mol * EXHAUST_MOLAR_MASS_KG_MOL
    else:
        mass = resample("exhaust_mass_flow_kg_s", 0.0)
        flow_mol = mass / EXHAUST_MOLAR_MASS_KG_MOL
    return ExhaustTrace(
        name=path.stem, dt=dt, time_s=grid, engine_speed_rpm=resample("engine_speed_rpm", 0.0),
        engine_torque_nm=resample("engine_torque_nm", 0.0), engine_power_kw=resample("engine_power_kw", 0.0),
        exhaust_mass_flow_kg_s=mass, exhaust_flow_mol_s=flow_mol,
        scr_inlet_temperature_k=resample("scr_inlet_temperature_k", 0.0), nox_ppm=resample("nox_ppm", 0.0),
        no2_fraction=resample("no2_fraction", _DEFAULT_NO2_FRACTION),
    )


@functools.lru_cache(maxsize=16)
def _csv_trace(path: str, mtime_ns: int, size: int, dt: float) -> ExhaustTrace:
    return _frozen(_from_csv_uncached(Path(path), dt))


def from_csv(path: str | os.PathLike, dt: float = 0.5) -> ExhaustTrace:
    """Replay measured SCR-inlet data from a CSV file (format in the module docstring), resampled to ``dt``.

    Parameters
    ----------
    path : str or os.PathLike
        The CSV file.
    dt : float
        Sample interval [s], in (0, 10].

    Returns
    -------
    ExhaustTrace
        Named after the file stem; ``time_s`` starts at 0.

    Raises
    ------
    ValueError
        Unreadable file, missing or duplicated columns (named), NaN or infinite values, non-increasing time,
        negative flows or concentrations, NO2/NOx outside [0, 1], temperatures below 200 K (data in degC rather
        than kelvin) or above 1500 K, fewer than two rows, a bad ``dt``, or more than :data:`MAX_TRACE_SAMPLES`
        samples at that ``dt``.

    Warns
    -----
    UserWarning
        Temperatures that look like degC: the whole column below 273.15 K, or a median below 373.15 K in a record
        that is no warm-up (its last tenth less than 100 K warmer than its first). A sub-zero or short cold start in
        kelvin is possible, so the data are used as they are.
    """
    dt = _check_dt(dt)
    p = Path(os.fspath(path)).expanduser().resolve()
    try:
        st = p.stat()
    except OSError:
        raise ValueError(f"path: no such file {str(path)!r}") from None
    if not p.is_file():
        raise ValueError(f"path: {str(path)!r} is not a file")
    return _csv_trace(str(p), st.st_mtime_ns, st.st_size, dt).copy()


# ---------------------------------------------------------------------------------------------------------- entry
def load_cycle(
    cycle: str | os.PathLike = "whtc",
    dt: float = 0.5,
    engine: EngineParams | None = None,
    cold_start: bool = False,
    seed: int | None = None,
    duration_s: float = _RANDOM_DEFAULT_DURATION_S,
) -> ExhaustTrace:
    """Load a drive cycle as an SCR-inlet :class:`ExhaustTrace`.

    Parameters
    ----------
    cycle : str or os.PathLike
        ``"whtc"``, ``"whsc"``, ``"random"`` or ``"random_modes"`` (need ``seed``; :func:`random_cycle` with
        ``kind="transient"`` / ``"ramped_modes"``) or a path to a user CSV file (see :func:`from_csv`).
    dt : float
        Sample interval [s], in (0, 10]. WHTC at 0.5 s has 3600 samples, WHSC 3790.
    engine : EngineParams, optional
        Engine model; the default generic 12.8 L engine if None. Not used for CSV data.
    cold_start : bool
        Aftertreatment starts at ambient temperature (cold WHTC); otherwise a hot start (module docstring). Not used
        for CSV data (measured temperatures already contain the start condition).
    seed : int, optional
        Seed of the random cycle; required for ``"random"`` and ``"random_modes"``, ignored otherwise.
    duration_s : float
        Length of the random cycle [s] (default 1800 s, as the WHTC); ignored otherwise.

    Returns
    -------
    ExhaustTrace
        A fresh copy; the parsed tables and computed traces are cached, so repeated calls are cheap.

    Raises
    ------
    ValueError
        Unknown cycle name (the valid ones are listed), missing seed, bad ``dt``, ``cold_start`` not True or False,
        or invalid CSV content.
    """
    dt = _check_dt(dt)
    cold_start = _check_flag("cold_start", cold_start)
    if engine is not None and not isinstance(engine, EngineParams):
        raise ValueError(f"engine must be an EngineParams or None, got {type(engine).__name__}")
    if isinstance(cycle, str) and cycle.strip().lower() in available_cycles():
        key = cycle.strip().lower()
        engine = EngineParams() if engine is None else engine
        if key in RANDOM_CYCLES:
            if seed is None:
                raise ValueError(f"seed: the {key!r} cycle needs an integer seed")
            return random_cycle(duration_s, seed, dt=dt, engine=engine, cold_start=cold_start,
                                kind=RANDOM_CYCLES[key])
        return _regulatory_trace(key, dt, engine, cold_start).copy()
    if isinstance(cycle, (str, os.PathLike)):
        p = Path(os.fspath(cycle)).expanduser()
        if p.is_file():
            return from_csv(p, dt=dt)
        raise ValueError(f"cycle: {str(cycle)!r} is neither one of {', '.join(available_cycles())} nor an "
                         "existing CSV file")
    raise ValueError(f"cycle must be a name ({', '.join(available_cycles())}) or a path, got {type(cycle).__name__}")
