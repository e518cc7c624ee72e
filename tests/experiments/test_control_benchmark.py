"""control_benchmark's bookkeeping over several sensor-noise seeds (cheap stand-in controllers, real episodes)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from control.baselines import LookupTableDosing
from experiments import control_benchmark as cb

PARAMS = [-0.0803, -0.2129, 0.2140, -0.1841, 0.1300, 0.9155, -0.0592, 0.0613, 0.9172, -0.2831, 0.0290]


@pytest.fixture
def cheap(monkeypatch, tmp_path):
    from ident.greybox import StorageGreyBox

    monkeypatch.chdir(tmp_path)   # the run folder goes to ./runs
    model = StorageGreyBox.from_params(PARAMS, [0.9394, 1.1639])
    monkeypatch.setattr(cb, "greybox_record", lambda *a, **k: (model, {
        "fit_seconds": 0.0, "validation_rmse_ppm_whtc": {}, "validation_mean_ppm_whtc": {}}))
    monkeypatch.setattr(cb, "make_controller", lambda name, model, quick: LookupTableDosing())
    monkeypatch.setattr(cb, "available_rl", lambda: ([], ""))
    monkeypatch.setattr(cb, "closed_loop_figure", lambda *a, **k: None)
    return tmp_path


def test_seeds_are_averaged_and_listed(cheap) -> None:
    out = cheap / "r.json"
    doc = cb.main(["--quick", "--workers", "1", "--seeds", "0", "3", "--json", str(out)])
    assert doc["seeds"] == [0, 3] and json.loads(out.read_text())["seeds"] == [0, 3]
    c = doc["cycles"]["whtc"]["controllers"]
    assert set(c) == {*cb.CORE, *cb.IDENTIFIED_VARIANTS}
    assert (cheap / doc["run_folder"] / "greybox_model.json").exists()   # the model the NMPCs were built on
    row = c["lookup_table"]
    per = row["per_seed"]
    assert per["seed"] == [0, 3]
    assert per["mean_nh3_slip_ppm"][0] != per["mean_nh3_slip_ppm"][1]   # different sensor noise, different episode
    assert row["mean_nh3_slip_ppm"] == pytest.approx(np.mean(per["mean_nh3_slip_ppm"]), rel=1e-12)
    assert row["tailpipe_nox_g_per_kwh"] == pytest.approx(np.mean(per["tailpipe_nox_g_per_kwh"]), rel=1e-12)
    # one seed (the default): no per-seed lists, the figures of that episode
    one = cb.main(["--quick", "--workers", "1", "--seeds", "3"])["cycles"]["whtc"]["controllers"]["lookup_table"]
    assert "per_seed" not in one
    assert one["mean_nh3_slip_ppm"] == pytest.approx(per["mean_nh3_slip_ppm"][1], rel=1e-12)
