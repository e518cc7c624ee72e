"""Kalman-filter-based initialisation of the RPEM (Brus and Wigren, SYSID 2006).

An extended Kalman filter runs on the model state augmented with the parameters, ``z = (x, theta)``, with theta
as a (possibly zero-variance) random walk. Because the filter corrects the state with every measurement, the
parameter estimate does not depend on a stable free-run simulation, which makes it a robust start for the
output-error RPEM whose criterion has local minima. Paper III's tuning: ``P(0) = 10 I``, process noise 50 on x and
0 on theta, measurement noise 3.
"""
from __future__ import annotations

import numpy as np

from ident.rpem import kernel
from ident.rpem.structure import ChainStructure

DEFAULT_KALMAN_OPTIONS = {"p0": 10.0, "q_state": 50.0, "q_theta": 0.0, "r": 3.0, "n_passes": 1}


def kalman_options(options: dict | None) -> dict:
    """Defaults merged with user options; unknown keys are an error (they are probably typos)."""
    opts = dict(DEFAULT_KALMAN_OPTIONS)
    for key, val in (options or {}).items():
        if key not in opts:
            raise ValueError(f"unknown kalman_options key {key!r}; known: {sorted(opts)}")
        opts[key] = val
    return opts


def ekf_initial_theta(structure: ChainStructure, cfg: np.ndarray, WS: np.ndarray, WH: np.ndarray, y: np.ndarray,
                      theta0: np.ndarray, options: dict | None = None, eta: np.ndarray | None = None,
                      x0: np.ndarray | None = None) -> np.ndarray:
    """Run the augmented-state EKF over the data and return its final parameter estimate.

    Parameters
    ----------
    structure : ChainStructure
        Model structure.
    cfg : numpy.ndarray
        Kernel configuration (scaled sampling period, discretisation, state bound).
    WS, WH : numpy.ndarray
        Input rows from :meth:`ChainStructure.input_rows`.
    y : numpy.ndarray
        Measured outputs, shape ``(T, d)``.
    theta0 : numpy.ndarray
        Parameter value the filter starts from.
    options : dict, optional
        ``p0`` (initial covariance scale), ``q_state``, ``q_theta`` (process noise variances), ``r``
        (measurement noise variance), ``n_passes`` (passes over the data, each restarting the state).
    eta : numpy.ndarray, optional
        Parameters of the static output function (held fixed; ``cfg`` names the function). None: identity.
    x0 : numpy.ndarray, optional
        Initial state of every pass (default ``(y(0), 0, ...)`` per chain).
    """
    opts = kalman_options(options)
    N, p, d = structure.n_states, structure.n_params, structure.n_outputs
    fvar, fpow, nf = structure.factor_arrays()
    theta = np.asarray(theta0, dtype=float).copy()
    Q = np.diag(np.r_[np.full(N, float(opts["q_state"])), np.full(p, float(opts["q_theta"]))])
    Rm = float(opts["r"]) * np.eye(d)
    X = np.empty((len(y), N))
    for _ in range(int(opts["n_passes"])):
        z = np.zeros(N + p)
        z[np.arange(d) * structure.n_chain] = y[0]
        if x0 is not None:
            z[:N] = x0
        z[N:] = theta
        Pz = float(opts["p0"]) * np.eye(N + p)
        kernel.ekf_run(WS, WH, y, z, Pz, Q, Rm, cfg, fvar, fpow, nf, structure.owner, structure.n_chain, X,
                       _eta(eta))
        if not np.all(np.isfinite(z[N:])):
            break
        theta = z[N:].copy()
    return theta


def _eta(eta: np.ndarray | None) -> np.ndarray:
    return np.zeros(1) if eta is None or np.size(eta) == 0 else np.ascontiguousarray(eta, dtype=float).ravel()


def ekf_state_estimates(structure: ChainStructure, cfg: np.ndarray, WS: np.ndarray, WH: np.ndarray,
                        y: np.ndarray, theta: np.ndarray, q_state: float, r: float,
                        eta: np.ndarray | None = None, x0: np.ndarray | None = None) -> np.ndarray:
    """Filtered states ``x(t | t)`` of the model with theta fixed (state-only EKF), shape ``(T, N)``; the filter
    starts at ``x0`` (default ``(y(0), 0, ...)`` per chain)."""
    N, p, d = structure.n_states, structure.n_params, structure.n_outputs
    fvar, fpow, nf = structure.factor_arrays()
    z = np.zeros(N + p)
    z[np.arange(d) * structure.n_chain] = y[0]
    if x0 is not None:
        z[:N] = x0
    z[N:] = theta
    Pz = np.zeros((N + p, N + p))
    Pz[:N, :N] = q_state * np.eye(N)
    Q = np.zeros((N + p, N + p))
    Q[:N, :N] = q_state * np.eye(N)
    X = np.empty((len(y), N))
    kernel.ekf_run(WS, WH, y, z, Pz, Q, r * np.eye(d), cfg, fvar, fpow, nf, structure.owner, structure.n_chain, X,
                   _eta(eta))
    return X
