"""Subspace identification of a state-space model (N4SID family, Van Overschee and De Moor 1996), in numpy.

Steps, with block Hankel matrices of ``i`` past and ``i`` future block rows (``horizon``):

1. Oblique projection of the future outputs along the future inputs onto the past data,
   ``O_i = Y_f /_{U_f} W_p`` with ``W_p = [U_p; Y_p]`` (a least-squares regression of Y_f on [W_p; U_f], keeping
   the W_p part).
2. SVD of the weighted projection ``W1 O_i W2``; the ``order`` dominant directions give the extended observability
   matrix ``Gamma_i = W1^-1 U_1 S_1^(1/2)`` (``weighting``: "n4sid" W1 = W2 = I; "moesp" W2 = projection onto the
   orthogonal complement of U_f; "cva" additionally W1 = (Y_f Pi Y_f^T)^-1/2, canonical correlations).
3. State sequence ``X_i = Gamma_i^+ O_i``; (A, B, C, D) by least squares on ``[x(t+1); y(t)] = [A B; C D]
   [x(t); u(t)]`` over consecutive columns; the residual covariances give the Kalman gain K from the Riccati
   equation (innovation form).
4. A is made stable if needed (eigenvalue reflection), then B, D and x0 are re-estimated by linear least squares
   on the *simulation* error for the fixed (A, C), which is exact because the output is linear in (B, D, x0).
"""
from __future__ import annotations

from typing import Any, Literal

import numpy as np
from scipy.linalg import solve_discrete_are

from ident.io import register_model
from ident.linear._statespace import (
    LinearStateSpaceModel,
    data_columns,
    spectral_radius,
    ss_sensitivities,
    stabilize,
    validate_fit_data,
)


def _hankel(x: np.ndarray, rows: int, cols: int, start: int = 0) -> np.ndarray:
    """Block Hankel matrix with ``rows`` block rows: block row r holds x(start + r .. start + r + cols - 1)."""
    m = x.shape[1]
    H = np.empty((rows * m, cols))
    for r in range(rows):
        H[r * m:(r + 1) * m] = x[start + r:start + r + cols].T
    return H


def _project_out(M: np.ndarray, U: np.ndarray) -> np.ndarray:
    """``M Pi_{U^perp}``: remove from the rows of M their projection on the row space of U."""
    coef, *_ = np.linalg.lstsq(U.T, M.T, rcond=None)
    return M - (U.T @ coef).T


