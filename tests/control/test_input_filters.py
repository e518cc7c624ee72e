"""Low-pass filtered inputs of identification for control (issue 18): the filtered surplus columns the models are
identified on are the ones the NMPC's model propagates, for the RPEM (explicit steps) and for a linear-state model
(held over a stage), and bad filter settings are refused by name."""
from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from ident.for_control import (
    check_input_filters,
    filtered_inputs,
    input_filter_coefficient,
    paper3_terms,
    rpem_storage_terms,
)


def test_filtered_inputs_are_the_first_order_recursion_started_at_rest() -> None:
    rng = np.random.default_rng(0)
    z = rng.normal(size=(300, 3))
    dt, tau = 0.5, 20.0
    s = filtered_inputs(z, [(1, tau), (0, 5.0)], dt)
    a = input_filter_coefficient(tau, dt)
    assert a == pytest.approx(1 - np.exp(-dt / tau))
    ref = np.empty(len(z))
    ref[0] = z[0, 1]
    for t in range(1, len(z)):
        ref[t] = ref[t - 1] + a * (z[t - 1, 1] - ref[t - 1])
    np.testing.assert_allclose(s[:, 0], ref, rtol=1e-12, atol=1e-12)
    # causal: the filtered input at t does not move with the input at t; unit gain: a held input is reached
    z2 = z.copy()
    z2[100:, 0] += 1.0
    s2 = filtered_inputs(z2, [(0, 5.0)], dt)
    np.testing.assert_array_equal(s2[:101, 0], s[:101, 1])
    held = filtered_inputs(np.full((400, 1), 3.0), [(0, 10.0)], dt)
    np.testing.assert_allclose(held, 3.0)


def test_bad_input_filters_are_refused_by_name() -> None:
    feats = ("surplus_ppm", "nox_ppm", "exp_t", "flow")
    assert check_input_filters([("surplus_ppm", 300)], feats) == [(0, 300.0)]
    assert check_input_filters([["flow", 60.0], ["surplus_ppm", 5]], feats) == [(3, 60.0), (0, 5.0)]
    for bad in ([("temp_k", 60.0)], [("surplus_ppm", 0.0)], [("surplus_ppm", -1.0)], [("surplus_ppm", np.inf)],
                [("surplus_ppm", "60")], [("surplus_ppm", True)], ["surplus_ppm"], [("surplus_ppm", 60.0, 1)]):
        with pytest.raises(ValueError, match="input_filters"):
            check_input_filters(bad, feats)


def test_term_generators_number_the_filtered_inputs_after_the_features() -> None:
    assert paper3_terms(1, 4, 2) == ["1", "x1", "x2", "u1", "u2", "u3", "u4", "u5", "u6"]
    t = rpem_storage_terms(2, 4, 1)
    assert {"u5", "x2*u5", "x1*u5", "u5*u3", "u5*u3'", "x2*u5*u3"} <= set(t) and "u6" not in t
    assert rpem_storage_terms(1, 4) == rpem_storage_terms(1, 4, 0)     # no filters: the regressor as before
    with pytest.raises(ValueError, match="n_filtered"):
        rpem_storage_terms(1, 4, -1)


def test_rpem_with_a_filtered_surplus_runs_in_the_nmpc_on_the_identified_columns() -> None:
    from control.blackbox import OBS_FLOW, OBS_NOX_IN, OBS_T, black_box_nmpc
    from control.evaluation import cycle_segment, evaluate
    from ident.for_control import fit_rpem_for_control, identification_records, model_arrays

    records = identification_records(seeds=(10,), duration_s=240.0)
    model, info = fit_rpem_for_control(records, input_filters=[("surplus_ppm", 120.0)])
    assert info["input_filters"] == [["surplus_ppm", 120.0]] and len(info["z_scale"]) == 5
    assert all("u5" in t for t in info["terms"])                       # the filtered surplus is an input
    mpc = black_box_nmpc(model, info, quick=True)
    bm = mpc.model
    nxm = int(model.to_casadi().size1_in(0))
    assert bm.nf == 1 and bm.nx == nxm + 1 and bm.nz == 4
    # the NMPC's filter state, propagated from the features, is the identified filtered column
    (z, _) = model_arrays(records[:1], info)[0]
    zn = (z - np.asarray(info["z_mean"])) / np.asarray(info["z_scale"])
    x = np.r_[np.zeros(nxm), zn[0, 4]]
    xs, zs = ca.SX.sym("x", bm.nx), ca.SX.sym("z", bm.nz)
    xn, _ = bm._call(xs, zs, ca.SX.zeros(0))
    step = ca.Function("step", [xs, zs], [xn])
    for t in range(1, 200):
        x = np.asarray(step(x, zn[t - 1, :4])).ravel()
        assert x[-1] == pytest.approx(zn[t, 4], abs=1e-9)
    # at the start of an episode the filter rests at the feature with no dose
    obs = np.zeros(7)
    obs[[OBS_NOX_IN, OBS_T, OBS_FLOW]] = (400.0, 550.0, 5.0)
    bm.reset_estimate(obs)
    z0 = bm.z_norm(0.0, 400.0, 550.0, 5.0)
    assert bm.ekf_.x_[bm.nx - 1] == pytest.approx(z0[0])
    k = evaluate(mpc, cycles=(cycle_segment("whtc", 20.0, name="whtc_0-20s"),), seeds=(0,),
                 env_kwargs=mpc.env_kwargs)[0].kpis
    assert np.isfinite(k["tailpipe_nox_g_per_kwh"]) and mpc.stats()["solves"] == 40


