"""How fast a piecewise-linear Hammerstein-Wiener model is fitted on a long record (issue 21: about 10^5 samples
within 10 s on 2 cores), measured by ``make bench`` (:mod:`experiments.benchmark_speed`).

The record comes from a known system of Paper IV's M-V shape, so the figure is reproducible anywhere: four inputs
(seeded random steps between -2 and 2, held 0.3 to 2 s at T = 0.1 s) through static nonlinearities (tanh, a
parabola, a kinked line, a sine), the same second-order ``B/F`` behind each, the sum saturated below at -0.5, plus
white noise of SD 0.05. The model is M-V's: piecewise-linear input blocks of 9, 5, 9 and 5 segments held constant
beyond the data, ``nb = nf = 2``, ``nk = 1``, an output saturation at the known limit, otherwise default settings.
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np
from scipy.signal import lfilter

from ident.excitation import RandomSteps
from ident.hammerstein_wiener.blocks import PiecewiseLinear, Saturation
from ident.hammerstein_wiener.estimator import HammersteinWiener
from ident.metrics import fit_percent

__all__ = ["measure_pwl_fit_speed", "pwl_benchmark_record"]

_SEGMENTS = (9, 5, 9, 5)
_LOWER = -0.5


def pwl_benchmark_record(n_samples: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inputs (N, 4), the noise-free output and the measured output (N,) of the benchmark system (module
    docstring), seeded by ``seed``."""
    u = np.column_stack([RandomSteps(-2.0, 2.0, 0.3, 2.0).generate(n_samples, 0.1, 4 * seed + k) for k in range(4)])
    g = (np.tanh(u[:, 0]), 0.5 * u[:, 1] ** 2, np.where(u[:, 2] > 0, u[:, 2], 0.3 * u[:, 2]), np.sin(u[:, 3]))
    w = sum(lfilter([0.0, 0.3, 0.1], [1.0, -1.2, 0.4], gi) for gi in g)
    y_true = np.maximum(w, _LOWER)
    y = y_true + 0.05 * np.random.default_rng(seed + 1000).standard_normal(n_samples)
    return u, y_true, y


def measure_pwl_fit_speed(n_samples: int = 100_000, seed: int = 0) -> dict[str, Any]:
    """Fit the benchmark's model (module docstring) once and time it.

    Returns ``hw_pwl_fit_s`` (wall-clock seconds of ``fit``, start included), ``hw_pwl_cpu_s`` (the process's CPU
    seconds over the same span, all threads: less sensitive to other load on the machine), ``hw_pwl_n_samples``,
    ``hw_pwl_validation_fit`` (FIT % on a fresh record of 20,000 samples against the noise-free output, simulated
    from x(0) = 0), ``hw_pwl_nfev`` (residual evaluations of the final fit) and ``hw_pwl_start`` (the start used).
    """
    if int(n_samples) != n_samples or n_samples < 1000:
        raise ValueError(f"n_samples must be an integer >= 1000, got {n_samples!r}")
    u, _, y = pwl_benchmark_record(int(n_samples), seed)
    u_val, y_val, _ = pwl_benchmark_record(20_000, seed + 1)
    model = HammersteinWiener([PiecewiseLinear(s, extrapolation="constant") for s in _SEGMENTS],
                              Saturation(lower=_LOWER))
    start, cpu = time.perf_counter(), time.process_time()
    model.fit(u, y)
    seconds, cpu = time.perf_counter() - start, time.process_time() - cpu
    return {"hw_pwl_fit_s": seconds, "hw_pwl_cpu_s": cpu, "hw_pwl_n_samples": int(n_samples),
            "hw_pwl_validation_fit": float(fit_percent(y_val, model.predict(u_val)[:, 0])),
            "hw_pwl_nfev": int(model.nfev_), "hw_pwl_start": model.start_}
