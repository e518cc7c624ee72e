"""The compiled plant step: urea decomposition, the multi-cell catalyst and the sensors, for a batch of catalysts.

One function, :func:`plant_step`, advances B independent plants by one control interval. The single environment
calls it with B = 1, the vector environment with B = num_envs; there is no other copy of the physics. The chemistry
of a cell comes from :mod:`scr_env.physics.cell` (compiled by :mod:`scr_env.physics.backends`).

Integration (per step of length dt, inputs held):

* solid temperature of each cell: implicit Euler of the linear heat balance
  ``C dT/dt = G (T_gas_in - T) - L (T - T_amb)`` with ``G = m cp (1 - exp(-NTU))`` (gas leaves a cell at
  ``T + (T_gas_in - T) exp(-NTU)``); cells in flow order, so the whole step is implicit and unconditionally stable;
* NH3 coverage of each cell: implicit Euler ``theta+ = theta + dt g(theta+)`` of :func:`cell_state`, solved by a
  Newton iteration safeguarded by the bracket [0, 1] (g(0) >= 0 and g(1) <= 0, so the root exists and coverage stays
  in [0, 1] by construction), at the end-of-step temperature, cells in flow order (implicit Euler of the
  block-triangular system). The iteration stops at theta* once the residual is below 1e-7 of the cell's nitrogen
  flux, and the step ends at theta+ = theta + dt g(theta*) with the outlets and rates of theta*: the stored NH3
  changes by exactly what the rates remove or add, so nitrogen is conserved to rounding in every step, whatever the
  tolerance (theta+ differs from theta* by dt times the residual, far below the O(dt) error of implicit Euler).

Array layouts (float64, C-contiguous):

* ``theta``, ``temperature_k``: (B, N) states, updated in place;
* ``sensor_state``: (B, N_SENSOR_STATES) lag states of the sensors, updated in place;
* ``inputs``: (B, N_INPUTS) held over the step, columns :data:`INPUT_FIELDS`;
* ``cat_params``: (B, len(PACKED_FIELDS)) from :func:`scr_env.params.pack`;
* ``aux_params``: (B, N_AUX) dosing and sensor parameters from :func:`pack_aux`;
* ``noise``: (B, N_NOISE) standard-normal draws for this step (the caller owns the random generator);
* ``out``: (B, N_OUTPUTS) written, columns :data:`OUTPUT_FIELDS`.
"""
from __future__ import annotations

import math

import numba
import numpy as np

from scr_env.constants import NH3_MOL_PER_G_ADBLUE
from scr_env.jit import njit
from scr_env.params import PACKED_FIELDS, DosingParams, P, SensorParams
from scr_env.physics.backends import (
    FASTMATH,
    arrhenius_constants_nb,
    cell_outlets_nb,
    cell_slope_nb,
    cell_state_nb,
    cell_temperature_step_nb,
    gas_solid_exchange_nb,
    inlet_conditions_nb,
    o2_factors_nb,
)
from scr_env.physics.dosing import MIN_FLOW_PER_SITE_1_S
from scr_env.physics.thermal import EXHAUST_MOLAR_HEAT_CAPACITY_J_MOL_K

INPUT_FIELDS = (
    "exhaust_flow_mol_s",  # mol/s
    "inlet_temperature_k",  # K, SCR inlet gas
    "inlet_nox_ppm",  # ppm (mole), NO + NO2
    "inlet_no2_fraction",  # -, NO2 / NOx
    "adblue_g_s",  # g/s AdBlue injected
    "o2_fraction",  # -, O2 mole fraction
)
I_FLOW, I_TIN, I_NOX, I_NO2F, I_ADBLUE, I_O2 = range(len(INPUT_FIELDS))

