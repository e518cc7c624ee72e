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
from typing import Any

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
        x = ca.MX.sym("x", nx)
        u = ca.MX.sym("u", nu)
        xn, y = step(x, u)
        ym = y[self.measured_]
        self._f = ca.Function("ekf_f", [x, u], [xn, ca.jacobian(xn, x)])
        self._h = ca.Function("ekf_h", [x, u], [ym, ca.jacobian(ym, x)])
        self.reset()  # checks x0 and p0

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
                raise ValueError(f"{name} must have {n} variances (one per {'measured output' if name == 'measurement_noise' else 'state'}), got {a.shape[0]}")
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
