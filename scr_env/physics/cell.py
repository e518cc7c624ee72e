"""The SCR chemistry of one catalyst cell, written once for every backend.

:func:`cell_balance` is plain Python arithmetic on scalars. It names its elementary functions ``exp``, ``log``,
``sqrt`` and ``select`` as module globals, so :mod:`scr_env.physics.backends` can compile the *same
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
r_n2o          2 NH3* + 2 NO + 3/2 O2 -> 2 N2O + 3 H2O                k_n2o x theta (per N2O; E of standard SCR)
r_ox           4 NH3* + 3 O2 -> 2 N2 + 6 H2O                          k_ox theta (per NH3)
r_ox_no        4 NH3* + 5 O2 -> 4 NO + 6 H2O                          k_ox_no theta (per NH3)
r_ox_n2o       2 NH3* + 2 O2 -> N2O + 3 H2O                           k_ox_n2o theta (per NH3; E of r_ox_no)
r_no_ox        NO + 1/2 O2 <-> NO2 (on sites free of NH3)             (1 - theta) (k_no_ox x - k_no2_red z)
r_an           2 NH3* + 2 NO2 -> NH4NO3* + N2 + H2O                   k_an theta z (per nitrate)
r_an_no        NH4NO3* + NO -> N2 + NO2 + 2 H2O (fast-SCR step)       k_an_no n x
r_an_dec       NH4NO3* -> NH3* + NO2 + 1/2 H2O + 1/4 O2               k_an_dec n
r_an_n2o       NH4NO3* -> N2O + 2 H2O                                 k_an_n2o n (E of r_an_dec)
=============  =====================================================  ==============================================

Fast SCR (2 NH3 + NO + NO2 -> 2 N2 + 3 H2O) is r_an followed by r_an_no; NO2-SCR (NH3 + NO2 -> N2 + ...) is r_an
followed by r_an_dec; the nitrate route to N2O is r_an followed by r_an_n2o (the reaction structure of the
ORNL/CLEERS Cu-SSZ-13 model, aladshaw3/cats ``rxns_v7.py`` r21-r33, and of Olsson et al. 2015's multi-site model).
The nitrate blocks NH3 adsorption (free sites 1 - theta - n). The reverse of NO oxidation is tied to the forward
rate by the gas-phase equilibrium: k_no2_red = k_no_ox / (K_p(T) sqrt(y_O2)) with :func:`no_oxidation_equilibrium`,
so the NO2/NO ratio of a long residence time is K_p sqrt(y_O2) at any temperature and O2.

Solution for given theta, in closed form: with m = n / (k_an theta) and w = m x, the NO and NO2 balances are
linear in (x, m) for fixed w, and w = x m is then a quadratic with exactly one root where x, m >= 0 (the bilinear
NO-nitrate term is the only non-linearity, as the bilinear NO-NO2 term of a global fast-SCR rate would be). Every
coefficient is a sum of non-negative terms, so the solution keeps its relative accuracy whatever the ratio of flow
to rates, and the balances -- nitrogen with them -- close to rounding. The derivative of the rate with respect to
theta differentiates that closed form (:func:`cell_slope`), for the implicit integrator of the kernel; the kernel
evaluates it only where it takes a Newton step (:func:`cell_state` at every iterate, :func:`cell_outlets` once).
"""
from __future__ import annotations

from math import exp, log, sqrt  # rebound per backend (see the module docstring)

from scr_env.constants import ATMOSPHERIC_PRESSURE_PA as _P_ATM  # Pa, the cell runs at 1 atm
from scr_env.constants import GAS_CONSTANT_J_MOL_K as _R  # J/(mol K), CODATA 2018

#: names of the per-site rate constants, the order :func:`arrhenius_constants` returns and :func:`cell_balance` takes
RATE_CONSTANT_NAMES = ("k_ads", "k_des", "e_des_gamma", "k_std", "k_n2o", "k_ox", "k_ox_no", "k_ox_n2o", "k_no_ox",
                       "k_no2_red", "k_an", "k_an_no", "k_an_dec", "k_an_n2o")
N_RATE_CONSTANTS = len(RATE_CONSTANT_NAMES)

