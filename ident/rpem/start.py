"""Data-driven starts for the RPEM: the system's time scale, an equation-error estimate of theta from
state-variable-filtered derivatives, and the sign unfolding of a sign-insensitive output.

The RPEM minimises the *simulation* error, a criterion with local minima, and its projection onto the model set
refuses any update that leaves the stable region; from theta = 0 (a chain of integrators, not stable) it may never
move. These starts put it near a stable model of the right time scale:

* :func:`time_scale`: an ARX model of order n (least squares refined by instrumental variables) gives the discrete
  poles; their continuous-time images
  ``s = log(z) / T`` give the characteristic frequency (geometric mean of ``|s|``) and the fastest one (1/s);
* :func:`filtered_derivatives`: the state-variable filter ``lambda^n / (s + lambda)^n`` applied to a signal gives
  its filtered derivatives of orders 0..n (Young 1981; the classic start of continuous-time identification);
* :func:`equation_error_thetas`: with the filtered output derivatives standing in for the chain's states, the last
  equation ``x_n' = phi(x, u, u')^T theta`` is linear in theta and is solved by least squares (exact for the linear
  terms, an approximation for the nonlinear ones);
* :func:`unfold_sign`: a sign-insensitive measurement ``y = |v|`` is turned back into a signed one by flipping the
  sign at every V-shaped dip to zero, so the start sees the oscillation the sensor folded.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import expm
from scipy.signal import lfilter, ss2tf

from ident.rpem.structure import ChainStructure


def time_scale(u: np.ndarray, z: np.ndarray, n: int, sampling_period: float) -> tuple[float, float]:
    """``(omega_c, omega_max)`` in rad/s of the output ``z`` (one column) from an ARX(n, n) fit on ``u`` (least
    squares, then up to three instrumental-variable iterations while the model is stable).

    ``omega_c`` is the geometric mean of the continuous-time pole magnitudes, ``omega_max`` the largest; both are
    limited to ``[2 pi / (N T), pi / T]`` (the record length and the Nyquist frequency). Discrete poles near the
    origin or with a negative real part (fitted noise rather than dynamics sampled this fast) are left out.
    """
    N = len(z)
    T = float(sampling_period)
    lo, hi = 2.0 * np.pi / (N * T), np.pi / T
    if N <= 4 * n + 2:
        return float(np.sqrt(lo * hi)), hi
    m = u.shape[1]
    ulags = [u[n - k:N - k, j] for k in range(1, n + 1) for j in range(m)]
    Phi = np.column_stack([z[n - k:N - k] for k in range(1, n + 1)] + ulags + [np.ones(N - n)])
    th = np.linalg.lstsq(Phi, z[n:], rcond=None)[0]
    # instrumental variables (the LS model's noise-free simulation as instruments): least squares on a noisy
    # output biases the poles towards fast noise modes; the IV estimate is consistent
    for _ in range(3):
        a = th[:n]
        if np.any(np.abs(np.roots(np.r_[1.0, -a])) >= 1.0):
            break
        b = th[n:n + n * m].reshape(n, m)
        drive = sum(lfilter(np.r_[0.0, b[:, j]], [1.0], u[:, j]) for j in range(m)) + th[-1]
        zs = lfilter([1.0], np.r_[1.0, -a], drive)
        Zi = np.column_stack([zs[n - k:N - k] for k in range(1, n + 1)] + ulags + [np.ones(N - n)])
        try:
            th_iv = np.linalg.solve(Zi.T @ Phi, Zi.T @ z[n:])
        except np.linalg.LinAlgError:
            break
        if not np.all(np.isfinite(th_iv)):
            break
        th = th_iv
    poles = np.roots(np.r_[1.0, -th[:n]]).astype(complex)
    # poles near the origin or on the left half of the unit disc describe the noise, not the dynamics
    poles = poles[(np.abs(poles) > 0.05) & (poles.real > 0.0)]
    if poles.size == 0:
        return hi, hi
    w = np.abs(np.log(poles)) / T
    w = np.clip(w[np.isfinite(w)], lo, hi)
    if w.size == 0:
        return float(np.sqrt(lo * hi)), hi
    return float(np.exp(np.mean(np.log(w)))), float(w.max())


def filtered_derivatives(x: np.ndarray, n: int, lam: float, ts: float, hold: bool = True) -> np.ndarray:
    """Derivatives of orders 0..n of ``x`` (1-D) filtered by ``lam^n / (s + lam)^n``, shape ``(len(x), n + 1)``.

    Time is the model's (sampling period ``ts``); the filter starts at rest, so the first ``~5 n / lam`` time
    units carry its transient. ``hold``: the signal is held between samples (zero-order hold); else it is taken
    as linear between samples (first-order hold), the right choice for samples of a smooth signal.
    """
    c = np.poly(-lam * np.ones(n))
    A = np.zeros((n, n))
    A[:-1, 1:] = np.eye(n - 1)
    A[-1, :] = -c[1:][::-1]
    E = np.zeros((n + 2, n + 2))
    E[:n, :n] = A
    E[n - 1, n] = 1.0
    E[n, n + 1] = 1.0 / ts
    M = expm(E * ts)
    Ad, B0, B1 = M[:n, :n], M[:n, n], M[:n, n + 1]
    if hold:
        Bc, Bn = B0, np.zeros(n)
    else:  # first-order hold: x(t) = x_k + (x_{k+1} - x_k) (t - t_k) / ts
        Bc, Bn = B0 - B1, B1
    # z_{k+1} = Ad z_k + Bc x_k + Bn x_{k+1}; outputs z_k and its derivative A[-1] z_k + x_k, run as IIR filters
    C = np.vstack([np.eye(n), A[-1:]])
    D = np.zeros((n + 1, 2))
    D[n, 0] = 1.0
    x = np.asarray(x, dtype=float)
    x_next = np.r_[x[1:], x[-1:]]
    out = np.empty((len(x), n + 1))
    Bs = np.column_stack([Bc, Bn])
    for i, w in enumerate((x, x_next)):
        num, den = ss2tf(Ad, Bs, C, D, input=i)
        for r in range(n + 1):
            contrib = lfilter(num[r], den, w)
            out[:, r] = contrib if i == 0 else out[:, r] + contrib
    return out * lam**n


def equation_error_thetas(structure: ChainStructure, u: np.ndarray, z: np.ndarray, lam: float, ts: float,
                          hold: bool) -> list[np.ndarray]:
    """Least-squares theta of the chain model from filtered derivatives (module docstring): two estimates, with
    all terms and with the terms of degree at most one only (the others zero); either is left out if it fails.

    ``u`` are the inputs as the model sees them (transformed, normalised), ``z`` the chain outputs ``x_1`` per
    chain (the measured outputs, unfolded or offset as the output function requires), ``lam`` the filter
    bandwidth and ``ts`` the sampling period, both in model time.
    """
    s = structure
    n, d, m = s.n_chain, s.n_outputs, s.n_inputs
    Zf = [filtered_derivatives(z[:, k], n, lam, ts, hold) for k in range(d)]
    Uf = [filtered_derivatives(u[:, j], max(n, 1), lam, ts, hold) for j in range(m)]
    variables = np.column_stack([Zf[k][:, i] for k in range(d) for i in range(n)]
                                + [Uf[j][:, 0] for j in range(m)] + [Uf[j][:, 1] for j in range(m)])
    skip = min(int(np.ceil(6.0 * n / (lam * ts))), len(z) // 3)
    V = variables[skip:]
    degree = s.exponents.sum(axis=1)
    out = []
    for linear_only in (False, True):
        theta = np.zeros(s.n_params)
        ok = True
        for k in range(d):
            rows = np.flatnonzero(s.owner == k)
            if linear_only:
                rows = rows[degree[rows] <= 1]
            if rows.size == 0:
                continue
            E = s.exponents[rows]
            with np.errstate(over="ignore", invalid="ignore"):
                Phi = np.prod(V[:, None, :] ** E[None, :, :], axis=2)
            target = Zf[k][skip:, n]
            if not (np.all(np.isfinite(Phi)) and np.all(np.isfinite(target))) or len(target) < rows.size + 2:
                ok = False
                break
            scale = np.sqrt(np.mean(Phi**2, axis=0)) + 1e-12
            G = Phi / scale
            sol = np.linalg.solve(G.T @ G + 1e-8 * len(target) * np.eye(rows.size), G.T @ target) / scale
            if not np.all(np.isfinite(sol)):
                ok = False
                break
            theta[rows] = sol
        if ok:
            out.append(theta)
    return out


def unfold_sign(y: np.ndarray, floor: float) -> np.ndarray:
    """A signed version of a sign-insensitive measurement ``y = floor + |v| + noise`` (1-D).

    The sign flips after every local minimum that looks like a zero crossing of v: a minimum of ``y - floor`` lower
    than three quarters of the larger step to its neighbours plus twice the noise SD (a sampled V reaches at most
    half a step above zero; a rounded dip where v turns back without crossing is flat, so its value exceeds its
    steps). The noise SD comes from the second differences. Between flips the sign is kept. The result is
    ``+-(y - floor)``; its overall sign is arbitrary (an even output function does not see it).
    """
    v = np.asarray(y, dtype=float) - floor
    if len(v) < 5:
        return v
    sigma = np.median(np.abs(np.diff(v, 2))) / 0.6745 / np.sqrt(6.0)
    k = np.arange(1, len(v) - 1)
    step = np.maximum(np.abs(v[k] - v[k - 1]), np.abs(v[k + 1] - v[k]))
    crossing = (v[k] <= v[k - 1]) & (v[k] < v[k + 1]) & (v[k] < 0.75 * step + 2.0 * sigma)
    flips = np.zeros(len(v), dtype=int)
    flips[k[crossing] + 1] = 1
    sign = np.where(np.cumsum(flips) % 2 == 1, -1.0, 1.0)
    return sign * np.abs(v)


def _unfold_quadratic(v: np.ndarray, half_width: int = 3) -> np.ndarray:
    """Signs by local smoothness: at every low local minimum of ``v = |signal|`` keep the sign, or flip it after or
    at the minimum, whichever a quadratic through the ``2 w + 1`` samples around it fits best (a V through zero
    becomes a straight line when flipped; a rounded dip stays smooth when kept)."""
    n = len(v)
    k = np.arange(1, n - 1)
    low = (v[k] <= v[k - 1]) & (v[k] < v[k + 1]) & (v[k] <= np.quantile(v, 0.3))
    tt = np.arange(-half_width, half_width + 1)
    X = np.column_stack([np.ones(tt.size), tt, tt**2])
    resid = np.eye(tt.size) - X @ np.linalg.pinv(X)
    flips = np.zeros(n, dtype=int)
    for c in k[low]:
        if c - half_width < 0 or c + half_width >= n:
            continue
        seg = v[c - half_width:c + half_width + 1]
        options = (seg, np.where(tt > 0, -seg, seg), np.where(tt >= 0, -seg, seg))
        best = int(np.argmin([np.sum((resid @ o) ** 2) for o in options]))
        if best:
            flips[c + (1 if best == 1 else 0)] ^= 1
    return np.where(np.cumsum(flips) % 2 == 1, -1.0, 1.0) * v


def _decode_arx(z: np.ndarray, v: np.ndarray, u: np.ndarray, order: int, rounds: int = 4) -> np.ndarray:
    """Signs from the one-step predictions of an ARX model fitted to the signed signal ``z`` (refitted ``rounds``
    times): each sample takes the sign the model predicts from the samples before it."""
    N, m = len(z), u.shape[1]
    for _ in range(rounds):
        Phi = np.column_stack([z[order - k:N - k] for k in range(1, order + 1)]
                              + [u[order - k:N - k, j] for k in range(1, order + 1) for j in range(m)]
                              + [np.ones(N - order)])
        th = np.linalg.lstsq(Phi, z[order:], rcond=None)[0]
        a, b, c = th[:order], th[order:order + order * m].reshape(order, m), th[-1]
        new = z.copy()
        for t in range(order, N):
            pred = a @ new[t - order:t][::-1] + np.sum(b * u[t - order:t][::-1]) + c
            new[t] = v[t] if pred >= 0.0 else -v[t]
        if np.array_equal(np.sign(new), np.sign(z)):
            break
        z = new
    return z


def unfold_candidates(y: np.ndarray, floor: float, u: np.ndarray, n_states: int) -> list[np.ndarray]:
    """Several signed versions of a sign-insensitive output ``y = floor + |v|`` (1-D): :func:`unfold_sign`, the
    local-quadratic rule, and each refined by ARX one-step sign decoding of orders ``n + 1`` and ``2 n``.

    A single wrong flip changes the sign of everything after it, and no rule is right on every record, so the
    estimator fits a start to each and keeps the one whose ``|x|`` model simulates the data best (a criterion the
    unknown overall sign cannot affect)."""
    v = np.abs(np.asarray(y, dtype=float) - floor)
    firsts = [unfold_sign(y, floor), _unfold_quadratic(v)]
    out: list[np.ndarray] = []
    for z in firsts:
        out.append(z)
        for order in (n_states + 1, 2 * n_states):
            if len(v) > 10 * (order + 1) * (u.shape[1] + 1):
                out.append(_decode_arx(z.copy(), v, u, order))
    unique: list[np.ndarray] = []
    for z in out:
        if not any(abs(np.mean(np.sign(z) == np.sign(w)) - 0.5) > 0.499 for w in unique):
            unique.append(z)
    return unique
