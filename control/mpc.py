"""Nonlinear MPC of AdBlue dosing with CasADi: one NLP, built once, for any prediction model.

The optimal control problem over ``horizon`` stages of ``stage_steps`` control intervals each (stage length
``h = stage_steps * dt``; the first input is applied for one interval, then the problem is solved again):

    min   sum_i [ h F_i (w_nox M_NO2 y_nox,i + w_nh3 M_NH3 y_nh3,i) 1e-6 + w_adblue h u_i + w_du (u_i - u_i-1)^2
                  + w_slack (s_i + s_i^2) ] + V(x_H)
    s.t.  r(x_i+1, x_i, u_i, d_i, p_i) = 0                 (the model, multiple shooting / implicit collocation)
          0 <= u_i <= u_max,  |u_i - u_i-1| <= du_max h     (injector range, rate limit; u_-1 the applied dose)
          y_nh3,i <= slip_limit_ppm + s_i,  s_i >= 0        (soft NH3-slip constraint)

with u the AdBlue rate [g/s], F the exhaust flow [mol/s], y the predicted tailpipe NOx and NH3 [ppm], d the
engine-out disturbance (flow, inlet temperature, NOx, NO2 fraction) and p model-specific stage parameters. The
default weights are the environment's economic reward (20 per g NOx, 60 per g NH3, 1 per g AdBlue). The
disturbance is held at its measured value over the horizon unless ``preview=True`` (then the cycle preview from
``env.disturbance_preview``, privileged information, given through :meth:`NonlinearMPC.attach`).

Model sources (:class:`PredictionModel`, in :mod:`control.models`): the first-principles catalyst (the oracle) and
any identified model's CasADi export. The state every solve starts from comes from a state estimator of its own
(:class:`control.estimation.StateEstimator`, do-mpc's split): at each step the controller calls
``x0 = estimator.make_step(observation, applied dose, disturbance)`` and then solves from ``x0`` -- the oracle's
:class:`~control.estimation.PrivilegedState`, an identified model's :class:`~control.estimation.ObservationEKF`
(``model.make_estimator()`` unless one is given). The NLP is an SX ``nlpsol`` (IPOPT by default), warm-started
from the previous solution.

A failed solve (solver status not successful, a non-finite result, or one of the numerical exceptions of
:data:`SOLVE_ERRORS`) never raises mid-episode: the controller applies the last good plan while it lasts, then the
fallback dose (the look-up table by default), counts the failure (``solver_failures``) and reports it in
:meth:`NonlinearMPC.stats`, with the solve times. An iterate at the iteration limit that satisfies every constraint
(model equations included, to 1e-6) is a valid but suboptimal plan: it is applied and counted as
``solver_suboptimal``, not as a failure.

What is *not* a failed solve, and raises: a bad observation (checked before anything else by
:func:`control.protocol.check_observation`: None, NaN/inf, wrong size, a batch of several plants -- nothing of the
controller's state is touched), and any other exception of the solve (``ValueError``, ``TypeError``,
``IndexError``, ``AttributeError``, ... from the model or its configuration). Those are errors of the caller or of
the code, the same at every step; counting them as solver failures would make a broken controller look like a
weak one that falls back to the look-up table.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
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


@dataclass(frozen=True)
class MPCWeights:
    """Objective weights in grams of AdBlue equivalent (the first three are the environment's reward weights)."""

    nox: float = 20.0  # per g tailpipe NOx (as NO2)
    nh3: float = 60.0  # per g NH3 slip
    adblue: float = 1.0  # per g AdBlue
    rate_change: float = 0.05  # per (g/s)^2 of dose change between stages
    slack: float = 50.0  # per ppm of slip above the limit (plus its square), per stage


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
        from the observation and the (H, 4) stage disturbances; stages of ``h`` seconds, control interval ``dt``."""

    def make_estimator(self) -> StateEstimator:
        """The model's default state estimator (used when the controller is given none)."""


class NonlinearMPC:
    """Economic NMPC with a soft NH3-slip constraint (module docstring). Satisfies the policy protocol.

    Parameters
    ----------
    model : a :class:`PredictionModel` (:class:`control.models.FirstPrinciplesModel` or
        :class:`control.models.IdentifiedModelAdapter`).
    horizon : number of stages.
    stage_steps : control intervals per stage.
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
    """

    def __init__(self, model: PredictionModel, horizon: int = 20, stage_steps: int = 4,
                 weights: MPCWeights | None = None, slip_limit_ppm: float = EURO_VI_NH3_SLIP_LIMIT_PPM,
                 max_rate_change_g_s2: float = 1.0, preview: bool = False, fallback: Any = None,
                 solver: str = "ipopt", solver_options: dict | None = None,
                 warm_start_duals: bool | None = None, slip_guard: tuple[int, float] | None = None,
                 estimator: StateEstimator | None = None) -> None:
        self.model = model
        self.estimator = model.make_estimator() if estimator is None else estimator
        self.horizon = horizon
        self.stage_steps = stage_steps
        self.weights = weights
        self.slip_limit_ppm = slip_limit_ppm
        self.max_rate_change_g_s2 = max_rate_change_g_s2
        self.preview = preview
        self.fallback = fallback
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
        self.dt = 0.5
        self.max_rate_g_s = DEFAULT_MAX_RATE_G_S
        self.observation_size_: int | None = None
        self._env = None
        self._solver = None
        self._reset_episode()

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
        self.model.attach(env)
        self.estimator.attach(env)
        self.observation_size_ = n_obs

    def stats(self) -> dict[str, float]:
        """Solver statistics of the episode: failures, solves, solve time median / p95 / max [ms], iterations, and
        the failed-solve steps the ``slip_guard`` set to zero dosing.

        ``solve_time_ms_*`` is the CPU time of the solving thread (what the solve costs, independent of other
        processes sharing the cores); ``solve_wall_ms_*`` the wall-clock time (includes waiting for a core)."""
        t = np.asarray(self._solve_ms) if self._solve_ms else np.array([math.nan])
        tw = np.asarray(self._solve_wall_ms) if self._solve_wall_ms else np.array([math.nan])
        it = np.asarray(self._iters) if self._iters else np.array([math.nan])
        return {"solver_failures": float(self._failures), "solves": float(len(self._solve_ms)),
                "solver_suboptimal": float(self._suboptimal), "slip_guarded_steps": float(self._guarded),
                "solve_time_ms_median": float(np.median(t)), "solve_time_ms_p95": float(np.percentile(t, 95)),
                "solve_time_ms_max": float(np.max(t)), "solve_wall_ms_median": float(np.median(tw)),
                "solve_wall_ms_p95": float(np.percentile(tw, 95)), "solver_iterations_mean": float(np.mean(it))}

    def _reset_episode(self) -> None:
        self._failures = 0
        self._suboptimal = 0
        self._guarded = 0
        self._plan_age = 0
        self._solve_ms: list[float] = []
        self._solve_wall_ms: list[float] = []
        self._iters: list[int] = []
        self._w0: np.ndarray | None = None
        self._lam_g0: np.ndarray | None = None
        self._u_prev = 0.0
        self.last_plan_: dict[str, np.ndarray] | None = None
        self.status_counts_: dict[str, int] = {}

    # ------------------------------------------------------------------------------------------------- the NLP
    def _build(self) -> None:
        m, H = self.model, int(self.horizon)
        w = self.weights or MPCWeights()
        h = self.stage_steps * self.dt
        nx = m.nx
        X = ca.SX.sym("X", nx, H)  # states at the ends of the stages
        U = ca.SX.sym("U", H)
        S = ca.SX.sym("S", H)
        x0 = ca.SX.sym("x0", nx)
        D = ca.SX.sym("D", N_DISTURBANCE, H)
        Pst = ca.SX.sym("P", max(m.n_stage_params, 1), H)
        Pt = ca.SX.sym("Pt", max(m.n_terminal_params, 1))
        u_prev = ca.SX.sym("u_prev")
        g, lbg, ubg = [], [], []
        cost = 0
        x = x0
        du_first = self.max_rate_change_g_s2 * self.dt
        du_max = self.max_rate_change_g_s2 * h
        for i in range(H):
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
            cost += w.adblue * h * U[i] + w.rate_change * du ** 2 + w.slack * (S[i] + S[i] ** 2)
            x = xn
        cost += m.terminal_cost(x, Pt)
        xlb, xub = m.state_bounds()
        self._lbw = np.concatenate([np.tile(xlb, H), np.zeros(H), np.zeros(H)])
        self._ubw = np.concatenate([np.tile(xub, H), np.full(H, self.max_rate_g_s), np.full(H, np.inf)])
        self._lbg, self._ubg = np.array(lbg), np.array(ubg)
        wv = ca.vertcat(ca.vec(X), U, S)
        pv = ca.vertcat(x0, ca.vec(D), ca.vec(Pst), Pt, u_prev)
        opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.max_iter": 60, "ipopt.tol": 1e-6,
                "ipopt.acceptable_tol": 1e-3, "ipopt.acceptable_iter": 3, "ipopt.warm_start_init_point": "yes",
                "ipopt.sb": "yes", "ipopt.mu_init": 1e-3} if self.solver == "ipopt" else {"print_time": False}
        opts.update(self.solver_options or {})
        self._solver = ca.nlpsol("mpc", self.solver, {"x": wv, "f": cost, "g": ca.vertcat(*g), "p": pv}, opts)
        self._H, self._nx = H, nx

    # ------------------------------------------------------------------------------------------------- acting
    def _disturbances(self, observation: np.ndarray) -> np.ndarray:
        """(H, 4) stage disturbances: block means of the preview, or the measurement held."""
        H, k = int(self.horizon), self.stage_steps
        if self._env is not None:
            prev = self._env.disturbance_preview(H * k)
            return prev.reshape(H, k, N_DISTURBANCE).mean(axis=1)
        no2f = 0.4  # the NO2 share is not measured: a typical value downstream of the DOC [chosen]
        return np.tile([observation[2], observation[1], observation[0], no2f], (H, 1))

    def _fallback_rate(self, observation: np.ndarray) -> float:
        fb = self.fallback or LookupTableDosing(max_rate_g_s=self.max_rate_g_s)
        a, _ = fb.predict(observation, deterministic=True)
        return action_to_rate(a, self.max_rate_g_s)

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
        try:
            rate = self._solve(obs)
        except SOLVE_ERRORS:  # a numerical failure of the solve falls back, counted (see SOLVE_ERRORS)
            rate = None
        self._solve_ms.append((time.thread_time() - c0) * 1e3)
        self._solve_wall_ms.append((time.perf_counter() - t0) * 1e3)
        if rate is None:
            self._failures += 1
            self._plan_age += 1
            plan = self.last_plan_
            i = self._plan_age // self.stage_steps
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
        h = self.stage_steps * self.dt
        dist = self._disturbances(obs)
        x0 = self.estimator.make_step(obs, self._u_prev, dist[0])
        pst, pt = self.model.stage_parameters(obs, dist, h, self.dt)
        pst = np.zeros((H, 1)) if pst.size == 0 else pst
        pt = np.zeros(1) if pt.size == 0 else pt
        pv = np.concatenate([x0, dist.ravel(), pst.ravel(), pt, [self._u_prev]])
        if self._w0 is None:
            w0 = np.concatenate([np.tile(x0, H), np.full(H, self._u_prev), np.zeros(H)])
        else:
            w0 = self._w0
        w0 = np.clip(w0, self._lbw, self._ubw)
        args = {"x0": w0, "p": pv, "lbx": self._lbw, "ubx": self._ubw, "lbg": self._lbg, "ubg": self._ubg}
        if self._lam_g0 is not None and self.warm_start_duals:
            args["lam_g0"] = self._lam_g0
        sol = self._solver(**args)
        st = self._solver.stats()
        self._iters.append(int(st.get("iter_count", 0)))
        status = str(st.get("return_status", ""))
        self.status_counts_[status] = self.status_counts_.get(status, 0) + 1
        wopt = np.asarray(sol["x"]).ravel()
        if not np.all(np.isfinite(wopt)):
            return None
        if not st.get("success", False):
            # an iterate that satisfies the model and the constraints is a valid (suboptimal) plan: use it, count it
            g = np.asarray(sol["g"]).ravel()
            viol = max(float(np.max(self._lbg - g)), float(np.max(g - self._ubg)), 0.0)
            if status not in ("Maximum_Iterations_Exceeded", "Maximum_CpuTime_Exceeded",
                              "Search_Direction_Becomes_Too_Small") or viol > 1e-6:
                return None
            self._suboptimal += 1
        X = wopt[:nx * H].reshape(H, nx)
        U = wopt[nx * H:nx * H + H]
        S = wopt[nx * H + H:]
        self.last_plan_ = {"x": X, "u": U, "slack": S}
        self._plan_age = 0
        # warm start: shift by one stage only every stage_steps intervals would be exact; a plain reuse is close
        self._w0 = wopt
        self._lam_g0 = np.asarray(sol["lam_g"]).ravel()
        return float(U[0])
