"""Tests of ident.rpem: recursive = batch, projection onto DM, validation, export, persistence, accuracy."""
from __future__ import annotations

import numpy as np
import pytest

from ident.base import NotFittedError
from ident.rpem import (
    PAPER2_TERMS,
    SCR_PAPER3_TERMS,
    RecursivePEM,
    backward_elimination,
    parse_terms,
    polynomial_terms,
)
from ident.rpem.kernel import is_hurwitz

THETA_TRUE = np.array([0.0, 2.0, -1.0, 0.0, -1.0, -1.0, 0.0, 0.0])
THETA_START = [0.0, 0.5, -0.5, 0.0, -0.25, 0.0, 0.0, 0.0]


def _rhs(x, u):
    return np.array([x[1], 2 * u - x[0] - x[1] - x[0] * u])


def _paper2_data(seed: int, n: int, continuous: bool, t_sample: float = 0.1):
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-0.5, 1.5, n // 10 + 1), rng.integers(5, 40))[:n]
    u = np.concatenate([u, np.repeat(rng.uniform(-0.5, 1.5, n), 20)])[:n]
    x, y = np.zeros(2), np.empty(n)
    for t in range(n):
        y[t] = x[0]
        if continuous:
            h = t_sample / 10
            for _ in range(10):
                k1 = _rhs(x, u[t])
                k2 = _rhs(x + h / 2 * k1, u[t])
                k3 = _rhs(x + h / 2 * k2, u[t])
                k4 = _rhs(x + h * k3, u[t])
                x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        else:
            ts = 1.5 * t_sample
            x = x + ts * _rhs(x + ts / 2 * _rhs(x, u[t]), u[t])
    return u, y + 0.1 * rng.standard_normal(n)


def _paper2_est(**kw) -> RecursivePEM:
    args = {"n_states": 2, "terms": PAPER2_TERMS, "sampling_period": 0.1, "alpha": 1.5, "stability_margin": 0.015,
                "theta0": THETA_START}
    args.update(kw)
    return RecursivePEM(**args)


