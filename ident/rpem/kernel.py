"""Compiled (numba) per-sample kernels of the RPEM: model step with its Jacobians, the Gauss-Newton recursion,
free-run simulation and the extended Kalman filter used for initialisation and k-step prediction.

Everything here works on plain arrays so that numba compiles it once; :mod:`ident.rpem.estimator` owns the
bookkeeping. Notation follows ALGORITHMS.md section 1:

* ``N`` states in ``d`` chains of length ``n`` (``N = n d``); chain ``k`` holds states ``k n .. k n + n - 1``, its
  output is its first state and its last state obeys ``dx/dt = sum_j theta_j phi_j`` over the terms it owns.
* The variable vector of the regressors is ``z = (x_1..x_N, w_1..w_{2m})`` where ``w = (u, u')`` is supplied per
  sample by the caller (inputs after transform, and their derivatives).
* A term is stored as up to ``F`` factors ``(variable index, power)`` in ``fvar``/``fpow`` with count ``nf``.

The step of the discretised model, with ``Ts = alpha T`` the scaled sampling period, returns ``x_next``,
``A = d x_next / d x`` and ``B = d x_next / d theta``, so the sensitivity recursion of the RPEM is simply
``S(t+T) = A S(t) + B`` (exactly the Euler / midpoint formulas of ALGORITHMS.md, multiplied out).
"""
from __future__ import annotations

import numpy as np

from scr_env.jit import njit  # numba.njit with the project's cache directory (never site-packages)

EULER = 0
MIDPOINT = 1

# Indices into the mutable scalar state vector of the recursion.
ST_GAMMA = 0  # normalised gain gamma(t), used for Lambda
ST_LAMBDA = 1  # forgetting factor lambda(t)
ST_STARTED = 2  # 1 once x(0) has been set from the first output sample
ST_REJECTED = 3  # number of candidate updates refused by the projection onto DM
ST_COUNT = 4  # number of samples processed
ST_BOUND_HITS = 5  # number of samples at which a state was clipped to the state bound (or reset from NaN)
N_ST = 6

# Indices into the float configuration vector.
CF_TS = 0  # scaled sampling period alpha * T
CF_METHOD = 1  # EULER or MIDPOINT
CF_LAM_RATE = 2  # lambda0 in lambda(t) = lambda0 lambda(t-1) + (1 - lambda0) lambda_inf
CF_LAM_INF = 3  # limit of the forgetting factor (1: gain ~ 1/t; < 1: tracking)
CF_MARGIN = 4  # delta: eigenvalues of the continuous-time linearisation must have real part < -delta
CF_XMAX = 5  # bound on |x|
CF_SMAX = 6  # bound on |dx/dtheta|
CF_UPDATE = 7  # 1: run the parameter update, 0: only propagate (evaluation)
CF_SUBSTEPS = 8  # integration sub-steps per sample (1: the thesis' single Euler / midpoint step)
CF_OUT_TYPE = 9  # static output function y = h(x1, eta): OUT_*
CF_OUT_Q = 10  # parameters eta per output
N_CF = 11

OUT_IDENTITY = 0  # y = x1
OUT_POLYNOMIAL = 1  # y = eta_0 + x1 + eta_2 x1^2 + ... + eta_q x1^q   (q = degree)
OUT_ABS = 2  # y = eta_0 + |x1|
OUT_SATURATION = 3  # y = min(max(x1, eta_0), eta_1)


@njit(cache=True, inline="always")
def _ipow(v, k):
    # Powers are small integers, mostly 1: a multiply loop beats the general pow().
    r = v
    for _ in range(k - 1):
        r *= v
    return r


