"""The plant is written once: every backend of the heat balance, the dosing and the reward/KPIs computes the same.

* the one-source functions of ``scr_env.physics.thermal`` and ``scr_env.physics.dosing`` agree across plain Python,
  numba (the kernel's fast-math build), numpy and CasADi;
* the kernel's step, :func:`~scr_env.physics.kernel.thermal_trajectory` (the MPC's forecast) and the CasADi step
  integrate the same heat balance, also far from equilibrium (a cold brick under hot gas, no flow);
* the reward and KPIs of the plant and of a surrogate come from one definition (``scr_env.envs.kpis``);
* the single and the vector environment start an episode identically (one reset).
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np
import pytest

from scr_env.casadi_model import catalyst_step
from scr_env.cycles import load_cycle
from scr_env.envs import kpis as KP
from scr_env.envs.urea_scr import UreaSCREnv
from scr_env.envs.vector import UreaSCRVectorEnv
from scr_env.params import PACKED_FIELDS, CatalystParams, DosingParams, SensorParams, pack
from scr_env.physics import backends as B
from scr_env.physics import dosing, thermal
from scr_env.physics import kernel as K

CAT = pack(CatalystParams())
RNG = np.random.default_rng(20261124)


def _samples(n: int = 200) -> list[tuple[float, ...]]:
    """Thermal inputs: solid T, gas T [K], heat capacity [J/K], flow [mol/s] (zero included), dt [s]."""
    out = []
    for i in range(n):
        flow = 0.0 if i % 17 == 0 else RNG.uniform(0.05, 25.0)
        out.append((RNG.uniform(250.0, 900.0), RNG.uniform(250.0, 900.0), flow, RNG.choice([0.05, 0.5, 5.0])))
    return out


def _casadi(fn_name: str, n_in: int, n_out: int) -> ca.Function:
    f = getattr(B.casadi_namespace(), fn_name)
    x = ca.SX.sym("x", n_in)
    res = f(*[x[i] for i in range(n_in)])
    res = res if isinstance(res, tuple) else (res,)
    return ca.Function(fn_name, [x], [ca.vertcat(*res[:n_out])])


def test_thermal_backends_agree() -> None:
    heat_cap, ua, loss, t_amb = (CAT[K._P_HEAT_CAPACITY], CAT[K._P_UA], CAT[K._P_LOSS], CAT[K._P_AMBIENT])
    npns = B.numpy_namespace()
    f_step = _casadi("cell_temperature_step", 8, 2)
    f_exch = _casadi("gas_solid_exchange", 2, 2)
    for t_solid, t_gas, flow, dt in _samples():
        g, d = thermal.gas_solid_exchange(flow, ua)
        for other in (B.gas_solid_exchange_nb(flow, ua), npns.gas_solid_exchange(flow, ua),
                      tuple(np.asarray(f_exch([flow, ua])).ravel())):
            np.testing.assert_allclose(other, (g, d), rtol=1e-14, atol=0)
        ref = thermal.cell_temperature_step(t_solid, t_gas, heat_cap, g, loss, t_amb, dt, d)
        for other in (B.cell_temperature_step_nb(t_solid, t_gas, heat_cap, g, loss, t_amb, dt, d),
                      npns.cell_temperature_step(t_solid, t_gas, heat_cap, g, loss, t_amb, dt, d),
                      tuple(np.asarray(f_step([t_solid, t_gas, heat_cap, g, loss, t_amb, dt, d])).ravel())):
            np.testing.assert_allclose(other, ref, rtol=1e-14, atol=0)
        if flow == 0.0:  # no flow: no exchange, the gas leaves at the solid temperature
            assert g == 0.0 and d == 0.0 and ref[1] == pytest.approx(ref[0], rel=1e-15)


def test_heat_balance_is_the_implicit_euler_of_its_rate() -> None:
    """cell_temperature_step solves T+ = T + dt rate(T+) exactly, and rate matches PHYSICS.md's balance."""
    heat_cap, ua, loss, t_amb = (CAT[K._P_HEAT_CAPACITY], CAT[K._P_UA], CAT[K._P_LOSS], CAT[K._P_AMBIENT])
    for t_solid, t_gas, flow, dt in _samples(50):
        g, d = thermal.gas_solid_exchange(flow, ua)
        t_new, _ = thermal.cell_temperature_step(t_solid, t_gas, heat_cap, g, loss, t_amb, dt, d)
        rate = thermal.cell_temperature_rate(t_new, t_gas, heat_cap, g, loss, t_amb)
        assert t_new == pytest.approx(t_solid + dt * rate, rel=1e-13)
        mcp = flow * thermal.EXHAUST_MOLAR_HEAT_CAPACITY_J_MOL_K
        if mcp > 0:
            assert g == pytest.approx(mcp * (1 - math.exp(-ua / mcp)), rel=1e-14)


