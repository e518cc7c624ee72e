"""Smoke test of the ageing experiment: the drift model, the estimator wiring and the whole pipeline on 20 s
segments (no identification: fixed grey-box numbers of a fresh-catalyst fit)."""
from __future__ import annotations

import json

import numpy as np

from control import adaptive, ageing
from experiments import adaptive_ageing as aa

IDENT = {"params": [-0.0803, -0.2129, 0.2140, -0.1841, 0.1300, 0.9155, -0.0592, 0.0613, 0.9172, -0.2831, 0.0290],
         "sensor_gains": [0.9394, 1.1639], "n_cells": 2, "dt": 0.5}


def test_drift_step_is_the_identified_model_at_zero_drift_and_loses_capacity() -> None:
    from ident.greybox import StorageGreyBox

    model = StorageGreyBox.from_params(IDENT["params"], IDENT["sensor_gains"])
    fixed = model.to_casadi()
    f = adaptive.drift_step(model)
    x, u = np.array([0.3, 0.1, 520.0]), np.array([400.0, 40.0, 530.0, 12.0])
    np.testing.assert_allclose(np.asarray(f(x, u, [0.0, 0.0])[1]), np.asarray(fixed(x, u)[1]), rtol=1e-12)
    # same stored amount in a smaller brick: higher coverage, more slip
    x_small = np.array([0.6, 0.5, 520.0])
    assert float(f(x_small, u, [np.log(0.5), 0.0])[1][1]) > float(f(x_small, u, [0.0, 0.0])[1][1])
    items = ageing.schedule(3, "alternate")
    assert [i["cycle"] for i in items] == ["whtc", "whsc", "whtc"] and items[-1]["severity"] == 1.0
    assert ageing.retention(1.0) == ageing.AGED_END


def test_pipeline_on_short_segments(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "ident.json").write_text(json.dumps(IDENT), encoding="utf-8")
    doc = aa.main(["--ident", str(tmp_path / "ident.json"), "--cycles", "2", "--seconds", "20", "--quick",
                   "--serial", "--json", str(tmp_path / "out.json")])
    assert len(doc["cycles"]) == 2
    c = doc["cycles"][1]
    assert c["severity"] == 1.0 and c["estimates"]["true_capacity_retention"] == 0.6
    for who in ("fixed", "adaptive"):
        assert np.isfinite(c[who]["mean_nh3_slip_ppm"])
    assert c["adaptive"]["rpem_updates"] == 2 * 39  # every step but the first of each episode
    est = c["estimates"]
    assert 0.2 - 1e-9 <= est["capacity_retention_end"] <= 1.05 + 1e-9
    assert (tmp_path / "out.json").exists()
    assert {"fixed_mean_slip_ppm", "adaptive_mean_slip_ppm", "done_criterion_met"} <= set(doc["summary"])
    out = tmp_path / doc["run_folder"]
    assert (out / "kpis_vs_cycle.png").exists() and (out / "parameter_tracking.png").exists()
