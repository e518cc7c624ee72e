"""control: one policy protocol, an evaluation harness, industrial baselines, state estimation and nonlinear MPC."""
from __future__ import annotations

from control.evaluation import EpisodeResult, comparison_table, evaluate, summarise
from control.protocol import PolicyPredictor, action_to_rate, rate_to_action

__all__ = ["EpisodeResult", "PolicyPredictor", "action_to_rate", "comparison_table", "evaluate", "rate_to_action",
           "summarise"]
