"""ident.thesis.paper4 (Paper IV reproduction): the validation figure is the simulation carried on from the
estimation data, M-V's choice is the best hold-out candidate, and no validation output reaches any fit or choice."""
from __future__ import annotations

import numpy as np
import pytest

from ident.metrics import fit_percent
from ident.plant_data import PAPER4_N_SAMPLES, whtc_dataset
from ident.thesis import paper4 as p4

MV_SMALL = {"nk": (1, 0), "smoothness": (10.0,)}


@pytest.fixture(scope="module")
def data():
    return whtc_dataset(seed=0)[:PAPER4_N_SAMPLES]


@pytest.fixture(scope="module")
def fitted(data):
    return p4.fit_models(data, models=("M-II", "M-V"), mv=MV_SMALL)


def test_validation_fit_is_the_continued_simulation(fitted) -> None:
    rows, sims = fitted
    ye, yv = sims["y_est"][:, None], sims["y_val"][:, None]
    for row in rows:
        model = sims["models"][row["model"]]
        y_run = model.predict(np.vstack([sims["u_est"][row["model"]], sims["u_val"][row["model"]]]), y0=ye)
        assert row["fit_validation"] == pytest.approx(float(fit_percent(yv, y_run[len(ye):, :1])), abs=1e-9)
        np.testing.assert_allclose(sims[row["model"]][1], y_run[len(ye):, 0])
        assert row["published"]["fit_validation"] == p4.PUBLISHED[row["model"]][2]
        assert np.isfinite(row["fit_validation_x0_from_validation"])


def test_mv_choice_is_the_best_holdout_candidate(fitted) -> None:
    rows, sims = fitted
    mv = next(r for r in rows if r["model"] == "M-V")
    assert list(mv["holdout_fit"]) == ["nk=1 smoothness=10", "nk=0 smoothness=10"]
    best = max(mv["holdout_fit"], key=mv["holdout_fit"].get)
    assert mv["chosen"] == best
    model = sims["models"]["M-V"]
    assert model.nk == (1 if best.startswith("nk=1") else 0) and model.smoothness == 10.0
    assert mv["n_params"] == 48   # knot values of 9, 5, 9, 5 segments (32) and 4 x (nb + nf) = 16


def test_no_validation_output_enters_fit_or_choice(data, fitted) -> None:
    rows, sims = fitted
    y = data.y.copy()
    y[900:, 0] = y[900:, 0][::-1] * 3.0 + 100.0   # different validation outputs, same statistics of the estimation part
    rows2, sims2 = p4.fit_models(data.with_signals(y=y), models=("M-II", "M-V"), mv=MV_SMALL)
    for a, b in zip(rows, rows2, strict=True):
        assert a["fit_estimation"] == b["fit_estimation"]
        if a["model"] == "M-V":
            assert a["holdout_fit"] == b["holdout_fit"] and a["chosen"] == b["chosen"]
        np.testing.assert_array_equal(sims["models"][a["model"]].b_, sims2["models"][b["model"]].b_)
        assert a["fit_validation"] != b["fit_validation"]


def test_diagnose_mv_scores_each_candidate_and_its_ceiling(data, fitted) -> None:
    rows, _ = fitted
    diag = p4.diagnose_mv(data, mv=MV_SMALL)
    assert [(d["nk"], d["smoothness"]) for d in diag] == [(1, 10.0), (0, 10.0)]
    mv = next(r for r in rows if r["model"] == "M-V")
    chosen = next(d for d in diag if mv["chosen"] == f"nk={d['nk']} smoothness={d['smoothness']:g}")
    assert chosen["fit_validation"] == pytest.approx(mv["fit_validation"], abs=1e-9)  # the table's M-V, refitted
    for d in diag:
        # fitted with the validation window in its data, a candidate does better there than carried on from the
        # estimation data alone
        assert d["fit_validation_ceiling"] > d["fit_validation"]


def test_seed_spread_collects_each_seeds_table(fitted) -> None:
    rows, _ = fitted
    spread = p4.seed_spread([0, 1], models=("M-II",))
    m2 = spread["models"]["M-II"]
    assert spread["seeds"] == [0, 1] and len(m2["fit_validation"]) == 2 and spread["design"] == "production"
    assert "mv_chosen" not in spread
    seed0 = next(r for r in rows if r["model"] == "M-II")
    assert m2["fit_validation"][0] == pytest.approx(seed0["fit_validation"], abs=1e-9)
    assert m2["min"] <= m2["median"] <= m2["max"]
    other = p4.fit_models(whtc_dataset(seed=1)[:PAPER4_N_SAMPLES], models=("M-II",))[0][0]
    assert m2["fit_validation"][1] == pytest.approx(other["fit_validation"], abs=1e-9)
    with pytest.raises(ValueError, match="seeds"):
        p4.seed_spread([])
