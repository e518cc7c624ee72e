"""Starting points of the Hammerstein-Wiener fit.

* :func:`linear_start` -- the linear block from the best linear model (an output-error fit from the outputs of the
  input blocks at their given parameters to y, or a given model), the output blocks at their initial parameters or,
  for blocks linear in their parameters, fitted by least squares from the start's linear output to y.
* :func:`overparametrised_inputs` -- data-driven parameters of the input blocks that are linear in their
  parameters (piecewise-linear, polynomial, odd and even polynomial): the over-parametrisation method of Bai
  (1998, "An optimal two-stage identification algorithm for Hammerstein-Wiener nonlinear systems", Automatica 34(3))
  and Chang and Luus (1971). With the block ``g_i(u) = Phi_i(u) p_i`` the Hammerstein part of the model is linear in
  the products ``b_ik p_i``: an ARX regression of y on the lagged basis functions gives a matrix ``Theta_i``
  (lags x basis functions) per input whose best rank-one approximation ``b_i p_i^T`` (SVD) gives the block's shape.
  Unlike the identity start this finds non-monotone and even input nonlinearities, through which the best linear
  approximation vanishes.
* :func:`random_start` -- random restarts: random block parameters (:meth:`StaticNonlinearity.random_params`),
  random stable denominators, random numerators scaled to the output's spread, output blocks fitted as in the
  linear start.
"""
from __future__ import annotations

import copy
from typing import Any

import numpy as np
from scipy.linalg import lstsq

from ident.base import check_is_fitted
from ident.hammerstein_wiener._structure import Structure, eta_from_poly
from ident.linear import OutputError
from ident.linear._statespace import random_stable_poly, simulate_ss
from ident.linear.oe import poly_from_reflection


def longest_run(mask: np.ndarray) -> tuple[int, int]:
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


def block_outputs(st: Structure, u: np.ndarray, p_in: list[np.ndarray]) -> np.ndarray:
    """v (N, nu): the input blocks' outputs at ``p_in``."""
    return np.column_stack([b.value(u[:, i], p) for i, (b, p) in enumerate(zip(st.blocks, p_in, strict=True))])


def linear_start(st: Structure, u: np.ndarray, Y: np.ndarray, p_in: list[np.ndarray], run: tuple[int, int],
                 init_model: Any, unit_gain: bool, fit_outputs: bool, max_nfev: int
                 ) -> tuple[Structure, np.ndarray, Any]:
    """A copy of ``st`` set up at the best linear start for input parameters ``p_in``, its theta and the linear
    model used (None when the orders differ between outputs).

    ``run`` is the range of samples the output-error start is fitted on (the longest run of weighted samples);
    ``init_model`` a fitted OutputError or HammersteinWiener on the same inputs and outputs (or None);
    ``fit_outputs`` fits the output blocks that are linear in their parameters by least squares (else they start at
    their initial parameters).
    """
    st = copy.deepcopy(st)
    st.p0_in = [np.asarray(p, dtype=float) for p in p_in]
    ny, nu = st.ny, st.nu
    v0 = block_outputs(st, u, st.p0_in)
    lin = init_model
    if lin is None:
        a, b = run
        try:
            lin = OutputError(nb=tuple(st.nb[0]), nf=tuple(st.nf[0]), nk=tuple(st.nk[0]), max_nfev=max_nfev) \
                if _same_rows(st) else None
            if lin is not None:
                lin.fit(v0[a:b], Y[a:b])
                lin_b, lin_f = lin.b_, lin.f_
            else:   # orders differ between outputs: one MISO output-error model per output
                lin_b = np.zeros((ny, nu, int((st.nk + st.nb).max())))
                lin_f = np.zeros((ny, nu, int(st.nf.max()) + 1))
                for j in range(ny):
                    m = OutputError(nb=tuple(st.nb[j]), nf=tuple(st.nf[j]), nk=tuple(st.nk[j]),
                                    max_nfev=max_nfev).fit(v0[a:b], Y[a:b, j])
                    lin_b[j, :, :m.b_.shape[2]] = m.b_[0]
                    lin_f[j, :, :m.f_.shape[2]] = m.f_[0]
        except ValueError as err:
            part = "" if run == (0, len(Y)) else f" on the longest run of weighted samples ({a} to {b - 1})"
            raise ValueError("cannot fit the Hammerstein-Wiener model: its linear start, an output-error model "
                             "from the outputs of the initial input blocks (called u below) to y"
                             f"{part}, failed: {err}") from err
        w0 = _simulate_tf(lin_b, lin_f, v0)
    else:
        check_is_fitted(lin, "b_")
        lin_b, lin_f = np.asarray(lin.b_, dtype=float), np.asarray(lin.f_, dtype=float)
        if lin_b.ndim == 2:
            lin_b, lin_f = lin_b[None], lin_f[None]
        if lin_b.shape[:2] != (ny, nu):
            raise ValueError(f"init_model has {lin_b.shape[0]} outputs and {lin_b.shape[1]} inputs, but the data "
                             f"have {ny} and {nu}: it must be fitted on the same inputs and outputs")
        w0 = simulate_ss(lin.A_, lin.B_, lin.C_, lin.D_, v0)[0]
    st.p0_out = []
    for j, blk in enumerate(st.outs):
        p = blk.initial_params(w0[:, j])
        if fit_outputs and blk.n_free():
            a, b = run
            fitted = blk.fit_params(w0[a:b, j], Y[a:b, j])
            p = p if fitted is None else np.clip(fitted, *blk.bounds())
        st.p0_out.append(np.asarray(p, dtype=float))
    st.gain = np.full((ny, nu), np.nan)
    bs: list[list[np.ndarray]] = []
    etas: list[list[np.ndarray]] = []
    for j in range(ny):
        brow, erow = [], []
        for i in range(nu):
            nb, nf, nk = int(st.nb[j, i]), int(st.nf[j, i]), int(st.nk[j, i])
            b_i = np.zeros(nk + nb)
            m = min(b_i.size, lin_b.shape[2])
            b_i[:m] = lin_b[j, i, :m]
            f_i = np.zeros(nf + 1)
            m = min(f_i.size, lin_f.shape[2])
            f_i[:m] = lin_f[j, i, :m]
            brow.append(b_i[nk:nk + nb])
            erow.append(eta_from_poly(f_i) if nf else np.zeros(0))
        bs.append(brow)
        etas.append(erow)
    if unit_gain:
        _unit_gains(st, bs, etas)
    return st, st.pack(st.p0_in, bs, etas, st.p0_out), lin