@njit(cache=True)
def _regressors(xv, w, fvar, fpow, nf, n_states, phi, dphi):
    """phi_j(z) and d phi_j / d x (shape p x N) at z = (xv, w)."""
    p = phi.shape[0]
    for j in range(p):
        val = 1.0
        for f in range(nf[j]):
            v = fvar[j, f]
            zv = xv[v] if v < n_states else w[v - n_states]
            val *= _ipow(zv, fpow[j, f])
        phi[j] = val
        for i in range(n_states):
            dphi[j, i] = 0.0
        for f in range(nf[j]):
            v = fvar[j, f]
            if v >= n_states:
                continue
            k = fpow[j, f]
            der = k * _ipow(xv[v], k - 1) if k > 1 else 1.0
            for g in range(nf[j]):
                if g != f:
                    vg = fvar[j, g]
                    zg = xv[vg] if vg < n_states else w[vg - n_states]
                    der *= _ipow(zg, fpow[j, g])
            dphi[j, v] += der


@njit(cache=True)
def _rhs(xv, w, theta, fvar, fpow, nf, owner, n_chain, F, J, G, phi, dphi):
    """F = dx/dt, J = dF/dx (N x N) and G = dF/dtheta (N x p) of the chain model."""
    N = xv.shape[0]
    p = fvar.shape[0]  # the terms; theta may carry output parameters after them
    _regressors(xv, w, fvar, fpow, nf, N, phi, dphi)
    for i in range(N):
        for c in range(N):
            J[i, c] = 0.0
        for j in range(p):
            G[i, j] = 0.0
        if (i % n_chain) != n_chain - 1:
            F[i] = xv[i + 1]
            J[i, i + 1] = 1.0
        else:
            F[i] = 0.0
    for j in range(p):
        last = owner[j] * n_chain + n_chain - 1
        F[last] += theta[j] * phi[j]
        G[last, j] = phi[j]
        for c in range(N):
            J[last, c] += theta[j] * dphi[j, c]


@njit(cache=True, inline="always")
def _single_step(xv, ws, wh, theta, cfg, Ts, fvar, fpow, nf, owner, n_chain, x_next, A, B, need_b, work):
    """One Euler / midpoint step of length ``Ts`` (see :func:`model_step`)."""
    F0, J0, G0, F1, J1, G1, phi, dphi, xbar, M = work[:10]
    N = xv.shape[0]
    p = fvar.shape[0]  # the terms; theta may carry output parameters after them
    _rhs(xv, ws, theta, fvar, fpow, nf, owner, n_chain, F0, J0, G0, phi, dphi)
    if cfg[CF_METHOD] == EULER:
        for i in range(N):
            x_next[i] = xv[i] + Ts * F0[i]
            for c in range(N):
                A[i, c] = Ts * J0[i, c]
            A[i, i] += 1.0
            if need_b:
                for j in range(p):
                    B[i, j] = Ts * G0[i, j]
        return
    for i in range(N):
        xbar[i] = xv[i] + 0.5 * Ts * F0[i]
    _rhs(xbar, wh, theta, fvar, fpow, nf, owner, n_chain, F1, J1, G1, phi, dphi)
    # M = I + Ts/2 J0 = d xbar / dx;  A = I + Ts J1 M;  B = Ts (J1 (Ts/2) G0 + G1)
    for i in range(N):
        for c in range(N):
            M[i, c] = 0.5 * Ts * J0[i, c]
        M[i, i] += 1.0
    for i in range(N):
        x_next[i] = xv[i] + Ts * F1[i]
        for c in range(N):
            acc = 0.0
            for k in range(N):
                acc += J1[i, k] * M[k, c]
            A[i, c] = Ts * acc
        A[i, i] += 1.0
        if need_b:
            for j in range(p):
                acc = 0.0
                for k in range(N):
                    acc += J1[i, k] * G0[k, j]
                B[i, j] = Ts * (0.5 * Ts * acc + G1[i, j])


