"""experiments.identify_then_control's scheduling: the model-free episodes run while the models are identified, the
NMPC episodes get the identified models, and the results come back in the task order."""
from __future__ import annotations

import multiprocessing
import time
from pathlib import Path
from typing import Any

import pytest

import control.factory
import experiments.identify_then_control as itc
from control import loop

# the stubs reach the worker processes because they are forked from this one (Linux's default start method)
pytestmark = pytest.mark.skipif(multiprocessing.get_start_method() != "fork",
                                reason="the stubbed functions reach the workers only through fork")


class _FakeGreyBox:
    def save(self, path: Path) -> Path:
        path.with_suffix(".json").write_text("{}", encoding="utf-8")
        return path.with_suffix(".json")


def _fake_episode(name: str, trace_index: int, seed: int, models: dict[str, Any], quick: bool,
                  record: bool = False) -> dict[str, Any]:
    return {"name": name, "cycle": f"c{trace_index}", "seed": seed, "finished": time.time(),
            "greybox": models["greybox"], "black_box": models["black_box"]}


def _slow_episode(**task: Any) -> dict[str, Any]:
    time.sleep(1.0)
    return {"name": task["name"]}


def test_model_free_episodes_run_during_identification_and_nmpcs_get_the_models(tmp_path, monkeypatch) -> None:
    stamps: dict[str, float] = {}

    def identify(out, quick, ablation):
        time.sleep(1.5)                              # the identification takes a while ...
        stamps["identified"] = time.time()
        return {"models": {"rpem": {"path": "x"}}}

    monkeypatch.setattr(loop, "identify_for_control", identify)
    monkeypatch.setattr(control.factory, "greybox_record", lambda: (_FakeGreyBox(), {"params": [1.0]}))
    names = ["lookup_table", "mpc_oracle", "mpc_greybox", "mpc_rpem", "pi", "ppo"]
    first = [{"name": n, "trace_index": i, "seed": 0, "models": None, "quick": True, "record": True}
             for n in names for i in range(2)]
    ident, models, results = loop.identify_while_running(_fake_episode, tmp_path, True, False, first, ["ppo"],
                                                         workers=2)
    assert ident["greybox"] == {"params": [1.0]} and ident["black_box"] == {"models": {"rpem": {"path": "x"}}}
    assert Path(models["greybox"]).parent == tmp_path
    assert [(r["name"], r["cycle"]) for r in results] == [(t["name"], f"c{t['trace_index']}") for t in first]
    for r in results:
        if r["name"] in ("lookup_table", "mpc_oracle", "pi", "ppo"):   # ... and these ran meanwhile
            assert r["finished"] < stamps["identified"] and r["black_box"] is None
        else:
            assert r["black_box"] == ident["black_box"] and r["greybox"] == models["greybox"]


def test_a_failed_identification_ends_the_run_without_waiting_for_the_queued_episodes(tmp_path, monkeypatch) -> None:
    def identify(out, quick, ablation):
        raise RuntimeError("identification failed")

    monkeypatch.setattr(loop, "identify_for_control", identify)
    monkeypatch.setattr(control.factory, "greybox_record", lambda: (_FakeGreyBox(), {}))
    first = [{"name": "mpc_oracle", "trace_index": 0, "seed": s, "models": None, "quick": True, "record": False}
             for s in range(30)]                                   # 15 s of queued work on 2 workers
    t0 = time.time()
    with pytest.raises(RuntimeError, match="identification failed"):
        loop.identify_while_running(_slow_episode, tmp_path, True, False, first, [], workers=2)
    assert time.time() - t0 < 10.0


@pytest.mark.parametrize("workers", [0, -1, 1.5, True])
def test_bad_worker_counts_are_refused_before_identifying(tmp_path, monkeypatch, workers) -> None:
    monkeypatch.setattr(itc, "identify_for_control", lambda *a, **k: pytest.fail("identified anyway"))
    with pytest.raises(ValueError, match="workers"):
        itc.run(quick=True, out=tmp_path, include_rl=False, sweep_kwargs={"backend": "local", "workers": workers})


def _greybox_waits_episode(**task: Any) -> dict[str, Any]:
    if task["name"] == "mpc_greybox":
        time.sleep(1.5)
    return {"name": task["name"], "cycle": f"c{task['trace_index']}"}


def test_progress_is_printed_as_episodes_end_and_results_keep_the_task_order(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.setattr(loop, "identify_for_control", lambda out, quick, ablation: {"models": {}})
    monkeypatch.setattr(control.factory, "greybox_record", lambda: (_FakeGreyBox(), {}))
    first = [{"name": n, "trace_index": 0, "seed": 0, "models": None, "quick": True, "record": False}
             for n in ("mpc_greybox", "mpc_rpem", "mpc_hammerstein_wiener")]
    _, _, results = loop.identify_while_running(_greybox_waits_episode, tmp_path, True, False, first, [], workers=2)
    assert [r["name"] for r in results] == ["mpc_greybox", "mpc_rpem", "mpc_hammerstein_wiener"]
    lines = [ln for ln in capsys.readouterr().out.splitlines() if "episode " in ln]
    assert len(lines) == 3 and "3/3: mpc_greybox" in lines[-1]      # the slow first task is reported last
