"""MIMO ARX model estimated by linear least squares.

    y(t) + A_1 y(t-1) + ... + A_na y(t-na) = sum_i sum_{k=nk_i}^{nk_i+nb_i-1} b_{i,k} u_i(t-k) + e(t)

``A_k`` are full ny x ny matrices (each output regressed on the past of every output); ``b_{i,k}`` are ny-vectors.
The least-squares estimate minimises the one-step prediction error, so it is consistent when the disturbance
really enters as white equation error, and biased for output-error noise (then use :class:`~ident.linear.oe.
OutputError`).

Realisation: the non-minimal state ``x(t) = [y(t-1) .. y(t-na), u(t-1) .. u(t-d)]`` with ``K`` writing the
innovation into the ``y(t-1)`` slot, so :meth:`predict_k_step` with k = 1 is exactly the ARX predictor.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ident.io import register_model
from ident.linear._statespace import LinearStateSpaceModel, _per_input, data_columns, validate_fit_data


@register_model("arx")
class ARX(LinearStateSpaceModel):
    """ARX model, MIMO, least squares.

    Parameters
    ----------
    na : int
        Number of past outputs (>= 0).
    nb : int or sequence of int
        Number of coefficients per input (one value for all inputs, or one per input).
    nk : int or sequence of int
        Input delay in samples per input (0 gives a direct feedthrough).
    ridge : float
        Tikhonov regularisation weight on the coefficients (0: plain least squares), in units of the regressor
        variance; useful for poorly excited local models.

    Attributes
    ----------
    a_ : ndarray, shape (na, ny, ny)
        ``A_1 .. A_na``.
    b_ : ndarray, shape (d + 1, ny, nu)
        ``b_[k][:, i]`` is the coefficient of ``u_i(t - k)`` (zero outside ``nk_i .. nk_i + nb_i - 1``).
    A_, B_, C_, D_, K_ : ndarray
        State-space realisation (see module docstring).
    noise_variance_ : ndarray, shape (ny,)
        Variance of the least-squares residuals.
    """

    _saved_arrays = ("a_", "b_", "noise_variance_")

    def __init__(self, na: int = 2, nb: int | tuple[int, ...] = 2, nk: int | tuple[int, ...] = 1,
                 ridge: float = 0.0) -> None:
        self.na = na
        self.nb = nb
        self.nk = nk
        self.ridge = ridge

    def _orders(self, nu: int) -> tuple[int, np.ndarray, np.ndarray, int]:
        if int(self.na) != self.na or self.na < 0:
            raise ValueError(f"na must be a non-negative integer, got {self.na}")
        nb = _per_input(self.nb, nu, "nb")
        nk = _per_input(self.nk, nu, "nk")
        d = int(max(np.max(np.where(nb > 0, nk + nb - 1, 0)), 0))
        return int(self.na), nb, nk, d

    @staticmethod
    def regressors(u: np.ndarray, y: np.ndarray, na: int, nb: np.ndarray, nk: np.ndarray, start: int
                   ) -> np.ndarray:
        """Regressor matrix rows t = start .. N-1: ``[-y(t-1) .. -y(t-na), u_i(t-nk_i) .. ]`` (y blocks by lag,
        then per input the lags in increasing order)."""
        N = u.shape[0]
        cols = [-y[start - k:N - k] for k in range(1, na + 1)]
        for i in range(u.shape[1]):
            cols += [u[start - k:N - k, i:i + 1] for k in range(nk[i], nk[i] + nb[i])]
        return np.hstack(cols) if cols else np.zeros((N - start, 0))

    def fit(self, u: Any, y: Any, sample_weight: Any = None) -> ARX:
        """Least-squares estimate.

        Parameters
        ----------
        u : array_like, shape (N, nu)
        y : array_like, shape (N, ny)
        sample_weight : array_like, shape (N,), optional
            Non-negative weights per sample (weighted least squares, used by the local models of
            :mod:`ident.multiple_model`).
        """
        nu_data, ny_data = data_columns(u, y, "ARX model")
        na, nb, nk, d = self._orders(nu_data)
        lag = max(na, d)
        n_par = na * ny_data + int(nb.sum())
        if n_par == 0:
            raise ValueError("the ARX model has no coefficients (na = 0 and nb = 0)")
        u, y = validate_fit_data(u, y, n_par, lag, "ARX model")
        N, nu = u.shape
        ny = y.shape[1]
        phi = self.regressors(u, y, na, nb, nk, lag)
        target = y[lag:]
        w = np.ones(N - lag) if sample_weight is None else np.asarray(sample_weight, dtype=float).ravel()[lag:]
        if w.shape != (N - lag,) or np.any(w < 0) or not np.all(np.isfinite(w)):
            raise ValueError("sample_weight must be finite, non-negative, one value per sample")
        sw = np.sqrt(w)[:, None]
        lhs = phi * sw
        rhs = target * sw
        if self.ridge > 0:
            scale = np.sqrt(self.ridge * max(np.sum(w), 1.0)) * np.maximum(phi.std(axis=0), 1e-12)
            lhs = np.vstack([lhs, np.diag(scale)])
            rhs = np.vstack([rhs, np.zeros((phi.shape[1], ny))])
        theta, *_ = np.linalg.lstsq(lhs, rhs, rcond=None)
        if np.linalg.matrix_rank(lhs) < phi.shape[1]:
            raise ValueError(self._rank_message(phi * sw, w, na * ny, nb, nk))
        resid = target - phi @ theta
        self.noise_variance_ = np.average(resid**2, axis=0, weights=w) if w.sum() > 0 else resid.var(axis=0)
        a = np.zeros((na, ny, ny))
        for k in range(na):
            a[k] = theta[k * ny:(k + 1) * ny].T
        b = np.zeros((d + 1, ny, nu))
        j = na * ny
        for i in range(nu):
            for k in range(nk[i], nk[i] + nb[i]):
                b[k, :, i] = theta[j]
                j += 1
        self.a_, self.b_ = a, b
        self._realise()
        return self

    def _rank_message(self, lhs: np.ndarray, w: np.ndarray, n_y_cols: int, nb: np.ndarray, nk: np.ndarray) -> str:
        """Why the weighted regression ``lhs`` (past outputs first, then lagged inputs) is rank deficient."""
        n_cols = lhs.shape[1]
        n_weighted = int(np.count_nonzero(w > 0))
        if n_weighted < n_cols:
            cause = (f"the sample weights leave {n_weighted} weighted samples for {n_cols} coefficients per output")
        elif np.linalg.matrix_rank(lhs[:, n_y_cols:]) < n_cols - n_y_cols:
            cause = (f"the inputs u are not persistently exciting for these orders (nb = {nb.tolist()}, "
                     f"nk = {nk.tolist()})")
        else:
            cause = (f"the past outputs are linearly dependent on each other and the lagged inputs: y is (nearly) "
                     f"constant, or (nearly) noise-free data are fitted with more past outputs (na = {self.na}) "
                     "than their order needs")
        return f"cannot fit the ARX model: its least-squares regression is rank deficient: {cause}"

    def _n_params(self) -> int:
        ny = self.C_.shape[0]
        nb = _per_input(self.nb, self.B_.shape[1], "nb")
        return int(self.na) * ny * ny + int(nb.sum()) * ny

    def _realise(self) -> None:
        a, b = self.a_, self.b_
        na, ny = a.shape[0], b.shape[1]
        d, nu = b.shape[0] - 1, b.shape[2]
        n = na * ny + d * nu
        if n == 0:
            raise ValueError("a static ARX model (na = 0, no delayed inputs) has no state-space realisation")
        C = np.hstack([-a[k] for k in range(na)] + [b[k] for k in range(1, d + 1)]) if n else np.zeros((ny, 0))
        D = b[0].copy()
        A = np.zeros((n, n))
        B = np.zeros((n, nu))
        K = np.zeros((n, ny))
        if na:
            A[:ny] = C
            B[:ny] = D
            K[:ny] = np.eye(ny)
            A[ny:na * ny, :(na - 1) * ny] = np.eye((na - 1) * ny)
        if d:
            o = na * ny
            B[o:o + nu] = np.eye(nu)
            A[o + nu:o + d * nu, o:o + (d - 1) * nu] = np.eye((d - 1) * nu)
        self.A_, self.B_, self.C_, self.D_, self.K_ = A, B, C, D, K
