"""Paper IV over many segments: segment choice, robust verdicts, summaries, the joint NOx + slip model and the
second-output study on a segment where the simulator slips."""
from __future__ import annotations

import numpy as np
import pytest

from ident.dataset import IODataset
from ident.linear._statespace import simulate_ss
from ident.thesis import multisegment as ms


def test_segments_do_not_overlap() -> None:
    segs = ms.segment_list(15)
    assert len(segs) == 15 and len(set(segs)) == 15
    per_run: dict[tuple[str, int], list[float]] = {}
    for cyc, seed, start in segs:
        if cyc == "random":
            per_run.setdefault((cyc, seed), []).append(start)
        else:
            per_run.setdefault((cyc, 0), []).append(start)
    for starts in per_run.values():
        s = np.sort(starts)
        assert np.all(np.diff(s) >= ms.SEGMENT_S)
    with pytest.raises(ValueError, match="at least 1"):
        ms.segment_list(0)


def test_unknown_design_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown design 'nope'"):
        ms.load_segment("whtc", 0, 0.0, design="nope")


def _rows(fits: dict[str, float]) -> list[dict[str, float]]:
    return [{"model": m, "fit_validation": f} for m, f in fits.items()]


def test_conclusions_pair_models_per_segment() -> None:
    rng = np.random.default_rng(0)
    per_segment = []
    for _ in range(10):
        base = rng.uniform(0, 50)
        per_segment.append({"nox": _rows({"M-I": base, "M-II": base - 5, "M-III": base + 10, "M-IV": base + 5,
                                          "M-V": base + 20})})
    per_segment.append({"nox": "not fitted"})   # entries without that output are skipped
    summary, verdicts = ms.conclusions(per_segment, "nox")
    assert summary["M-V"]["n"] == 10
    assert verdicts["nonlinear beats linear (M-III vs best linear)"]["median_diff"] == pytest.approx(10.0)
    assert verdicts["exp(-a/T) input helps (M-IV vs M-III)"]["verdict"] == "does not hold"
    assert verdicts["piecewise-linear inputs help (M-V vs M-IV)"]["verdict"] == "holds"


def _two_output_system(n: int = 1200, seed: int = 0) -> IODataset:
    rng = np.random.default_rng(seed)
    A = np.array([[0.9, 0.1], [0.0, 0.7]])
    B = rng.normal(size=(2, 4))
    C = np.array([[1.0, 0.0], [0.5, 1.0]])
    u = np.repeat(rng.normal(size=(n // 10, 4)), 10, axis=0)
    y, _ = simulate_ss(A, B, C, np.zeros((2, 4)), u, np.zeros(2))
    return IODataset(u=u, y=np.column_stack([y, np.zeros(n)]), dt=0.5)


def test_joint_model_recovers_a_two_output_linear_system() -> None:
    ds = _two_output_system()
    res = ms.fit_mimo(ds, order=2)
    assert res["order"] == 2 and len(res["fit_validation"]) == 2
    assert min(res["fit_estimation"]) > 99.0 and min(res["fit_validation"]) > 99.0


def test_slip_is_studied_where_it_varies() -> None:
    # a hot random-cycle segment that slips under the over-dosing design (SD ~ 127 / 30 ppm)
    ds = ms.load_segment("random", 3, 300.0, design="slip")
    assert ms.slip_varies(ds)
    entry = ms.study_segment(ds, models=("M-I", "M-II"), mimo_orders=(2,))
    assert [r["model"] for r in entry["nh3_slip"]] == ["M-I", "M-II"]
    assert entry["mimo"][0]["outputs"] == ["tailpipe_nox_ppm", "nh3_slip_ppm"]
    assert all(np.isfinite(r["fit_validation"]) for r in entry["nh3_slip"])
    assert entry["nox"][0]["fit_validation"] != entry["nh3_slip"][0]["fit_validation"]
    assert entry["nh3_slip_sd_ppm"][0] > ms.SLIP_MIN_SD_PPM
    # the excitation design stores all of its NH3 on the first WHTC segment: no slip study there
    quiet = ms.load_segment("whtc", 100, 0.0, design="excitation")
    assert not ms.slip_varies(quiet)
    e2 = ms.study_segment(quiet, models=("M-I",), mimo_orders=(2,))
    assert isinstance(e2["nh3_slip"], str) and "not identifiable" in e2["nh3_slip"] and "mimo" not in e2
