"""Storage-capable regressors for the RPEM's polynomial chain model of the dosing loop (issue 18, research prototype).

The thesis' SCR regressor (Paper III) is a polynomial in the chain states, the inputs and input derivatives. For a
model that an NMPC can dose with, the regressor must be able to express that the dose fills a store whose effect on
NOx depends on temperature and flow, and that a full store spills NH3. :func:`storage_candidates` lists generic
candidates for that (products of states and inputs up to degree three, input derivatives of the exogenous inputs
only -- never of the dose, which acts through the state), and :func:`select_terms` picks among them with the
thesis' forward selection, ranked by the equation error (orthogonal least squares, fast) and stopped by the
multi-step prediction error on held-out records (Shook, Mohtadi and Shah 1991: the horizon the NMPC predicts over).

Inputs are numbered as the estimator's columns (``u1`` .. ``um``); ``dose_input`` (1-based) is the dose's column.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ident.rpem.estimator import RecursivePEM


def storage_candidates(k: int, n_outputs: int = 2, n_inputs: int = 4, dose_input: int = 1,
                       derivative_inputs: Sequence[int] = (2, 3, 4), state_input_degree: int = 2) -> list[str]:
    """Candidate terms of chain ``k`` (1-based) of a model with one-state chains (states ``x1..xd`` = outputs).

    Constant; every state and its square and the products of two states; every input; state x input; own state^2 x
    input; input x input; own state x input x input (``state_input_degree`` 2 adds these); the derivatives of the
    ``derivative_inputs`` alone and times the own state (never the dose's)."""
    xs = [f"x{i}" for i in range(1, n_outputs + 1)]
    us = [f"u{j}" for j in range(1, n_inputs + 1)]
    own = f"x{k}"
    terms = ["1", *xs]
    terms += [f"{a}*{b}" for i, a in enumerate(xs) for b in xs[i + 1:]]
    terms += [f"{a}^2" for a in xs]
    terms += us
    terms += [f"{x}*{u}" for x in xs for u in us]
    terms += [f"{own}^2*{u}" for u in us]
    terms += [f"{a}*{b}" for i, a in enumerate(us) for b in us[i + 1:]]
    if state_input_degree >= 2:
        terms += [f"{own}*{a}*{b}" for i, a in enumerate(us) for b in us[i + 1:]]
    for j in derivative_inputs:
        if j == dose_input:
            continue
        terms += [f"u{j}'", f"{own}*u{j}'"]
    out, seen = [], set()
    for t in terms:
        if t not in seen:
            out.append(t)
            seen.add(t)
    return out


def regressor_matrix(est: RecursivePEM, k: int, terms: Sequence[str], records: Sequence[tuple[np.ndarray, np.ndarray]]
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(Phi, dy) of the equation error of chain k (0-based): the Euler difference quotient of output k against the
    terms evaluated at the measured outputs and the held inputs (the start of a fit; the multi-step criterion
    refines it)."""
    from ident.rpem.regressors import parse_terms

    d = records[0][1].shape[1]
    E = parse_terms(list(terms), d, est.n_inputs_)
    A, b = [], []
    for u, y in records:
        WS, _, _, _ = est._rows(np.asarray(u, float), carry=False)
        v = np.column_stack([y[:-1], WS[1:]])
        A.append(np.prod(v[:, None, :] ** E[None], axis=2))
        b.append((y[1:, k] - y[:-1, k]) / est.ts_model)
    return np.vstack(A), np.concatenate(b)


def ols_order(Phi: np.ndarray, b: np.ndarray, max_terms: int, forced: Sequence[int] = ()) -> list[int]:
    """Forward orthogonal least squares (Billings' error reduction ratio): the column indices in the order they are
    selected, starting with ``forced``."""
    p = Phi.shape[1]
    chosen = list(forced)
    Q = []
    for j in chosen:
        w = Phi[:, j].astype(float).copy()
        for q in Q:
            w -= (q @ w) * q
        nw = np.linalg.norm(w)
        if nw > 1e-12:
            Q.append(w / nw)
    r = b.astype(float).copy()
    for q in Q:
        r -= (q @ r) * q
    while len(chosen) < min(max_terms, p):
        best, best_gain, best_q = None, 0.0, None
        for j in range(p):
            if j in chosen:
                continue
            w = Phi[:, j].astype(float).copy()
            for q in Q:
                w -= (q @ w) * q
            nw = np.linalg.norm(w)
            if nw < 1e-9 * (np.linalg.norm(Phi[:, j]) + 1e-300):
                continue
            g = (w @ r) ** 2 / (nw * nw)
            if g > best_gain:
                best, best_gain, best_q = j, g, w / nw
        if best is None:
            break
        chosen.append(best)
        Q.append(best_q)
        r -= (best_q @ r) * best_q
    return chosen


def ridge_theta(Phi: np.ndarray, b: np.ndarray, ridge: float = 1e-4) -> np.ndarray:
    """Ridge least squares (ridge relative to the number of rows)."""
    p = Phi.shape[1]
    return np.linalg.solve(Phi.T @ Phi + ridge * len(b) * np.eye(p), Phi.T @ b)
