"""Adaptive NMPC for an ageing catalyst: the grey-box NMPC whose model drift is estimated online by RPEM.

The identified grey-box model (:class:`ident.greybox.StorageGreyBox`, fitted once on the fresh catalyst) gets two
drift parameters d = (d_cap, d_act), log retentions relative to the identified model: storage capacity
Omega exp(d_cap) (``p[0] + d_cap``) and activity exp(d_act) on both the SCR and the NH3-oxidation pre-exponentials
(``p[5] + d_act``, ``p[7] + d_act``, as ageing scales both in the simulator) -- :func:`drift_step`.

:class:`AdaptiveMPC` is the fixed NMPC's twin (:func:`control.factory.identified_mpc` with explicit stages, NOx
sensor only, no preview: same horizon, weights, solver and estimator settings) whose prediction model
(:class:`DriftModelAdapter`) takes d as NLP parameters. A :class:`ident.rpem.parametric.ParametricRPEM` estimates
d at every step from the inputs [upstream NOx ppm, urea g/min of the applied dose (obs[4]), inlet T, flow] and the
tailpipe NOx sensor only (model output ``a NOx + b NH3`` with the fitted sensor gains), the estimates clipped to a
retention box (ageing only removes capacity and activity; a clip rather than the recursion's reject-the-update
projection, which froze both estimates whenever one of them sat at a bound). Certainty equivalence at every step:
d enters the NLP as stage parameters (and the terminal value of the stored NH3 scales with exp(d_cap)), so the NLP
is built once; the EKF's model follows d every ``ekf_refresh`` steps (:meth:`ObservationEKF.set_step`, keeping its
estimate).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import casadi as ca
import numpy as np

from control.protocol import action_to_rate, check_observation, is_episode_start
from control.signals import urea_g_min

__all__ = ["DRIFT_NAMES", "AdaptiveMPC", "DriftModelAdapter", "drift_step"]

#: the drift parameters, in the order of d
DRIFT_NAMES = ("capacity", "activity")
#: grey-box parameters each drift shifts (log capacity; log SCR and oxidation pre-exponentials)
_DRIFT_PARAMS = {0: (0,), 1: (5, 7)}


def drift_step(model: Any, dt: float | None = None) -> ca.Function:
    """``Function('step_d', [x, u, d], [x_next, y])`` of a fitted grey-box ``model`` with the drift d = (d_cap,
    d_act) (module docstring), at its sample time or ``dt`` [s]; y = [NOx ppm, NH3 ppm, sensor ppm = a NOx + b NH3]
    with the model's sensor gains."""
    from ident.greybox import N_PARAMS, StorageGreyBox

    base = StorageGreyBox(n_cells=int(model.n_cells), dt=float(model.dt if dt is None else dt))
    n = int(model.n_cells)
    x, u, d = ca.SX.sym("x", n + 1), ca.SX.sym("u", 4), ca.SX.sym("d", len(DRIFT_NAMES))
    shift: list[Any] = [0] * N_PARAMS
    for k, cols in _DRIFT_PARAMS.items():
        for c in cols:
            shift[c] = d[k]
    p = ca.DM(np.asarray(model.params_, float)) + ca.vertcat(*shift)
    xn, y = base.step_expression(x, u, p)
    a, b = (float(v) for v in model.sensor_gains_)
    return ca.Function("step_d", [x, u, d], [xn, ca.vertcat(y, a * y[0] + b * y[1])], ["x", "u", "d"],
                       ["x_next", "y"])