def _scr_data(n: int = 400, seed: int = 1):
    rng = np.random.default_rng(seed)
    u = np.column_stack([400 + 100 * rng.standard_normal(n), np.abs(rng.standard_normal(n)),
                         550 + 50 * rng.standard_normal(n), 0.3 + 0.05 * rng.standard_normal(n)])
    u = np.repeat(u[: n // 5], 5, axis=0)[:n]
    y = np.convolve(0.002 * u[:, 0] - 0.3 * u[:, 1], np.full(10, 0.1))[:n] + 0.01 * rng.standard_normal(n)
    return u, y


def _scr_est(**kw) -> RecursivePEM:
    args = {"n_states": 2, "terms": list(SCR_PAPER3_TERMS), "input_transforms": {3: ("exp_neg_inv", 1e4)},
                "sampling_period": 0.5, "alpha": 1.5}
    args.update(kw)
    return RecursivePEM(**args)


def test_terms_language():
    E = parse_terms(["1", "x1*u2", "u1'", "x2^2*u1"], n_states=2, n_inputs=2)
    assert E.shape == (4, 6)
    assert E[1].tolist() == [1, 0, 0, 1, 0, 0] and E[2].tolist() == [0, 0, 0, 0, 1, 0]
    assert E[3].tolist() == [0, 2, 1, 0, 0, 0]
    assert len(polynomial_terms(2, 4, 1, derivative_inputs=(1, 2, 4))) == 512  # Paper III's full polynomial
    with pytest.raises(ValueError, match="x3"):
        parse_terms(["x3"], 2, 1)
    with pytest.raises(ValueError, match="same monomial"):
        parse_terms(["x1*u1", "u1*x1"], 2, 1)


def test_paper2_scaled_example_converges():
    u, y = _paper2_data(0, 10000, continuous=False)
    est = _paper2_est().fit(u, y)
    assert np.max(np.abs(est.theta_ - THETA_TRUE)) < 0.1


def test_recursive_equals_batch():
    u, y = _paper2_data(3, 600, continuous=False)
    batch = _paper2_est().fit(u, y)
    online = _paper2_est()
    preds = [online.update(u[t], y[t]) for t in range(len(u))]
    np.testing.assert_allclose(online.theta_, batch.theta_, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(online.P_, batch.P_, rtol=1e-10, atol=1e-14)
    assert np.asarray(preds).shape == (600, 1)
    chunked = _paper2_est()
    for s in range(0, 600, 70):
        chunked.partial_fit(u[s:s + 70], y[s:s + 70])
    np.testing.assert_allclose(chunked.theta_, batch.theta_, rtol=1e-12, atol=1e-12)


def test_recursive_equals_batch_with_derivatives_and_interpolation():
    u, y = _scr_data(300)
    batch = _scr_est(half_step_input="interpolate").fit(u, y)
    online = _scr_est(half_step_input="interpolate")
    for t in range(len(u)):
        online.update(u[t], y[t])
    np.testing.assert_allclose(online.theta_, batch.theta_, rtol=1e-10, atol=1e-12)


def test_projection_keeps_estimate_in_model_set():
    # Data from an unstable system x'' = u + 0.4 x' - 4 x: an unconstrained estimate would follow it out of DM.
    n, h = 1500, 0.02
    rng = np.random.default_rng(0)
    u = np.repeat(rng.standard_normal(n // 10), 10)
    x, y = np.array([0.1, 0.0]), np.empty(n)
    for t in range(n):
        y[t] = x[0]
        x = x + h * np.array([x[1], u[t] + 0.4 * x[1] - 4.0 * x[0]])
    y = y + 0.01 * rng.standard_normal(n)
    margin = 0.05
    est = RecursivePEM(n_states=2, terms=["u1", "x1", "x2"], sampling_period=h, method="euler",
                       stability_margin=margin, theta0=[0.5, -2.0, -1.0]).fit(u, y)
    assert est.n_rejected_ > 0
    assert np.all(np.isfinite(est.theta_))
    J = np.array([[0.0, 1.0], [est.theta_[1], est.theta_[2]]])  # linear model: J does not depend on x
    assert is_hurwitz(J, margin)
    assert np.all(np.isfinite(est.predict(u, y0=y[:1])))


def test_validation_errors():
    u, y = _paper2_data(0, 50, continuous=False)
    with pytest.raises(NotFittedError):
        _paper2_est().predict(u)
    u_bad = u.copy()
    u_bad[7] = np.nan
    with pytest.raises(ValueError, match="u contains NaN"):
        _paper2_est().fit(u_bad, y)
    y_bad = y.copy()
    y_bad[3] = np.inf
    with pytest.raises(ValueError, match="y contains NaN"):
        _paper2_est().fit(u, y_bad)
    est = _paper2_est().fit(u, y)
    with pytest.raises(ValueError, match="u contains NaN"):
        est.update(np.nan, 0.0)
    with pytest.raises(ValueError, match="theta0"):
        _paper2_est(theta0=[1.0, 2.0]).fit(u, y)


def test_midpoint_beats_euler_on_continuous_data():
    errs = {"midpoint": [], "euler": []}
    for seed in range(3):
        u, y = _paper2_data(seed, 6000, continuous=True)
        for method, errs_m in errs.items():
            est = _paper2_est(alpha=1.0, method=method).fit(u, y)
            errs_m.append(np.max(np.abs(est.theta_ - THETA_TRUE)))
    assert np.median(errs["midpoint"]) < np.median(errs["euler"])


def test_casadi_export_matches_predict(tmp_path):
    u, y = _scr_data(200)
    est = _scr_est(output_limits=(-0.5, np.inf)).fit(u, y)
    y_sim = est.predict(u, y0=y[:1])
    f = est.to_casadi()
    assert f.name() == "step"
    N = est.structure_.n_states
    x = np.zeros(N + 4)
    x[0] = y[0]
    x[N:] = u[0]
    x[N + 2] = np.exp(-1e4 / u[0, 2])  # the state carries the previous *transformed* input
    out = []
    for t in range(len(u)):
        x_next, yk = f(x, u[t])
        out.append(float(yk))
        x = np.asarray(x_next).ravel()
    np.testing.assert_allclose(out, y_sim[:, 0], rtol=1e-8, atol=1e-10)


def test_save_load_roundtrip(tmp_path):
    u, y = _scr_data(200)
    est = _scr_est().fit(u, y)
    path = est.save(tmp_path / "model")
    loaded = RecursivePEM.load(path)
    np.testing.assert_allclose(loaded.predict(u, y0=y[:1]), est.predict(u, y0=y[:1]))
    assert loaded.terms_ == est.terms_
    loaded.partial_fit(u[:20], y[:20])
    assert loaded.n_samples_seen_ == est.n_samples_seen_ + 20


def test_k_step_and_passes_and_kalman_init():
    u, y = _paper2_data(1, 3000, continuous=False)
    est = _paper2_est(init="kalman", theta0=None, n_passes=3,
                      kalman_options={"q_state": 1e-3, "r": 1e-2}).fit(u, y)
    assert np.all(np.isfinite(est.theta_init_)) and 1 <= len(est.pass_fits_) <= 3
    # An unmodelled output step: the free run cannot see it, the Kalman-filtered k-step predictor can.
    y_dist = y + 0.5 * (np.arange(len(y)) > 1500)
    free = est.predict(u, y0=y[:1])
    one = est.predict_k_step(u, y_dist, 1)
    assert one.shape == free.shape
    assert np.mean((one[:, 0] - y_dist) ** 2) < 0.5 * np.mean((free[:, 0] - y_dist) ** 2)
    np.testing.assert_allclose(est.predict_k_step(u, y_dist, 5)[:5], free[:5])


def test_mimo_one_chain_per_output():
    u, y1 = _paper2_data(2, 1500, continuous=False)
    _, y2 = _paper2_data(5, 1500, continuous=False)
    y = np.column_stack([y1, 0.5 * y2])
    est = RecursivePEM(n_states=2, terms=["u1", "x1", "x2"], sampling_period=0.1, theta0=[0.5, -1, -1] * 2).fit(u, y)
    assert est.theta_.shape == (6,) and est.predict(u).shape == (1500, 2)
    assert est.Lambda_.shape == (2, 2)
    x_next, yk = est.to_casadi()(np.zeros(4), [0.3])
    assert np.asarray(x_next).shape == (4, 1) and np.asarray(yk).shape == (2, 1)


def test_backward_elimination_drops_useless_term():
    rng = np.random.default_rng(0)
    n = 1500
    u = np.repeat(rng.uniform(-1, 1, n // 20 + 1), 20)[:n, None]
    u = np.column_stack([u[:, 0], rng.standard_normal(n)])  # the second input is irrelevant noise
    x, y = np.zeros(2), np.empty(n)
    for t in range(n):
        y[t] = x[0]
        x = x + 0.1 * np.array([x[1], u[t, 0] - x[0] - x[1]])
    y = y + 0.01 * rng.standard_normal(n)
    template = RecursivePEM(n_states=2, sampling_period=0.1, method="euler", n_passes=2)
    res = backward_elimination(template, ["u1", "u2", "x1", "x2"], u[:1000], y[:1000], u[1000:], y[1000:],
                               theta0={"x1": -0.5, "x2": -0.5})
    assert "u2" not in res.terms and {"u1", "x1", "x2"} <= set(res.terms)


@pytest.mark.parametrize("value", [0.0, 1.0])
def test_constant_output_is_refused_naming_y(value):
    u, _ = _paper2_data(0, 200, continuous=False)
    with pytest.raises(ValueError, match=r"^y is constant in column\(s\) \[0\].*RPEM model"):
        _paper2_est().fit(u, np.full(200, value))
    with pytest.raises(ValueError, match=r"y is constant in column\(s\) \[1\]"):
        _paper2_est().fit(u, np.column_stack([_paper2_data(0, 200, continuous=False)[1], np.zeros(200)]))


def test_output_constant_over_part_of_the_record_is_fitted_and_online_updates_accept_it():
    u, y = _paper2_data(0, 400, continuous=False)
    y_part = np.where(np.arange(400) < 300, 0.0, y)
    est = _paper2_est().fit(u, y_part)
    assert np.all(np.isfinite(est.theta_))
    online = _paper2_est()
    online.partial_fit(u[:20], np.zeros(20))   # online: a constant stretch is just data
    online.update(u[20], 0.0)
    assert online.n_samples_seen_ == 21


@pytest.mark.parametrize("n_passes", [0, -1, 1.5])
def test_n_passes_must_be_a_positive_integer(n_passes):
    u, y = _paper2_data(0, 100, continuous=False)
    with pytest.raises(ValueError, match=f"^n_passes must be a positive integer.*got {n_passes}"):
        _paper2_est(n_passes=n_passes).fit(u, y)
    assert not hasattr(_paper2_est(n_passes=n_passes), "theta_")


def test_other_constructor_arguments_are_checked():
    u, y = _paper2_data(0, 100, continuous=False)
    with pytest.raises(ValueError, match="^pass_tol"):
        _paper2_est(n_passes=2, pass_tol=-1.0).fit(u, y)
    with pytest.raises(ValueError, match="^n_states must be a positive integer"):
        _paper2_est(n_states=1.5, terms=None).fit(u, y)
    with pytest.raises(ValueError, match="^state_bound must be a finite number"):
        _paper2_est(state_bound=-1.0).fit(u, y)


@pytest.mark.parametrize("limits", [(1.0, 0.0), (0.5, 0.5), (np.nan, 1.0), (0.0, 1.0, 2.0), [(0.0, 1.0)] * 2])
def test_output_limits_are_checked(limits):
    u, y = _paper2_data(0, 100, continuous=False)
    with pytest.raises(ValueError, match="^output_limits"):
        _paper2_est(output_limits=limits).fit(u, y)


def test_one_sided_output_limits_are_accepted():
    u, y = _paper2_data(0, 100, continuous=False)
    est = _paper2_est(output_limits=(-0.5, np.inf)).fit(u, y)
    assert est.predict(u, y0=y[:1]).min() >= -0.5


def test_predict_k_step_checks_k_like_the_linear_models():
    u, y = _paper2_data(0, 100, continuous=False)
    est = _paper2_est().fit(u, y)
    for k in (0, 1.5, -1):
        with pytest.raises(ValueError, match=f"^k must be a positive integer number of steps, got {k}"):
            est.predict_k_step(u, y, k)
    with pytest.raises(ValueError, match="mismatched lengths"):
        est.predict_k_step(u, y[:10], 1)
    np.testing.assert_array_equal(est.predict_k_step(u, y, 2.0), est.predict_k_step(u, y, 2))