OUTPUT_FIELDS = (
    "tailpipe_no_ppm",
    "tailpipe_no2_ppm",
    "tailpipe_nh3_ppm",
    "tailpipe_n2o_ppm",
    "n2_formed_mol_s",  # mol N2 / s formed in the step (rates at the end of the step)
    "nh3_injected_mol_s",  # mol NH3 / s reaching the catalyst (decomposed urea)
    "urea_undecomposed_n_mol_s",  # mol N / s of urea not decomposed (deposit / HNCO, leaves the N balance)
    "outlet_temperature_k",
    "nh3_stored_mol",  # mol NH3 on the brick at the end of the step
    "mean_coverage",  # -
    "nox_sensor_ppm",  # tailpipe NOx sensor reading (cross-sensitive to NH3, lagged, noisy)
    "nh3_sensor_ppm",  # tailpipe NH3 sensor reading (lagged, noisy)
    "inlet_temperature_sensor_k",
    "upstream_nox_sensor_ppm",
    "exhaust_flow_estimate_mol_s",
)
(O_NO, O_NO2, O_NH3, O_N2O, O_N2, O_NH3_INJ, O_UREA_N, O_TOUT, O_STORED, O_COV, O_NOX_SENSOR, O_NH3_SENSOR,
 O_TIN_SENSOR, O_UPSTREAM_NOX, O_FLOW_EST) = range(len(OUTPUT_FIELDS))

N_SENSOR_STATES = 3  # lag states: tailpipe NOx sensor, NH3 sensor, inlet thermocouple
N_NOISE = 5  # draws per step: NOx sensor, NH3 sensor, thermocouple, upstream NOx, flow estimate

AUX_FIELDS = (
    "max_rate_g_s", "decomposition_t50_k", "decomposition_width_k",
    "nox_sensor_no2_gain", "nox_sensor_nh3_gain", "nox_sensor_time_constant_s", "nox_sensor_noise_ppm",
    "upstream_nox_noise_ppm", "temperature_time_constant_s", "temperature_noise_k", "flow_noise_fraction",
    "nh3_sensor_time_constant_s", "nh3_sensor_noise_ppm",
)
N_AUX = len(AUX_FIELDS)
(X_MAX_RATE, X_DECOMPOSITION_T50, X_DECOMPOSITION_WIDTH, X_NOX_NO2_GAIN, X_NOX_NH3_GAIN, X_NOX_TAU, X_NOX_NOISE,
 X_UPSTREAM_NOX_NOISE, X_TEMPERATURE_TAU, X_TEMPERATURE_NOISE, X_FLOW_NOISE, X_NH3_TAU, X_NH3_NOISE) = range(N_AUX)
N_PACKED = len(PACKED_FIELDS)  # columns of the packed catalyst parameters (scr_env.params.pack)
# the packed columns the non-chemistry parts of the step read, by name (scr_env.params.P)
_P_SITES = P["sites_per_cell_mol"]
_P_HEAT_CAPACITY = P["heat_capacity_per_cell_j_k"]
_P_UA = P["gas_solid_ua_per_cell_w_k"]
_P_LOSS = P["ambient_loss_per_cell_w_k"]
_P_AMBIENT = P["ambient_temperature_k"]

# The implicit solve stops when its residual, a flux per site [1/s], is below _FLUX_TOL times the net nitrogen flux
# of the cell (fed and stored) plus _GROSS_TOL times its gross adsorption flux (y_nh3 (q + k_ads) bounds adsorption
# and desorption, which nearly cancel in a hot cell, where d residual / d theta reaches 1e6 1/s). In a time step the
# end state is then corrected to theta + dt g(theta*) (module docstring), so the tolerances set only how exactly the
# rates belong to the end state, not the nitrogen balance, which closes to rounding. Measured with
# tests/scr_env/test_casadi_model.py's 50 random states (dt 0.05-5 s) against CasADi's exact implicit step: coverage
# within 4e-7, outlet concentrations within 1.3e-6 relative (with the NO2 chemistry of #20 and its 2.5 times smaller
# storage capacity per volume, a dumping hot cell feeding a cold one needed _GROSS_TOL 3e-11 for the same agreement;
# no change in the evaluations on WHTC states); on the WHTC the tailpipe NOx changes by 1e-8 relative and the
# chemistry evaluations per cell and step drop from 3.0 (tolerance 1e-14) to 2.2 (2.5 with the NO2 chemistry). [chosen]
# Without a time step (steady state, inv_dt = 0) there is nothing to correct with: a tolerance of a few tens of ulps.
_FLUX_TOL = 1e-7  # - [chosen, see above]
_GROSS_TOL = 3e-11  # - [chosen, see above]
_STEADY_FLUX_TOL = 1e-14  # - [chosen: a few tens of ulps, above the rounding floor of the residual]
_BRACKET_TOL = 4.0 * 2.220446049250313e-16  # relative width of a collapsed bracket (a few ulps of theta) [-]
_NEWTON_MAX_IT = 100
_MIN_Q = MIN_FLOW_PER_SITE_1_S  # 1/s: floor of flow per site (scr_env.physics.dosing)
_EXP_CP = EXHAUST_MOLAR_HEAT_CAPACITY_J_MOL_K  # J/(mol K) of exhaust (scr_env.physics.thermal)
_NH3_PER_G = NH3_MOL_PER_G_ADBLUE
# packed kinetic parameters (scr_env.params.PACKED_FIELDS): the first, and the O2 reference and orders
_K0 = P["a_ads"]
_K_O2_REF = P["o2_reference_fraction"]
_K_O2_STD = P["o2_order_std"]
_K_O2_OX = P["o2_order_ox"]


