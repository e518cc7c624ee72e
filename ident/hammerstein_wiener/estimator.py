"""The Hammerstein-Wiener estimator (Paper IV's M-III, M-IV, M-V, and its multi-output form): static input
blocks, one transfer function per (output, input) pair, one static block per output

    v_i(t) = g_i(u_i(t); p_i)                         i = 1..n_inputs      (Hammerstein part)
    w_j(t) = sum_i B_ji(q) / F_ji(q) v_i(t)                                (the linear block; M-II's for one output)
    y_j(t) = h_j(w_j(t); p_hj)                        j = 1..n_outputs     (Wiener part)

(MATLAB ``idnlhw``'s structure). ``B_ji(q) = b_1 q^-nk + ... + b_nb q^-(nk + nb - 1)`` and
``F_ji(q) = 1 + f_1 q^-1 + ... + f_nf q^-nf``, F parametrised by reflection coefficients ``tanh(eta)`` so every
estimate is stable (as :class:`~ident.linear.OutputError`). The input blocks are shared by all outputs.

Fit: the simulation error ``sum_t sum_j (y_j(t) - yhat_j(t))^2`` (zero initial state, as the output-error fit,
unless ``initial="steady"``; outputs in different units should be normalised first, e.g. with
:class:`~ident.preprocessing.Normalizer`) is minimised by a Levenberg-Marquardt method on the normal equations
(:func:`ident.linear._lsq.levenberg_marquardt`: fast for long records) with the exact Jacobian, every column from
one linear filter pass: ``dyhat_j/dtheta = h_j'(w_j) dw_j/dtheta`` with ``dw_j/dp_i = B_ji/F_ji [dg_i/dp_i]``,
``dw_j/db_jik = q^-(nk+k) F_ji^-1 v_i``, ``dw_j/df_jik = -q^-k F_ji^-1 w_ji`` (chained through the reflection map),
plus ``dh_j/dp_hj``. A small ridge term ``regularization * sum ((p - p0) / max(|p0|, 1))^2`` on the static
parameters removes the gain and offset ambiguity between the static blocks and the linear block (a piecewise-linear
input block scaled by c and B_i by 1/c give the same output).

Starts (``start``):

* ``"identity"``: the blocks at their initial (identity-like) parameters and the best linear model through them
  (an :class:`~ident.linear.OutputError` fit from the initial blocks' outputs to y);
* ``"data"``: data-driven: the input blocks that are linear in their parameters (piecewise-linear with fixed knots,
  polynomial, odd and even polynomial) from the over-parametrisation method (an ARX regression on the blocks'
  basis functions, a rank-one SVD per input: :mod:`ident.hammerstein_wiener.starts`), then the best linear model
  through them; output blocks linear in their parameters fitted by least squares from that model's output to y;
* ``"auto"`` (default): both when they differ, the one with the lower simulation error on the estimation data kept
  (``start_`` says which). With ``init_model`` the start is always that model's linear block.

Random restarts (``n_restarts``): the start above and ``n_restarts`` random ones (random block parameters, random
stable denominators, random numerators: :func:`~ident.hammerstein_wiener.starts.random_start`) are each fitted with
the last ``holdout`` of the estimation data given zero weight and scored by the simulated FIT there (as
:func:`select_by_holdout` scores); the best is refitted on all of it from where it ended (``restart_scores_``).
``"auto"`` gives 4 restarts when a block is even (:class:`AbsoluteValue`, :class:`EvenPolynomial`: through an even
block the best linear approximation of a system driven by a symmetric input is zero, so neither deterministic start
can find the linear block), also when a free output block can take an even shape (linear in more than two
parameters: piecewise-linear, polynomial) and the deterministic start explains less than half of the output
variance (``AUTO_RESTART_R2``: the signature of such a nonlinearity), and none otherwise (no ``init_model``).

Options against overfitting flexible input blocks (Paper IV's M-V):

* ``smoothness``: a penalty ``smoothness * N * sum_blocks ||R p||^2`` on the blocks' ``roughness_matrix`` (for a
  piecewise-linear block the changes of slope at its inner knots), i.e. ``smoothness`` per unit of mean squared
  error; it pulls every block toward a straight line, which the linear block can absorb. A sequence of values is a
  grid, chosen exactly as :func:`select_by_holdout` chooses: each value fitted with the last ``holdout`` of the
  estimation data given zero weight and scored by the simulated FIT there (simulated through the whole record from
  an x(0) estimated on the fitted part, so the hold-out continues the fitted record), the best refitted on all of it
  (``smoothness_``, ``holdout_scores_``). Nothing outside the data passed to ``fit`` is used.
* ``init_model`` may be a fitted :class:`~ident.linear.OutputError` or :class:`HammersteinWiener` on the same inputs
  and outputs, or an *unfitted* :class:`HammersteinWiener` template, which is then fitted first on the data passed
  to ``fit`` (also on the inner split of the hold-out selection): e.g. M-V started from M-IV, a Wiener model on the
  same inputs, so the start is M-IV itself (identity-like piecewise-linear blocks) and the fit can only improve on it.
* block bounds (``StaticNonlinearity.bounds``, e.g. ``PiecewiseLinear(monotone=True)``) are honoured.
* :func:`select_by_holdout` chooses among whole model templates (orders, delays, smoothness...) the same way: each
  fitted on the first part of the estimation data, scored on the held-out end, the best refitted on all of it.

Further options:

* ``fit(u, y, sample_weight)``: weights on the squared simulation errors; the record is still simulated through
  zero-weight samples (a hold-out inside one record, or blocked cross-validation).
* ``unit_gain``: removes the scale ambiguity between a free input block and its transfer functions by giving one
  ``B_ji/F_ji`` per input (the output where the start's static gain is largest) a static gain of +-1 (the sign of
  the start's) and letting the block carry the gain; without it the ambiguity is only held by the ridge term, and a
  roughness penalty can be evaded by shrinking the block and growing ``B_i`` (slow convergence, results that depend
  on the iteration budget).
* ``initial="steady"``: the fit assumes the linear block at rest at the first input (``w_ji(0) = G_ji v_i(0)``)
  instead of at zero, so normalised inputs that start far from zero do not start a transient the data never had.

Special cases: :func:`wiener` (identity inputs) and :func:`hammerstein` (identity outputs).
"""
from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.linalg import block_diag

