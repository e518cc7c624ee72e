"""The EKF converges on simulated identified models (a linear state-space model and the grey-box storage model);
bad arguments and non-finite signals are refused before they touch the estimate."""
import casadi as ca
import numpy as np
import pytest

from control.estimation import ExtendedKalmanFilter
from ident.greybox import StorageGreyBox
from ident.linear.statespace import StateSpaceModel


def _simulate(step, x0, u):
    x, ys = np.asarray(x0, float), []
    for uk in u:
        xn, y = step(x, uk)
        ys.append(np.asarray(y).ravel())
        x = np.asarray(xn).ravel()
    return np.array(ys), x


def test_ekf_converges_on_linear_identified_model():
    model = StateSpaceModel(A=[[0.9, 0.1], [0.0, 0.8]], B=[[0.5], [1.0]], C=[[1.0, 0.0]])
    step = model.to_casadi()
    rng = np.random.default_rng(0)
    u = rng.standard_normal((200, 1))
    y, _ = _simulate(step, [3.0, -2.0], u)
    ekf = ExtendedKalmanFilter(step, process_noise=1e-6, measurement_noise=1e-2, x0=np.zeros(2), p0=10.0)
    x_true = np.array([3.0, -2.0])
    for k in range(200):
        xn, _ = step(x_true, u[k])
        ekf.step(u[k], y[k] + 0.05 * rng.standard_normal(1))
        x_true = np.asarray(xn).ravel()
    assert np.allclose(ekf.x_, x_true, atol=0.1)


def test_ekf_converges_on_greybox_storage_model():
    """Start the filter empty while the simulated catalyst is half loaded; the NOx sensor alone recovers it."""
    model = StorageGreyBox.from_params(np.zeros(11), np.array([0.95, 1.0]), n_cells=2)
    step = model.to_casadi()
    n = 600
    u = np.column_stack([np.full(n, 600.0), np.full(n, 25.0), np.full(n, 520.0), np.full(n, 6.0)])
    x0 = np.array([0.5, 0.5, 520.0])
    y, x_end = _simulate(step, x0, u)
    ekf = ExtendedKalmanFilter(step, process_noise=np.array([1e-6, 1e-6, 1e-2]), measurement_noise=4.0,
                               measured=[2], x0=np.array([0.0, 0.0, 520.0]), p0=np.array([0.1, 0.1, 1.0]),
                               state_bounds=(np.array([0, 0, 250.0]), np.array([1, 1, 900.0])))
    rng = np.random.default_rng(1)
    for k in range(n):
        ekf.step(u[k], y[k, 2:3] + 2.0 * rng.standard_normal(1))
    assert abs(ekf.x_[0] - x_end[0]) < 0.05 and abs(ekf.x_[1] - x_end[1]) < 0.1


# ------------------------------------------------------------------------------------------------ input checks

def _linear_step():
    return StateSpaceModel(A=[[0.9, 0.1], [0.0, 0.8]], B=[[0.5], [1.0]], C=[[1.0, 0.0]]).to_casadi()