def pack_aux(dosing: DosingParams, sensors: SensorParams) -> np.ndarray:
    """Pack dosing and sensor parameters in the order of :data:`AUX_FIELDS`."""
    values = {**{k: getattr(dosing, k) for k in AUX_FIELDS[:X_NOX_NO2_GAIN]},
              **{k: getattr(sensors, k) for k in AUX_FIELDS[X_NOX_NO2_GAIN:]}}
    return np.array([values[k] for k in AUX_FIELDS], dtype=np.float64)


@njit(nogil=True, error_model="numpy", fastmath=set(FASTMATH), inline="always")
def solve_coverage(theta_old, inv_dt, q, y_nh3_in, y_no_in, y_no2_in, k):
    """Root in [0, 1] of R(theta) = (theta - theta_old) inv_dt - g(theta), and :func:`cell_state` there.

    ``k`` is the tuple of per-site rate constants (:data:`scr_env.physics.cell.RATE_CONSTANT_NAMES`).
    inv_dt = 1/dt gives the implicit Euler step; inv_dt = 0 gives the steady state. R(0) <= 0 <= R(1) always,
    so a Newton iteration kept inside a shrinking bracket always converges. Returns (theta_end, th, cell_state(th))
    at the accepted iterate th: for inv_dt > 0, theta_end = theta_old + g(th) / inv_dt (the conservative end state
    of the module docstring), for inv_dt = 0, theta_end = th. The outlets belong to th (:func:`cell_outlets`).
    """
    k_ads = k[0]
    lo = 0.0
    hi = 1.0
    th = min(max(theta_old, 0.0), 1.0)
    inflow = q * (y_nh3_in + y_no_in + y_no2_in) + theta_old * inv_dt  # N fed to the cell per site [1/s]
    # One call site of cell_state (so the compiler inlines it): a bracket collapse or the iteration limit marks
    # th as final, and the next pass only evaluates there.
    final = False
    it = 0
    stepping = inv_dt > 0.0
    net_tol = _FLUX_TOL if stepping else _STEADY_FLUX_TOL
    gross_tol = _GROSS_TOL if stepping else _STEADY_FLUX_TOL
    while True:
        r = cell_state_nb(th, q, y_nh3_in, y_no_in, y_no2_in, k[0], k[1], k[2], k[3], k[4], k[5], k[6], k[7], k[8],
                          k[9], k[10], k[11], k[12], k[13])
        res = (th - theta_old) * inv_dt - r[0]
        # converged when the residual flux is negligible against the N fluxes of the cell (net: fed and stored;
        # gross: r[1] (q + k_ads) bounds the adsorption and desorption rates); the outputs r belong to this theta
        if final or abs(res) <= net_tol * (inflow + th * inv_dt) + gross_tol * r[1] * (q + k_ads):
            if stepping:
                # conservative end state theta_old + dt g(th) = th - res dt (module docstring), kept in [0, 1]
                end = th - res / inv_dt
                if 0.0 <= end <= 1.0:
                    return end, th, r
                if final:
                    return min(max(end, 0.0), 1.0), th, r
            else:
                return th, th, r
        # the slope only where a Newton step is taken (the accepted state does not need it)
        d_res = inv_dt - cell_slope_nb(th, q, k[0], k[1], k[2], k[3], k[4], k[5], k[6], k[7], k[8], k[9], k[10],
                                       k[11], k[12], k[13], r[1], r[3], r[4], r[5])
        if res > 0.0:
            hi = th
        else:
            lo = th
        new = th - res / d_res if d_res > 0.0 else -1.0
        if not (lo <= new <= hi):
            new = 0.5 * (lo + hi)
        if hi - lo <= _BRACKET_TOL * hi:
            new = 0.5 * (lo + hi)
            final = True
        it += 1
        if it == _NEWTON_MAX_IT:
            final = True
        th = new


