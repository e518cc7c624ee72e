"""The SCR chemistry of one catalyst cell, written once for every backend.

:func:`cell_balance` is plain Python arithmetic on scalars. It names its elementary functions ``exp``, ``sqrt`` and
``select`` as module globals, so :mod:`scr_env.physics.backends` can compile the *same code object* twice: with
:mod:`math` and numba for the simulator, and with CasADi symbols for the model-based controllers. There is no second
copy of the chemistry anywhere.

Model (PHYSICS.md section 2): a continuously stirred cell at uniform temperature; gas phase quasi-steady (residence
time of milliseconds), surface NH3 coverage ``theta`` dynamic. With F the molar flow [mol/s], S the storage sites of
the cell [mol] and q = F / S [1/s], the gas balances are, per site and in mole fractions y:

    NH3:  q (y_in - y) = r_ads - r_des
    NO:   q (y_in - y) = r_std + r_fast + r_n2o - r_ox_no
    NO2:  q (y_in - y) = r_fast + r_no2
    N2O:  q (y - y_in) = r_n2o

and the surface balance is

    d theta / dt = r_ads - r_des - r_std - 2 r_fast - (4/3) r_no2 - r_ox - r_ox_no - r_n2o

with r_ads = k_ads y_NH3 (1 - theta), r_des = k_des exp(e_des (gamma theta)) theta (Temkin),
r_std = k_std y_NO theta, r_fast = k_fast y_NO y_NO2 theta, r_no2 = k_no2 y_NO2 theta, r_ox = k_ox theta,
r_ox_no = k_ox_no theta (produces NO), r_n2o = k_n2o y_NO theta (NH3* + NO -> N2O, the low-temperature N2O
of the CLEERS standard-SCR data; per N2O). All k are the temperature-dependent
constants *per site in mole-fraction units* (Arrhenius and the ideal-gas concentration already applied).
The NO/NO2 pair is bilinear through fast SCR and is solved exactly (positive root of a quadratic).
Every rate also returns its derivative with respect to theta, for the implicit integrator.
"""
from __future__ import annotations

from math import exp, log, sqrt  # rebound per backend (see the module docstring)


def select(condition, if_true, if_false):  # rebound per backend
    """``if_true`` where ``condition`` else ``if_false`` (scalar; CasADi uses ``if_else``)."""
    return if_true if condition else if_false


def cell_balance(theta, q, y_nh3_in, y_no_in, y_no2_in, k_ads, k_des, e_des_gamma, k_std, k_fast, k_no2, k_ox,
                 k_ox_no, k_n2o):
    """Quasi-steady gas phase and coverage rate of one cell.

    Parameters
    ----------
    theta : NH3 coverage [-], in [0, 1].
    q : F / S, molar flow per storage site [1/s].
    y_nh3_in, y_no_in, y_no2_in : inlet mole fractions [-].
    k_ads : adsorption constant per site [1/s per unit mole fraction].
    k_des : desorption constant at zero coverage [1/s], ``e_des_gamma`` = gamma E_des0 / (R T) [-] (Temkin).
    k_std, k_no2 : SCR constants per site [1/s per unit mole fraction]; k_fast [1/s per unit mole fraction^2].
    k_ox, k_ox_no : NH3 oxidation constants per site [1/s]; k_n2o [1/s per unit mole fraction].

    Returns
    -------
    (g, dg, y_nh3, y_no, y_no2, r_std, r_fast, r_no2, r_ox, r_ox_no, r_n2o):
        g = d theta / dt [1/s], dg = d g / d theta [1/s], outlet mole fractions, and the reaction rates per site
        [1/s] (r_n2o per N2O formed). N2O outlet: y_n2o = y_n2o_in + r_n2o / q.
    """
    free = 1.0 - theta
    # Temkin desorption: k_des exp(-E0 (1 - gamma theta) / RT) theta; the exp(-E0/RT) factor is inside k_des.
    e_cov = exp(e_des_gamma * theta)
    r_des = k_des * e_cov * theta
    dr_des = k_des * e_cov * (1.0 + e_des_gamma * theta)
    # NH3 gas: q (y_in - y) = k_ads y (1 - theta) - r_des  ->  y = (q y_in + r_des) / (q + k_ads (1 - theta))
    inv_den = 1.0 / (q + k_ads * free)
    y_nh3 = (q * y_nh3_in + r_des) * inv_den
    dy_nh3 = (dr_des + y_nh3 * k_ads) * inv_den
    r_ads = k_ads * y_nh3 * free
    dr_ads = k_ads * (dy_nh3 * free - y_nh3)
    # NO and NO2. With a = (k_std + k_n2o) theta, f = k_fast theta, n = k_no2 theta, p = k_ox_no theta:
    #   NO:  B - D x - f x z = 0,  NO2:  q z0 - E z - f x z = 0,  B = q x0 + p, D = q + a, E = q + n
    # eliminating z gives D f x^2 + b x - B E = 0 with b = D E + f q z0 - B f; x is its non-negative root.
    k_no = k_std + k_n2o  # both consume NO first order
    a = k_no * theta
    f = k_fast * theta
    n = k_no2 * theta
    p = k_ox_no * theta
    big_b = q * y_no_in + p
    big_d = q + a
    big_e = q + n
    b = big_d * big_e + f * q * y_no2_in - big_b * f
    s = sqrt(b * b + 4.0 * big_d * f * big_b * big_e) + abs(b)
    # The root is 2 B E / (b + sqrt(disc)) for b >= 0 and (sqrt(disc) - b) / (2 D f) for b < 0: each form is free
    # of cancellation on its side, and with s = sqrt(disc) + |b| both are one division.
    pos = b >= 0.0
    y_no = select(pos, 2.0 * big_b * big_e, s) / (select(pos, s, 2.0 * big_d * f) + 1e-300)
    db = k_no * big_e + big_d * k_no2 + k_fast * q * y_no2_in - k_ox_no * f - big_b * k_fast
    # implicit differentiation of D f x^2 + b x - B E = 0 with respect to theta
    dpoly = (k_no * f + big_d * k_fast) * y_no * y_no + db * y_no - (k_ox_no * big_e + big_b * k_no2)
    dy_no = -dpoly / (2.0 * big_d * f * y_no + b + 1e-300)
    inv_g = 1.0 / (big_e + f * y_no)
    y_no2 = q * y_no2_in * inv_g
    dy_no2 = -y_no2 * (k_no2 + k_fast * y_no + f * dy_no) * inv_g
    r_std = k_std * theta * y_no
    dr_std = k_std * (y_no + theta * dy_no)
    r_fast = f * y_no * y_no2
    dr_fast = k_fast * y_no * y_no2 + f * (dy_no * y_no2 + y_no * dy_no2)
    r_no2 = n * y_no2
    dr_no2 = k_no2 * y_no2 + n * dy_no2
    r_ox = k_ox * theta
    r_ox_no = k_ox_no * theta
    r_n2o = k_n2o * theta * y_no
    dr_n2o = k_n2o * (y_no + theta * dy_no)
    g = r_ads - r_des - r_std - 2.0 * r_fast - (4.0 / 3.0) * r_no2 - r_ox - r_ox_no - r_n2o
    dg = dr_ads - dr_des - dr_std - 2.0 * dr_fast - (4.0 / 3.0) * dr_no2 - k_ox - k_ox_no - dr_n2o
    return g, dg, y_nh3, y_no, y_no2, r_std, r_fast, r_no2, r_ox, r_ox_no, r_n2o


