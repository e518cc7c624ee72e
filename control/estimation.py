"""State estimation: an extended Kalman filter on any CasADi step function, and the estimators an NMPC calls.

The controller and its estimator are separate objects (do-mpc's split): at every step the NMPC calls
``x = estimator.make_step(observation, applied_dose_g_s, disturbance)`` and then optimises from ``x``. Estimators
(:class:`StateEstimator`):

* :class:`ObservationEKF` -- the state of any identified model (``model.to_casadi()``) from the measured signals of
  the environment's observation (the tailpipe NOx sensor, optionally an NH3 sensor), by
  :class:`ExtendedKalmanFilter`;
* :class:`PrivilegedState` -- the simulator's own catalyst state (the oracle: privileged information).

The model is ``Function('step', [x, u], [x_next, y])`` -- the export of every identified model of :mod:`ident`
(``model.to_casadi()``) or a first-principles step (:func:`scr_env.casadi_model.catalyst_step`). Jacobians
``A = d x_next / d x`` and ``C = d y / d x`` come from CasADi's automatic differentiation, built once.

Timing convention (that of the identification data and of the environment): ``y_k = h(x_k, u_k)`` is measured
after the input ``u_k`` has been applied, ``x_{k+1} = f(x_k, u_k)``. :meth:`ExtendedKalmanFilter.step` does the
measurement update of ``x_k`` with ``(u_k, y_k)`` and then the time update to ``x_{k+1}``.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Protocol, runtime_checkable

import casadi as ca
import numpy as np


class ExtendedKalmanFilter:
    """EKF for ``x+ = f(x, u) + w``, ``y_m = h_m(x, u) + v`` with ``w ~ N(0, Q)``, ``v ~ N(0, R)``.

    Parameters
    ----------
    step : CasADi ``Function('step', [x, u], [x_next, y])`` with column-vector inputs ``x`` (nx) and ``u`` (nu) and
        outputs ``x_next`` (nx) and ``y`` (ny).
    process_noise : Q: a scalar (``q I``), a vector of nx variances (diagonal) or an (nx, nx) symmetric positive
        semidefinite matrix; finite, >= 0.
    measurement_noise : R of the measured outputs: a scalar, a vector of nm variances or an (nm, nm) symmetric
        positive definite matrix; finite, > 0 (the innovation covariance ``C P C' + R`` must stay invertible).
    measured : indices (in ``range(ny)``) of the outputs of ``step`` that are measured (default: all); nm of them.
    x0 : initial estimate, nx values (default zeros).
    p0 : its covariance, like ``process_noise`` (scalar, nx variances or (nx, nx) PSD matrix; default the identity).
    state_bounds : optional (lower, upper), each a scalar or nx values with lower <= upper (inf allowed), that the
        estimate is clipped to after each update.

    Every argument is checked here (``ValueError`` naming it: wrong size, NaN/inf, negative variance, a matrix that
    is not symmetric PSD, a measured index out of range), and so is :meth:`reset`'s ``x0``/``p0``.

    Signals of :meth:`step` / :meth:`correct` / :meth:`propagate` (units: those of ``step``, which the filter does
    not know -- for :class:`control.models.IdentifiedModelAdapter` the identification data normalised as
    ``(x - mean) / scale``; with mean 0 and scale 1, as for :class:`ident.greybox.StorageGreyBox`, physical:
    u = [inlet NOx ppm, urea g/min, inlet temperature K, exhaust flow mol/s], y = [tailpipe NOx ppm, NH3 ppm,
    NOx sensor ppm])

    * ``u``: the input ``u_k`` applied during the interval, nu values (shape ``(nu,)``; ``(nu, 1)``, ``(1, nu)`` and,
      for nu = 1, a scalar are accepted);
    * ``y_measured``: the measured outputs ``y_k`` in the order of ``measured``, nm values (same shapes accepted).

    A non-finite or wrongly sized ``u`` or ``y_measured`` raises ``ValueError`` naming it before the estimate,
    its covariance or ``innovation_`` change. An update whose result would be non-finite (the model evaluated far
    outside its range) raises ``FloatingPointError`` and also leaves the filter as it was. A singular innovation
    covariance raises ``numpy.linalg.LinAlgError``, likewise before any change.
    """

    def __init__(self, step: ca.Function, process_noise: float | np.ndarray = 1e-4,
                 measurement_noise: float | np.ndarray = 1e-2, measured: Sequence[int] | None = None,
                 x0: np.ndarray | None = None, p0: float | np.ndarray = 1.0,
                 state_bounds: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        self.step_function = step
        self.process_noise = process_noise
        self.measurement_noise = measurement_noise
        self.measured = measured
        self.x0 = x0
        self.p0 = p0
        self.state_bounds = state_bounds
        nx, nu, ny = self._check_step(step)
        self.nx_ = nx
        self.nu_ = nu
        self.measured_ = self._check_measured(measured, ny)
        self.Q_ = self._matrix(process_noise, nx, "process_noise", definite=False)
        self.R_ = self._matrix(measurement_noise, len(self.measured_), "measurement_noise", definite=True)
        self._bounds = None if state_bounds is None else self._check_bounds(state_bounds, nx)
        self._functions(step)
        self.reset()  # checks x0 and p0

    def _functions(self, step: ca.Function) -> None:
        """The time-update and measurement functions with their Jacobians (CasADi AD), from ``step``."""
        x = ca.MX.sym("x", self.nx_)
        u = ca.MX.sym("u", self.nu_)
        xn, y = step(x, u)
        ym = y[self.measured_]
        self._f = ca.Function("ekf_f", [x, u], [xn, ca.jacobian(xn, x)])
        self._h = ca.Function("ekf_h", [x, u], [ym, ca.jacobian(ym, x)])

    # ------------------------------------------------------------------------------------------------ checks
    @staticmethod
    def _check_step(step: Any) -> tuple[int, int, int]:
        if not isinstance(step, ca.Function):
            raise TypeError(f"step must be a casadi.Function('step', [x, u], [x_next, y]), got {type(step).__name__}")
        if step.n_in() != 2 or step.n_out() < 2:
            raise ValueError(f"step must have the inputs (x, u) and the outputs (x_next, y), got {step.n_in()} "
                             f"inputs and {step.n_out()} outputs")
        for k, what in ((0, "x"), (1, "u")):
            if step.size2_in(k) != 1:
                raise ValueError(f"step's input {what} must be a column vector, got {step.size_in(k)}")
        nx = step.size1_in(0)
        if step.size_out(0) != (nx, 1):
            raise ValueError(f"step's output x_next must have the size of its input x ({nx}, 1), got "
                             f"{step.size_out(0)}")
        if step.size2_out(1) != 1:
            raise ValueError(f"step's output y must be a column vector, got {step.size_out(1)}")
        return nx, step.size1_in(1), step.size1_out(1)

    @staticmethod
    def _check_measured(measured: Sequence[int] | None, ny: int) -> list[int]:
        if measured is None:
            return list(range(ny))
        idx = np.asarray(measured).reshape(-1) if np.ndim(measured) <= 1 else None
        if idx is None or idx.size == 0 or not np.issubdtype(idx.dtype, np.integer) or idx.dtype == bool:
            raise ValueError(f"measured must be a non-empty sequence of output indices in range({ny}), got "
                             f"{measured!r}")
        if idx.min() < 0 or idx.max() >= ny:
            raise ValueError(f"measured indices must be in range({ny}) (step has {ny} outputs), got {measured!r}")
        return [int(i) for i in idx]

    @staticmethod
    def _matrix(v: Any, n: int, name: str, definite: bool) -> np.ndarray:
        """Covariance (n, n) from a scalar, n variances or a matrix; ValueError naming ``name`` unless finite and
        symmetric positive semidefinite (``definite``: positive definite)."""
        try:
            a = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be a number, a vector of {n} variances or an ({n}, {n}) matrix, got "
                             f"{v!r}") from None
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains NaN or inf: {v!r}")
        sign = "> 0" if definite else ">= 0"
        if a.ndim == 0:
            if not (a > 0 if definite else a >= 0):
                raise ValueError(f"{name} must be a variance {sign}, got {float(a)!r}")
            return float(a) * np.eye(n)
        if a.ndim == 1:
            if a.shape != (n,):
                per = "measured output" if name == "measurement_noise" else "state"
                raise ValueError(f"{name} must have {n} variances (one per {per}), got {a.shape[0]}")
            if not np.all(a > 0 if definite else a >= 0):
                raise ValueError(f"{name} variances must be {sign}, got {a.tolist()}")
            return np.diag(a)
        if a.shape != (n, n):
            raise ValueError(f"{name} must be a scalar, {n} variances or an ({n}, {n}) matrix, got shape {a.shape}")
        if not np.allclose(a, a.T, rtol=1e-10, atol=1e-12 * max(1.0, float(np.abs(a).max()))):
            raise ValueError(f"{name} must be a symmetric matrix")
        eig = np.linalg.eigvalsh(a)
        tol = 1e-12 * max(1.0, float(np.abs(eig).max()))
        if (eig.min() <= 0.0) if definite else (eig.min() < -tol):
            raise ValueError(f"{name} must be positive {'definite' if definite else 'semidefinite'}, its smallest "
                             f"eigenvalue is {eig.min():.3g}")
        return a.copy()

    @staticmethod
    def _vector(v: Any, n: int, name: str) -> np.ndarray:
        """n finite values as a float64 vector; (n,), (n, 1), (1, n) or, for n = 1, a scalar."""
        try:
            a = np.asarray(v, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be {n} numbers, got {v!r}") from None
        if a.size != n or a.ndim > 2 or (a.ndim == 2 and 1 not in a.shape):
            raise ValueError(f"{name} must have {n} values (shape ({n},)), got shape {a.shape}")
        a = a.reshape(n)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains NaN or inf at entries {np.flatnonzero(~np.isfinite(a)).tolist()}: "
                             f"{a.tolist()}")
        return a

    @staticmethod
    def _check_bounds(bounds: Any, n: int) -> tuple[np.ndarray, np.ndarray]:
        def one(v: Any) -> np.ndarray:
            a = np.asarray(v, dtype=np.float64)
            return np.broadcast_to(a.reshape(-1) if a.ndim else a, (n,))

        try:
            lo, hi = (one(v) for v in bounds)
        except (TypeError, ValueError):
            raise ValueError(f"state_bounds must be (lower, upper), each a number or {n} values, got "
                             f"{bounds!r}") from None
        if np.any(np.isnan(lo)) or np.any(np.isnan(hi)) or np.any(lo > hi):
            raise ValueError(f"state_bounds must be (lower, upper) without NaN and with lower <= upper, got "
                             f"{bounds!r}")
        return lo, hi

    # ------------------------------------------------------------------------------------------------ filter
    def set_step(self, step: ca.Function) -> None:
        """Replace the model by ``step`` (same state, input and output sizes), keeping the estimate, its covariance
        and the noise settings: the route for a model whose parameters are re-estimated online (adaptive control).
        ``TypeError`` / ``ValueError`` as the constructor's for a step of other sizes; nothing changes then."""
        nx, nu, ny = self._check_step(step)
        if (nx, nu) != (self.nx_, self.nu_) or max(self.measured_) >= ny:
            raise ValueError(f"step must keep the sizes of the filter's model (nx={self.nx_}, nu={self.nu_}, at "
                             f"least {max(self.measured_) + 1} outputs), got nx={nx}, nu={nu}, ny={ny}")
        self._functions(step)
        self.step_function = step

    def reset(self, x0: np.ndarray | None = None, p0: float | np.ndarray | None = None) -> None:
        """Restart from ``x0`` (nx values) / ``p0`` (covariance, as the constructor's; default: the constructor's).
        Both are checked (``ValueError`` naming them) before the filter changes."""
        x0 = self.x0 if x0 is None else x0
        x = np.zeros(self.nx_) if x0 is None else self._vector(x0, self.nx_, "x0")
        p = self._matrix(self.p0 if p0 is None else p0, self.nx_, "p0", definite=False)
        self.x_ = x.copy()
        self.P_ = p

    def _clipped(self, x: np.ndarray) -> np.ndarray:
        if self._bounds is not None:
            return np.clip(x, self._bounds[0], self._bounds[1])
        return x

    def _check_result(self, x: np.ndarray, p: np.ndarray, what: str) -> None:
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(p))):
            raise FloatingPointError(f"the EKF {what} gave a non-finite state estimate or covariance (the model "
                                     "evaluated outside its range?); the filter is left unchanged")

    def correct(self, u: np.ndarray, y_measured: np.ndarray) -> np.ndarray:
        """Measurement update of the current state with ``y_k`` measured under ``u_k``; returns the estimate."""
        u = self._vector(u, self.nu_, "u")
        ym = self._vector(y_measured, len(self.measured_), "y_measured")
        return self._correct(u, ym)

    def _correct(self, u: np.ndarray, y_measured: np.ndarray) -> np.ndarray:
        yhat, C = self._h(self.x_, u)
        yhat = np.asarray(yhat).ravel()
        C = np.asarray(C)
        S = C @ self.P_ @ C.T + self.R_
        K = np.linalg.solve(S, C @ self.P_).T
        innovation = y_measured - yhat
        x = self.x_ + K @ innovation
        I_KC = np.eye(self.nx_) - K @ C
        P = I_KC @ self.P_ @ I_KC.T + K @ self.R_ @ K.T  # Joseph form: stays symmetric positive definite
        x = self._clipped(x)
        self._check_result(x, P, "measurement update")
        self.innovation_, self.x_, self.P_ = innovation, x, P
        return self.x_

    def propagate(self, u: np.ndarray) -> np.ndarray:
        """Time update ``x_{k+1} = f(x_k, u_k)``; returns the predicted state."""
        return self._propagate(self._vector(u, self.nu_, "u"))

    def _propagate(self, u: np.ndarray) -> np.ndarray:
        xn, A = self._f(self.x_, u)
        A = np.asarray(A)
        x = np.asarray(xn).ravel()
        P = A @ self.P_ @ A.T + self.Q_
        x = self._clipped(x)
        self._check_result(x, P, "time update")
        self.x_, self.P_ = x, P
        return self.x_

    def step(self, u: np.ndarray, y_measured: np.ndarray) -> np.ndarray:
        """:meth:`correct` with ``(u_k, y_k)`` then :meth:`propagate` with ``u_k``; returns ``x_{k+1|k}``.

        Both arguments are checked before anything changes; if the time update fails (``FloatingPointError``) the
        measurement update is undone too, so a failed step leaves the filter as it was."""
        u = self._vector(u, self.nu_, "u")
        ym = self._vector(y_measured, len(self.measured_), "y_measured")
        saved = (self.x_, self.P_, getattr(self, "innovation_", None))
        self._correct(u, ym)
        try:
            return self._propagate(u)
        except BaseException:
            self.x_, self.P_ = saved[0], saved[1]
            if saved[2] is None:
                del self.innovation_
            else:
                self.innovation_ = saved[2]
            raise


