"""Preprocessing as in the thesis (Paper III section 4.1, Paper IV section 3.1).

* :class:`Normalizer`: zero mean, unit standard deviation, with statistics taken from the *estimation* data only and
  applied unchanged to the validation data (Paper IV); or fixed statistics such as Paper III's Table 1
  (:meth:`Normalizer.from_stats`).
* :func:`arrhenius_transform`: the temperature nonlinearity ``exp(-a / T)`` with ``a = 1e4`` K (Paper III's u3*,
  Paper IV's v3 of model M-IV), T in kelvin.
* :func:`finite_difference`: input derivatives u' for the RPEM regressors (Paper III).
* :func:`normalize_split`: the whole Paper IV protocol for an (estimation, validation) pair of data sets.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ident.base import as_2d, check_is_fitted
from ident.dataset import IODataset

#: Activation-temperature constant of Paper III/IV's temperature transform, kelvin.
ARRHENIUS_A_K = 1.0e4


class Normalizer:
    """Affine scaling ``z = (x - mean_) / scale_`` per column, fitted on estimation data.

    Parameters
    ----------
    names : sequence of str, optional
        Column names, used only in error messages.
    ddof : int
        Delta degrees of freedom of the standard deviation (0: population SD, as numpy; 1: sample SD, as MATLAB).

    Attributes
    ----------
    mean_ : ndarray, shape (n_columns,)
    scale_ : ndarray, shape (n_columns,)
        Standard deviations used as scale (units of the data).
    """

    def __init__(self, names: Sequence[str] | None = None, ddof: int = 0) -> None:
        self.names = names
        self.ddof = ddof

    def fit(self, x: np.ndarray) -> Normalizer:
        """Compute mean and SD per column; raises ``ValueError`` on NaN or on a constant column (its SD is 0, so the
        normalised signal would be undefined)."""
        x = as_2d("x", x, min_rows=2)
        if not (int(self.ddof) == self.ddof and 0 <= self.ddof < x.shape[0]):
            raise ValueError(f"ddof must be a non-negative integer below the number of samples ({x.shape[0]}), got "
                             f"{self.ddof}")
        sd = x.std(axis=0, ddof=self.ddof)
        mean = x.mean(axis=0)
        # relative threshold: a column at 1e-3 ppm levels with tiny variation is not constant, one at 500 K
        # varying by 1e-13 K is
        const = sd <= 1e-12 * np.maximum(1.0, np.abs(mean))
        if np.any(const):
            names = list(self.names) if self.names is not None else []
            bad = [names[i] if i < len(names) else f"column {i}" for i in np.flatnonzero(const)]
            raise ValueError(f"cannot normalise a constant signal: {', '.join(map(str, bad))} has zero standard "
                             "deviation in the estimation data")
        self.mean_ = mean
        self.scale_ = sd
        return self

    @classmethod
    def from_stats(cls, mean: Sequence[float], sd: Sequence[float], names: Sequence[str] | None = None
                   ) -> Normalizer:
        """A normalizer with given statistics (e.g. Paper III Table 1), no fitting needed."""
        mean_a = np.atleast_1d(np.asarray(mean, dtype=float))
        sd_a = np.atleast_1d(np.asarray(sd, dtype=float))
        if mean_a.shape != sd_a.shape or not np.all(np.isfinite(mean_a)) or not np.all(np.isfinite(sd_a)) \
                or np.any(sd_a <= 0):
            raise ValueError(f"mean and sd must have equal shapes, finite values and positive sd, got mean "
                             f"{mean_a.tolist()} and sd {sd_a.tolist()}")
        obj = cls(names=names)
        obj.mean_, obj.scale_ = mean_a, sd_a
        return obj

    def fit_transform(self, x: np.ndarray) -> np.ndarray:
        return self.fit(x).transform(x)

    def transform(self, x: np.ndarray) -> np.ndarray:
        """Normalise ``x`` (shape (n, n_columns)) with the fitted statistics."""
        check_is_fitted(self, "mean_")
        x = as_2d("x", x, n_columns=self.mean_.size)
        return (x - self.mean_) / self.scale_

    def inverse_transform(self, z: np.ndarray) -> np.ndarray:
        """Back to physical units."""
        check_is_fitted(self, "mean_")
        z = as_2d("z", z, n_columns=self.mean_.size)
        return z * self.scale_ + self.mean_

    def to_dict(self) -> dict[str, list[float]]:
        """JSON-friendly statistics (for saving next to a model)."""
        check_is_fitted(self, "mean_")
        return {"mean": self.mean_.tolist(), "sd": self.scale_.tolist()}


def arrhenius_transform(temperature_k: np.ndarray, a: float = ARRHENIUS_A_K) -> np.ndarray:
    """``exp(-a / T)``, the temperature dependence of the reaction rates, T in kelvin (must be > 0).

    For T around 530 K this is about 6e-9, so normalise the result afterwards (Paper IV: mean 2.614e-8,
    SD 5.372e-8 on its data).
    """
    t = np.asarray(temperature_k, dtype=float)
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise ValueError("temperature must be finite and positive, in kelvin (did you pass degrees Celsius?)")
    return np.exp(-a / t)


def inverse_arrhenius_transform(v: np.ndarray, a: float = ARRHENIUS_A_K) -> np.ndarray:
    """Inverse of :func:`arrhenius_transform`: ``T = -a / ln(v)`` in kelvin, for 0 < v < 1."""
    v = np.asarray(v, dtype=float)
    if np.any(v <= 0) or np.any(v >= 1):
        raise ValueError("values of exp(-a/T) lie strictly between 0 and 1")
    return -a / np.log(v)


def finite_difference(x: np.ndarray, dt: float,
                      method: Literal["backward", "central", "forward"] = "backward") -> np.ndarray:
    """Time derivative of each column by finite differences, same shape as ``x``, units of x per second.

    ``backward`` (default) is causal, ``(x[t] - x[t-1]) / dt``, which is what a recursive estimator running online
    can use; ``central`` is second-order accurate for offline data. The end samples use one-sided differences.
    """
    arr = np.asarray(x, dtype=float)
    one_d = arr.ndim == 1
    a2 = as_2d("x", arr, min_rows=2)
    if not np.isfinite(dt) or dt <= 0:
        raise ValueError(f"dt must be a positive sample time in seconds, got {dt}")
    d = np.empty_like(a2)
    if method == "backward":
        d[1:] = np.diff(a2, axis=0) / dt
        d[0] = d[1]
    elif method == "forward":
        d[:-1] = np.diff(a2, axis=0) / dt
        d[-1] = d[-2]
    elif method == "central":
        d = np.gradient(a2, dt, axis=0)
    else:
        raise ValueError(f"method must be 'backward', 'central' or 'forward', got {method!r}")
    return d[:, 0] if one_d else d


def add_input_derivatives(ds: IODataset, columns: Sequence[int | str],
                          method: Literal["backward", "central", "forward"] = "backward") -> IODataset:
    """Append finite-difference derivatives of the chosen inputs as new input columns named ``<name>_dot``."""
    idx = [ds.input_names.index(c) if isinstance(c, str) else int(c) for c in columns]
    du = finite_difference(ds.u[:, idx], ds.dt, method=method)
    return ds.with_signals(
        u=np.column_stack([ds.u, du]),
        input_names=list(ds.input_names) + [ds.input_names[i] + "_dot" for i in idx],
        input_units=list(ds.input_units) + [f"({ds.input_units[i]})/s" if ds.input_units[i] else "1/s"
                                            for i in idx])


def transform_temperature(ds: IODataset, column: int | str, a: float = ARRHENIUS_A_K) -> IODataset:
    """Replace input ``column`` (temperature in kelvin) by ``exp(-a / T)``; the name gets a ``exp(-a/T)`` tag."""
    i = ds.input_names.index(column) if isinstance(column, str) else int(column)
    u = ds.u.copy()
    u[:, i] = arrhenius_transform(u[:, i], a)
    names = list(ds.input_names)
    units = list(ds.input_units)
    names[i] = f"exp(-a/{names[i]})"
    units[i] = "1"
    return ds.with_signals(u=u, input_names=names, input_units=units)


@dataclass(frozen=True)
class NormalizedSplit:
    """Result of :func:`normalize_split`: normalised data sets and the normalizers that map back."""

    estimation: IODataset
    validation: IODataset
    input_normalizer: Normalizer
    output_normalizer: Normalizer


def normalize_split(estimation: IODataset, validation: IODataset, ddof: int = 0) -> NormalizedSplit:
    """Normalise both data sets with the statistics of the estimation set only (Paper IV protocol).

    Units of the normalised signals become ``"1"`` (dimensionless); the original units stay available from the
    input data sets and the normalizers.
    """
    nu = Normalizer(names=estimation.input_names, ddof=ddof).fit(estimation.u)
    ny = Normalizer(names=estimation.output_names, ddof=ddof).fit(estimation.y)

    def apply(ds: IODataset) -> IODataset:
        return ds.with_signals(u=nu.transform(ds.u), y=ny.transform(ds.y), input_units=["1"] * ds.n_inputs,
                               output_units=["1"] * ds.n_outputs)

    return NormalizedSplit(apply(estimation), apply(validation), nu, ny)
