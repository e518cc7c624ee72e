"""The spill-over features of identification for control (issue 18): the logarithms of the stoichiometric deficit
and excess, the same in numpy and CasADi, with the limits they are meant to have, and an RPEM that uses them."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from ident.control_relevant import (
    DEFICIT_RATIO_FLOOR,
    EXCESS_FLOOR_PPM,
    RATIO_EPS_PPM,
    FeatureMap,
    feature_values,
    smooth_positive_part,
)
from scr_env.constants import NH3_MOL_PER_G_ADBLUE

FLOW_MOL_S, NOX_PPM, T_K = 5.0, 500.0, 600.0


def _dose_g_s(anr: float) -> float:
    """AdBlue [g/s] that doses ``anr`` times the inlet NOx flow."""
    return anr * NOX_PPM * 1e-6 * FLOW_MOL_S / NH3_MOL_PER_G_ADBLUE


def test_deficit_and_excess_follow_the_spill_over_of_a_fast_catalyst() -> None:
    anrs = np.array([0.0, 0.5, 0.9, 0.99, 1.01, 1.1, 2.0])
    deficit = np.array([feature_values("log_deficit", _dose_g_s(a), NOX_PPM, T_K, FLOW_MOL_S) for a in anrs])
    excess = np.array([feature_values("log_excess", _dose_g_s(a), NOX_PPM, T_K, FLOW_MOL_S) for a in anrs])
    assert np.all(np.diff(deficit) < 0) and np.all(np.diff(excess) > 0)
    # below ANR 1 the deficit is the NOx slip ratio of a catalyst that converts every ppm of NH3
    expect = np.log((1 - 0.5) * NOX_PPM / (NOX_PPM + RATIO_EPS_PPM) + DEFICIT_RATIO_FLOOR)
    assert deficit[1] == pytest.approx(expect, abs=1e-3)
    assert deficit[-1] == pytest.approx(np.log(DEFICIT_RATIO_FLOOR), abs=1e-3)       # NOx used up: the floor
    assert excess[0] == pytest.approx(np.log(EXCESS_FLOOR_PPM), abs=1e-2)             # nothing to spill
    assert excess[-1] == pytest.approx(np.log(NOX_PPM + EXCESS_FLOOR_PPM), abs=1e-2)  # ANR 2: the excess slips
    # the marginal NOx benefit is steepest near ANR 1, where a log-linear model in the surplus flattens out
    assert (deficit[2] - deficit[3]) / 0.09 > 5 * (deficit[0] - deficit[1]) / 0.5


@pytest.mark.parametrize("name", ["log_deficit", "log_excess"])
def test_spill_features_are_the_same_in_casadi_and_smooth(name: str) -> None:
    d = ca.SX.sym("d")
    f = ca.Function("f", [d], [feature_values(name, d, NOX_PPM, T_K, FLOW_MOL_S)])
    g = ca.Function("g", [d], [ca.jacobian(f(d), d)])
    for anr in (0.0, 0.7, 1.0, 1.3):
        assert float(f(_dose_g_s(anr))) == pytest.approx(
            float(feature_values(name, _dose_g_s(anr), NOX_PPM, T_K, FLOW_MOL_S)), rel=1e-12)
        assert np.isfinite(float(g(_dose_g_s(anr))))
    fm = FeatureMap(("surplus_ppm", name))
    rec = np.array([[NOX_PPM, _dose_g_s(1.2) * 19.5, T_K, FLOW_MOL_S]])   # inlet NOx, urea g/min, T, flow
    assert fm.from_record(rec).shape == (1, 2)


def test_rpem_for_control_takes_the_spill_features_and_its_nmpc_an_interior_point_solver() -> None:
    from control.blackbox import black_box_nmpc
    from control.evaluation import cycle_segment, evaluate
    from ident.for_control import CONTROL_FEATURES, SPILL_FEATURES, fit_rpem_for_control, identification_records

    records = identification_records(seeds=(10,), duration_s=240.0)
    model, info = fit_rpem_for_control(records, features=CONTROL_FEATURES + SPILL_FEATURES)
    assert info["features"] == [*CONTROL_FEATURES, *SPILL_FEATURES] and len(info["z_scale"]) == 6
    assert all("u5" in t and "u6" in t for t in info["terms"])                # Paper III's linear terms in them
    mpc = black_box_nmpc(model, info, quick=True, solver="ipopt")
    assert mpc.solver == "ipopt" and black_box_nmpc(model, info, quick=True).solver == "sqpmethod"
    for bad in ("newton", ["ipopt"], None):
        with pytest.raises(ValueError, match="solver"):
            black_box_nmpc(model, info, quick=True, solver=bad)
    k = evaluate(mpc, cycles=(cycle_segment("whtc", 20.0, name="whtc_0-20s"),), seeds=(0,),
                 env_kwargs=mpc.env_kwargs)[0].kpis
    assert np.isfinite(k["tailpipe_nox_g_per_kwh"]) and k["adblue_g"] > 0 and mpc.stats()["solves"] == 40
    with pytest.raises(ValueError, match="features"):
        fit_rpem_for_control(records, features=("nox_ppm", "surplus_ppm", "exp_t", "flow"))
    with pytest.raises(ValueError, match="features"):
        fit_rpem_for_control(records, features=(*CONTROL_FEATURES, "temp_k"))


def test_term_generators_name_a_bad_input_count() -> None:
    from ident.for_control import paper3_terms, rpem_storage_terms

    assert paper3_terms(1) == ["1", "x1", "x2", "u1", "u2", "u3", "u4"]
    assert "x2*u6" in rpem_storage_terms(2, 6) and "u5*u3" in rpem_storage_terms(1, 5)
    for bad in (2, 7, True):
        with pytest.raises(ValueError, match="n_inputs"):
            paper3_terms(1, bad)
        with pytest.raises(ValueError, match="n_inputs"):
            rpem_storage_terms(1, bad)


def test_spill_features_match_a_finite_difference_across_anr_one() -> None:
    d = ca.SX.sym("d")
    for name in ("log_deficit", "log_excess"):
        jac = ca.Function("j", [d], [ca.jacobian(feature_values(name, d, NOX_PPM, T_K, FLOW_MOL_S), d)])
        for anr in (0.99, 1.0, 1.01):
            u, h = _dose_g_s(anr), 1e-7
            fd = (feature_values(name, u + h, NOX_PPM, T_K, FLOW_MOL_S)
                  - feature_values(name, u - h, NOX_PPM, T_K, FLOW_MOL_S)) / (2 * h)
            assert float(jac(u)) == pytest.approx(fd, rel=1e-4)
    doses = np.array([0.0, _dose_g_s(1.0), 50.0])                  # vectorised, up to a far over-dose
    for name in ("log_deficit", "log_excess"):
        v = feature_values(name, doses, np.array([0.0, NOX_PPM, 2000.0]), T_K, np.array([0.0, FLOW_MOL_S, 20.0]))
        assert v.shape == (3,) and np.all(np.isfinite(v))


def test_smooth_positive_part_is_within_half_eps_of_the_max_in_numpy_and_casadi() -> None:
    v = np.linspace(-50.0, 50.0, 201)
    eps = 2.0
    got = smooth_positive_part(v, eps)
    assert np.all(got >= np.maximum(v, 0.0)) and np.all(got - np.maximum(v, 0.0) <= eps / 2 + 1e-12)
    x = ca.SX.sym("x")
    f = ca.Function("f", [x], [smooth_positive_part(x, eps)])
    np.testing.assert_allclose(np.asarray(f(ca.DM(v).T)).ravel(), got, rtol=1e-12)
