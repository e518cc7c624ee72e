"""Reinforcement-learning dosing policies with stable-baselines3: vector-env adapter, observation pipeline,
training, surrogate-model environments and the shipped policies (``load_policy("ppo")``)."""
from control.rl.policy import RLPolicy, available_policies, load_policy

__all__ = ["RLPolicy", "available_policies", "load_policy"]