@pytest.mark.parametrize("kwargs, match", [
    ({"process_noise": np.ones(3)}, r"process_noise must have 2 variances"),
    ({"process_noise": -1e-3}, r"process_noise must be a variance >= 0"),
    ({"process_noise": np.array([1e-3, np.nan])}, r"process_noise contains NaN"),
    ({"process_noise": np.array([[1.0, 2.0], [2.0, 1.0]])}, r"process_noise must be positive semidefinite"),
    ({"process_noise": np.array([[1.0, 0.5], [0.0, 1.0]])}, r"process_noise must be a symmetric matrix"),
    ({"process_noise": np.ones((3, 3))}, r"process_noise must be a scalar, 2 variances or an \(2, 2\) matrix"),
    ({"measurement_noise": 0.0}, r"measurement_noise must be a variance > 0"),
    ({"measurement_noise": [1.0, 1.0]}, r"measurement_noise must have 1 variances"),
    ({"measurement_noise": float("inf")}, r"measurement_noise contains NaN or inf"),
    ({"measured": [1]}, r"measured indices must be in range\(1\)"),
    ({"measured": [-1]}, r"measured indices must be in range\(1\)"),
    ({"measured": []}, r"measured must be a non-empty sequence"),
    ({"x0": np.zeros(3)}, r"x0 must have 2 values"),
    ({"x0": [0.0, np.nan]}, r"x0 contains NaN or inf"),
    ({"p0": -1.0}, r"p0 must be a variance >= 0"),
    ({"state_bounds": (np.ones(2), np.zeros(2))}, r"state_bounds .* lower <= upper"),
    ({"state_bounds": (np.zeros(3), np.ones(3))}, r"state_bounds must be \(lower, upper\)"),
])
def test_constructor_rejects_bad_arguments_naming_them(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ExtendedKalmanFilter(_linear_step(), **kwargs)


def test_step_must_be_a_casadi_step_function():
    with pytest.raises(TypeError, match="step must be a casadi.Function"):
        ExtendedKalmanFilter(lambda x, u: (x, x))
    x = ca.SX.sym("x", 2)
    with pytest.raises(ValueError, match=r"step must have the inputs \(x, u\)"):
        ExtendedKalmanFilter(ca.Function("f", [x], [x, x]))


def test_valid_arguments_in_every_accepted_form():
    step = _linear_step()
    for q in (1e-3, [1e-3, 0.0], np.array([[1e-3, 0.0], [0.0, 1e-3]])):
        ekf = ExtendedKalmanFilter(step, process_noise=q, p0=np.zeros(2), x0=np.ones((2, 1)), state_bounds=(-5, 5.0))
        assert ekf.Q_.shape == (2, 2) and ekf.x_.shape == (2,)
    ekf.step(np.array([[0.3]]), 0.5)  # (nu, 1) input, scalar measurement for nm = 1
    assert ekf.x_.shape == (2,)


def _state(ekf):
    return ekf.x_.copy(), ekf.P_.copy(), getattr(ekf, "innovation_", None)


def _same(a, b):
    return all((x is None and y is None) or np.array_equal(x, y) for x, y in zip(a, b, strict=True))


def test_a_nan_measurement_or_input_is_rejected_before_any_state_changes():
    step = _linear_step()
    ekf = ExtendedKalmanFilter(step, process_noise=1e-4, measurement_noise=1e-2, x0=[1.0, -1.0], p0=2.0)
    ref = ExtendedKalmanFilter(step, process_noise=1e-4, measurement_noise=1e-2, x0=[1.0, -1.0], p0=2.0)
    rng = np.random.default_rng(0)
    u, y = rng.standard_normal((20, 1)), rng.standard_normal((20, 1))
    for k in range(20):
        if k in (3, 11):
            before = _state(ekf)
            for call, args, match in ((ekf.step, ([0.1], [np.nan]), "y_measured contains NaN"),
                                      (ekf.step, ([np.inf], [0.1]), "u contains NaN or inf"),
                                      (ekf.step, ([0.1, 0.2], [0.1]), "u must have 1 values"),
                                      (ekf.step, ([0.1], [0.1, 0.2]), "y_measured must have 1 values"),
                                      (ekf.correct, ([0.1], [np.nan]), "y_measured contains NaN"),
                                      (ekf.propagate, ([np.nan],), "u contains NaN")):
                with pytest.raises(ValueError, match=match):
                    call(*args)
                assert _same(before, _state(ekf))
        ekf.step(u[k], y[k])
        ref.step(u[k], y[k])
        assert np.array_equal(ekf.x_, ref.x_) and np.array_equal(ekf.P_, ref.P_)


def test_reset_checks_x0_and_p0_before_changing_anything():
    ekf = ExtendedKalmanFilter(_linear_step(), x0=[1.0, 2.0])
    ekf.step([0.5], [3.0])
    before = _state(ekf)
    with pytest.raises(ValueError, match=r"x0 must have 2 values"):
        ekf.reset(np.zeros(3))
    with pytest.raises(ValueError, match=r"p0 must be a variance >= 0"):
        ekf.reset([0.0, 0.0], p0=-1.0)
    assert _same(before, _state(ekf))
    ekf.reset()
    assert np.array_equal(ekf.x_, [1.0, 2.0]) and np.array_equal(ekf.P_, np.eye(2))


def test_a_non_finite_update_raises_and_leaves_the_filter_as_it_was():
    """A model that blows up (here 1 / (x - 1) at x = 1) must not leave NaN/inf in the estimate."""
    x, u = ca.SX.sym("x", 1), ca.SX.sym("u", 1)
    step = ca.Function("step", [x, u], [1.0 / (x - 1.0) + u, x])
    ekf = ExtendedKalmanFilter(step, x0=[0.0])
    ekf.step([1.0], [0.0])      # x_{1} = 1 / (0 - 1) + 1 = 0 after a zero innovation ...
    ekf.reset([1.0])            # ... now from the pole
    before = _state(ekf)
    with pytest.raises(FloatingPointError, match="non-finite"):
        ekf.step([0.0], [1.0])
    assert _same(before, _state(ekf))
    ekf.reset([0.0])
    assert np.isfinite(ekf.step([0.0], [0.0])).all()


# ------------------------------------------------------------------------------------------------ estimators
def test_observation_ekf_is_the_filter_on_the_loop_signals():
    """make_step maps (observation, applied dose) to the model's inputs and the sensor reading to its measured
    output, and runs ExtendedKalmanFilter.step: the same numbers as the filter fed by hand."""
    from control.estimation import ObservationEKF
    from control.signals import ModelSignals, urea_g_min

    model = StorageGreyBox.from_params(np.zeros(11), np.array([0.95, 1.0]), n_cells=2)
    step = model.to_casadi()
    kw = {"process_noise": np.array([1e-6, 1e-6, 0.5]), "measurement_noise": 100.0,
          "state_bounds": (np.array([0, 0, 250.0]), np.array([1, 1, 900.0]))}
    est = ObservationEKF(step, ModelSignals.physical(), measured_output=2, measured_obs=(3,),
                         initial_state=lambda obs: np.array([0.0, 0.0, obs[1]]), **kw)
    ref = ExtendedKalmanFilter(step, measured=[2], x0=np.array([0.0, 0.0, 550.0]), **kw)
    obs = [np.array([500.0 + 10 * k, 550.0, 6.0, 20.0 + k, 0.0]) for k in range(6)]
    est.reset(obs[0])
    assert np.array_equal(est.make_step(obs[0], 0.0, np.array([6.0, 550.0, 500.0, 0.4])), ref.x_)
    for k in range(1, 6):
        dose = 0.1 * k
        x = est.make_step(obs[k], dose, np.array([6.0, 550.0, obs[k][0], 0.4]))
        ref.step([obs[k][0], urea_g_min(dose), obs[k][1], obs[k][2]], [obs[k][3]])
        assert np.array_equal(x, ref.x_) and x is not est.x_   # a copy
    with pytest.raises(ValueError, match="measured_obs"):
        ObservationEKF(step, ModelSignals.physical(), measured_output=(2, 1), measured_obs=(3,))


def test_set_step_keeps_the_estimate_and_refuses_other_sizes():
    lin = _linear_step()
    ekf = ExtendedKalmanFilter(lin, x0=np.array([1.0, 2.0]))
    ekf.step([0.3], [1.1])
    x, p = ekf.x_.copy(), ekf.P_.copy()
    x_s, u_s = ca.SX.sym("x", 2), ca.SX.sym("u", 1)
    faster = ca.Function("step", [x_s, u_s], [0.5 * x_s + u_s[0], x_s[0]])
    ekf.set_step(faster)
    assert np.array_equal(ekf.x_, x) and np.array_equal(ekf.P_, p) and ekf.step_function is faster
    assert np.allclose(ekf.propagate([1.0]), 0.5 * x + 1.0)
    three = ca.Function("step", [ca.SX.sym("x", 3), u_s], [ca.SX.zeros(3), ca.SX.zeros(1)])
    with pytest.raises(ValueError, match="sizes"):
        ekf.set_step(three)
    with pytest.raises(TypeError, match="casadi.Function"):
        ekf.set_step("not a function")


def test_privileged_state_reads_the_simulator_and_needs_it():
    from control.estimation import PrivilegedState
    from scr_env.envs.urea_scr import UreaSCREnv

    est = PrivilegedState()
    with pytest.raises(RuntimeError, match="attach"):
        est.make_step(np.zeros(5), 0.0, np.zeros(4))
    env = UreaSCREnv(cycle="whsc")
    obs, _ = env.reset(seed=0)
    est.attach(env)
    assert np.array_equal(est.make_step(obs, 0.0, np.zeros(4)), np.clip(env.state["nh3_coverage"], 0, 1))
