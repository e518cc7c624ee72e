"""experiments.limit on a short segment: the JSON the acceptance check reads, the replay, the figure, and the
benchmark controllers placed against the limit."""
from __future__ import annotations

import json

import pytest

from experiments import limit


def test_limit_experiment_on_a_segment(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    bench = tmp_path / "bench.json"
    bench.write_text(json.dumps({"cycles": {"whtc": {"controllers": {
        "lookup_table": {"tailpipe_nox_g_per_kwh": 5.0, "mean_nh3_slip_ppm": 3.0},
        "impossible": {"tailpipe_nox_g_per_kwh": 1e-6, "mean_nh3_slip_ppm": 1.0},
        "over_budget": {"tailpipe_nox_g_per_kwh": 1e-6, "mean_nh3_slip_ppm": 30.0}}}}}), encoding="utf-8")
    out = tmp_path / "limit.json"
    doc = limit.main(["--cycles", "whtc", "--budgets", "5", "10", "--segment", "2800", "160", "--json", str(out),
                      "--benchmark", str(bench)])
    assert json.loads(out.read_text(encoding="utf-8"))["cycles"]["whtc"]["budgets"].keys() == {"5", "10"}
    budgets = doc["cycles"]["whtc"]["budgets"]
    for key, rec in budgets.items():
        for field in ("tailpipe_nox_g_per_kwh", "mean_nh3_slip_ppm", "replay_tailpipe_nox_g_per_kwh",
                      "solve_time_s", "status", "dose_g_s"):
            assert field in rec
        assert rec["replay_tailpipe_nox_g_per_kwh"] == pytest.approx(rec["tailpipe_nox_g_per_kwh"], rel=0.01)
        assert rec["mean_nh3_slip_ppm"] <= float(key) * 1.01
        assert len(rec["dose_g_s"]) == 160
    assert budgets["10"]["tailpipe_nox_g_per_kwh"] <= budgets["5"]["tailpipe_nox_g_per_kwh"] * 1.01
    assert doc["command"].startswith("python -m experiments.limit --cycles whtc")
    placed = doc["controllers_against_limit"]["whtc"]
    assert placed["impossible"]["below_limit"] and not placed["over_budget"]["below_limit"]
    assert not placed["lookup_table"]["below_limit"] and placed["lookup_table"]["gap_to_limit"] == 0.0
    run = next((tmp_path / "runs" / "limit").iterdir())
    assert (run / "pareto_front.png").stat().st_size > 0 and (run / "limit.json").exists()


    # --stored: no solve, the package's document (here the segment's, so the plant check warns: another cycle)
    from control.limit import StaleLimitWarning, stored

    package = tmp_path / "package_limit.json"
    package.write_text(json.dumps(doc), encoding="utf-8")
    monkeypatch.setattr(stored, "stored_limit_path", lambda: package)
    again = tmp_path / "again.json"
    with pytest.warns(StaleLimitWarning, match="cycle"):
        redo = limit.main(["--stored", "--cycles", "whtc", "--benchmark", str(bench), "--json", str(again)])
    assert redo["cycles"]["whtc"]["budgets"] == json.loads(json.dumps(budgets))
    assert redo["controllers_against_limit"]["whtc"]["impossible"]["below_limit"]
    assert json.loads(again.read_text(encoding="utf-8"))["cycles"]["whtc"]["budgets"].keys() == {"5", "10"}


def test_store_only_for_the_default_problem(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit):
        limit.main(["--segment", "0", "100", "--store"])
    with pytest.raises(SystemExit):
        limit.main(["--budgets", "10", "--store"])
    with pytest.raises(SystemExit):
        limit.main(["--stored", "--store"])