def _same_rows(st: Structure) -> bool:
    return all(np.array_equal(a, a[:1].repeat(a.shape[0], axis=0)) for a in (st.nb, st.nf, st.nk))


def _simulate_tf(b: np.ndarray, f: np.ndarray, v: np.ndarray) -> np.ndarray:
    from scipy.signal import lfilter

    w = np.zeros((v.shape[0], b.shape[0]))
    for j in range(b.shape[0]):
        for i in range(b.shape[1]):
            if np.any(b[j, i]):
                w[:, j] += lfilter(b[j, i], f[j, i], v[:, i])
    return w


def _unit_gains(st: Structure, bs: list[list[np.ndarray]], etas: list[list[np.ndarray]]) -> None:
    """Give, for each free scalable input block, the ``B_ji/F_ji`` with the largest static gain of the start a gain
    of +-1 (its sign) and scale the block to carry the gain; the other outputs' pairs of that input are divided by
    the same factor (the model's output is unchanged)."""
    for i, blk in enumerate(st.blocks):
        if not blk.n_free():
            continue
        gains = np.array([float(np.sum(bs[j][i])) / float(np.sum(poly_from_reflection(np.tanh(etas[j][i]))[0]))
                          if st.nb[j, i] else 0.0 for j in range(st.ny)])
        j = int(np.argmax(np.abs(gains)))
        if abs(gains[j]) <= 1e-8:
            continue
        scaled = blk.scaled_params(st.p0_in[i], abs(gains[j]))
        if scaled is None:
            continue
        st.p0_in[i] = np.asarray(scaled, dtype=float)
        st.gain[j, i] = float(np.sign(gains[j]))
        for jj in range(st.ny):
            bs[jj][i] = bs[jj][i] / abs(gains[j])


