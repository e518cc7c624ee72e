"""control.factory: the benchmarked controllers by name, built from a fitted grey-box object (never a dict)."""
from __future__ import annotations

import numpy as np
import pytest

from control.baselines import FeedforwardPI, LookupTableDosing
from control.estimation import ObservationEKF, PrivilegedState
from control.factory import (
    CONTROLLERS,
    IDENTIFIED_COVERAGE_P0,
    IDENTIFIED_VARIANTS,
    identified_mpc,
    make_controller,
    multirate_oracle_mpc,
    oracle_mpc,
    single_rate_oracle_mpc,
)
from control.mpc import NonlinearMPC
from ident.greybox import StorageGreyBox

PARAMS = [-0.0803, -0.2129, 0.2140, -0.1841, 0.1300, 0.9155, -0.0592, 0.0613, 0.9172, -0.2831, 0.0290]


@pytest.fixture(scope="module")
def model():
    return StorageGreyBox.from_params(PARAMS, [0.9394, 1.1639])


def test_every_controller_by_name(model) -> None:
    built = {n: make_controller(n, model, quick=True) for n in CONTROLLERS}
    assert isinstance(built["lookup_table"], LookupTableDosing) and isinstance(built["pi"], FeedforwardPI)
    for n in IDENTIFIED_VARIANTS:
        mpc = built[n]
        assert isinstance(mpc, NonlinearMPC) and isinstance(mpc.estimator, ObservationEKF) and mpc.horizon == 10
    assert built["mpc_identified"].env_kwargs == {"nh3_sensor": True}
    assert built["mpc_identified"].estimator.measured_obs == (3, 5) and built["mpc_identified"].slip_guard
    assert built["mpc_identified_nox_sensor"].env_kwargs == {} and built["mpc_identified_nox_sensor"].preview
    assert not built["mpc_identified_no_preview"].preview
    assert isinstance(built["mpc_oracle"].estimator, PrivilegedState) and built["mpc_oracle"].preview


def test_identified_mpc_takes_a_fitted_model_not_a_dict(model) -> None:
    with pytest.raises(TypeError, match="StorageGreyBox"):
        identified_mpc({"params": PARAMS, "sensor_gains": [1, 1], "n_cells": 2, "dt": 0.5})
    from ident.base import NotFittedError

    with pytest.raises(NotFittedError, match="not fitted"):
        identified_mpc(StorageGreyBox())
    with pytest.raises(ValueError, match="needs the fitted grey-box"):
        make_controller("mpc_identified", None)
    assert single_rate_oracle_mpc(safe_slip_ppm=20.0).model.safe_slip_ppm == 20.0
    # the reference oracle is the multi-rate one: 10 stages of 2 s, then 4 of 60 s (a 260 s horizon)
    assert oracle_mpc().stage_intervals() == (4,) * 10 + (120,) * 4
    assert oracle_mpc().slip_budget_ppm == multirate_oracle_mpc().slip_budget_ppm == 8.0
    assert make_controller("mpc_oracle_single_rate").stage_intervals() == (4,) * 20


def test_the_estimator_is_shared_not_hidden(model) -> None:
    """An estimator object passed on to another MPC goes on from where it is (do-mpc's split)."""
    from control.evaluation import evaluate

    mpc = identified_mpc(model, quick=True, nh3_sensor=False)
    evaluate(mpc, cycles="whsc", max_steps=5)
    x = mpc.estimator.x_.copy()
    twin = NonlinearMPC(mpc.model, horizon=5, stage_steps=4, estimator=mpc.estimator, solver=mpc.solver,
                        solver_options=mpc.solver_options)
    assert twin.estimator is mpc.estimator and np.array_equal(twin.estimator.x_, x)


def test_oracle_stages_take_whole_numbers_and_name_the_bad_argument():
    from control.factory import ORACLE_FINE_STAGES, oracle_stages

    fine = (4,) * ORACLE_FINE_STAGES
    assert oracle_stages(2, coarse_stage_steps=np.int64(60)) == fine + (60, 60)
    assert oracle_stages(2.0, coarse_stage_steps=60.0) == fine + (60, 60)
    assert oracle_stages(0) == fine
    assert oracle_stages(3, quick=True, coarse_stage_steps=8) == (4,) * (ORACLE_FINE_STAGES // 2) + (8,)
    assert oracle_stages(1, quick=True) == (4,) * (ORACLE_FINE_STAGES // 2)   # half of one coarse stage: none
    for bad in (-1, 2.5, True, "4", float("nan"), float("inf")):
        with pytest.raises(ValueError, match="coarse_stages"):
            oracle_stages(bad)
    for bad in (0, 0.5, False, None.__class__):
        with pytest.raises(ValueError, match="coarse_stage_steps"):
            oracle_stages(coarse_stage_steps=bad)


def test_the_coverage_prior_bounds_what_one_noisy_nh3_reading_does_at_a_cold_start(model) -> None:
    """At 500 K the NH3 sensor sees the coverage weakly: with the EKF's unit prior one 20 ppm reading of a clean
    catalyst put 0.12 coverage in the outlet cell (the NMPC then predicted slip and stopped dosing); the coverage
    prior keeps that reading from moving the estimate far."""
    def coverage_after_one_reading(p0: float) -> np.ndarray:
        est = identified_mpc(model, quick=True, coverage_p0=p0).estimator
        obs = np.array([300.0, 500.0, 0.3, 300.0, -1.0, 0.0])   # NOx in, T in [K], flow, NOx sensor, action, NH3
        dist = np.array([0.3, 500.0, 300.0, 0.0])
        est.reset(obs)
        est.make_step(obs, 0.0, dist)
        noisy = obs.copy()
        noisy[3] += 20.0
        noisy[5] = 20.0                                          # a 20 ppm NH3 reading (sensor noise)
        return est.make_step(noisy, 0.0, dist)[:model.n_cells]

    wide, tight = coverage_after_one_reading(1.0), coverage_after_one_reading(1e-2)
    assert np.max(wide) > 0.05 and np.max(tight) < 0.01
    # the default is the calibrated prior on every cell (the temperature state keeps 1 K^2)
    est = identified_mpc(model, quick=True).estimator
    est.reset(np.array([300.0, 500.0, 0.3, 300.0, -1.0, 0.0]))
    assert np.allclose(np.diag(est.ekf_.P_), [IDENTIFIED_COVERAGE_P0] * model.n_cells + [1.0])
    assert np.max(coverage_after_one_reading(IDENTIFIED_COVERAGE_P0)) < np.max(tight)
    with pytest.raises(ValueError, match="coverage_p0"):
        identified_mpc(model, coverage_p0=0.0)
    for bad in (float("nan"), True, "0.001", -1e-3):
        with pytest.raises(ValueError, match="coverage_p0"):
            identified_mpc(model, coverage_p0=bad)


def test_the_control_interval_is_the_environments() -> None:
    from control.factory import CONTROL_INTERVAL_S
    from scr_env.envs.config import make_config

    assert make_config().dt == CONTROL_INTERVAL_S
