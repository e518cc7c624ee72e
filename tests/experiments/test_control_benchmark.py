"""control_benchmark's bookkeeping over several sensor-noise seeds (cheap stand-in controllers, real episodes)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from control.baselines import LookupTableDosing
from experiments import control_benchmark as cb


@pytest.fixture
def cheap(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)   # the run folder goes to ./runs
    monkeypatch.setattr(cb, "identify", lambda *a, **k: {"fit_seconds": 0.0, "validation_rmse_ppm_whtc": {},
                                                         "validation_mean_ppm_whtc": {}})
    monkeypatch.setattr(cb, "make", lambda name, ident, quick: LookupTableDosing())
    monkeypatch.setattr(cb, "available_rl", lambda: ([], ""))
    monkeypatch.setattr(cb, "plot", lambda *a, **k: None)
    return tmp_path


def test_seeds_are_averaged_and_listed(cheap) -> None:
    out = cheap / "r.json"
    doc = cb.main(["--quick", "--workers", "1", "--seeds", "0", "3", "--json", str(out)])
    assert doc["seeds"] == [0, 3] and json.loads(out.read_text())["seeds"] == [0, 3]
    c = doc["cycles"]["whtc"]["controllers"]
    assert set(c) == {*cb.CORE, *cb.IDENTIFIED_VARIANTS}
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