def overparametrised_inputs(st: Structure, u: np.ndarray, Y: np.ndarray, run: tuple[int, int]
                            ) -> list[np.ndarray] | None:
    """Data-driven parameters of the free input blocks that are linear in their parameters (module docstring);
    the other blocks keep ``st.p0_in``. None when no block qualifies or the regression has too few samples.

    Each shape is scaled to the mean and SD of its input and signed to correlate positively with it (as the
    identity start), then fitted by the block's ``fit_params`` (bounds honoured).
    """
    which = [blk.n_free() > 0 and blk.linear_in_params() for blk in st.blocks]
    if not any(which):
        return None
    a, b = run
    ua, Ya = u[a:b], Y[a:b]
    bases = []
    for i, blk in enumerate(st.blocks):
        phi = blk.dp(ua[:, i], st.p0_in[i]) if which[i] else blk.value(ua[:, i], st.p0_in[i])[:, None]
        bases.append(phi - phi.mean(axis=0))
    lag = int(max((st.nk + st.nb).max(), st.nf.max()))
    n_cols = [int(st.nf[j].max()) + sum(int(st.nb[j, i]) * bases[i].shape[1] for i in range(st.nu)) + 1
              for j in range(st.ny)]
    if len(ua) - lag < 2 * max(n_cols):
        return None
    thetas: list[list[np.ndarray]] = [[] for _ in range(st.nu)]
    rows = slice(lag, len(ua))
    for j in range(st.ny):
        na = int(st.nf[j].max())
        cols = [-Ya[lag - k:len(ua) - k, j] for k in range(1, na + 1)]
        spans = []
        for i in range(st.nu):
            start = len(cols)
            for k in range(int(st.nk[j, i]), int(st.nk[j, i] + st.nb[j, i])):
                cols += list(bases[i][lag - k:len(ua) - k].T)
            spans.append((start, len(cols)))
        cols.append(np.ones(len(ua) - lag))
        X = np.column_stack(cols)
        coef = lstsq(X, Ya[rows, j], lapack_driver="gelsy")[0]   # QR with pivoting: rank-revealing, fast
        for i, (s0, s1) in enumerate(spans):
            if s1 > s0:
                thetas[i].append(coef[s0:s1].reshape(int(st.nb[j, i]), bases[i].shape[1]))
    p_in = [p.copy() for p in st.p0_in]
    for i, blk in enumerate(st.blocks):
        if not which[i] or not thetas[i]:
            continue
        M = np.vstack(thetas[i])
        if not np.all(np.isfinite(M)) or not np.any(M):
            continue
        shape = np.linalg.svd(M, full_matrices=False)[2][0]
        g = blk.dp(u[:, i], st.p0_in[i]) @ shape
        sd = float(np.std(g))
        if sd <= 0 or not np.isfinite(sd):
            continue
        g = (g - g.mean()) / sd
        if float(np.mean(g * (u[:, i] - u[:, i].mean()))) < 0:
            g = -g
        fitted = blk.fit_params(u[:, i], float(np.mean(u[:, i])) + float(np.std(u[:, i])) * g)
        if fitted is not None and np.all(np.isfinite(fitted)):
            p_in[i] = np.clip(fitted, *blk.bounds())
    return p_in


def random_start(st: Structure, u: np.ndarray, Y: np.ndarray, run: tuple[int, int], rng: np.random.Generator
                 ) -> np.ndarray:
    """A random theta for the structure ``st`` (its unit gains kept): random free input-block parameters, random
    stable denominators with time constants up to a tenth of the record, random numerators scaled so each linear
    output has the SD of its measured output, output blocks fitted as in :func:`linear_start` (linear in their
    parameters) or at their initial parameters."""
    a, b = run
    ua, Ya = u[a:b], Y[a:b]
    p_in = [blk.random_params(ua[:, i], rng) if blk.n_free() else p0
            for i, (blk, p0) in enumerate(zip(st.blocks, st.p0_in, strict=True))]
    p_in = [np.clip(p, *blk.bounds()) if blk.n_free() else p for blk, p in zip(st.blocks, p_in, strict=True)]
    v = block_outputs(st, ua, p_in)
    v = (v - v.mean(axis=0)) / np.maximum(v.std(axis=0), 1e-12)   # for scaling B only
    tau_max = max(10.0, len(ua) / 10.0)
    bs = [[rng.standard_normal(int(st.nb[j, i])) for i in range(st.nu)] for j in range(st.ny)]
    fs = [[random_stable_poly(int(st.nf[j, i]), rng, tau_max) for i in range(st.nu)] for j in range(st.ny)]
    from scipy.signal import lfilter

    for j in range(st.ny):
        w = sum(lfilter(np.r_[np.zeros(int(st.nk[j, i])), bs[j][i]], fs[j][i], v[:, i]) for i in range(st.nu))
        sd_w = float(np.std(w))
        scale = float(np.std(Ya[:, j])) / sd_w if sd_w > 0 else 1.0
        bs[j] = [bij * scale for bij in bs[j]]
    etas = [[eta_from_poly(fs[j][i]) if st.nf[j, i] else np.zeros(0) for i in range(st.nu)] for j in range(st.ny)]
    # the output blocks from the random linear output through the actual blocks
    theta = st.pack(p_in, bs, etas, st.p0_out)
    w0 = st.linear_outputs(theta, ua)
    p_out = []
    for j, blk in enumerate(st.outs):
        p = st.p0_out[j]
        if blk.n_free():
            fitted = blk.fit_params(w0[:, j], Ya[:, j])
            if fitted is not None and np.all(np.isfinite(fitted)):
                p = np.clip(fitted, *blk.bounds())
        p_out.append(p)
    return st.pack(p_in, st.unpack(theta)[1], etas, p_out)