# ---------------------------------------------------------------------------------------------------- estimators
@runtime_checkable
class StateEstimator(Protocol):
    """What :class:`control.mpc.NonlinearMPC` calls for the state its prediction model starts from."""

    def attach(self, env: Any) -> None:
        """Called by the controller's ``attach`` with the unwrapped environment (checks, privileged access)."""

    def reset(self, observation: np.ndarray) -> None:
        """Start of an episode, with its first observation."""

    def make_step(self, observation: np.ndarray, applied_dose_g_s: float, disturbance: np.ndarray) -> np.ndarray:
        """The state estimate for this step from the new ``observation``, the AdBlue dose [g/s] applied over the
        interval that led to it, and the current disturbance ``(flow mol/s, inlet T K, NOx ppm, NO2 fraction)``."""


class ObservationEKF:
    """The state of an identified model from the environment's observation: an :class:`ExtendedKalmanFilter` on
    ``step`` fed with the physical signals of the loop through ``signals``.

    Parameters
    ----------
    step : the model's ``Function('step', [x, u], [x_next, y])`` on normalised signals (``model.to_casadi()``).
    signals : :class:`control.signals.ModelSignals` of the model (input map, normalisation).
    measured_output : index of the model output the filter corrects with, or a sequence of them.
    measured_obs : observation index of each measured output (default ``(3,)``: the tailpipe NOx sensor; with
        ``UreaSCREnv(nh3_sensor=True)`` the NH3 sensor is obs[5]).
    process_noise, measurement_noise : the filter's covariances (normalised units; ``measurement_noise`` a scalar or
        one variance per measured output).
    state_bounds : (lower, upper) the estimate is clipped to (default +/-50 on every state).
    initial_state : ``f(observation) -> x0`` at episode start (default zeros).
    p0 : the covariance of that initial state (scalar, one variance per state or a matrix; default the identity,
        :class:`ExtendedKalmanFilter`'s): how far the filter may move a state it cannot yet see well.

    Timing: the observation of step k holds the sensor readings ``y_{k-1}`` measured after the interval whose input
    was the applied dose ``u_{k-1}`` under the disturbance measured now. :meth:`make_step` corrects ``x_{k-1}`` with
    ``(u_{k-1}, y_{k-1})`` and propagates to ``x_k`` (:meth:`ExtendedKalmanFilter.step`); at the first step of an
    episode there is nothing to correct yet and the estimate is the initial state.
    """

    def __init__(self, step: ca.Function, signals: Any, measured_output: int | Sequence[int] = 2,
                 measured_obs: Sequence[int] = (3,), process_noise: float | np.ndarray = 1e-3,
                 measurement_noise: float | Sequence[float] = 1e-2,
                 state_bounds: tuple[np.ndarray, np.ndarray] | None = None,
                 initial_state: Callable[[np.ndarray], np.ndarray] | None = None,
                 p0: float | np.ndarray = 1.0) -> None:
        self.step = step
        self.signals = signals
        self.measured_output = measured_output
        self.measured_obs = tuple(int(j) for j in measured_obs)
        self.process_noise = process_noise
        self.measurement_noise = measurement_noise
        self.state_bounds = state_bounds
        self.initial_state = initial_state
        self.p0 = p0
        self.measured_ = ([int(measured_output)] if np.ndim(measured_output) == 0
                          else [int(k) for k in measured_output])
        if len(self.measured_obs) != len(self.measured_):
            raise ValueError(f"measured_obs must name one observation index per measured output "
                             f"({len(self.measured_)}), got {measured_obs!r}")
        nx = int(step.size1_in(0)) if isinstance(step, ca.Function) else 0
        bounds = state_bounds or (np.full(nx, -50.0), np.full(nx, 50.0))
        self.ekf_ = ExtendedKalmanFilter(step, process_noise, measurement_noise, measured=self.measured_,
                                         state_bounds=bounds, p0=p0)
        self._u_last: np.ndarray | None = None

    @property
    def x_(self) -> np.ndarray:
        """The current estimate (the filter's)."""
        return self.ekf_.x_

    def attach(self, env: Any) -> None:
        """Check that the environment observes every entry ``measured_obs`` reads."""
        n_obs = int(env.observation_space.shape[0])
        if max(self.measured_obs) >= n_obs:
            raise ValueError(f"measured_obs {self.measured_obs}: the environment observes {n_obs} signals "
                             f"({', '.join(getattr(env, 'observation_names', []))}); an NH3-sensor model needs "
                             "UreaSCREnv(nh3_sensor=True)")

    def reset(self, observation: np.ndarray) -> None:
        """Restart the filter at ``initial_state(observation)`` (zeros by default)."""
        x0 = None if self.initial_state is None else self.initial_state(np.asarray(observation, dtype=np.float64))
        self.ekf_.reset(x0)
        self._u_last = None

    def make_step(self, observation: np.ndarray, applied_dose_g_s: float, disturbance: np.ndarray) -> np.ndarray:
        """The estimate of the model state now (class docstring); a copy."""
        obs = np.asarray(observation, dtype=np.float64)
        d_now = np.array([obs[2], obs[1], obs[0], disturbance[3]])
        u_now = np.asarray(self.signals.inputs(applied_dose_g_s, d_now), dtype=np.float64)
        if self._u_last is not None:
            self.ekf_.step(u_now, np.array([self.signals.output_to_model(obs[j], k)
                                            for k, j in zip(self.measured_, self.measured_obs, strict=True)]))
        self._u_last = u_now
        return self.ekf_.x_.copy()

    def set_step(self, step: ca.Function) -> None:
        """Continue with another model of the same sizes (:meth:`ExtendedKalmanFilter.set_step`), e.g. the same
        model with re-estimated parameters; the estimate and its covariance carry over."""
        self.ekf_.set_step(step)
        self.step = step


class PrivilegedState:
    """The simulator's own catalyst state: the NH3 coverage of every cell, clipped to [0, 1], read from the
    environment given to :meth:`attach` (``env.state``). Privileged information, for the oracle NMPC."""

    def __init__(self) -> None:
        self._env: Any = None

    def attach(self, env: Any) -> None:
        self._env = env

    def reset(self, observation: np.ndarray) -> None:
        pass

    def make_step(self, observation: np.ndarray, applied_dose_g_s: float, disturbance: np.ndarray) -> np.ndarray:
        if self._env is None:
            raise RuntimeError("PrivilegedState needs attach(env) before use (it reads the simulator's state)")
        return np.clip(self._env.state["nh3_coverage"], 0.0, 1.0)
