"""The SCR chemistry of one catalyst cell, written once for every backend.

:func:`cell_balance` is plain Python arithmetic on scalars. It names its elementary functions ``exp``, ``log``,
``sqrt``, ``select`` and ``converged`` as module globals, so :mod:`scr_env.physics.backends` can compile the *same
code object* twice: with :mod:`math` and numba for the simulator, and with CasADi symbols for the model-based
controllers. There is no second copy of the chemistry anywhere.

Model (PHYSICS.md section 2): a continuously stirred cell at uniform temperature; gas phase quasi-steady (residence
time of milliseconds), surface NH3 coverage ``theta`` dynamic. Ammonium nitrate ``n`` (a fraction of the sites) is
a quasi-steady surface intermediate: formed from NH3* and NO2, consumed by NO, by decomposition back to NH3* + HNO3
(-> NO2) and by decomposition to N2O, its formation equals its consumption at every instant (no nitrate state; the
minutes-long build-up of nitrate on a cold catalyst fed NO2 is therefore not modelled, only its steady level). With
F the molar flow [mol/s], S the storage sites of the cell [mol] and q = F / S [1/s], the balances per site are, in
mole fractions y (x = y_NO, z = y_NO2):

    NH3:     q (y_in - y) = r_ads - r_des
    NO:      q (x_in - x) = r_std + r_n2o - r_ox_no + r_no_ox + r_an_no
    NO2:     q (z_in - z) = -r_no_ox + 2 r_an - r_an_no - r_an_dec
    N2O:     q (w - w_in) = r_n2o + r_ox_n2o / 2 + r_an_n2o
    nitrate: 0 = r_an - r_an_no - r_an_dec - r_an_n2o
    d theta / dt = r_ads - r_des - r_std - r_n2o - r_ox - r_ox_no - r_ox_n2o - 2 r_an + r_an_dec

with the reactions (per site, 1/s; every k is a per-site constant in mole-fraction units, Arrhenius, O2 factor and
the ideal-gas concentration already applied by :func:`arrhenius_constants`):

=============  =====================================================  ==============================================
rate           reaction                                               form
=============  =====================================================  ==============================================
r_ads, r_des   NH3 + S <-> NH3* (Temkin desorption)                   k_ads y (1 - theta - n), k_des e^(eg theta) th
r_std          4 NH3* + 4 NO + O2 -> 4 N2 + 6 H2O (standard SCR)      k_std x theta (per NO)
r_n2o          2 NH3* + 2 NO + 3/2 O2 -> 2 N2O + 3 H2O                k_n2o x theta (per N2O)
r_ox           4 NH3* + 3 O2 -> 2 N2 + 6 H2O                          k_ox theta (per NH3)
r_ox_no        4 NH3* + 5 O2 -> 4 NO + 6 H2O                          k_ox_no theta (per NH3)
r_ox_n2o       2 NH3* + 2 O2 -> N2O + 3 H2O                           k_ox_n2o theta (per NH3)
r_no_ox        NO + 1/2 O2 <-> NO2 (on sites free of NH3)             (1 - theta) (k_no_ox x - k_no2_red z)
r_an           2 NH3* + 2 NO2 -> NH4NO3* + N2 + H2O                   k_an theta z (per nitrate)
r_an_no        NH4NO3* + NO -> N2 + NO2 + 2 H2O (fast-SCR step)       k_an_no n x
r_an_dec       NH4NO3* -> NH3* + NO2 + 1/2 H2O + 1/4 O2               k_an_dec n
r_an_n2o       NH4NO3* -> N2O + 2 H2O                                 k_an_n2o n
=============  =====================================================  ==============================================

Fast SCR (2 NH3 + NO + NO2 -> 2 N2 + 3 H2O) is r_an followed by r_an_no; NO2-SCR (NH3 + NO2 -> N2 + ...) is r_an
followed by r_an_dec; the nitrate route to N2O is r_an followed by r_an_n2o (the reaction structure of the
ORNL/CLEERS Cu-SSZ-13 model, aladshaw3/cats ``rxns_v7.py`` r21-r33, and of Olsson et al. 2015's multi-site model).
The nitrate blocks NH3 adsorption (free sites 1 - theta - n). The reverse of NO oxidation is tied to the forward
rate by the gas-phase equilibrium: k_no2_red = k_no_ox / (K_p(T) sqrt(y_O2)) with :func:`no_oxidation_equilibrium`,
so the NO2/NO ratio of a long residence time is K_p sqrt(y_O2) at any temperature and O2.

Solution for given theta: the nitrate and NO2 balances are linear in n and z once x is fixed, which leaves one
scalar equation h(x) = 0 for NO (a cubic after clearing denominators). It is solved by a bracketed Newton
iteration (h(0) >= 0 >= h(x_max) with x_max = x_in + z_in + r_ox_no / q), at most ``X_NEWTON_ITERATIONS`` steps
(numba stops as soon as the step is at the rounding floor, CasADi runs them all). The outlet NO is then taken from
the NO balance with the rates of the last iterate, so every balance -- and nitrogen -- closes to rounding whatever
the iteration's last residual. Every rate also has its derivative with respect to theta (implicit differentiation
through h), for the implicit integrator of the kernel.
"""
from __future__ import annotations

