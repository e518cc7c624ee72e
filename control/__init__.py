"""control: every controller of the project and everything a controller is built from.

* :mod:`control.protocol` -- :class:`PolicyPredictor` (the stable-baselines3 ``predict``), optional ``attach(env)``
  and ``stats()`` hooks, :func:`check_observation` (the observation check every ``predict`` starts with);
  :mod:`control.evaluation` -- :func:`evaluate` (any Gymnasium environment), :func:`comparison_table`.
* :mod:`control.baselines` -- :class:`LookupTableDosing`, :class:`FeedforwardPI`, :class:`FeedforwardDosing` and
  the one feedforward law :func:`feedforward_dose_g_s`.
* :mod:`control.estimation` -- :class:`~control.estimation.ExtendedKalmanFilter` on any CasADi step function, and the
  state estimators an NMPC calls (:class:`~control.estimation.ObservationEKF`,
  :class:`~control.estimation.PrivilegedState`).
* :mod:`control.mpc` -- :class:`~control.mpc.NonlinearMPC`; :mod:`control.models` -- its prediction models
  (:class:`~control.models.FirstPrinciplesModel`, the oracle's; :class:`~control.models.IdentifiedModelAdapter`
  for any model of :mod:`ident`); :mod:`control.signals` -- an identified model's input map and normalisation.
* :mod:`control.factory` -- the grey-box identification recipe, the identified-model, black-box and oracle NMPCs,
  every benchmarked controller by name; :mod:`control.adaptive` -- the RPEM-adapted NMPC; :mod:`control.ageing`,
  :mod:`control.loop` -- the ageing and identify-then-control studies' library parts; :mod:`control.plots` --
  closed-loop figures.
* :mod:`control.rl` -- reinforcement learning.

Heavy modules (CasADi) are imported lazily: ``from control.mpc import NonlinearMPC``.
"""
from __future__ import annotations

# marks this package as scr-dosing's (python-control shares the name `control`: scr_env.installation)
__scr_dosing_package__ = True

from control.baselines import FeedforwardDosing, FeedforwardPI, LookupTableDosing, feedforward_dose_g_s
from control.evaluation import EpisodeResult, comparison_table, evaluate, summarise
from control.protocol import PolicyPredictor, action_to_rate, check_observation, rate_to_action

__all__ = ["EpisodeResult", "FeedforwardDosing", "FeedforwardPI", "LookupTableDosing", "PolicyPredictor",
           "action_to_rate", "check_observation", "comparison_table", "evaluate", "feedforward_dose_g_s",
           "rate_to_action", "summarise"]
