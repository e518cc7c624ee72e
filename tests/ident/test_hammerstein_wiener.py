"""ident.hammerstein_wiener: block derivatives, exact Jacobian, recovery of known systems, CasADi, save/load, errors."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from ident.base import NotFittedError
from ident.excitation import RandomSteps
from ident.hammerstein_wiener import (
    AbsoluteValue,
    Arrhenius,
    DeadZone,
    EvenPolynomial,
    HammersteinWiener,
    Identity,
    OddPolynomial,
    PiecewiseLinear,
    Polynomial,
    Saturation,
    block_from_dict,
    hammerstein,
    select_by_holdout,
    wiener,
)
from ident.io import load_model

BLOCKS = [
    (Identity(), np.linspace(-2, 2, 41)),
    (Arrhenius(a=3000.0, estimate=True), np.linspace(450, 650, 41)),
    (PiecewiseLinear(4, estimate_knots=True), np.linspace(-3, 3, 41)),
    (PiecewiseLinear(3, knots=[-1.0, 0.0, 0.5, 1.5], estimate_knots=True, extrapolation="constant"),
     np.linspace(-3, 3, 41)),
    (PiecewiseLinear(5, extrapolation="constant", monotone=True), np.linspace(-3, 3, 41)),
    (Saturation(-0.5, 1.2, estimate=True), np.linspace(-2, 2, 41)),
    (DeadZone(-0.3, 0.4), np.linspace(-2, 2, 41)),
    (Polynomial(3, coefficients=[0.1, 1.0, -0.3, 0.2]), np.linspace(-2, 2, 41)),
    (OddPolynomial(5, coefficients=[0.8, -0.2, 0.05]), np.linspace(-2, 2, 41)),
    (EvenPolynomial(4, coefficients=[0.1, 0.7, -0.1], centre=0.33), np.linspace(-2, 2, 41)),
    (AbsoluteValue(centre=0.27, offset=-0.4), np.linspace(-2, 2, 41)),
]


def _inputs(n: int, seed: int, lo: float = -2.0, hi: float = 2.0) -> np.ndarray:
    return RandomSteps(lo, hi, 0.3, 2.0).generate(n, 0.1, seed)


def _start(m: HammersteinWiener, u: np.ndarray, y: np.ndarray):
    """The working structure, the validated inputs and the start theta of ``m`` on these data."""
    u_arr, Y, base = m._validate(u, y)
    st, th, _ = m._deterministic_start(base, u_arr, Y, None)
    return st, u_arr, th


def _assert_exact_jacobian(st, u_arr: np.ndarray, th: np.ndarray) -> None:
    """The structure's analytic simulation Jacobian at ``th`` equals central finite differences."""
    _, J = st.simulate(th, u_arr, True)

    def flat(t: np.ndarray) -> np.ndarray:
        return st.simulate(t, u_arr, False)[0].T.ravel()   # outputs stacked, as the Jacobian's rows

    h = 1e-6
    num = np.column_stack([(flat(th + h * e * max(1, abs(th[i]))) - flat(th - h * e * max(1, abs(th[i]))))
                           / (2 * h * max(1, abs(th[i]))) for i, e in enumerate(np.eye(th.size))])
    np.testing.assert_allclose(J, num, rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("block,x", BLOCKS, ids=lambda b: type(b).__name__)
def test_block_derivatives_casadi_and_dict(block, x) -> None:
    import casadi as ca

    blk = block.copy()
    p = blk.initial_params(x)
    if isinstance(blk, PiecewiseLinear):
        p = p + 0.1 * np.sin(np.arange(p.size))  # a non-identity shape, knots still increasing
    x = x + 1e-3  # keep off the kinks
    h = 1e-6
    num_dx = (blk.value(x + h, p) - blk.value(x - h, p)) / (2 * h)
    np.testing.assert_allclose(blk.dx(x, p), num_dx, rtol=1e-5, atol=1e-6)
    if p.size:
        num_dp = np.column_stack([(blk.value(x, p + h * e) - blk.value(x, p - h * e)) / (2 * h)
                                  for e in np.eye(p.size) * max(1.0, np.abs(p).max())])
        num_dp /= max(1.0, np.abs(p).max())
        np.testing.assert_allclose(blk.dp(x, p), num_dp, rtol=1e-4, atol=1e-6)
    xs = ca.SX.sym("x")
    f = ca.Function("g", [xs], [blk.casadi(xs, p)])
    np.testing.assert_allclose([float(f(xi)) for xi in x[::5]], blk.value(x[::5], p), rtol=1e-12, atol=1e-12)
    again = block_from_dict(blk.to_dict())
    np.testing.assert_allclose(again.value(x, p), blk.value(x, p))


def test_exact_jacobian_matches_finite_differences() -> None:
    rng = np.random.default_rng(0)
    u = np.column_stack([_inputs(300, 1), np.abs(_inputs(300, 2)) * 50 + 500])
    y = rng.standard_normal(300)
    m = HammersteinWiener([PiecewiseLinear(3), Arrhenius(a=3000.0, estimate=True)],
                          Saturation(-0.8, estimate=True), nb=(2, 1), nf=(2, 1))
    st, u_arr, th = _start(m, u, y)
    th = th + 0.05 * rng.standard_normal(th.size)
    _assert_exact_jacobian(st, u_arr, th)


def test_recovers_wiener_saturation_and_dynamics() -> None:
    u = np.column_stack([_inputs(800, 3), _inputs(800, 4)])
    w = lfilter([0, 0.5, 0.2], [1, -1.2, 0.5], u[:, 0]) + lfilter([0, 0.4, 0], [1, -0.6, 0.0], u[:, 1])
    y = np.clip(w, -0.7, np.inf)
    m = wiener(Saturation(-0.2, estimate=True), nb=2, nf=2, nk=1).fit(u, y)
    assert m.output_params_[0] == pytest.approx(-0.7, abs=1e-3)
    np.testing.assert_allclose(m.f_[0, 0], [1, -1.2, 0.5], atol=1e-3)
    np.testing.assert_allclose(m.b_[0, 0], [0, 0.5, 0.2], atol=1e-3)
    assert m.cost_ < 1e-6 < m.initial_cost_


def test_recovers_hammerstein_nonlinearity_up_to_scale() -> None:
    u = np.column_stack([_inputs(800, 5), _inputs(800, 6)])
    g1 = np.tanh(u[:, 0])
    g2 = u[:, 1] + 0.4 * u[:, 1] ** 2
    y = lfilter([0, 0.3], [1, -0.8], g1) + lfilter([0, 0.2], [1, -0.5], g2)
    m = hammerstein([PiecewiseLinear(8), Polynomial(2)], nb=1, nf=1, nk=1).fit(u, y)
    np.testing.assert_allclose(m.f_[0, :, 1], [-0.8, -0.5], atol=2e-2)
    # the polynomial block times its gain is the true one (the split of the gain is not identifiable)
    c = m.input_params_[1] * m.b_[0, 1, 1]
    np.testing.assert_allclose(c[1:], [0.2, 0.08], atol=1e-2)
    u_val = np.column_stack([_inputs(400, 7), _inputs(400, 8)])
    y_val = lfilter([0, 0.3], [1, -0.8], np.tanh(u_val[:, 0])) + lfilter([0, 0.2], [1, -0.5],
                                                                          u_val[:, 1] + 0.4 * u_val[:, 1] ** 2)
    err = y_val - m.predict(u_val)[:, 0]
    assert np.linalg.norm(err) / np.linalg.norm(y_val - y_val.mean()) < 0.05


@pytest.fixture(scope="module")
def fitted() -> tuple[HammersteinWiener, np.ndarray, np.ndarray]:
    u = np.column_stack([_inputs(400, 9), np.abs(_inputs(400, 10)) * 40 + 480])
    w = lfilter([0, 0.5], [1, -0.7], u[:, 0]) + lfilter([0, 0.3], [1, -0.5], (np.exp(-3000 / u[:, 1]) - 0.002) * 500)
    y = np.clip(w, -0.5, np.inf)
    m = HammersteinWiener([PiecewiseLinear(4), Arrhenius(a=3000.0)], Saturation(-0.5), max_nfev=30).fit(u, y)
    return m, u, y


def test_casadi_step_equals_predict(fitted) -> None:
    m, u, y = fitted
    f = m.to_casadi()
    assert f.name() == "step" and f.name_in() == ["x", "u"] and f.name_out() == ["x_next", "y"]
    x = m.initial_state(u, y[:, None])
    y_ref = m.predict(u, y0=y)
    out = []
    for t in range(len(u)):
        x_next, yt = f(x, u[t])
        out.append(float(yt))
        x = np.asarray(x_next).ravel()
    np.testing.assert_allclose(out, y_ref[:, 0], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(m.predict_k_step(u, y, 3), y_ref)


def test_save_load_round_trip(fitted, tmp_path) -> None:
    m, u, _ = fitted
    path = m.save(tmp_path / "hw")
    for again in (HammersteinWiener.load(path), load_model(tmp_path / "hw")):
        np.testing.assert_array_equal(again.predict(u), m.predict(u))
        assert again.n_params_ == m.n_params_ and again.get_params()["nb"] == m.nb


def test_bad_inputs() -> None:
    u = np.column_stack([_inputs(200, 11), _inputs(200, 12)])
    y = u[:, 0] * 0.5
    m = HammersteinWiener()
    with pytest.raises(NotFittedError):
        m.predict(u)
    with pytest.raises(ValueError, match="2 output blocks for 3 outputs"):
        HammersteinWiener(output_block=[Identity(), Identity()]).fit(u, np.column_stack([y, y, y]))
    with pytest.raises(ValueError, match="input blocks"):
        HammersteinWiener(input_blocks=[Identity()]).fit(u, y)
    bad = u.copy()
    bad[5, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        HammersteinWiener().fit(bad, y)
    with pytest.raises(ValueError, match="constant"):
        HammersteinWiener().fit(np.column_stack([u[:, 0], np.ones(200)]), y)
    with pytest.raises(ValueError, match="kelvin"):
        HammersteinWiener(input_blocks=[Identity(), Arrhenius()]).fit(u, y)
    with pytest.raises(TypeError):
        HammersteinWiener(input_blocks=[Identity(), "exp"]).fit(u, y)
    fitted_m = HammersteinWiener(max_nfev=5).fit(u, y)
    with pytest.raises(ValueError, match="columns"):
        fitted_m.predict(u[:, :1])


def test_pwl_monotone_and_roughness() -> None:
    x = np.linspace(-2, 2, 101)
    blk = PiecewiseLinear(4, monotone=True)
    p = blk.initial_params(x)
    np.testing.assert_allclose(blk.value(x, p), x, atol=1e-12)  # starts as the identity
    lo, hi = blk.bounds()
    assert lo[0] == -np.inf and np.all(lo[1:] == 0) and np.all(hi == np.inf)
    R = blk.roughness_matrix()
    assert R.shape == (3, 5)
    np.testing.assert_allclose(R @ p, 0.0, atol=1e-12)  # a straight line is not rough
    kinked = p.copy()
    kinked[3] += 1.0  # a step up of the slope at one knot
    assert np.linalg.norm(R @ kinked) > 0.5
    free = PiecewiseLinear(4)
    pf = free.initial_params(x)
    np.testing.assert_allclose(free.roughness_matrix() @ pf, 0.0, atol=1e-12)
    assert PiecewiseLinear(4, estimate_knots=True).roughness_matrix() is None
    with pytest.raises(ValueError, match="monotone"):
        PiecewiseLinear(4, monotone=True, estimate_knots=True).initial_params(x)


def test_monotone_fit_stays_non_decreasing() -> None:
    u = np.column_stack([_inputs(600, 21), _inputs(600, 22)])
    g1 = np.where(u[:, 0] > 0, u[:, 0], -0.5 * u[:, 0])  # V-shaped: a free fit would make it decrease
    y = lfilter([0, 0.3], [1, -0.8], g1) + lfilter([0, 0.2], [1, -0.5], u[:, 1])
    m = hammerstein([PiecewiseLinear(6, monotone=True), Identity()], nb=1, nf=1, max_nfev=60).fit(u, y)
    vals = m.input_blocks_[0]._split(m.input_params_[0])[1]
    assert np.all(np.diff(vals) >= -1e-9)
    free = hammerstein([PiecewiseLinear(6), Identity()], nb=1, nf=1, max_nfev=60).fit(u, y)
    assert free.cost_ < m.cost_  # the constraint binds on this system


def test_smoothness_grid_holdout_and_init_from_template() -> None:
    u = np.column_stack([_inputs(800, 23), _inputs(800, 24)])
    w = lfilter([0, 0.5], [1, -0.7], u[:, 0]) + lfilter([0, 0.3], [1, -0.5], u[:, 1])
    y = np.clip(w + 0.05 * np.random.default_rng(3).standard_normal(800), -0.5, np.inf)
    template = wiener(Saturation(-0.5), nb=1, nf=1)
    m = HammersteinWiener([PiecewiseLinear(8), PiecewiseLinear(8)], Saturation(-0.5), nb=1, nf=1,
                          init_model=template, smoothness=(0.0, 1.0, 100.0), max_nfev=40).fit(u, y)
    assert set(m.holdout_scores_) == {0.0, 1.0, 100.0} and m.smoothness_ in m.holdout_scores_
    assert m.holdout_scores_[m.smoothness_] == max(m.holdout_scores_.values())
    assert not hasattr(template, "b_")  # the template itself is left unfitted
    wien = wiener(Saturation(-0.5), nb=1, nf=1).fit(u, y)
    assert m.initial_cost_ == pytest.approx(wien.cost_, rel=1e-6)  # started from the fitted template
    assert m.cost_ <= m.initial_cost_
    # a heavy roughness penalty keeps the blocks straight lines
    stiff = HammersteinWiener([PiecewiseLinear(8), PiecewiseLinear(8)], Saturation(-0.5), nb=1, nf=1,
                              init_model=wien, smoothness=1e4, max_nfev=40).fit(u, y)
    for blk, p in zip(stiff.input_blocks_, stiff.input_params_, strict=False):
        assert np.linalg.norm(blk.roughness_matrix() @ p) < 1e-2
    with pytest.raises(ValueError, match="smoothness"):
        HammersteinWiener(smoothness=-1.0).fit(u, y)


@pytest.mark.parametrize("unit_gain,initial", [(True, "zero"), (False, "steady"), (True, "steady")])
def test_exact_jacobian_with_unit_gain_and_steady_start(unit_gain, initial) -> None:
    rng = np.random.default_rng(1)
    u = np.column_stack([_inputs(300, 31), np.abs(_inputs(300, 32)) * 50 + 500, _inputs(300, 33)])
    y = rng.standard_normal(300)
    m = HammersteinWiener([PiecewiseLinear(3), Arrhenius(a=3000.0, estimate=True), PiecewiseLinear(4, monotone=True)],
                          Saturation(-0.8, estimate=True), nb=(2, 1, 3), nf=(2, 1, 2), nk=(1, 0, 1),
                          unit_gain=unit_gain, initial=initial)
    st, u_arr, th = _start(m, u, y)
    # the Arrhenius block cannot be rescaled by its parameter: its B/F keeps a free gain
    assert np.isnan(st.gain[0, 1]) and (np.isfinite(st.gain[0, 0]) == unit_gain)
    th = th + 0.05 * rng.standard_normal(th.size)
    _assert_exact_jacobian(st, u_arr, th)


def test_sample_weight_zero_samples_do_not_enter_the_fit() -> None:
    u = np.column_stack([_inputs(700, 41), _inputs(700, 42)])
    w = lfilter([0, 0.5, 0.2], [1, -1.2, 0.5], u[:, 0]) + lfilter([0, 0.4], [1, -0.6], u[:, 1])
    y = np.clip(w + 0.05 * np.random.default_rng(4).standard_normal(700), -0.7, np.inf)
    weights = np.ones(700)
    weights[500:] = 0.0
    model = wiener(Saturation(-0.7), nb=2, nf=2, nk=1)
    a = HammersteinWiener(**model.get_params()).fit(u, y, sample_weight=weights)
    bad = y.copy()
    bad[500:] = 50.0  # whatever the held-out samples say
    b = HammersteinWiener(**model.get_params()).fit(u, bad, sample_weight=weights)
    np.testing.assert_array_equal(a.b_, b.b_)
    np.testing.assert_array_equal(a.f_, b.f_)
    # the same fit as on the first 500 samples alone: the same model output; the same parameters for input 0 (input
    # 1's first-order truth leaves its second-order B/F a near pole-zero cancellation, a flat direction where the
    # two fits stop at points 2e-6 apart)
    c = HammersteinWiener(**model.get_params()).fit(u[:500], y[:500])
    np.testing.assert_allclose(a.predict(u), c.predict(u), atol=1e-6)
    np.testing.assert_allclose(a.b_[0, 0], c.b_[0, 0], atol=1e-6)
    np.testing.assert_allclose(a.f_[0, 0], c.f_[0, 0], atol=1e-6)
    with pytest.raises(ValueError, match="sample_weight"):
        HammersteinWiener().fit(u, y, sample_weight=np.zeros(700))
    with pytest.raises(ValueError, match="sample_weight"):
        HammersteinWiener().fit(u, y, sample_weight=np.ones(10))


def test_select_by_holdout_finds_the_delay_and_refits_on_all() -> None:
    u = np.column_stack([_inputs(800, 43), _inputs(800, 44)])
    g0 = np.tanh(u[:, 0])
    w = lfilter([0.6, 0.2], [1, -0.5], g0) + lfilter([0, 0.4], [1, -0.6], u[:, 1])  # input 0 acts at once
    y = np.clip(w + 0.02 * np.random.default_rng(5).standard_normal(800), -0.6, np.inf)
    cands = [HammersteinWiener([PiecewiseLinear(6), Identity()], Saturation(-0.6), nb=2, nf=1, nk=nk, max_nfev=60)
             for nk in (1, (0, 1))]
    best, scores = select_by_holdout(cands, u, y)
    assert len(scores) == 2 and scores[1] > scores[0] + 5.0
    assert best.nk == (0, 1) and best.b_[0, 0, 0] != 0.0   # the direct term
    direct = HammersteinWiener(**cands[1].get_params()).fit(u, y)
    np.testing.assert_allclose(best.b_, direct.b_, rtol=1e-9, atol=1e-12)  # the winner refitted on all samples
    assert not hasattr(cands[1], "b_")  # templates stay unfitted
    with pytest.raises(ValueError, match="holdout"):
        select_by_holdout(cands, u, y, holdout=1.0)


def test_smoothness_grid_chooses_as_select_by_holdout() -> None:
    """The ``smoothness`` grid inside ``fit`` and ``select_by_holdout`` share one hold-out rule: same scores, same
    choice, and with ``sample_weight`` the zero-weight samples stay out of the hold-out too."""
    u = np.column_stack([_inputs(600, 47), _inputs(600, 48)])
    y = lfilter([0, 0.5], [1, -0.7], np.tanh(2 * u[:, 0])) + lfilter([0, 0.3], [1, -0.5], u[:, 1])
    y = y + 0.05 * np.random.default_rng(6).standard_normal(600)
    kw = {"input_blocks": [PiecewiseLinear(6), PiecewiseLinear(6)], "nb": 1, "nf": 1, "max_nfev": 30}
    grid = HammersteinWiener(**kw, smoothness=(0.0, 10.0)).fit(u, y)
    best, scores = select_by_holdout([HammersteinWiener(**kw, smoothness=lam) for lam in (10.0, 0.0)], u, y)
    assert grid.holdout_scores_ == pytest.approx({10.0: scores[0], 0.0: scores[1]}, rel=1e-12)
    assert grid.smoothness_ == best.smoothness
    np.testing.assert_allclose(grid.b_, best.b_, rtol=1e-9, atol=1e-12)
    # trailing zero weights: the hold-out is the end of the weighted samples, so the outputs after them do not
    # change the choice or the fit
    w = np.r_[np.ones(500), np.zeros(100)]
    m = HammersteinWiener(**kw, smoothness=(0.0, 10.0)).fit(u, y, sample_weight=w)
    y_junk = np.r_[y[:500], 100.0 + y[500:]]
    m2 = HammersteinWiener(**kw, smoothness=(0.0, 10.0)).fit(u, y_junk, sample_weight=w)
    assert m2.holdout_scores_ == pytest.approx(m.holdout_scores_, rel=1e-9)
    np.testing.assert_allclose(m2.b_, m.b_, rtol=1e-9, atol=1e-12)
    with pytest.raises(ValueError, match="holdout"):   # nothing weighted before the hold-out
        HammersteinWiener(**kw, smoothness=(0.0, 10.0)).fit(u, y, sample_weight=np.r_[np.zeros(590), np.ones(10)])


def test_unit_gain_moves_the_gain_into_the_block() -> None:
    u = np.column_stack([_inputs(800, 45), _inputs(800, 46)])
    g1 = np.tanh(u[:, 0])
    y = lfilter([0, 0.6], [1, -0.8], g1) + lfilter([0, 0.2], [1, -0.5], u[:, 1])  # static gains 3 and 0.4
    m = hammerstein([PiecewiseLinear(8), Identity()], nb=1, nf=1, nk=1, unit_gain=True).fit(u, y)
    gains = m.b_[0].sum(axis=1) / m.f_[0].sum(axis=1)
    assert gains[0] == pytest.approx(1.0, abs=1e-9)        # the free block's B/F: unit static gain
    assert gains[1] == pytest.approx(0.4, abs=1e-2)        # the identity input keeps its gain
    x = np.linspace(-1.5, 1.5, 7)
    np.testing.assert_allclose(m.input_blocks_[0].value(x, m.input_params_[0]), 3.0 * np.tanh(x), atol=0.05)
    assert m.cost_ < 1e-3 * np.var(y)   # up to the piecewise-linear approximation of tanh


def test_steady_start_fits_a_record_that_starts_at_rest() -> None:
    u = np.column_stack([_inputs(600, 47), _inputs(600, 48)])
    u[:, 0] += 1.5   # the record starts far from zero
    pre = np.vstack([np.repeat(u[:1], 400, axis=0), u])   # the system was at rest at u(0) before the record
    w = lfilter([0, 0.1], [1, -0.95], pre[:, 0]) + lfilter([0, 0.4], [1, -0.6], pre[:, 1])
    y = w[400:]
    zero = HammersteinWiener(nb=1, nf=1, nk=1).fit(u, y)
    steady = HammersteinWiener(nb=1, nf=1, nk=1, initial="steady").fit(u, y)
    assert steady.cost_ < 1e-8 and zero.cost_ > 1e-3   # zero start: a transient the data never had
    np.testing.assert_allclose(steady.f_[0, :, 1], [-0.95, -0.6], atol=1e-4)
    with pytest.raises(ValueError, match="initial"):
        HammersteinWiener(initial="guess").fit(u, y)


def test_initial_state_through_the_saturation(fitted) -> None:
    m, u, _ = fitted
    from ident.linear._statespace import simulate_ss

    v = m.transform_inputs(u)
    x_ss = np.linalg.solve(np.eye(m.n_states_) - m.A_, m.B_ @ v[0]) * 1.3   # a state off zero and off rest
    y = m.predict(u, x0=x_ss)
    x_hat = m.initial_state(u, y)
    y_hat = m.predict(u, x0=x_hat)
    np.testing.assert_allclose(y_hat, y, atol=1e-6)
    assert simulate_ss(m.A_, m.B_, m.C_, m.D_, v, x_hat)[0].shape == (len(u), 1)


@pytest.mark.parametrize("value", [0.0, 2.5])
def test_constant_output_is_refused_naming_y(value: float) -> None:
    u = np.column_stack([_inputs(200, 11), _inputs(200, 12)])
    with pytest.raises(ValueError, match=r"^y is constant in column\(s\) \[0\].*Hammerstein-Wiener model"):
        HammersteinWiener(max_nfev=5).fit(u, np.full(200, value))
    with pytest.raises(ValueError, match="^y has no columns"):
        HammersteinWiener(max_nfev=5).fit(u, np.zeros((200, 0)))


def test_output_zero_most_of_the_time_is_fitted() -> None:
    # an NH3-slip-like output, zero over most of the record, is informative where it moves
    u = np.column_stack([_inputs(300, 11), _inputs(300, 12)])
    w = lfilter([0.0, 0.4], [1.0, -0.6], u[:, 0]) + lfilter([0.0, 0.2], [1.0, -0.5], u[:, 1])
    slip = np.maximum(w - np.quantile(w, 0.8), 0.0)
    m = wiener(Saturation(lower=0.0), max_nfev=20).fit(u, slip)
    assert np.all(np.isfinite(m.predict(u)))


def test_failing_linear_start_names_the_hammerstein_wiener_model() -> None:
    # y is not constant over the record, but it is over the weighted part the linear start is fitted on
    u = np.column_stack([_inputs(300, 11), _inputs(300, 12)])
    y = 0.5 * u[:, 0]
    y[:200] = 0.0
    w = np.ones(300)
    w[200:] = 0.0
    with pytest.raises(ValueError, match=r"^cannot fit the Hammerstein-Wiener model: its linear start.*samples "
                                         r"\(0 to 199\).*y is constant"):
        HammersteinWiener(max_nfev=5).fit(u, y, sample_weight=w)


def test_predict_k_step_checks_lengths_k_and_x0() -> None:
    u = np.column_stack([_inputs(200, 11), _inputs(200, 12)])
    y = lfilter([0.0, 0.5], [1.0, -0.7], u[:, 0])
    m = HammersteinWiener(max_nfev=5).fit(u, y)
    with pytest.raises(ValueError, match=r"mismatched lengths \(u: 200, y: 10\)"):
        m.predict_k_step(u, y[:10], 1)
    with pytest.raises(ValueError, match="^y must have 1 columns"):
        m.predict_k_step(u, np.column_stack([y, y]), 1)
    for k in (0, 1.5, -2):
        with pytest.raises(ValueError, match="^k must be a positive integer"):
            m.predict_k_step(u, y, k)
    np.testing.assert_array_equal(m.predict_k_step(u, y, 2), m.predict(u, y0=y))
    with pytest.raises(ValueError, match="^x0 must have"):
        m.predict(u, x0=np.zeros(m.n_states_ + 2))
    with pytest.raises(ValueError, match="^x0 contains NaN"):
        m.predict(u, x0=np.full(m.n_states_, np.inf))