from math import exp, log, sqrt  # rebound per backend (see the module docstring)

#: names of the per-site rate constants, the order :func:`arrhenius_constants` returns and :func:`cell_balance` takes
RATE_CONSTANT_NAMES = ("k_ads", "k_des", "e_des_gamma", "k_std", "k_n2o", "k_ox", "k_ox_no", "k_ox_n2o", "k_no_ox",
                       "k_no2_red", "k_an", "k_an_no", "k_an_dec", "k_an_n2o")
N_RATE_CONSTANTS = len(RATE_CONSTANT_NAMES)

#: Newton steps of the NO equation at most (from the linear start below, 3 to 5 reach the rounding floor in the
#: envelope of tests/scr_env/test_physics.py; the bracket makes every step safe) [chosen]
X_NEWTON_ITERATIONS = 12

# NO + 1/2 O2 <-> NO2 in the gas phase: standard reaction enthalpy and entropy at 298 K from the formation data
# (NO: 90.25 kJ/mol, 210.76 J/(mol K); NO2: 33.18 kJ/mol, 240.06 J/(mol K); O2: 205.15 J/(mol K)) [lit: CRC Handbook
# of Chemistry and Physics, standard thermodynamic properties of chemical substances], taken constant over 400-900 K
# (the heat-capacity correction changes K_p by under 3 % there) [chosen]. K_p in atm^-1/2.
NO_OXIDATION_DH_J_MOL = 33180.0 - 90250.0  # J/mol
NO_OXIDATION_DS_J_MOL_K = 240.06 - 210.76 - 0.5 * 205.15  # J/(mol K)
_R = 8.314462618  # J/(mol K), CODATA 2018 (scr_env.constants.GAS_CONSTANT_J_MOL_K)
_P_ATM = 101325.0  # Pa, the cell runs at 1 atm (scr_env.constants.ATMOSPHERIC_PRESSURE_PA)


def select(condition, if_true, if_false):  # rebound per backend
    """``if_true`` where ``condition`` else ``if_false`` (scalar; CasADi uses ``if_else``)."""
    return if_true if condition else if_false


def converged(condition):  # rebound per backend
    """Whether an iteration may stop early: ``condition`` in numba, never in CasADi (its loops are unrolled)."""
    return condition


def no_oxidation_equilibrium(temperature_k):
    """K_p(T) = y_NO2 / (y_NO sqrt(y_O2)) of NO + 1/2 O2 <-> NO2 at 1 atm [atm^-1/2] (van 't Hoff, constant dH, dS)."""
    return exp(NO_OXIDATION_DS_J_MOL_K / _R - NO_OXIDATION_DH_J_MOL / (_R * temperature_k))