@njit(cache=True)
def model_step(xv, ws, wh, theta, cfg, fvar, fpow, nf, owner, n_chain, x_next, A, B, need_b, work):
    """One sample step of the discretised model from ``x`` with inputs ``ws`` (start) and ``wh`` (half step).

    Writes ``x_next``, ``A = dx_next/dx`` and, if ``need_b``, ``B = dx_next/dtheta``; ``theta`` holds the
    right-hand side's parameters only. ``work`` is a tuple of scratch arrays (see :func:`_make_work`); after the
    call ``work[1]`` holds ``dF/dx`` at ``(x, ws)``, which the projection onto DM tests.

    With ``m = cfg[CF_SUBSTEPS] > 1`` the sample interval is integrated in m steps of ``Ts / m``; the input at a
    sub-step is interpolated linearly between the sample's start value ``ws`` and its end value ``2 wh - ws`` (so
    a held input stays held), and ``A``, ``B`` are the chained derivatives of the m steps. ``m = 1`` is exactly
    the single step of ALGORITHMS.md.
    """
    m = int(cfg[CF_SUBSTEPS])
    if m <= 1:
        _single_step(xv, ws, wh, theta, cfg, cfg[CF_TS], fvar, fpow, nf, owner, n_chain, x_next, A, B, need_b, work)
        return
    N = xv.shape[0]
    p = fvar.shape[0]  # the terms; theta may carry output parameters after them
    nw = ws.shape[0]
    half = nw // 2
    h = cfg[CF_TS] / m
    xc, A1, B1, Aacc, Bacc, wsj, whj, J0keep = work[10:18]
    for i in range(N):
        xc[i] = xv[i]
        for c in range(N):
            Aacc[i, c] = 1.0 if i == c else 0.0
        if need_b:
            for j in range(p):
                Bacc[i, j] = 0.0
    for sub in range(m):
        f0 = sub / m
        f1 = (sub + 0.5) / m
        for k in range(nw):
            end = 2.0 * wh[k] - ws[k]
            if k < half:
                wsj[k] = ws[k] + f0 * (end - ws[k])
                whj[k] = ws[k] + f1 * (end - ws[k])
            else:  # derivatives: the start row's at the sample start, the half-step row's afterwards
                wsj[k] = ws[k] if sub == 0 else wh[k]
                whj[k] = wh[k]
        _single_step(xc, wsj, whj, theta, cfg, h, fvar, fpow, nf, owner, n_chain, x_next, A1, B1, need_b, work)
        if sub == 0:
            for i in range(N):
                for c in range(N):
                    J0keep[i, c] = work[1][i, c]
        # chain rule: Aacc <- A1 Aacc, Bacc <- A1 Bacc + B1
        for i in range(N):
            for c in range(N):
                acc = 0.0
                for k in range(N):
                    acc += A1[i, k] * Aacc[k, c]
                A[i, c] = acc
            if need_b:
                for j in range(p):
                    acc = B1[i, j]
                    for k in range(N):
                        acc += A1[i, k] * Bacc[k, j]
                    B[i, j] = acc
        for i in range(N):
            xc[i] = x_next[i]
            for c in range(N):
                Aacc[i, c] = A[i, c]
            if need_b:
                for j in range(p):
                    Bacc[i, j] = B[i, j]
    for i in range(N):
        for c in range(N):
            work[1][i, c] = J0keep[i, c]


@njit(cache=True)
def _make_work(N, p, nw):
    return (np.empty(N), np.empty((N, N)), np.empty((N, p)), np.empty(N), np.empty((N, N)), np.empty((N, p)),
            np.empty(p), np.empty((p, N)), np.empty(N), np.empty((N, N)),
            np.empty(N), np.empty((N, N)), np.empty((N, p)), np.empty((N, N)), np.empty((N, p)), np.empty(nw),
            np.empty(nw), np.empty((N, N)))


