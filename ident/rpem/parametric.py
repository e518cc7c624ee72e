"""The recursive prediction error method for the parameters of any model written as a CasADi step.

:class:`RecursivePEM` identifies the black-box polynomial ODE models of the thesis. This class applies the same
Gauss-Newton recursion (ALGORITHMS.md section 1; Ljung and Soderstrom 1983) to any discrete-time model

    x(t+1) = f(x(t), u(t), p),    yhat(t) = h(x(t), u(t), p)

given as a CasADi function ``step(x, u, p) -> (x_next, y)``, for example a grey-box catalyst model whose
parameters drift as the catalyst ages. Per sample, with the state sensitivity S = dx/dp:

    psi^T   = dh/dx S + dh/dp                      (gradient of the prediction, ny x np)
    eps     = y - yhat
    Lambda <- Lambda + gamma (eps eps^T - Lambda)
    R      <- R + gamma (psi Lambda^-1 psi^T - R)
    p      <- [p + gamma R^-1 psi Lambda^-1 eps]_DM   (kept if the candidate leaves the box DM)
    x      <- f(x, u, p),   S <- df/dx S + df/dp

with the gain gamma(t) = gamma(t-1) / (gamma(t-1) + lambda): a forgetting factor lambda < 1 keeps the gain at
about 1 - lambda, so the estimate tracks a drifting plant (the reason for a recursive method on an ageing
catalyst). Only the parameters listed in ``free`` are estimated; the others stay at ``p0``.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np


class ParametricRPEM:
    """Online (recursive) prediction-error estimation of the free parameters of a CasADi step model.

    Parameters
    ----------
    step : ``casadi.Function`` with inputs (x, u, p) and outputs (x_next, y); y may hold more signals than are
        measured (``output_indices`` selects the measured ones).
    p0 : initial parameter vector (all parameters).
    free : indices of the parameters to estimate (default: all).
    output_indices : indices of y that are measured (default: all).
    forgetting : forgetting factor lambda in (0, 1]; 1 gives the decreasing gain 1/t.
    p_bounds : (lower, upper) box of the free parameters (the model set DM); an update leaving it is rejected.
    R0, Lambda0 : initial R (scalar times identity or matrix) and Lambda (scalar or matrix).
    gamma0 : initial gain.
    """

    def __init__(self, step: Any, p0: Sequence[float], free: Sequence[int] | None = None,
                 output_indices: Sequence[int] | None = None, forgetting: float = 0.999,
                 p_bounds: tuple[Sequence[float], Sequence[float]] | None = None, R0: float | np.ndarray = 100.0,
                 Lambda0: float | np.ndarray = 1.0, gamma0: float = 1.0) -> None:
        self.step = step
        self.p0 = p0
        self.free = free
        self.output_indices = output_indices
        self.forgetting = forgetting
        self.p_bounds = p_bounds
        self.R0 = R0
        self.Lambda0 = Lambda0
        self.gamma0 = gamma0

    def _setup(self, x0: np.ndarray) -> None:
        import casadi as ca

        if not isinstance(self.step, ca.Function) or self.step.n_in() != 3 or self.step.n_out() != 2:
            raise ValueError("step must be a casadi.Function (x, u, p) -> (x_next, y)")
        nx, nu, n_p = (self.step.size1_in(i) for i in range(3))
        p0 = np.asarray(self.p0, dtype=float).ravel()
        if p0.size != n_p or not np.all(np.isfinite(p0)):
            raise ValueError(f"p0 must be {n_p} finite numbers, got {p0.size}")
        free = np.arange(n_p) if self.free is None else np.asarray(self.free, dtype=int)
        if free.size == 0 or free.min() < 0 or free.max() >= n_p or len(set(free.tolist())) != free.size:
            raise ValueError(f"free must be distinct parameter indices in [0, {n_p})")
        ny_all = self.step.size1_out(1)
        out = np.arange(ny_all) if self.output_indices is None else np.asarray(self.output_indices, dtype=int)
        if out.size == 0 or out.min() < 0 or out.max() >= ny_all:
            raise ValueError(f"output_indices must be indices in [0, {ny_all})")
        if not 0.0 < float(self.forgetting) <= 1.0:
            raise ValueError(f"forgetting must be in (0, 1], got {self.forgetting!r}")
        x = ca.SX.sym("x", nx)
        u = ca.SX.sym("u", nu)
        pf = ca.SX.sym("pf", free.size)
        pp = ca.SX.sym("p", n_p)
        # free parameters enter through pf; the rest are the numbers passed in p
        p_expr = ca.vertcat(*[pf[list(free).index(i)] if i in free else pp[i] for i in range(n_p)])
        xn, y = self.step(x, u, p_expr)
        y = y[out.tolist()]
        self._jac = ca.Function("rpem_jac", [x, u, pf, pp],
                                [xn, y, ca.jacobian(xn, x), ca.jacobian(xn, pf), ca.jacobian(y, x),
                                 ca.jacobian(y, pf)])
        self._free = free
        self._out = out
        self.n_params_ = int(free.size)
        self.params_ = p0.copy()
        self.state_ = np.asarray(x0, dtype=float).ravel().copy()
        if self.state_.size != nx:
            raise ValueError(f"x0 must have {nx} elements, got {self.state_.size}")
        if not np.all(np.isfinite(self.state_)):
            raise ValueError("x0 contains NaN or inf")
        nf, ny = free.size, out.size
        self.sensitivity_ = np.zeros((nx, nf))
        self.R_ = np.eye(nf) * self.R0 if np.isscalar(self.R0) else np.asarray(self.R0, dtype=float).copy()
        self.Lambda_ = (np.eye(ny) * self.Lambda0 if np.isscalar(self.Lambda0)
                        else np.asarray(self.Lambda0, dtype=float).copy())
        self.gamma_ = float(self.gamma0)
        if self.p_bounds is not None:
            lo, hi = (np.asarray(b, dtype=float).ravel() for b in self.p_bounds)
            if lo.size != nf or hi.size != nf or np.any(lo > hi):
                raise ValueError(f"p_bounds must be two arrays of {nf} numbers with lower <= upper")
            self._lo, self._hi = lo, hi
        else:
            self._lo, self._hi = np.full(nf, -np.inf), np.full(nf, np.inf)
        self.n_updates_ = 0
        self.n_rejected_ = 0

    def start(self, x0: Sequence[float]) -> ParametricRPEM:
        """Initialise (or restart) the recursion at state ``x0`` with parameters ``p0``."""
        self._setup(np.asarray(x0, dtype=float))
        return self

    def update(self, u: Sequence[float], y: Sequence[float]) -> np.ndarray:
        """Process one sample: input ``u`` applied over the step, measured outputs ``y`` at its end.

        Returns the prediction of the measured outputs made before the update.
        """
        if not hasattr(self, "_jac"):
            raise RuntimeError("call start(x0) before update()")
        u = np.asarray(u, dtype=float).ravel()
        y = np.asarray(y, dtype=float).ravel()
        if not np.all(np.isfinite(u)):
            raise ValueError("u contains NaN or inf")
        if y.size != self._out.size or not np.all(np.isfinite(y)):
            raise ValueError(f"y must be {self._out.size} finite numbers")
        pf = self.params_[self._free]
        xn, yhat, fx, fp, hx, hp = (np.asarray(v) for v in self._jac(self.state_, u, pf, self.params_))
        yhat = yhat.ravel()
        S_next = fx @ self.sensitivity_ + fp
        psi = (hx @ self.sensitivity_ + hp).T  # (n_free, ny)
        eps = y - yhat
        lam = float(self.forgetting)
        self.gamma_ = self.gamma_ / (self.gamma_ + lam)
        g = self.gamma_
        self.Lambda_ = self.Lambda_ + g * (np.outer(eps, eps) - self.Lambda_)
        lam_inv = np.linalg.inv(self.Lambda_)
        self.R_ = self.R_ + g * (psi @ lam_inv @ psi.T - self.R_)
        candidate = pf + g * np.linalg.solve(self.R_, psi @ lam_inv @ eps)
        self.n_updates_ += 1
        if np.all(np.isfinite(candidate)) and np.all(candidate >= self._lo) and np.all(candidate <= self._hi):
            self.params_[self._free] = candidate
        else:
            self.n_rejected_ += 1  # projection onto DM: keep the previous estimate
        self.state_ = xn.ravel()
        self.sensitivity_ = S_next
        return yhat

    def reset_state(self, x0: Sequence[float]) -> ParametricRPEM:
        """Restart the model state at ``x0`` with zero sensitivities, keeping the estimate, R, Lambda and the gain:
        the plant restarted (a new episode from a known state), its parameters did not change."""
        if not hasattr(self, "_jac"):
            raise RuntimeError("call start(x0) before reset_state()")
        x = np.asarray(x0, dtype=float).ravel().copy()
        if x.shape != self.state_.shape or not np.all(np.isfinite(x)):
            raise ValueError(f"x0 must be {self.state_.size} finite numbers, got {np.asarray(x0).tolist()}")
        self.state_ = x
        self.sensitivity_ = np.zeros_like(self.sensitivity_)
        return self

    def clip_params(self, lower: float | Sequence[float], upper: float | Sequence[float]) -> np.ndarray:
        """Clip the parameter estimate (all parameters) to [``lower``, ``upper``] in place and return it: a
        projection onto a box that lets the other parameters move on, where the recursion's ``p_bounds`` reject a
        whole update that leaves the box."""
        if not hasattr(self, "_jac"):
            raise RuntimeError("call start(x0) before clip_params()")
        self.params_[:] = np.clip(self.params_, lower, upper)
        return self.params_

    @property
    def free_params_(self) -> np.ndarray:
        """Current estimate of the free parameters."""
        return self.params_[self._free].copy()
