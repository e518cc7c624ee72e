"""experiments.reproduce_paper4: the table of each design, written by main (the fits:
tests/ident/test_thesis_paper4.py)."""
from __future__ import annotations

import json

import pytest

from experiments import reproduce_paper4 as rp4
from ident.plant_data import PAPER4_N_SAMPLES, whtc_dataset
from ident.thesis import paper4 as p4


def test_main_writes_the_table(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)  # the run folder goes to ./runs
    monkeypatch.setattr(p4, "MV_DEFAULT", {**p4.MV_DEFAULT, "nk": (1,), "smoothness": (10.0,)})
    out = tmp_path / "r.json"
    assert rp4.main(["--no-plots", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert [r["model"] for r in res["rows"]] == list(p4.MODELS)
    for r in res["rows"]:
        assert {"fit_estimation", "fit_validation", "fit_validation_x0_from_validation", "mse_validation"} <= set(r)
    assert res["protocol"]["n_estimation"] == 900 and "carried" in res["protocol"]["fit"]
    # the table is the thesis' design; the excitation design's table follows it
    assert res["design"] == "production" and res["data"]["design"] == "production"
    assert list(res["other_designs"]) == ["excitation"]
    other = res["other_designs"]["excitation"]["rows"]
    assert [r["model"] for r in other] == list(p4.MODELS)
    assert other[0]["fit_validation"] != res["rows"][0]["fit_validation"]


def test_main_one_design(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(p4, "MV_DEFAULT", {**p4.MV_DEFAULT, "nk": (1,), "smoothness": (10.0,)})
    out = tmp_path / "r.json"
    assert rp4.main(["--no-plots", "--design", "excitation", "--only-design", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["design"] == "excitation" and res["data"]["design"] == "excitation" and "other_designs" not in res
    expected = p4.fit_models(whtc_dataset(seed=0, design="excitation")[:PAPER4_N_SAMPLES], models=("M-II",))[0]
    assert res["rows"][1]["fit_validation"] == pytest.approx(expected[0]["fit_validation"], abs=1e-9)
    with pytest.raises(SystemExit):
        rp4.main(["--design", "nope"])

