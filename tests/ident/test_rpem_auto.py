"""ident.rpem on the simulated benchmark systems (issue 21): the automatic choices, the static output functions,
the initial state, the diagnostics, and the accuracy goals against the best linear model."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from ident.benchmarks import simulated_benchmark
from ident.linear import ARX, N4SID, OutputError
from ident.metrics import compare, fit_percent
from ident.rpem import AUTO_SETTINGS, PAPER2_TERMS, R0_GRID, RecursivePEM

#: the structural choices per system (model order, polynomial degree, output function); everything else is
#: AUTO_SETTINGS, the same for all three
STRUCTURE = {
    "duffing_oscillator": {"n_states": 2, "max_degrees": 3, "total_degree": 3},
    "cascaded_tanks": {"n_states": 2, "max_degrees": 3, "total_degree": 3},
    "coupled_drives": {"n_states": 3, "output": "abs", "max_degrees": 1, "total_degree": 1},
}
GOAL = {"duffing_oscillator": 95.0, "cascaded_tanks": 85.0, "coupled_drives": 70.0}


def _rpem(name: str, **extra) -> RecursivePEM:
    b = simulated_benchmark(name)
    return RecursivePEM(sampling_period=b.sampling_period, **STRUCTURE[name], **{**AUTO_SETTINGS, **extra})


def _best_linear_fit(name: str) -> float:
    """The best validation FIT over a grid of ident.linear models (orders 2-4), chosen on the validation data
    itself: generous to the linear side."""
    b = simulated_benchmark(name)
    e, v = b.estimation, b.validation
    fits = []
    for model in (ARX(2, 2, 1), ARX(3, 3, 1), ARX(4, 4, 1), OutputError(2, 2, 1), OutputError(3, 3, 1), N4SID(2),
                  N4SID(3), N4SID(4)):
        try:
            model.fit(e.u, e.y)
            fits.append(float(compare(model, v.u, v.y).fit))
        except (ValueError, np.linalg.LinAlgError):
            continue
    return max(fits)


#: validation FIT (%) measured with seed 0 (tests below hold them as floors; the report gives the seed spread)
MEASURED = {"duffing_oscillator": 98.9, "cascaded_tanks": 86.4, "coupled_drives": 96.2}


@pytest.fixture(scope="module")
def fitted_benchmarks():
    out = {}
    for name in sorted(GOAL):
        b = simulated_benchmark(name)
        with warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # no divergence or rejection warning on these
            est = _rpem(name).fit(b.estimation.u, b.estimation.y)
        out[name] = float(compare(est, b.validation.u, b.validation.y).fit)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(GOAL))
def test_goal_on_the_simulated_benchmarks(name, fitted_benchmarks):
    """Issue 21's goals: validation FIT >= 95 % (Duffing), >= 85 % (tanks), >= 70 % (sign-insensitive drive), with
    the automatic choices only (no per-data-set tuning)."""
    assert fitted_benchmarks[name] >= GOAL[name]


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(GOAL))
def test_rpem_beats_the_best_linear_model(name, fitted_benchmarks):
    fit = fitted_benchmarks[name]
    assert fit > _best_linear_fit(name) + 5.0
    assert fit >= MEASURED[name] - 1.0  # no regression from the figure in the report


def test_half_step_auto_follows_the_input():
    """Interpolation for a band-limited multisine (Duffing), the held value for a zero-order-hold input."""
    b = simulated_benchmark("duffing_oscillator", n_estimation=4096, n_validation=1024)
    est = _rpem("duffing_oscillator", n_passes=3, pass_mode="restart").fit(b.estimation.u, b.estimation.y)
    assert est.half_step_input_ == "interpolate"
    assert est.choice_scores_["interpolate/restart"] > est.choice_scores_["hold/restart"] + 5.0
    u, y = _zoh_data(2000, seed=0, t_sample=0.3)  # input steps large against the dynamics: the choice matters
    y = y + 0.01 * np.random.default_rng(0).standard_normal(len(y))
    est = RecursivePEM(n_states=2, terms=PAPER2_TERMS, sampling_period=0.3,
                       **{**AUTO_SETTINGS, "n_passes": 3, "pass_mode": "restart"}).fit(u, y)
    assert est.half_step_input_ == "hold"
    assert est.choice_scores_["hold/restart"] > est.choice_scores_["interpolate/restart"] + 2.0


def _rhs(x, u):
    return np.array([x[1], 2 * u - x[0] - x[1] - x[0] * u])


def _zoh_data(n: int, seed: int, t_sample: float = 0.1):
    """Paper II's system integrated finely under a held (zero-order-hold) input."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-0.5, 1.5, n // 10 + 1), 10)[:n]
    x, y = np.zeros(2), np.empty(n)
    h = t_sample / 10
    for t in range(n):
        y[t] = x[0]
        for _ in range(10):
            k1 = _rhs(x, u[t])
            k2 = _rhs(x + h / 2 * k1, u[t])
            k3 = _rhs(x + h / 2 * k2, u[t])
            k4 = _rhs(x + h * k3, u[t])
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return u, y


