"""Smoke test of the speed benchmark's contract (the figures themselves are measured by ``make bench``)."""
from __future__ import annotations

import json

import pytest

from experiments import benchmark_speed


def test_measure_reports_medians_of_interleaved_rounds() -> None:
    r = benchmark_speed.measure(num_envs=4, seconds=0.05, rpem=False, rounds=2)
    for key in ("pendulum_steps_per_s", "env_steps_per_s", "vector_env_steps_per_s"):
        assert len(r["rounds"][key]) == 2 and all(v > 0 for v in r["rounds"][key])
        assert min(r["rounds"][key]) <= r[key] <= max(r["rounds"][key])
    assert r["num_envs"] == 4
    assert r["vector_vs_pendulum"] == pytest.approx(r["vector_env_steps_per_s"] / r["pendulum_steps_per_s"])
    with pytest.raises(ValueError, match="rounds"):
        benchmark_speed.measure(num_envs=4, seconds=0.05, rpem=False, rounds=0)


def test_main_writes_json(tmp_path) -> None:
    path = tmp_path / "speed.json"
    benchmark_speed.main(["--json", str(path), "--num-envs", "4", "--seconds", "0.05", "--rounds", "1", "--no-rpem",
                         "--no-first-step"])
    doc = json.loads(path.read_text())
    assert {"env_steps_per_s", "pendulum_steps_per_s", "vector_env_steps_per_s", "num_envs"} <= set(doc)
    with pytest.raises(SystemExit):
        benchmark_speed.main(["--rounds", "0", "--no-rpem"])
