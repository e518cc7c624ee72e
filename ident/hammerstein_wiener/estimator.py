"""The Hammerstein-Wiener estimator (Paper IV's M-III, M-IV, M-V): static input blocks, per-input transfer functions,
a static output block

    v_i(t) = g_i(u_i(t); p_i)                         i = 1..n_inputs      (Hammerstein part)
    w(t)   = sum_i B_i(q) / F_i(q) v_i(t)                                  (M-II's linear block)
    y(t)   = h(w(t); p_h)                                                   (Wiener part)

``B_i(q) = b_i1 q^-nk_i + ... + b_i,nb q^-(nk_i + nb_i - 1)`` and ``F_i(q) = 1 + f_i1 q^-1 + ... + f_i,nf q^-nf``,
F_i parametrised by reflection coefficients ``tanh(eta)`` so every estimate is stable (as
:class:`~ident.linear.OutputError`).

Fit: the simulation error ``sum_t (y(t) - yhat(t))^2`` (zero initial state, as the output-error fit, unless
``initial="steady"``) is minimised
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
  grid, chosen exactly as :func:`select_by_holdout` chooses: each value fitted with the last ``holdout`` of the
  estimation data given zero weight and scored by the simulated FIT there (simulated through the whole record from
  an x(0) estimated on the fitted part, so the hold-out continues the fitted record), the best refitted on all of it
  (``smoothness_``, ``holdout_scores_``). Nothing outside the data passed to ``fit`` is used.
* ``init_model`` may be a fitted :class:`~ident.linear.OutputError` or :class:`HammersteinWiener` on the same inputs,
  or an *unfitted* :class:`HammersteinWiener` template, which is then fitted first on the data passed to ``fit``
  (also on the inner split of the hold-out selection): e.g. M-V started from M-IV, a Wiener model on the same
  inputs, so the start is M-IV itself (identity-like piecewise-linear blocks) and the fit can only improve on it.
* block bounds (``StaticNonlinearity.bounds``, e.g. ``PiecewiseLinear(monotone=True)``) are honoured.
* :func:`select_by_holdout` chooses among whole model templates (orders, delays, smoothness...) the same way: each
  fitted on the first part of the estimation data, scored on the held-out end, the best refitted on all of it.

Further options:

* ``fit(u, y, sample_weight)``: weights on the squared simulation errors; the record is still simulated through
  zero-weight samples (a hold-out inside one record, or blocked cross-validation).
* ``unit_gain``: removes the scale ambiguity between a free input block and its ``B_i/F_i`` by giving ``B_i/F_i`` a
  static gain of +-1 (the sign of the start's) and letting the block carry the gain; without it the ambiguity is
  only held by the ridge term, and a roughness penalty can be evaded by shrinking the block and growing ``B_i``
  (slow convergence, results that depend on the iteration budget).
* ``initial="steady"``: the fit assumes the linear block at rest at the first input (``w_i(0) = G_i v_i(0)``)
  instead of at zero, so normalised inputs that start far from zero do not start a transient the data never had.

Special cases: :func:`wiener` (identity inputs) and :func:`hammerstein` (identity output).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.linalg import block_diag
from scipy.optimize import least_squares
from scipy.signal import lfilter

from ident.base import BaseEstimator, as_2d, as_vector, check_is_fitted, check_same_length
from ident.hammerstein_wiener.blocks import Identity, StaticNonlinearity, block_from_dict
from ident.io import register_model
from ident.linear import OutputError
from ident.linear._statespace import _per_input, data_columns, simulate_ss, tf_to_ss, validate_fit_data
from ident.linear.oe import _KAPPA_MAX, poly_from_reflection, reflection_from_poly, stabilize_poly
from ident.metrics import fit_percent

__all__ = ["HammersteinWiener", "hammerstein", "select_by_holdout", "wiener"]


def _shift(x: np.ndarray, k: int) -> np.ndarray:
    out = np.zeros_like(x)
    if k < len(x):
        out[k:] = x[:len(x) - k]
    return out


def _longest_run(mask: np.ndarray) -> tuple[int, int]:
    """Start and end (exclusive) of the longest run of True in ``mask``."""
    best, start = (0, 0), None
    for t, m in enumerate(np.append(mask, False)):
        if m and start is None:
            start = t
        elif not m and start is not None:
            if t - start > best[1] - best[0]:
                best = (start, t)
            start = None
    return best


@register_model("hammerstein_wiener")
class HammersteinWiener(BaseEstimator):
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
    unit_gain : bool
        Give each ``B_i/F_i`` behind a free, scalable input block a static gain of +-1 (see module docstring).
    initial : {"zero", "steady"}
        The linear block's state the fit assumes at the first sample: zero, or at rest at the first input.
        (Prediction starts from zero or from an estimated state either way, see :meth:`predict`.)

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
                 smoothness: float | Sequence[float] = 0.0, holdout: float = 0.25, unit_gain: bool = False,
                 initial: str = "zero") -> None:
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
        self.unit_gain = unit_gain
        self.initial = initial

    # ------------------------------------------------------------------------------------------- helpers
    def _orders(self, nu: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return _per_input(self.nb, nu, "nb"), _per_input(self.nf, nu, "nf"), _per_input(self.nk, nu, "nk")

    def _unpack(self, theta: np.ndarray) -> tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray],
                                                  np.ndarray]:
        """theta -> (input params per block, b per input, eta per input, output params), fixed ones filled in."""
        j = 0
        p_in = []
        for blk, p0 in zip(self._blocks, self._p0_in, strict=False):
            m = blk.n_free()
            p_in.append(theta[j:j + m] if m else p0)
            j += m
        bs, etas = [], []
        for i in range(len(self._blocks)):
            g = self._gain[i]
            nb_free = self._nb[i] - (g is not None)
            b = theta[j:j + nb_free]
            j += nb_free
            etas.append(theta[j:j + self._nf[i]])
            j += self._nf[i]
            if g is not None:  # unit static gain: sum(b) = g F(1)
                f_sum = max(float(np.sum(poly_from_reflection(np.tanh(etas[i]))[0])), 1e-12)
                b = np.append(b, g * f_sum - np.sum(b))
            bs.append(b)
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
            # "steady": at rest at the first input, w_i = B/F (v - v(0)) + G v(0), G = B(1)/F(1) the static gain
            v0 = float(v[0]) if self._steady else 0.0
            f_sum = max(float(np.sum(f)), 1e-12)   # F(1) > 0 for a stable F
            gain = float(np.sum(bs[i])) / f_sum
            wi = lfilter(num, f, v - v0) + gain * v0
            w += wi
            if not jac:
                continue
            if blk.n_free():
                dp = blk.dp(u[:, i], p_in[i])
                dp0 = dp[:1] if self._steady else np.zeros((1, dp.shape[1]))
                cols_static.append(lfilter(num, f, dp - dp0, axis=0) + gain * dp0)
            vf = lfilter([1.0], f, v - v0)
            db = [_shift(vf, self._nk[i] + k)[:, None] + v0 / f_sum for k in range(self._nb[i])]
            g = self._gain[i]
            if g is not None:  # b_last = g F(1) - sum(other b): chain its column into the free ones
                last = db.pop()
                db = [c - last for c in db]
            cols_lin += db
            if self._nf[i]:
                wf = lfilter([1.0], f, wi - gain * v0)   # the filtered part (the steady offset: below)
                dw_df = np.column_stack([-_shift(wf, k) for k in range(1, self._nf[i] + 1)])
                dw_df = dw_df - gain * v0 / f_sum       # d(G v0)/df_k, dF(1)/df_k = 1
                d_eta = dw_df @ df_dk[1:]
                if g is not None:
                    d_eta = d_eta + last * (g * df_dk.sum(axis=0))[None, :]
                cols_lin.append(d_eta * (1.0 - np.tanh(etas[i]) ** 2))
        y = self._out.value(w, p_out)
        if not jac:
            return y, None
        dw = np.concatenate(cols_static + cols_lin, axis=1)
        J = self._out.dx(w, p_out)[:, None] * dw
        if self._out.n_free():
            J = np.concatenate([J, self._out.dp(w, p_out)], axis=1)
        return y, J

    # ----------------------------------------------------------------------------------------------- fit
    def fit(self, u: Any, y: Any, sample_weight: Any = None) -> HammersteinWiener:
        """Minimise the simulation error from the best linear start; returns ``self``.

        ``sample_weight`` (shape (N,), >= 0) weights each sample's squared simulation error; the model is still
        simulated through every sample, so zero weights leave a gap in the criterion, not in the record (blocked
        cross-validation on one record).

        Raises ``ValueError`` for NaN/inf, mismatched lengths, constant inputs, an output constant over all samples
        (``"y is constant ..."``), more than one output, a wrong number of input blocks or too few samples.
        """
        grid = np.atleast_1d(np.asarray(self.smoothness, dtype=float))
        if grid.ndim != 1 or grid.size == 0 or np.any(~np.isfinite(grid)) or np.any(grid < 0):
            raise ValueError(f"smoothness must be a non-negative number or a sequence of them, got "
                             f"{self.smoothness!r}")
        scores: dict[float, float] = {}
        if np.ndim(self.smoothness) > 0 and grid.size > 1:
            # smoother first, so a tie goes to the smoother value (the earlier candidate wins ties)
            lams = sorted({float(lam) for lam in grid}, reverse=True)
            templates = [HammersteinWiener(**{**self.get_params(), "smoothness": lam}) for lam in lams]
            fits = _holdout_scores(templates, u, y, self.holdout, sample_weight)
            scores = dict(zip(lams, fits, strict=False))
            best = lams[int(np.argmax(fits))]
        else:
            best = float(grid[0])
        self._fit_once(u, y, best, sample_weight)
        self.smoothness_ = best
        self.holdout_scores_ = scores
        return self

    def _fit_once(self, u: Any, y: Any, smoothness: float, sample_weight: Any = None) -> HammersteinWiener:
        u_arr, yv, th0 = self._prepare(u, y, sample_weight)
        nu = u_arr.shape[1]
        sw = self._sqrt_weights(sample_weight, yv.size)
        n_eff = float(np.sum(sw ** 2))
        # ridge rows on the free static parameters (input blocks first, output block last)
        n_in_free = sum(b.n_free() for b in self._blocks)
        end_out = th0.size   # theta: input blocks, linear block, output block
        idx_arr = np.asarray(list(range(n_in_free)) + list(range(end_out - self._out.n_free(), end_out)), dtype=int)
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
                    rows[:, j:j + m] = np.sqrt(smoothness * n_eff) * R
                    rough_rows.append(rows)
            j += m
        if self._out.n_free():
            sl = slice(end_out - self._out.n_free(), end_out)
            lo[sl], hi[sl] = self._out.bounds()
        Rr = np.vstack(rough_rows) if rough_rows else np.zeros((0, th0.size))
        th0 = np.clip(th0, lo, hi)

        def resid(th: np.ndarray) -> np.ndarray:
            e = sw * (yv - self._simulate(th, u_arr, False)[0])
            parts = [e, Rr @ th]
            if use_reg:
                parts.append(wts * (th[idx_arr] - ref))
            return np.concatenate(parts)

        def jac(th: np.ndarray) -> np.ndarray:
            J = [-sw[:, None] * self._simulate(th, u_arr, True)[1], Rr]
            if use_reg:
                R = np.zeros((idx_arr.size, th.size))
                R[np.arange(idx_arr.size), idx_arr] = wts
                J.append(R)
            return np.vstack(J)

        def mse(th: np.ndarray) -> float:
            return float(np.sum((sw * (yv - self._simulate(th, u_arr, False)[0])) ** 2) / n_eff)

        self.initial_cost_ = mse(th0)
        bounded = bool(np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)))
        res = least_squares(resid, th0, jac=jac, method="trf", x_scale="jac", ftol=self.tol, xtol=self.tol,
                            gtol=self.tol, max_nfev=self.max_nfev, bounds=(lo, hi) if bounded else (-np.inf, np.inf))
        th = res.x
        cost = mse(th)
        if not np.isfinite(cost) or cost > self.initial_cost_:
            th, cost = th0, self.initial_cost_
        self._store(th, nu)
        self.cost_ = cost
        for k in ("_blocks", "_out", "_p0_in", "_p0_out", "_nb", "_nf", "_nk", "_gain", "_steady"):
            delattr(self, k)
        return self

    @staticmethod
    def _sqrt_weights(sample_weight: Any, n: int) -> np.ndarray:
        if sample_weight is None:
            return np.ones(n)
        w = np.asarray(sample_weight, dtype=float).reshape(-1)
        if w.size != n or np.any(~np.isfinite(w)) or np.any(w < 0) or not np.any(w > 0):
            raise ValueError(f"sample_weight must be {n} finite non-negative weights, not all zero")
        return np.sqrt(w)

    def _prepare(self, u: Any, y: Any, sample_weight: Any = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Validate, set up the working blocks and orders, fit the linear start; return (u, y, theta0)."""
        data_columns(u, y, "Hammerstein-Wiener model")
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
        if self.initial not in ("zero", "steady"):
            raise ValueError(f"initial must be 'zero' or 'steady', got {self.initial!r}")
        self._steady = self.initial == "steady"
        nb, nf, nk = self._orders(nu)
        self._blocks = [b.copy() for b in blocks]
        self._out = out.copy()
        self._nb, self._nf, self._nk = nb, nf, nk
        n_par = int(nb.sum() + nf.sum()) + sum(b.n_free() for b in self._blocks) + self._out.n_free()
        u_arr, y_arr = validate_fit_data(u_arr, y_arr, n_par, int(max(nk + nb)), "Hammerstein-Wiener model")
        yv = y_arr[:, 0]
        self._p0_in = [b.initial_params(u_arr[:, i]) for i, b in enumerate(self._blocks)]
        v0 = np.column_stack([b.value(u_arr[:, i], p)
                              for i, (b, p) in enumerate(zip(self._blocks, self._p0_in, strict=False))])
        lin = self.init_model
        if lin is None:
            # the best linear model; with sample weights, fitted on the longest run of weighted samples only (a
            # start: the weighted fit refines it), so samples held out by zero weights never enter the fit
            a, b = _longest_run(self._sqrt_weights(sample_weight, yv.size) > 0)
            try:
                lin = OutputError(nb=tuple(nb), nf=tuple(nf), nk=tuple(nk), max_nfev=self.max_nfev).fit(v0[a:b],
                                                                                                        yv[a:b])
            except ValueError as err:
                part = "" if sample_weight is None else f" on the longest run of weighted samples ({a} to {b - 1})"
                raise ValueError("cannot fit the Hammerstein-Wiener model: its linear start, an output-error model "
                                 "from the outputs of the initial input blocks (called u below) to y"
                                 f"{part}, failed: {err}") from err
        elif isinstance(lin, HammersteinWiener) and not hasattr(lin, "b_"):
            # a template: fit it on these data (same weights) first
            lin = HammersteinWiener(**lin.get_params()).fit(u_arr, yv, sample_weight=sample_weight)
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
        self._gain = [None] * nu
        lin_part: list[float] = []
        for i in range(nu):
            b_i = np.zeros(nk[i] + nb[i])
            m = min(b_i.size, lin_b.shape[1])
            b_i[:m] = lin_b[i, :m]
            b_i = b_i[nk[i]:nk[i] + nb[i]]
            eta = np.zeros(0)
            if nf[i]:
                f_i = np.zeros(nf[i] + 1)
                m = min(f_i.size, lin_f.shape[1])
                f_i[:m] = lin_f[i, :m]
                f_i = stabilize_poly(f_i, 0.999)
                eta = np.arctanh(np.clip(reflection_from_poly(f_i), -_KAPPA_MAX, _KAPPA_MAX))
            f_sum = float(np.sum(poly_from_reflection(np.tanh(eta))[0]))
            gain = float(np.sum(b_i)) / f_sum
            blk = self._blocks[i]
            scaled = blk.scaled_params(self._p0_in[i], abs(gain)) if (self.unit_gain and blk.n_free() and nb[i]
                                                                       and abs(gain) > 1e-8) else None
            if scaled is not None:
                # unit static gain of B_i/F_i (sign of the start's gain), the block scaled to carry the gain
                self._gain[i] = float(np.sign(gain))
                self._p0_in[i] = np.asarray(scaled, dtype=float)
                b_i = b_i[:-1] / abs(gain)
            lin_part += list(b_i) + list(eta)
        theta0: list[float] = []
        for blk, p0 in zip(self._blocks, self._p0_in, strict=False):
            if blk.n_free():
                theta0 += list(p0)
        theta0 += lin_part
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
                                enumerate(zip(self.input_blocks_, self.input_params_, strict=False))])

    def output_nonlinearity(self, w: Any) -> np.ndarray:
        """h(w) for the linear block's output w."""
        check_is_fitted(self, "b_")
        return self.output_block_.value(np.asarray(w, dtype=float), self.output_params_)

    def initial_state(self, u: Any, y: Any, n_iter: int = 8) -> np.ndarray:
        """The linear block's x(0) that best explains the measured ``y`` given ``u`` (Gauss-Newton through the
        output block from x(0) = 0 and from the steady state for the first input, the better kept; truncated steps,
        step halving so the squared error never rises; samples where the output block saturates carry no
        information)."""
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

        def sse(x: np.ndarray) -> float:
            return float(np.sum((y - self.output_block_.value(w_zero + obs @ x, self.output_params_)) ** 2))

        def gauss_newton(x0: np.ndarray) -> tuple[np.ndarray, float]:
            cost = sse(x0)
            for _ in range(n_iter):
                w = w_zero + obs @ x0
                r = y - self.output_block_.value(w, self.output_params_)
                J = self.output_block_.dx(w, self.output_params_)[:, None] * obs
                # truncated least squares: directions the data barely observe (fast modes that died out, modes
                # hidden behind the saturation) stay put instead of taking huge steps the linearisation does not
                # support
                dx, *_ = np.linalg.lstsq(J, r, rcond=1e-8)
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
            return x0, cost

        # two starts, the better kept: x(0) = 0 and the steady state for the first input (through a saturation the
        # squared error is not convex in x(0))
        starts = [np.zeros(A.shape[0])]
        try:
            starts.append(np.linalg.solve(np.eye(A.shape[0]) - A, B @ v[0]))
        except np.linalg.LinAlgError:
            pass
        best = min((gauss_newton(x) for x in starts if np.all(np.isfinite(x))), key=lambda xc: xc[1])
        return best[0]

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
            x0 = as_vector("x0", x0, self.n_states_, "values (one per state of the linear block)")
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
        u_arr = self._u(u)
        y_arr = as_2d("y", y, n_columns=1)
        check_same_length(u=u_arr, y=y_arr)
        if int(k) != k or k < 1:
            raise ValueError(f"k must be a positive integer number of steps, got {k}")
        return self.predict(u_arr, y0=y_arr)

    # ---------------------------------------------------------------------------------------------- export
    def to_casadi(self) -> Any:
        """``casadi.Function('step', [x, u], [x_next, y])``: x the linear block's state, u the raw inputs."""
        import casadi as ca

        check_is_fitted(self, "b_")
        x = ca.SX.sym("x", self.n_states_)
        u = ca.SX.sym("u", self.n_inputs_)
        v = ca.vertcat(*[b.casadi(u[i], p)
                         for i, (b, p) in enumerate(zip(self.input_blocks_, self.input_params_, strict=False))])
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


