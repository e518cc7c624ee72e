"""control: one policy protocol, an evaluation harness, industrial baselines, state estimation and nonlinear MPC.

* :mod:`control.protocol` -- :class:`PolicyPredictor` (the stable-baselines3 ``predict``), optional ``attach(env)``
  and ``stats()`` hooks, :func:`check_observation` (the observation check every ``predict`` starts with);
  :mod:`control.evaluation` -- :func:`evaluate`, :func:`comparison_table`.
* :mod:`control.baselines` -- :class:`LookupTableDosing`, :class:`FeedforwardPI`.
* :mod:`control.estimation` -- :class:`ExtendedKalmanFilter` on any CasADi step function.
* :mod:`control.mpc` -- :class:`NonlinearMPC`; :mod:`control.models` -- :class:`FirstPrinciplesModel` (oracle),
  :class:`IdentifiedModelAdapter` (the identified models themselves, the grey-box
  :class:`ident.greybox.StorageGreyBox` among them, live in :mod:`ident`).
* :mod:`control.rl` -- reinforcement learning (separate owner).

Heavy modules (CasADi) are imported lazily: ``from control.mpc import NonlinearMPC``.
"""
from __future__ import annotations

# marks this package as scr-dosing's (python-control shares the name `control`: scr_env.installation)
__scr_dosing_package__ = True

from control.baselines import FeedforwardPI, LookupTableDosing
from control.evaluation import EpisodeResult, comparison_table, evaluate, summarise
from control.protocol import PolicyPredictor, action_to_rate, check_observation, rate_to_action

__all__ = ["EpisodeResult", "FeedforwardPI", "LookupTableDosing", "PolicyPredictor", "action_to_rate",
           "check_observation", "comparison_table", "evaluate", "rate_to_action", "summarise"]
