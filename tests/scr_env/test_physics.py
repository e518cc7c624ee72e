"""Properties of the compiled plant step (scr_env.physics.kernel): coverage bounds, finite outlets, nitrogen balance.

The nitrogen balance of a step (PHYSICS.md section 2), all in mol over the step:

    N in  = (NO + NO2 inlet flow + NH3 reaching the catalyst) dt
    N out = (tailpipe NO + NO2 + NH3 + 2 N2O) dt + 2 N2 formed dt + change of the stored NH3

Its error is measured against the gross nitrogen turnover of the step (N in + N out + the sum over cells of
|change of stored NH3|): a hot, over-loaded cell can release and the next cell re-adsorb far more NH3 inside one
step than crosses the brick's faces, and the rounding floor of the balance scales with those internal flows.
The stored amount is a sum of ~mol-sized numbers, so its change is known to a few ulps of the stored total only;
that floor is added to the tolerance.
"""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from scr_env.params import CatalystParams, DosingParams, SensorParams, pack
from scr_env.physics import kernel as K

PARAMS = CatalystParams()
N = PARAMS.n_cells
CAT = pack(PARAMS)[None, :]
AUX = K.pack_aux(DosingParams(), SensorParams().noiseless())[None, :]
SITES = CAT[0, 1]  # mol per cell
EPS = np.finfo(float).eps
# Absolute floor of the balance [mol]: when a coverage is within a few ulps of the smallest normal float, the rates,
# outlets and N2 are subnormal, where IEEE arithmetic has no relative accuracy left (a coverage near 0 is resolved
# to 2**-1074 only, and the implicit residual multiplies that by the cell's stiffness, up to ~1e6 1/s, and SITES).
# 1e-300 mol (6e-277 molecules) only ignores that; e.g. theta = [0, 0, 0, 0, 2.2e-308] at 400 K leaves 6.5e-320.
SUBNORMAL_FLOOR_MOL = 1e-300
O = {name: i for i, name in enumerate(K.OUTPUT_FIELDS)}


def _step(theta: np.ndarray, temps: np.ndarray, inputs: np.ndarray, dt: float) -> tuple[np.ndarray, ...]:
    """One plant step (B = 1, no noise) on copies; returns (theta+, T+, outputs)."""
    th = np.array(theta, dtype=float)[None, :].copy()
    tk = np.array(temps, dtype=float)[None, :].copy()
    out = np.zeros((1, len(K.OUTPUT_FIELDS)))
    K.plant_step(th, tk, np.zeros((1, K.N_SENSOR_STATES)), np.array(inputs, dtype=float)[None, :], dt, CAT, AUX,
                 np.zeros((1, K.N_NOISE)), out)
    return th[0], tk[0], out[0]


def _nitrogen_mol(inputs: np.ndarray, out: np.ndarray, dt: float) -> tuple[float, float]:
    """(N in, N out through the faces and to N2) over the step [mol]."""
    flow = inputs[K.I_FLOW]
    n_in = (inputs[K.I_NOX] * 1e-6 * flow + out[O["nh3_injected_mol_s"]]) * dt
    tail_ppm = (out[O["tailpipe_no_ppm"]] + out[O["tailpipe_no2_ppm"]] + out[O["tailpipe_nh3_ppm"]]
                + 2.0 * out[O["tailpipe_n2o_ppm"]])
    n_out = (tail_ppm * 1e-6 * flow + 2.0 * out[O["n2_formed_mol_s"]]) * dt
    return n_in, n_out


def _floats(lo: float, hi: float) -> st.SearchStrategy[float]:
    return st.floats(lo, hi, allow_subnormal=False)  # subnormal inputs only test IEEE arithmetic


coverages = st.lists(_floats(0.0, 1.0), min_size=N, max_size=N)
temperatures = st.lists(_floats(400.0, 850.0), min_size=N, max_size=N)
step_inputs = st.tuples(
    _floats(0.5, 20.0),  # exhaust flow [mol/s]
    _floats(420.0, 800.0),  # inlet temperature [K]
    _floats(0.0, 3000.0),  # inlet NOx [ppm]
    _floats(0.0, 0.7),  # NO2 / NOx [-]
    _floats(0.0, 3.0),  # AdBlue [g/s]
    _floats(0.02, 0.15),  # O2 [-]
)
dts = _floats(0.05, 5.0)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(theta=coverages, temps=temperatures, u=step_inputs, dt=dts)
def test_step_keeps_coverage_bounded_outlets_finite_and_conserves_nitrogen(theta, temps, u, dt):
    inputs = np.array(u)
    th_new, t_new, out = _step(theta, temps, inputs, dt)

    assert np.all((th_new >= 0.0) & (th_new <= 1.0))
    assert np.all(np.isfinite(t_new))
    tail = out[[O["tailpipe_no_ppm"], O["tailpipe_no2_ppm"], O["tailpipe_nh3_ppm"], O["tailpipe_n2o_ppm"]]]
    assert np.all(np.isfinite(tail)) and np.all(tail >= 0.0)
    assert np.isfinite(out[O["n2_formed_mol_s"]]) and out[O["n2_formed_mol_s"]] >= 0.0

    stored_before = float(np.sum(theta)) * SITES
    stored_after = out[O["nh3_stored_mol"]]
    n_in, n_out = _nitrogen_mol(inputs, out, dt)
    imbalance = n_in - n_out - (stored_after - stored_before)
    gross = n_in + n_out + SITES * float(np.abs(th_new - np.asarray(theta)).sum())
    assert abs(imbalance) <= 1e-9 * gross + 16 * EPS * (stored_before + stored_after) + SUBNORMAL_FLOOR_MOL, \
        (imbalance, gross)


