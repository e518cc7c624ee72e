"""Nonlinear MPC of AdBlue dosing with CasADi: one NLP, built once, for any prediction model.

The optimal control problem over ``horizon`` stages of ``stage_steps`` control intervals each (stage length
``h = stage_steps * dt``; the first input is applied for one interval, then the problem is solved again), or over
multi-rate ``stages`` (control intervals of each stage, e.g. 10 stages of 4 then 8 of 40: fine stages now, coarse
ones that see minutes ahead at the same NLP size; stage i lasts ``h_i = stages[i] * dt``):

    min   sum_i [ h_i F_i ((w_nox M_NO2 y_nox,i + w_nh3 M_NH3 y_nh3,i) 1e-6) + w_nh3_ppm_s h_i y_nh3,i
                  + w_adblue h_i u_i + w_du (u_i - u_i-1)^2 + w_slack (h_i / h_0) (s_i + s_i^2) ] + V(x_H)
    s.t.  r(x_i+1, x_i, u_i, d_i, p_i) = 0                 (the model, multiple shooting / implicit collocation)
          0 <= u_i <= u_max,  |u_i - u_i-1| <= du_max h_i   (injector range, rate limit; u_-1 the applied dose,
                                                             over one control interval for the first stage)
          y_nh3,i <= slip_limit_ppm + s_i,  s_i >= 0        (soft NH3-slip constraint)

with u the AdBlue rate [g/s], F the exhaust flow [mol/s], y the predicted tailpipe NOx and NH3 [ppm], d the
engine-out disturbance (flow, inlet temperature, NOx, NO2 fraction) and p model-specific stage parameters. The
default weights are the environment's economic reward (20 per g NOx, 60 per g NH3, 1 per g AdBlue; the
time-weighted slip price ``w_nh3_ppm_s``, per ppm s of tailpipe NH3 as the mean-slip KPI counts it, is 0). The
disturbance is held at its measured value over the horizon unless ``preview=True`` (then the cycle preview from
``env.disturbance_preview``, privileged information, given through :meth:`NonlinearMPC.attach`).

Slip budget (``slip_budget_ppm``, with ``w_nh3_ppm_s > 0``): the slip price is then an NLP parameter, set at each step
from the episode's mean slip so far ``m`` (``env.episode_kpis()``, privileged) by a multiplicative dual update of
the mean-slip constraint ``m <= b`` (Lagrangian relaxation of an average constraint, as in drift-plus-penalty
control; Neely 2010): ``price = w_nh3_ppm_s exp(gain max(m' - b, 0) / b)`` with ``m'`` the mean over the episode so
far and ``BUDGET_PRIOR_S`` seconds at the budget (early spikes do not dominate). One-sided: the price only rises
above ``w_nh3_ppm_s``, so a cycle that stays within the budget is controlled as without it.

Model sources (:class:`PredictionModel`, in :mod:`control.models`): the first-principles catalyst (the oracle) and
any identified model's CasADi export. The state every solve starts from comes from a state estimator of its own
(:class:`control.estimation.StateEstimator`, do-mpc's split): at each step the controller calls
``x0 = estimator.make_step(observation, applied dose, disturbance)`` and then solves from ``x0`` -- the oracle's
:class:`~control.estimation.PrivilegedState`, an identified model's :class:`~control.estimation.ObservationEKF`
(``model.make_estimator()`` unless one is given). The NLP is an SX ``nlpsol`` (IPOPT by default), warm-started
from the previous solution.

A failed solve (solver status not successful, a non-finite result, or one of the numerical exceptions of
:data:`SOLVE_ERRORS`) never raises mid-episode: the controller applies the last good plan while it lasts, then the
fallback dose (the look-up table by default), counts the failure (``solver_failures``), classifies it by kind
(:data:`FAILURE_KINDS`, ``solver_failures_<kind>``) and reports it in :meth:`NonlinearMPC.stats`, with the solve
times. An iterate at the iteration limit that satisfies every constraint (model equations included, to 1e-6) is a
valid but suboptimal plan: it is applied and counted as ``solver_suboptimal``, not as a failure. A fallback policy
that raises or returns a non-finite action is replaced by the safe action, no dosing (counted as
``fallback_errors``; the episode goes on).

The solvers are quiet: IPOPT, CasADi's SQP method and its QP solver print nothing, and NaN/Inf found in the NLP's
functions (CasADi's ``show_eval_warnings``) are not printed but counted (kind ``nonfinite_model``). Every failed
solve is logged at debug level on the ``control.mpc`` logger (``logging.getLogger("control.mpc")``) with its step,
kind and solver status, and kept in :attr:`NonlinearMPC.failures_` for the episode.

Settings are checked when the controller is built (and again when its NLP is built, for attributes changed
later): ``horizon`` and ``stage_steps`` whole numbers >= 1 (``stages``, when given, a non-empty sequence of them,
and then ``horizon == len(stages)``, ``stage_steps == stages[0]``), ``slip_limit_ppm`` >= 0 (inf: no slip bound),
``max_rate_change_g_s2`` > 0 (inf: no rate limit), :class:`MPCWeights` finite and >= 0, ``fallback`` a policy;
a bad one raises ``ValueError`` naming it.

What is *not* a failed solve, and raises: a bad observation (checked before anything else by
:func:`control.protocol.check_observation`: None, NaN/inf, wrong size, a batch of several plants -- nothing of the
controller's state is touched), and any other exception of the solve (``ValueError``, ``TypeError``,
``IndexError``, ``AttributeError``, ... from the model or its configuration). Those are errors of the caller or of
the code, the same at every step; counting them as solver failures would make a broken controller look like a
weak one that falls back to the look-up table.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, fields
from typing import Any, Protocol

import casadi as ca
import numpy as np

from control.baselines import LookupTableDosing
from control.estimation import StateEstimator
from control.protocol import (
    DEFAULT_MAX_RATE_G_S,
    N_BASE_OBSERVATION,
    action_to_rate,
    check_observation,
    is_episode_start,
    observation_size,
    rate_to_action,
)
from scr_env.constants import EURO_VI_NH3_SLIP_LIMIT_PPM, NH3_MOLAR_MASS_G_MOL, NO2_MOLAR_MASS_G_MOL

#: disturbance columns per stage, as ``UreaSCREnv.disturbance_preview``: flow mol/s, inlet T K, NOx ppm, NO2 frac
N_DISTURBANCE = 4
#: the slip budget's prior [s]: the mean slip the price tracks counts this many seconds at the budget before the
#: episode's own, so that a spike in the first minutes does not multiply the price (a design constant, not tuned)
BUDGET_PRIOR_S = 300.0
#: the largest exponent of the slip budget's price factor (a factor of e^5 = 148 at most)
MAX_PRICE_EXPONENT = 5.0

#: exceptions of a solve that count as a failed solve (fallback dose, ``solver_failures``) instead of raising:
#:
#: * ``RuntimeError``: what CasADi raises for any failure inside a ``Function`` call -- the NLP solver with
#:   ``error_on_fail``, NaN/Inf in its functions with regularity checks, a QP solver giving up;
#: * ``numpy.linalg.LinAlgError``: the state estimator's innovation covariance (``estimator.make_step``)
#:   numerically singular -- a degenerate estimate, not a wrong argument (it is a ``ValueError`` subclass: only it
#:   is caught, not ``ValueError`` in general);
#: * ``ArithmeticError`` (``FloatingPointError`` -- numpy under ``errstate(all="raise")``, or the EKF refusing an
#:   update that would make its estimate non-finite --, ``OverflowError``, ``ZeroDivisionError`` from the numba or
#:   Python model preparation at an extreme state).
#:
#: Everything else propagates (module docstring).
SOLVE_ERRORS: tuple[type[BaseException], ...] = (RuntimeError, np.linalg.LinAlgError, ArithmeticError)

logger = logging.getLogger(__name__)

#: the kinds a failed solve is counted under (``stats()["solver_failures_<kind>"]``):
#:
#: * ``iteration_limit``: the solver stopped at its iteration or time limit at an iterate that violates the
#:   constraints (an iterate that satisfies them is a suboptimal plan, applied, not a failure);
#: * ``infeasible``: the solver found the problem locally infeasible (IPOPT ``Infeasible_Problem_Detected``);
#: * ``restoration``: IPOPT's feasibility restoration failed (``Restoration_Failed``, ``Error_In_Step_Computation``);
#: * ``small_step``: the search direction became too small at an iterate that violates the constraints;
#: * ``qp_failure``: the QP subproblem of an SQP method failed;
#: * ``nonfinite_model``: NaN or Inf in the model's functions or in the returned solution;
#: * ``estimator``: the state estimator failed (a singular innovation covariance, a non-finite update);
#: * ``error``: any other numerical exception of the solve (:data:`SOLVE_ERRORS`, e.g. CasADi's RuntimeError);
#: * ``other``: any other unsuccessful solver status.
FAILURE_KINDS: tuple[str, ...] = ("iteration_limit", "infeasible", "restoration", "small_step", "qp_failure",
                                  "nonfinite_model", "estimator", "error", "other")
_STATUS_KINDS = {
    "Maximum_Iterations_Exceeded": "iteration_limit", "Maximum_CpuTime_Exceeded": "iteration_limit",
    "Maximum_WallTime_Exceeded": "iteration_limit", "Infeasible_Problem_Detected": "infeasible",
    "Restoration_Failed": "restoration", "Error_In_Step_Computation": "restoration",
    "Search_Direction_Becomes_Too_Small": "small_step", "Invalid_Number_Detected": "nonfinite_model",
    "Not_Enough_Degrees_Of_Freedom": "infeasible", "QP_solver_failed": "qp_failure",
    "Solve_Failed": "qp_failure", "Non_Regular_Sensitivities": "qp_failure"}
#: solver statuses whose iterate may still be a valid (suboptimal) plan when it satisfies every constraint
_USABLE_STATUSES = ("Maximum_Iterations_Exceeded", "Maximum_CpuTime_Exceeded", "Maximum_WallTime_Exceeded",
                    "Search_Direction_Becomes_Too_Small")


def failure_kind(status: str, unified: str = "") -> str:
    """The :data:`FAILURE_KINDS` entry of an unsuccessful solver ``status`` (``return_status`` of the NLP solver's
    stats; ``unified`` its ``unified_return_status``: NaN/Inf met by the solver first, then the status, then the
    unified status when the status itself is not known here)."""
    if unified == "SOLVER_RET_NAN":
        return "nonfinite_model"   # e.g. sqpmethod's Non_Regular_Sensitivities after NaN in its functions
    kind = _STATUS_KINDS.get(status)
    if kind is not None:
        return kind
    low = status.lower()
    if "qp" in low:
        return "qp_failure"
    if "nan" in low or "inf detected" in low or "invalid" in low:
        return "nonfinite_model"
    return {"SOLVER_RET_LIMITED": "iteration_limit", "SOLVER_RET_NAN": "nonfinite_model",
            "SOLVER_RET_INFEASIBLE": "infeasible"}.get(unified, "other")


def _check_count(value: Any, name: str) -> int:
    """A whole number >= 1 (bool refused), as int; ``ValueError`` naming ``name`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a whole number >= 1, got {value!r}")
    return int(value)


def _check_number(value: Any, name: str, *, positive: bool, allow_inf: bool) -> float:
    """A real number, not NaN, >= 0 (``positive``: > 0), finite unless ``allow_inf``; ``ValueError`` naming
    ``name`` otherwise."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if isinstance(value, bool) or math.isnan(v) or (math.isinf(v) and not allow_inf) or (v <= 0 if positive
                                                                                         else v < 0):
        bound = "> 0" if positive else ">= 0"
        raise ValueError(f"{name} must be a {'' if allow_inf else 'finite '}number {bound}, got {value!r}")
    return v


@dataclass(frozen=True)
class MPCWeights:
    """Objective weights in grams of AdBlue equivalent (the first three are the environment's reward weights)."""

    nox: float = 20.0  # per g tailpipe NOx (as NO2)
    nh3: float = 60.0  # per g NH3 slip
    adblue: float = 1.0  # per g AdBlue
    rate_change: float = 0.05  # per (g/s)^2 of dose change between stages
    slack: float = 50.0  # per ppm of slip above the limit (plus its square), per stage
    #: per ppm s of predicted tailpipe NH3, time-weighted as the mean-slip KPI counts it (not by mass: the KPI's
    #: mean slip [ppm] is a time average, so a ppm at low exhaust flow uses as much of the budget as one at high
    #: flow); 0 (the default) adds nothing to the objective
    nh3_ppm_s: float = 0.0

    def __post_init__(self) -> None:
        """Every weight a finite number >= 0 (``ValueError`` naming it): a negative AdBlue weight would pay the
        controller for dosing, a NaN one makes every solve fail."""
        for f in fields(self):
            _check_number(getattr(self, f.name), f"MPCWeights.{f.name}", positive=False, allow_inf=False)


class PredictionModel(Protocol):
    """What :class:`NonlinearMPC` needs from a model (see :mod:`control.models`)."""

    nx: int
    n_stage_params: int
    n_terminal_params: int

    def residual(self, x_next: Any, x: Any, u: Any, d: Any, p: Any, h: float) -> Any:
        """Model equations of one stage of length h [s], zero when satisfied (SX, length nx)."""

    def outputs(self, x_next: Any, x: Any, u: Any, d: Any, p: Any) -> Any:
        """Predicted (tailpipe NOx ppm, tailpipe NH3 ppm) of the stage (SX, length 2)."""

    def terminal_cost(self, x: Any, p: Any) -> Any:
        """Cost of the terminal state (SX scalar, grams of AdBlue equivalent)."""

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of the state."""

    def attach(self, env: Any) -> None:
        """Called by the controller's ``attach`` with the unwrapped environment."""

    def reset(self, observation: np.ndarray) -> None:
        """Start of an episode."""

    def stage_parameters(self, observation: np.ndarray, disturbances: np.ndarray, h: float,
                         dt: float) -> tuple[np.ndarray, np.ndarray]:
        """Numeric (stage parameters (H, n_stage_params), terminal parameters (n_terminal_params,)) for this step,
        from the observation and the (H, 4) stage disturbances; stages of ``h`` seconds (a float; an (H,) array of
        each stage's length for multi-rate stages), control interval ``dt``."""

    def make_estimator(self) -> StateEstimator:
        """The model's default state estimator (used when the controller is given none)."""


def solver_defaults(solver: str) -> dict[str, Any]:
    """The quiet ``nlpsol`` options every NMPC of the project starts from (IPOPT: warm start, at most 60 iterations,
    no output; other solvers: no timing output). NaN/Inf in the NLP's functions is a failed solve, counted by kind
    (``nonfinite_model``), not a printed line."""
    opts: dict[str, Any] = {"ipopt.print_level": 0, "print_time": False, "ipopt.max_iter": 60, "ipopt.tol": 1e-6,
                            "ipopt.acceptable_tol": 1e-3, "ipopt.acceptable_iter": 3,
                            "ipopt.warm_start_init_point": "yes", "ipopt.sb": "yes",
                            "ipopt.mu_init": 1e-3} if solver == "ipopt" else {"print_time": False}
    opts["show_eval_warnings"] = False
    return opts


class NonlinearMPC:
    """Economic NMPC with a soft NH3-slip constraint (module docstring). Satisfies the policy protocol.

    Parameters
    ----------
    model : a :class:`PredictionModel` (:class:`control.models.FirstPrinciplesModel` or
        :class:`control.models.IdentifiedModelAdapter`).
    horizon : number of stages.
    stage_steps : control intervals per stage.
    stages : multi-rate stages, the control intervals of each stage (e.g. ``(4,) * 10 + (40,) * 8``: 20 s of 2 s
        stages, then 320 s of 20 s stages); None (default): ``horizon`` stages of ``stage_steps``. When given,
        ``horizon`` and ``stage_steps`` become ``len(stages)`` and ``stages[0]``. Uniform stages give the same NLP
        as ``horizon`` and ``stage_steps``. The model's ``stage_parameters`` is then given the stage lengths as an
        array (a float for uniform stages). Kept as the attribute ``stage_layout`` (a subclass may keep a ``stages``
        of its own: :class:`control.blackbox.BlackBoxMPC` builds its multi-rate NLP itself).
    weights : :class:`MPCWeights`.
    slip_limit_ppm : soft bound of the predicted tailpipe NH3 [ppm].
    max_rate_change_g_s2 : dosing rate limit [g/s per s].
    preview : use the cycle preview (privileged) instead of holding the measured disturbance.
    fallback : policy applied when a solve fails (default: the look-up table).
    estimator : the :class:`~control.estimation.StateEstimator` the solves start from (default
        ``model.make_estimator()``); an object of its own, reusable with any model of the same state.
    slip_guard : ``(observation index, ppm)`` of a tailpipe NH3 sensor, or None. On a failed solve, while that
        reading is above the threshold, nothing is dosed (neither the last plan nor the fallback): a failed solve
        typically comes when the catalyst already slips (heating desorbs its store and the slip bound cannot be
        met), and the open-loop fallback would dose into the slip. Solved plans are never overridden.
    solver, solver_options : CasADi ``nlpsol`` plugin and options (IPOPT quiet, 50 iterations by default).
    warm_start_duals : pass the previous solution's constraint multipliers (``lam_g0``) to the next solve; default
        True for IPOPT (interior point: only used with its warm-start option) and False otherwise. An SQP method
        with the exact Hessian builds its first QP from the Hessian of the Lagrangian at ``lam_g0``: the unshifted
        multipliers of the previous problem (another disturbance, another active set) make that Hessian indefinite
        after a transient, and the QP solver then pivots for long or fails (non-finite steps and NaN gradients
        downstream); starting from zero multipliers (the objective's Hessian) converges in a few iterations.
    rescue_solver, rescue_options : an optional second ``nlpsol`` plugin (and its options; IPOPT's defaults as
        above) that solves the same NLP when the first solver fails, from the cold start (the estimated state held
        over the horizon, the last dose): a fast SQP method for the common case, a robust interior-point method
        for the rest. A rescued solve is not a failure; it is counted as ``solver_rescued`` (and kept in
        :attr:`rescues_` with the first solver's failure kind); a solve that both fail counts as failed, with the
        rescue's kind.
    slip_budget_ppm, slip_budget_gain : the mean-slip budget ``b`` [ppm] the slip price tracks and the gain of
        its update (module docstring; ``None``: a fixed price). Needs ``weights.nh3_ppm_s > 0`` and an environment
        with ``episode_kpis()`` (read through :meth:`attach`, privileged: for reference controllers such as the
        oracle). The price factor of each step is kept for :meth:`stats` (``slip_price_factor_mean`` / ``_max``).
    rescue_hold_steps : after a rescue, the next ``rescue_hold_steps`` solves go to the rescue solver first
        (warm-started from the last plan; the first solver, then the rescue from the cold start, if it fails):
        failed solves come in stretches (a heat-up desorbing the store), and a first solver that fails again at
        every step would double each step's cost there. Counted as ``solver_rescue_held`` (the solves it made).
    """

    def __init__(self, model: PredictionModel, horizon: int = 20, stage_steps: int = 4,
                 weights: MPCWeights | None = None, slip_limit_ppm: float = EURO_VI_NH3_SLIP_LIMIT_PPM,
                 max_rate_change_g_s2: float = 1.0, preview: bool = False, fallback: Any = None,
                 solver: str = "ipopt", solver_options: dict | None = None,
                 warm_start_duals: bool | None = None, slip_guard: tuple[int, float] | None = None,
                 estimator: StateEstimator | None = None, rescue_solver: str | None = None,
                 rescue_options: dict | None = None, rescue_hold_steps: int = 0,
                 stages: Any = None, slip_budget_ppm: float | None = None, slip_budget_gain: float = 1.0) -> None:
        self.model = model
        self.slip_budget_ppm = slip_budget_ppm
        self.slip_budget_gain = slip_budget_gain
        self.stage_layout = stages
        if stages is not None and not isinstance(stages, (str, bytes)) and hasattr(stages, "__len__") \
                and len(stages) > 0:
            horizon, stage_steps = len(stages), stages[0]
        self.horizon = horizon
        self.stage_steps = stage_steps
        self.weights = weights
        self.slip_limit_ppm = slip_limit_ppm
        self.max_rate_change_g_s2 = max_rate_change_g_s2
        self.preview = preview
        self.fallback = fallback
        self._check_settings()
        self.estimator = model.make_estimator() if estimator is None else estimator
        if slip_guard is not None:
            idx, ppm = slip_guard
            if int(idx) != idx or idx < 0 or not np.isfinite(ppm) or ppm < 0:
                raise ValueError("slip_guard must be (observation index >= 0, threshold ppm >= 0), "
                                 f"got {slip_guard!r}")
            slip_guard = (int(idx), float(ppm))
        self.slip_guard = slip_guard
        self.solver = solver
        self.solver_options = solver_options
        self.warm_start_duals = (solver == "ipopt") if warm_start_duals is None else bool(warm_start_duals)
        if not isinstance(solver, str) or not solver:
            raise ValueError(f"solver must be the name of a CasADi nlpsol plugin, got {solver!r}")
        if solver_options is not None and not isinstance(solver_options, dict):
            raise ValueError(f"solver_options must be a dict of CasADi options or None, got {solver_options!r}")
        if rescue_solver is not None and (not isinstance(rescue_solver, str) or not rescue_solver):
            raise ValueError(f"rescue_solver must be the name of a CasADi nlpsol plugin or None, got "
                             f"{rescue_solver!r}")
        if rescue_options is not None and not isinstance(rescue_options, dict):
            raise ValueError(f"rescue_options must be a dict of CasADi options or None, got {rescue_options!r}")
        if isinstance(rescue_hold_steps, bool) or not isinstance(rescue_hold_steps, (int, np.integer)) \
                or rescue_hold_steps < 0:
            raise ValueError(f"rescue_hold_steps must be a whole number >= 0, got {rescue_hold_steps!r}")
        self.rescue_solver = rescue_solver
        self.rescue_options = rescue_options
        self.rescue_hold_steps = int(rescue_hold_steps)
        self._default_fallback: Any = None
        self.dt = 0.5
        self.max_rate_g_s = DEFAULT_MAX_RATE_G_S
        self.observation_size_: int | None = None
        self._env = None
        self._budget_env = None
        self._solver = None
        self._reset_episode()

    def _check_settings(self) -> None:
        """The settings (module docstring); ``ValueError`` naming the first bad one. Normalises the counts to int."""
        if self.stage_layout is not None:
            st = self.stage_layout
            if isinstance(st, (str, bytes)) or not hasattr(st, "__len__") or len(st) == 0:
                raise ValueError(f"stages must be a non-empty sequence of whole numbers >= 1 or None, got {st!r}")
            self.stage_layout = tuple(_check_count(k, "stages") for k in st)
            if self.horizon != len(self.stage_layout) or self.stage_steps != self.stage_layout[0]:
                raise ValueError(f"stages {self.stage_layout!r} fix horizon = {len(self.stage_layout)} and "
                                 f"stage_steps = {self.stage_layout[0]}, got horizon {self.horizon!r} and "
                                 f"stage_steps {self.stage_steps!r} (set stage_layout = None to use them)")
        self.horizon = _check_count(self.horizon, "horizon")
        self.stage_steps = _check_count(self.stage_steps, "stage_steps")
        _check_number(self.slip_limit_ppm, "slip_limit_ppm", positive=False, allow_inf=True)
        _check_number(self.max_rate_change_g_s2, "max_rate_change_g_s2", positive=True, allow_inf=True)
        if self.weights is not None and not isinstance(self.weights, MPCWeights):
            raise ValueError(f"weights must be an MPCWeights or None, got {type(self.weights).__name__}")
        if self.weights is not None:
            self.weights.__post_init__()   # a frozen dataclass can still be changed by object.__setattr__
        if self.fallback is not None and not callable(getattr(self.fallback, "predict", None)):
            raise ValueError(f"fallback must be a policy with predict(observation, ...) or None, got "
                             f"{type(self.fallback).__name__}")
        if not isinstance(self.preview, (bool, np.bool_)):
            raise ValueError(f"preview must be True or False, got {self.preview!r}")  # noqa: TRY004  (the rule)
        if self.slip_budget_ppm is not None:
            _check_number(self.slip_budget_ppm, "slip_budget_ppm", positive=True, allow_inf=False)
            _check_number(self.slip_budget_gain, "slip_budget_gain", positive=False, allow_inf=False)
            if (self.weights or MPCWeights()).nh3_ppm_s <= 0:
                raise ValueError("slip_budget_ppm prices slip per ppm s: it needs weights.nh3_ppm_s > 0")

    # ------------------------------------------------------------------------------------------- protocol hooks
    def attach(self, env: Any) -> None:
        """Read dt, the injector limit and the observation size; keep the env for the cycle preview if ``preview``;
        attach the model and the estimator."""
        n_obs = observation_size(env)
        if self.slip_guard is not None and self.slip_guard[0] >= n_obs:
            raise ValueError(f"slip_guard reads observation index {self.slip_guard[0]}, but the environment's "
                             f"observation has {n_obs} entries (an NH3 sensor needs nh3_sensor=True)")
        if float(env.dt) != self.dt or float(env.max_rate_g_s) != self.max_rate_g_s:
            self._solver = None
        self.dt = float(env.dt)
        self.max_rate_g_s = float(env.max_rate_g_s)
        self._env = env if self.preview else None
        if self.slip_budget_ppm is not None and not callable(getattr(env, "episode_kpis", None)):
            raise ValueError("slip_budget_ppm needs an environment with episode_kpis() (the mean slip so far)")
        self._budget_env = env if self.slip_budget_ppm is not None else None
        self.model.attach(env)
        self.estimator.attach(env)
        self.observation_size_ = n_obs

    def stats(self) -> dict[str, float]:
        """Solver statistics of the episode: failures (in total and by kind, ``solver_failures_<kind>`` for every
        kind of :data:`FAILURE_KINDS`), solves, suboptimal plans applied, solve time median / p95 / max [ms],
        iterations, the failed-solve steps the ``slip_guard`` set to zero dosing, and the steps whose fallback
        raised or gave a non-finite action (``fallback_errors``: the safe action, no dosing, was applied).

        ``solve_time_ms_*`` is the CPU time of the solving thread (what the solve costs, independent of other
        processes sharing the cores); ``solve_wall_ms_*`` the wall-clock time (includes waiting for a core)."""
        t = np.asarray(self._solve_ms) if self._solve_ms else np.array([math.nan])
        tw = np.asarray(self._solve_wall_ms) if self._solve_wall_ms else np.array([math.nan])
        it = np.asarray(self._iters) if self._iters else np.array([math.nan])
        out = {"solver_failures": float(self._failures), "solves": float(len(self._solve_ms)),
               "solver_suboptimal": float(self._suboptimal), "slip_guarded_steps": float(self._guarded),
               "fallback_errors": float(self._fallback_errors), "solver_rescued": float(self._rescued),
               "solver_rescue_held": float(self._held),
               "solve_time_ms_median": float(np.median(t)), "solve_time_ms_p95": float(np.percentile(t, 95)),
               "solve_time_ms_max": float(np.max(t)), "solve_wall_ms_median": float(np.median(tw)),
               "solve_wall_ms_p95": float(np.percentile(tw, 95)), "solver_iterations_mean": float(np.mean(it))}
        out.update({f"solver_failures_{k}": float(self._kinds.get(k, 0)) for k in FAILURE_KINDS})
        if self.slip_budget_ppm is not None:
            pf = np.asarray(self._price_factors) if self._price_factors else np.array([math.nan])
            out.update({"slip_price_factor_mean": float(np.mean(pf)), "slip_price_factor_max": float(np.max(pf))})
        return out

    def _reset_episode(self) -> None:
        self._failures = 0
        self._suboptimal = 0
        self._guarded = 0
        self._fallback_errors = 0
        self._rescued = 0
        self._held = 0
        self._hold = 0
        self._kinds: dict[str, int] = {}
        self._plan_age = 0
        self._step = 0
        self._solve_ms: list[float] = []
        self._solve_wall_ms: list[float] = []
        self._iters: list[int] = []
        self._w0: np.ndarray | None = None
        self._lam_g0: np.ndarray | None = None
        self._price_factors: list[float] = []
        self._u_prev = 0.0
        self._failure: tuple[str, str] | None = None
        self.last_plan_: dict[str, np.ndarray] | None = None
        self.status_counts_: dict[str, int] = {}
        #: the failed solves of the episode: (step, kind, solver status or exception)
        self.failures_: list[tuple[int, str, str]] = []
        #: the solves the rescue solver saved: (step, the first solver's failure kind, its status)
        self.rescues_: list[tuple[int, str, str]] = []

    # ------------------------------------------------------------------------------------------------- the NLP
    def stage_intervals(self) -> tuple[int, ...]:
        """The control intervals of each stage: the multi-rate ``stages`` (attribute ``stage_layout``), or
        ``horizon`` times ``stage_steps``."""
        if self.stage_layout is not None:
            return tuple(self.stage_layout)
        return (int(self.stage_steps),) * int(self.horizon)

    def _stage_lengths(self) -> float | np.ndarray:
        """The stage lengths [s] given to the model's ``stage_parameters``: one float when the stages are uniform
        (as before multi-rate stages existed), else an (H,) array."""
        ks = self.stage_intervals()
        if len(set(ks)) == 1:
            return ks[0] * self.dt
        return np.asarray(ks, dtype=np.float64) * self.dt

    def _build(self) -> None:
        self._check_settings()
        m, H = self.model, int(self.horizon)
        w = self.weights or MPCWeights()
        ks = self.stage_intervals()
        nx = m.nx
        X = ca.SX.sym("X", nx, H)  # states at the ends of the stages
        U = ca.SX.sym("U", H)
        S = ca.SX.sym("S", H)
        x0 = ca.SX.sym("x0", nx)
        D = ca.SX.sym("D", N_DISTURBANCE, H)
        Pst = ca.SX.sym("P", max(m.n_stage_params, 1), H)
        Pt = ca.SX.sym("Pt", max(m.n_terminal_params, 1))
        u_prev = ca.SX.sym("u_prev")
        price = ca.SX.sym("price") if self.slip_budget_ppm is not None else w.nh3_ppm_s
        g, lbg, ubg = [], [], []
        cost = 0
        x = x0
        du_first = self.max_rate_change_g_s2 * self.dt
        for i in range(H):
            h = ks[i] * self.dt
            du_max = self.max_rate_change_g_s2 * h
            xn = X[:, i]
            d, p = D[:, i], Pst[:, i]
            g.append(m.residual(xn, x, U[i], d, p, h))
            lbg += [0.0] * nx
            ubg += [0.0] * nx
            y = m.outputs(xn, x, U[i], d, p)
            g.append(y[1] - S[i])
            lbg.append(-ca.inf)
            ubg.append(self.slip_limit_ppm)
            du = U[i] - (u_prev if i == 0 else U[i - 1])
            g.append(du)
            lim = du_first if i == 0 else du_max
            lbg.append(-lim)
            ubg.append(lim)
            flow = d[0]
            cost += h * flow * 1e-6 * (w.nox * NO2_MOLAR_MASS_G_MOL * y[0] + w.nh3 * NH3_MOLAR_MASS_G_MOL * y[1])
            if w.nh3_ppm_s > 0:
                cost += price * h * y[1]
            # the slack is per stage of the first stage's length: a longer stage weighs it by its length
            slack_w = w.slack if ks[i] == ks[0] else w.slack * (ks[i] / ks[0])
            cost += w.adblue * h * U[i] + w.rate_change * du ** 2 + slack_w * (S[i] + S[i] ** 2)
            x = xn
        cost += m.terminal_cost(x, Pt)
        xlb, xub = m.state_bounds()
        self._lbw = np.concatenate([np.tile(xlb, H), np.zeros(H), np.zeros(H)])
        self._ubw = np.concatenate([np.tile(xub, H), np.full(H, self.max_rate_g_s), np.full(H, np.inf)])
        self._lbg, self._ubg = np.array(lbg), np.array(ubg)
        wv = ca.vertcat(ca.vec(X), U, S)
        pv = ca.vertcat(x0, ca.vec(D), ca.vec(Pst), Pt, u_prev)
        if self.slip_budget_ppm is not None:
            pv = ca.vertcat(pv, price)
        self._nlp = {"x": wv, "f": cost, "g": ca.vertcat(*g), "p": pv}
        self._solver = self._nlpsol("mpc", self.solver, self.solver_options)
        self._rescue = None if self.rescue_solver is None else self._nlpsol("mpc_rescue", self.rescue_solver,
                                                                            self.rescue_options)
        self._H, self._nx = H, nx

    def _nlpsol(self, name: str, solver: str, options: dict | None) -> ca.Function:
        """The NLP's ``nlpsol`` with ``solver``'s quiet defaults updated by ``options``."""
        return ca.nlpsol(name, solver, self._nlp, {**solver_defaults(solver), **(options or {})})

    # ------------------------------------------------------------------------------------------------- acting
    def _disturbances(self, observation: np.ndarray) -> np.ndarray:
        """(H, 4) stage disturbances: block means of the preview over each stage, or the measurement held."""
        H, k = int(self.horizon), self.stage_steps
        if self._env is not None:
            ks = self.stage_intervals()
            if len(set(ks)) == 1:
                prev = self._env.disturbance_preview(H * k)
                return prev.reshape(H, k, N_DISTURBANCE).mean(axis=1)
            prev = self._env.disturbance_preview(int(sum(ks)))
            edges = np.concatenate([[0], np.cumsum(ks)])
            return np.array([prev[edges[i]:edges[i + 1]].mean(axis=0) for i in range(H)])
        no2f = 0.4  # the NO2 share is not measured: a typical value downstream of the DOC [chosen]
        return np.tile([observation[2], observation[1], observation[0], no2f], (H, 1))

    def _fallback_rate(self, observation: np.ndarray) -> float:
        """The fallback policy's dose [g/s]; the safe action (0, no dosing) if it raises or gives a non-finite
        action (counted as ``fallback_errors``, logged)."""
        fb = self.fallback
        if fb is None:
            if self._default_fallback is None or self._default_fallback.max_rate_g_s != self.max_rate_g_s:
                self._default_fallback = LookupTableDosing(max_rate_g_s=self.max_rate_g_s)
            fb = self._default_fallback
        try:
            a, _ = fb.predict(observation, deterministic=True)
            a = np.asarray(a, dtype=np.float64)
            rate = action_to_rate(a, self.max_rate_g_s)
        except Exception as exc:  # noqa: BLE001  (a broken user fallback must not end the episode: safe action)
            return self._fallback_error(f"raised {type(exc).__name__}: {exc}")
        if not (np.all(np.isfinite(a)) and math.isfinite(rate)):
            return self._fallback_error(f"returned a non-finite action {a.tolist()!r}")
        return rate

    def _fallback_error(self, what: str) -> float:
        self._fallback_errors += 1
        log = logger.warning if self._fallback_errors == 1 else logger.debug
        log("NonlinearMPC step %d: the fallback policy %s; the safe action (no dosing) is applied instead",
            self._step, what)
        return 0.0

    def predict(self, observation: np.ndarray, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        """The policy protocol (:mod:`control.protocol`): one plant, ``observation`` of shape ``(n,)`` (action
        ``(1,)``) or ``(1, n)`` (action ``(1, 1)``); ``n`` the environment's observation size after :meth:`attach`
        (before it, at least the entries the controller reads). A bad observation raises before any state changes;
        a failed solve falls back (module docstring)."""
        batch, single = check_observation(observation, self.observation_size_, min_size=self._min_observation_size(),
                                          owner=type(self).__name__)
        obs = batch[0]
        if is_episode_start(episode_start):
            self._reset_episode()
            self.model.reset(obs)
            self.estimator.reset(obs)
        if self._solver is None:
            self._build()
        t0, c0 = time.perf_counter(), time.thread_time()
        rate = None
        self._failure = None
        try:
            rate = self._solve(obs)
        except SOLVE_ERRORS as exc:  # a numerical failure of the solve falls back, counted (see SOLVE_ERRORS)
            rate = None
            kind = "error" if self._failure is None else self._failure[0]
            self._failure = (kind, f"{type(exc).__name__}: {exc}")
        self._solve_ms.append((time.thread_time() - c0) * 1e3)
        self._solve_wall_ms.append((time.perf_counter() - t0) * 1e3)
        if rate is None:
            self._failures += 1
            kind, status = self._failure or ("other", "unknown")
            self._kinds[kind] = self._kinds.get(kind, 0) + 1
            self.failures_.append((self._step, kind, status))
            logger.debug("NonlinearMPC step %d: failed solve (%s: %s)", self._step, kind, status)
            self._plan_age += 1
            plan = self.last_plan_
            i = int(np.searchsorted(np.cumsum(self.stage_intervals()), self._plan_age, side="right"))
            if self.slip_guard is not None and float(obs[self.slip_guard[0]]) > self.slip_guard[1]:
                rate = 0.0   # the catalyst slips: a failed solve doses nothing (see slip_guard)
                self._guarded += 1
            else:  # the last good plan while it lasts, then the fallback policy (the look-up table by default)
                rate = float(plan["u"][i]) if plan is not None and i < len(plan["u"]) else self._fallback_rate(obs)
            self._w0 = None
            self._lam_g0 = None
            lim = self.max_rate_change_g_s2 * self.dt
            rate = min(max(rate, self._u_prev - lim), self._u_prev + lim)
        rate = min(max(rate, 0.0), self.max_rate_g_s)
        self._u_prev = rate
        self._step += 1
        action = rate_to_action(rate, self.max_rate_g_s)
        return (action if single else action[None, :]), state

    def _min_observation_size(self) -> int:
        """Entries an observation needs before :meth:`attach` tells the exact size: the default observation, and
        the entries the slip guard and the estimator read (``measured_obs``)."""
        n = N_BASE_OBSERVATION
        if self.slip_guard is not None:
            n = max(n, self.slip_guard[0] + 1)
        measured = getattr(self.estimator, "measured_obs", None)
        if measured:
            n = max(n, max(int(j) for j in measured) + 1)
        return n

    def _solve(self, obs: np.ndarray) -> float | None:
        H, nx = self._H, self._nx
        h = self._stage_lengths()
        dist = self._disturbances(obs)
        try:
            x0 = self.estimator.make_step(obs, self._u_prev, dist[0])
        except SOLVE_ERRORS:
            self._failure = ("estimator", "the state estimator failed")
            raise
        pst, pt = self.model.stage_parameters(obs, dist, h, self.dt)
        pst = np.zeros((H, 1)) if pst.size == 0 else pst
        pt = np.zeros(1) if pt.size == 0 else pt
        pv = np.concatenate([x0, dist.ravel(), pst.ravel(), pt, [self._u_prev]])
        if self.slip_budget_ppm is not None:
            pv = np.append(pv, (self.weights or MPCWeights()).nh3_ppm_s * self._slip_price_factor())
        if not np.all(np.isfinite(pv)):
            self._failure = ("nonfinite_model", "non-finite initial state or stage parameters")
            return None
        if self._w0 is None:
            w0 = np.concatenate([np.tile(x0, H), np.full(H, self._u_prev), np.zeros(H)])
        else:
            w0 = self._w0
        w0 = np.clip(w0, self._lbw, self._ubw)
        args = {"x0": w0, "p": pv, "lbx": self._lbw, "ubx": self._ubw, "lbg": self._lbg, "ubg": self._ubg}
        if self._lam_g0 is not None and self.warm_start_duals:
            args["lam_g0"] = self._lam_g0
        bounds = {k: args[k] for k in ("p", "lbx", "ubx", "lbg", "ubg")}
        sol = None
        if self._rescue is not None and self._hold > 0:   # a hard stretch: the rescue solver first, warm-started
            self._hold -= 1
            sol, _ = self._attempt(self._rescue, {**bounds, "x0": w0}, "rescue:")
            self._held += sol is not None
        if sol is None:
            sol, failure = self._attempt(self._solver, args, "")
        if sol is None and self._rescue is not None:
            cold = np.clip(np.concatenate([np.tile(x0, H), np.full(H, self._u_prev), np.zeros(H)]), self._lbw,
                           self._ubw)
            sol, second = self._attempt(self._rescue, {**bounds, "x0": cold}, "rescue:")
            if sol is not None:
                self._rescued += 1
                self._hold = self.rescue_hold_steps
                self.rescues_.append((self._step, *failure))
            else:
                failure = (second[0], f"{failure[1]}; rescue: {second[1]}")
        if sol is None:
            self._failure = failure
            return None
        wopt = np.asarray(sol["x"]).ravel()
        X = wopt[:nx * H].reshape(H, nx)
        U = wopt[nx * H:nx * H + H]
        S = wopt[nx * H + H:]
        self.last_plan_ = {"x": X, "u": U, "slack": S}
        self._plan_age = 0
        # warm start: shift by one stage only every stage_steps intervals would be exact; a plain reuse is close
        self._w0 = wopt
        self._lam_g0 = np.asarray(sol["lam_g"]).ravel()
        return float(U[0])

    def _slip_price_factor(self) -> float:
        """The slip price's factor this step (module docstring: the one-sided dual update on the mean slip so far,
        ``BUDGET_PRIOR_S`` seconds of it at the budget); kept for :meth:`stats`."""
        b = float(self.slip_budget_ppm)
        env = self._budget_env
        t = float(env.step_index) * self.dt if env is not None else 0.0
        m = float(env.episode_kpis()["mean_nh3_slip_ppm"]) if env is not None and t > 0 else b
        m_prior = (m * t + b * BUDGET_PRIOR_S) / (t + BUDGET_PRIOR_S)
        factor = math.exp(min(self.slip_budget_gain * max(m_prior - b, 0.0) / b, MAX_PRICE_EXPONENT))
        self._price_factors.append(factor)
        return factor

    def _attempt(self, solver: ca.Function, args: dict[str, Any],
                 tag: str) -> tuple[dict[str, Any] | None, tuple[str, str]]:
        """One solve: ``(solution, ("", ""))``, or ``(None, (failure kind, status))`` for a failed one (an unusable
        status, a non-finite result, CasADi's RuntimeError). Counts iterations, statuses (``tag`` + status) and
        suboptimal plans."""
        try:
            sol = solver(**args)
            st = solver.stats()
        except RuntimeError as exc:
            return None, ("error", f"RuntimeError: {exc}")
        self._iters.append(int(st.get("iter_count", 0)))
        status = str(st.get("return_status", ""))
        key = tag + status
        self.status_counts_[key] = self.status_counts_.get(key, 0) + 1
        wopt = np.asarray(sol["x"]).ravel()
        g = np.asarray(sol["g"]).ravel()
        if not (np.all(np.isfinite(wopt)) and np.all(np.isfinite(g))):
            return None, ("nonfinite_model", status or "non-finite solution")
        if not st.get("success", False):
            # an iterate that satisfies the model and the constraints is a valid (suboptimal) plan: use it, count it
            viol = max(float(np.max(self._lbg - g)), float(np.max(g - self._ubg)), 0.0)
            if status not in _USABLE_STATUSES or viol > 1e-6:
                return None, (failure_kind(status, str(st.get("unified_return_status", ""))),
                              f"{status} (constraint violation {viol:.3g})")
            self._suboptimal += 1
        return sol, ("", "")
