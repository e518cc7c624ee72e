"""The projection onto the model set DM (issue 21, part 2): the stability degree and spectral radius used to measure
how far an estimate is outside DM, and an estimate that starts outside DM (theta = 0, a chain of integrators) moving
towards it instead of freezing with every update rejected."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from ident.rpem import RecursivePEM
from ident.rpem.kernel import dm_violation, is_hurwitz, max_real_eigenvalue, spectral_radius


@pytest.mark.parametrize("n", [1, 2, 3, 4])
def test_stability_degree_and_spectral_radius_match_the_eigenvalues(n):
    rng = np.random.default_rng(n)
    for _ in range(25):
        J = rng.standard_normal((n, n)) * rng.uniform(0.1, 10.0)
        eig = np.linalg.eigvals(J)
        scale = max(1.0, np.abs(eig).max())
        assert max_real_eigenvalue(J) == pytest.approx(eig.real.max(), abs=1e-6 * scale)
        assert spectral_radius(J) == pytest.approx(np.abs(eig).max(), abs=1e-6 * scale)
    assert spectral_radius(np.zeros((n, n))) == 0.0
    v, w = dm_violation(-np.eye(n), 0.5 * np.eye(n), 0.1)  # inside DM: no violation
    assert v == 0.0 and w == 0.0
    v, w = dm_violation(np.eye(n), 2.0 * np.eye(n), 0.1)
    assert v == pytest.approx(1.1) and w == pytest.approx(1.0)


def _linear_data(n: int, seed: int):
    """x'' = 2 u - x - x' under a held input, sampled at 0.1 s."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-1.0, 1.0, n // 10 + 1), 10)[:n]
    x, y = np.zeros(2), np.empty(n)
    for t in range(n):
        y[t] = x[0]
        for _ in range(10):
            x = x + 0.01 * np.array([x[1], 2.0 * u[t] - x[0] - x[1]])
    return u, y + 0.005 * rng.standard_normal(n)


def test_a_start_outside_the_model_set_moves_towards_it():
    """A start just outside DM (x2' = u - x1 + 0.05 x2: unstable everywhere): the thesis' rule refused every update
    that did not land inside DM at once, and the estimate froze there ("N of N updates rejected"). Updates that make
    it no less stable are now accepted: it moves into DM and fits, without a warning."""
    u, y = _linear_data(3000, seed=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        est = RecursivePEM(n_states=2, terms=["u1", "x1", "x2"], sampling_period=0.1, method="euler",
                           theta0=[1.0, -1.0, 0.05], n_passes=3).fit(u, y)
    assert est.n_rejected_ < 0.5 * est.n_updates_
    J = np.array([[0.0, 1.0], [est.theta_[1], est.theta_[2]]])
    assert is_hurwitz(J, est.stability_margin)  # it ends inside DM
    uv, yv = _linear_data(1000, seed=1)
    assert est.score(uv, yv) > 90.0


def test_theta_zero_start_with_the_thesis_defaults_still_warns():
    """theta = 0 is a chain of integrators, on the edge of stability: every small update from it makes either the
    continuous-time or the discretised model less stable, so nearly every update is refused, and fit says so (a
    real freeze, not a false alarm); the automatic settings start from data instead."""
    u, y = _linear_data(1000, seed=0)
    with pytest.warns(RuntimeWarning, match="parameter updates were rejected"):
        est = RecursivePEM(n_states=2, terms=["u1", "x1", "x2"], sampling_period=0.1, method="euler").fit(u, y)
    assert est.n_rejected_ > 0.9 * est.n_updates_
