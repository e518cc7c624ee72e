"""A multi-output model made of one fitted single-output model per output (states stacked).

Several estimators of :mod:`ident` are single-output (the Hammerstein-Wiener models of Paper IV, the OE model per
output); :class:`OutputStack` presents a set of them as one MIMO model with the common interface, so an MPC can
use, for example, one Hammerstein-Wiener model of tailpipe NOx and another of NH3 slip together.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ident.base import as_2d, check_is_fitted


class OutputStack:
    """Fit one copy of a single-output estimator per output column, and predict/export them as one model.

    Parameters
    ----------
    estimators : one unfitted single-output estimator per output (``fit(u, y)`` with y of one column).
    """

    def __init__(self, estimators: Sequence[Any]) -> None:
        self.estimators = estimators

    def fit(self, u: np.ndarray, y: np.ndarray) -> OutputStack:
        """Fit estimator i on output column i; returns self."""
        y = as_2d("y", y)
        u = as_2d("u", u, min_rows=2)
        if y.shape[1] != len(self.estimators):
            raise ValueError(f"y has {y.shape[1]} outputs but {len(self.estimators)} estimators were given")
        if y.shape[0] != u.shape[0]:
            raise ValueError(f"signals have mismatched lengths (u: {u.shape[0]}, y: {y.shape[0]})")
        self.models_ = [est.fit(u, y[:, [i]]) for i, est in enumerate(self.estimators)]
        return self

    def predict(self, u: np.ndarray, y0: np.ndarray | None = None) -> np.ndarray:
        """Simulated outputs, one column per model."""
        check_is_fitted(self, "models_")
        cols = []
        for i, m in enumerate(self.models_):
            yi = None if y0 is None else np.asarray(y0, dtype=float).reshape(len(np.atleast_1d(y0)), -1)[:, [i]]
            cols.append(np.asarray(m.predict(u) if yi is None else m.predict(u, yi)).reshape(-1))
        return np.column_stack(cols)

    def to_casadi(self) -> Any:
        """``Function('step', [x, u], [x_next, y])`` with the models' states stacked in order."""
        import casadi as ca

        check_is_fitted(self, "models_")
        fs = [m.to_casadi() for m in self.models_]
        nxs = [int(f.size1_in(0)) for f in fs]
        nu = int(fs[0].size1_in(1))
        x = ca.SX.sym("x", sum(nxs))
        u = ca.SX.sym("u", nu)
        xs, ys, k = [], [], 0
        for f, n in zip(fs, nxs, strict=False):
            xn, yi = f(x[k:k + n], u)
            xs.append(xn)
            ys.append(yi[0])
            k += n
        return ca.Function("step", [x, u], [ca.vertcat(*xs), ca.vertcat(*ys)], ["x", "u"], ["x_next", "y"])

    @property
    def n_states_(self) -> int:
        check_is_fitted(self, "models_")
        return sum(int(m.to_casadi().size1_in(0)) for m in self.models_)