@njit(cache=True)
def output_value(x1, eta, k, cfg, dh_deta):
    """Static output function ``h(x1, eta_k)`` of output k (``cfg[CF_OUT_TYPE]``): returns ``(h, dh/dx1)`` and
    writes ``dh/deta_k`` (``cfg[CF_OUT_Q]`` values) into ``dh_deta``."""
    typ = int(cfg[CF_OUT_TYPE])
    q = int(cfg[CF_OUT_Q])
    if typ == OUT_IDENTITY:
        return x1, 1.0
    b = k * q
    if typ == OUT_POLYNOMIAL:
        y = eta[b] + x1
        d = 1.0
        dh_deta[0] = 1.0
        prev = x1
        for i in range(2, q + 1):
            cur = prev * x1
            y += eta[b + i - 1] * cur
            d += i * eta[b + i - 1] * prev
            dh_deta[i - 1] = cur
            prev = cur
        return y, d
    if typ == OUT_ABS:
        dh_deta[0] = 1.0
        if x1 >= 0.0:
            return eta[b] + x1, 1.0
        return eta[b] - x1, -1.0
    # OUT_SATURATION
    lo = eta[b]
    hi = eta[b + 1]
    dh_deta[0] = 0.0
    dh_deta[1] = 0.0
    if x1 < lo:
        dh_deta[0] = 1.0
        return lo, 0.0
    if x1 > hi:
        dh_deta[1] = 1.0
        return hi, 0.0
    return x1, 1.0


@njit(cache=True)
def _charpoly(M):
    """Coefficients c of det(sI - M) = c[0] s^N + ... + c[N] (Faddeev-LeVerrier; no LAPACK, so it compiles fast)."""
    N = M.shape[0]
    c = np.zeros(N + 1)
    c[0] = 1.0
    Mk = np.zeros((N, N))
    AM = np.zeros((N, N))
    for k in range(1, N + 1):
        for i in range(N):
            for j in range(N):
                acc = 0.0
                for q in range(N):
                    acc += M[i, q] * Mk[q, j]
                AM[i, j] = acc
        for i in range(N):
            for j in range(N):
                Mk[i, j] = AM[i, j]
            Mk[i, i] += c[k - 1]
        tr = 0.0
        for i in range(N):
            for q in range(N):
                tr += M[i, q] * Mk[q, i]
        c[k] = -tr / k
    return c


@njit(cache=True)
def _routh_stable(c):
    """Routh test: all roots of the polynomial c (c[0] > 0) in the open left half plane."""
    N = c.shape[0] - 1
    W = N // 2 + 2
    a = np.zeros(W)
    b = np.zeros(W)
    for j in range(W):
        if 2 * j <= N:
            a[j] = c[2 * j]
        if 2 * j + 1 <= N:
            b[j] = c[2 * j + 1]
    if a[0] <= 0.0:
        return False
    for _ in range(N):
        if b[0] <= 0.0:
            return False
        new = np.zeros(W)
        for j in range(W - 1):
            new[j] = (b[0] * a[j + 1] - a[0] * b[j + 1]) / b[0]
        a = b
        b = new
    return True


@njit(cache=True)
def _schur_stable(c):
    """Schur-Cohn step-down test: all roots of the monic polynomial c strictly inside the unit circle."""
    a = c.copy()
    n = a.shape[0] - 1
    while n > 0:
        k = a[n]
        if abs(k) >= 1.0:
            return False
        new = np.empty(n)
        for i in range(n):
            new[i] = (a[i] - k * a[n - i]) / (1.0 - k * k)
        a = new
        n -= 1
    return True


@njit(cache=True)
def is_hurwitz(J, margin):
    """True if every eigenvalue of ``J`` has real part below ``-margin``."""
    N = J.shape[0]
    if N == 1:
        return J[0, 0] < -margin
    if N == 2:
        # J + margin I is Hurwitz iff its trace is negative and its determinant positive.
        tr = J[0, 0] + J[1, 1] + 2.0 * margin
        det = (J[0, 0] + margin) * (J[1, 1] + margin) - J[0, 1] * J[1, 0]
        return tr < 0.0 and det > 0.0
    Js = J.copy()
    for i in range(N):
        Js[i, i] += margin
    return _routh_stable(_charpoly(Js))