def wiener(output_block: StaticNonlinearity, **kwargs: Any) -> HammersteinWiener:
    """A Wiener model: identity inputs, linear block, ``output_block`` (Paper IV's M-III with a Saturation)."""
    return HammersteinWiener(input_blocks=None, output_block=output_block, **kwargs)


def hammerstein(input_blocks: Sequence[StaticNonlinearity], **kwargs: Any) -> HammersteinWiener:
    """A Hammerstein model: static input blocks, linear block, identity output."""
    return HammersteinWiener(input_blocks=input_blocks, output_block=None, **kwargs)


def select_by_holdout(candidates: Sequence[HammersteinWiener], u: Any, y: Any, holdout: float = 0.25
                      ) -> tuple[HammersteinWiener, list[float]]:
    """Choose among unfitted model templates on the estimation data alone, then refit the choice on all of it.

    Each candidate is fitted with the last ``holdout`` fraction of the samples given zero weight (so it is fitted on
    the first part only, its linear start too) and scored by the FIT over the held-out end of its output simulated
    through the whole record from an x(0) estimated on the fitted part: the model continues the record it was
    fitted on, as it will continue into new data (and as the validation data are scored). The best score wins
    (ties: the earlier candidate, so list simpler ones first); it is refitted on all samples. Candidates whose fit
    fails score -inf.

    Returns the fitted winner and the hold-out FIT (%) of every candidate, in order.
    """
    if not candidates:
        raise ValueError("no candidate models")
    u_arr, y_arr = as_2d("u", u), as_2d("y", y)
    scores = _holdout_scores(candidates, u_arr, y_arr, holdout)
    best = int(np.argmax(scores))
    return HammersteinWiener(**candidates[best].get_params()).fit(u_arr, y_arr), scores


