"""Gymnasium environments of the SCR plant: the single and the native vector environment."""
from scr_env.envs.urea_scr import UreaSCREnv
from scr_env.envs.vector import UreaSCRVectorEnv

__all__ = ["UreaSCREnv", "UreaSCRVectorEnv"]