@njit(cache=True)
def is_stable(A, radius):
    """True if every eigenvalue of ``A`` lies strictly inside the circle of the given radius."""
    N = A.shape[0]
    if N == 1:
        return abs(A[0, 0]) < radius
    if N == 2:
        # Jury test on A / radius: |det| < 1 and |trace| < 1 + det.
        tr = (A[0, 0] + A[1, 1]) / radius
        det = (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) / (radius * radius)
        return abs(det) < 1.0 and abs(tr) < 1.0 + det
    return _schur_stable(_charpoly(A / radius))


@njit(cache=True)
def _clip(v, bound):
    if v > bound:
        return bound
    if v < -bound:
        return -bound
    return v


@njit(cache=True)
def _inv_small(M, out):
    """Inverse of a small symmetric positive definite matrix via Cholesky; False if not positive definite.

    Written with loops rather than np.linalg so that the kernels compile without LAPACK bindings.
    """
    d = M.shape[0]
    if d == 1:
        if M[0, 0] <= 0.0:
            return False
        out[0, 0] = 1.0 / M[0, 0]
        return True
    L = np.zeros((d, d))
    for i in range(d):
        for j in range(i + 1):
            acc = 0.5 * (M[i, j] + M[j, i])
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            if i == j:
                if acc <= 0.0:
                    return False
                L[i, i] = np.sqrt(acc)
            else:
                L[i, j] = acc / L[j, j]
    Li = np.zeros((d, d))  # inverse of the lower-triangular factor
    for i in range(d):
        Li[i, i] = 1.0 / L[i, i]
        for j in range(i):
            acc = 0.0
            for k in range(j, i):
                acc -= L[i, k] * Li[k, j]
            Li[i, j] = acc / L[i, i]
    for i in range(d):
        for j in range(d):
            acc = 0.0
            for k in range(max(i, j), d):
                acc += Li[k, i] * Li[k, j]
            out[i, j] = acc
    return True


@njit(cache=True)
def _start_state(xv, S, Y, t, eta, cfg, n_chain):
    """x(0) = (y(0), 0, ...) per chain (y(0) less the output offset for the polynomial and |x| outputs), S = 0."""
    N = xv.shape[0]
    d = Y.shape[1]
    typ = int(cfg[CF_OUT_TYPE])
    q = int(cfg[CF_OUT_Q])
    for i in range(N):
        xv[i] = 0.0
        for j in range(S.shape[1]):
            S[i, j] = 0.0
    for k in range(d):
        off = eta[k * q] if (typ == OUT_POLYNOMIAL or typ == OUT_ABS) else 0.0
        xv[k * n_chain] = Y[t, k] - off


