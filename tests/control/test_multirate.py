"""Multi-rate stages of NonlinearMPC (issue 19): uniform ``stages`` are the old NLP exactly, the settings are checked
(ValueError naming the argument), the preview is averaged over each stage, the oracle's stage temperatures are the
plant's at each stage's end, and the time-weighted slip price enters the objective only when set."""
from __future__ import annotations

import math

import numpy as np
import pytest
from toy_models import OBS
from toy_models import toy_greybox_adapter as _adapter

from control.evaluation import evaluate
from control.models import FirstPrinciplesModel
from control.mpc import MPCWeights, NonlinearMPC
from scr_env.envs.urea_scr import UreaSCREnv


def _doses(mpc, cycle="whsc", steps=8):
    res = evaluate(mpc, cycles=(cycle,), max_steps=steps, record_trajectory=True)[0]
    assert res.stats["solver_failures"] == 0
    return res.trajectory["adblue_g_s"]


@pytest.mark.parametrize("make", [
    lambda **kw: NonlinearMPC(_adapter(), **kw),
    lambda **kw: NonlinearMPC(FirstPrinciplesModel(), preview=True, **kw),
], ids=["identified", "oracle"])
def test_uniform_stages_are_the_old_nlp_exactly(make):
    old = _doses(make(horizon=3, stage_steps=2))
    new = make(stages=(2, 2, 2))
    assert new.horizon == 3 and new.stage_steps == 2 and new.stage_intervals() == (2, 2, 2)
    assert np.array_equal(_doses(new), old)


@pytest.mark.parametrize("stages", [[], [4, 0], [4, -1], [4, 2.5], [4, True], "44", 4])
def test_bad_stages_are_refused_naming_the_argument(stages):
    with pytest.raises(ValueError, match="stages"):
        NonlinearMPC(_adapter(), stages=stages)


def test_stages_changed_against_horizon_are_refused_when_the_nlp_is_built():
    mpc = NonlinearMPC(_adapter(), stages=(2, 4))
    mpc.horizon = 3
    with pytest.raises(ValueError, match="horizon"):
        mpc.predict(OBS, episode_start=np.array([True]))


@pytest.mark.parametrize("value", [math.nan, math.inf, -1.0, "x"])
def test_bad_slip_price_is_refused_naming_it(value):
    with pytest.raises(ValueError, match="MPCWeights.nh3_ppm_s"):
        MPCWeights(nh3_ppm_s=value)


def test_multirate_preview_is_the_mean_over_each_stage():
    mpc = NonlinearMPC(_adapter(), stages=(1, 3, 6), preview=True)
    env = UreaSCREnv(cycle="whtc")
    env.reset(seed=0)
    for _ in range(300):
        env.step(np.zeros(1, dtype=np.float32))
    mpc.attach(env)
    d = mpc._disturbances(OBS)
    prev = env.disturbance_preview(10)
    assert d.shape == (3, 4)
    assert np.allclose(d, [prev[0], prev[1:4].mean(axis=0), prev[4:10].mean(axis=0)])


def test_oracle_multirate_stage_temperatures_are_the_plant_s_at_each_stage_end():
    env = UreaSCREnv(cycle="whtc")
    env.reset(seed=0)
    for _ in range(600):   # into the cycle: the temperatures move
        env.step(np.zeros(1, dtype=np.float32))
    model = FirstPrinciplesModel()
    model.attach(env)
    dt, ks = float(env.dt), np.array([2, 2, 6])
    dist = env.disturbance_preview(10)
    stage_d = np.array([dist[0:2].mean(0), dist[2:4].mean(0), dist[4:10].mean(0)])
    pst, _ = model.stage_parameters(None, stage_d, ks * dt, dt)
    temps = model._temperatures(env.state["temperature_k"].astype(np.float64), np.repeat(stage_d, ks, axis=0), dt)
    assert np.allclose(pst[:, 4:], model._constants(temps[np.cumsum(ks) - 1].ravel()).reshape(3, -1))
    # an array of equal lengths is the uniform call
    u1, c1 = model.stage_parameters(None, stage_d, 2 * dt, dt)
    u2, c2 = model.stage_parameters(None, stage_d, np.full(3, 2 * dt), dt)
    assert np.array_equal(u1, u2) and np.array_equal(c1, c2)
    with pytest.raises(ValueError, match="one per stage"):
        model.stage_parameters(None, stage_d, np.full(2, dt), dt)