class DriftModelAdapter:
    """The fixed NMPC's prediction model (an explicit-stage :class:`control.models.IdentifiedModelAdapter`) with the
    drift d as NLP parameters: stage parameters d, terminal parameter d_cap (the value of the stored NH3 scales
    with the capacity). A :class:`control.mpc.PredictionModel`; :meth:`set_drift` sets the d of the next solves.

    Parameters
    ----------
    base : the fixed NMPC's adapter (its signals, output indices, state bounds, model sample time, terminal cost).
    step : :func:`drift_step` of the model at its sample time.
    stage_step : :func:`drift_step` at the NLP's stage length, or None to chain ``step`` over a stage.
    """

    n_stage_params = len(DRIFT_NAMES)
    n_terminal_params = 1

    def __init__(self, base: Any, step: ca.Function, stage_step: ca.Function | None = None) -> None:
        self.base = base
        self.step = step
        self.stage_step = stage_step
        self.nx = base.nx
        self.drift_ = np.zeros(len(DRIFT_NAMES))

    def set_drift(self, d: Sequence[float]) -> None:
        """The drift (d_cap, d_act) of the next solves."""
        self.drift_ = np.asarray(d, float).copy()

    def _simulate(self, x: Any, u: Any, d: Any, h: float, p: Any) -> tuple[Any, Any]:
        un = self.base.stage_inputs(u, d)
        if self.stage_step is not None:
            return self.stage_step(x, un, p)
        y = None
        for _ in range(max(round(h / self.base.model_dt), 1)):
            x, y = self.step(x, un, p)
        return x, y

    def residual(self, x_next: Any, x: Any, u: Any, d: Any, p: Any, h: float) -> Any:
        self._h = h
        return x_next - self._simulate(x, u, d, h, p)[0]

    def outputs(self, x_next: Any, x: Any, u: Any, d: Any, p: Any) -> Any:
        return self.base.physical_outputs(self._simulate(x, u, d, self._h, p)[1])

    def terminal_cost(self, x: Any, p: Any) -> Any:
        fn = self.base.terminal_cost_fn
        return 0 if fn is None else fn(x) * ca.exp(p[0])

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.base.state_bounds()

    def attach(self, env: Any) -> None:
        self.base.attach(env)

    def reset(self, observation: np.ndarray) -> None:
        pass

    def make_estimator(self) -> Any:
        return self.base.make_estimator()

    def stage_parameters(self, observation: np.ndarray, disturbances: np.ndarray, h: float,
                         dt: float) -> tuple[np.ndarray, np.ndarray]:
        return np.tile(self.drift_, (disturbances.shape[0], 1)), self.drift_[:1].copy()


