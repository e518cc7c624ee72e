"""Smoke test of the Paper III reproduction: tiny segments, one RPEM pass, the JSON structure."""
from __future__ import annotations

import json

import numpy as np

from experiments import reproduce_paper3 as rp3


def test_smoke_run_writes_the_table(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the run folder goes to ./runs
    out = tmp_path / "r.json"
    code = rp3.main(["--quick", "--n-samples", "120", "--passes", "1", "--segments", "1", "--no-plots",
                     "--json", str(out)])
    res = json.loads(out.read_text())
    assert code in (0, 1)
    assert [r["method"] for r in res["rows"]] == list(rp3.METHODS)
    for r in res["rows"]:
        assert set(r) >= {"method", "n_params", "fit_estimation", "fit_validation"}
        assert r["n_params"] == (9 if r["method"].endswith("_linear") else 16)
        assert r["published_fit_validation"] == rp3.PUBLISHED[r["method"]]
    assert res["data"]["n_estimation"] == 90 and res["data"]["n_validation"] == 30
    assert res["data"]["align"] is True
    assert len(res["paper4_excitation_design"]["rows"]) == 4 and len(res["paper4_production_design"]["rows"]) == 4
    sel = res["selection"]
    assert sel["method"] == "midpoint_selected" and set(sel["terms"]) <= set(sel["candidates"])
    rep = res["repetition"]
    assert len(rep["segments"]) == 1
    assert set(rep["verdicts"]) == {"nonlinear_beats_linear", "midpoint_beats_euler"}
    assert all(isinstance(v["holds"], bool) for v in rep["verdicts"].values())
    assert list((tmp_path / "runs" / "reproduce_paper3").iterdir())


def test_alignment_pairs_the_next_input_with_each_output():
    a = rp3.load_segment("whtc", seed=0, n_samples=40, align=True)
    b = rp3.load_segment("whtc", seed=0, n_samples=41, align=False)
    np.testing.assert_array_equal(a["y"], b["y"][:40])
    np.testing.assert_array_equal(a["u"], b["u"][1:41])
