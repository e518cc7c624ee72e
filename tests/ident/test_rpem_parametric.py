"""The recursive prediction error method on the parameters of a CasADi step model."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from ident.rpem.parametric import ParametricRPEM


def _first_order() -> ca.Function:
    x, u, p = ca.SX.sym("x", 1), ca.SX.sym("u", 1), ca.SX.sym("p", 3)
    xn = p[0] * x + p[1] * u
    return ca.Function("step", [x, u, p], [xn, ca.vertcat(p[2] * xn, xn ** 2)])


def _data(a: np.ndarray, b: np.ndarray, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.choice([-1.0, 1.0], size=n // 5 + 1), 5)[:n]
    x, y = 0.0, np.empty(n)
    for t in range(n):
        x = a[t] * x + b[t] * u[t]
        y[t] = 2.0 * x + 0.01 * rng.standard_normal()
    return u, y


def test_recovers_constant_parameters() -> None:
    n = 3000
    u, y = _data(np.full(n, 0.8), np.full(n, 0.5), n)
    est = ParametricRPEM(_first_order(), p0=[0.5, 0.2, 2.0], free=[0, 1], output_indices=[0], forgetting=1.0,
                         p_bounds=([-0.99, -5.0], [0.99, 5.0])).start([0.0])
    for t in range(n):
        est.update([u[t]], [y[t]])
    np.testing.assert_allclose(est.free_params_, [0.8, 0.5], atol=0.01)
    assert est.params_[2] == 2.0  # fixed parameter untouched


def test_forgetting_factor_tracks_a_drifting_parameter() -> None:
    n = 6000
    b = np.where(np.arange(n) < n // 2, 0.5, 0.3)  # the gain drops halfway, as an ageing catalyst's activity
    u, y = _data(np.full(n, 0.8), b, n, seed=1)
    est = ParametricRPEM(_first_order(), p0=[0.8, 0.5, 2.0], free=[1], output_indices=[0],
                         forgetting=0.99).start([0.0])
    for t in range(n):
        est.update([u[t]], [y[t]])
    assert abs(est.free_params_[0] - 0.3) < 0.02


def test_projection_keeps_estimate_in_the_box_and_nan_raises() -> None:
    u, y = _data(np.full(500, 0.8), np.full(500, 0.5), 500)
    est = ParametricRPEM(_first_order(), p0=[0.5, 0.2, 2.0], free=[0, 1], output_indices=[0],
                         p_bounds=([0.0, 0.0], [0.6, 0.3])).start([0.0])
    for t in range(500):
        est.update([u[t]], [y[t]])
    assert 0.0 <= est.free_params_[0] <= 0.6 and 0.0 <= est.free_params_[1] <= 0.3
    assert est.n_rejected_ > 0
    with pytest.raises(ValueError, match="u"):
        est.update([np.nan], [0.0])
    with pytest.raises(ValueError, match="free"):
        ParametricRPEM(_first_order(), p0=[0.5, 0.2, 2.0], free=[5]).start([0.0])


def test_start_state_must_be_finite() -> None:
    est = ParametricRPEM(_first_order(), p0=[0.5, 0.2, 2.0])
    with pytest.raises(ValueError, match="^x0 contains NaN"):
        est.start([np.nan])
    with pytest.raises(ValueError, match="^x0 must have 1 elements"):
        est.start([0.0, 1.0])
