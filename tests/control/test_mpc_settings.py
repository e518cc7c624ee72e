"""NonlinearMPC settings are checked (ValueError naming the argument), a broken fallback is replaced by the safe
action and counted, and failed solves are counted by kind (issue 24)."""
from __future__ import annotations

import math

import numpy as np
import pytest
from toy_models import OBS
from toy_models import toy_greybox_adapter as _adapter

from control.baselines import LookupTableDosing
from control.evaluation import evaluate
from control.mpc import FAILURE_KINDS, MPCWeights, NonlinearMPC, failure_kind
from control.protocol import action_to_rate


def _mpc(**kw):
    kw.setdefault("horizon", 4)
    kw.setdefault("stage_steps", 2)
    return NonlinearMPC(_adapter(), **kw)


@pytest.mark.parametrize("kw, name", [
    ({"slip_limit_ppm": math.nan}, "slip_limit_ppm"),
    ({"slip_limit_ppm": -1.0}, "slip_limit_ppm"),
    ({"slip_limit_ppm": "ten"}, "slip_limit_ppm"),
    ({"max_rate_change_g_s2": -1.0}, "max_rate_change_g_s2"),
    ({"max_rate_change_g_s2": 0.0}, "max_rate_change_g_s2"),
    ({"max_rate_change_g_s2": math.nan}, "max_rate_change_g_s2"),
    ({"stage_steps": -1}, "stage_steps"),
    ({"stage_steps": 0}, "stage_steps"),
    ({"stage_steps": 2.5}, "stage_steps"),
    ({"stage_steps": True}, "stage_steps"),
    ({"horizon": 0}, "horizon"),
    ({"horizon": -3}, "horizon"),
    ({"horizon": 4.0}, "horizon"),
    ({"horizon": None}, "horizon"),
    ({"weights": {"nox": 20.0}}, "weights"),
    ({"fallback": "lookup_table"}, "fallback"),
    ({"fallback": 0.0}, "fallback"),
    ({"preview": "yes"}, "preview"),
    ({"solver": ""}, "solver"),
    ({"solver_options": [("max_iter", 5)]}, "solver_options"),
])
def test_bad_settings_are_refused_naming_the_argument(kw, name):
    with pytest.raises(ValueError, match=name):
        _mpc(**kw)


@pytest.mark.parametrize("field", ["nox", "nh3", "adblue", "rate_change", "slack"])
@pytest.mark.parametrize("value", [math.nan, math.inf, -1.0, "x"])
def test_bad_weights_are_refused_naming_the_weight(field, value):
    with pytest.raises(ValueError, match=f"MPCWeights.{field}"):
        MPCWeights(**{field: value})


def test_good_settings_pass_and_are_normalised():
    mpc = _mpc(horizon=np.int64(3), stage_steps=np.int32(2), slip_limit_ppm=math.inf,
               max_rate_change_g_s2=math.inf, weights=MPCWeights(adblue=0.0, rate_change=0.0))
    assert type(mpc.horizon) is int and type(mpc.stage_steps) is int
    res = evaluate(mpc, cycles="whsc", max_steps=4)[0]
    assert res.stats["solves"] == 4 and res.stats["solver_failures"] == 0


def test_settings_changed_after_construction_are_checked_when_the_nlp_is_built():
    mpc = _mpc()
    mpc.horizon = 0
    with pytest.raises(ValueError, match="horizon"):
        mpc.predict(OBS, episode_start=np.array([True]))
    mpc = _mpc()
    object.__setattr__(mpc, "weights", MPCWeights())
    object.__setattr__(mpc.weights, "nox", math.nan)   # a frozen dataclass forced
    with pytest.raises(ValueError, match="MPCWeights.nox"):
        mpc.predict(OBS, episode_start=np.array([True]))


class _BadFallback:
    def __init__(self, mode):
        self.mode = mode

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        if self.mode == "raise":
            raise RuntimeError("broken user fallback")
        if self.mode == "nan":
            return np.array([np.nan], dtype=np.float32), None
        if self.mode == "inf":
            return np.array([np.inf]), None
        if self.mode == "empty":
            return np.array([]), None
        return None, None


def _always_failing(mpc):
    def broken(*a, **k):
        raise RuntimeError("casadi: solver error")

    mpc.estimator.make_step = broken
    return mpc


@pytest.mark.parametrize("mode", ["raise", "nan", "inf", "empty", "none"])
def test_a_broken_fallback_gives_the_safe_action_counted_and_the_episode_goes_on(mode, caplog):
    mpc = _always_failing(_mpc(fallback=_BadFallback(mode), max_rate_change_g_s2=100.0))
    res = evaluate(mpc, cycles="whsc", max_steps=6, record_trajectory=True)[0]
    assert res.stats["solver_failures"] == 6 and res.stats["fallback_errors"] == 6
    assert np.all(res.trajectory["adblue_g_s"] == 0.0)   # the safe action: no dosing
    assert res.stats["solver_failures_estimator"] == 6   # the estimator raised (test double)
    # said once per episode at warning level (a user's bug), the rest at debug level
    assert sum("fallback policy" in r.getMessage() and r.levelname == "WARNING" for r in caplog.records) <= 1


