"""experiments.calibrate_black_box refuses the held-out-style seed 0 and configurations that are not JSON, before
any identification runs."""
from __future__ import annotations

import casadi
import pytest

from experiments import calibrate_black_box


def test_refuses_seed_zero_and_bad_configs(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        calibrate_black_box.main(["--seeds", "0", "5"])
    assert "--seeds" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        calibrate_black_box.main(["--configs", "{not json"])
    assert "--configs" in capsys.readouterr().err


def test_identified_reuses_saved_models_without_identifying(tmp_path, monkeypatch) -> None:
    import json

    from ident.for_control import fit_rpem_for_control, identification_records
    from ident.io import save_model

    model, info = fit_rpem_for_control(identification_records(seeds=(10,), duration_s=120.0))
    ident = {"models": {"rpem": {"kind": "rpem", "path": str(save_model(model, tmp_path / "model_rpem")),
                                 "info": info}}}
    (tmp_path / "prev.json").write_text(json.dumps({"identification": ident}))

    def refuse(*a, **k):
        raise AssertionError("identified again")

    monkeypatch.chdir(tmp_path)   # the run folder goes under ./runs, not the checkout's
    monkeypatch.setattr(calibrate_black_box, "identify_for_control", refuse)
    doc = calibrate_black_box.main(["--models", "rpem", "--seeds", "5", "--duration", "10", "--identified",
                                    str(tmp_path / "prev.json"), "--configs", '{"anr_band_hi": null}',
                                    "--json", str(tmp_path / "out.json")])
    assert doc["table"][0]["config"] == {"anr_band_hi": None} and len(doc["table"][0]["per_seed"]) == 1
    cycle, _nox, _slip, failures, _adblue, _peak, suboptimal = doc["table"][0]["per_seed"][0]
    assert cycle == 5 and 0.0 <= suboptimal <= 20.0 and failures + suboptimal <= 20.0  # 10 s: 20 solves


def test_refuses_bad_hw_fit_and_reuses_an_earlier_identification(capsys: pytest.CaptureFixture[str],
                                                                  tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    import json

    with pytest.raises(SystemExit):
        calibrate_black_box.main(["--hw-fit", "{not json"])
    assert "--hw-fit" in capsys.readouterr().err

    earlier = tmp_path / "earlier.json"
    earlier.write_text(json.dumps({"identification": {"models": {"hammerstein_wiener": {"path": "x"}}}}))

    def no_identification(*a: object, **k: object) -> None:
        raise AssertionError("identified again")

    def sweep(fn: object, tasks: list, **kw: object) -> list:
        return [{"model": t["model"], "config": t["config"], "seed": t["seed"], "nox": 1.0, "slip": 0.0,
                 "adblue_g": 1.0, "failures": 0.0, "peak": 0.0, "suboptimal": 0.0} for t in tasks]

    monkeypatch.chdir(tmp_path)   # the run folder goes under ./runs
    monkeypatch.setattr(calibrate_black_box, "identify_for_control", no_identification)
    monkeypatch.setattr(calibrate_black_box, "run_sweep", sweep)
    doc = calibrate_black_box.main(["--models", "hammerstein_wiener", "--seeds", "5", "--identified", str(earlier),
                                    "--json", str(tmp_path / "out.json")])
    assert doc["identification"]["models"]["hammerstein_wiener"]["path"] == "x"
    assert doc["chosen"] == {"hammerstein_wiener": {}}
    assert doc["environment"]["packages"]["casadi"] == casadi.__version__   # what the figures were computed with


def test_ramped_mode_cycles_join_the_rule(capsys: pytest.CaptureFixture[str], tmp_path,
                                          monkeypatch: pytest.MonkeyPatch) -> None:
    """--ramped-seeds adds WHSC-like ramped-mode cycles to the calibration set: their episodes run with
    kind="ramped_modes", are labelled "modes-<seed>", and a configuration that slips above the target on one of
    them is not chosen even if it is the best on the transient cycles."""
    import json

    earlier = tmp_path / "earlier.json"
    earlier.write_text(json.dumps({"identification": {"models": {"rpem": {"path": "x"}}}}))
    seen: list[tuple[str, int, float]] = []

    def sweep(fn: object, tasks: list, **kw: object) -> list:
        rows = []
        for t in tasks:
            seen.append((t["kind"], t["seed"], t["duration"]))
            bold = t["config"].get("anr_band_lo") == 1.0
            slip = 20.0 if bold and t["kind"] == "ramped_modes" else 1.0
            rows.append({"model": t["model"], "config": t["config"], "seed": t["seed"], "nox": 0.5 if bold else 1.0,
                         "slip": slip, "adblue_g": 1.0, "failures": 0.0, "peak": 0.0, "suboptimal": 0.0})
        return rows

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(calibrate_black_box, "run_sweep", sweep)
    doc = calibrate_black_box.main(["--models", "rpem", "--seeds", "5", "--ramped-seeds", "6", "--ramped-duration",
                                    "300", "--identified", str(earlier), "--configs", "{}", '{"anr_band_lo": 1.0}'])
    assert ("ramped_modes", 6, 300.0) in seen and ("transient", 5, 600.0) in seen
    assert [c for c, *_ in doc["table"][1]["per_seed"]] == [5, "modes-6"]
    assert doc["chosen"] == {"rpem": {}} and doc["ramped_seeds"] == [6]
    with pytest.raises(SystemExit):
        calibrate_black_box.main(["--seeds", "--ramped-seeds", "0"])
    assert "--ramped-seeds" in capsys.readouterr().err


def test_ramped_identification_cycles_reach_the_identification_and_differ_from_calibration(
        capsys: pytest.CaptureFixture[str], tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(SystemExit):
        calibrate_black_box.main(["--ramped-seeds", "5", "6", "--ident-ramped-seeds", "6", "10"])
    assert "--ident-ramped-seeds" in capsys.readouterr().err
    seen: dict = {}

    def identify(out: object, **kw: object) -> dict:
        seen.update(kw)
        return {"models": {"rpem": {"path": "x"}}}

    def sweep(fn: object, tasks: list, **kw: object) -> list:
        return [{"model": t["model"], "config": t["config"], "seed": t["seed"], "nox": 1.0, "slip": 0.0,
                 "adblue_g": 1.0, "failures": 0.0, "peak": 0.0, "suboptimal": 0.0} for t in tasks]

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(calibrate_black_box, "identify_for_control", identify)
    monkeypatch.setattr(calibrate_black_box, "run_sweep", sweep)
    calibrate_black_box.main(["--models", "rpem", "--seeds", "5", "--ident-ramped-seeds", "10", "11"])
    assert seen["ramped_seeds"] == [10, 11]
    calibrate_black_box.main(["--models", "rpem", "--seeds", "5"])
    assert seen["ramped_seeds"] is None   # the loop's default data