@settings(max_examples=60, deadline=None)
@given(temps=temperatures, u=step_inputs, dt=dts)
def test_temperatures_stay_between_ambient_and_hottest_source(temps, u, dt):
    """Implicit Euler of a linear heat balance is monotone: no cell over- or undershoots its sources."""
    _, t_new, out = _step(np.zeros(N), temps, np.array(u), dt)
    lo = min(PARAMS.ambient_temperature_k, u[1], *temps)
    hi = max(u[1], *temps)
    assert np.all(t_new >= lo - 1e-9) and np.all(t_new <= hi + 1e-9)
    assert lo - 1e-9 <= out[O["outlet_temperature_k"]] <= hi + 1e-9


def test_hour_of_varying_inputs_closes_the_nitrogen_balance():
    """3600 steps of 1 s with randomly varying inputs: the cumulative balance closes to rounding (1e-12 relative)."""
    rng = np.random.default_rng(20240611)
    n_steps, dt = 3600, 1.0
    t = np.arange(n_steps) * dt
    flow = np.clip(6.0 + 4.0 * np.sin(2 * np.pi * t / 600.0) + rng.normal(0, 1.0, n_steps), 0.5, 20.0)
    t_in = 560.0 + 120.0 * np.sin(2 * np.pi * t / 1800.0) + rng.normal(0, 5.0, n_steps)
    nox = np.clip(800.0 + 600.0 * np.sin(2 * np.pi * t / 300.0) + rng.normal(0, 50.0, n_steps), 0.0, 3000.0)
    adblue = np.clip(rng.gamma(2.0, 0.25, n_steps), 0.0, 3.0)
    no2 = np.clip(0.3 + rng.normal(0, 0.05, n_steps), 0.0, 0.7)
    inputs = np.stack([flow, t_in, nox, no2, adblue, np.full(n_steps, 0.1)], axis=1)

    theta = np.zeros((1, N))
    temps = np.full((1, N), 500.0)
    sensors = np.zeros((1, K.N_SENSOR_STATES))
    out = np.zeros((1, len(K.OUTPUT_FIELDS)))
    noise = np.zeros((1, K.N_NOISE))
    total_in = total_out = 0.0
    for k in range(n_steps):
        K.plant_step(theta, temps, sensors, inputs[k][None, :].copy(), dt, CAT, AUX, noise, out)
        n_in, n_out = _nitrogen_mol(inputs[k], out[0], dt)
        total_in += n_in
        total_out += n_out
        assert 0.0 <= theta.min() and theta.max() <= 1.0
    stored = out[0, O["nh3_stored_mol"]]
    assert stored > 0.0  # the test exercises storage, not a trivially empty catalyst
    assert total_in > 1.0  # mol
    # the step ends on the conservative state (kernel module docstring): the balance closes to rounding (measured
    # 1e-15), not merely to the solver tolerance
    assert abs(total_in - total_out - stored) <= 1e-12 * total_in


@pytest.mark.parametrize("severity", [0.0, 1.0])
def test_zero_input_keeps_an_empty_catalyst_empty(severity):
    from scr_env.params import aged

    cat = pack(aged(PARAMS, severity))[None, :]
    th = np.zeros((1, N))
    tk = np.full((1, N), 600.0)
    out = np.zeros((1, len(K.OUTPUT_FIELDS)))
    K.plant_step(th, tk, np.zeros((1, K.N_SENSOR_STATES)), np.array([[5.0, 600.0, 0.0, 0.0, 0.0, 0.1]]), 1.0, cat,
                 AUX, np.zeros((1, K.N_NOISE)), out)
    assert np.all(th == 0.0)
    assert out[0, O["tailpipe_nh3_ppm"]] == 0.0 and out[0, O["n2_formed_mol_s"]] == 0.0


def test_numba_exp_bound_past_glibcs_wrapper_gives_math_exps_values() -> None:
    """The plant binds numba's exp to glibc's computation without its compatibility wrapper
    (scr_env.physics.libm): the same bits as Python's math.exp over the whole double range."""
    import math

    import numba

    from scr_env.physics import libm

    assert libm.bind_direct_exp() == (libm.direct_exp_address() is not None)

    @numba.njit(cache=False)
    def exp_all(x: np.ndarray, out: np.ndarray) -> None:
        for i in range(x.size):
            out[i] = math.exp(x[i])

    rng = np.random.default_rng(0)
    tiny = np.finfo(float).tiny
    x = np.concatenate([
        rng.uniform(-750.0, 720.0, 200_000),  # the whole range of finite, subnormal and zero results
        rng.standard_normal(100_000) * 20.0,  # the arguments of the plant (rate constants, Temkin factor)
        rng.integers(0, 2**64, 50_000, dtype=np.uint64).view(np.float64),  # any bit pattern
        [0.0, -0.0, np.inf, -np.inf, np.nan, 709.782712893384, 709.7827128933841, -708.3964185322641,
         -745.1332191019411, -745.1332191019412, 5e-324, -5e-324, tiny, -tiny, 1e-310]])
    got = np.empty_like(x)
    exp_all(x, got)

    def math_exp(v: float) -> float:
        try:
            return math.exp(v)
        except OverflowError:
            return math.inf

    expected = np.array([math_exp(v) for v in x.tolist()])
    nan = np.isnan(expected)
    np.testing.assert_array_equal(np.isnan(got), nan)
    np.testing.assert_array_equal(got[~nan].view(np.uint64), expected[~nan].view(np.uint64))