# The per-plant code indexes the (B, ...) arrays with [b, j] instead of taking row views, and is compiled without
# reference counting (``_nrt=False``: it allocates nothing, the caller holds the arrays). Each view or array
# argument otherwise costs two atomic updates of the reference count of the one buffer shared by all plants, which
# made the threads of the parallel loop fight over one cache line (measured: a fifth of the serial step time went
# to NRT_incref/NRT_decref, and the parallel step scaled far below 2x on 2 cores).
_NO_REFCOUNT = {"nogil": True, "error_model": "numpy", "fastmath": set(FASTMATH), "_nrt": False}


@njit(nogil=True, error_model="numpy", fastmath=set(FASTMATH), inline="always")
def _chemistry_row(theta, temperature_k, b, q, y_nh3_in, y_no_in, y_no2_in, o2_fraction, inv_dt, p):
    """:func:`catalyst_chemistry` of row ``b`` of (B, N) states and (B, len(PACKED_FIELDS)) parameters."""
    n = theta.shape[1]
    y_nh3 = y_nh3_in
    y_no = y_no_in
    y_no2 = y_no2_in
    y_n2o = 0.0
    n2_per_site = 0.0
    o2_ref = p[b, _K_O2_REF]
    if o2_fraction == o2_ref and 0.0 < o2_fraction < math.inf:
        # O2 at the lab reference (the environments' O2_FRACTION): o2_factors gives exactly 1, 1, 1 (log(1) = 0,
        # exp(0) = 1); skipping its log and three exps saves transcendental calls of a plant step
        f_std = 1.0
        f_ox = 1.0
        f_half = 1.0
    else:
        f_std, f_ox, f_half = o2_factors_nb(o2_fraction, o2_ref, p[b, _K_O2_STD], p[b, _K_O2_OX])
    k0 = _K0
    inv_sqrt_ref = 1.0 / math.sqrt(o2_ref)
    for j in range(n):
        k = arrhenius_constants_nb(
            temperature_k[b, j], f_std, f_ox, f_half, inv_sqrt_ref, p[b, k0], p[b, k0 + 1], p[b, k0 + 2],
            p[b, k0 + 3], p[b, k0 + 4], p[b, k0 + 5], p[b, k0 + 6], p[b, k0 + 7], p[b, k0 + 8], p[b, k0 + 9],
            p[b, k0 + 10], p[b, k0 + 11], p[b, k0 + 12], p[b, k0 + 13], p[b, k0 + 14], p[b, k0 + 15],
            p[b, k0 + 16], p[b, k0 + 17], p[b, k0 + 18], p[b, k0 + 19], p[b, k0 + 20], p[b, k0 + 21],
            p[b, k0 + 22])
        end, th, r = solve_coverage(theta[b, j], inv_dt, q, y_nh3, y_no, y_no2, k)
        theta[b, j] = end
        y_nh3 = r[1]
        # outlets with the rates of the accepted iterate th (the end state differs from it by dt times the residual)
        y_no, y_no2, n2o_per_site, n2_cell = cell_outlets_nb(th, q, k[3], k[4], k[5], k[6], k[7], k[8], k[9], k[10],
                                                              k[11], k[12], k[13], r[3], r[4])
        y_n2o += n2o_per_site / q
        n2_per_site += n2_cell
    return y_no, y_no2, y_nh3, y_n2o, n2_per_site


@njit(nogil=True, error_model="numpy", fastmath=set(FASTMATH))
def catalyst_chemistry(theta, temperature_k, q, y_nh3_in, y_no_in, y_no2_in, o2_fraction, inv_dt, p):
    """Advance the coverage of every cell (in place) at given cell temperatures.

    ``theta``, ``temperature_k``: (N,) per cell; ``p``: packed catalyst parameters.
    Returns (y_no, y_no2, y_nh3, y_n2o at the outlet [-], N2 formed per site and second summed over cells [1/s]).
    """
    return _chemistry_row(theta[np.newaxis, :], temperature_k[np.newaxis, :], 0, q, y_nh3_in, y_no_in, y_no2_in,
                          o2_fraction, inv_dt, p[np.newaxis, :])