@njit(cache=True)
def rpem_run(WS, WH, Y, theta, P, Lam, xv, S, st, cfg, y_lo, y_hi, fvar, fpow, nf, owner, n_chain, Yhat):
    """Run the RPEM recursion over ``len(Y)`` samples, updating the estimator state in place.

    Parameters
    ----------
    WS, WH : (T, 2m) arrays
        Inputs ``(u, u')`` for the step *into* sample t, at the step start and at the half step.
    Y : (T, d) measured outputs.
    theta, P, Lam, xv, S, st : estimator state (modified in place). ``theta`` holds the right-hand side's
        parameters (as many as terms, ``fvar.shape[0]``) followed by the output functions' parameters eta
        (``cfg[CF_OUT_Q]`` per output). ``P`` is the inverse of the unnormalised Hessian ``R(t) / gamma(t)``
        over all of them; ``S = dx/dtheta`` covers the right-hand side's parameters.
    cfg : float configuration (``CF_*``).
    y_lo, y_hi : output saturation limits per output (applied after the output function).
    Yhat : (T, d) output buffer for the one-step predictions ``yhat(t | theta(t-1))``.
    """
    T = Y.shape[0]
    d = Y.shape[1]
    N = xv.shape[0]
    pf = fvar.shape[0]
    p = theta.shape[0]
    q = int(cfg[CF_OUT_Q])
    work = _make_work(N, pf, WS.shape[1])
    x_next = np.empty(N)
    A = np.empty((N, N))
    B = np.empty((N, pf))
    S_new = np.empty((N, pf))
    psi = np.empty((p, d))
    eps = np.empty(d)
    Ppsi = np.empty((p, d))
    Mm = np.empty((d, d))
    Mi = np.empty((d, d))
    L = np.empty((p, d))
    theta_c = np.empty(p)
    A_c = np.empty((N, N))
    B_dummy = np.empty((1, 1))
    dh_eta = np.zeros(max(q, 1))
    eta = theta[pf:]
    eta_c = theta_c[pf:]
    xmax = cfg[CF_XMAX]
    smax = cfg[CF_SMAX]
    typ = int(cfg[CF_OUT_TYPE])
    for t in range(T):
        if st[ST_STARTED] == 0.0:
            _start_state(xv, S, Y, t, eta, cfg, n_chain)
            st[ST_STARTED] = 1.0
        else:
            model_step(xv, WS[t], WH[t], theta, cfg, fvar, fpow, nf, owner, n_chain, x_next, A, B, True, work)
            for i in range(N):
                for j in range(pf):
                    acc = B[i, j]
                    for c in range(N):
                        acc += A[i, c] * S[c, j]
                    S_new[i, j] = _clip(acc, smax)
            hit = False
            for i in range(N):
                xv[i] = _clip(x_next[i], xmax)
                if not np.isfinite(xv[i]):
                    xv[i] = 0.0
                    hit = True
                elif x_next[i] > xmax or x_next[i] < -xmax:
                    hit = True
                for j in range(pf):
                    S[i, j] = S_new[i, j] if np.isfinite(S_new[i, j]) else 0.0
            if hit:
                st[ST_BOUND_HITS] += 1.0
        for k in range(d):
            x1 = xv[k * n_chain]
            if typ == OUT_IDENTITY:
                yk, dh = x1, 1.0
            else:
                yk, dh = output_value(x1, eta, k, cfg, dh_eta)
            active = yk <= y_lo[k] or yk >= y_hi[k]
            yh = min(max(yk, y_lo[k]), y_hi[k])
            Yhat[t, k] = yh
            eps[k] = Y[t, k] - yh
            for j in range(pf):
                psi[j, k] = 0.0 if active else dh * S[k * n_chain, j]
            if typ != OUT_IDENTITY:
                for j in range(pf, p):
                    psi[j, k] = 0.0
            if typ != OUT_IDENTITY and not active:
                for r in range(q):
                    psi[pf + k * q + r, k] = dh_eta[r]
        st[ST_COUNT] += 1.0
        if cfg[CF_UPDATE] == 0.0:
            continue
        lam = cfg[CF_LAM_RATE] * st[ST_LAMBDA] + (1.0 - cfg[CF_LAM_RATE]) * cfg[CF_LAM_INF]
        st[ST_LAMBDA] = lam
        gamma = st[ST_GAMMA] / (st[ST_GAMMA] + lam)
        st[ST_GAMMA] = gamma
        for a in range(d):
            for b in range(d):
                Lam[a, b] += gamma * (eps[a] * eps[b] - Lam[a, b])
        # P-form of R(t) = lambda R(t-1) + psi Lambda^-1 psi^T (matrix inversion lemma, d x d inverse only).
        for j in range(p):
            for k in range(d):
                acc = 0.0
                for c in range(p):
                    acc += P[j, c] * psi[c, k]
                Ppsi[j, k] = acc
        for a in range(d):
            for b in range(d):
                acc = lam * Lam[a, b]
                for j in range(p):
                    acc += psi[j, a] * Ppsi[j, b]
                Mm[a, b] = acc
        if not _inv_small(Mm, Mi):
            st[ST_REJECTED] += 1.0
            continue
        for j in range(p):
            for k in range(d):
                acc = 0.0
                for a in range(d):
                    acc += Ppsi[j, a] * Mi[a, k]
                L[j, k] = acc
        inv_lam = 1.0 / lam
        for j in range(p):
            for c in range(j, p):
                acc = 0.0
                for k in range(d):
                    acc += L[j, k] * Ppsi[c, k]
                v = (P[j, c] - acc) * inv_lam
                P[j, c] = v
                P[c, j] = v
        ok = True
        for j in range(p):
            acc = theta[j]
            for k in range(d):
                acc += L[j, k] * eps[k]
            theta_c[j] = acc
            if not np.isfinite(acc):
                ok = False
        if ok and typ == OUT_SATURATION:
            for k in range(d):
                if not eta_c[k * q] < eta_c[k * q + 1]:
                    ok = False
        if ok:
            # Projection onto DM: the continuous-time linearisation at the current point must have its
            # eigenvalues left of -delta, and the discretised step must be stable (work[1] holds J(x, u)).
            model_step(xv, WS[t], WH[t], theta_c, cfg, fvar, fpow, nf, owner, n_chain, x_next, A_c, B_dummy,
                       False, work)
            ok = is_hurwitz(work[1], cfg[CF_MARGIN]) and is_stable(A_c, 1.0)
        if ok:
            for j in range(p):
                theta[j] = theta_c[j]
        else:
            st[ST_REJECTED] += 1.0


