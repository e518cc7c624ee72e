"""ident.rpem.StructureSearch (the automatic structure choice of issue 21) and RecursivePEM's refit on the whole
record: what is tried, what is chosen, on which data, and the checks of its arguments."""
from __future__ import annotations

import numpy as np
import pytest

from ident.metrics import compare
from ident.rpem import AUTO_SETTINGS, RecursivePEM, StructureSearch


def _sign_insensitive_data(n: int, seed: int):
    """A lightly damped second-order system under a held random input, measured as ``|v|`` plus noise."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-1.0, 1.0, n // 8 + 1), 8)[:n]
    h, v, dv, y = 0.05, 0.0, 0.0, np.empty(n)
    for t in range(n):
        y[t] = abs(v)
        for _ in range(5):  # Euler sub-steps of the continuous system v'' + 0.8 v' + 4 v = 4 u
            v, dv = v + h / 5 * dv, dv + h / 5 * (4.0 * u[t] - 4.0 * v - 0.8 * dv)
    return u, y + 0.01 * rng.standard_normal(n)


SMALL_GRID = {"orders": (1, 2), "degrees": (1, 2), "outputs": ("identity", "abs")}


@pytest.fixture(scope="module")
def drive_search():
    u, y = _sign_insensitive_data(1200, seed=0)
    return StructureSearch(sampling_period=0.05, **SMALL_GRID).fit(u, y), (u, y)


def test_search_finds_the_sign_insensitive_output_and_reports_what_it_tried(drive_search):
    search, _ = drive_search
    assert search.best_params_["output"] == "abs" and search.best_params_["n_states"] == 2
    stage1 = [r for r in search.results_ if r["stage"] == 1]
    assert {(r["n_states"], r["output"]) for r in stage1} == {(1, "identity"), (1, "abs"), (2, "identity"),
                                                             (2, "abs")}
    assert all(r["total_degree"] == 1 for r in stage1)
    assert any(r["stage"] == 2 and r["total_degree"] == 2 for r in search.results_)
    chosen = [r for r in search.results_ if "chosen" in r["note"]]
    assert len(chosen) == 1 and chosen[0]["holdout_fit"] == pytest.approx(search.best_score_)
    # the identity output cannot follow a sign-insensitive sensor: the hold-out says so
    identity = max(r["holdout_fit"] for r in search.results_ if r["output"] == "identity")
    assert search.best_score_ > identity + 20.0
    text = search.table()
    assert "hold-out FIT" in text and "chosen" in text and len(text.splitlines()) == len(search.results_) + 1
    # the record is short (1200 <= screen_samples): the chosen screening fit is the final model, refitted
    assert search.n_screen_samples_ == 1200 and not any(r["stage"] == "final" for r in search.results_)
    assert isinstance(search.best_estimator_, RecursivePEM) and search.best_estimator_.output == "abs"
    assert search.search_time_s_ > 0


def test_search_forwards_to_the_chosen_model(drive_search, tmp_path):
    search, _ = drive_search
    uv, yv = _sign_insensitive_data(600, seed=7)
    fit = compare(search, uv, yv).fit
    assert fit == pytest.approx(compare(search.best_estimator_, uv, yv).fit) and fit > 80.0
    np.testing.assert_array_equal(search.predict(uv), search.best_estimator_.predict(uv))
    assert search.score(uv, yv) == pytest.approx(search.best_estimator_.score(uv, yv))
    assert search.predict_k_step(uv, yv, 3).shape == (600, 1)
    back = RecursivePEM.load(search.save(tmp_path / "chosen"))
    np.testing.assert_array_equal(back.predict(uv, x0=search.initial_state(uv, yv)),
                                  search.predict(uv, x0=search.initial_state(uv, yv)))
    with pytest.raises(ValueError, match="RecursivePEM.load"):
        StructureSearch.load(tmp_path / "chosen")


def test_long_records_are_screened_on_their_first_samples_and_the_choice_refitted_on_all():
    u, y = _sign_insensitive_data(900, seed=3)
    search = StructureSearch(sampling_period=0.05, orders=(2,), degrees=(1,), outputs=("identity", "abs"),
                             screen_samples=400).fit(u, y)
    assert search.n_screen_samples_ == 400
    final = search.results_[-1]
    assert final["stage"] == "final" and final["output"] == search.best_params_["output"] == "abs"
    chosen = next(r for r in search.results_ if "chosen" in r["note"])
    est = search.best_estimator_
    assert np.isfinite(final["holdout_fit"]) and chosen["stage"] == 1
    if search.final_kept_:  # the final fit's hold-out is the last 20 % of the whole record, not of the screened part
        assert est.half_step_input == est.half_step_input_  # the screening's choice, carried over
        assert est.holdout_fit_ == pytest.approx(final["holdout_fit"])
    else:  # the final fit scored worse on the whole record's hold-out: the screened fit is kept, and says so
        assert "not kept" in final["note"] and est is not None


def test_structures_beyond_max_terms_are_skipped_and_listed():
    u, y = _sign_insensitive_data(400, seed=1)
    search = StructureSearch(sampling_period=0.05, orders=(2,), degrees=(1, 3), outputs=("abs",), max_terms=5,
                             settings={**AUTO_SETTINGS, "n_passes": 3}).fit(u, y)
    skipped = [r for r in search.results_ if r["note"].startswith("skipped")]
    assert len(skipped) == 1 and skipped[0]["total_degree"] == 3 and skipped[0]["holdout_fit"] is None
    assert search.best_params_ == {"n_states": 2, "total_degree": 1, "output": "abs"}


@pytest.mark.parametrize("kwargs, match", [
    ({"orders": ()}, "orders"), ({"orders": (0,)}, "orders"), ({"orders": "12"}, "orders"),
    ({"degrees": (1, 9)}, "degrees"), ({"outputs": ("identity", "sqrt")}, "outputs"), ({"outputs": "abs"}, "outputs"),
    ({"n_finalists": 0}, "n_finalists"), ({"max_terms": -1}, "max_terms"), ({"tolerance": -1.0}, "tolerance"),
    ({"tolerance": float("nan")}, "tolerance"), ({"holdout": 0.0}, "holdout"), ({"holdout": 0.6}, "holdout"),
    ({"screen_samples": 50}, "screen_samples"), ({"screen_passes": 0}, "screen_passes"),
    ({"settings": {"n_states": 3}}, "settings must not set"), ({"settings": {"n_pases": 3}}, "unknown"),
    ({"settings": [1, 2]}, "settings"), ({"random_state": 1.5}, "random_state"),
])
def test_search_arguments_are_checked(kwargs, match):
    u, y = _sign_insensitive_data(200, seed=0)
    with pytest.raises(ValueError, match=match):
        StructureSearch(**kwargs).fit(u, y)


def test_search_needs_a_record_long_enough_to_hold_out():
    u, y = _sign_insensitive_data(80, seed=0)
    with pytest.raises(ValueError, match="at least 100"):
        StructureSearch(sampling_period=0.05).fit(u, y)
    with pytest.raises(ValueError, match="not fitted"):
        StructureSearch().predict(u)


def test_refit_runs_the_chosen_recipe_over_the_whole_record():
    u, y = _sign_insensitive_data(1000, seed=2)
    kw = {"n_states": 2, "output": "abs", "sampling_period": 0.05, **AUTO_SETTINGS, "half_step_input": "hold",
          "pass_mode": "continue"}
    chosen = RecursivePEM(**{**kw, "refit": False}).fit(u, y)
    refitted = RecursivePEM(**kw).fit(u, y)
    assert refitted.holdout_fit_ == pytest.approx(chosen.holdout_fit_)  # the same choice on the same hold-out
    assert chosen.refit_ is False and isinstance(refitted.refit_, bool)
    if refitted.refit_:  # kept: it has seen every sample, and fits the whole record at least as well
        assert refitted.score(u, y) >= chosen.score(u, y) - 1e-9
        assert not np.array_equal(refitted.theta_, chosen.theta_)
    else:
        np.testing.assert_array_equal(refitted.theta_, chosen.theta_)
    with pytest.raises(ValueError, match="refit"):
        RecursivePEM(refit="yes").fit(u, y)