def _inv_sqrt(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w, V = np.linalg.eigh((S + S.T) / 2)
    w = np.maximum(w, 1e-12 * max(w.max(), 1e-300))
    return (V / np.sqrt(w)) @ V.T, (V * np.sqrt(w)) @ V.T


def kalman_gain(A: np.ndarray, C: np.ndarray, Q: np.ndarray, R: np.ndarray, S: np.ndarray) -> np.ndarray:
    """Steady-state predictor gain ``K = (A P C' + S)(C P C' + R)^-1`` from the filtering Riccati equation; zero if
    the equation has no stabilising solution."""
    try:
        P = solve_discrete_are(A.T, C.T, Q, R, s=S)
        K = (A @ P @ C.T + S) @ np.linalg.inv(C @ P @ C.T + R)
        if not np.all(np.isfinite(K)) or spectral_radius(A - K @ C) >= 1:
            raise np.linalg.LinAlgError
        return K
    except (np.linalg.LinAlgError, ValueError):
        return np.zeros((A.shape[0], C.shape[0]))


def refine_bd_x0(A: np.ndarray, C: np.ndarray, u: np.ndarray, y: np.ndarray, feedthrough: bool
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares (B, D, x0) minimising the simulation error for fixed (A, C)."""
    n, ny, nu = A.shape[0], C.shape[0], u.shape[1]
    B0 = np.zeros((n, nu))
    D0 = np.zeros((ny, nu))
    free = {"D": feedthrough, "x0": True}
    _, J = ss_sensitivities(A, B0, C, D0, None, u, None, np.zeros(n), free)
    # columns: vec A (n*n), vec B, vec C, [vec D], x0; output is linear in B, D, x0 with these sensitivities
    cols = np.r_[n * n:n * n + n * nu, n * n + n * nu + ny * n:J.shape[2]]
    Jr = J[:, :, cols].reshape(-1, cols.size)
    theta, *_ = np.linalg.lstsq(Jr, y.ravel(), rcond=None)
    B = theta[:n * nu].reshape(n, nu)
    D = theta[n * nu:n * nu + ny * nu].reshape(ny, nu) if feedthrough else D0
    x0 = theta[-n:]
    return B, D, x0


@register_model("n4sid")
class N4SID(LinearStateSpaceModel):
    """Subspace state-space identification.

    Parameters
    ----------
    order : int
        State dimension n.
    horizon : int, optional
        Number of past (= future) block rows i; must exceed ``order / n_outputs``. Default ``max(2 order, 10)``.
    weighting : {"moesp", "n4sid", "cva"}
        SVD weighting (see module docstring).
    feedthrough : bool
        Estimate D (False: D = 0, a strictly proper model as MATLAB's default).
    estimate_k : bool
        Estimate the Kalman gain K for k-step prediction (False: K = 0, output-error form).
    refine : bool
        Re-estimate B, D, x0 on the simulation error (step 4).

    Attributes
    ----------
    A_, B_, C_, D_, K_ : ndarray
        Innovation-form model.
    x0_ : ndarray, shape (n,)
        Initial state for the estimation data.
    singular_values_ : ndarray
        Singular values of the weighted projection (look for the gap to choose the order).
    """

    _saved_arrays = ("singular_values_",)

    def __init__(self, order: int = 2, horizon: int | None = None,
                 weighting: Literal["moesp", "n4sid", "cva"] = "moesp", feedthrough: bool = False,
                 estimate_k: bool = True, refine: bool = True) -> None:
        self.order = order
        self.horizon = horizon
        self.weighting = weighting
        self.feedthrough = feedthrough
        self.estimate_k = estimate_k
        self.refine = refine

    def fit(self, u: Any, y: Any) -> N4SID:
        n = int(self.order)
        if n < 1 or n != self.order:
            raise ValueError(f"order must be a positive integer, got {self.order}")
        if self.weighting not in ("moesp", "n4sid", "cva"):
            raise ValueError(f"weighting must be 'moesp', 'n4sid' or 'cva', got {self.weighting!r}")
        i = int(self.horizon) if self.horizon is not None else max(2 * n, 10)
        nu, ny = data_columns(u, y, f"subspace model (horizon {i})")
        if i * ny < n + 1:
            raise ValueError(f"horizon {i} too short for order {n} with {ny} output(s): need horizon * ny > order")
        n_rows = 2 * i * (nu + ny)
        u, y = validate_fit_data(u, y, n_rows, 2 * i, f"subspace model (horizon {i})")
        N = u.shape[0]
        j = N - 2 * i + 1
        U = _hankel(u, 2 * i, j)
        Y = _hankel(y, 2 * i, j)
        Up, Uf = U[:i * nu], U[i * nu:]
        Yp, Yf = Y[:i * ny], Y[i * ny:]
        Wp = np.vstack([Up, Yp])
        Z = np.vstack([Wp, Uf])
        coef, *_ = np.linalg.lstsq(Z.T, Yf.T, rcond=None)
        Lw = coef[:Wp.shape[0]].T
        O = Lw @ Wp
        if self.weighting == "n4sid":
            M, W1inv = O, None
        else:
            M = _project_out(O, Uf)
            W1inv = None
            if self.weighting == "cva":
                Yf_perp = _project_out(Yf, Uf)
                W1, W1inv = _inv_sqrt(Yf_perp @ Yf_perp.T / j)
                M = W1 @ M
        Us, s, _ = np.linalg.svd(M, full_matrices=False)
        self.singular_values_ = s
        gamma = Us[:, :n] * np.sqrt(s[:n])
        if W1inv is not None:
            gamma = W1inv @ gamma
        X = np.linalg.pinv(gamma) @ O  # x(i .. i + j - 1)
        Xc, Xn = X[:, :-1], X[:, 1:]
        uc = u[i:i + j - 1].T
        yc = y[i:i + j - 1].T
        reg = np.vstack([Xc, uc])
        AB, *_ = np.linalg.lstsq(reg.T, Xn.T, rcond=None)
        AB = AB.T
        A, B = AB[:, :n], AB[:, n:]
        if self.feedthrough:
            CD, *_ = np.linalg.lstsq(reg.T, yc.T, rcond=None)
            C, D = CD.T[:, :n], CD.T[:, n:]
        else:
            Ct, *_ = np.linalg.lstsq(Xc.T, yc.T, rcond=None)
            C, D = Ct.T, np.zeros((ny, nu))
        W = Xn - A @ Xc - B @ uc
        V = yc - C @ Xc - D @ uc
        if spectral_radius(A) >= 0.999:
            A = stabilize(A, 0.999)
        x0 = np.zeros(n)
        if self.refine:
            B, D, x0 = refine_bd_x0(A, C, u, y, self.feedthrough)
        if self.estimate_k:
            cov = np.cov(np.vstack([W, V])) if W.shape[1] > 1 else np.eye(n + ny)
            K = kalman_gain(A, C, cov[:n, :n], cov[n:, n:] + 1e-12 * np.eye(ny), cov[:n, n:])
        else:
            K = np.zeros((n, ny))
        self.A_, self.B_, self.C_, self.D_, self.K_, self.x0_ = A, B, C, D, K, x0
        return self

    def _n_params(self) -> int:
        n, nu, ny = self.A_.shape[0], self.B_.shape[1], self.C_.shape[0]
        # free parameters of an observable canonical form: n (ny + nu) + ny nu [D] + n ny [K]
        return n * (ny + nu) + (ny * nu if self.feedthrough else 0) + (n * ny if self.estimate_k else 0)
