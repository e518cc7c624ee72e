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