@njit(cache=True)
def simulate(WS, WH, theta, eta, x0, cfg, y_lo, y_hi, fvar, fpow, nf, owner, n_chain, d, Yhat, X):
    """Free-run simulation from ``x0``: ``X[t]`` is the state at sample t, ``Yhat[t]`` its output. ``theta``: the
    right-hand side's parameters, ``eta``: the output functions'. Returns the number of samples at which a state
    was clipped to the state bound."""
    T = WS.shape[0]
    N = x0.shape[0]
    p = theta.shape[0]
    work = _make_work(N, p, WS.shape[1])
    xv = x0.copy()
    x_next = np.empty(N)
    A = np.empty((N, N))
    B = np.empty((1, 1))
    dh_eta = np.zeros(max(int(cfg[CF_OUT_Q]), 1))
    xmax = cfg[CF_XMAX]
    hits = 0
    for t in range(T):
        if t > 0:
            model_step(xv, WS[t], WH[t], theta, cfg, fvar, fpow, nf, owner, n_chain, x_next, A, B, False, work)
            hit = False
            for i in range(N):
                v = x_next[i]
                if not np.isfinite(v):
                    v = xmax if v > 0 else (-xmax if v < 0 else 0.0)
                    hit = True
                elif v > xmax or v < -xmax:
                    hit = True
                xv[i] = _clip(v, xmax)
            if hit:
                hits += 1
        for i in range(N):
            X[t, i] = xv[i]
        for k in range(d):
            yk, _ = output_value(xv[k * n_chain], eta, k, cfg, dh_eta)
            Yhat[t, k] = min(max(yk, y_lo[k]), y_hi[k])
    return hits


@njit(cache=True)
def _sandwich(F, P, Q, tmp):
    """P <- F P F^T + Q with loops (no BLAS binding to compile)."""
    n = P.shape[0]
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for k in range(n):
                acc += F[i, k] * P[k, j]
            tmp[i, j] = acc
    for i in range(n):
        for j in range(n):
            acc = Q[i, j]
            for k in range(n):
                acc += tmp[i, k] * F[j, k]
            P[i, j] = acc