@njit(nogil=True, error_model="numpy", fastmath=set(FASTMATH), inline="always")
def _plant_step_one(b, theta, temperature_k, sensor_state, inputs, dt, cat_params, aux_params, noise, out):
    n = theta.shape[1]
    sites = cat_params[b, _P_SITES]
    flow = inputs[b, I_FLOW]
    t_in = inputs[b, I_TIN]

    # --- thermal: implicit Euler per cell in flow order (scr_env.physics.thermal) --------------------------------
    coupling, decay = gas_solid_exchange_nb(flow, cat_params[b, _P_UA])
    heat_cap = cat_params[b, _P_HEAT_CAPACITY]
    loss = cat_params[b, _P_LOSS]
    t_amb = cat_params[b, _P_AMBIENT]
    t_gas = t_in
    for j in range(n):
        t_new, t_gas = cell_temperature_step_nb(temperature_k[b, j], t_gas, heat_cap, coupling, loss, t_amb, dt,
                                                decay)
        temperature_k[b, j] = t_new

    # --- urea decomposition upstream of the brick, gas at the catalyst face (scr_env.physics.dosing) --------------
    q, y_nh3_in, y_no_in, y_no2_in, nh3_mol_s, urea_n_mol_s = inlet_conditions_nb(
        flow, t_in, inputs[b, I_NOX], inputs[b, I_NO2F], inputs[b, I_ADBLUE], aux_params[b, X_MAX_RATE],
        aux_params[b, X_DECOMPOSITION_T50], aux_params[b, X_DECOMPOSITION_WIDTH], sites)

    # --- chemistry --------------------------------------------------------------------------------------------
    y_no, y_no2, y_nh3, y_n2o, n2_per_site = _chemistry_row(
        theta, temperature_k, b, q, y_nh3_in, y_no_in, y_no2_in, inputs[b, I_O2], 1.0 / dt, cat_params)
    no_ppm = y_no * 1e6
    no2_ppm = y_no2 * 1e6
    nh3_ppm = y_nh3 * 1e6
    out[b, O_NO] = no_ppm
    out[b, O_NO2] = no2_ppm
    out[b, O_NH3] = nh3_ppm
    out[b, O_N2O] = y_n2o * 1e6
    out[b, O_N2] = n2_per_site * sites
    out[b, O_NH3_INJ] = nh3_mol_s
    out[b, O_UREA_N] = urea_n_mol_s
    out[b, O_TOUT] = t_gas
    cov = 0.0
    for j in range(n):
        cov += theta[b, j]
    out[b, O_STORED] = cov * sites
    out[b, O_COV] = cov / n

    # --- sensors: first-order lags (exact discretisation) plus additive noise ------------------------------------
    raw_nox = no_ppm + aux_params[b, X_NOX_NO2_GAIN] * no2_ppm + aux_params[b, X_NOX_NH3_GAIN] * nh3_ppm
    s0 = sensor_state[b, 0]
    s0 += (1.0 - math.exp(-dt / max(aux_params[b, X_NOX_TAU], 1e-9))) * (raw_nox - s0)
    s1 = sensor_state[b, 1]
    s1 += (1.0 - math.exp(-dt / max(aux_params[b, X_NH3_TAU], 1e-9))) * (nh3_ppm - s1)
    s2 = sensor_state[b, 2]
    s2 += (1.0 - math.exp(-dt / max(aux_params[b, X_TEMPERATURE_TAU], 1e-9))) * (t_in - s2)
    sensor_state[b, 0] = s0
    sensor_state[b, 1] = s1
    sensor_state[b, 2] = s2
    out[b, O_NOX_SENSOR] = max(s0 + aux_params[b, X_NOX_NOISE] * noise[b, 0], 0.0)
    out[b, O_NH3_SENSOR] = max(s1 + aux_params[b, X_NH3_NOISE] * noise[b, 1], 0.0)
    out[b, O_TIN_SENSOR] = s2 + aux_params[b, X_TEMPERATURE_NOISE] * noise[b, 2]
    out[b, O_UPSTREAM_NOX] = max(inputs[b, I_NOX] + aux_params[b, X_UPSTREAM_NOX_NOISE] * noise[b, 3], 0.0)
    out[b, O_FLOW_EST] = max(flow * (1.0 + aux_params[b, X_FLOW_NOISE] * noise[b, 4]), 0.0)