@pytest.mark.parametrize("output, true_output", [("polynomial", lambda w: w + 0.5 * w**2),
                                                 ("saturation", lambda w: np.clip(w, -0.3, 0.9))])
def test_static_output_functions_are_estimated_with_the_recursion(output, true_output):
    u, w = _zoh_data(2000, seed=0)
    y = true_output(w) + 0.01 * np.random.default_rng(1).standard_normal(len(w))
    uv, wv = _zoh_data(800, seed=5)
    settings = {**AUTO_SETTINGS, "n_passes": 10, "half_step_input": "hold", "normalize": False}
    est = RecursivePEM(n_states=2, terms=PAPER2_TERMS, sampling_period=0.1, output=output, output_degree=2,
                       **settings).fit(u, y)
    ident_only = RecursivePEM(n_states=2, terms=PAPER2_TERMS, sampling_period=0.1, **settings).fit(u, y)
    fit = fit_percent(true_output(wv), est.predict(uv, true_output(wv)))
    assert fit > 95.0 and fit > fit_percent(true_output(wv), ident_only.predict(uv, true_output(wv)))
    assert est.output_params_.shape == (1, 2)
    if output == "saturation":
        np.testing.assert_allclose(est.output_params_[0], [-0.3, 0.9], atol=0.02)


def test_output_function_and_scaling_in_casadi_export_and_files(tmp_path):
    """The exported step and a reloaded model give the predictions of the fitted one (abs output, scaling,
    sub-steps)."""
    b = simulated_benchmark("coupled_drives", n_estimation=600, n_validation=200)
    est = RecursivePEM(n_states=3, output="abs", sampling_period=b.sampling_period,
                       **{**AUTO_SETTINGS, "n_passes": 2, "n_substeps": 2, "half_step_input": "hold"}
                       ).fit(b.estimation.u, b.estimation.y)  # the export holds the input (ident.rpem.export)
    u = b.validation.u
    x0 = est.initial_state(u, b.validation.y)
    y_pred = est.predict(u, x0=x0)
    step = est.to_casadi()
    x, ys = x0.copy(), []
    for t in range(len(u)):
        x_next, yt = step(x, u[t])
        ys.append(float(yt))
        x = np.asarray(x_next).ravel()
    np.testing.assert_allclose(ys, y_pred[:, 0], rtol=1e-9, atol=1e-9)
    back = RecursivePEM.load(est.save(tmp_path / "drive"))
    np.testing.assert_array_equal(back.predict(u, x0=x0), y_pred)
    assert back.n_substeps_ == 2 and back.output == "abs" and back.normalize


def test_initial_state_estimate_and_compare():
    """compare() works for the RPEM (x0 estimated from the record, issue 21), and the estimate beats the thesis'
    (y(0), 0) start on a record that begins mid-oscillation."""
    b = simulated_benchmark("duffing_oscillator", n_estimation=4096, n_validation=1024)
    est = _rpem("duffing_oscillator", n_passes=3, half_step_input="interpolate",
                pass_mode="restart").fit(b.estimation.u, b.estimation.y)
    u, y = b.validation.u[:200], b.validation.y[:200]
    x0 = est.initial_state(u, y)
    assert x0.shape == (2,) and np.all(np.isfinite(x0))
    early = slice(0, 40)  # the start's transient lasts about 1 / (zeta w0 T) = 32 samples
    from_x0 = fit_percent(y[early], est.predict(u, x0=x0)[early])
    from_y0 = fit_percent(y[early], est.predict(u, y[0])[early])
    assert from_x0 > from_y0 + 5.0
    c = compare(est, u, y)
    assert c.fit == pytest.approx(fit_percent(y, est.predict(u, y0=y)))
    with pytest.raises(ValueError) as info:
        compare(est, u, np.column_stack([y, y]))
    assert len(str(info.value)) < 300


def test_compare_works_for_every_model_class():
    from ident.greybox import StorageGreyBox
    from ident.hammerstein_wiener import HammersteinWiener
    from ident.multiple_model import MultipleModel, quantile_edges
    from ident.stack import OutputStack

    u, y = _zoh_data(600, seed=2)
    rpem = RecursivePEM(n_states=2, terms=PAPER2_TERMS, sampling_period=0.1, alpha=1.5,
                        theta0=[0.0, 0.5, -0.5, 0.0, -0.25, 0.0, 0.0, 0.0]).fit(u, y)
    models = [rpem, ARX(2, 2, 1).fit(u, y), OutputError(2, 2, 1).fit(u, y), N4SID(2).fit(u, y),
              MultipleModel([0], [quantile_edges(u, 2)], na=2, nb=2).fit(u[:, None], y),
              HammersteinWiener(max_nfev=10).fit(u, y), OutputStack([ARX(2, 2, 1)]).fit(u, y)]
    for m in models:
        c = compare(m, u[:, None] if isinstance(m, MultipleModel) else u, y)
        assert np.isfinite(c.fit) and c.fit > 50.0, type(m).__name__
    gb = StorageGreyBox.from_params(np.zeros(11), np.array([1.0, 1.0]))
    rng = np.random.default_rng(0)
    ug = np.column_stack([300 + 50 * rng.random(200), 10 * rng.random(200), np.full(200, 550.0), np.full(200, 5.0)])
    yg = gb.predict(ug) + rng.standard_normal((200, 3))
    assert np.all(np.isfinite(np.atleast_1d(compare(gb, ug, yg).fit)))


