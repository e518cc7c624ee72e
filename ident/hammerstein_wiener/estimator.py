"""The Hammerstein-Wiener estimator (Paper IV's M-III, M-IV, M-V): static input blocks, per-input transfer functions,
a static output block

    v_i(t) = g_i(u_i(t); p_i)                         i = 1..n_inputs      (Hammerstein part)
    w(t)   = sum_i B_i(q) / F_i(q) v_i(t)                                  (M-II's linear block)
    y(t)   = h(w(t); p_h)                                                   (Wiener part)

``B_i(q) = b_i1 q^-nk_i + ... + b_i,nb q^-(nk_i + nb_i - 1)`` and ``F_i(q) = 1 + f_i1 q^-1 + ... + f_i,nf q^-nf``,
F_i parametrised by reflection coefficients ``tanh(eta)`` so every estimate is stable (as
:class:`~ident.linear.OutputError`).

Fit: the simulation error ``sum_t (y(t) - yhat(t))^2`` (zero initial state, as the output-error fit) is minimised
by ``scipy.optimize.least_squares`` with the exact Jacobian, every column from one linear filter pass:
``dyhat/dtheta = h'(w) dw/dtheta`` with ``dw/dp_i = B_i/F_i [dg_i/dp_i]``, ``dw/db_ik = q^-(nk+k) F_i^-1 v_i``,
``dw/df_ik = -q^-k F_i^-1 w_i`` (chained through the reflection map), plus ``dh/dp_h``. The start is the best
linear model: an :class:`~ident.linear.OutputError` fit from the inputs through the initial static blocks
(identity-like) to y. A small ridge term ``regularization * sum ((p - p0) / max(|p0|, 1))^2`` on the static
parameters removes the gain and offset ambiguity between the static blocks and the linear block (a piecewise-linear
input block scaled by c and B_i by 1/c give the same output).

Options against overfitting flexible input blocks (Paper IV's M-V):

* ``smoothness``: a penalty ``smoothness * N * sum_blocks ||R p||^2`` on the blocks' ``roughness_matrix`` (for a
  piecewise-linear block the changes of slope at its inner knots), i.e. ``smoothness`` per unit of mean squared
  error; it pulls every block toward a straight line, which the linear block can absorb. A sequence of values is a
  grid: each is fitted on the first ``1 - holdout`` of the estimation data and scored by the simulated FIT on the
  rest (simulated from the start, so the hold-out continues the fitted record), the best is refitted on all of it
  (``smoothness_``, ``holdout_scores_``). Nothing outside the data passed to ``fit`` is used.
* ``init_model`` may be a fitted :class:`~ident.linear.OutputError` or :class:`HammersteinWiener` on the same inputs,
  or an *unfitted* :class:`HammersteinWiener` template, which is then fitted first on the data passed to ``fit``
  (also on the inner split of the hold-out selection): e.g. M-V started from M-IV, a Wiener model on the same
  inputs, so the start is M-IV itself (identity-like piecewise-linear blocks) and the fit can only improve on it.
* block bounds (``StaticNonlinearity.bounds``, e.g. ``PiecewiseLinear(monotone=True)``) are honoured.

Special cases: :func:`wiener` (identity inputs) and :func:`hammerstein` (identity output).
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from scipy.linalg import block_diag
from scipy.optimize import least_squares
from scipy.signal import lfilter

from ident.base import as_2d, check_is_fitted, check_same_length
from ident.hammerstein_wiener.blocks import Identity, StaticNonlinearity, block_from_dict
from ident.io import load_model, register_model, save_model
from ident.linear import OutputError
from ident.linear._statespace import _per_input, simulate_ss, tf_to_ss, validate_fit_data
from ident.linear.oe import _KAPPA_MAX, poly_from_reflection, reflection_from_poly, stabilize_poly

__all__ = ["HammersteinWiener", "hammerstein", "wiener"]


def _shift(x: np.ndarray, k: int) -> np.ndarray:
    out = np.zeros_like(x)
    if k < len(x):
        out[k:] = x[:len(x) - k]
    return out


@register_model("hammerstein_wiener")
class HammersteinWiener:
    """Hammerstein-Wiener model with one static block per input, per-input ``B_i/F_i`` and one output block (MISO).

    Parameters
    ----------
    input_blocks : sequence of StaticNonlinearity, optional
        One block per input (see :mod:`ident.hammerstein_wiener.blocks`); default: identity on every input.
        The blocks given are templates: ``fit`` works on copies (``input_blocks_``).
    output_block : StaticNonlinearity, optional
        The output block h (default identity), e.g. ``Saturation(lower=w_min)``.
    nb, nf, nk : int or sequence of int
        Numerator length, denominator order and delay of each ``B_i/F_i`` (Paper IV: 2, 2, 1).
    regularization : float
        Weight of the ridge term on the static parameters (see module docstring; 0 switches it off).
    max_nfev : int
        Iteration budget of ``least_squares``.
    tol : float
        ``ftol``, ``xtol`` and ``gtol`` of ``least_squares``.
    init_model : OutputError, optional
        A fitted output-error model (same inputs, orders) to start the linear block from, instead of fitting one
        on the inputs passed through the initial static blocks. Also a fitted HammersteinWiener (its linear block is
        used), or an unfitted HammersteinWiener template, fitted first on the data given to ``fit``.
    smoothness : float or sequence of float
        Weight of the roughness penalty on the static blocks (see module docstring); a sequence is a grid chosen by
        the hold-out inside the estimation data.
    holdout : float
        Fraction of the estimation data (its end) held out to choose ``smoothness`` from a grid.

    Attributes
    ----------
    input_blocks_ : list of StaticNonlinearity
    input_params_ : list of ndarray
        Parameters of each input block.
    output_block_ : StaticNonlinearity
    output_params_ : ndarray
    b_ : ndarray, shape (n_inputs, max(nk + nb))
        Numerators in powers of q^-1 (leading delay zeros included).
    f_ : ndarray, shape (n_inputs, max(nf) + 1)
        Monic denominators.
    A_, B_, C_, D_ : ndarray
        State-space realisation of the linear block (input v, output w); its state is the model state.
    cost_, initial_cost_ : float
        Mean squared simulation error on the estimation data after the fit and at the start.
    smoothness_ : float
        The smoothness weight used (chosen from the grid when ``smoothness`` is a sequence).
    holdout_scores_ : dict
        Hold-out FIT (%) per grid value (empty when ``smoothness`` is a single value).
    """

    def __init__(self, input_blocks: Sequence[StaticNonlinearity] | None = None,
                 output_block: StaticNonlinearity | None = None, nb: int | Sequence[int] = 2,
                 nf: int | Sequence[int] = 2, nk: int | Sequence[int] = 1, regularization: float = 1e-3,
                 max_nfev: int = 200, tol: float = 1e-8,
                 init_model: OutputError | HammersteinWiener | None = None,
                 smoothness: float | Sequence[float] = 0.0, holdout: float = 0.25) -> None:
        self.input_blocks = input_blocks
        self.output_block = output_block
        self.nb = nb
        self.nf = nf
        self.nk = nk
        self.regularization = regularization
        self.max_nfev = max_nfev
        self.tol = tol
        self.init_model = init_model
        self.smoothness = smoothness
        self.holdout = holdout

    # ------------------------------------------------------------------------------------------- helpers
    def get_params(self) -> dict[str, Any]:
        """Constructor arguments as stored (scikit-learn convention)."""
        return {k: getattr(self, k) for k in ("input_blocks", "output_block", "nb", "nf", "nk", "regularization",
                                              "max_nfev", "tol", "init_model", "smoothness", "holdout")}

    def __repr__(self) -> str:
        return f"HammersteinWiener(input_blocks={self.input_blocks!r}, output_block={self.output_block!r}, " \
               f"nb={self.nb!r}, nf={self.nf!r}, nk={self.nk!r})"

    def _orders(self, nu: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return _per_input(self.nb, nu, "nb"), _per_input(self.nf, nu, "nf"), _per_input(self.nk, nu, "nk")

    def _unpack(self, theta: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray],
                                                  np.ndarray]:
        """theta -> (input params per block, b per input, eta per input, output params), fixed ones filled in."""
        j = 0
        p_in = []
        for blk, p0 in zip(self._blocks, self._p0_in):
            m = blk.n_free()
            p_in.append(theta[j:j + m] if m else p0)
            j += m
        bs, etas = [], []
        for i in range(len(self._blocks)):
            bs.append(theta[j:j + self._nb[i]])
            j += self._nb[i]
            etas.append(theta[j:j + self._nf[i]])
            j += self._nf[i]
        m = self._out.n_free()
        p_out = theta[j:j + m] if m else self._p0_out
        return p_in, bs, etas, p_out

    def _simulate(self, theta: np.ndarray, u: np.ndarray, jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        p_in, bs, etas, p_out = self._unpack(theta)
        N = u.shape[0]
        w = np.zeros(N)
        cols_static: list[np.ndarray] = []
        cols_lin: list[np.ndarray] = []
        for i, blk in enumerate(self._blocks):
            v = blk.value(u[:, i], p_in[i])
            f, df_dk = poly_from_reflection(np.tanh(etas[i]))
            num = np.concatenate([np.zeros(self._nk[i]), bs[i]])
            wi = lfilter(num, f, v)
            w += wi
            if not jac:
                continue
            if blk.n_free():
                cols_static.append(lfilter(num, f, blk.dp(u[:, i], p_in[i]), axis=0))
            vf = lfilter([1.0], f, v)
            cols_lin += [_shift(vf, self._nk[i] + k)[:, None] for k in range(self._nb[i])]
            if self._nf[i]:
                wf = lfilter([1.0], f, wi)
                dw_df = np.column_stack([-_shift(wf, k) for k in range(1, self._nf[i] + 1)])
                cols_lin.append(dw_df @ df_dk[1:] * (1.0 - np.tanh(etas[i]) ** 2))
        y = self._out.value(w, p_out)
        if not jac:
            return y, None
        dw = np.concatenate(cols_static + cols_lin, axis=1)
        J = self._out.dx(w, p_out)[:, None] * dw
        if self._out.n_free():
            J = np.concatenate([J, self._out.dp(w, p_out)], axis=1)
        return y, J

    # ----------------------------------------------------------------------------------------------- fit
    def fit(self, u: Any, y: Any) -> HammersteinWiener:
        """Minimise the simulation error from the best linear start; returns ``self``.

        Raises ``ValueError`` for NaN/inf, mismatched lengths, constant inputs, more than one output, a wrong
        number of input blocks or too few samples.
        """
        grid = np.atleast_1d(np.asarray(self.smoothness, dtype=float))
        if grid.ndim != 1 or grid.size == 0 or np.any(~np.isfinite(grid)) or np.any(grid < 0):
            raise ValueError(f"smoothness must be a non-negative number or a sequence of them, got "
                             f"{self.smoothness!r}")
        scores: dict[float, float] = {}
        if np.ndim(self.smoothness) > 0 and grid.size > 1:
            if not 0.0 < float(self.holdout) < 1.0:
                raise ValueError(f"holdout must be in (0, 1), got {self.holdout!r}")
            u_all, y_all = as_2d("u", u), as_2d("y", y)
            n = check_same_length(u=u_all, y=y_all)
            n_in = round(n * (1.0 - float(self.holdout)))
            for lam in grid:
                inner = HammersteinWiener(**{**self.get_params(), "smoothness": float(lam)})
                try:
                    inner._fit_once(u_all[:n_in], y_all[:n_in], float(lam))
                    y_hat = inner.predict(u_all)[n_in:, 0]
                    y_ho = y_all[n_in:, 0]
                    score = 100.0 * (1.0 - np.linalg.norm(y_ho - y_hat) / np.linalg.norm(y_ho - y_ho.mean()))
                except (ValueError, np.linalg.LinAlgError):
                    score = -np.inf
                scores[float(lam)] = float(score) if np.isfinite(score) else -np.inf
            best = max(scores, key=lambda k: (scores[k], k))  # ties: the smoother
        else:
            best = float(grid[0])
        self._fit_once(u, y, best)
        self.smoothness_ = best
        self.holdout_scores_ = scores
        return self

    def _fit_once(self, u: Any, y: Any, smoothness: float) -> HammersteinWiener:
        u_arr, yv, th0 = self._prepare(u, y)
        nu = u_arr.shape[1]
        # ridge rows on the free static parameters (input blocks first, output block last)
        n_in_free = sum(b.n_free() for b in self._blocks)
        idx_arr = np.asarray(list(range(n_in_free)) + list(range(th0.size - self._out.n_free(), th0.size)),
                             dtype=int)
        ref = th0[idx_arr]
        wts = np.sqrt(max(float(self.regularization), 0.0)) / np.maximum(np.abs(ref), 1.0)
        use_reg = self.regularization > 0 and idx_arr.size > 0
        # roughness rows: sqrt(smoothness * N) * R_i p_i for every free input block that has a roughness measure
        rough_rows: list[np.ndarray] = []
        lo, hi = np.full(th0.size, -np.inf), np.full(th0.size, np.inf)
        j = 0
        for blk in self._blocks:
            m = blk.n_free()
            if m:
                lo[j:j + m], hi[j:j + m] = blk.bounds()
                R = blk.roughness_matrix() if smoothness > 0 else None
                if R is not None and R.size:
                    rows = np.zeros((R.shape[0], th0.size))
                    rows[:, j:j + m] = np.sqrt(smoothness * yv.size) * R
                    rough_rows.append(rows)
            j += m
        if self._out.n_free():
            lo[-self._out.n_free():], hi[-self._out.n_free():] = self._out.bounds()
        Rr = np.vstack(rough_rows) if rough_rows else np.zeros((0, th0.size))
        th0 = np.clip(th0, lo, hi)

        def resid(th: np.ndarray) -> np.ndarray:
            e = yv - self._simulate(th, u_arr, False)[0]
            parts = [e, Rr @ th]
            if use_reg:
                parts.append(wts * (th[idx_arr] - ref))
            return np.concatenate(parts)

        def jac(th: np.ndarray) -> np.ndarray:
            J = [-self._simulate(th, u_arr, True)[1], Rr]
            if use_reg:
                R = np.zeros((idx_arr.size, th.size))
                R[np.arange(idx_arr.size), idx_arr] = wts
                J.append(R)
            return np.vstack(J)

        self.initial_cost_ = float(np.mean((yv - self._simulate(th0, u_arr, False)[0]) ** 2))
        bounded = bool(np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)))
        res = least_squares(resid, th0, jac=jac, method="trf", x_scale="jac", ftol=self.tol, xtol=self.tol,
                            gtol=self.tol, max_nfev=self.max_nfev, bounds=(lo, hi) if bounded else (-np.inf, np.inf))
        th = res.x
        cost = float(np.mean((yv - self._simulate(th, u_arr, False)[0]) ** 2))
        if not np.isfinite(cost) or cost > self.initial_cost_:
            th, cost = th0, self.initial_cost_
        self._store(th, nu)
        self.cost_ = cost
        for k in ("_blocks", "_out", "_p0_in", "_p0_out", "_nb", "_nf", "_nk"):
            delattr(self, k)
        return self

    def _prepare(self, u: Any, y: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Validate, set up the working blocks and orders, fit the linear start; return (u, y, theta0)."""
        u_arr = as_2d("u", u)
        y_arr = as_2d("y", y)
        if y_arr.shape[1] != 1:
            raise ValueError(f"HammersteinWiener is MISO: y must have one column, got {y_arr.shape[1]} "
                             "(fit one model per output)")
        nu = u_arr.shape[1]
        blocks = [Identity() for _ in range(nu)] if self.input_blocks is None else list(self.input_blocks)
        if len(blocks) != nu:
            raise ValueError(f"{len(blocks)} input blocks for {nu} inputs")
        if not all(isinstance(b, StaticNonlinearity) for b in blocks):
            raise TypeError("input_blocks must be StaticNonlinearity instances (see ident.hammerstein_wiener)")
        out = Identity() if self.output_block is None else self.output_block
        if not isinstance(out, StaticNonlinearity):
            raise TypeError("output_block must be a StaticNonlinearity instance")
        nb, nf, nk = self._orders(nu)
        self._blocks = [b.copy() for b in blocks]
        self._out = out.copy()
        self._nb, self._nf, self._nk = nb, nf, nk
        n_par = int(nb.sum() + nf.sum()) + sum(b.n_free() for b in self._blocks) + self._out.n_free()
        u_arr, y_arr = validate_fit_data(u_arr, y_arr, n_par, int(max(nk + nb)), "Hammerstein-Wiener model")
        yv = y_arr[:, 0]
        self._p0_in = [b.initial_params(u_arr[:, i]) for i, b in enumerate(self._blocks)]
        v0 = np.column_stack([b.value(u_arr[:, i], p) for i, (b, p) in enumerate(zip(self._blocks, self._p0_in))])
        lin = self.init_model
        if lin is None:
            lin = OutputError(nb=tuple(nb), nf=tuple(nf), nk=tuple(nk), max_nfev=self.max_nfev).fit(v0, yv)
        elif isinstance(lin, HammersteinWiener) and not hasattr(lin, "b_"):
            lin = HammersteinWiener(**lin.get_params()).fit(u_arr, yv)  # a template: fit it on these data first
        check_is_fitted(lin, "b_")
        if isinstance(lin, HammersteinWiener):
            if lin.b_.shape[0] != nu:
                raise ValueError("init_model must be a HammersteinWiener fitted on the same inputs")
            lin_b, lin_f = lin.b_, lin.f_
            w0 = simulate_ss(lin.A_, lin.B_, lin.C_, lin.D_, v0)[0][:, 0]
        else:
            if lin.b_.shape[:2] != (1, nu):
                raise ValueError("init_model must be a single-output OutputError fitted on the same inputs")
            lin_b, lin_f = lin.b_[0], lin.f_[0]
            w0 = lin.predict(v0)[:, 0]
        self._p0_out = self._out.initial_params(w0)
        theta0: list[float] = []
        for blk, p0 in zip(self._blocks, self._p0_in):
            if blk.n_free():
                theta0 += list(p0)
        for i in range(nu):
            b_i = np.zeros(nk[i] + nb[i])
            m = min(b_i.size, lin_b.shape[1])
            b_i[:m] = lin_b[i, :m]
            theta0 += list(b_i[nk[i]:nk[i] + nb[i]])
            if nf[i]:
                f_i = np.zeros(nf[i] + 1)
                m = min(f_i.size, lin_f.shape[1])
                f_i[:m] = lin_f[i, :m]
                f_i = stabilize_poly(f_i, 0.999)
                theta0 += list(np.arctanh(np.clip(reflection_from_poly(f_i), -_KAPPA_MAX, _KAPPA_MAX)))
        if self._out.n_free():
            theta0 += list(self._p0_out)
        return u_arr, yv, np.asarray(theta0, dtype=float)

    def _store(self, th: np.ndarray, nu: int) -> None:
        p_in, bs, etas, p_out = self._unpack(th)
        self.input_blocks_ = self._blocks
        self.input_params_ = [np.array(p, dtype=float) for p in p_in]
        self.output_block_ = self._out
        self.output_params_ = np.array(p_out, dtype=float)
        lb = int(max(self._nk + self._nb))
        self.b_ = np.zeros((nu, lb))
        self.f_ = np.zeros((nu, int(self._nf.max()) + 1))
        for i in range(nu):
            self.b_[i, self._nk[i]:self._nk[i] + self._nb[i]] = bs[i]
            self.f_[i, :self._nf[i] + 1] = poly_from_reflection(np.tanh(etas[i]))[0]
        self.n_params_ = int(th.size)
        self._realise()

    def _realise(self) -> None:
        nu = self.b_.shape[0]
        blocks = [tf_to_ss(self.b_[i], self.f_[i]) for i in range(nu)]
        A = block_diag(*[b[0] for b in blocks])
        n = A.shape[0]
        B = np.zeros((n, nu))
        C = np.zeros((1, n))
        D = np.zeros((1, nu))
        o = 0
        for i, (Ai, Bi, Ci, Di) in enumerate(blocks):
            m = Ai.shape[0]
            B[o:o + m, i] = Bi[:, 0]
            C[0, o:o + m] = Ci[0]
            D[0, i] = Di[0, 0]
            o += m
        self.A_, self.B_, self.C_, self.D_ = A, B, C, D

    # ----------------------------------------------------------------------------------------- simulation
    @property
    def n_inputs_(self) -> int:
        check_is_fitted(self, "b_")
        return self.b_.shape[0]

    @property
    def n_states_(self) -> int:
        check_is_fitted(self, "b_")
        return self.A_.shape[0]

    def _u(self, u: Any) -> np.ndarray:
        check_is_fitted(self, "b_")
        return as_2d("u", u, n_columns=self.n_inputs_)

    def transform_inputs(self, u: Any) -> np.ndarray:
        """The static input blocks' outputs v, shape (N, n_inputs)."""
        u = self._u(u)
        return np.column_stack([b.value(u[:, i], p) for i, (b, p) in
                                enumerate(zip(self.input_blocks_, self.input_params_))])

    def output_nonlinearity(self, w: Any) -> np.ndarray:
        """h(w) for the linear block's output w."""
        check_is_fitted(self, "b_")
        return self.output_block_.value(np.asarray(w, dtype=float), self.output_params_)

    def initial_state(self, u: Any, y: Any, n_iter: int = 8) -> np.ndarray:
        """The linear block's x(0) that best explains the measured ``y`` given ``u`` (Gauss-Newton through the
        output block, from x(0) = 0, with step halving so the squared error never rises; samples where the output block
        saturates carry no information)."""
        v = self.transform_inputs(u)
        y = as_2d("y", y, n_columns=1)[:, 0]
        n0 = check_same_length(u=v, y=y)
        A, B, C, D = self.A_, self.B_, self.C_, self.D_
        w_zero = simulate_ss(A, B, C, D, v)[0][:, 0]
        obs = np.empty((n0, A.shape[0]))
        m = C[0].copy()
        for t in range(n0):
            obs[t] = m
            m = m @ A
        x0 = np.zeros(A.shape[0])

        def sse(x: np.ndarray) -> float:
            return float(np.sum((y - self.output_block_.value(w_zero + obs @ x, self.output_params_)) ** 2))

        cost = sse(x0)
        for _ in range(n_iter):
            w = w_zero + obs @ x0
            r = y - self.output_block_.value(w, self.output_params_)
            J = self.output_block_.dx(w, self.output_params_)[:, None] * obs
            dx, *_ = np.linalg.lstsq(J, r, rcond=None)
            # step halving: through a saturating output block the Gauss-Newton step may overshoot (samples that
            # leave the saturation change the residual), so accept only steps that lower the squared error
            step, new_cost = 1.0, sse(x0 + dx)
            while not new_cost <= cost and step > 1e-6:
                step *= 0.5
                new_cost = sse(x0 + step * dx)
            if not new_cost <= cost:
                break
            x0, cost = x0 + step * dx, new_cost
            if np.linalg.norm(step * dx) <= 1e-10 * (1.0 + np.linalg.norm(x0)):
                break
        return x0

    def predict(self, u: Any, y0: Any = None, *, x0: Any = None) -> np.ndarray:
        """Simulated output, shape (N, 1).

        Parameters
        ----------
        u : array_like, shape (N, n_inputs)
        y0 : array_like, shape (n0,) or (n0, 1), optional
            Measured outputs at the start; x(0) is then estimated from them (:meth:`initial_state`), like the
            linear models. Default x(0) = 0, the state the fit assumes.
        x0 : array_like, shape (n_states,), optional
            Explicit initial state of the linear block.
        """
        u = self._u(u)
        if x0 is not None:
            x0 = np.asarray(x0, dtype=float).reshape(self.n_states_)
        elif y0 is not None:
            y0a = as_2d("y0", y0, n_columns=1)
            n0 = min(len(y0a), len(u))
            x0 = self.initial_state(u[:n0], y0a[:n0])
        v = self.transform_inputs(u)
        w, _ = simulate_ss(self.A_, self.B_, self.C_, self.D_, v, x0)
        return self.output_nonlinearity(w[:, 0])[:, None]

    def predict_k_step(self, u: Any, y: Any, k: int) -> np.ndarray:
        """k-step-ahead prediction. The model has no noise model (output-error structure), so every horizon gives
        the simulated output from the x(0) estimated on the record (as the linear output-error model)."""
        if int(k) != k or k < 1:
            raise ValueError(f"k must be a positive integer number of steps, got {k}")
        return self.predict(u, y0=y)

    # ---------------------------------------------------------------------------------------------- export
    def to_casadi(self) -> Any:
        """``casadi.Function('step', [x, u], [x_next, y])``: x the linear block's state, u the raw inputs."""
        import casadi as ca

        check_is_fitted(self, "b_")
        x = ca.SX.sym("x", self.n_states_)
        u = ca.SX.sym("u", self.n_inputs_)
        v = ca.vertcat(*[b.casadi(u[i], p) for i, (b, p) in enumerate(zip(self.input_blocks_, self.input_params_))])
        x_next = ca.mtimes(ca.DM(self.A_), x) + ca.mtimes(ca.DM(self.B_), v)
        w = ca.mtimes(ca.DM(self.C_), x) + ca.mtimes(ca.DM(self.D_), v)
        y = self.output_block_.casadi(w, self.output_params_)
        return ca.Function("step", [x, u], [x_next, y], ["x", "u"], ["x_next", "y"])

    # ---------------------------------------------------------------------------------------------- saving
    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        check_is_fitted(self, "b_")
        params = {k: v for k, v in self.get_params().items() if k not in ("init_model",)}
        params["input_blocks"] = None if self.input_blocks is None else [b.to_dict() for b in self.input_blocks]
        params["output_block"] = None if self.output_block is None else self.output_block.to_dict()
        meta = {"params": params, "input_blocks_": [b.to_dict() for b in self.input_blocks_],
                "output_block_": self.output_block_.to_dict(), "cost_": self.cost_,
                "initial_cost_": self.initial_cost_, "n_params_": self.n_params_}
        arrays = {"b_": self.b_, "f_": self.f_, "output_params_": self.output_params_}
        for i, p in enumerate(self.input_params_):
            arrays[f"input_params_{i}"] = p
        return meta, arrays

    @classmethod
    def _from_state(cls, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> HammersteinWiener:
        p = dict(meta["params"])
        p["input_blocks"] = None if p["input_blocks"] is None else [block_from_dict(d) for d in p["input_blocks"]]
        p["output_block"] = None if p["output_block"] is None else block_from_dict(p["output_block"])
        for k in ("nb", "nf", "nk"):
            if isinstance(p[k], list):
                p[k] = tuple(p[k])
        obj = cls(**p)
        obj.input_blocks_ = [block_from_dict(d) for d in meta["input_blocks_"]]
        obj.output_block_ = block_from_dict(meta["output_block_"])
        obj.input_params_ = [np.asarray(arrays[f"input_params_{i}"], dtype=float)
                             for i in range(len(obj.input_blocks_))]
        obj.output_params_ = np.asarray(arrays["output_params_"], dtype=float)
        obj.b_ = np.asarray(arrays["b_"], dtype=float)
        obj.f_ = np.asarray(arrays["f_"], dtype=float)
        obj.cost_ = float(meta["cost_"])
        obj.initial_cost_ = float(meta["initial_cost_"])
        obj.n_params_ = int(meta["n_params_"])
        obj._realise()
        return obj

    def save(self, path: str | Path) -> Path:
        """Save as ``<path>.json`` + ``<path>.npz`` (see :mod:`ident.io`); returns the JSON path."""
        return save_model(self, path)

    @classmethod
    def load(cls, path: str | Path) -> HammersteinWiener:
        """Load a model saved with :meth:`save`."""
        obj = load_model(path)
        if not isinstance(obj, cls):
            raise TypeError(f"{path} holds a {type(obj).__name__}, not a {cls.__name__}")
        return obj


def wiener(output_block: StaticNonlinearity, **kwargs: Any) -> HammersteinWiener:
    """A Wiener model: identity inputs, linear block, ``output_block`` (Paper IV's M-III with a Saturation)."""
    return HammersteinWiener(input_blocks=None, output_block=output_block, **kwargs)


def hammerstein(input_blocks: Sequence[StaticNonlinearity], **kwargs: Any) -> HammersteinWiener:
    """A Hammerstein model: static input blocks, linear block, identity output."""
    return HammersteinWiener(input_blocks=input_blocks, output_block=None, **kwargs)
