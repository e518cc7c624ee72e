"""Lab-reactor configuration of the catalyst model: the CLEERS protocol's isothermal monolith sample.

This is the API for catalyst studies and the one the simulator is validated with (PHYSICS.md section 6): an
isothermal monolith sample at a given gas hourly space velocity, fed a gas mixture. It runs the same compiled
chemistry as the environments (:func:`scr_env.physics.kernel.catalyst_chemistry`):

* :func:`steady_state`: a constant feed at steady state (the implicit-Euler weight 1/dt set to zero, which turns the
  step into the steady-state equations);
* :func:`run_protocol`: a measured inlet time series replayed through the sample (implicit Euler in time, the inlet
  held between samples), returning the outlet time series -- storage, breakthrough and oxidation dynamics, to
  compare with the transient records of ``cleers_cu_ssz13_isothermal_steps.csv``.

The space velocity is referred to standard conditions (0 C, 1 atm), as in the CLEERS protocol (PROVENANCE.md of
the catalyst data: 1000 reactor volumes per minute at 273.15 K), so the molar flow through the sample does not
change with its temperature.

Example
-------
>>> from scr_env.lab import steady_state
>>> r = steady_state("cu_zeolite", temperature_c=250.0, no_ppm=300.0, nh3_ppm=300.0, age_h=16.0)
>>> round(r["nox_conversion"], 2)  # doctest: +SKIP
0.9
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from scr_env.constants import ATMOSPHERIC_PRESSURE_PA, GAS_CONSTANT_J_MOL_K
from scr_env.jit import njit
from scr_env.params import KINETIC_SLICE, CatalystParams, catalyst_preset, check_age_h, pack
from scr_env.physics.backends import rate_constants_nb
from scr_env.physics.kernel import catalyst_chemistry, solve_coverage

LAB_CELLS = 10  # axial cells of the lab monolith: the basis of the calibration (experiments.calibrate_catalyst)
MIN_TEMPERATURE_C = 100.0  # C; below this the kinetics are extrapolated far outside the lab data [chosen]
MAX_TEMPERATURE_C = 700.0  # C; above this zeolite catalysts degrade and the data end at 600 C [chosen]
STANDARD_TEMPERATURE_K = 273.15  # K, reference of the space velocity (CLEERS protocol, PROVENANCE.md)
MAX_PPM = 1.0e4  # ppm, upper bound of every inlet concentration [chosen: 1 %, far above any SCR feed]
#: measured inlet concentrations down to this [ppm] are analyser offsets and are read as zero by run_protocol
NEGATIVE_OFFSET_PPM = 5.0
#: implicit-Euler steps per inlet sample interval at most this long [s] (run_protocol) [chosen: 1 s resolves the
#: breakthrough fronts of minutes; halving it changes the replayed outlets by under 0.5 ppm RMS]
MAX_SUBSTEP_S = 1.0
#: protocol columns read by run_protocol (inlet, ppm or %) and written (outlet, ppm)
INLET_COLUMNS = ("O2_in_percent", "NH3_in_ppm", "NO_in_ppm", "NO2_in_ppm")
OUTLET_COLUMNS = ("NH3_out_ppm", "NO_out_ppm", "NO2_out_ppm", "N2O_out_ppm")


def _check(name: str, value: float, lo: float, hi: float) -> float:
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be a number, got {value!r}")  # noqa: TRY004 (the module's one error type)
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or not lo <= v <= hi:
        raise ValueError(f"{name} must be a finite number in [{lo}, {hi}], got {value!r}")
    return v


def _cells(n_cells: Any) -> int:
    if isinstance(n_cells, (bool, np.bool_)) or not isinstance(n_cells, (int, float, np.integer, np.floating)) \
            or int(n_cells) != n_cells or not 1 <= n_cells <= 200:
        raise ValueError(f"n_cells must be an integer in [1, 200], got {n_cells!r}")
    return int(n_cells)


def _sample(catalyst: str | CatalystParams, age_h: float | None, ghsv_per_h: float, n_cells: int
            ) -> tuple[CatalystParams, np.ndarray, float, float]:
    """(catalyst at its age, packed parameters, storage capacity [mol/m3], molar flow per m3 catalyst [mol/s])."""
    params = catalyst_preset(catalyst)
    if age_h is not None:
        params = params.replace(age_h=check_age_h(age_h))
    ghsv = _check("ghsv_per_h", ghsv_per_h, 1.0, 1.0e7)
    flow = ghsv / 3600.0 * ATMOSPHERIC_PRESSURE_PA / (GAS_CONSTANT_J_MOL_K * STANDARD_TEMPERATURE_K)
    return params, pack(params), params.storage_capacity_effective_mol_m3, flow


def steady_state(catalyst: str | CatalystParams, temperature_c: float, ghsv_per_h: float = 60000.0,
                 no_ppm: float = 0.0, no2_ppm: float = 0.0, nh3_ppm: float = 0.0, o2_percent: float = 10.0,
                 n_cells: int = LAB_CELLS, age_h: float | None = None) -> dict[str, float]:
    """Steady state of an isothermal catalyst sample fed a constant gas mixture.

    Parameters
    ----------
    catalyst : preset name (e.g. ``"cu_zeolite"``) or :class:`~scr_env.params.CatalystParams`. Its kinetics and
        storage capacity per catalyst volume are used; the brick size is irrelevant at a given space velocity.
    temperature_c : reactor temperature [C], 100 to 700.
    ghsv_per_h : gas hourly space velocity [1/h] referred to 0 C and 1 atm (CLEERS: 60000).
    no_ppm, no2_ppm, nh3_ppm : inlet mole fractions [ppm], 0 to 10000.
    o2_percent : inlet O2 [mol %], 0 to 21.
    n_cells : axial cells of the sample model (default 10, the calibration basis).
    age_h : hours of hydrothermal ageing, 0 to 16 (:data:`scr_env.params.MAX_AGE_H`); None keeps the catalyst's
        own ``age_h`` (0 for the presets).

    Returns
    -------
    dict with ``nox_conversion`` [-] (NaN when no NOx is fed), ``nox_out_ppm``, ``no_out_ppm``, ``no2_out_ppm``,
    ``nh3_out_ppm``, ``n2o_out_ppm`` [ppm], ``nh3_conversion`` [-] (NaN without NH3),
    ``nh3_stored_mol_per_m3``: the NH3 uptake [mol per m3 catalyst] in adsorption equilibrium with the feed gas at
    this temperature, the quantity an adsorption isotherm reports (with NH3 oxidation or SCR running, the gas
    inside the sample is leaner than the feed, so the stored amount is lower along the sample: that is
    ``nh3_stored_reactor_mean_mol_per_m3``, the mean over the sample at the reactive steady state),
    ``mean_coverage`` [-] of the reactive steady state and ``nitrate_coverage`` [-], the mean quasi-steady
    ammonium-nitrate coverage.
    """
    t_c = _check("temperature_c", temperature_c, MIN_TEMPERATURE_C, MAX_TEMPERATURE_C)
    no = _check("no_ppm", no_ppm, 0.0, MAX_PPM)
    no2 = _check("no2_ppm", no2_ppm, 0.0, MAX_PPM)
    nh3 = _check("nh3_ppm", nh3_ppm, 0.0, MAX_PPM)
    o2 = _check("o2_percent", o2_percent, 0.0, 21.0)
    n_cells = _cells(n_cells)
    _params, p, capacity, flow = _sample(catalyst, age_h, ghsv_per_h, n_cells)

    t_k = t_c + 273.15
    q = flow / (capacity / n_cells)
    theta = np.zeros(n_cells)
    temps = np.full(n_cells, t_k)
    result = catalyst_chemistry(theta, temps, q, nh3 * 1e-6, no * 1e-6, no2 * 1e-6, o2 / 100.0, 0.0, p)
    no_out, no2_out, nh3_out, n2o_out = (result[i] * 1e6 for i in range(4))
    nitrate = _nitrate_profile(theta, t_k, q, nh3, no, no2, o2, p)
    # adsorption equilibrium with the feed: the same cell with every consuming reaction switched off
    k = rate_constants_nb(t_k, max(o2, 1e-9) / 100.0, *p[KINETIC_SLICE])
    k_eq = (k[0], k[1], k[2]) + (0.0,) * (len(k) - 3)
    theta_eq, _, _ = solve_coverage(0.0, 0.0, q, nh3 * 1e-6, 0.0, 0.0, k_eq)
    nox_in = no + no2
    nox_out = no_out + no2_out
    return {
        "nox_conversion": (1.0 - nox_out / nox_in) if nox_in > 0 else float("nan"),
        "nox_out_ppm": nox_out,
        "no_out_ppm": no_out,
        "no2_out_ppm": no2_out,
        "nh3_out_ppm": nh3_out,
        "n2o_out_ppm": n2o_out,
        "nh3_conversion": (1.0 - nh3_out / nh3) if nh3 > 0 else float("nan"),
        "nh3_stored_mol_per_m3": float(theta_eq * capacity),
        "nh3_stored_reactor_mean_mol_per_m3": float(theta.mean() * capacity),
        "mean_coverage": float(theta.mean()),
        "nitrate_coverage": nitrate,
    }


def _nitrate_profile(theta: np.ndarray, t_k: float, q: float, nh3: float, no: float, no2: float, o2: float,
                     p: np.ndarray) -> float:
    """Mean quasi-steady nitrate coverage along the sample at the steady coverages ``theta``."""
    from scr_env.physics.backends import cell_balance_nb

    k = rate_constants_nb(t_k, o2 / 100.0, *p[KINETIC_SLICE])
    y = (nh3 * 1e-6, no * 1e-6, no2 * 1e-6)
    total = 0.0
    for th in theta:
        r = cell_balance_nb(float(th), q, y[0], y[1], y[2], *k)
        total += r[7]
        y = (r[2], r[3], r[4])
    return float(total / theta.size)


def _column(inlet: Any, name: str, n: int | None, default: float | None = None) -> np.ndarray:
    try:
        raw = inlet[name]
    except (KeyError, IndexError, ValueError, TypeError):
        if default is None:
            raise ValueError(f"inlet has no column {name!r} (needs time_min or time_s, and "
                             f"{', '.join(INLET_COLUMNS)}; NO2_in_ppm may be left out)") from None
        return np.full(n, default)
    try:
        arr = np.asarray(raw, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"inlet column {name!r} must hold numbers") from None
    if n is not None and arr.size != n:
        raise ValueError(f"inlet column {name!r} has {arr.size} values, the time column {n}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"inlet column {name!r} holds non-finite values")
    return arr


def run_protocol(inlet: Mapping[str, Any] | Any, temperature_c: float | np.ndarray,
                 catalyst: str | CatalystParams = "cu_zeolite", age_h: float | None = None,
                 ghsv_per_h: float = 60000.0, n_cells: int = LAB_CELLS,
                 initial_coverage: float = 0.0) -> dict[str, np.ndarray]:
    """Replay a measured inlet time series through the isothermal lab sample and return the outlet time series.

    Parameters
    ----------
    inlet : columns by name (a dict of arrays, a pandas DataFrame, a numpy structured array): the time, as
        ``time_min`` [min] or ``time_s`` [s], strictly increasing, and the inlet ``O2_in_percent`` [%],
        ``NH3_in_ppm``, ``NO_in_ppm`` and optionally ``NO2_in_ppm`` [ppm] -- the columns of
        ``cleers_cu_ssz13_isothermal_steps.csv``. Other columns (H2O, the outlets) are ignored. Concentrations down
        to -5 ppm (analyser offsets) are read as zero. Between two samples the inlet of the first is held.
    temperature_c : reactor temperature [C], one number (isothermal) or one per sample, 100 to 700.
    catalyst, age_h, ghsv_per_h, n_cells : as :func:`steady_state`.
    initial_coverage : NH3 coverage [-] of every cell at the first sample (0: a clean sample, as after the
        protocol's pretreatment).

    Returns
    -------
    dict of arrays, one value per sample: ``time_min``, the outlets ``NH3_out_ppm``, ``NO_out_ppm``, ``NO2_out_ppm``,
    ``N2O_out_ppm`` [ppm], ``mean_coverage`` [-] and ``nh3_stored_mol_per_m3`` [mol per m3 catalyst]. The first
    sample is the outlet of the initial state fed the first inlet (at steady gas phase).
    """
    if isinstance(inlet, (str, bytes)) or inlet is None:
        raise ValueError("inlet must be columns by name (dict of arrays, DataFrame, structured array), got "
                         f"{type(inlet).__name__}")
    has_min = _has(inlet, "time_min")
    if not has_min and not _has(inlet, "time_s"):
        raise ValueError("inlet needs a time column: time_min [min] or time_s [s]")
    t_s = _column(inlet, "time_min", None) * 60.0 if has_min else _column(inlet, "time_s", None)
    n = t_s.size
    if n < 2:
        raise ValueError(f"inlet needs at least 2 samples, got {n}")
    dt_s = np.diff(t_s)
    if not np.all(dt_s > 0.0):
        raise ValueError("inlet time must be strictly increasing")
    if t_s[-1] - t_s[0] > 7 * 86400.0:
        raise ValueError(f"inlet spans {(t_s[-1] - t_s[0]) / 3600:.0f} h; run_protocol replays at most a week")
    cols = {}
    for name, hi in (("O2_in_percent", 21.0), ("NH3_in_ppm", MAX_PPM), ("NO_in_ppm", MAX_PPM),
                     ("NO2_in_ppm", MAX_PPM)):
        arr = _column(inlet, name, n, 0.0 if name == "NO2_in_ppm" else None)
        low = -NEGATIVE_OFFSET_PPM if name.endswith("_ppm") else -0.05
        if np.any(arr < low) or np.any(arr > hi):
            bad = arr[(arr < low) | (arr > hi)][0]
            raise ValueError(f"inlet column {name!r} must be within [0, {hi:g}] (analyser offsets down to {low:g} "
                             f"read as zero), got {bad!r}")
        cols[name] = np.maximum(arr, 0.0)
    temps = np.asarray(temperature_c, dtype=np.float64).reshape(-1)
    if temps.size == 1:
        temps = np.full(n, _check("temperature_c", float(temps[0]), MIN_TEMPERATURE_C, MAX_TEMPERATURE_C))
    elif temps.size != n:
        raise ValueError(f"temperature_c must be one number or one per sample ({n}), got {temps.size} values")
    else:
        for v in temps:
            _check("temperature_c", v, MIN_TEMPERATURE_C, MAX_TEMPERATURE_C)
    coverage = _check("initial_coverage", initial_coverage, 0.0, 1.0)
    n_cells = _cells(n_cells)
    _params, p, capacity, flow = _sample(catalyst, age_h, ghsv_per_h, n_cells)
    q = flow / (capacity / n_cells)

    nh3 = cols["NH3_in_ppm"] * 1e-6
    no = cols["NO_in_ppm"] * 1e-6
    no2 = cols["NO2_in_ppm"] * 1e-6
    o2 = cols["O2_in_percent"] / 100.0
    theta = np.full(n_cells, coverage)
    temps_k = temps + 273.15
    out = np.empty((n, 4))
    stored = np.empty(n)
    first = theta.copy()  # outlet of the initial state fed the first inlet (steady gas phase, no time passes)
    y = _outlet_at(first, temps_k[0], q, nh3[0], no[0], no2[0], o2[0], p)
    out[0] = y
    stored[0] = theta.mean()
    _replay_loop(theta, temps_k, q, nh3, no, no2, o2, dt_s, p, out, stored)
    return {"time_min": t_s / 60.0,
            "NH3_out_ppm": out[:, 0] * 1e6, "NO_out_ppm": out[:, 1] * 1e6, "NO2_out_ppm": out[:, 2] * 1e6,
            "N2O_out_ppm": out[:, 3] * 1e6, "mean_coverage": stored.copy(),
            "nh3_stored_mol_per_m3": stored * capacity}


def _has(inlet: Any, name: str) -> bool:
    try:
        inlet[name]
    except (KeyError, IndexError, ValueError, TypeError):
        return False
    return True


def _outlet_at(theta: np.ndarray, t_k: float, q: float, nh3: float, no: float, no2: float, o2: float,
               p: np.ndarray) -> tuple[float, float, float, float]:
    """(NH3, NO, NO2, N2O) outlet mole fractions of the sample at fixed coverages."""
    from scr_env.physics.backends import cell_balance_nb

    k = rate_constants_nb(t_k, o2, *p[KINETIC_SLICE])
    y = (nh3, no, no2)
    n2o = 0.0
    for th in theta:
        r = cell_balance_nb(float(th), q, y[0], y[1], y[2], *k)
        n2o += r[5] / q
        y = (r[2], r[3], r[4])
    return y[0], y[1], y[2], n2o


@njit
def _replay_loop(theta, temps_k, q, nh3, no, no2, o2, dt_s, p, out, stored):  # pragma: no cover - compiled
    """Implicit Euler through the samples: the interval k-1 -> k holds the inlet of sample k-1; out[k] is the
    outlet at sample k (y_nh3, y_no, y_no2, y_n2o), stored[k] the mean coverage."""
    n = theta.shape[0]
    t = np.empty(n)
    for k in range(1, nh3.shape[0]):
        h = dt_s[k - 1]
        m = max(math.ceil(h / MAX_SUBSTEP_S - 1e-9), 1)
        sub = h / m
        for j in range(n):
            t[j] = temps_k[k - 1]
        y_no, y_no2, y_nh3, y_n2o = 0.0, 0.0, 0.0, 0.0
        for _ in range(m):
            y_no, y_no2, y_nh3, y_n2o, _n2 = catalyst_chemistry(theta, t, q, nh3[k - 1], no[k - 1], no2[k - 1],
                                                                 o2[k - 1], 1.0 / sub, p)
        out[k, 0] = y_nh3
        out[k, 1] = y_no
        out[k, 2] = y_no2
        out[k, 3] = y_n2o
        s = 0.0
        for j in range(n):
            s += theta[j]
        stored[k] = s / n
