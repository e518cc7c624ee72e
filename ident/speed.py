"""Throughput of the compiled RPEM recursion (samples per second on one core, after JIT warm-up).

* ``rpem_samples_per_s``: Paper III's 16-term SCR model (2 states, 4 inputs: inlet NOx, urea, exp(-a/T_in) with
  a = 1e4, exhaust flow; derivatives of three inputs), midpoint integration, one ``fit`` pass.
* ``rpem_full_degree2_samples_per_s``: the full polynomial of total degree <= 2 in (x1, x2, u1..u4), 28 terms.
* ``rpem_update_calls_per_s``: the one-sample ``update`` call from Python (API overhead included).

The data are synthetic SCR-like signals (throughput does not depend on their meaning). Measured by
``python -m experiments.benchmark_rpem`` and ``make bench`` (:mod:`experiments.benchmark_speed`).
"""
from __future__ import annotations

import time
from collections.abc import Sequence

import numpy as np

from ident.rpem import SCR_PAPER3_TERMS, RecursivePEM, polynomial_terms

__all__ = ["measure_rpem_speed"]


def _scr_like_data(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Piecewise-smooth random inputs (NOx ppm, urea g/s, T_in K, flow kg/s) and a filtered output, normalised."""
    rng = np.random.default_rng(seed)
    steps = np.repeat(rng.standard_normal((n // 50 + 1, 4)), 50, axis=0)[:n]
    nox = 400 + 150 * steps[:, 0]
    urea = np.clip(0.5 + 0.2 * steps[:, 1], 0.0, None)
    t_in = 550 + 60 * steps[:, 2]
    flow = 0.3 + 0.05 * steps[:, 3]
    u = np.column_stack([nox, urea, t_in, flow])
    y = np.zeros(n)
    for t in range(1, n):  # a stable first-order response so that the estimator sees realistic errors
        y[t] = 0.95 * y[t - 1] + 0.05 * (0.002 * nox[t] - 0.5 * urea[t])
    y += 0.01 * rng.standard_normal(n)
    return u, y


def _scr_estimator(terms: Sequence[str]) -> RecursivePEM:
    return RecursivePEM(n_states=2, terms=list(terms), input_transforms={3: ("exp_neg_inv", 1e4)},
                        sampling_period=0.5, alpha=1.5, method="midpoint", stability_margin=0.015)


def _samples_per_s(terms: Sequence[str], u: np.ndarray, y: np.ndarray, repeats: int = 3) -> float:
    _scr_estimator(terms).fit(u[:200], y[:200])  # JIT warm-up (compiled code is cached on disk as well)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        _scr_estimator(terms).fit(u, y)
        best = min(best, time.perf_counter() - t0)
    return len(u) / best


def _update_calls_per_s(u: np.ndarray, y: np.ndarray, n: int = 5000) -> float:
    est = _scr_estimator(SCR_PAPER3_TERMS)
    est.update(u[0], y[0])
    t0 = time.perf_counter()
    for t in range(1, n):
        est.update(u[t], y[t])
    return (n - 1) / (time.perf_counter() - t0)


def measure_rpem_speed(n_samples: int = 200_000) -> dict:
    """RPEM throughput figures (samples/s, one core, after warm-up)."""
    u, y = _scr_like_data(n_samples)
    full2 = polynomial_terms(2, 4, max_degrees=2, total_degree=2)
    return {
        "rpem_samples_per_s": _samples_per_s(SCR_PAPER3_TERMS, u, y),
        "rpem_full_degree2_samples_per_s": _samples_per_s(full2, u, y),
        "rpem_full_degree2_n_terms": len(full2),
        "rpem_update_calls_per_s": _update_calls_per_s(u, y),
    }