def _holdout_scores(candidates: Sequence[HammersteinWiener], u: Any, y: Any, holdout: float,
                    sample_weight: Any = None) -> list[float]:
    """Hold-out FIT (%) of each unfitted template. With ``n_end`` one past the last sample of positive weight, the
    samples from ``round(n_end * (1 - holdout))`` to ``n_end`` get zero weight (the record is still simulated through
    them); each candidate is fitted so and scored on those held-out samples (the ones of positive weight) of its
    output simulated through the record from an x(0) estimated on the fitted part. A candidate whose fit fails scores
    -inf. Shared by :func:`select_by_holdout` and the ``smoothness`` grid of :meth:`HammersteinWiener.fit`. Zero-weight
    outputs enter neither fit nor score; the inputs of the whole record may still place the blocks' starting knots
    or scales (as in any fit with ``sample_weight``)."""
    if not 0.0 < float(holdout) < 1.0:
        raise ValueError(f"holdout must be in (0, 1), got {holdout!r}")
    u_arr, y_arr = as_2d("u", u), as_2d("y", y)
    n = check_same_length(u=u_arr, y=y_arr)
    HammersteinWiener._sqrt_weights(sample_weight, n)   # validates the weights
    base = np.ones(n) if sample_weight is None else np.asarray(sample_weight, dtype=float).reshape(-1)
    n_end = int(np.flatnonzero(base > 0)[-1]) + 1
    n_in = round(n_end * (1.0 - float(holdout)))
    w = np.where(np.arange(n) < n_in, base, 0.0)
    keep = base[n_in:n_end] > 0
    if not np.any(w > 0) or not np.any(keep):
        raise ValueError(f"holdout {holdout!r} leaves no weighted sample to fit on or none to score on")
    y_ho = y_arr[n_in:n_end, 0][keep]
    scores: list[float] = []
    for cand in candidates:
        try:
            m = HammersteinWiener(**cand.get_params()).fit(u_arr, y_arr, sample_weight=w)
            y_hat = m.predict(u_arr[:n_end], y0=y_arr[:n_in])[n_in:, 0][keep]
            score = fit_percent(y_ho, y_hat)
        except (ValueError, np.linalg.LinAlgError):
            score = -np.inf
        scores.append(float(score) if np.isfinite(score) else -np.inf)
    return scores