def cell_balance(theta, q, y_nh3_in, y_no_in, y_no2_in, k_ads, k_des, e_des_gamma, k_std, k_n2o, k_ox, k_ox_no,
                 k_ox_n2o, k_no_ox, k_no2_red, k_an, k_an_no, k_an_dec, k_an_n2o):
    """Quasi-steady gas phase and coverage rate of one cell.

    Parameters
    ----------
    theta : NH3 coverage [-], in [0, 1].
    q : F / S, molar flow per storage site [1/s].
    y_nh3_in, y_no_in, y_no2_in : inlet mole fractions [-].
    k_* : the per-site constants of :data:`RATE_CONSTANT_NAMES` (module docstring): k_ads, k_std, k_n2o, k_an_no,
        k_an [1/s per unit mole fraction]; k_des, k_ox, k_ox_no, k_ox_n2o, k_an_dec, k_an_n2o [1/s];
        k_no_ox, k_no2_red [1/s per unit mole fraction, per free site]; e_des_gamma = gamma E_des0 / (R T) [-].

    Returns
    -------
    (g, dg, y_nh3, y_no, y_no2, n2o, n2, nitrate):
        g = d theta / dt [1/s], dg = d g / d theta [1/s], outlet mole fractions, N2O and N2 formed per site [1/s]
        (N2O outlet: y_n2o = y_n2o_in + n2o / q), and the quasi-steady nitrate coverage [-].
    """
    free0 = 1.0 - theta
    # Temkin desorption: k_des exp(-E0 (1 - gamma theta) / RT) theta; the exp(-E0/RT) factor is inside k_des.
    e_cov = exp(e_des_gamma * theta)
    r_des = k_des * e_cov * theta
    dr_des = k_des * e_cov * (1.0 + e_des_gamma * theta)

    # --- NO / NO2 / nitrate for this theta ------------------------------------------------------------------------
    a = (k_std + k_n2o) * theta  # first-order NO consumption [1/s]
    p = k_ox_no * theta  # NO source [1/s per site]
    kfw = k_no_ox * free0
    krv = k_no2_red * free0
    phi = k_an * theta  # nitrate formation per unit NO2
    c_dec = k_an_dec + k_an_n2o
    big_b = q * y_no_in + p
    big_d = q + a + kfw
    qz = q * y_no2_in
    # start: the linear system with the nitrate's NO consumption left out and its NO2 use at x = 0
    e0 = q + krv + phi * (1.0 + k_an_n2o / (c_dec + 1e-300))
    x = (big_b * e0 + krv * qz) / (big_d * e0 - krv * kfw + 1e-300)
    lo = 0.0
    hi = y_no_in + y_no2_in + p / q
    x = select(x > hi, 0.5 * hi, x)
    for _ in range(X_NEWTON_ITERATIONS):
        den = k_an_no * x + c_dec + 1e-300
        big_e = q + krv + phi * (1.0 + k_an_n2o / den)
        big_n = qz + kfw * x
        z = big_n / big_e
        n = phi * z / den
        h = big_b + krv * z - big_d * x - k_an_no * x * n
        e_x = -phi * k_an_n2o * k_an_no / (den * den)
        z_x = (kfw - z * e_x) / big_e
        n_x = (phi * z_x - n * k_an_no) / den
        h_x = krv * z_x - big_d - k_an_no * (n + x * n_x)
        lo = select(h > 0.0, x, lo)
        hi = select(h > 0.0, hi, x)
        step = h / (h_x - 1e-300)
        new = x - step
        new = select((new >= lo) * (new <= hi), new, 0.5 * (lo + hi))
        if converged(abs(step) <= 4.0 * 2.220446049250313e-16 * x):
            break
        x = new
    # rates at the last iterate x, and the NO2 and nitrate that solve their balances exactly there
    den = k_an_no * x + c_dec + 1e-300
    big_e = q + krv + phi * (1.0 + k_an_n2o / den)
    z = (qz + kfw * x) / big_e
    n = phi * z / den
    r_no_ox = kfw * x - krv * z
    r_an = phi * z
    r_an_no = k_an_no * n * x
    r_an_dec = k_an_dec * n
    r_an_n2o = k_an_n2o * n
    r_std = k_std * theta * x
    r_n2o = k_n2o * theta * x
    r_ox = k_ox * theta
    r_ox_n2o = k_ox_n2o * theta
    # outlet NO from its balance (equals x to the iteration's residual; closes the nitrogen balance exactly)
    y_no = y_no_in + (p - r_std - r_n2o - r_no_ox - r_an_no) / q
    # derivatives with respect to theta: partials at fixed x, then through x(theta) from h(x, theta) = 0
    e_x = -phi * k_an_n2o * k_an_no / (den * den)
    z_x = (kfw - z * e_x) / big_e
    n_x = (phi * z_x - n * k_an_no) / den
    h_x = krv * z_x - big_d - k_an_no * (n + x * n_x)
    e_t = -k_no2_red + k_an * (1.0 + k_an_n2o / den)
    z_t = (-k_no_ox * x - z * e_t) / big_e
    n_t = (k_an * z + phi * z_t) / den
    h_t = k_ox_no - k_no2_red * z + krv * z_t - (k_std + k_n2o - k_no_ox) * x - k_an_no * x * n_t
    dx = -h_t / (h_x - 1e-300)
    dz = z_t + z_x * dx
    dn = n_t + n_x * dx

    # --- NH3: q (y_in - y) = k_ads y free - r_des, free = 1 - theta - n (nitrate blocks adsorption) ----------------
    free = 1.0 - theta - n
    blocked = free < 0.0
    free = select(blocked, 0.0, free)
    dfree = select(blocked, 0.0, -1.0 - dn)
    inv_den = 1.0 / (q + k_ads * free)
    y_nh3 = (q * y_nh3_in + r_des) * inv_den
    dy_nh3 = (dr_des - y_nh3 * k_ads * dfree) * inv_den
    r_ads = k_ads * y_nh3 * free
    dr_ads = k_ads * (dy_nh3 * free + y_nh3 * dfree)

    g = r_ads - r_des - r_std - r_n2o - r_ox - p - r_ox_n2o - 2.0 * r_an + r_an_dec
    dg = (dr_ads - dr_des - (k_std + k_n2o) * (x + theta * dx) - k_ox - k_ox_no - k_ox_n2o
          - 2.0 * k_an * (z + theta * dz) + k_an_dec * dn)
    n2o = r_n2o + 0.5 * r_ox_n2o + r_an_n2o
    # N2 per site: standard SCR 1 per NO, oxidation 1/2 per NH3, nitrate formation 1, nitrate + NO 1
    n2 = r_std + 0.5 * r_ox + r_an + r_an_no
    return g, dg, y_nh3, y_no, z, n2o, n2, n


