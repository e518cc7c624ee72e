"""Smoke test of experiments.rpem_structure_search: a short record, a small grid, the JSON structure."""
from __future__ import annotations

import json

from experiments import rpem_structure_search as rss


def test_smoke_run_writes_the_chosen_structures(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the run folder goes to ./runs
    out = tmp_path / "r.json"
    code = rss.main(["--quick", "--systems", "coupled_drives", "--seeds", "0", "--json", str(out)])
    res = json.loads(out.read_text())
    assert code == 0 and res["quick"] is True
    (row,) = res["rows"]
    assert row["system"] == "coupled_drives" and row["seed"] == 0 and row["goal"] == 70.0
    assert set(row["chosen"]) == {"n_states", "total_degree", "output"}
    assert row["chosen"]["output"] in ("identity", "abs")  # the quick grid
    assert row["validation_fit"] == res["summary"]["coupled_drives"]["fits"][0]
    assert "hold-out FIT" in row["table"]
    assert list((tmp_path / "runs" / "rpem_structure_search").iterdir())


def test_hand_chosen_structures_are_fitted_without_a_search(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "h.json"
    args = ["--quick", "--hand-chosen", "--systems", "cascaded_tanks", "--seeds", "0", "--json", str(out)]
    assert rss.main(args) == 0
    res = json.loads(out.read_text())
    (row,) = res["rows"]
    assert res["hand_chosen"] is True and row["chosen"] == rss.HAND_CHOSEN["cascaded_tanks"]
    assert row["n_candidates"] == 1 and row["R0"] > 0 and row["validation_fit"] > 50.0
