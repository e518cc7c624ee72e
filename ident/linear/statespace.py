"""A linear state-space model with given matrices (a known system, or a model built elsewhere)."""
from __future__ import annotations

from typing import Any

import numpy as np

from ident.io import register_model
from ident.linear._statespace import LinearStateSpaceModel


@register_model("ss")
class StateSpaceModel(LinearStateSpaceModel):
    """``x(t+1) = A x + B u + K e``, ``y = C x + D u + e`` with given matrices.

    Parameters
    ----------
    A, B, C : array_like
        Shapes (n, n), (n, nu), (ny, n).
    D : array_like, optional
        Shape (ny, nu); zero if omitted.
    K : array_like, optional
        Innovation gain, shape (n, ny); zero (output-error form) if omitted.

    ``fit`` only validates and realises the matrices (there is nothing to estimate), so the object behaves like
    any other fitted model.
    """

    def __init__(self, A: Any, B: Any, C: Any, D: Any = None, K: Any = None) -> None:
        self.A = A
        self.B = B
        self.C = C
        self.D = D
        self.K = K
        self.fit()

    def fit(self, u: Any = None, y: Any = None) -> StateSpaceModel:
        A = np.atleast_2d(np.asarray(self.A, dtype=float))
        B = np.asarray(self.B, dtype=float).reshape(A.shape[0], -1)
        C = np.asarray(self.C, dtype=float).reshape(-1, A.shape[0])
        D = np.zeros((C.shape[0], B.shape[1])) if self.D is None else np.asarray(self.D, dtype=float).reshape(
            C.shape[0], B.shape[1])
        K = np.zeros((A.shape[0], C.shape[0])) if self.K is None else np.asarray(self.K, dtype=float).reshape(
            A.shape[0], C.shape[0])
        if A.shape[0] != A.shape[1]:
            raise ValueError(f"A must be square, got shape {A.shape}")
        for name, m in {"A": A, "B": B, "C": C, "D": D, "K": K}.items():
            if not np.all(np.isfinite(m)):
                raise ValueError(f"{name} contains NaN or inf")
        self.A_, self.B_, self.C_, self.D_, self.K_ = A, B, C, D, K
        return self
