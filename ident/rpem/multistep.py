"""Multi-step (long-range) prediction-error fit of the RPEM's polynomial chain model (issue 18, research prototype).

Shook, Mohtadi and Shah (IEE Proc. D 138:75, 1991): a model for predictive control should minimise the error of
the predictor the controller uses -- the K-step prediction over its horizon -- not the one-step error. For the
chain model of :class:`~ident.rpem.RecursivePEM` (the same regressors, the same midpoint or Euler step on the
scaled sampling period, the same held input at the half step and the same backward-difference input derivatives)
this module minimises

    V(theta) = sum over windows w, steps k = 1..K-1, outputs j of  ( c_j (y_j(t_w + k) - yhat_j(t_w + k | t_w)) )^2
               + ridge * |theta - theta_ref|^2

where each window restarts the model from the measured outputs, ``x(t_w) = (y(t_w), 0, ...)`` per chain (the
RPEM's own start, :meth:`~ident.rpem.RecursivePEM.reset_state`), and runs it K - 1 steps on the measured inputs.
With one-state chains every state is an output, so this is exactly the K-step prediction from measured states.
The Jacobian comes from CasADi's automatic differentiation; ``scipy.optimize.least_squares`` solves it.

The estimate is a ``theta`` for a :class:`~ident.rpem.RecursivePEM` of the same structure
(:func:`rpem_from_theta` builds the fitted estimator, so its ``to_casadi``, ``predict`` and online ``partial_fit``
apply), typically the start of the recursive passes / the online adaptation.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import casadi as ca
import numpy as np
from scipy.optimize import least_squares

from ident.rpem.estimator import RecursivePEM
from ident.rpem.structure import ChainStructure


def chain_rhs(structure: ChainStructure, x: Any, w: Any, theta: Any) -> Any:
    """dx/dt of the chain model (CasADi): x (N), w = (u, u') (2m), theta (p)."""
    s = structure
    N, n = s.n_states, s.n_chain
    zvars = [x[i] for i in range(N)] + [w[j] for j in range(2 * s.n_inputs)]
    f = [0] * s.n_outputs
    for j, row in enumerate(s.exponents):
        term = 1
        for v in np.flatnonzero(row):
            term = term * zvars[v] ** int(row[v])
        f[int(s.owner[j])] = f[int(s.owner[j])] + theta[j] * term
    return ca.vertcat(*[x[i + 1] if (i % n) != n - 1 else f[i // n] for i in range(N)])


def step_function(structure: ChainStructure, ts: float, method: str = "midpoint") -> ca.Function:
    """``Function('step', [x, ws, wh, theta], [x_next])`` of the discretised chain model."""
    s = structure
    x = ca.SX.sym("x", s.n_states)
    ws = ca.SX.sym("ws", 2 * s.n_inputs)
    wh = ca.SX.sym("wh", 2 * s.n_inputs)
    th = ca.SX.sym("th", s.n_params)
    if method == "euler":
        xn = x + ts * chain_rhs(s, x, ws, th)
    else:
        xb = x + 0.5 * ts * chain_rhs(s, x, ws, th)
        xn = x + ts * chain_rhs(s, xb, wh, th)
    return ca.Function("step", [x, ws, wh, th], [xn])


def windows(n: int, horizon: int, stride: int, skip: int = 0) -> np.ndarray:
    """Start indices of the prediction windows in a record of n samples."""
    return np.arange(skip, n - horizon, stride)


def fit_multistep(est: RecursivePEM, records: Sequence[tuple[np.ndarray, np.ndarray]], horizon: int = 80,
                  stride: int | None = None, theta0: np.ndarray | None = None,
                  output_weights: Sequence[float] | None = None,
                  ridge: float = 1e-4, max_nfev: int = 50, skip: int = 0, verbose: bool = False) -> np.ndarray:
    """The multi-step prediction-error estimate (module docstring) of ``est``'s structure on ``records`` [(u, y)].

    ``est`` is a :class:`RecursivePEM` (unfitted is fine: its constructor arguments define the structure,
    sampling, transforms, saturation). Returns theta."""
    u0, y0 = records[0]
    est._setup(u0.shape[1], y0.shape[1])
    s = est.structure_
    N, d, n = s.n_states, s.n_outputs, s.n_chain
    K = int(horizon)
    stride = stride or K // 2
    step = step_function(s, est.ts_model, est.method)
    th = ca.SX.sym("th", s.n_params)
    x0 = ca.SX.sym("x0", N)
    WSw = ca.SX.sym("WS", 2 * s.n_inputs, K - 1)
    WHw = ca.SX.sym("WH", 2 * s.n_inputs, K - 1)
    Yw = ca.SX.sym("Y", d, K - 1)
    cw = np.ones(d) if output_weights is None else np.asarray(output_weights, float)
    lo, hi = est.y_lo_, est.y_hi_
    x = x0
    res = []
    for k in range(K - 1):
        x = step(x, WSw[:, k], WHw[:, k], th)
        x = ca.fmin(ca.fmax(x, -est.state_bound), est.state_bound)
        for j in range(d):
            yh = x[j * n]
            if np.isfinite(lo[j]):
                yh = ca.fmax(yh, float(lo[j]))
            if np.isfinite(hi[j]):
                yh = ca.fmin(yh, float(hi[j]))
            res.append(cw[j] * (Yw[j, k] - yh))
    r = ca.vertcat(*res)
    fw = ca.Function("win", [th, x0, WSw, WHw, Yw], [r, ca.jacobian(r, th)])
    # assemble all windows
    X0s, WSs, WHs, Ys = [], [], [], []
    for u, y in records:
        WS, WH, _, _ = est._rows(np.asarray(u, float), carry=False)
        for t0 in windows(len(u), K, stride, skip):
            xs = np.zeros(N)
            xs[np.arange(d) * n] = y[t0]
            X0s.append(xs)
            WSs.append(WS[t0 + 1:t0 + K].T)
            WHs.append(WH[t0 + 1:t0 + K].T)
            Ys.append(y[t0 + 1:t0 + K].T)
    nw = len(X0s)
    fmap = fw.map(nw)
    X0a = np.column_stack(X0s)
    WSa = np.hstack(WSs)
    WHa = np.hstack(WHs)
    Ya = np.hstack(Ys)
    ref = est._initial_theta() if theta0 is None else np.asarray(theta0, float)
    sr = np.sqrt(ridge * nw * (K - 1))
    cache: dict[str, Any] = {}

    def evaluate(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = v.tobytes()
        if cache.get("key") != key:
            rr, jj = fmap(ca.repmat(ca.DM(v), 1, nw), X0a, WSa, WHa, Ya)
            rv = np.asarray(rr).T.ravel()
            jv = np.asarray(jj)                      # (res, p * nw): horizontal blocks per window
            p = s.n_params
            jv = jv.reshape(jv.shape[0], nw, p).transpose(1, 0, 2).reshape(nw * jv.shape[0], p)
            cache.update(key=key, r=np.nan_to_num(rv, nan=1e3), j=np.nan_to_num(jv))
        return cache["r"], cache["j"]

    def fun(v: np.ndarray) -> np.ndarray:
        return np.r_[evaluate(v)[0], sr * (v - ref)]

    def jac(v: np.ndarray) -> np.ndarray:
        return np.vstack([evaluate(v)[1], sr * np.eye(v.size)])

    sol = least_squares(fun, ref.copy(), jac=jac, method="trf", max_nfev=max_nfev, x_scale="jac",
                        verbose=2 if verbose else 0)
    return sol.x


def rpem_from_theta(est: RecursivePEM, theta: np.ndarray, n_inputs: int, n_outputs: int) -> RecursivePEM:
    """A fitted copy of ``est`` with parameters ``theta`` (state of the recursion at its start): ``to_casadi``,
    ``predict``, ``partial_fit`` (online adaptation from theta) all apply."""
    m = est.clone()
    m._setup(n_inputs, n_outputs)
    th = np.asarray(theta, float).copy()
    m.theta_init_ = th.copy()
    m._reset_recursion(th)
    return m


def k_step_predictions(est: RecursivePEM, u: np.ndarray, y: np.ndarray, horizon: int) -> np.ndarray:
    """Windowed K-step predictions (each window from the measured outputs, as :func:`fit_multistep`), NaN where a
    sample is a window start; for validation."""
    s = est.structure_
    N, d, n = s.n_states, s.n_outputs, s.n_chain
    WS, WH, _, _ = est._rows(np.asarray(u, float), carry=False)
    step = step_function(s, est.ts_model, est.method)
    f = step.map(1)
    out = np.full_like(np.asarray(y, float), np.nan)
    th = ca.DM(est.theta_)
    for t0 in windows(len(u), horizon, horizon):
        x = np.zeros(N)
        x[np.arange(d) * n] = y[t0]
        for k in range(1, horizon):
            x = np.clip(np.asarray(f(x, WS[t0 + k], WH[t0 + k], th)).ravel(), -est.state_bound, est.state_bound)
            out[t0 + k] = np.clip(x[np.arange(d) * n], est.y_lo_, est.y_hi_)
    return out