@njit(**_NO_REFCOUNT)
def _plant_step_b(b, theta, temperature_k, sensor_state, inputs, dt, cat_params, aux_params, noise, out):
    _plant_step_one(b, theta, temperature_k, sensor_state, inputs, dt, cat_params, aux_params, noise, out)


@njit(nogil=True, error_model="numpy", fastmath=set(FASTMATH))
def _plant_step_serial(theta, temperature_k, sensor_state, inputs, dt, cat_params, aux_params, noise, out):
    for b in range(theta.shape[0]):
        _plant_step_b(b, theta, temperature_k, sensor_state, inputs, dt, cat_params, aux_params, noise, out)


@njit(nogil=True, error_model="numpy", fastmath=set(FASTMATH), parallel=True)
def _plant_step_parallel(theta, temperature_k, sensor_state, inputs, dt, cat_params, aux_params, noise, out):
    for b in numba.prange(theta.shape[0]):
        _plant_step_b(np.int64(b), theta, temperature_k, sensor_state, inputs, dt, cat_params, aux_params, noise, out)


# fastmath=False on purpose: the MPC's temperature forecasts (control.models.FirstPrinciplesModel) were computed
# without the fast-math flags before the heat balance had one source, and keeping them so keeps the oracle's closed
# loop bit for bit; they differ from the plant's fast-math step by rounding only (1e-11 K over a WHTC).
@njit(nogil=True, error_model="numpy", fastmath=False)
def thermal_trajectory(temperature_k: np.ndarray, flow_mol_s: np.ndarray, inlet_temperature_k: np.ndarray,
                       cat_params: np.ndarray, dt: float) -> np.ndarray:
    """Solid temperatures [K] of the cells after each of ``len(flow_mol_s)`` steps of ``dt`` seconds (rows), from
    ``temperature_k`` (N,) under the given exhaust flow [mol/s] and SCR inlet temperature [K] per step: the plant's
    heat balance (:func:`scr_env.physics.thermal.cell_temperature_step`, cells in flow order) on its own, for
    forecasts. The temperatures do not depend on the dosing. ``cat_params``: one packed catalyst
    (:func:`scr_env.params.pack`)."""
    n = temperature_k.size
    heat_cap = cat_params[_P_HEAT_CAPACITY]
    ua = cat_params[_P_UA]
    loss = cat_params[_P_LOSS]
    t_amb = cat_params[_P_AMBIENT]
    out = np.empty((flow_mol_s.size, n))
    t = temperature_k.copy()
    for k in range(flow_mol_s.size):
        coupling, decay = gas_solid_exchange_nb(flow_mol_s[k], ua)
        t_gas = inlet_temperature_k[k]
        for j in range(n):
            t_new, t_gas = cell_temperature_step_nb(t[j], t_gas, heat_cap, coupling, loss, t_amb, dt, decay)
            t[j] = t_new
        out[k] = t
    return out


PARALLEL_MIN_BATCH = 64  # below this, thread start-up costs more than it saves


def plant_step(theta: np.ndarray, temperature_k: np.ndarray, sensor_state: np.ndarray, inputs: np.ndarray, dt: float,
               cat_params: np.ndarray, aux_params: np.ndarray, noise: np.ndarray, out: np.ndarray) -> None:
    """Advance B plants by ``dt`` seconds in place (layouts in the module docstring). No validation here: the
    environments validate their inputs once; see :func:`scr_env.physics.simulate.step` for a checked wrapper."""
    if theta.shape[0] >= PARALLEL_MIN_BATCH:
        _plant_step_parallel(theta, temperature_k, sensor_state, inputs, dt, cat_params, aux_params, noise, out)
    else:
        _plant_step_serial(theta, temperature_k, sensor_state, inputs, dt, cat_params, aux_params, noise, out)
