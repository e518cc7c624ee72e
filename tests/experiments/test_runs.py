"""experiments._runs: the run folder and the --json path are checked before a long run; records written atomically."""
from __future__ import annotations

import json

import pytest

from experiments import _runs, control_benchmark, linear_baselines, reproduce_paper4
from scr_env import fileio


def test_run_folder_is_created_checked_and_unique(tmp_path) -> None:
    a = _runs.run_folder("x", root=tmp_path)
    b = _runs.run_folder("x", root=tmp_path)
    assert a.is_dir() and b.is_dir() and a != b
    doc = {"k": 1}
    _runs.save_results(a, "r.json", doc, tmp_path / "copy.json")
    assert json.loads((a / "r.json").read_text()) == doc == json.loads((tmp_path / "copy.json").read_text())


def test_a_bad_json_path_fails_before_the_run_folder_exists(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="--json file"):
        _runs.run_folder("x", root=tmp_path, json_path=tmp_path / "no" / "such" / "r.json")
    with pytest.raises(IsADirectoryError, match="--json file"):
        _runs.run_folder("x", root=tmp_path, json_path=tmp_path)
    assert not (tmp_path / "x").exists()


def test_a_read_only_run_folder_fails_at_once(tmp_path, monkeypatch) -> None:
    def denied(folder):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(fileio, "_probe", denied)
    with pytest.raises(PermissionError, match="run folder"):
        _runs.run_folder("x", root=tmp_path)


@pytest.mark.parametrize("module, argv", [
    (control_benchmark, ["--quick"]),
    (linear_baselines, []),
    (reproduce_paper4, ["--no-plots"]),
])
def test_experiments_check_their_outputs_before_working(tmp_path, monkeypatch, module, argv) -> None:
    """A mistyped --json path stops the experiment at once, before any identification or episode."""
    monkeypatch.chdir(tmp_path)

    def no_work(*a, **k):
        raise AssertionError("the experiment started working before checking its outputs")

    for name in ("greybox_record", "whtc_dataset", "fit_models"):
        if hasattr(module, name):
            monkeypatch.setattr(module, name, no_work)
    with pytest.raises(FileNotFoundError, match="--json file"):
        module.main([*argv, "--json", str(tmp_path / "missing" / "r.json")])


def test_a_given_output_folder_is_created_or_reused_and_checked(tmp_path) -> None:
    out = _runs.run_folder("x", folder=tmp_path / "my" / "out")
    assert out == tmp_path / "my" / "out" and out.is_dir()
    assert _runs.run_folder("x", folder=out) == out   # an existing folder is fine
    with pytest.raises(NotADirectoryError, match="not a folder"):
        _runs.run_folder("x", folder=_runs.write_text(tmp_path / "file", "x"))


def test_write_figure_writes_the_png_atomically_and_closes_the_figure(tmp_path) -> None:
    from control.plots import pyplot
    from experiments._runs import write_figure

    plt = pyplot()
    fig, ax = plt.subplots()
    ax.plot([0, 1], [1, 0])
    path = write_figure(fig, tmp_path / "f.png", dpi=50)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not plt.fignum_exists(fig.number)
    assert [p.name for p in tmp_path.iterdir()] == ["f.png"]  # no temporary file left behind


def test_environment_records_the_versions_and_the_commit() -> None:
    import casadi
    import numpy as np

    env = _runs.environment()
    assert env["packages"]["casadi"] == casadi.__version__ and env["packages"]["numpy"] == np.__version__
    assert set(env["packages"]) == set(_runs.RECORDED_PACKAGES) and env["python"].count(".") == 2
    json.dumps(env)   # JSON-ready
    commit = env["git_commit"]
    assert commit is None or len(commit.removesuffix("+dirty")) == 40


def test_environment_without_git_records_no_commit(monkeypatch) -> None:
    def no_git(*args, **kwargs):
        raise FileNotFoundError("git")

    monkeypatch.setattr(_runs.subprocess, "run", no_git)
    assert _runs.environment()["git_commit"] is None


def test_two_runs_started_in_the_same_second_get_two_folders(tmp_path, monkeypatch) -> None:
    """The name is claimed by mkdir, not checked then created: a second run that saw the name free (a race,
    simulated by an ``exists`` that always says no) takes the next suffix instead of failing."""
    monkeypatch.setattr(_runs.time, "strftime", lambda fmt: "20261129-105041")
    monkeypatch.setattr(_runs.Path, "exists", lambda self: False)
    paths = [_runs.run_folder("x", root=tmp_path) for _ in range(3)]
    assert [p.name for p in paths] == ["20261129-105041", "20261129-105041-1", "20261129-105041-2"]
