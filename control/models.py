"""Prediction models for :class:`control.mpc.NonlinearMPC`: the first-principles catalyst (oracle) and an adapter
for any identified model of :mod:`ident`.

:class:`FirstPrinciplesModel`
    The catalyst of :mod:`scr_env` with the packed parameters of the episode (``env.catalyst_params_array``) and
    its privileged state (``env.state``: cell coverages and solid temperatures), both read through ``attach(env)``.
    The chemistry is the one-source :func:`scr_env.physics.cell.cell_balance` (CasADi backend); the discretisation
    is the plant's own -- implicit Euler of the coverage, cells in flow order -- written as collocation equality
    constraints of the NLP instead of an inner Newton solve, so the NLP stays one SX problem (at a solution the
    stages equal :func:`scr_env.casadi_model.catalyst_step`, ``tests/control/test_models.py``). The solid
    temperatures do not depend on the dosing: they are propagated numerically (the kernel's closed-form implicit
    Euler) over the horizon and the rate constants enter the NLP as stage parameters.

    Terminal cost: a value ``storage_value_g_per_mol`` for each stored mol of NH3 (it converts NOx later) and a
    quadratic penalty on coverage above a *safe coverage* per cell: the coverage whose desorption, at the hottest
    cell temperature predicted over the next ``lookahead_s`` seconds (cycle preview when given, else the current
    temperature), would put ``safe_slip_ppm`` of NH3 into the gas. This is what lets the oracle fill the storage at
    low temperature and empty it before a heat-up.

:class:`IdentifiedModelAdapter`
    Any fitted model with ``to_casadi() -> Function('step', [x, u], [x_next, y])`` on normalised signals; the
    adapter maps the physical signals to the model's inputs and its outputs back to (tailpipe NOx ppm, NH3 ppm).

The state each solve starts from comes from a state estimator the MPC calls (:mod:`control.estimation`): the
oracle's :class:`~control.estimation.PrivilegedState` (the simulator's coverages), an identified model's
:class:`~control.estimation.ObservationEKF` (the measured signals only). ``model.make_estimator()`` gives each
model's default one.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import casadi as ca
import numpy as np

from control.estimation import ObservationEKF, PrivilegedState
from control.signals import ModelSignals
from scr_env.jit import njit
from scr_env.params import KINETIC_SLICE, DosingParams, P
from scr_env.physics.backends import casadi_functions, cell_balance_nb, numpy_namespace
from scr_env.physics.cell import N_RATE_CONSTANTS
from scr_env.physics.dosing import MIN_FLOW_PER_SITE_1_S as _MIN_Q
from scr_env.physics.kernel import thermal_trajectory

_KIN = KINETIC_SLICE
_N_K = N_RATE_CONSTANTS  # rate constants per cell


@njit
def _safe_coverage(k: np.ndarray, q: float, target: float) -> float:
    """Coverage whose desorption into NH3- and NOx-free gas gives the mole fraction ``target`` (bisection)."""
    lo, hi = 0.0, 1.0
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        y = cell_balance_nb(mid, q, 0.0, 0.0, 0.0, k[0], k[1], k[2], k[3], k[4], k[5], k[6], k[7], k[8], k[9], k[10],
                            k[11], k[12], k[13])[2]
        if y < target:
            lo = mid
        else:
            hi = mid
    return lo


def _rate_constants_function(params: np.ndarray, o2_fraction: float) -> ca.Function:
    """Function mapping a row of temperatures [K] to the (N_RATE_CONSTANTS, n) rate constants of cell_balance."""
    rate_constants = casadi_functions()[1]
    t = ca.SX.sym("t")
    k = ca.vertcat(*rate_constants(t, o2_fraction, *[float(v) for v in params[_KIN]]))
    return ca.Function("k", [t], [k])


class FirstPrinciplesModel:
    """The oracle's model (module docstring). Needs ``attach(env)`` before use.

    Parameters
    ----------
    o2_fraction : inlet O2 mole fraction [-] (the environment's constant).
    dosing : urea decomposition parameters (default :class:`DosingParams`).
    storage_value_g_per_mol : terminal value of stored NH3 [g AdBlue equivalent per mol].
    safe_slip_ppm : desorption level that defines the safe coverage [ppm].
    lookahead_s : how far ahead the hottest temperature is sought [s] (needs the preview to see further than now).
    cap_weight : terminal penalty per (coverage above the safe coverage)^2 per cell.
    use_preview : look ``lookahead_s`` ahead in the cycle preview (``env.disturbance_preview``) for the safe
        coverage; False uses the horizon's temperatures only.
    """

    def __init__(self, o2_fraction: float = 0.10, dosing: DosingParams | None = None,
                 storage_value_g_per_mol: float = 200.0, safe_slip_ppm: float = 20.0, lookahead_s: float = 120.0,
                 cap_weight: float = 2.0e4, use_preview: bool = True) -> None:
        self.o2_fraction = o2_fraction
        self.dosing = dosing
        self.storage_value_g_per_mol = storage_value_g_per_mol
        self.safe_slip_ppm = safe_slip_ppm
        self.lookahead_s = lookahead_s
        self.cap_weight = cap_weight
        self.use_preview = use_preview
        self._env = None
        self._params: np.ndarray | None = None

    # --- sizes ---------------------------------------------------------------------------------------------------
    @property
    def n_cells(self) -> int:
        if self._params is None:
            raise RuntimeError("FirstPrinciplesModel needs attach(env) before use (privileged catalyst parameters)")
        return int(self._params[P["n_cells"]])

    @property
    def nx(self) -> int:
        return self.n_cells

    @property
    def n_stage_params(self) -> int:
        return 4 + _N_K * self.n_cells  # q, y_nh3 per g/s, y_no_in, y_no2_in, rate constants per cell

    @property
    def n_terminal_params(self) -> int:
        return self.n_cells  # safe coverage per cell

    def attach(self, env: Any) -> None:
        self._env = env
        params = np.asarray(env.catalyst_params_array, dtype=np.float64)
        if self._params is None or not np.array_equal(params, self._params):
            self._params = params
            self._k_fun = _rate_constants_function(params, self.o2_fraction)
            self._k_map: dict[int, ca.Function] = {}

    def _constants(self, temperatures_k: np.ndarray) -> np.ndarray:
        """(len, 9) rate constants at the given temperatures [K]."""
        t = np.asarray(temperatures_k, dtype=np.float64).ravel()
        f = self._k_map.get(t.size)
        if f is None:
            f = self._k_map[t.size] = self._k_fun.map(t.size)
        return np.asarray(f(t[None, :])).T

    def reset(self, observation: np.ndarray) -> None:
        pass

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return np.zeros(self.nx), np.ones(self.nx)

    # --- symbolic stage --------------------------------------------------------------------------------------------
    def _cells(self, x_next: Any, u: Any, p: Any) -> tuple[list, tuple]:
        cell_balance = casadi_functions()[0]
        q, c_nh3, y_no, y_no2 = p[0], p[1], p[2], p[3]
        y_nh3 = c_nh3 * u
        g = []
        for j in range(self.n_cells):
            k = [p[4 + _N_K * j + i] for i in range(_N_K)]
            r = cell_balance(x_next[j], q, y_nh3, y_no, y_no2, *k)
            g.append(r[0])
            y_nh3, y_no, y_no2 = r[2], r[3], r[4]
        return g, (y_nh3, y_no, y_no2)

    def residual(self, x_next: Any, x: Any, u: Any, d: Any, p: Any, h: float) -> Any:
        g, _ = self._cells(x_next, u, p)
        return ca.vertcat(*[(x_next[j] - x[j]) / h - g[j] for j in range(self.n_cells)])

    def outputs(self, x_next: Any, x: Any, u: Any, d: Any, p: Any) -> Any:
        _, (y_nh3, y_no, y_no2) = self._cells(x_next, u, p)
        return ca.vertcat((y_no + y_no2) * 1e6, y_nh3 * 1e6)

    def terminal_cost(self, x: Any, p: Any) -> Any:
        sites = self._params[P["sites_per_cell_mol"]]
        cost = 0
        for j in range(self.n_cells):
            cost += -self.storage_value_g_per_mol * sites * x[j] + self.cap_weight * ca.fmax(x[j] - p[j], 0) ** 2
        return cost

    # --- numeric preparation ----------------------------------------------------------------------------------
    def safe_coverage(self, temperature_k: float, flow_mol_s: float) -> float:
        """Coverage [-] whose desorption into NH3-free gas gives ``safe_slip_ppm`` at this temperature and flow."""
        q = max(flow_mol_s / self._params[P["sites_per_cell_mol"]], _MIN_Q)
        return float(_safe_coverage(self._constants(np.array([temperature_k]))[0], q, self.safe_slip_ppm * 1e-6))

    def _temperatures(self, temps: np.ndarray, rows: np.ndarray, dt: float) -> np.ndarray:
        return thermal_trajectory(temps, np.ascontiguousarray(rows[:, 0]), np.ascontiguousarray(rows[:, 1]),
                                  self._params, dt)

    def make_estimator(self) -> PrivilegedState:
        """The oracle's state estimator: the simulator's own coverages (privileged)."""
        return PrivilegedState()

    def stage_parameters(self, observation: np.ndarray, disturbances: np.ndarray, h: float,
                         dt: float) -> tuple[np.ndarray, np.ndarray]:
        """(stage parameters (H, n_stage_params), safe coverage per cell) from the privileged solid temperatures
        and the stage disturbances (module docstring)."""
        env, p = self._env, self._params
        temps0 = env.state["temperature_k"].astype(np.float64)
        dose = self.dosing or DosingParams()
        sites = p[P["sites_per_cell_mol"]]
        H, n = disturbances.shape[0], self.n_cells
        if np.ndim(h) == 0:   # uniform stages of h seconds
            n_sub = max(round(h / dt), 1)
            # stage temperatures: the held stage disturbance over n_sub intervals of dt (end of each stage)
            temps = self._temperatures(temps0, np.repeat(disturbances, n_sub, axis=0), dt)[n_sub - 1::n_sub]
            n_total = H * n_sub
        else:                 # multi-rate stages: each stage's own number of intervals
            subs = np.maximum(np.rint(np.asarray(h, dtype=np.float64) / dt).astype(np.int64), 1)
            if subs.shape != (H,):
                raise ValueError(f"h must be a stage length or one per stage ({H}), got shape {np.shape(h)}")
            temps = self._temperatures(temps0, np.repeat(disturbances, subs, axis=0), dt)[np.cumsum(subs) - 1]
            n_total = int(subs.sum())
        flow, t_in, nox, no2f = disturbances.T
        pst = np.empty((H, self.n_stage_params))
        # the plant's inlet gas (scr_env.physics.dosing) for 1 g/s of AdBlue: y_nh3 is linear in the dose, which the
        # NLP keeps within the injector limit
        pst[:, 0], pst[:, 1], pst[:, 2], pst[:, 3] = numpy_namespace().inlet_conditions(
            flow, t_in, nox, no2f, 1.0, np.inf, dose.decomposition_t50_k, dose.decomposition_width_k, sites)[:4]
        pst[:, 4:] = self._constants(temps.ravel()).reshape(H, n * _N_K)
        t_hot = np.maximum(temps.max(axis=0), temps0)
        # hottest temperature further ahead, from the cycle preview (privileged) if the model is given one
        n_far = int(self.lookahead_s / dt) - n_total
        if n_far > 0 and self.use_preview:
            far = env.disturbance_preview(n_total + n_far)[n_total:]
            t_far = self._temperatures(temps[-1], far, dt)
            t_hot = np.maximum(t_hot, t_far.max(axis=0))
        flow_ref = float(np.mean(flow))
        kh = self._constants(t_hot)
        q = max(flow_ref / sites, _MIN_Q)
        cap = np.array([_safe_coverage(kh[j], q, self.safe_slip_ppm * 1e-6) for j in range(n)])
        return pst, cap


class IdentifiedModelAdapter:
    """An identified model (``to_casadi()`` on normalised signals) as a :class:`control.mpc.PredictionModel`.

    The model's inputs are built from the MPC's physical signals by ``signals`` (:class:`control.signals.ModelSignals`:
    input map and normalisation); its outputs are de-normalised and ``output_indices`` pick (tailpipe NOx ppm, NH3
    ppm) for the objective and the slip constraint. The adapter holds no state: the model state the NLP starts from
    comes from a state estimator the MPC calls (:class:`control.estimation.ObservationEKF` on the same model; the
    EKF settings given here build it in :meth:`make_estimator`, which :class:`~control.mpc.NonlinearMPC` uses when
    it is not given an estimator of its own).

    Parameters
    ----------
    model : fitted model with ``to_casadi()``.
    input_mean, input_scale, output_mean, output_scale : normalisation of the identification data
        (``Normalizer.mean_`` / ``scale_``); z = (x - mean) / scale.
    input_map : ``f(adblue_g_s, d) -> list`` of the model's physical inputs from the dose [g/s] and the
        disturbance ``d = (flow mol/s, inlet T K, NOx ppm, NO2 fraction)`` (works on CasADi symbols and floats).
        Default: :func:`control.signals.plant_data_inputs` (inlet NOx ppm, urea g/min, inlet T K, flow mol/s).
    output_indices : indices of (tailpipe NOx ppm, NH3 ppm) among the model outputs.
    measured_output, measured_obs, process_noise, measurement_noise, initial_state : the settings of the default
        estimator (:class:`~control.estimation.ObservationEKF`: the output(s) it corrects with, their observation
        entries -- default the tailpipe NOx sensor obs[3] --, its covariances and the state at episode start).
    state_bounds : (lower, upper) of the model state (NLP bounds and the default estimator's clipping); default
        +/-50.
    model_dt : sample time of the model [s]; a stage of the MPC is round(h / model_dt) model steps.
    terminal_cost : optional ``f(x) -> SX`` terminal cost of the MPC.
    stage_model : optional second export of the same identified model discretised at the MPC's stage length
        (continuous-time parameters, e.g. :meth:`ident.greybox.StorageGreyBox.from_params` with ``dt = h``):
        one step per stage keeps the NLP small; the estimator still runs ``model`` at the data's sample time.
    implicit_stage : optional ``f(x_next, x, u, h) -> (residual, y)``, the model over a stage as implicit
        equations in the NLP's end state (e.g. :meth:`ident.greybox.StorageGreyBox.implicit_stage`, on the
        normalised inputs); used instead of ``stage_model`` / ``model`` in the NLP when given: an implicit stage
        needs no clipping and keeps the NLP smooth. Its ``y`` holds the outputs named by ``output_indices``.
    """

    n_terminal_params = 0
    n_stage_params = 0

    def __init__(self, model: Any, input_mean: Sequence[float], input_scale: Sequence[float],
                 output_mean: Sequence[float], output_scale: Sequence[float],
                 input_map: Callable[[Any, Any], list] | None = None, output_indices: tuple[int, int] = (0, 1),
                 measured_output: int | Sequence[int] = 2, process_noise: float | np.ndarray = 1e-3,
                 measurement_noise: float | Sequence[float] = 1e-2,
                 state_bounds: tuple[np.ndarray, np.ndarray] | None = None,
                 initial_state: Callable[[np.ndarray], np.ndarray] | None = None, model_dt: float = 0.5,
                 terminal_cost: Callable[[Any], Any] | None = None, stage_model: Any = None,
                 implicit_stage: Callable[[Any, Any, Any, float], tuple[Any, Any]] | None = None,
                 measured_obs: Sequence[int] = (3,)) -> None:
        self.model = model
        self.input_mean = input_mean
        self.input_scale = input_scale
        self.output_mean = output_mean
        self.output_scale = output_scale
        self.input_map = input_map
        self.output_indices = output_indices
        self.measured_output = measured_output
        self.process_noise = process_noise
        self.measurement_noise = measurement_noise
        self.state_bounds_arg = state_bounds
        self.initial_state = initial_state
        self.model_dt = model_dt
        self.terminal_cost_fn = terminal_cost
        self.stage_model = stage_model
        self.implicit_stage = implicit_stage
        self.measured_obs = tuple(int(j) for j in measured_obs)
        n_measured = 1 if np.ndim(measured_output) == 0 else len(measured_output)
        if len(self.measured_obs) != n_measured:
            raise ValueError(f"measured_obs must name one observation index per measured output ({n_measured}), "
                             f"got {measured_obs!r}")
        self.signals = ModelSignals(input_mean, input_scale, output_mean, output_scale, input_map)
        self.step_ = model.to_casadi()
        self.stage_step_ = None if stage_model is None else stage_model.to_casadi()
        self.nx = int(self.step_.size1_in(0))
        bounds = state_bounds or (np.full(self.nx, -50.0), np.full(self.nx, 50.0))
        self._bounds = (np.asarray(bounds[0], float), np.asarray(bounds[1], float))

    def make_estimator(self) -> ObservationEKF:
        """A new :class:`~control.estimation.ObservationEKF` on this model with the estimator settings given to the
        constructor."""
        return ObservationEKF(self.step_, self.signals, measured_output=self.measured_output,
                              measured_obs=self.measured_obs, process_noise=self.process_noise,
                              measurement_noise=self.measurement_noise, state_bounds=self.state_bounds_arg,
                              initial_state=self.initial_state)

    def stage_inputs(self, u: Any, d: Any) -> Any:
        """The model's normalised input vector (CasADi) for the dose ``u`` [g/s] under the disturbance ``d``."""
        return ca.vertcat(*self.signals.inputs(u, d))

    def _simulate(self, x: Any, u: Any, d: Any, h: float) -> tuple[Any, Any]:
        """Model steps of model_dt over one stage of length h (input held): (x at the end, y of the last step)."""
        un = self.stage_inputs(u, d)
        if self.stage_step_ is not None:
            return self.stage_step_(x, un)
        y = None
        for _ in range(max(round(h / self.model_dt), 1)):
            x, y = self.step_(x, un)
        return x, y

    def _stage(self, x_next: Any, x: Any, u: Any, d: Any, h: float) -> tuple[Any, Any]:
        """(residual, y) of one stage. The NLP asks for the residual and then the outputs of the same stage: the
        last stage is kept, so its expressions are built (and evaluated at every solve) once, not twice."""
        key = (x_next, x, u, d, h)
        last = getattr(self, "_last_stage", None)
        if last is not None and all(a is b for a, b in zip(last[0], key, strict=True)):
            return last[1]
        if self.implicit_stage is not None:
            stage = self.implicit_stage(x_next, x, self.stage_inputs(u, d), h)
        else:
            xs, y = self._simulate(x, u, d, h)
            stage = (x_next - xs, y)
        self._last_stage = (key, stage)
        return stage

    def residual(self, x_next: Any, x: Any, u: Any, d: Any, p: Any, h: float) -> Any:
        self._h = h
        return self._stage(x_next, x, u, d, h)[0]

    def physical_outputs(self, y: Any) -> Any:
        """(tailpipe NOx ppm, NH3 ppm) from the model outputs ``y`` (de-normalised ``output_indices``)."""
        i, j = self.output_indices
        return ca.vertcat(self.signals.output_to_physical(y[i], i), self.signals.output_to_physical(y[j], j))

    def outputs(self, x_next: Any, x: Any, u: Any, d: Any, p: Any) -> Any:
        return self.physical_outputs(self._stage(x_next, x, u, d, self._h)[1])

    def terminal_cost(self, x: Any, p: Any) -> Any:
        return 0 if self.terminal_cost_fn is None else self.terminal_cost_fn(x)

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self._bounds

    def attach(self, env: Any) -> None:
        pass

    def reset(self, observation: np.ndarray) -> None:
        pass

    def stage_parameters(self, observation: np.ndarray, disturbances: np.ndarray, h: float,
                         dt: float) -> tuple[np.ndarray, np.ndarray]:
        """No stage or terminal parameters: the identified model is fixed."""
        return np.zeros((disturbances.shape[0], 0)), np.zeros(0)