def test_a_linear_state_model_holds_the_filtered_input_over_a_stage_and_filters_exactly() -> None:
    from control.blackbox import BlackBoxModel
    from ident.control_relevant import FeatureMap

    A = np.array([[0.9]])
    xs, zs = ca.SX.sym("x", 1), ca.SX.sym("z", 3)          # two features and one filtered input
    bz = 0.1 * zs[0] + 0.05 * zs[2] ** 2
    step = ca.Function("step", [xs, zs], [A[0, 0] * xs + bz, ca.vertcat(xs, xs)])
    bfun = ca.Function("b", [zs], [bz])
    bm = BlackBoxModel(step, FeatureMap(("surplus_ppm", "exp_t")), [0, 0], [1, 1], [0, 0], [1, 1],
                       linear=(A, lambda z: bfun(z)), input_filters=[(0, 10.0)], nh3_sensor=False)
    assert bm.nx == 2 and bm.nz == 2
    a = input_filter_coefficient(10.0, bm.model_dt)
    x0, z = np.array([0.3, -0.5]), np.array([1.5, 0.2])
    xe, _ = bm.stage_function(8)(x0, z, np.zeros(2))
    xe = np.asarray(xe).ravel()
    assert xe[1] == pytest.approx(z[0] + (1 - a) ** 8 * (x0[1] - z[0]))          # the filter state exact
    held = 0.9 ** 8 * x0[0] + sum(0.9 ** j for j in range(8)) * (0.1 * z[0] + 0.05 * x0[1] ** 2)
    assert xe[0] == pytest.approx(held)                                          # the filtered input held
    one, _ = bm.stage_function(1)(x0, z, np.zeros(2))
    exact, _ = bm._call(ca.DM(x0), ca.DM(z), ca.DM.zeros(0))
    np.testing.assert_allclose(np.asarray(one).ravel(), np.asarray(exact).ravel(), rtol=1e-12)
    with pytest.raises(ValueError, match="input_filters"):
        BlackBoxModel(step, FeatureMap(("surplus_ppm", "exp_t")), [0, 0], [1, 1], [0, 0], [1, 1],
                      input_filters=[(2, 10.0)], nh3_sensor=False)


def test_hammerstein_wiener_with_a_filtered_surplus_is_normalised_as_its_feature_and_runs_in_the_nmpc() -> None:
    from control.blackbox import black_box_nmpc
    from control.evaluation import cycle_segment, evaluate
    from ident.for_control import fit_hw_for_control, identification_records

    records = identification_records(seeds=(10,), duration_s=240.0)
    model, info = fit_hw_for_control(records, max_nfev=3, input_filters=[("surplus_ppm", 60.0)])
    assert info["input_filters"] == [["surplus_ppm", 60.0]] and model.n_inputs_ == 5
    assert info["z_mean"][4] == info["z_mean"][0] and info["z_scale"][4] == info["z_scale"][0]
    mpc = black_box_nmpc(model, info, quick=True)
    assert mpc.model.nf == 1 and mpc.model.nx == mpc.model.nx_model + 1
    k = evaluate(mpc, cycles=(cycle_segment("whtc", 20.0, name="whtc_0-20s"),), seeds=(0,),
                 env_kwargs=mpc.env_kwargs)[0].kpis
    assert np.isfinite(k["tailpipe_nox_g_per_kwh"]) and mpc.stats()["solves"] == 40