# NO + 1/2 O2 <-> NO2 in the gas phase: standard reaction enthalpy and entropy at 298 K from the formation data
# (NO: 90.25 kJ/mol, 210.76 J/(mol K); NO2: 33.18 kJ/mol, 240.06 J/(mol K); O2: 205.15 J/(mol K)) [lit: CRC Handbook
# of Chemistry and Physics, standard thermodynamic properties of chemical substances], taken constant over 400-900 K
# (the heat-capacity correction changes K_p by under 3 % there) [chosen]. K_p in atm^-1/2.
NO_OXIDATION_DH_J_MOL = 33180.0 - 90250.0  # J/mol
NO_OXIDATION_DS_J_MOL_K = 240.06 - 210.76 - 0.5 * 205.15  # J/(mol K)
#: temperatures [K] of the two ageing factors of the SCR sites (scr_env.params.AGEING_TABLE "activity_200c" and
#: "activity_550c"): log-linear in 1/T between them, held beyond [chosen: the CLEERS ages span 250-550 C]
SCR_FACTOR_ANCHORS_K = (473.15, 823.15)
_U_LO = 1.0 / (_R * SCR_FACTOR_ANCHORS_K[0])
_U_HI = 1.0 / (_R * SCR_FACTOR_ANCHORS_K[1])


def select(condition, if_true, if_false):  # rebound per backend
    """``if_true`` where ``condition`` else ``if_false`` (scalar; CasADi uses ``if_else``)."""
    return if_true if condition else if_false


def no_oxidation_equilibrium(temperature_k):
    """K_p(T) = y_NO2 / (y_NO sqrt(y_O2)) of NO + 1/2 O2 <-> NO2 at 1 atm [atm^-1/2] (van 't Hoff, constant dH, dS)."""
    return exp(NO_OXIDATION_DS_J_MOL_K / _R - NO_OXIDATION_DH_J_MOL / (_R * temperature_k))


def cell_state(theta, q, y_nh3_in, y_no_in, y_no2_in, k_ads, k_des, e_des_gamma, k_std, k_n2o, k_ox, k_ox_no,
               k_ox_n2o, k_no_ox, k_no2_red, k_an, k_an_no, k_an_dec, k_an_n2o):
    """Coverage rate and NH3 outlet of one cell at coverage ``theta`` (the part of :func:`cell_balance` a Newton
    iteration needs at every iterate; :func:`cell_outlets` and :func:`cell_slope` take it from there).

    Returns (g, y_nh3, nitrate, x, m, c): g = d theta / dt [1/s], the outlet NH3 [-], the quasi-steady nitrate
    coverage [-], x = outlet NO [-], m = nitrate / (k_an theta) (outlet NO2 = (k_an_no x + k_an_dec + k_an_n2o) m)
    and ``c``, a tuple of intermediate values for :func:`cell_slope`.
    """
    free0 = 1.0 - theta
    # Temkin desorption: k_des exp(-E0 (1 - gamma theta) / RT) theta; the exp(-E0/RT) factor is inside k_des.
    e_cov = exp(e_des_gamma * theta)
    r_des = k_des * e_cov * theta

    # --- NO / NO2 / nitrate for this theta ------------------------------------------------------------------------
    # With m = n / phi (= z / (k_an_no x + c), finite as theta -> 0) and w = m x, the NO and NO2 balances are linear
    # in (x, m) for a given w: x = X0 + X1 w, m = M0 + M1 w, with X0, M0 >= 0 and X1, M1 <= 0 written as sums of
    # non-negative terms over a non-negative determinant (no cancellation, also where the flow is far below the
    # NO-oxidation rates). w = x m is then F(w) = qa w^2 + qb w + qc = 0 with qa, qc >= 0 > qb and F(0) >= 0 >= F
    # where m = 0: its smaller root qc / qs, qs = (sqrt(disc) - qb) / 2, is the one with x, m >= 0.
    c_dec = k_an_dec + k_an_n2o
    k2 = c_dec + k_an_n2o
    kfw = k_no_ox * free0
    krv = k_no2_red * free0
    phi = k_an * theta  # nitrate formation per unit NO2
    qa_ = q + (k_std + k_n2o) * theta  # q + first-order NO consumption
    big_b = q * y_no_in + k_ox_no * theta
    big_d = qa_ + kfw
    qz = q * y_no2_in
    b2 = (q + krv) * c_dec + phi * k2
    big_p = qa_ * (q + krv) + kfw * q
    big_s = c_dec * q + k_an_dec * krv + k2 * phi
    big_t = qa_ * (q + krv + phi) + kfw * (q + 2.0 * phi)
    inv_det = 1.0 / (big_p * c_dec + big_d * phi * k2 + 1e-300)
    x0 = (b2 * big_b + krv * c_dec * qz) * inv_det
    x1 = -k_an_no * phi * big_s * inv_det
    m0 = (big_d * qz + kfw * big_b) * inv_det
    m1 = -k_an_no * big_t * inv_det
    qa = x1 * m1
    qb = x0 * m1 + x1 * m0 - 1.0
    qc = x0 * m0
    disc = qb * qb - 4.0 * qa * qc
    qs = 0.5 * (sqrt(select(disc > 0.0, disc, 0.0)) - qb)
    w = qc / qs
    x = x0 + x1 * w
    x = select(x > 0.0, x, 0.0)
    m = m0 + m1 * w
    m = select(m > 0.0, m, 0.0)
    z = (k_an_no * x + c_dec) * m
    n = phi * m

    # --- NH3: q (y_in - y) = k_ads y free - r_des, free = 1 - theta - n (nitrate blocks adsorption) ----------------
    free = free0 - n
    free = select(free > 0.0, free, 0.0)
    inv_nh3 = 1.0 / (q + k_ads * free)
    y_nh3 = (q * y_nh3_in + r_des) * inv_nh3
    g = (k_ads * y_nh3 * free - r_des - (k_std + k_n2o) * theta * x - (k_ox + k_ox_no + k_ox_n2o) * theta
         - 2.0 * phi * z + k_an_dec * n)
    return g, y_nh3, n, x, m, (z, e_cov, free, inv_nh3, inv_det, x0, x1, m0, m1, qa_, kfw, krv, big_b, qz, b2,
                               big_s, big_d)


