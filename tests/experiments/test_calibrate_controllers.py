"""The controller calibration rule: lowest mean NOx among knob values within the slip target on every cycle."""
import pytest

from experiments.calibrate_controllers import KNOBS, _controller, choose


def _row(value, seed, tp, slip, fails=0.0):
    return {"controller": "identified", "value": value, "seed": seed, "tailpipe_nox_g_per_kwh": tp,
            "mean_nh3_slip_ppm": slip, "solver_failures": fails}


def test_choose_takes_lowest_nox_within_the_slip_target_on_every_cycle():
    rows = [_row(0, 5, 0.40, 1.0), _row(0, 6, 0.30, 2.0),
            _row(100, 5, 0.15, 2.0), _row(100, 6, 0.25, 5.0),
            _row(200, 5, 0.05, 3.0), _row(200, 6, 0.10, 9.0)]  # lowest NOx, but one cycle above 8 ppm
    res = choose(rows, slip_target_ppm=8.0)
    assert res["value"] == 100
    t = {r["value"]: r for r in res["table"]}
    assert t[100]["mean_tailpipe_nox_g_per_kwh"] == pytest.approx(0.20)
    assert t[200]["max_mean_nh3_slip_ppm"] == pytest.approx(9.0)


def test_choose_reports_none_when_no_value_meets_the_target():
    assert choose([_row(0, 5, 0.4, 12.0)], slip_target_ppm=8.0)["value"] is None


def test_unknown_controller_is_named():
    with pytest.raises(ValueError, match="controller"):
        _controller("lqr", 1.0, None)
    assert set(KNOBS) == {"identified", "identified_preview", "identified_nh3", "oracle", "lookup_table"}


def test_identification_cycles_must_not_be_calibration_cycles(capsys):
    from experiments.calibrate_controllers import main

    with pytest.raises(SystemExit):
        main(["--controller", "identified", "--seeds", "5", "6", "--ident-seeds", "1", "5"])
    assert "--ident-seeds" in capsys.readouterr().err


def test_identified_kinds_differ_only_in_the_preview():
    from control.factory import IDENT_SEEDS
    from ident.greybox import StorageGreyBox

    model = StorageGreyBox.from_params([0.0] * 11, [0.95, 1.0])
    plain, preview = _controller("identified", 50.0, model), _controller("identified_preview", 50.0, model)
    assert (plain.preview, preview.preview) == (False, True)
    assert plain.model.implicit_stage is not None and preview.model.implicit_stage is not None
    assert 5 not in IDENT_SEEDS and 6 not in IDENT_SEEDS
