"""The Hammerstein-Wiener model for the NMPC (issue 18, stream hw2): output blocks per output, the multi-step
(horizon) prediction-error refinement, and the NMPC's lower dose band."""
from __future__ import annotations

import numpy as np
import pytest

from control.blackbox import black_box_nmpc
from ident.for_control import (
    HW_OUTPUT_BLOCKS,
    concat_records,
    control_arrays,
    fit_hw_for_control,
    hw_linear_export,
    hw_multistep_refine,
    identification_records,
    k_step_fit,
)


@pytest.fixture(scope="module")
def records() -> list:
    return identification_records(seeds=(10, 11), duration_s=240.0)


@pytest.mark.parametrize("blocks", [("pwl", "saturation"), ("deadzone", "identity")])
def test_output_blocks_per_output_export_to_casadi(records: list, blocks: tuple[str, str]) -> None:
    model, info = fit_hw_for_control(records, max_nfev=5, output_blocks=blocks)
    assert [type(b).__name__ for b in model.output_blocks_] == [
        {"pwl": "PiecewiseLinear", "saturation": "Saturation", "deadzone": "DeadZone", "identity": "Identity"}[k]
        for k in blocks]
    assert info["output_blocks"] == list(blocks)
    step, A, _ = hw_linear_export(model)
    fit = k_step_fit(step, info, records[0], 40)
    assert len(fit) == 2 and all(np.isfinite(fit))
    # the CasADi step is the model: same outputs as predict on the normalised features
    (z, _y), = control_arrays([records[0]], info["features"], info["nox_kind"], info["nh3_kind"])
    zn = (z[:50] - np.asarray(info["z_mean"])) / np.asarray(info["z_scale"])
    x, ys = np.zeros(A.shape[0]), []
    for t in range(50):
        xn, y = step(x, zn[t])
        ys.append(np.asarray(y).ravel())
        x = np.asarray(xn).ravel()
    np.testing.assert_allclose(np.array(ys), model.predict(zn), rtol=1e-6, atol=1e-8)


def test_unknown_output_block_and_output_kinds(records: list) -> None:
    assert set(HW_OUTPUT_BLOCKS) >= {"identity", "pwl", "saturation", "deadzone"}
    with pytest.raises(ValueError, match="output block"):
        fit_hw_for_control(records, max_nfev=2, output_blocks=("spline", "identity"))
    with pytest.raises(ValueError, match="one per output"):
        fit_hw_for_control(records, max_nfev=2, output_blocks=("identity",))
    _, info = fit_hw_for_control(records, max_nfev=2, nox_kind="ratio", nh3_kind="ppm")
    assert (info["nox_kind"], info["nh3_kind"]) == ("ratio", "ppm")


def _multistep_cost(model: object, u: np.ndarray, y: np.ndarray, w: np.ndarray, h: int) -> float:
    e = y - model.predict(u)
    t0 = np.repeat(np.arange(0, len(y) - h, h), h)
    tj = t0 + np.tile(np.arange(1, h + 1), len(np.arange(0, len(y) - h, h)))
    return float(np.sum(w[tj, None] * w[t0, None] * (e[tj] - e[t0]) ** 2))


def test_multistep_refinement_lowers_the_horizon_prediction_error(records: list) -> None:
    model, info = fit_hw_for_control(records, max_nfev=5)
    arrs = control_arrays(records)
    U, Y, W = concat_records([(z - np.asarray(info["z_mean"])) / np.asarray(info["z_scale"]) for z, _ in arrs],
                             [y for _, y in arrs], warmup=120)
    Yn = (Y - np.asarray(info["y_mean"])) / np.asarray(info["y_scale"])
    before = _multistep_cost(model, U, Yn, W, 40)
    hw_multistep_refine(model, U, Yn, W, horizon=40, max_nfev=20)
    after = _multistep_cost(model, U, Yn, W, 40)
    assert after < before
    refined, rinfo = fit_hw_for_control(records, max_nfev=5, multistep_horizon=40, multistep_nfev=20)
    assert rinfo["multistep_horizon"] == 40
    np.testing.assert_allclose(refined.A_, model.A_)


def test_lower_dose_band_enters_the_nlp_only_when_set(records: list) -> None:
    model, info = fit_hw_for_control(records, max_nfev=2)
    plain = black_box_nmpc(model, info, quick=True, anr_band_lo=0.0, anr_band_lo_hot=None)
    banded = black_box_nmpc(model, info, quick=True, anr_band_lo=0.8, anr_band_lo_hot=None)
    hot_only = black_box_nmpc(model, info, quick=True, anr_band_lo=0.0, anr_band_lo_hot=1.0)
    assert plain.anr_band[0] == 0.0 and banded.anr_band[0] == 0.8 and hot_only.band_lo_hot == 1.0
    plain._build()
    banded._build()
    hot_only._build()
    assert banded._lbg.size == plain._lbg.size + len(banded.stages)
    assert hot_only._lbg.size == banded._lbg.size      # the hot band alone puts the lower bound in the NLP