def o2_factors(o2_fraction, o2_reference_fraction, o2_order_std, o2_order_ox):
    """Rate multipliers for the O2 mole fraction [-] relative to the lab's: (standard SCR, NH3 oxidations and the
    N2O routes that take O2, NO oxidation). NO oxidation is half order (its reverse is zero order, so the pair keeps
    the gas-phase equilibrium at any O2); all are zero at zero O2."""
    log_rel = log(o2_fraction / o2_reference_fraction)
    return exp(o2_order_std * log_rel), exp(o2_order_ox * log_rel), exp(0.5 * log_rel)


def arrhenius_constants(temperature_k, f_o2_std, f_o2_ox, f_o2_half, o2_reference_fraction, a_ads, a_des, e_des,
                        temkin_gamma, a_std, e_std, a_n2o, e_n2o, a_ox, e_ox, a_ox_no, e_ox_no, a_ox_n2o, e_ox_n2o,
                        a_no_ox, e_no_ox, a_an, e_an, a_an_no, e_an_no, a_an_dec, e_an_dec, a_an_n2o, e_an_n2o):
    """Per-site constants of :func:`cell_balance` at a temperature [K], with the O2 factors of :func:`o2_factors`.

    Converts the literature units (C in mol/m3) to mole fractions with the ideal gas at 1 atm: C = y P / (R T).
    The NO oxidation constant is given at the reference O2; its reverse follows from the equilibrium
    (:func:`no_oxidation_equilibrium`). Returns the constants in the order of :data:`RATE_CONSTANT_NAMES`.
    """
    inv_rt = 1.0 / (_R * temperature_k)  # mol/J (one division, then products)
    c_total = _P_ATM * inv_rt  # mol/m3 at 1 atm
    k_ads = a_ads * c_total
    k_des = a_des * exp(-e_des * inv_rt)
    e_des_gamma = temkin_gamma * e_des * inv_rt
    k_std = a_std * exp(-e_std * inv_rt) * c_total * f_o2_std
    k_n2o = a_n2o * exp(-e_n2o * inv_rt) * c_total * f_o2_ox
    k_ox = a_ox * exp(-e_ox * inv_rt) * f_o2_ox
    k_ox_no = a_ox_no * exp(-e_ox_no * inv_rt) * f_o2_ox
    k_ox_n2o = a_ox_n2o * exp(-e_ox_n2o * inv_rt) * f_o2_ox
    # forward at the reference O2 times (y_O2 / y_ref)^1/2; reverse k_fwd / (K_p sqrt(y_ref)), folded into one exp
    k_no_ox_ref = a_no_ox * c_total
    k_no_ox = k_no_ox_ref * exp(-e_no_ox * inv_rt) * f_o2_half
    k_no2_red = (k_no_ox_ref / sqrt(o2_reference_fraction)
                 * exp(-NO_OXIDATION_DS_J_MOL_K / _R - (e_no_ox - NO_OXIDATION_DH_J_MOL) * inv_rt))
    k_an = a_an * exp(-e_an * inv_rt) * c_total
    k_an_no = a_an_no * exp(-e_an_no * inv_rt) * c_total
    k_an_dec = a_an_dec * exp(-e_an_dec * inv_rt)
    k_an_n2o = a_an_n2o * exp(-e_an_n2o * inv_rt)
    return (k_ads, k_des, e_des_gamma, k_std, k_n2o, k_ox, k_ox_no, k_ox_n2o, k_no_ox, k_no2_red, k_an, k_an_no,
            k_an_dec, k_an_n2o)


