"""The RL benchmark pipeline end to end at smoke size: anchors, baselines trained over seeds, datasets and behaviour
cloning, the leaderboard JSON (the contract of experiments.rl_benchmark)."""
from __future__ import annotations

import json

import gymnasium as gym
import pytest

pytest.importorskip("stable_baselines3")
pytest.importorskip("minari")
pytest.importorskip("jax")


@pytest.mark.slow
def test_pipeline_smoke_writes_the_leaderboard_contract(tmp_path):
    from experiments import make_datasets, rl_anchors, rl_benchmark, train_baselines

    anchors = tmp_path / "anchors.json"
    policies = tmp_path / "policies"
    rl_anchors.main(["--tasks", "WHTC", "--max-steps", "40", "--quick", "--out", str(anchors)])
    assert json.loads(anchors.read_text())["tasks"]["scr_env/UreaSCR-WHTC-v0"]["partial_episodes"] == 40
    rep = train_baselines.main(["--groups", "fresh", "--algos", "td3", "--seeds", "0", "1", "--timesteps", "256",
                                "--jobs", "1", "--ship", "--policies", str(policies), "--validation-s", "20",
                                "--out", str(tmp_path / "train")])
    assert not rep["failed"] and len(rep["runs"]) == 2
    assert all(r["steps_per_s"] > 0 and isinstance(r["within_slip_limit"], bool) for r in rep["runs"])
    make_datasets.main(["--root", str(tmp_path / "datasets"), "--groups", "fresh", "--episodes", "1",
                        "--duration-s", "20", "--quick", "--bc-seeds", "0", "1", "--ship-bc", "--policies",
                        str(policies), "--out", str(tmp_path / "ds")])
    out = tmp_path / "board.json"
    rl_benchmark.main(["--tasks", "WHTC", "--policies", str(policies), "--anchors", str(anchors), "--max-steps", "40",
                       "--single", "--out", str(tmp_path / "bench"), "--json", str(out)])
    board = json.loads(out.read_text())
    assert list(board["tasks"]) == ["scr_env/UreaSCR-WHTC-v0"]
    for tid, d in board["tasks"].items():
        assert tid in gym.registry
        s = d["scores"]
        assert s["lookup_table"]["iqm"] == pytest.approx(0.0, abs=1e-9) and s["lookup_table"]["learned"] is False
        assert s["reference"]["iqm"] == pytest.approx(100.0) and s["reference"]["learned"] is False
        for method in ("td3", "bc"):
            e = s[method]
            assert e["learned"] is True and e["n_seeds"] == 2 and len(e["ci"]) == 2
            assert e["ci"][0] <= e["iqm"] <= e["ci"][1] and e["chatter_g_s_per_h"] >= 0
    assert (tmp_path / "bench" / "leaderboard.md").read_text().count("scr_env/UreaSCR-WHTC-v0") == 1
    assert (tmp_path / "bench" / "learning_curves_fresh.png").stat().st_size > 0
