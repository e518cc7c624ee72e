"""Every controller satisfies the policy protocol; a failing MPC solve returns the fallback dose and is counted;
the oracle's collocation equations are the plant's step (scr_env.casadi_model)."""
import numpy as np
import pytest

from control.baselines import FeedforwardPI, LookupTableDosing
from control.evaluation import evaluate
from control.identified import StorageGreyBox
from control.models import FirstPrinciplesModel, IdentifiedModelAdapter
from control.mpc import NonlinearMPC
from control.protocol import PolicyPredictor, action_to_rate


def _identified_mpc(**kw):
    m = StorageGreyBox.from_params(np.zeros(11), np.array([0.95, 1.0]), n_cells=2)
    adapter = IdentifiedModelAdapter(m, np.zeros(4), np.ones(4), np.zeros(3), np.ones(3), measurement_noise=100.0,
                                     process_noise=np.array([1e-6, 1e-6, 0.5]),
                                     state_bounds=(np.array([0, 0, 250.0]), np.array([1, 1, 900.0])),
                                     initial_state=lambda obs: np.array([0.0, 0.0, obs[1]]))
    return NonlinearMPC(adapter, horizon=4, stage_steps=2, **kw)


CONTROLLERS = {
    "lookup_table": LookupTableDosing,
    "pi": FeedforwardPI,
    "mpc_oracle": lambda: NonlinearMPC(FirstPrinciplesModel(), horizon=3, stage_steps=2, preview=True),
    "mpc_identified": _identified_mpc,
}


@pytest.mark.parametrize("name", list(CONTROLLERS))
def test_controller_satisfies_protocol(name):
    policy = CONTROLLERS[name]()
    assert isinstance(policy, PolicyPredictor)
    res = evaluate(policy, cycles=("whsc",), max_steps=10, name=name)[0]
    assert res.timing["policy_time_ms_median"] > 0
    if name.startswith("mpc"):
        assert res.stats["solves"] == 10 and res.stats["solver_failures"] == 0
    a, state = policy.predict(np.array([500.0, 550.0, 6.0, 30.0, 0.0], dtype=np.float32))
    assert a.shape == (1,) and -1.0 <= float(a[0]) <= 1.0 and state is None


def test_failing_solve_returns_fallback_and_is_counted():
    lut = LookupTableDosing()
    mpc = _identified_mpc(fallback=lut, max_rate_change_g_s2=100.0, solver_options={"ipopt.max_iter": 1})
    res = evaluate(mpc, cycles=("whsc",), max_steps=10, record_trajectory=True)[0]
    assert res.stats["solver_failures"] == 10
    # every dose was the look-up table's (the rate limit is wide open here)
    from scr_env.envs.urea_scr import UreaSCREnv

    env = UreaSCREnv(cycle="whsc")
    obs, _ = env.reset(seed=0)
    expected = action_to_rate(lut.predict(obs)[0])
    assert abs(res.trajectory["adblue_g_s"][0] - expected) < 1e-5


def test_model_error_falls_back_not_raises():
    mpc = _identified_mpc()
    mpc.model.prepare = lambda *a, **k: (_ for _ in ()).throw(RuntimeError("broken model"))
    res = evaluate(mpc, cycles=("whsc",), max_steps=5)[0]
    assert res.stats["solver_failures"] == 5


def test_slip_guard_doses_nothing_on_failed_solves_while_the_nh3_sensor_reads_slip():
    from scr_env.envs.urea_scr import UreaSCREnv

    lut = LookupTableDosing()
    mpc = _identified_mpc(fallback=lut, max_rate_change_g_s2=100.0, slip_guard=(5, 10.0))
    env = UreaSCREnv(cycle="whsc", nh3_sensor=True)
    obs, _ = env.reset(seed=0)
    mpc.attach(env)
    mpc.model.prepare = lambda *a, **k: (_ for _ in ()).throw(RuntimeError("broken model"))  # every solve fails
    slipping = np.array([500.0, 550.0, 6.0, 30.0, 0.0, 25.0])
    clean = slipping.copy()
    clean[5] = 2.0
    a, _ = mpc.predict(slipping, episode_start=True)
    assert action_to_rate(a[0]) == 0.0                      # the fallback would dose; the guard stops it
    a, _ = mpc.predict(clean)
    assert action_to_rate(a[0]) == pytest.approx(lut.dose_g_s(clean), rel=1e-6) and lut.dose_g_s(clean) > 0
    assert mpc.stats()["slip_guarded_steps"] == 1 and mpc.stats()["solver_failures"] == 2
    # an environment without the NH3 sensor is refused, and so are malformed guards
    with pytest.raises(ValueError, match="slip_guard"):
        mpc.attach(UreaSCREnv(cycle="whsc"))
    for bad in ((-1, 10.0), (5, float("nan")), (5, -1.0), (2.5, 10.0)):
        with pytest.raises(ValueError, match="slip_guard"):
            _identified_mpc(slip_guard=bad)


def test_oracle_collocation_equals_plant_step():
    """At the plant's next state (casadi_model.catalyst_step, implicit Euler) the oracle's residual vanishes."""
    import casadi as ca

    from scr_env.casadi_model import catalyst_step
    from scr_env.envs.urea_scr import UreaSCREnv
    from scr_env.params import CatalystParams

    env = UreaSCREnv(cycle="whsc")
    env.reset(seed=0)
    model = FirstPrinciplesModel()
    model.attach(env)
    n, h = model.n_cells, 2.0
    theta = np.linspace(0.1, 0.5, n)
    temps = np.full(n, 560.0)
    d = np.array([8.0, 560.0, 800.0, 0.4])
    dose = 0.6
    x_next, y = catalyst_step(CatalystParams(), dt=h)(np.r_[theta, temps], [*d, dose, 0.10])
    x_next = np.asarray(x_next).ravel()
    # the oracle's stage parameters at those end-of-step temperatures
    model._env = type("E", (), {"state": {"nh3_coverage": theta, "temperature_k": temps}})()
    model.use_preview = False
    _, pst, _ = model.prepare(None, 0.0, d[None, :], h, h)
    xs, us = ca.SX.sym("x", n), ca.SX.sym("u")
    r = ca.Function("r", [xs, us], [model.residual(xs, ca.DM(theta), us, d, ca.DM(pst[0]), h),
                                    model.outputs(xs, None, us, d, ca.DM(pst[0]))])
    res, out = r(x_next[:n], dose)
    assert np.max(np.abs(np.asarray(res))) < 1e-6
    y = np.asarray(y).ravel()
    assert np.allclose(np.asarray(out).ravel(), [y[0] + y[1], y[2]], rtol=1e-6, atol=1e-6)