def rate_constants(temperature_k, o2_fraction, a_ads, a_des, e_des, temkin_gamma, a_std, e_std, a_n2o, e_n2o, a_ox,
                   e_ox, a_ox_no, e_ox_no, a_ox_n2o, e_ox_n2o, a_no_ox, e_no_ox, a_an, e_an, a_an_no, e_an_no,
                   a_an_dec, e_an_dec, a_an_n2o, e_an_n2o, o2_reference_fraction, o2_order_std, o2_order_ox):
    """:func:`arrhenius_constants` at an O2 mole fraction [-] (the argument order of the packed parameters)."""
    f_std, f_ox, f_half = o2_factors(o2_fraction, o2_reference_fraction, o2_order_std, o2_order_ox)
    return arrhenius_constants(temperature_k, f_std, f_ox, f_half, o2_reference_fraction, a_ads, a_des, e_des,
                               temkin_gamma, a_std, e_std, a_n2o, e_n2o, a_ox, e_ox, a_ox_no, e_ox_no, a_ox_n2o,
                               e_ox_n2o, a_no_ox, e_no_ox, a_an, e_an, a_an_no, e_an_no, a_an_dec, e_an_dec, a_an_n2o,
                               e_an_n2o)


def decomposition_efficiency(temperature_k, t50_k, width_k):
    """Fraction [-] of the injected urea that has decomposed to NH3 (thermolysis + HNCO hydrolysis) at the SCR inlet
    temperature [K]: a logistic curve, 50 % at ``t50_k`` (PHYSICS.md section 3; the curve shape is [chosen])."""
    return 1.0 / (1.0 + exp(-(temperature_k - t50_k) / width_k))