from ident.base import BaseEstimator, as_2d, as_vector, check_is_fitted, check_same_length
from ident.hammerstein_wiener._structure import Structure
from ident.hammerstein_wiener.blocks import Identity, StaticNonlinearity, block_from_dict
from ident.hammerstein_wiener.starts import linear_start, longest_run, overparametrised_inputs, random_start
from ident.io import register_model
from ident.linear import OutputError
from ident.linear._lsq import levenberg_marquardt
from ident.linear._statespace import data_columns, simulate_ss, tf_to_ss, validate_fit_data
from ident.linear.oe import poly_from_reflection
from ident.metrics import fit_percent

__all__ = ["HammersteinWiener", "hammerstein", "select_by_holdout", "wiener"]

#: Random restarts ``n_restarts="auto"`` gives when it restarts (module docstring).
AUTO_RESTARTS = 4
#: ``n_restarts="auto"`` restarts a model with a flexible output block when its deterministic start explains less
#: than this fraction of the output variance (the best linear approximation vanishes behind an even nonlinearity).
AUTO_RESTART_R2 = 0.5


def _orders(value: Any, ny: int, nu: int, name: str) -> np.ndarray:
    """An order given as one int, one per input, or one per (output, input) pair, as an int array (ny, nu)."""
    arr = np.asarray(value)
    if arr.ndim <= 1:
        arr = np.atleast_1d(arr)
        if arr.size == 1:
            arr = np.repeat(arr, nu)
        if arr.size != nu:
            raise ValueError(f"{name} has {arr.size} entries but the data have {nu} inputs")
        arr = np.tile(arr, (ny, 1))
    elif arr.shape != (ny, nu):
        raise ValueError(f"{name} must be an int, one per input ({nu}) or one per output and input ({ny}, {nu}), "
                         f"got shape {arr.shape}")
    if np.any(arr < 0) or np.any(arr != np.round(arr)):
        raise ValueError(f"{name} must hold non-negative integers, got {arr.tolist()}")
    return arr.astype(int)


def _holdout_split(sample_weight: Any, n: int, holdout: float) -> tuple[np.ndarray, int, int, np.ndarray]:
    """The inner fit weights and the hold-out of :func:`select_by_holdout`: with ``n_end`` one past the last sample
    of positive weight, the samples from ``n_in = round(n_end * (1 - holdout))`` to ``n_end`` get zero weight;
    returns (inner weights, n_in, n_end, mask of the held-out samples that have positive weight)."""
    if not 0.0 < float(holdout) < 1.0:
        raise ValueError(f"holdout must be in (0, 1), got {holdout!r}")
    HammersteinWiener._sqrt_weights(sample_weight, n)   # validates the weights
    base = np.ones(n) if sample_weight is None else np.asarray(sample_weight, dtype=float).reshape(-1)
    n_end = int(np.flatnonzero(base > 0)[-1]) + 1
    n_in = round(n_end * (1.0 - float(holdout)))
    w = np.where(np.arange(n) < n_in, base, 0.0)
    keep = base[n_in:n_end] > 0
    if not np.any(w > 0) or not np.any(keep):
        raise ValueError(f"holdout {holdout!r} leaves no weighted sample to fit on or none to score on")
    return w, n_in, n_end, keep


def _holdout_fit(model: HammersteinWiener, u: np.ndarray, Y: np.ndarray, n_in: int, n_end: int,
                 keep: np.ndarray) -> float:
    """Mean FIT (%) over the outputs on the held-out samples of the output simulated through the record from an
    x(0) estimated on the fitted part; -inf for a non-finite result."""
    y_hat = model.predict(u[:n_end], y0=Y[:n_in])[n_in:]
    score = float(np.mean(np.atleast_1d(fit_percent(Y[n_in:n_end][keep], y_hat[keep]))))
    return score if np.isfinite(score) else -np.inf


