"""The EKF converges on simulated identified models (a linear state-space model and the grey-box storage model)."""
import numpy as np

from control.estimation import ExtendedKalmanFilter
from control.identified import StorageGreyBox
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