def test_dosing_backends_agree_and_clamp_the_dose() -> None:
    dose = DosingParams()
    npns = B.numpy_namespace()
    f = _casadi("inlet_conditions", 9, 6)
    sites = CAT[K._P_SITES]
    for i in range(200):
        args = (0.0 if i % 23 == 0 else RNG.uniform(0.1, 20.0), RNG.uniform(300.0, 800.0), RNG.uniform(0.0, 2500.0),
                RNG.uniform(0.0, 0.7), RNG.uniform(-1.0, 4.0), dose.max_rate_g_s, dose.decomposition_t50_k,
                dose.decomposition_width_k, sites)
        ref = dosing.inlet_conditions(*args)
        for other in (B.inlet_conditions_nb(*args), npns.inlet_conditions(*args), np.asarray(f(args)).ravel()):
            np.testing.assert_allclose(np.asarray(other, dtype=float), ref, rtol=1e-13, atol=0)
        injected = min(max(args[4], 0.0), dose.max_rate_g_s)
        nh3, urea_n = ref[4], ref[5]
        assert nh3 + urea_n == pytest.approx(injected * dosing.NH3_MOL_PER_G_ADBLUE, rel=1e-12, abs=1e-300)
        assert ref[0] >= dosing.MIN_FLOW_PER_SITE_1_S and all(math.isfinite(v) for v in ref)


def test_numpy_backend_broadcasts_over_a_horizon() -> None:
    """control.models prepares a whole MPC horizon at once: arrays in, arrays out, equal to the scalar calls."""
    flow = np.array([0.0, 1.5, 8.0, 17.0])
    t_in = np.array([420.0, 460.0, 600.0, 700.0])
    nox = np.array([100.0, 800.0, 1200.0, 2000.0])
    no2 = np.array([0.1, 0.2, 0.3, 0.4])
    rows = B.numpy_namespace().inlet_conditions(flow, t_in, nox, no2, 1.0, np.inf, 453.15, 10.0, CAT[K._P_SITES])
    for k in range(4):
        ref = dosing.inlet_conditions(flow[k], t_in[k], nox[k], no2[k], 1.0, np.inf, 453.15, 10.0, CAT[K._P_SITES])
        np.testing.assert_allclose([r[k] for r in rows], ref, rtol=1e-15)


def _kernel_step(theta, temps, u, dt):
    theta, temps = theta[None, :].copy(), temps[None, :].copy()
    out = np.zeros((1, len(K.OUTPUT_FIELDS)))
    aux = K.pack_aux(DosingParams(), SensorParams().noiseless())
    K.plant_step(theta, temps, np.zeros((1, K.N_SENSOR_STATES)), u[None, :].copy(), dt, CAT[None, :], aux[None, :],
                 np.zeros((1, K.N_NOISE)), out)
    return theta[0], temps[0], out[0]


def test_casadi_and_kernel_agree_on_a_cold_start_under_hot_gas() -> None:
    """Inlet gas and brick far apart: a brick at 298 K under 650 K gas for 80 s, then 480 K gas (the brick now
    hotter than the gas at its inlet), at the flows and NOx of the cold WHTC's first 120 s, with dosing, a stretch
    without flow, and a gradient along the cells; CasADi's step and the kernel's."""
    trace = load_cycle("whtc", cold_start=True)
    dt = 0.5
    n = CatalystParams().n_cells
    step = catalyst_step(CatalystParams(), dt)
    theta_k, temps_k = np.zeros(n), np.full(n, 298.15)
    x_c = np.concatenate([theta_k, temps_k])
    gaps = []
    for k in range(240):
        flow = 0.0 if 100 <= k < 110 else trace.exhaust_flow_mol_s[k]
        u = np.array([flow, 650.0 if k < 160 else 480.0, trace.nox_ppm[k], trace.no2_fraction[k],
                      0.4 if k % 40 < 20 else 0.0, 0.1])
        theta_k, temps_k, out = _kernel_step(theta_k, temps_k, u, dt)
        x_next, y = (np.asarray(v).ravel() for v in step(x_c, u))
        x_c = x_next
        gaps.append(abs(u[1] - temps_k[0]))
        np.testing.assert_allclose(x_c[n:], temps_k, rtol=0, atol=1e-9)  # K
        np.testing.assert_allclose(x_c[:n], theta_k, rtol=0, atol=1e-6)
        assert y[4] == pytest.approx(out[K.O_TOUT], abs=1e-9)
        np.testing.assert_allclose(y[:4], out[[K.O_NO, K.O_NO2, K.O_NH3, K.O_N2O]], rtol=1e-5, atol=1e-6)
    assert max(gaps) > 300.0  # the case this test is about: gas and brick hundreds of kelvin apart
    assert abs(temps_k[0] - temps_k[-1]) > 20.0  # and a gradient along the brick