@register_model("hammerstein_wiener")
class HammersteinWiener(BaseEstimator):
    """Hammerstein-Wiener model: one static block per input, one ``B_ji/F_ji`` per (output, input) pair, one static
    block per output (MISO or MIMO).

    Parameters
    ----------
    input_blocks : sequence of StaticNonlinearity, optional
        One block per input (see :mod:`ident.hammerstein_wiener.blocks`); default: identity on every input.
        The blocks given are templates: ``fit`` works on copies (``input_blocks_``).
    output_block : StaticNonlinearity or sequence of them, optional
        The output block h (default identity), e.g. ``Saturation(lower=w_min)``: one block used (as copies) for
        every output, or one per output.
    nb, nf, nk : int, sequence of int, or nested sequence
        Numerator length, denominator order and delay of each ``B_ji/F_ji`` (Paper IV: 2, 2, 1): one value, one per
        input (the same for every output) or one per (output, input) pair (shape (n_outputs, n_inputs)).
    regularization : float
        Weight of the ridge term on the static parameters (see module docstring; 0 switches it off).
    max_nfev : int
        Iteration budget of the optimiser (residual evaluations per fit).
    tol : float
        ``ftol``, ``xtol`` and ``gtol`` of the optimiser (:func:`~ident.linear._lsq.levenberg_marquardt`).
    init_model : OutputError, optional
        A fitted output-error model (same inputs, outputs, orders) to start the linear block from, instead of
        fitting one on the inputs passed through the initial static blocks. Also a fitted HammersteinWiener (its
        linear block is used), or an unfitted HammersteinWiener template, fitted first on the data given to ``fit``.
    smoothness : float or sequence of float
        Weight of the roughness penalty on the static blocks (see module docstring); a sequence is a grid chosen by
        the hold-out inside the estimation data.
    holdout : float
        Fraction of the estimation data (its end) held out to choose ``smoothness`` from a grid and to score random
        restarts.
    unit_gain : bool
        Give one ``B_ji/F_ji`` behind each free, scalable input block a static gain of +-1 (module docstring).
    initial : {"zero", "steady"}
        The linear block's state the fit assumes at the first sample: zero, or at rest at the first input.
        (Prediction starts from zero or from an estimated state either way, see :meth:`predict`.)
    start : {"auto", "identity", "data"}
        The deterministic start (module docstring).
    n_restarts : int or "auto"
        Random restarts scored on the hold-out (module docstring); 0 switches them off.
    random_state : int or None
        Seed of the random restarts (None: fresh entropy, not reproducible).

    Attributes
    ----------
    input_blocks_ : list of StaticNonlinearity
    input_params_ : list of ndarray
        Parameters of each input block.
    output_blocks_ : list of StaticNonlinearity
        One per output.
    output_params_ : list of ndarray
        Parameters of each output block.
    b_ : ndarray, shape (n_outputs, n_inputs, max(nk + nb))
        Numerators in powers of q^-1 (leading delay zeros included), as :class:`~ident.linear.OutputError`.
    f_ : ndarray, shape (n_outputs, n_inputs, max(nf) + 1)
        Monic denominators.
    A_, B_, C_, D_ : ndarray
        State-space realisation of the linear block (input v, output w); its state is the model state.
    cost_, initial_cost_ : float
        Mean squared simulation error on the estimation data (over samples and outputs) after the fit and at its
        start.
    start_ : str
        The start the fit came from: "identity", "data", "model" (``init_model``) or "random".
    restart_scores_ : list of float
        Hold-out FIT (%) of the deterministic start and of each random restart (empty without restarts).
    nfev_ : int
        Residual evaluations of the final fit.
    smoothness_ : float
        The smoothness weight used (chosen from the grid when ``smoothness`` is a sequence).
    holdout_scores_ : dict
        Hold-out FIT (%) per grid value (empty when ``smoothness`` is a single value).
    """

    def __init__(self, input_blocks: Sequence[StaticNonlinearity] | None = None,
                 output_block: StaticNonlinearity | Sequence[StaticNonlinearity] | None = None,
                 nb: int | Sequence[int] = 2, nf: int | Sequence[int] = 2, nk: int | Sequence[int] = 1,
                 regularization: float = 1e-3, max_nfev: int = 200, tol: float = 1e-8,
                 init_model: OutputError | HammersteinWiener | None = None,
                 smoothness: float | Sequence[float] = 0.0, holdout: float = 0.25, unit_gain: bool = False,
                 initial: str = "zero", start: str = "auto", n_restarts: int | str = "auto",
                 random_state: int | None = 0) -> None:
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
        self.start = start
        self.n_restarts = n_restarts
        self.random_state = random_state

    # ----------------------------------------------------------------------------------------------- fit
    def fit(self, u: Any, y: Any, sample_weight: Any = None) -> HammersteinWiener:
        """Minimise the simulation error from the chosen start (module docstring); returns ``self``.

        ``y`` has one column per output. ``sample_weight`` (shape (N,), >= 0) weights each sample's squared
        simulation error (all outputs alike); the model is still simulated through every sample, so zero weights
        leave a gap in the criterion, not in the record (blocked cross-validation on one record).

        Raises ``ValueError`` for NaN/inf, mismatched lengths, constant inputs, an output constant over all samples
        (``"y is constant ..."``), a wrong number of input or output blocks, bad options or too few samples.
        """
        grid = np.atleast_1d(np.asarray(self.smoothness, dtype=float))
        if grid.ndim != 1 or grid.size == 0 or np.any(~np.isfinite(grid)) or np.any(grid < 0):
            raise ValueError(f"smoothness must be a non-negative number or a sequence of them, got "
                             f"{self.smoothness!r}")
        self._check_options()
        scores: dict[float, float] = {}
        if np.ndim(self.smoothness) > 0 and grid.size > 1:
            # smoother first, so a tie goes to the smoother value (the earlier candidate wins ties)
            lams = sorted({float(lam) for lam in grid}, reverse=True)
            templates = [self.clone(smoothness=lam) for lam in lams]
            fits = _holdout_scores(templates, u, y, self.holdout, sample_weight)
            scores = dict(zip(lams, fits, strict=True))
            best = lams[int(np.argmax(fits))]
        else:
            best = float(grid[0])
        self._fit_once(u, y, best, sample_weight)
        self.smoothness_ = best
        self.holdout_scores_ = scores
        return self

    def _check_options(self) -> None:
        if self.start not in ("auto", "identity", "data"):
            raise ValueError(f"start must be 'auto', 'identity' or 'data', got {self.start!r}")
        if self.n_restarts != "auto":
            try:
                ok = int(self.n_restarts) == self.n_restarts and self.n_restarts >= 0
            except (TypeError, ValueError):
                ok = False
            if not ok:
                raise ValueError(f"n_restarts must be a non-negative integer or 'auto', got {self.n_restarts!r}")
        if self.initial not in ("zero", "steady"):
            raise ValueError(f"initial must be 'zero' or 'steady', got {self.initial!r}")

    def _n_restarts(self, st: Structure) -> int | None:
        """Random restarts, or None when "auto" decides after seeing the deterministic start."""
        if self.n_restarts == "auto":
            if any(b.even for b in st.blocks + st.outs):
                return AUTO_RESTARTS
            flexible = any(b.n_free() and b.linear_in_params() and b.n_params() > 2 for b in st.outs)
            return None if flexible and self.init_model is None else 0
        return int(self.n_restarts)

    def _fit_once(self, u: Any, y: Any, smoothness: float, sample_weight: Any = None) -> HammersteinWiener:
        u_arr, Y, base = self._validate(u, y)
        n = len(Y)
        restarts = self._n_restarts(base)
        det = None
        if restarts is None:
            # a flexible output block (piecewise-linear, polynomial): restart when the start explains little
            det = self._deterministic_start(base, u_arr, Y, sample_weight)
            sw = self._sqrt_weights(sample_weight, n)
            e = sw[:, None] * (Y - det[0].simulate(det[1], u_arr, False)[0])
            d = sw[:, None] * (Y - np.average(Y, axis=0, weights=sw ** 2))
            r2 = 1.0 - float(np.sum(e ** 2)) / max(float(np.sum(d ** 2)), 1e-300)
            restarts = AUTO_RESTARTS if r2 < AUTO_RESTART_R2 else 0
        scores: list[float] = []
        if restarts:
            w_in, n_in, n_end, keep = _holdout_split(sample_weight, n, self.holdout)
            st, th0, how = self._deterministic_start(base, u_arr, Y, w_in)
            rng = np.random.default_rng(self.random_state)
            run = longest_run(w_in > 0)
            starts = [(th0, how)] + [(random_start(st, u_arr, Y, run, rng), "random") for _ in range(restarts)]
            fitted = []
            for th_start, label in starts:
                th = self._solve(st, th_start, u_arr, Y, w_in, smoothness)[0]
                cand = self.clone()
                cand._store(st, th)
                try:
                    score = _holdout_fit(cand, u_arr, Y, n_in, n_end, keep)
                except (ValueError, np.linalg.LinAlgError):
                    score = -np.inf
                scores.append(score)
                fitted.append((th, label))
            th0, how = fitted[int(np.argmax(scores))]
        else:
            st, th0, how = det if det is not None else self._deterministic_start(base, u_arr, Y, sample_weight)
        th, cost, cost0, res = self._solve(st, th0, u_arr, Y, sample_weight, smoothness)
        self._store(st, th)
        self.cost_ = cost
        self.initial_cost_ = cost0
        self.start_ = how
        self.restart_scores_ = scores
        self.nfev_ = int(res.nfev)
        return self

    def _validate(self, u: Any, y: Any) -> tuple[np.ndarray, np.ndarray, Structure]:
        """Check data and options; the working structure with copies of the blocks and the orders."""
        nu, ny = data_columns(u, y, "Hammerstein-Wiener model")
        blocks = [Identity() for _ in range(nu)] if self.input_blocks is None else list(self.input_blocks)
        if len(blocks) != nu:
            raise ValueError(f"{len(blocks)} input blocks for {nu} inputs")
        if not all(isinstance(b, StaticNonlinearity) for b in blocks):
            raise TypeError("input_blocks must be StaticNonlinearity instances (see ident.hammerstein_wiener)")
        if self.output_block is None:
            outs: list[Any] = [Identity() for _ in range(ny)]
        elif isinstance(self.output_block, StaticNonlinearity):
            outs = [self.output_block.copy() for _ in range(ny)]
        else:
            outs = list(self.output_block)
            if len(outs) != ny:
                raise ValueError(f"{len(outs)} output blocks for {ny} outputs (give one block for all or one per "
                                 "output)")
        if not all(isinstance(b, StaticNonlinearity) for b in outs):
            raise TypeError("output_block must be a StaticNonlinearity instance or a sequence of them")
        nb, nf, nk = (_orders(v, ny, nu, k) for v, k in ((self.nb, "nb"), (self.nf, "nf"), (self.nk, "nk")))
        st = Structure([b.copy() for b in blocks], [b.copy() for b in outs], nb, nf, nk,
                       steady=self.initial == "steady")
        n_par = int(nb.sum(axis=1).max() + nf.sum(axis=1).max()) + sum(b.n_free() for b in st.blocks) + \
            max(b.n_free() for b in st.outs)
        u_arr, Y = validate_fit_data(u, y, n_par, int((nk + nb).max()), "Hammerstein-Wiener model")
        st.p0_in = [b.initial_params(u_arr[:, i]) for i, b in enumerate(st.blocks)]
        return u_arr, Y, st

    def _deterministic_start(self, base: Structure, u: np.ndarray, Y: np.ndarray, sample_weight: Any
                             ) -> tuple[Structure, np.ndarray, str]:
        """The start of the fit (module docstring): (structure, theta, which)."""
        run = longest_run(self._sqrt_weights(sample_weight, len(Y)) > 0)
        lin = self.init_model
        if lin is not None:
            if isinstance(lin, HammersteinWiener) and not hasattr(lin, "b_"):
                # a template: fit it on these data (same weights) first
                lin = HammersteinWiener(**lin.get_params()).fit(u, Y, sample_weight=sample_weight)
            st, th, _ = linear_start(base, u, Y, base.p0_in, run, lin, self.unit_gain, False, self.max_nfev)
            return st, th, "model"
        cands: list[tuple[Structure, np.ndarray, str]] = []
        lin_identity = None
        if self.start in ("auto", "identity"):
            st, th, lin_identity = linear_start(base, u, Y, base.p0_in, run, None, self.unit_gain, False,
                                                self.max_nfev)
            cands.append((st, th, "identity"))
        if self.start in ("auto", "data"):
            p_data = overparametrised_inputs(base, u, Y, run)
            fit_out = any(b.n_free() and (b.linear_in_params() or b.even) for b in base.outs)
            if p_data is not None or fit_out or self.start == "data":
                # the same input blocks as the identity start: its linear model serves again
                lin = lin_identity if p_data is None else None
                try:
                    st, th, _ = linear_start(base, u, Y, base.p0_in if p_data is None else p_data, run, lin,
                                             self.unit_gain, True, self.max_nfev)
                    cands.append((st, th, "data"))
                except ValueError:
                    if not cands:
                        raise
        if len(cands) == 1:
            return cands[0]
        sw = self._sqrt_weights(sample_weight, len(Y))
        costs = [float(np.sum((sw[:, None] * (Y - st.simulate(th, u, False)[0])) ** 2)) for st, th, _ in cands]
        costs = [c if np.isfinite(c) else np.inf for c in costs]
        return cands[int(np.argmin(costs))]

    def _solve(self, st: Structure, th0: np.ndarray, u: np.ndarray, Y: np.ndarray, sample_weight: Any,
               smoothness: float) -> tuple[np.ndarray, float, float, Any]:
        """Minimise the weighted simulation error (+ ridge toward th0's static parameters, + roughness) from th0;
        returns (theta, mse, mse at the start, solver result). Never worse than the start."""
        sw = self._sqrt_weights(sample_weight, len(Y))
        n_eff = float(np.sum(sw ** 2))
        ny = st.ny
        sw_all = np.tile(sw, ny)
        idx = st.static_index()
        lo, hi = st.bounds()
        th0 = np.clip(th0, lo, hi)
        ref = th0[idx]
        wts = np.sqrt(max(float(self.regularization), 0.0)) / np.maximum(np.abs(ref), 1.0)
        use_reg = self.regularization > 0 and idx.size > 0
        # roughness rows: sqrt(smoothness * N) * R_i p_i for every free input block that has a roughness measure
        rough_rows: list[np.ndarray] = []
        s_in = st.slices()[0]
        for blk, s in zip(st.blocks, s_in, strict=True):
            R = blk.roughness_matrix() if smoothness > 0 and blk.n_free() else None
            if R is not None and R.size:
                rows = np.zeros((R.shape[0], th0.size))
                rows[:, s] = np.sqrt(smoothness * n_eff) * R
                rough_rows.append(rows)
        Rr = np.vstack(rough_rows) if rough_rows else np.zeros((0, th0.size))
        y_flat = Y.T.ravel()
        reg_rows = np.zeros((idx.size, th0.size))
        reg_rows[np.arange(idx.size), idx] = wts

        def resid(th: np.ndarray) -> np.ndarray:
            e = sw_all * (y_flat - st.simulate(th, u, False)[0].T.ravel())
            parts = [e, Rr @ th]
            if use_reg:
                parts.append(wts * (th[idx] - ref))
            return np.concatenate(parts)

        # one Jacobian buffer for the fit: the simulation's rows on top, the constant penalty rows below
        n_sim = ny * len(Y)
        buf = np.zeros((n_sim + Rr.shape[0] + (idx.size if use_reg else 0), th0.size))
        buf[n_sim:n_sim + Rr.shape[0]] = Rr
        if use_reg:
            buf[n_sim + Rr.shape[0]:] = reg_rows

        def jac(th: np.ndarray) -> np.ndarray:
            st.simulate(th, u, True, out=buf)
            buf[:n_sim] *= -sw_all[:, None]
            return buf

        def mse(th: np.ndarray) -> float:
            return float(np.sum((sw_all * (y_flat - st.simulate(th, u, False)[0].T.ravel())) ** 2) / (n_eff * ny))

        st.bind(u)
        cost0 = mse(th0)
        bounded = bool(np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)))
        res = levenberg_marquardt(resid, jac, th0, bounds=(lo, hi) if bounded else None, max_nfev=self.max_nfev,
                                  ftol=self.tol, xtol=self.tol, gtol=self.tol)
        th = res.x
        cost = mse(th)
        st.bind(None)
        if not np.isfinite(cost) or not cost <= cost0:
            th, cost = th0, cost0
        return th, cost, cost0, res

    @staticmethod
    def _sqrt_weights(sample_weight: Any, n: int) -> np.ndarray:
        if sample_weight is None:
            return np.ones(n)
        w = np.asarray(sample_weight, dtype=float).reshape(-1)
        if w.size != n or np.any(~np.isfinite(w)) or np.any(w < 0) or not np.any(w > 0):
            raise ValueError(f"sample_weight must be {n} finite non-negative weights, not all zero")
        return np.sqrt(w)

    def _store(self, st: Structure, th: np.ndarray) -> None:
        p_in, bs, etas, p_out = st.unpack(th)
        ny, nu = st.ny, st.nu
        self.input_blocks_ = [copy.deepcopy(b) for b in st.blocks]
        self.input_params_ = [np.array(p, dtype=float) for p in p_in]
        self.output_blocks_ = [copy.deepcopy(b) for b in st.outs]
        self.output_params_ = [np.array(p, dtype=float) for p in p_out]
        lb = int((st.nk + st.nb).max())
        self.b_ = np.zeros((ny, nu, lb))
        self.f_ = np.zeros((ny, nu, int(st.nf.max()) + 1))
        for j in range(ny):
            for i in range(nu):
                nk, nb, nf = int(st.nk[j, i]), int(st.nb[j, i]), int(st.nf[j, i])
                self.b_[j, i, nk:nk + nb] = bs[j][i]
                self.f_[j, i, :nf + 1] = poly_from_reflection(np.tanh(etas[j][i]))[0]
        self.n_params_ = int(th.size)
        self._realise()

    def _realise(self) -> None:
        ny, nu = self.b_.shape[:2]
        parts = [(tf_to_ss(self.b_[j, i], self.f_[j, i]), j, i) for j in range(ny) for i in range(nu)]
        A = block_diag(*[p[0][0] for p in parts])
        n = A.shape[0]
        B = np.zeros((n, nu))
        C = np.zeros((ny, n))
        D = np.zeros((ny, nu))
        o = 0
        for (Ai, Bi, Ci, Di), j, i in parts:
            m = Ai.shape[0]
            B[o:o + m, i] = Bi[:, 0]
            C[j, o:o + m] = Ci[0]
            D[j, i] = Di[0, 0]
            o += m
        self.A_, self.B_, self.C_, self.D_ = A, B, C, D

    # ----------------------------------------------------------------------------------------- simulation
    @property
    def n_inputs_(self) -> int:
        check_is_fitted(self, "b_")
        return self.b_.shape[1]

    @property
    def n_outputs_(self) -> int:
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
                                enumerate(zip(self.input_blocks_, self.input_params_, strict=True))])

    def output_nonlinearity(self, w: Any) -> np.ndarray:
        """h(w) for the linear block's outputs w (shape (N,) for one output, or (N, n_outputs)); same shape back."""
        check_is_fitted(self, "b_")
        w = np.asarray(w, dtype=float)
        if w.ndim == 1 and self.n_outputs_ == 1:
            return self.output_blocks_[0].value(w, self.output_params_[0])
        w2 = w.reshape(len(w), -1)
        if w2.shape[1] != self.n_outputs_:
            raise ValueError(f"w must have {self.n_outputs_} columns, got shape {w.shape}")
        return np.column_stack([b.value(w2[:, j], p) for j, (b, p) in
                                enumerate(zip(self.output_blocks_, self.output_params_, strict=True))])

    def _y(self, name: str, y: Any) -> np.ndarray:
        y = np.asarray(y, dtype=float)
        if y.ndim == 1 and self.n_outputs_ > 1 and y.size == self.n_outputs_:
            y = y[None, :]
        return as_2d(name, y, n_columns=self.n_outputs_)

    def initial_state(self, u: Any, y: Any, n_iter: int = 8) -> np.ndarray:
        """The linear block's x(0) that best explains the measured ``y`` (shape (n0, n_outputs)) given ``u``
        (Gauss-Newton through the output blocks from x(0) = 0 and from the steady state for the first input, the
        better kept; truncated steps, step halving so the squared error never rises; samples where an output block
        saturates carry no information)."""
        v = self.transform_inputs(u)
        y = self._y("y", y)
        n0 = check_same_length(u=v, y=y)
        A, B, C, D = self.A_, self.B_, self.C_, self.D_
        ny, n = self.n_outputs_, A.shape[0]
        w_zero = simulate_ss(A, B, C, D, v)[0]
        obs = np.empty((n0, ny, n))
        m = C.copy()
        for t in range(n0):
            obs[t] = m
            m = m @ A

        def out(x: np.ndarray) -> np.ndarray:
            return self.output_nonlinearity(w_zero + obs @ x).reshape(n0, ny)

        def sse(x: np.ndarray) -> float:
            return float(np.sum((y - out(x)) ** 2))

        def gauss_newton(x0: np.ndarray) -> tuple[np.ndarray, float]:
            cost = sse(x0)
            for _ in range(n_iter):
                w = w_zero + obs @ x0
                r = (y - out(x0)).ravel()
                dh = np.column_stack([b.dx(w[:, j], p) for j, (b, p) in
                                      enumerate(zip(self.output_blocks_, self.output_params_, strict=True))])
                J = (dh[:, :, None] * obs).reshape(n0 * ny, n)
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
        starts = [np.zeros(n)]
        try:
            starts.append(np.linalg.solve(np.eye(n) - A, B @ v[0]))
        except np.linalg.LinAlgError:
            pass
        best = min((gauss_newton(x) for x in starts if np.all(np.isfinite(x))), key=lambda xc: xc[1])
        return best[0]

    def predict(self, u: Any, y0: Any = None, *, x0: Any = None) -> np.ndarray:
        """Simulated output, shape (N, n_outputs).

        Parameters
        ----------
        u : array_like, shape (N, n_inputs)
        y0 : array_like, shape (n0, n_outputs) (or (n0,) for one output), optional
            Measured outputs at the start; x(0) is then estimated from them (:meth:`initial_state`), like the
            linear models. Default x(0) = 0, the state the fit assumes.
        x0 : array_like, shape (n_states,), optional
            Explicit initial state of the linear block.
        """
        u = self._u(u)
        if x0 is not None:
            x0 = as_vector("x0", x0, self.n_states_, "values (one per state of the linear block)")
        elif y0 is not None:
            y0a = self._y("y0", y0)
            n0 = min(len(y0a), len(u))
            x0 = self.initial_state(u[:n0], y0a[:n0])
        v = self.transform_inputs(u)
        w, _ = simulate_ss(self.A_, self.B_, self.C_, self.D_, v, x0)
        return self.output_nonlinearity(w).reshape(len(u), self.n_outputs_)

    def predict_k_step(self, u: Any, y: Any, k: int) -> np.ndarray:
        """k-step-ahead prediction. The model has no noise model (output-error structure), so every horizon gives
        the simulated output from the x(0) estimated on the record (as the linear output-error model)."""
        u_arr = self._u(u)
        y_arr = self._y("y", y)
        check_same_length(u=u_arr, y=y_arr)
        if int(k) != k or k < 1:
            raise ValueError(f"k must be a positive integer number of steps, got {k}")
        return self.predict(u_arr, y0=y_arr)

    # ---------------------------------------------------------------------------------------------- export
    def to_casadi(self) -> Any:
        """``casadi.Function('step', [x, u], [x_next, y])``: x the linear block's state, u the raw inputs, y one
        entry per output."""
        import casadi as ca

        check_is_fitted(self, "b_")
        x = ca.SX.sym("x", self.n_states_)
        u = ca.SX.sym("u", self.n_inputs_)
        v = ca.vertcat(*[b.casadi(u[i], p) for i, (b, p) in
                         enumerate(zip(self.input_blocks_, self.input_params_, strict=True))])
        x_next = ca.mtimes(ca.DM(self.A_), x) + ca.mtimes(ca.DM(self.B_), v)
        w = ca.mtimes(ca.DM(self.C_), x) + ca.mtimes(ca.DM(self.D_), v)
        y = ca.vertcat(*[b.casadi(w[j], p) for j, (b, p) in enumerate(zip(self.output_blocks_,
                                                                          self.output_params_, strict=True))])
        return ca.Function("step", [x, u], [x_next, y], ["x", "u"], ["x_next", "y"])

    # ---------------------------------------------------------------------------------------------- saving
    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        check_is_fitted(self, "b_")
        params = {k: v for k, v in self.get_params().items() if k not in ("init_model",)}
        params["input_blocks"] = None if self.input_blocks is None else [b.to_dict() for b in self.input_blocks]
        ob = self.output_block
        params["output_block"] = None if ob is None else (ob.to_dict() if isinstance(ob, StaticNonlinearity) else
                                                          [b.to_dict() for b in ob])
        meta = {"params": params, "input_blocks_": [b.to_dict() for b in self.input_blocks_],
                "output_blocks_": [b.to_dict() for b in self.output_blocks_], "cost_": self.cost_,
                "initial_cost_": self.initial_cost_, "n_params_": self.n_params_}
        arrays = {"b_": self.b_, "f_": self.f_}
        for i, p in enumerate(self.input_params_):
            arrays[f"input_params_{i}"] = p
        for j, p in enumerate(self.output_params_):
            arrays[f"output_params_{j}"] = p
        return meta, arrays

    @classmethod
    def _from_state(cls, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> HammersteinWiener:
        p = dict(meta["params"])
        p["input_blocks"] = None if p["input_blocks"] is None else [block_from_dict(d) for d in p["input_blocks"]]
        ob = p["output_block"]
        p["output_block"] = None if ob is None else (block_from_dict(ob) if isinstance(ob, dict) else
                                                     [block_from_dict(d) for d in ob])
        for k in ("nb", "nf", "nk", "smoothness"):
            if isinstance(p.get(k), list):
                p[k] = tuple(tuple(v) if isinstance(v, list) else v for v in p[k])
        obj = cls(**p)
        obj.input_blocks_ = [block_from_dict(d) for d in meta["input_blocks_"]]
        obj.input_params_ = [np.asarray(arrays[f"input_params_{i}"], dtype=float)
                             for i in range(len(obj.input_blocks_))]
        obj.b_ = np.asarray(arrays["b_"], dtype=float)
        obj.f_ = np.asarray(arrays["f_"], dtype=float)
        if "output_blocks_" in meta:
            obj.output_blocks_ = [block_from_dict(d) for d in meta["output_blocks_"]]
            obj.output_params_ = [np.asarray(arrays[f"output_params_{j}"], dtype=float)
                                  for j in range(len(obj.output_blocks_))]
        else:   # files written before the multi-output model: one output, 2-D b_ and f_
            obj.output_blocks_ = [block_from_dict(meta["output_block_"])]
            obj.output_params_ = [np.asarray(arrays["output_params_"], dtype=float)]
            obj.b_, obj.f_ = obj.b_[None], obj.f_[None]
        obj.cost_ = float(meta["cost_"])
        obj.initial_cost_ = float(meta["initial_cost_"])
        obj.n_params_ = int(meta["n_params_"])
        obj._realise()
        return obj


def wiener(output_block: StaticNonlinearity | Sequence[StaticNonlinearity], **kwargs: Any) -> HammersteinWiener:
    """A Wiener model: identity inputs, linear block, ``output_block`` (Paper IV's M-III with a Saturation)."""
    return HammersteinWiener(input_blocks=None, output_block=output_block, **kwargs)


def hammerstein(input_blocks: Sequence[StaticNonlinearity], **kwargs: Any) -> HammersteinWiener:
    """A Hammerstein model: static input blocks, linear block, identity output."""
    return HammersteinWiener(input_blocks=input_blocks, output_block=None, **kwargs)


def select_by_holdout(candidates: Sequence[HammersteinWiener], u: Any, y: Any, holdout: float = 0.25
                      ) -> tuple[HammersteinWiener, list[float]]:
    """Choose among unfitted model templates on the estimation data alone, then refit the choice on all of it.

    Each candidate is fitted with the last ``holdout`` fraction of the samples given zero weight (so it is fitted on
    the first part only, its linear start too) and scored by the FIT (mean over the outputs) over the held-out end
    of its output simulated through the whole record from an x(0) estimated on the fitted part: the model continues
    the record it was fitted on, as it will continue into new data (and as the validation data are scored). The best
    score wins (ties: the earlier candidate, so list simpler ones first); it is refitted on all samples. Candidates
    whose fit fails score -inf.

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
    """Hold-out FIT (%) of each unfitted template (:func:`_holdout_split`): each candidate is fitted with the
    held-out samples given zero weight and scored on those of them that have positive weight, its output simulated
    through the record from an x(0) estimated on the fitted part. A candidate whose fit fails scores -inf. Shared by
    :func:`select_by_holdout` and the ``smoothness`` grid of :meth:`HammersteinWiener.fit`. Zero-weight outputs
    enter neither fit nor score; the inputs of the whole record may still place the blocks' starting knots or
    scales (as in any fit with ``sample_weight``)."""
    u_arr, y_arr = as_2d("u", u), as_2d("y", y)
    n = check_same_length(u=u_arr, y=y_arr)
    w, n_in, n_end, keep = _holdout_split(sample_weight, n, holdout)
    scores: list[float] = []
    for cand in candidates:
        try:
            m = HammersteinWiener(**cand.get_params()).fit(u_arr, y_arr, sample_weight=w)
            score = _holdout_fit(m, u_arr, y_arr, n_in, n_end, keep)
        except (ValueError, np.linalg.LinAlgError):
            score = -np.inf
        scores.append(score)
    return scores
