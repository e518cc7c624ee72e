"""The limit of the dosing task: the clairvoyant whole-cycle optimum (issue 19).

The dosing that minimises the tailpipe NOx [g/kWh] over a whole drive cycle at a given mean NH3-slip budget [ppm],
knowing the plant and the whole cycle in advance. No causal controller can do better on that plant, so it is the
100 % mark of a normalised score (:func:`gap_to_limit`) and, over several budgets, the NOx-against-slip Pareto front
of the task.

Reading the stored limit (never re-solved; ``control/data/limit.json``, written by ``python -m experiments.limit
--store``) and scoring a controller with it::

    from control.limit import gap_to_limit, stored_limit
    limit = stored_limit("whtc", 10.0)                  # the hot WHTC at the Euro VI 10 ppm mean-slip limit
    limit.replay_tailpipe_nox_g_per_kwh                 # the optimum's NOx, replayed through the environment
    gap_to_limit(lut_nox, controller_nox, limit.replay_tailpipe_nox_g_per_kwh)   # 0: look-up table, 1: the limit

Solving it (:mod:`control.limit.problem`; a minute or more per budget on a whole cycle)::

    from control.limit import CycleOptimum, pareto_front, replay
    problem = CycleOptimum("whtc")                      # the hot WHTC at dt = 0.5 s, as the benchmark runs it
    best = problem.solve(10.0)                          # mean slip <= 10 ppm
    best.tailpipe_nox_g_per_kwh, best.dose_g_s          # the optimum and its dose trajectory [g/s]
    replay("whtc", best.dose_g_s)                       # the environment's KPIs of that dose, open loop
    front = pareto_front(problem, (1, 2, 5, 10, 20))    # every budget, warm-started from its neighbour

Modules: :mod:`~control.limit.common` (the result record, the score, the environment of a limit and the replay),
:mod:`~control.limit.problem` (the optimal-control problem and how it is solved), :mod:`~control.limit.stored`
(the stored limit, the plant fingerprint that says whether it is still valid, the Pareto figure).
"""
from __future__ import annotations

from control.limit.common import (
    DEFAULT_BUDGETS_PPM,
    PLANT_ARGUMENTS,
    REFERENCE_BUDGET_PPM,
    STORED_CYCLES,
    LimitResult,
    cycle_segment,
    gap_to_limit,
    make_env,
    replay,
)
from control.limit.problem import CycleOptimum, pareto_front
from control.limit.stored import (
    StaleLimitWarning,
    annotate_gap_to_limit,
    controllers_against_limit,
    fingerprint_changes,
    limit_nox,
    pareto_figure,
    plant_entry_name,
    plant_fingerprint,
    stored_limit,
    stored_limit_path,
    stored_limits,
    task_limit_metrics,
    write_limit_document,
)

__all__ = [
    "DEFAULT_BUDGETS_PPM",
    "PLANT_ARGUMENTS",
    "REFERENCE_BUDGET_PPM",
    "STORED_CYCLES",
    "CycleOptimum",
    "LimitResult",
    "StaleLimitWarning",
    "annotate_gap_to_limit",
    "controllers_against_limit",
    "cycle_segment",
    "fingerprint_changes",
    "gap_to_limit",
    "limit_nox",
    "make_env",
    "pareto_figure",
    "pareto_front",
    "plant_entry_name",
    "plant_fingerprint",
    "replay",
    "stored_limit",
    "stored_limit_path",
    "stored_limits",
    "task_limit_metrics",
    "write_limit_document",
]
