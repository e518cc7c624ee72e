"""MISO / MIMO output-error model, one rational transfer function per input, like MATLAB ``oe`` (Paper IV's M-II):

    y_j(t) = sum_i B_ji(q) / F_ji(q) u_i(t) + e_j(t)
    B_ji(q) = b_1 q^-nk_i + ... + b_nb q^-(nk_i + nb_i - 1),   F_ji(q) = 1 + f_1 q^-1 + ... + f_nf q^-nf

Each output is a separate MISO model. The parameters minimise the simulation error ``sum (y - yhat)^2`` (zero
initial conditions, as data normalised to zero mean start near rest) by Levenberg-Marquardt
(:func:`~ident.linear._lsq.levenberg_marquardt`, fast on long records) with the exact Jacobian:
``d yhat / d b_k = q^-k u_i / F_i`` and ``d yhat / d f_k = -q^-k yhat_i / F_i``, each one filter pass.

Stability is guaranteed by construction: each F is parametrised by its reflection coefficients
``kappa_m = tanh(eta_m)`` (Schur-Cohn / Levinson step-up recursion), and ``|kappa_m| < 1`` for all m is equivalent to
all roots of F inside the unit circle. The Jacobian is chained through that map analytically.
"""
from __future__ import annotations

from typing import Any

import numpy as np
from scipy.linalg import block_diag
from scipy.signal import lfilter

from ident.io import register_model
from ident.linear._lsq import levenberg_marquardt
from ident.linear._statespace import (
    LinearStateSpaceModel,
    _per_input,
    data_columns,
    tf_to_ss,
    validate_fit_data,
)
from ident.linear.arx import ARX

_KAPPA_MAX = 0.995  # keep initial reflection coefficients off the unit circle so arctanh stays finite