def cell_outlets(theta, q, k_std, k_n2o, k_ox, k_ox_no, k_ox_n2o, k_no_ox, k_no2_red, k_an, k_an_no, k_an_dec,
                 k_an_n2o, x, m):
    """(y_no, y_no2, n2o, n2): outlet NO and NO2 [-] at the solution (x, m) of :func:`cell_state`, and the N2O and N2
    formed per site [1/s] (N2O outlet: y_n2o = y_n2o_in + n2o / q)."""
    z = (k_an_no * x + k_an_dec + k_an_n2o) * m
    n = k_an * theta * m
    r_std = k_std * theta * x
    r_an = k_an * theta * z
    n2o = k_n2o * theta * x + 0.5 * k_ox_n2o * theta + k_an_n2o * n
    # N2 per site: standard SCR 1 per NO, oxidation 1/2 per NH3, nitrate formation 1, nitrate + NO 1
    n2 = r_std + 0.5 * k_ox * theta + r_an + k_an_no * n * x
    return x, z, n2o, n2


def cell_slope(theta, q, k_ads, k_des, e_des_gamma, k_std, k_n2o, k_ox, k_ox_no, k_ox_n2o, k_no_ox, k_no2_red, k_an,
               k_an_no, k_an_dec, k_an_n2o, y_nh3, x, m, c):
    """d g / d theta [1/s] at the state of :func:`cell_state` (its y_nh3, x, m and intermediates c): the closed-form
    solution differentiated through the root of F (dw = -F_theta / F_w); the suffix _t marks d / d theta."""
    z, e_cov, free, inv_nh3, inv_det, x0, x1, m0, m1, qa_, kfw, krv, big_b, qz, b2, big_s, big_d = c
    c_dec = k_an_dec + k_an_n2o
    k2 = c_dec + k_an_n2o
    phi = k_an * theta
    k_sn = k_std + k_n2o
    big_p_t = k_sn * (q + krv) - qa_ * k_no2_red - k_no_ox * q
    det_t = big_p_t * c_dec + k2 * ((k_sn - k_no_ox) * phi + big_d * k_an)
    b2_t = k_an * k2 - k_no2_red * c_dec
    x0_t = (b2_t * big_b + b2 * k_ox_no - k_no2_red * c_dec * qz) * inv_det - x0 * det_t * inv_det
    x1_t = -k_an_no * (k_an * big_s + phi * (k2 * k_an - k_an_dec * k_no2_red)) * inv_det - x1 * det_t * inv_det
    m0_t = ((k_sn - k_no_ox) * qz - k_no_ox * big_b + kfw * k_ox_no) * inv_det - m0 * det_t * inv_det
    big_t_t = (k_sn * (q + krv + phi) + qa_ * (k_an - k_no2_red) - k_no_ox * (q + 2.0 * phi)
               + 2.0 * kfw * k_an)
    m1_t = -k_an_no * big_t_t * inv_det - m1 * det_t * inv_det
    w = x * m
    xt = x0_t + x1_t * w
    mt = m0_t + m1_t * w
    f_w = x1 * m + x * m1 - 1.0  # < 0
    dw = -(xt * m + x * mt) / f_w
    dx = xt + x1 * dw
    dm = mt + m1 * dw
    dz = k_an_no * dx * m + (k_an_no * x + c_dec) * dm
    dn = k_an * m + phi * dm
    dr_des = k_des * e_cov * (1.0 + e_des_gamma * theta)
    dfree = select(free > 0.0, -1.0 - dn, 0.0)
    dy_nh3 = (dr_des - y_nh3 * k_ads * dfree) * inv_nh3
    dr_ads = k_ads * (dy_nh3 * free + y_nh3 * dfree)
    return (dr_ads - dr_des - k_sn * (x + theta * dx) - k_ox - k_ox_no - k_ox_n2o
            - 2.0 * k_an * (z + theta * dz) + k_an_dec * dn)


