"""control.adaptive: the drift model, the RPEM wiring through public methods, and a bad observation refused
before any estimator moves. (The ageing study end to end: tests/experiments/test_adaptive_ageing.py.)"""
from __future__ import annotations

import numpy as np
import pytest

from control.adaptive import AdaptiveMPC, DriftModelAdapter, drift_step
from control.evaluation import evaluate
from ident.greybox import StorageGreyBox

PARAMS = [-0.0803, -0.2129, 0.2140, -0.1841, 0.1300, 0.9155, -0.0592, 0.0613, 0.9172, -0.2831, 0.0290]


@pytest.fixture(scope="module")
def model():
    return StorageGreyBox.from_params(PARAMS, [0.9394, 1.1639])


def test_adaptive_mpc_estimates_and_carries_the_drift_over_episodes(model) -> None:
    pol = AdaptiveMPC(model, quick=True)
    assert isinstance(pol.mpc.model, DriftModelAdapter) and pol.mpc.estimator is pol.estimator
    assert np.array_equal(pol.drift_, [0.0, 0.0])
    evaluate(pol, cycles="whsc", max_steps=30, seeds=(0, 1))
    d = pol.drift_
    assert pol.rpem.n_updates_ == 2 * 29 and np.all(d >= np.log(0.2) - 1e-12) and np.all(d <= np.log(1.05) + 1e-12)
    assert pol.episode == 1 and np.array_equal(pol.adapter.drift_, d)
    # the estimator's model follows the drift: its step at the current d
    x, u = np.array([0.2, 0.1, 520.0]), np.array([400.0, 20.0, 530.0, 8.0])
    np.testing.assert_array_equal(np.asarray(pol.estimator.step(x, u)[1]),
                                  np.asarray(drift_step(model)(x, u, pol._estimator_drift)[1]))


def test_a_bad_observation_changes_nothing(model) -> None:
    pol = AdaptiveMPC(model, quick=True)
    obs = np.array([500.0, 560.0, 6.0, 30.0, -1.0])
    pol.predict(obs, episode_start=np.array([True]))
    before = (pol.rpem.n_updates_, pol.drift_.copy(), pol._calls, len(pol.history))
    with pytest.raises(ValueError, match="NaN"):
        pol.predict(np.array([500.0, np.nan, 6.0, 30.0, -1.0]))
    assert (pol.rpem.n_updates_, pol._calls, len(pol.history)) == (before[0], before[2], before[3])
    assert np.array_equal(pol.drift_, before[1])


def test_arguments_are_checked(model) -> None:
    with pytest.raises(ValueError, match="free"):
        AdaptiveMPC(model, free=("capacity", "colour"))
    with pytest.raises(ValueError, match="box"):
        AdaptiveMPC(model, box=(1.2, 2.0))


def test_rpem_restarts_its_state_and_clips_its_estimate_through_public_methods() -> None:
    from ident.rpem.parametric import ParametricRPEM

    model = StorageGreyBox.from_params(PARAMS, [0.9394, 1.1639])
    r = ParametricRPEM(drift_step(model), p0=[0.0, 0.0], output_indices=[2])
    with pytest.raises(RuntimeError, match="start"):
        r.reset_state([0.0, 0.0, 500.0])
    r.start([0.0, 0.0, 500.0])
    r.update([500.0, 30.0, 550.0, 8.0], [40.0])
    r.params_[:] = [0.5, -3.0]
    assert np.array_equal(r.clip_params(np.log(0.2), np.log(1.05)), [np.log(1.05), np.log(0.2)])
    r.reset_state([0.1, 0.1, 520.0])
    assert np.array_equal(r.state_, [0.1, 0.1, 520.0]) and not r.sensitivity_.any()
    with pytest.raises(ValueError, match="x0"):
        r.reset_state([0.0, np.nan, 500.0])