@njit(cache=True)
def ekf_run(WS, WH, Y, z, Pz, Q, Rm, cfg, fvar, fpow, nf, owner, n_chain, X, eta):
    """Extended Kalman filter on the state augmented with theta, ``z = (x, theta)`` (Brus and Wigren 2006).

    theta is modelled as a random walk with the covariance in the lower block of ``Q``; with that block zero and
    the theta block of ``Pz`` zero, theta stays fixed and this is a plain state filter (used for k-step
    prediction). Output k observes ``h(x_{k n}, eta_k)`` (the output function, with ``eta`` fixed). ``X[t]``
    receives the filtered state ``x(t | t)``. ``z`` and ``Pz`` are updated in place.
    """
    T = Y.shape[0]
    d = Y.shape[1]
    nz = z.shape[0]
    N = X.shape[1]
    p = nz - N
    work = _make_work(N, p, WS.shape[1])
    x_next = np.empty(N)
    A = np.empty((N, N))
    B = np.empty((N, p))
    Fz = np.zeros((nz, nz))
    tmp = np.empty((nz, nz))
    Sm = np.empty((d, d))
    Si = np.empty((d, d))
    K = np.empty((nz, d))
    hv = np.empty(d)
    dh = np.empty(d)
    dh_eta = np.zeros(max(int(cfg[CF_OUT_Q]), 1))
    xmax = cfg[CF_XMAX]
    for t in range(T):
        if t > 0:
            xv = z[:N].copy()
            th = z[N:].copy()
            model_step(xv, WS[t], WH[t], th, cfg, fvar, fpow, nf, owner, n_chain, x_next, A, B, True, work)
            Fz[:, :] = 0.0
            for i in range(nz):
                Fz[i, i] = 1.0
            Fz[:N, :N] = A
            Fz[:N, N:] = B
            for i in range(N):
                z[i] = _clip(x_next[i], xmax)
            _sandwich(Fz, Pz, Q, tmp)
        # Measurement update: output k observes h(state k * n_chain).
        for k in range(d):
            hv[k], dh[k] = output_value(z[k * n_chain], eta, k, cfg, dh_eta)
        for a in range(d):
            for b in range(d):
                Sm[a, b] = Pz[a * n_chain, b * n_chain] * dh[a] * dh[b] + Rm[a, b]
        if _inv_small(Sm, Si):
            for i in range(nz):
                for k in range(d):
                    acc = 0.0
                    for a in range(d):
                        acc += Pz[i, a * n_chain] * dh[a] * Si[a, k]
                    K[i, k] = acc
            for k in range(d):
                e = Y[t, k] - hv[k]
                for i in range(nz):
                    z[i] += K[i, k] * e
            KH = np.zeros((nz, nz))
            for i in range(nz):
                for k in range(d):
                    for c in range(nz):
                        KH[i, c] += K[i, k] * dh[k] * Pz[k * n_chain, c]
            Pz[:, :] = Pz - KH
            Pz[:, :] = 0.5 * (Pz + Pz.T)
        for i in range(N):
            if not np.isfinite(z[i]):
                z[i] = 0.0
            X[t, i] = z[i]


@njit(cache=True)
def k_step_predict(WS, WH, Xf, theta, eta, k, cfg, y_lo, y_hi, fvar, fpow, nf, owner, n_chain, d, Yfree, Yhat):
    """``Yhat[t] = yhat(t | t - k)``: k model steps from the filtered state ``Xf[t - k]``; ``Yfree`` for t < k."""
    T = WS.shape[0]
    N = Xf.shape[1]
    p = theta.shape[0]
    work = _make_work(N, p, WS.shape[1])
    x_next = np.empty(N)
    A = np.empty((N, N))
    B = np.empty((1, 1))
    dh_eta = np.zeros(max(int(cfg[CF_OUT_Q]), 1))
    xmax = cfg[CF_XMAX]
    for t in range(T):
        if t < k:
            for c in range(d):
                Yhat[t, c] = Yfree[t, c]
            continue
        xv = Xf[t - k].copy()
        for s in range(t - k + 1, t + 1):
            model_step(xv, WS[s], WH[s], theta, cfg, fvar, fpow, nf, owner, n_chain, x_next, A, B, False, work)
            for i in range(N):
                xv[i] = _clip(x_next[i], xmax)
        for c in range(d):
            yk, _ = output_value(xv[c * n_chain], eta, c, cfg, dh_eta)
            Yhat[t, c] = min(max(yk, y_lo[c]), y_hi[c])