def cell_balance(theta, q, y_nh3_in, y_no_in, y_no2_in, k_ads, k_des, e_des_gamma, k_std, k_n2o, k_ox, k_ox_no,
                 k_ox_n2o, k_no_ox, k_no2_red, k_an, k_an_no, k_an_dec, k_an_n2o):
    """Quasi-steady gas phase and coverage rate of one cell, with the derivative of the rate.

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
    g, y_nh3, n, x, m, c = cell_state(theta, q, y_nh3_in, y_no_in, y_no2_in, k_ads, k_des, e_des_gamma, k_std,
                                      k_n2o, k_ox, k_ox_no, k_ox_n2o, k_no_ox, k_no2_red, k_an, k_an_no, k_an_dec,
                                      k_an_n2o)
    dg = cell_slope(theta, q, k_ads, k_des, e_des_gamma, k_std, k_n2o, k_ox, k_ox_no, k_ox_n2o, k_no_ox, k_no2_red,
                    k_an, k_an_no, k_an_dec, k_an_n2o, y_nh3, x, m, c)
    y_no, y_no2, n2o, n2 = cell_outlets(theta, q, k_std, k_n2o, k_ox, k_ox_no, k_ox_n2o, k_no_ox, k_no2_red, k_an,
                                        k_an_no, k_an_dec, k_an_n2o, x, m)
    return g, dg, y_nh3, y_no, y_no2, n2o, n2, n


def o2_factors(o2_fraction, o2_reference_fraction, o2_order_std, o2_order_ox):
    """Rate multipliers for the O2 mole fraction [-] relative to the lab's: (standard SCR, NH3 oxidations and the
    N2O routes that take O2, NO oxidation). NO oxidation is half order (its reverse is zero order, so the pair keeps
    the gas-phase equilibrium at any O2); all are zero at zero O2."""
    log_rel = log(o2_fraction / o2_reference_fraction)
    return exp(o2_order_std * log_rel), exp(o2_order_ox * log_rel), exp(0.5 * log_rel)


def arrhenius_constants(temperature_k, f_o2_std, f_o2_ox, f_o2_half, inv_sqrt_o2_reference, a_ads, a_des, e_des,
                        temkin_gamma, a_std, e_std, a_n2o, a_ox, e_ox, a_ox_no, e_ox_no, a_ox_n2o, a_no_ox, e_no_ox,
                        a_an, e_an, a_an_no, e_an_no, a_an_dec, e_an_dec, a_an_n2o, scr_log_factor_low,
                        scr_log_factor_high):
    """Per-site constants of :func:`cell_balance` at a temperature [K], with the O2 factors of :func:`o2_factors`.

    Converts the literature units (C in mol/m3) to mole fractions with the ideal gas at 1 atm: C = y P / (R T).
    Three pairs share an activation energy (and so one exponential; each is [chosen] on what the data separate):
    N2O from NH3* + NO with standard SCR (the same surface step; fitted 1.3 kJ/mol apart when free), N2O from NH3
    oxidation with NH3 oxidation to NO (high-temperature oxidation over Cu oxide, a constant selectivity), and
    nitrate -> N2O with nitrate -> NH3 + HNO3 (2.4 kJ/mol apart in the lumped cats constants). The NO oxidation
    constant is given at the reference O2; its reverse follows from the equilibrium (:func:`no_oxidation_equilibrium`).
    The reactions of the SCR sites (standard SCR, its N2O route, the nitrate route) carry the ageing factor
    exp(L(T)), L the log-factor ``scr_log_factor_low`` at 200 C and ``scr_log_factor_high`` at 550 C, linear in 1/T
    between them and constant beyond (:data:`SCR_FACTOR_ANCHORS_K`), added to their exponents.
    Returns the constants in the order of :data:`RATE_CONSTANT_NAMES`.
    """
    inv_rt = 1.0 / (_R * temperature_k)  # mol/J (one division, then products)
    c_total = _P_ATM * inv_rt  # mol/m3 at 1 atm
    k_ads = a_ads * c_total
    k_des = a_des * exp(-e_des * inv_rt)
    e_des_gamma = temkin_gamma * e_des * inv_rt
    s_t = (_U_LO - inv_rt) / (_U_LO - _U_HI)
    s_t = select(s_t > 0.0, select(s_t < 1.0, s_t, 1.0), 0.0)
    log_scr = scr_log_factor_low + (scr_log_factor_high - scr_log_factor_low) * s_t
    x_std = exp(log_scr - e_std * inv_rt) * c_total
    k_std = a_std * x_std * f_o2_std
    k_n2o = a_n2o * x_std * f_o2_ox
    k_ox = a_ox * exp(-e_ox * inv_rt) * f_o2_ox
    x_ox_no = exp(-e_ox_no * inv_rt) * f_o2_ox
    k_ox_no = a_ox_no * x_ox_no
    k_ox_n2o = a_ox_n2o * x_ox_no
    # forward at the reference O2 times (y_O2 / y_ref)^1/2; reverse k_fwd / (K_p sqrt(y_ref)), folded into one exp
    k_no_ox_ref = a_no_ox * c_total
    k_no_ox = k_no_ox_ref * exp(-e_no_ox * inv_rt) * f_o2_half
    k_no2_red = (k_no_ox_ref * inv_sqrt_o2_reference
                 * exp(-NO_OXIDATION_DS_J_MOL_K / _R - (e_no_ox - NO_OXIDATION_DH_J_MOL) * inv_rt))
    k_an = a_an * exp(log_scr - e_an * inv_rt) * c_total
    k_an_no = a_an_no * exp(log_scr - e_an_no * inv_rt) * c_total
    x_dec = exp(log_scr - e_an_dec * inv_rt)
    k_an_dec = a_an_dec * x_dec
    k_an_n2o = a_an_n2o * x_dec
    return (k_ads, k_des, e_des_gamma, k_std, k_n2o, k_ox, k_ox_no, k_ox_n2o, k_no_ox, k_no2_red, k_an, k_an_no,
            k_an_dec, k_an_n2o)


def rate_constants(temperature_k, o2_fraction, a_ads, a_des, e_des, temkin_gamma, a_std, e_std, a_n2o, a_ox, e_ox,
                   a_ox_no, e_ox_no, a_ox_n2o, a_no_ox, e_no_ox, a_an, e_an, a_an_no, e_an_no, a_an_dec, e_an_dec,
                   a_an_n2o, scr_log_factor_low, scr_log_factor_high, o2_reference_fraction, o2_order_std,
                   o2_order_ox):
    """:func:`arrhenius_constants` at an O2 mole fraction [-] (the argument order of the packed parameters)."""
    f_std, f_ox, f_half = o2_factors(o2_fraction, o2_reference_fraction, o2_order_std, o2_order_ox)
    return arrhenius_constants(temperature_k, f_std, f_ox, f_half, 1.0 / sqrt(o2_reference_fraction), a_ads, a_des,
                               e_des, temkin_gamma, a_std, e_std, a_n2o, a_ox, e_ox, a_ox_no, e_ox_no, a_ox_n2o,
                               a_no_ox, e_no_ox, a_an, e_an, a_an_no, e_an_no, a_an_dec, e_an_dec, a_an_n2o,
                               scr_log_factor_low, scr_log_factor_high)


def decomposition_efficiency(temperature_k, t50_k, width_k):
    """Fraction [-] of the injected urea that has decomposed to NH3 (thermolysis + HNCO hydrolysis) at the SCR inlet
    temperature [K]: a logistic curve, 50 % at ``t50_k`` (PHYSICS.md section 3; the curve shape is [chosen])."""
    return 1.0 / (1.0 + exp(-(temperature_k - t50_k) / width_k))
