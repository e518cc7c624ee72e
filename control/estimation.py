"""State estimation from measured signals only: an extended Kalman filter on any CasADi step function.

The model is ``Function('step', [x, u], [x_next, y])`` -- the export of every identified model of :mod:`ident`
(``model.to_casadi()``) or a first-principles step (:func:`scr_env.casadi_model.catalyst_step`). Jacobians
``A = d x_next / d x`` and ``C = d y / d x`` come from CasADi's automatic differentiation, built once.

Timing convention (that of the identification data and of the environment): ``y_k = h(x_k, u_k)`` is measured
after the input ``u_k`` has been applied, ``x_{k+1} = f(x_k, u_k)``. :meth:`ExtendedKalmanFilter.step` does the
measurement update of ``x_k`` with ``(u_k, y_k)`` and then the time update to ``x_{k+1}``.
"""
from __future__ import annotations

from collections.abc import Sequence

import casadi as ca
import numpy as np


class ExtendedKalmanFilter:
    """EKF for ``x+ = f(x, u) + w``, ``y_m = h_m(x, u) + v`` with ``w ~ N(0, Q)``, ``v ~ N(0, R)``.

    Parameters
    ----------
    step : CasADi ``Function('step', [x, u], [x_next, y])``.
    process_noise : Q, (nx, nx) or a scalar / vector for a diagonal.
    measurement_noise : R for the measured outputs, (nm, nm) or scalar / vector.
    measured : indices of the outputs of ``step`` that are measured (default: all).
    x0, p0 : initial estimate and its covariance (default zeros and the identity).
    state_bounds : optional (lower, upper) arrays the estimate is clipped to after each update.
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
        nx = step.size1_in(0)
        ny = step.size1_out(1)
        self.nx_ = nx
        self.measured_ = list(range(ny)) if measured is None else [int(i) for i in measured]
        x = ca.MX.sym("x", nx)
        u = ca.MX.sym("u", step.size1_in(1))
        xn, y = step(x, u)
        ym = y[self.measured_]
        self._f = ca.Function("ekf_f", [x, u], [xn, ca.jacobian(xn, x)])
        self._h = ca.Function("ekf_h", [x, u], [ym, ca.jacobian(ym, x)])
        self.Q_ = self._matrix(process_noise, nx)
        self.R_ = self._matrix(measurement_noise, len(self.measured_))
        self.reset()

    @staticmethod
    def _matrix(v: float | np.ndarray, n: int) -> np.ndarray:
        a = np.asarray(v, dtype=np.float64)
        if a.ndim == 0:
            return float(a) * np.eye(n)
        if a.ndim == 1:
            return np.diag(a)
        return a

    def reset(self, x0: np.ndarray | None = None, p0: float | np.ndarray | None = None) -> None:
        """Restart from ``x0`` / ``p0`` (default: the constructor's)."""
        x = x0 if x0 is not None else self.x0
        self.x_ = np.zeros(self.nx_) if x is None else np.asarray(x, dtype=np.float64).copy()
        self.P_ = self._matrix(self.p0 if p0 is None else p0, self.nx_)

    def _clip(self) -> None:
        if self.state_bounds is not None:
            self.x_ = np.clip(self.x_, self.state_bounds[0], self.state_bounds[1])

    def correct(self, u: np.ndarray, y_measured: np.ndarray) -> np.ndarray:
        """Measurement update of the current state with ``y_k`` measured under ``u_k``; returns the estimate."""
        yhat, C = self._h(self.x_, u)
        yhat = np.asarray(yhat).ravel()
        C = np.asarray(C)
        S = C @ self.P_ @ C.T + self.R_
        K = np.linalg.solve(S, C @ self.P_).T
        self.innovation_ = np.asarray(y_measured, dtype=np.float64).ravel() - yhat
        self.x_ = self.x_ + K @ self.innovation_
        I_KC = np.eye(self.nx_) - K @ C
        self.P_ = I_KC @ self.P_ @ I_KC.T + K @ self.R_ @ K.T  # Joseph form: stays symmetric positive definite
        self._clip()
        return self.x_

    def propagate(self, u: np.ndarray) -> np.ndarray:
        """Time update ``x_{k+1} = f(x_k, u_k)``; returns the predicted state."""
        xn, A = self._f(self.x_, u)
        A = np.asarray(A)
        self.x_ = np.asarray(xn).ravel()
        self.P_ = A @ self.P_ @ A.T + self.Q_
        self._clip()
        return self.x_

    def step(self, u: np.ndarray, y_measured: np.ndarray) -> np.ndarray:
        """:meth:`correct` with ``(u_k, y_k)`` then :meth:`propagate` with ``u_k``; returns ``x_{k+1|k}``."""
        self.correct(u, y_measured)
        return self.propagate(u)