class AdaptiveMPC:
    """The fixed NMPC's twin whose model drift d is estimated online by RPEM (module docstring).

    A :class:`control.protocol.PolicyPredictor`; the estimate survives episode resets (the catalyst ages between
    cycles, the estimate carries over; the recursion's model state restarts with the empty catalyst at each reset,
    where the plant restarts too). ``history`` holds (episode index, time s, d_cap, d_act) every ``log_every``
    steps.

    Parameters
    ----------
    model : the fitted :class:`ident.greybox.StorageGreyBox` (fresh catalyst).
    quick : the fixed NMPC's shorter horizon.
    storage_value : terminal value of stored NH3 [g AdBlue per mol] (``identified_mpc``'s
        ``storage_value_g_per_mol``).
    forgetting : RPEM forgetting factor per step (0.998 at 0.5 s: a memory of about 250 s).
    box : retention box (lower, upper) the estimates are clipped to.
    free : the drift parameters estimated (the others stay at the fresh model).
    ekf_refresh : steps between updates of the estimator's model to the current d.
    R0, Lambda0 : the recursion's initial R and Lambda.
    log_every : steps between entries of ``history``.
    """

    def __init__(self, model: Any, quick: bool = False, storage_value: float = 200.0, forgetting: float = 0.998,
                 box: tuple[float, float] = (0.2, 1.05), free: Sequence[str] = DRIFT_NAMES, ekf_refresh: int = 20,
                 R0: float = 1e3, Lambda0: float = 100.0, log_every: int = 20) -> None:
        from control.factory import identified_mpc
        from control.mpc import NonlinearMPC
        from ident.rpem.parametric import ParametricRPEM

        unknown = [f for f in free if f not in DRIFT_NAMES]
        if unknown or not free:
            raise ValueError(f"free must name drift parameters among {DRIFT_NAMES}, got {list(free)!r}")
        if not (0.0 < box[0] <= 1.0 <= box[1]):
            raise ValueError(f"box must be (lower, upper) retentions with 0 < lower <= 1 <= upper, got {box!r}")
        self.model = model
        self.quick = quick
        self.storage_value = storage_value
        self.forgetting = forgetting
        self.box = box
        self.free = tuple(free)
        self.ekf_refresh = int(ekf_refresh)
        self.R0 = R0
        self.Lambda0 = Lambda0
        self.log_every = int(log_every)
        # explicit stages in both arms: the drift adapter re-parametrises the explicit stage model online, and the
        # comparison is fixed versus adapted model, not one NLP formulation against another
        fixed = identified_mpc(model, quick, storage_value_g_per_mol=storage_value, implicit=False,
                               nh3_sensor=False, preview=False)
        self._step = drift_step(model)
        stage_dt = float(model.dt) * fixed.stage_steps
        stage = drift_step(model, stage_dt) if fixed.model.stage_model is not None else None
        self.adapter = DriftModelAdapter(fixed.model, self._step, stage)
        self.estimator = fixed.estimator
        self.mpc = NonlinearMPC(self.adapter, horizon=fixed.horizon, stage_steps=fixed.stage_steps,
                                weights=fixed.weights, slip_limit_ppm=fixed.slip_limit_ppm,
                                max_rate_change_g_s2=fixed.max_rate_change_g_s2, preview=False,
                                fallback=fixed.fallback, solver=fixed.solver, solver_options=fixed.solver_options,
                                estimator=self.estimator)
        # the recursion's own box (reject an update leaving it) only guards against divergence; the model set is
        # the retention box ``box``, imposed by clipping (a projection that lets the other parameter move on)
        idx = [DRIFT_NAMES.index(f) for f in self.free]
        self.rpem = ParametricRPEM(self._step, p0=np.zeros(len(DRIFT_NAMES)), free=idx, output_indices=[2],
                                   forgetting=forgetting, p_bounds=(np.full(len(idx), np.log(0.02)),
                                                                    np.full(len(idx), np.log(10.0))),
                                   R0=R0, Lambda0=Lambda0)
        self._lo, self._hi = np.log(box[0]), np.log(box[1])
        self.n_cells = int(model.n_cells)
        self.history: list[tuple[float, float, float, float]] = []
        self.episode = -1
        self._k = 0
        self._calls = 0
        self._estimator_drift = np.zeros(len(DRIFT_NAMES))
        self._env: Any = None

    @property
    def drift_(self) -> np.ndarray:
        """The current drift estimate (d_cap, d_act) (zeros before the first step)."""
        return self.rpem.params_.copy() if hasattr(self.rpem, "params_") else np.zeros(len(DRIFT_NAMES))

    def attach(self, env: Any) -> None:
        self._env = env
        self.mpc.attach(env)

    def _refresh_estimator(self, d: np.ndarray) -> None:
        """The estimator's model at the drift ``d`` (its estimate and covariance carry over)."""
        if np.array_equal(d, self._estimator_drift):
            return
        x, u = ca.SX.sym("x", self.adapter.nx), ca.SX.sym("u", 4)
        xn, y = self._step(x, u, ca.DM(d))
        self.estimator.set_step(ca.Function("step", [x, u], [xn, y]))
        self._estimator_drift = d.copy()

    def predict(self, observation: np.ndarray, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        batch, _ = check_observation(observation, self.mpc.observation_size_, owner=type(self).__name__)
        obs = batch[0]
        x0 = np.r_[np.zeros(self.n_cells), obs[1]]
        if is_episode_start(episode_start):
            self.episode += 1
            self._k = 0
            if not hasattr(self.rpem, "params_"):
                self.rpem.start(x0)
            else:  # the plant restarts hot and empty: so does the model; estimate, R, Lambda, gain carry over
                self.rpem.reset_state(x0)
        else:
            max_rate = float(getattr(self._env, "max_rate_g_s", self.mpc.max_rate_g_s))
            dose = action_to_rate(obs[4], max_rate)  # the applied (clipped) dose of the last interval
            self.rpem.update(np.array([obs[0], urea_g_min(dose), obs[1], obs[2]]), [obs[3]])
            self.rpem.clip_params(self._lo, self._hi)
        d = self.rpem.params_.copy()
        self.adapter.set_drift(d)
        if self._calls % max(self.ekf_refresh, 1) == 0:
            self._refresh_estimator(self.adapter.drift_)
        self._calls += 1
        if self._k % self.log_every == 0:
            self.history.append((float(self.episode), self._k * self.mpc.dt, float(d[0]), float(d[1])))
        self._k += 1
        return self.mpc.predict(observation, state, episode_start, deterministic)

    def stats(self) -> dict[str, float]:
        s = dict(self.mpc.stats())
        s["rpem_rejected"] = float(self.rpem.n_rejected_)
        s["rpem_updates"] = float(self.rpem.n_updates_)
        return s
