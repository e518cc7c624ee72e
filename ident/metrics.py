"""Fit measures used in every table of the thesis (ALGORITHMS.md section 2).

FIT = 100 * (1 - ||y - yhat|| / ||y - mean(y)||) with the 2-norm, per output, on the *simulated* output.
MSE = mean((y - yhat)^2); NRMSE = ||y - yhat|| / ||y - mean(y)|| (so FIT = 100 * (1 - NRMSE)).

:func:`compare` scores any model with the common interface on simulated output or k-step-ahead predictions.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np


def _pair(y: np.ndarray, y_hat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    y = np.asarray(y, dtype=float)
    y_hat = np.asarray(y_hat, dtype=float)
    if y.ndim == 1:
        y = y[:, None]
    if y_hat.ndim == 1:
        y_hat = y_hat[:, None]
    if y.shape != y_hat.shape:
        raise ValueError(f"y and y_hat have different shapes: {y.shape} vs {y_hat.shape}")
    if y.shape[0] < 2:
        raise ValueError("at least two samples are needed to compute a fit")
    if not (np.all(np.isfinite(y)) and np.all(np.isfinite(y_hat))):
        raise ValueError("y or y_hat contains NaN or inf")
    return y, y_hat


def nrmse(y: np.ndarray, y_hat: np.ndarray) -> np.ndarray | float:
    """Normalised RMS error ||y - yhat|| / ||y - mean(y)|| per output (float for a single output)."""
    y, y_hat = _pair(y, y_hat)
    den = np.linalg.norm(y - y.mean(axis=0), axis=0)
    if np.any(den == 0):
        raise ValueError("y is constant: the normalised error (and FIT) is undefined")
    out = np.linalg.norm(y - y_hat, axis=0) / den
    return float(out[0]) if out.size == 1 else out


def fit_percent(y: np.ndarray, y_hat: np.ndarray) -> np.ndarray | float:
    """FIT in percent, 100 * (1 - NRMSE), per output (float for a single output)."""
    e = nrmse(y, y_hat)
    return 100.0 * (1.0 - e)


def mse(y: np.ndarray, y_hat: np.ndarray) -> np.ndarray | float:
    """Mean squared error per output (float for a single output)."""
    y, y_hat = _pair(y, y_hat)
    out = np.mean((y - y_hat) ** 2, axis=0)
    return float(out[0]) if out.size == 1 else out


def rms(y: np.ndarray, y_hat: np.ndarray) -> np.ndarray | float:
    """Root-mean-square error per output, in the units of y (float for a single output)."""
    out = np.sqrt(np.asarray(mse(y, y_hat)))
    return float(out) if out.ndim == 0 else out


@dataclass(frozen=True)
class Comparison:
    """Result of :func:`compare`. Figures are floats for one output, arrays (one per output) otherwise.

    Attributes
    ----------
    fit : float or ndarray
        FIT in percent.
    mse : float or ndarray
        Mean squared error, in squared units of y.
    nrmse : float or ndarray
        ``||y - yhat|| / ||y - mean(y)||``.
    y_hat : ndarray, shape (N, n_outputs)
        Simulated output (k = None) or k-step-ahead prediction.
    k : int or None
        Prediction horizon (None: free-run simulation).
    """

    fit: float | np.ndarray
    mse: float | np.ndarray
    nrmse: float | np.ndarray
    y_hat: np.ndarray
    k: int | None

    def as_dict(self) -> dict[str, Any]:
        """The figures as JSON-friendly values (without ``y_hat``)."""
        def conv(v: float | np.ndarray) -> float | list[float]:
            return v.tolist() if isinstance(v, np.ndarray) else float(v)
        return {"fit": conv(self.fit), "mse": conv(self.mse), "nrmse": conv(self.nrmse), "k": self.k}


def compare(model: Any, u: Any, y: Any = None, k: int | None = None,
            initial: Literal["estimate", "zero"] = "estimate") -> Comparison:
    """Score a fitted model on data: simulated output (``k=None``, the thesis' measure) or k-step prediction.

    Works with any model with the common interface of :mod:`ident.base` (``predict(u, y0)``,
    ``predict_k_step(u, y, k)``).

    Parameters
    ----------
    model : DynamicModel
        A fitted model.
    u : array_like, shape (N, n_inputs), or IODataset
        Inputs; or a data set, in which case ``y`` is taken from it.
    y : array_like, shape (N, n_outputs)
        Measured outputs.
    k : int, optional
        Prediction horizon in samples; None gives the free-run simulation.
    initial : {"estimate", "zero"}
        For simulation: "estimate" passes the measured outputs as ``y0`` so the model estimates its initial state
        from the data (like MATLAB ``compare``); "zero" simulates from the model's default (zero) state.
    """
    if y is None:
        if not hasattr(u, "u") or not hasattr(u, "y"):
            raise ValueError("give y, or pass an IODataset as u")
        u, y = u.u, u.y
    y = np.asarray(y, dtype=float)
    y2 = y[:, None] if y.ndim == 1 else y
    if initial not in ("estimate", "zero"):
        raise ValueError(f"initial must be 'estimate' or 'zero', got {initial!r}")
    if k is None:
        y_hat = model.predict(u, y0=y2 if initial == "estimate" else None)
    else:
        y_hat = model.predict_k_step(u, y2, k)
    y_hat = np.asarray(y_hat, dtype=float)
    if y_hat.ndim == 1:
        y_hat = y_hat[:, None]
    return Comparison(fit=fit_percent(y2, y_hat), mse=mse(y2, y_hat), nrmse=nrmse(y2, y_hat), y_hat=y_hat, k=k)
