"""Lab-reactor configuration of the catalyst model: isothermal steady states as in the CLEERS protocol.

This is the API for catalyst studies and the one the simulator is validated with (PHYSICS.md section 6): an
isothermal monolith sample at a given gas hourly space velocity, fed a constant gas mixture, at steady state. It
runs the same compiled chemistry as the environments (:func:`scr_env.physics.kernel.catalyst_chemistry`, with the
implicit-Euler weight 1/dt set to zero, which turns the step into the steady-state equations).

Example
-------
>>> from scr_env.lab import steady_state
>>> r = steady_state("cu_zeolite", temperature_c=250.0, no_ppm=300.0, nh3_ppm=300.0)
>>> round(r["nox_conversion"], 2)  # doctest: +SKIP
0.95
"""
from __future__ import annotations

import math

import numpy as np

from scr_env.constants import ATMOSPHERIC_PRESSURE_PA, GAS_CONSTANT_J_MOL_K
from scr_env.params import CatalystParams, catalyst_preset, pack
from scr_env.physics.backends import rate_constants_nb
from scr_env.physics.kernel import catalyst_chemistry, solve_coverage

LAB_CELLS = 10  # axial cells of the lab monolith: the basis of the lumped calibration (lumped_cu_ssz13_params.txt)
MIN_TEMPERATURE_C = 100.0  # C; below this the kinetics are extrapolated far outside the lab data [chosen]
MAX_TEMPERATURE_C = 700.0  # C; above this zeolite catalysts degrade and the data end at 600 C [chosen]


def _check(name: str, value: float, lo: float, hi: float) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(v) or not lo <= v <= hi:
        raise ValueError(f"{name} must be a finite number in [{lo}, {hi}], got {value!r}")
    return v


def steady_state(catalyst: str | CatalystParams, temperature_c: float, ghsv_per_h: float = 60000.0,
                 no_ppm: float = 0.0, no2_ppm: float = 0.0, nh3_ppm: float = 0.0, o2_percent: float = 10.0,
                 n_cells: int = LAB_CELLS) -> dict[str, float]:
    """Steady state of an isothermal catalyst sample fed a constant gas mixture.

    Parameters
    ----------
    catalyst : preset name (e.g. ``"cu_zeolite"``) or :class:`~scr_env.params.CatalystParams`. Its kinetics and
        storage capacity per catalyst volume are used; the brick size is irrelevant at a given space velocity.
    temperature_c : reactor temperature [C], 100 to 700.
    ghsv_per_h : gas hourly space velocity at reactor conditions [1/h] (CLEERS: 60000).
    no_ppm, no2_ppm, nh3_ppm : inlet mole fractions [ppm], 0 to 10000.
    o2_percent : inlet O2 [mol %], 0 to 21.
    n_cells : axial cells of the sample model (default 10, the calibration basis).

    Returns
    -------
    dict with ``nox_conversion`` [-] (NaN when no NOx is fed), ``nox_out_ppm``, ``no_out_ppm``, ``no2_out_ppm``,
    ``nh3_out_ppm``, ``n2o_out_ppm`` [ppm], ``nh3_conversion`` [-] (NaN without NH3),
    ``nh3_stored_mol_per_m3``: the NH3 uptake [mol per m3 catalyst] in adsorption equilibrium with the feed gas at
    this temperature, the quantity an adsorption isotherm reports (with NH3 oxidation or SCR running, the gas
    inside the sample is leaner than the feed, so the stored amount is lower along the sample: that is
    ``nh3_stored_reactor_mean_mol_per_m3``, the mean over the sample at the reactive steady state), and
    ``mean_coverage`` [-] of the reactive steady state.
    """
    params = catalyst_preset(catalyst)
    t_c = _check("temperature_c", temperature_c, MIN_TEMPERATURE_C, MAX_TEMPERATURE_C)
    ghsv = _check("ghsv_per_h", ghsv_per_h, 1.0, 1.0e7)
    no = _check("no_ppm", no_ppm, 0.0, 1.0e4)
    no2 = _check("no2_ppm", no2_ppm, 0.0, 1.0e4)
    nh3 = _check("nh3_ppm", nh3_ppm, 0.0, 1.0e4)
    o2 = _check("o2_percent", o2_percent, 0.0, 21.0)
    if int(n_cells) != n_cells or not 1 <= n_cells <= 200:
        raise ValueError(f"n_cells must be an integer in [1, 200], got {n_cells!r}")
    n_cells = int(n_cells)

    t_k = t_c + 273.15
    p = pack(params)
    capacity = params.storage_capacity_mol_m3 * params.storage_retention  # mol/m3 catalyst
    # Per m3 of catalyst: molar flow F = GHSV/3600 * P / (R T) [mol/s], sites per cell capacity / n_cells [mol].
    flow = ghsv / 3600.0 * ATMOSPHERIC_PRESSURE_PA / (GAS_CONSTANT_J_MOL_K * t_k)
    q = flow / (capacity / n_cells)
    theta = np.zeros(n_cells)
    temps = np.full(n_cells, t_k)
    result = catalyst_chemistry(theta, temps, q, nh3 * 1e-6, no * 1e-6, no2 * 1e-6, o2 / 100.0, 0.0, p)
    no_out, no2_out, nh3_out, n2o_out = (result[i] * 1e6 for i in range(4))
    # adsorption equilibrium with the feed: the same cell with every consuming reaction switched off
    k_ads, k_des, e_dg = rate_constants_nb(t_k, max(o2, 1e-9) / 100.0, *p[6:])[:3]
    theta_eq, _ = solve_coverage(0.0, 0.0, q, nh3 * 1e-6, 0.0, 0.0, k_ads, k_des, e_dg, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
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
    }
