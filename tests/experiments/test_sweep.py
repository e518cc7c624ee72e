"""The sweep runner: serial, local processes and a local Ray instance give the same results in task order."""
from __future__ import annotations

import argparse

import pytest

from experiments.sweep import add_arguments, from_args, run_sweep
from scr_env.lab import steady_state

TASKS = [{"catalyst": "cu_zeolite", "temperature_c": t, "no_ppm": 300.0, "nh3_ppm": 300.0} for t in (160, 200, 250)]


def test_serial_and_local_processes_agree_in_task_order() -> None:
    serial = run_sweep(steady_state, TASKS, backend="serial", progress=False)
    local = run_sweep(steady_state, TASKS, backend="local", workers=2, progress=False)
    assert [r["nox_conversion"] for r in serial] == [r["nox_conversion"] for r in local]
    assert serial[0]["nox_conversion"] < serial[1]["nox_conversion"] < serial[2]["nox_conversion"]


def test_ray_local_instance() -> None:
    pytest.importorskip("ray")
    serial = run_sweep(steady_state, TASKS, backend="serial", progress=False)
    ray_results = run_sweep(steady_state, TASKS, backend="ray", address=None, progress=False)
    assert [r["nox_conversion"] for r in ray_results] == [r["nox_conversion"] for r in serial]


def test_bad_arguments() -> None:
    with pytest.raises(ValueError, match="backend"):
        run_sweep(steady_state, TASKS, backend="spark")
    with pytest.raises(ValueError, match="tasks"):
        run_sweep(steady_state, [1, 2])
    with pytest.raises(ValueError, match="workers"):
        run_sweep(steady_state, TASKS, workers=0)
    assert run_sweep(steady_state, []) == []


def test_command_line_options() -> None:
    ap = argparse.ArgumentParser()
    add_arguments(ap)
    assert from_args(ap.parse_args([])) == {"backend": "local", "workers": None}
    assert from_args(ap.parse_args(["--ray-address", "auto"])) == {"backend": "ray", "address": "auto"}
