"""Urea dosing and the gas at the catalyst face, written once for every backend.

Plain scalar functions compiled by :mod:`scr_env.physics.backends` for numba (the plant kernel), CasADi
(:mod:`scr_env.casadi_model`) and numpy (:mod:`control.models`), as :mod:`scr_env.physics.cell` is. They turn the
held inputs of a control interval (exhaust flow, inlet temperature, NOx and its NO2 share, AdBlue rate) into what
the first cell sees: the flow per storage site and the inlet mole fractions of NH3, NO and NO2 (PHYSICS.md
section 3: AdBlue -> urea -> 2 NH3, incomplete below about 200 C, see :func:`~scr_env.physics.cell.
decomposition_efficiency`).
"""
from __future__ import annotations

from scr_env.constants import NH3_MOL_PER_G_ADBLUE
from scr_env.physics.cell import decomposition_efficiency  # rebound per backend

#: 1/s: floor of the flow per storage site, which keeps the cell algebra defined at zero flow [chosen]
MIN_FLOW_PER_SITE_1_S = 1e-12


def fmin(a, b):  # rebound per backend
    """The smaller of two floats (numba: ``min``; CasADi: ``fmin``; numpy: ``minimum``)."""
    return min(a, b)


def fmax(a, b):  # rebound per backend
    """The larger of two floats (numba: ``max``; CasADi: ``fmax``; numpy: ``maximum``)."""
    return max(a, b)


def actuator_step(command_g_s, delivered_g_s, lag_coefficient, max_change_g_s):
    """The AdBlue rate a dosing unit delivers over the next control interval [g/s] (the optional actuator of
    :mod:`scr_env.actuator`): a first-order lag of the delivered rate ``delivered_g_s`` towards the command
    ``command_g_s``, ``lag_coefficient`` = 1 - exp(-dt / time constant) [-], its change per interval bounded by
    ``max_change_g_s`` = slew limit [g/s per s] * dt [g/s]."""
    change = lag_coefficient * (command_g_s - delivered_g_s)
    return delivered_g_s + fmin(fmax(change, -max_change_g_s), max_change_g_s)


def injected_adblue(adblue_g_s, max_rate_g_s):
    """The AdBlue rate the injector delivers [g/s]: the command clamped to [0, ``max_rate_g_s``]."""
    return fmin(fmax(adblue_g_s, 0.0), max_rate_g_s)


def urea_decomposition(adblue_g_s, inlet_temperature_k, t50_k, width_k):
    """(NH3 reaching the catalyst [mol/s], nitrogen of the undecomposed urea [mol N/s]) from an injected AdBlue
    rate [g/s] at the SCR inlet temperature [K]. The second leaves the nitrogen balance (deposits, HNCO); both
    count 2 N per urea, the NH3 equivalents of a full decomposition."""
    eta = decomposition_efficiency(inlet_temperature_k, t50_k, width_k)
    return eta * adblue_g_s * NH3_MOL_PER_G_ADBLUE, (1.0 - eta) * adblue_g_s * NH3_MOL_PER_G_ADBLUE


def flow_per_site(flow_mol_s, sites_per_cell_mol):
    """q = F / S [1/s], the molar flow per storage site of a cell, floored at :data:`MIN_FLOW_PER_SITE_1_S`."""
    return fmax(flow_mol_s / sites_per_cell_mol, MIN_FLOW_PER_SITE_1_S)


def inlet_nh3_fraction(nh3_mol_s, flow_mol_s, sites_per_cell_mol):
    """NH3 mole fraction [-] at the catalyst face: the NH3 flow [mol/s] in the exhaust flow (floored as q is)."""
    return nh3_mol_s / fmax(flow_mol_s, MIN_FLOW_PER_SITE_1_S * sites_per_cell_mol)


def inlet_nox_fractions(nox_ppm, no2_fraction):
    """(NO, NO2) mole fractions [-] at the catalyst face from the NOx [ppm] and its NO2 share [-]."""
    nox = nox_ppm * 1e-6
    return nox * (1.0 - no2_fraction), nox * no2_fraction


def inlet_conditions(flow_mol_s, inlet_temperature_k, nox_ppm, no2_fraction, adblue_g_s, max_rate_g_s, t50_k,
                     width_k, sites_per_cell_mol):
    """Everything the first cell sees in a control interval, from the held inputs.

    Returns (q [1/s], y_nh3_in, y_no_in, y_no2_in [-], NH3 reaching the catalyst [mol/s], undecomposed urea
    nitrogen [mol N/s]) for the AdBlue command ``adblue_g_s`` clamped by :func:`injected_adblue`.
    """
    adblue = injected_adblue(adblue_g_s, max_rate_g_s)
    nh3_mol_s, urea_n_mol_s = urea_decomposition(adblue, inlet_temperature_k, t50_k, width_k)
    q = flow_per_site(flow_mol_s, sites_per_cell_mol)
    y_nh3_in = inlet_nh3_fraction(nh3_mol_s, flow_mol_s, sites_per_cell_mol)
    y_no_in, y_no2_in = inlet_nox_fractions(nox_ppm, no2_fraction)
    return q, y_nh3_in, y_no_in, y_no2_in, nh3_mol_s, urea_n_mol_s
