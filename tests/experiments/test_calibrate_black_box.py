"""experiments.calibrate_black_box refuses the held-out-style seed 0 and configurations that are not JSON, before
any identification runs."""
from __future__ import annotations

import pytest

from experiments import calibrate_black_box


def test_refuses_seed_zero_and_bad_configs(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        calibrate_black_box.main(["--seeds", "0", "5"])
    assert "--seeds" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        calibrate_black_box.main(["--configs", "{not json"])
    assert "--configs" in capsys.readouterr().err