def test_a_good_fallback_is_not_counted_as_an_error():
    lut = LookupTableDosing()
    mpc = _always_failing(_mpc(fallback=lut, max_rate_change_g_s2=100.0))
    a, _ = mpc.predict(OBS, episode_start=np.array([True]))
    assert action_to_rate(a[0]) == pytest.approx(lut.dose_g_s(OBS), rel=1e-6)
    assert mpc.stats()["fallback_errors"] == 0 and mpc.stats()["solver_failures"] == 1


def test_failures_are_counted_by_kind_and_logged(caplog):
    import logging

    caplog.set_level(logging.DEBUG, logger="control.mpc")
    mpc = _mpc(solver_options={"ipopt.max_iter": 1}, max_rate_change_g_s2=100.0)
    res = evaluate(mpc, cycles="whsc", max_steps=5)[0]
    s = res.stats
    assert s["solver_failures"] == 5
    assert sum(s[f"solver_failures_{k}"] for k in FAILURE_KINDS) == s["solver_failures"]
    assert s["solver_failures_iteration_limit"] == 5
    assert [f[:2] for f in mpc.failures_] == [(k, "iteration_limit") for k in range(5)]
    assert sum("failed solve (iteration_limit" in r.getMessage() for r in caplog.records) == 5
    # an estimator failure is its own kind
    est = _mpc()
    est.estimator.make_step = lambda *a, **k: (_ for _ in ()).throw(np.linalg.LinAlgError("singular"))
    assert evaluate(est, cycles="whsc", max_steps=2)[0].stats["solver_failures_estimator"] == 2


def test_failure_kinds_of_solver_statuses():
    assert failure_kind("Maximum_Iterations_Exceeded") == "iteration_limit"
    assert failure_kind("Infeasible_Problem_Detected") == "infeasible"
    assert failure_kind("Restoration_Failed") == "restoration"
    assert failure_kind("Invalid_Number_Detected") == "nonfinite_model"
    assert failure_kind("Search_Direction_Becomes_Too_Small") == "small_step"
    assert failure_kind("QP_solver_failed") == "qp_failure"
    assert failure_kind("something new", "SOLVER_RET_NAN") == "nonfinite_model"
    assert failure_kind("Non_Regular_Sensitivities", "SOLVER_RET_NAN") == "nonfinite_model"
    assert failure_kind("Non_Regular_Sensitivities", "SOLVER_RET_UNKNOWN") == "qp_failure"
    assert failure_kind("something new") == "other"


def test_a_rescue_solver_saves_the_failed_solves_of_the_first():
    """An SQP method whose QP solver may pivot once fails every solve; IPOPT as the rescue solver solves them all: no
    failure, every solve counted as rescued with the first solver's kind, and plans applied (not the fallback)."""
    sqp = {"qpsol": "qrqp", "qpsol_options": {"print_iter": False, "print_header": False, "error_on_fail": False,
                                              "max_iter": 1},
           "print_iteration": False, "print_header": False, "print_status": False, "max_iter": 1,
           "error_on_fail": False}
    alone = _mpc(solver="sqpmethod", solver_options=sqp)
    assert evaluate(alone, cycles="whsc", max_steps=4)[0].stats["solver_failures"] == 4
    mpc = _mpc(solver="sqpmethod", solver_options=sqp, rescue_solver="ipopt")
    s = evaluate(mpc, cycles="whsc", max_steps=4)[0].stats
    assert s["solver_failures"] == 0 and s["solver_rescued"] == 4 and len(mpc.rescues_) == 4
    assert all(r[1] in FAILURE_KINDS for r in mpc.rescues_) and mpc.last_plan_ is not None
    assert any(k.startswith("rescue:") for k in mpc.status_counts_)
    # with a hold, the rescue solver goes first for that many steps after a rescue
    held = _mpc(solver="sqpmethod", solver_options=sqp, rescue_solver="ipopt", rescue_hold_steps=3)
    s = evaluate(held, cycles="whsc", max_steps=8)[0].stats
    assert s["solver_failures"] == 0 and s["solver_rescued"] == 2 and s["solver_rescue_held"] == 6
    assert [r[0] for r in held.rescues_] == [0, 4]
    with pytest.raises(ValueError, match="rescue_hold_steps"):
        _mpc(rescue_solver="ipopt", rescue_hold_steps=-1)
    with pytest.raises(ValueError, match="rescue_solver"):
        _mpc(rescue_solver="")
    with pytest.raises(ValueError, match="rescue_options"):
        _mpc(rescue_solver="ipopt", rescue_options="max_iter=5")