def test_multirate_oracle_solves_and_its_plan_covers_every_stage():
    mpc = NonlinearMPC(FirstPrinciplesModel(), stages=(2, 2, 8, 8), preview=True,
                       weights=MPCWeights(nh3_ppm_s=1e-3), slip_limit_ppm=math.inf)
    _doses(mpc, steps=6)
    assert mpc.last_plan_["u"].shape == (4,) and mpc.last_plan_["x"].shape[0] == 4


def test_a_failed_solve_follows_the_last_plan_through_its_multirate_stages():
    mpc = NonlinearMPC(_adapter(), stages=(1, 2, 3), max_rate_change_g_s2=100.0)
    mpc.predict(OBS, episode_start=np.array([True]))
    plan = np.array([0.1, 0.2, 0.3])
    mpc.last_plan_ = {"u": plan, "x": np.zeros((3, 3)), "slack": np.zeros(3)}

    def broken(*a, **k):
        raise RuntimeError("casadi: solver error")

    mpc.estimator.make_step = broken
    rates = []
    for _ in range(7):
        mpc.predict(OBS)
        rates.append(mpc._u_prev)
    # ages 1..6 fall in stages 1, 1, 2, 2, 2 and then past the plan (the look-up table)
    assert rates[:5] == pytest.approx([0.2, 0.2, 0.3, 0.3, 0.3])
    assert mpc.stats()["solver_failures"] == 7


class _FakeEnv:
    """What the slip budget reads: the step index and the episode's mean slip so far."""

    def __init__(self, mean_slip: float, steps: int) -> None:
        self.mean_slip, self.step_index = mean_slip, steps

    def episode_kpis(self) -> dict:
        return {"mean_nh3_slip_ppm": self.mean_slip}


def test_slip_budget_price_rises_only_above_the_budget():
    from control.mpc import BUDGET_PRIOR_S, MAX_PRICE_EXPONENT

    mpc = NonlinearMPC(_adapter(), weights=MPCWeights(nh3_ppm_s=1e-3), slip_budget_ppm=8.0, slip_budget_gain=3.0)
    for slip, steps, want in [(0.0, 0, 1.0), (5.0, 3600, 1.0), (8.0, 3600, 1.0),
                              (16.0, 3600, math.exp(3.0 * (16.0 * 1800 + 8.0 * BUDGET_PRIOR_S)
                                                    / (1800 + BUDGET_PRIOR_S) / 8.0 - 3.0)),
                              (1e6, 3600, math.exp(MAX_PRICE_EXPONENT))]:
        mpc._budget_env = _FakeEnv(slip, steps)
        assert mpc._slip_price_factor() == pytest.approx(want)
    # a spike in the first seconds barely moves it (the prior of BUDGET_PRIOR_S at the budget)
    mpc._budget_env = _FakeEnv(40.0, 10)   # 5 s at 40 ppm
    assert mpc._slip_price_factor() < 1.5
    assert mpc.stats()["slip_price_factor_max"] == pytest.approx(math.exp(MAX_PRICE_EXPONENT))


def test_slip_budget_settings_are_checked_naming_them():
    with pytest.raises(ValueError, match="nh3_ppm_s"):
        NonlinearMPC(_adapter(), slip_budget_ppm=8.0)
    for bad in (0.0, -1.0, math.nan, math.inf):
        with pytest.raises(ValueError, match="slip_budget_ppm"):
            NonlinearMPC(_adapter(), weights=MPCWeights(nh3_ppm_s=1e-3), slip_budget_ppm=bad)
    with pytest.raises(ValueError, match="slip_budget_gain"):
        NonlinearMPC(_adapter(), weights=MPCWeights(nh3_ppm_s=1e-3), slip_budget_ppm=8.0, slip_budget_gain=-1.0)


def test_slip_budget_under_budget_is_the_fixed_price_nlp():
    """Within the budget the price factor is 1: the doses equal the fixed-price NMPC's (the price is an NLP
    parameter instead of a constant)."""
    w = MPCWeights(nh3_ppm_s=1e-3)
    fixed = _doses(NonlinearMPC(FirstPrinciplesModel(), preview=True, stages=(2, 2, 8), weights=w))
    tracked = NonlinearMPC(FirstPrinciplesModel(), preview=True, stages=(2, 2, 8), weights=w, slip_budget_ppm=8.0)
    np.testing.assert_allclose(_doses(tracked), fixed, rtol=1e-9, atol=1e-12)
    assert tracked.stats()["slip_price_factor_max"] == 1.0