def test_thermal_trajectory_is_the_kernel_heat_balance() -> None:
    """The MPC's temperature forecast and the plant's step integrate the same heat balance (the forecast is built
    without the fast-math flags, so the two agree to rounding, not bit for bit)."""
    trace = load_cycle("whtc", cold_start=True)
    n = CatalystParams().n_cells
    temps0 = np.full(n, 298.15)
    traj = K.thermal_trajectory(temps0, trace.exhaust_flow_mol_s[:600], trace.scr_inlet_temperature_k[:600], CAT,
                                0.5)
    theta, temps = np.zeros(n), temps0.copy()
    for k in range(600):
        u = np.array([trace.exhaust_flow_mol_s[k], trace.scr_inlet_temperature_k[k], 0.0, 0.0, 0.0, 0.1])
        theta, temps, _ = _kernel_step(theta, temps, u, 0.5)
        np.testing.assert_allclose(traj[k], temps, rtol=1e-13)


def test_packed_width_follows_the_parameter_fields() -> None:
    """The buffer's parameter block is as wide as params.PACKED_FIELDS (a new parameter needs no edit here)."""
    env = UreaSCREnv()
    assert env._batch.cat_params.shape == (1, len(PACKED_FIELDS)) == (1, K.N_PACKED)
    assert K.pack_aux(DosingParams(), SensorParams())[K.X_NH3_NOISE] == SensorParams().nh3_sensor_noise_ppm
    assert K.pack_aux(DosingParams(max_rate_g_s=2.5), SensorParams())[K.X_MAX_RATE] == 2.5


def test_plant_and_surrogate_share_the_reward_and_kpi_definition() -> None:
    """account_batch on the plant's own step records gives the plant's reward terms and accumulators."""
    env = UreaSCREnv(cycle="whtc", nh3_sensor=True)
    env.reset(seed=3)
    b = env._batch
    acc = np.zeros((1, KP.N_ACC))
    for k in range(400):
        env.step(np.array([0.3 if k > 100 else -1.0], dtype=np.float32))
        terms, reward = np.zeros((1, 3)), np.zeros(1)
        KP.account_commands(b.inputs[:, K.I_ADBLUE].copy(), acc)  # no actuator: the command is delivered
        KP.account_batch(b.inputs.copy(), b.power_kw.copy(), env.dt, b.out.copy(), b.weights.copy(), terms, reward,
                         acc)
        np.testing.assert_array_equal(terms, b.terms)
        np.testing.assert_array_equal(reward, b.reward)
    acc[0, KP.A_STORED0_MOL] = b.acc[0, KP.A_STORED0_MOL]
    np.testing.assert_array_equal(acc, b.acc)
    assert KP.episode_kpis(acc[0], float(b.out[0, K.O_STORED])) == env.unwrapped.episode_kpis()
    no_balance = KP.episode_kpis(acc[0])
    assert "nitrogen_balance_error" not in no_balance and "n2o_g" not in no_balance


@pytest.mark.parametrize("kwargs", [{}, {"cold_start": True, "initial_coverage": 0.3, "nh3_sensor": True},
                                    {"privileged": True, "randomize": 0.2, "ageing": 0.4}])
def test_single_and_vector_environment_start_episodes_the_same_way(kwargs) -> None:
    env = UreaSCREnv(cycle="whsc", **kwargs)
    venv = UreaSCRVectorEnv(num_envs=1, cycle="whsc", **kwargs)
    obs, _ = env.reset(seed=5)
    vobs, _ = venv.reset(seed=5)
    a, b = env._batch, venv._batch
    np.testing.assert_array_equal(obs, vobs[0])
    for name in ("theta", "temperature_k", "sensor_state", "acc"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    if not kwargs.get("randomize"):  # the randomised catalyst is drawn from each env's own generator
        np.testing.assert_array_equal(a.cat_params, b.cat_params)