def o2_factors(o2_fraction, o2_reference_fraction, o2_order_std, o2_order_ox):
    """Rate multipliers for the O2 mole fraction [-] relative to the lab's: (standard SCR, NH3 oxidations)."""
    log_rel = log(o2_fraction / o2_reference_fraction)
    return exp(o2_order_std * log_rel), exp(o2_order_ox * log_rel)


def arrhenius_constants(temperature_k, f_o2_std, f_o2_ox, a_ads, a_des, e_des, temkin_gamma, a_std, e_std,
                        a_fast, e_fast, a_no2, e_no2, a_ox, e_ox, a_ox_no, e_ox_no, a_n2o, e_n2o):
    """Per-site constants of :func:`cell_balance` at a temperature [K], with the O2 factors of :func:`o2_factors`.

    Converts the literature units (C in mol/m3) to mole fractions with the ideal gas at 1 atm:
    C = y P / (R T). Returns (k_ads, k_des, e_des_gamma, k_std, k_fast, k_no2, k_ox, k_ox_no, k_n2o).
    """
    inv_rt = 1.0 / (8.314462618 * temperature_k)  # mol/J; R from CODATA 2018 (one division, then products)
    c_total = 101325.0 * inv_rt  # mol/m3 at 1 atm (scr_env.constants.ATMOSPHERIC_PRESSURE_PA)
    k_ads = a_ads * c_total
    k_des = a_des * exp(-e_des * inv_rt)
    e_des_gamma = temkin_gamma * e_des * inv_rt
    k_std = a_std * exp(-e_std * inv_rt) * c_total * f_o2_std
    k_fast = a_fast * exp(-e_fast * inv_rt) * c_total * c_total
    k_no2 = a_no2 * exp(-e_no2 * inv_rt) * c_total
    k_ox = a_ox * exp(-e_ox * inv_rt) * f_o2_ox
    k_ox_no = a_ox_no * exp(-e_ox_no * inv_rt) * f_o2_ox
    k_n2o = a_n2o * exp(-e_n2o * inv_rt) * c_total
    return k_ads, k_des, e_des_gamma, k_std, k_fast, k_no2, k_ox, k_ox_no, k_n2o


def rate_constants(temperature_k, o2_fraction, a_ads, a_des, e_des, temkin_gamma, a_std, e_std, a_fast, e_fast,
                   a_no2, e_no2, a_ox, e_ox, a_ox_no, e_ox_no, a_n2o, e_n2o, o2_reference_fraction, o2_order_std,
                   o2_order_ox):
    """:func:`arrhenius_constants` at an O2 mole fraction [-] (the argument order of the packed parameters)."""
    f_std, f_ox = o2_factors(o2_fraction, o2_reference_fraction, o2_order_std, o2_order_ox)
    return arrhenius_constants(temperature_k, f_std, f_ox, a_ads, a_des, e_des, temkin_gamma, a_std, e_std, a_fast,
                               e_fast, a_no2, e_no2, a_ox, e_ox, a_ox_no, e_ox_no, a_n2o, e_n2o)


def decomposition_efficiency(temperature_k, t50_k, width_k):
    """Fraction [-] of the injected urea that has decomposed to NH3 (thermolysis + HNCO hydrolysis) at the SCR inlet
    temperature [K]: a logistic curve, 50 % at ``t50_k`` (PHYSICS.md section 3; the curve shape is [chosen])."""
    return 1.0 / (1.0 + exp(-(temperature_k - t50_k) / width_k))
