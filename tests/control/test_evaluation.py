"""The evaluation harness runs any predict()-policy, calls the optional hooks and reports KPIs and timing."""
import numpy as np

from control.evaluation import comparison_table, evaluate, summarise
from control.protocol import PolicyPredictor, action_to_rate, rate_to_action


class _Const:
    def __init__(self, rate):
        self.rate = rate
        self.attached = 0

    def attach(self, env):
        self.attached += 1
        assert env.disturbance_preview(3).shape == (3, 4)

    def predict(self, observation, state=None, episode_start=None, deterministic=True):
        return rate_to_action(self.rate), state

    def stats(self):
        return {"solver_failures": 0}


def test_rate_action_round_trip():
    for r in (0.0, 0.7, 3.0):
        assert abs(action_to_rate(rate_to_action(r)) - r) < 1e-6
    assert rate_to_action(-1.0)[0] == -1.0 and rate_to_action(9.0)[0] == 1.0


def test_evaluate_whsc_kpis_hooks_and_table():
    p = _Const(0.2)
    assert isinstance(p, PolicyPredictor)
    res = evaluate(p, cycles=("whsc",), seeds=(0, 1), name="const", record_trajectory=True)
    assert len(res) == 2 and p.attached == 2
    r = res[0]
    assert 0.0 < r.kpis["nox_conversion"] < 1.0
    assert r.kpis["adblue_g"] > 0 and r.timing["policy_time_ms_median"] >= 0
    assert r.stats["solver_failures"] == 0
    assert np.allclose(r.trajectory["adblue_g_s"], 0.2, atol=1e-5)
    s = summarise(res)["whsc"]["const"]
    assert s["n_seeds"] == 2
    table = comparison_table(res)
    assert "const" in table and "TP g/kWh" in table


def test_max_steps_stops_early_without_kpis():
    res = evaluate(_Const(0.0), cycles=("whtc",), max_steps=5)
    assert res[0].kpis == {} and res[0].timing["policy_time_ms_median"] >= 0


def test_a_single_cycle_and_seed_are_one_element_sequences():
    """evaluate(policy, cycles="whsc") runs the WHSC, not the cycles 'w', 'h', 's', 'c'."""
    res = evaluate(_Const(0.1), cycles="whsc", seeds=3, max_steps=3)
    assert [(r.cycle, r.seed) for r in res] == [("whsc", 3)]
    res = evaluate(_Const(0.1), cycles=["whsc"], seeds=np.int64(2), max_steps=3)
    assert [(r.cycle, r.seed) for r in res] == [("whsc", 2)]
    res = evaluate(_Const(0.1), cycles=("whsc",), seeds=None, max_steps=3)
    assert [r.seed for r in res] == [None]


def test_empty_or_non_iterable_cycles_and_seeds_are_refused():
    import pytest

    with pytest.raises(ValueError, match="cycles is empty"):
        evaluate(_Const(0.1), cycles=(), max_steps=3)
    with pytest.raises(ValueError, match="seeds is empty"):
        evaluate(_Const(0.1), cycles="whsc", seeds=[], max_steps=3)
    with pytest.raises(TypeError, match="seeds must be one item or a sequence"):
        evaluate(_Const(0.1), cycles="whsc", seeds=1.5, max_steps=3)


def test_max_steps_must_be_a_positive_number_of_steps():
    """max_steps=0 used to end in UnboundLocalError; now 0, negatives, floats and bools are named errors."""
    import pytest

    for bad in (0, -3, 2.5, True, "5"):
        with pytest.raises(ValueError, match="max_steps"):
            evaluate(_Const(0.0), cycles=("whtc",), max_steps=bad)
    one = evaluate(_Const(0.0), cycles=("whtc",), max_steps=np.int64(1), record_trajectory=True)[0]
    assert len(one.trajectory["reward"]) == 1 and one.kpis == {}


def test_evaluate_runs_any_gymnasium_environment():
    """A surrogate of the plant, a wrapped plant and a classic-control task run through the same harness."""
    import gymnasium as gym
    import pytest

    from control.rl.surrogate import SurrogateSCREnv
    from scr_env.envs.urea_scr import UreaSCREnv
    from tests.control.test_rl import _surrogate

    class Plain:   # a policy without attach() or stats()
        def predict(self, observation, state=None, episode_start=None, deterministic=True):
            return np.array([0.0], dtype=np.float32), state

    sur = SurrogateSCREnv(_surrogate(), cycle="random", random_cycle_duration_s=60.0)
    res = evaluate(Plain(), env=sur, seeds=(0, 1), record_trajectory=True, name="plain")
    assert [r.seed for r in res] == [0, 1] and len(res[0].trajectory["reward"]) == 120
    assert {"tailpipe_nox_g_per_kwh", "mean_nh3_slip_ppm"} <= set(res[0].kpis)
    assert np.isnan(res[0].trajectory["mean_coverage"]).all()   # a surrogate has no catalyst state
    # a wrapped plant gives the same KPIs as the harness's own plant
    wrapped = gym.wrappers.ClipAction(UreaSCREnv(cycle="whsc"))
    a = evaluate(_Const(0.2), env=wrapped, seeds=0)[0].kpis
    b = evaluate(_Const(0.2), cycles="whsc", seeds=0)[0].kpis
    assert a == b
    # any Gymnasium task: the episode ends when the environment says so
    cart = gym.make("CartPole-v1")

    class Left:
        def predict(self, observation, state=None, episode_start=None, deterministic=True):
            return 0, state

    r = evaluate(Left(), env=cart, seeds=0, record_trajectory=True)[0]
    assert r.kpis == {} and 5 < len(r.trajectory["reward"]) < 100
    with pytest.raises(ValueError, match="either env or cycles"):
        evaluate(Plain(), env=sur, cycles="whtc")
    with pytest.raises(TypeError, match="Gymnasium environment"):
        evaluate(Plain(), env=object())


def test_cycle_segment_cuts_every_signal():
    from control.evaluation import cycle_segment
    from scr_env.cycles import load_cycle

    seg = cycle_segment("whtc", 60.0, name="whtc_0-60s")
    full = load_cycle("whtc", dt=0.5)
    assert seg.n_steps == 120 and seg.name == "whtc_0-60s"
    np.testing.assert_array_equal(seg.scr_inlet_temperature_k, full.scr_inlet_temperature_k[:120])
    assert cycle_segment(full, 1e6).n_steps == full.n_steps
    res = evaluate(_Const(0.1), cycles=seg)[0]
    assert res.cycle == "whtc_0-60s" and res.kpis["engine_work_kwh"] > 0