def poly_from_reflection(kappa: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Monic polynomial ``[1, f_1, .., f_n]`` from reflection coefficients, and its Jacobian d f / d kappa
    (shape (n + 1, n)). Step-up: ``a_m[j] = a_{m-1}[j] + kappa_m a_{m-1}[m - j]``."""
    n = len(kappa)
    a = np.zeros(n + 1)
    a[0] = 1.0
    da = np.zeros((n + 1, n))
    for m in range(1, n + 1):
        rev = a[m::-1].copy()          # a_{m-1}[m - j] for j = 0..m (a_{m-1}[m] = 0)
        drev = da[m::-1].copy()
        new = a[:m + 1] + kappa[m - 1] * rev
        dnew = da[:m + 1] + kappa[m - 1] * drev
        dnew[:, m - 1] += rev
        a[:m + 1] = new
        da[:m + 1] = dnew
    return a, da


def reflection_from_poly(f: np.ndarray) -> np.ndarray:
    """Inverse of :func:`poly_from_reflection` (step-down recursion) for a stable monic polynomial."""
    a = np.asarray(f, dtype=float) / f[0]
    n = len(a) - 1
    kappa = np.zeros(n)
    for m in range(n, 0, -1):
        k = a[m]
        if abs(k) >= 1:
            raise ValueError("polynomial is not stable (reflection coefficient outside (-1, 1))")
        kappa[m - 1] = k
        a = (a[:m + 1] - k * a[m::-1]) / (1 - k * k)
        a = a[:m]
    return kappa


def stabilize_poly(f: np.ndarray, max_radius: float = 0.99) -> np.ndarray:
    """Reflect roots of the monic polynomial ``f`` (in q^-1) that lie outside radius ``max_radius`` inside it."""
    if len(f) <= 1:
        return np.asarray(f, dtype=float)
    r = np.roots(f)
    big = np.abs(r) > max_radius
    r[big] = max_radius**2 / np.conj(r[big])
    return np.real(np.poly(r))


def _shift(x: np.ndarray, k: int) -> np.ndarray:
    out = np.zeros_like(x)
    if k < len(x):
        out[k:] = x[:len(x) - k]
    return out


@register_model("oe")
class OutputError(LinearStateSpaceModel):
    """Output-error model with per-input ``B_i / F_i`` (MISO; MIMO as one MISO model per output).

    Parameters
    ----------
    nb, nf, nk : int or sequence of int
        Numerator length, denominator order and input delay (samples), one value or one per input. Paper IV's
        M-II is ``nb = nf = 2, nk = 1`` on four inputs.
    max_nfev : int
        Iteration budget of the optimiser (function evaluations).
    tol : float
        ``ftol``, ``xtol`` and ``gtol`` of the optimiser.

    Attributes
    ----------
    b_ : ndarray, shape (ny, nu, max(nk + nb))
        Numerators in powers of q^-1 including the leading delay zeros.
    f_ : ndarray, shape (ny, nu, max(nf) + 1)
        Monic denominators (zero-padded).
    A_, B_, C_, D_ : ndarray
        Block-diagonal state-space realisation (K_ = 0).
    cost_ : ndarray, shape (ny,)
        Final mean squared simulation error per output on the estimation data.
    """

    _saved_arrays = ("b_", "f_", "cost_")

    def __init__(self, nb: int | tuple[int, ...] = 2, nf: int | tuple[int, ...] = 2,
                 nk: int | tuple[int, ...] = 1, max_nfev: int = 200, tol: float = 1e-8) -> None:
        self.nb = nb
        self.nf = nf
        self.nk = nk
        self.max_nfev = max_nfev
        self.tol = tol

    # ------------------------------------------------------------------------------ single output
    def _simulate(self, theta: np.ndarray, u: np.ndarray, nb: np.ndarray, nf: np.ndarray, nk: np.ndarray,
                  jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        N, nu = u.shape
        yhat = np.zeros(N)
        cols = []
        j = 0
        for i in range(nu):
            b = theta[j:j + nb[i]]
            eta = theta[j + nb[i]:j + nb[i] + nf[i]]
            j += nb[i] + nf[i]
            f, df_dk = poly_from_reflection(np.tanh(eta))
            num = np.concatenate([np.zeros(nk[i]), b])
            yi = lfilter(num, f, u[:, i])
            yhat += yi
            if jac:
                uf = lfilter([1.0], f, u[:, i])
                cols += [_shift(uf, nk[i] + k) for k in range(nb[i])]
                if nf[i]:
                    yf = lfilter([1.0], f, yi)
                    dy_df = np.column_stack([-_shift(yf, k) for k in range(1, nf[i] + 1)])
                    dk_deta = 1.0 - np.tanh(eta) ** 2
                    cols += list((dy_df @ df_dk[1:] * dk_deta).T)
        return yhat, (np.column_stack(cols) if jac else None)

    def _init_theta(self, u: np.ndarray, y: np.ndarray, nb: np.ndarray, nf: np.ndarray, nk: np.ndarray
                    ) -> np.ndarray:
        # ARX with a common denominator of order max(nf) gives B_i and a stable-ised F shared by all inputs;
        # the output-error iterations then separate the F_i.
        na = int(nf.max())
        try:
            arx = ARX(na=na, nb=tuple(nb.tolist()), nk=tuple(nk.tolist()), ridge=1e-8).fit(u, y)
        except ValueError as err:
            raise ValueError(f"cannot fit the output-error model: its initial estimate, an ARX model with na = "
                             f"max(nf) = {na} and the same nb, nk, failed: {err}") from err
        f_common = stabilize_poly(np.concatenate([[1.0], arx.a_[:, 0, 0]]), 0.95)
        theta = []
        for i in range(u.shape[1]):
            theta += [arx.b_[k, 0, i] for k in range(nk[i], nk[i] + nb[i])]
            if nf[i]:
                f_i = f_common[:nf[i] + 1] if nf[i] <= na else np.concatenate([f_common, np.zeros(nf[i] - na)])
                f_i = stabilize_poly(f_i, 0.95)
                kappa = np.clip(reflection_from_poly(f_i), -_KAPPA_MAX, _KAPPA_MAX)
                theta += list(np.arctanh(kappa))
        return np.asarray(theta, dtype=float)

    def fit(self, u: Any, y: Any) -> OutputError:
        """Minimise the simulation error for each output separately; returns ``self``."""
        nu_guess, _ = data_columns(u, y, "output-error model")
        nb = _per_input(self.nb, nu_guess, "nb")
        nf = _per_input(self.nf, nu_guess, "nf")
        nk = _per_input(self.nk, nu_guess, "nk")
        n_par = int(nb.sum() + nf.sum())
        if n_par == 0 or not np.any(nb):
            raise ValueError("the output-error model has no numerator coefficients (nb = 0)")
        u, y = validate_fit_data(u, y, n_par, int(max(nk + nb)), "output-error model")
        _N, nu = u.shape
        ny = y.shape[1]
        lb = int(max(nk + nb))
        lf = int(nf.max()) + 1
        self.b_ = np.zeros((ny, nu, lb))
        self.f_ = np.zeros((ny, nu, lf))
        self.cost_ = np.zeros(ny)
        for j in range(ny):
            yj = y[:, j]
            theta0 = self._init_theta(u, yj, nb, nf, nk)
            res = levenberg_marquardt(lambda th, yj=yj: yj - self._simulate(th, u, nb, nf, nk, False)[0],
                                      lambda th: -self._simulate(th, u, nb, nf, nk, True)[1], theta0,
                                      max_nfev=self.max_nfev, ftol=self.tol, xtol=self.tol, gtol=self.tol)
            th = res.x
            self.cost_[j] = float(np.mean(res.fun**2))
            k = 0
            for i in range(nu):
                self.b_[j, i, nk[i]:nk[i] + nb[i]] = th[k:k + nb[i]]
                f, _ = poly_from_reflection(np.tanh(th[k + nb[i]:k + nb[i] + nf[i]]))
                self.f_[j, i, :nf[i] + 1] = f
                k += nb[i] + nf[i]
        self._realise()
        return self

    def _n_params(self) -> int:
        nu = self.b_.shape[1]
        return int(self.b_.shape[0] * (_per_input(self.nb, nu, "nb").sum() + _per_input(self.nf, nu, "nf").sum()))

    def _realise(self) -> None:
        ny, nu = self.b_.shape[:2]
        blocks = []  # (A_i, B_i, C_i, D_i, j, i)
        for j in range(ny):
            for i in range(nu):
                blocks.append((*tf_to_ss(self.b_[j, i], self.f_[j, i]), j, i))
        A = block_diag(*[blk[0] for blk in blocks]) if blocks else np.zeros((0, 0))
        n = A.shape[0]
        B = np.zeros((n, nu))
        C = np.zeros((ny, n))
        D = np.zeros((ny, nu))
        o = 0
        for Ai, Bi, Ci, Di, j, i in blocks:
            m = Ai.shape[0]
            B[o:o + m, i] = Bi[:, 0]
            C[j, o:o + m] = Ci[0]
            D[j, i] = Di[0, 0]
            o += m
        self.A_, self.B_, self.C_, self.D_ = A, B, C, D
        self.K_ = np.zeros((n, ny))

    def transfer_functions(self) -> list[list[tuple[np.ndarray, np.ndarray]]]:
        """``[[(num, den), ...per input], ...per output]`` in powers of q^-1."""
        return [[(self.b_[j, i].copy(), self.f_[j, i].copy()) for i in range(self.b_.shape[1])]
                for j in range(self.b_.shape[0])]