def test_diagnostics_and_divergence_warnings():
    """The thesis defaults on raw Duffing data reject almost every update: fit says so. A model whose simulation
    sits on its state bound is called diverged."""
    b = simulated_benchmark("duffing_oscillator", n_estimation=2048, n_validation=256)
    with pytest.warns(RuntimeWarning, match="parameter updates were rejected"):
        est = RecursivePEM(n_states=2, sampling_period=b.sampling_period).fit(b.estimation.u, b.estimation.y)
    assert est.n_rejected_ > 0.5 * est.n_updates_ and est.n_updates_ == 2048
    with pytest.warns(RuntimeWarning, match="sits on its state bound"):
        est = RecursivePEM(n_states=2, terms=PAPER2_TERMS, sampling_period=0.1, alpha=1.5, state_bound=0.2,
                           theta0=[0.0, 2.0, -1.0, 0.0, -1.0, -1.0, 0.0, 0.0]).fit(*_zoh_data(800, seed=1))
    assert est.n_bound_hits_ > 8
    ok = _rpem("duffing_oscillator", n_passes=2, half_step_input="interpolate", pass_mode="restart")
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        ok.fit(b.estimation.u, b.estimation.y)
    assert ok.n_rejected_ < 0.5 * ok.n_updates_ and ok.stability_margin_per_s_ == pytest.approx(0.015 * ok.alpha_)


def test_keep_best_keeps_the_best_pass_on_the_hold_out():
    u, y = _zoh_data(1500, seed=3)
    kw = {"n_states": 2, "terms": PAPER2_TERMS, "sampling_period": 0.1, "alpha": 1.5, "n_passes": 6,
          "theta0": [0.0, 0.5, -0.5, 0.0, -0.25, 0.0, 0.0, 0.0], "holdout": 0.25, "pass_mode": "continue"}
    best = RecursivePEM(**kw).fit(u, y)
    assert best.holdout_fit_ == pytest.approx(max(best.pass_fits_))
    last = RecursivePEM(**{**kw, "keep": "last"}).fit(u, y)
    assert len(last.pass_fits_) == 6


def test_substeps_recursive_equals_batch():
    u, y = _zoh_data(400, seed=4)
    kw = {"n_states": 2, "terms": PAPER2_TERMS, "sampling_period": 0.1, "alpha": 1.5, "n_substeps": 3,
          "half_step_input": "interpolate", "theta0": [0.0, 0.5, -0.5, 0.0, -0.25, 0.0, 0.0, 0.0]}
    batch = RecursivePEM(**kw).fit(u, y)
    online = RecursivePEM(**kw)
    for t in range(len(u)):
        online.update(u[t], y[t])
    np.testing.assert_allclose(online.theta_, batch.theta_, rtol=1e-10, atol=1e-12)
    one = RecursivePEM(**{**kw, "n_substeps": 1}).fit(u, y)
    assert not np.allclose(one.theta_, batch.theta_)


def test_r0_auto_chooses_the_initial_hessian_scale_on_the_hold_out(tmp_path):
    """With standardised signals the thesis' R0 = 100 lets the first samples of every pass throw the data-driven
    start away (2048 samples of the oscillator, seed 2: the passes never beat the start); R0="auto" tries the grid
    on the hold-out, keeps the best and saves what it chose."""
    b = simulated_benchmark("duffing_oscillator", seed=2)
    u, y = b.estimation.u[:2048], b.estimation.y[:2048]  # what StructureSearch screens on
    kw = {"half_step_input": "interpolate"}
    thesis = _rpem("duffing_oscillator", R0=100.0, **kw).fit(u, y)
    auto = _rpem("duffing_oscillator", **kw).fit(u, y)
    assert AUTO_SETTINGS["R0"] == "auto" and auto.R0_ in R0_GRID and thesis.R0_ == 100.0
    assert auto.holdout_fit_ > thesis.holdout_fit_ + 20.0 and auto.holdout_fit_ > 95.0
    middle = R0_GRID[len(R0_GRID) // 2]
    assert set(auto.choice_scores_) == {"interpolate/restart", "interpolate/continue"} | {
        f"interpolate/{m}/R0={r:g}" for m in ("restart", "continue") for r in R0_GRID if r != middle}
    assert auto.holdout_fit_ == pytest.approx(max(auto.choice_scores_.values()))
    back = RecursivePEM.load(auto.save(tmp_path / "r0"))
    assert back.R0 == "auto" and back.R0_ == auto.R0_
    for bad in ("big", float("nan"), -1.0):
        with pytest.raises(ValueError, match="R0"):
            RecursivePEM(R0=bad).fit(u[:200], y[:200])
