"""A multi-output model made of fitted models side by side (states stacked, outputs concatenated).

Several estimators of :mod:`ident` are single-output (the Hammerstein-Wiener models of Paper IV, the multiple-model
ARX/OE per output); :class:`OutputStack` presents a set of them as one MIMO model with the common interface, so an
MPC can use, for example, one Hammerstein-Wiener model of tailpipe NOx and another of NH3 slip together. Every part
gets the same inputs; part i gives the next ``n_outputs`` columns of the stacked output (one for a single-output
model).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from ident.base import BaseEstimator, as_2d, check_is_fitted
from ident.io import register_model

__all__ = ["OutputStack"]


@register_model("output_stack")
class OutputStack(BaseEstimator):
    """Fit one copy of a single-output estimator per output column, and predict/export them as one model.

    Parameters
    ----------
    estimators : sequence
        One unfitted single-output estimator per output (``fit(u, y)`` with y of one column).

    Attributes
    ----------
    models_ : list
        The fitted models, in output order. :meth:`from_models` builds a fitted stack from models fitted elsewhere.

    ``save``/``load`` write every part into one model file (:mod:`ident.io`); each part must itself be a
    registered model class.
    """

    def __init__(self, estimators: Sequence[Any]) -> None:
        self.estimators = estimators

    @classmethod
    def from_models(cls, models: Sequence[Any]) -> OutputStack:
        """A fitted stack of already fitted models (each keeps its own outputs; unfitted copies become
        ``estimators``)."""
        models = list(models)
        if not models:
            raise ValueError("models is empty: an OutputStack needs at least one fitted model")
        for i, m in enumerate(models):
            if not hasattr(m, "to_casadi") or not hasattr(m, "predict"):
                raise ValueError(f"models[{i}] ({type(m).__name__}) has no predict/to_casadi: not a fitted model")
        stack = cls([m.clone() if hasattr(m, "clone") else m for m in models])
        stack.models_ = models
        return stack

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

    def _output_counts(self) -> list[int]:
        return [int(m.to_casadi().size1_out(1)) for m in self.models_]

    def predict(self, u: np.ndarray, y0: np.ndarray | None = None) -> np.ndarray:
        """Simulated outputs, the parts' columns side by side; ``y0`` (measured outputs, one column per stacked
        output) is split between the parts."""
        check_is_fitted(self, "models_")
        counts = self._output_counts()
        y0a = None
        if y0 is not None:
            y0a = np.asarray(y0, dtype=float)
            if y0a.ndim == 1:  # one value per output (a single row), or the series of a single-output stack
                y0a = y0a[:, None] if sum(counts) == 1 else y0a[None, :]
            y0a = as_2d("y0", y0a, n_columns=sum(counts))
        cols = []
        k = 0
        for m, n in zip(self.models_, counts, strict=True):
            yi = None if y0a is None else y0a[:, k:k + n]
            out = np.asarray(m.predict(u) if yi is None else m.predict(u, yi), dtype=float)
            cols.append(out.reshape(out.shape[0], -1))
            k += n
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
        for f, n in zip(fs, nxs, strict=True):
            xn, yi = f(x[k:k + n], u)
            xs.append(xn)
            ys.append(yi)
            k += n
        return ca.Function("step", [x, u], [ca.vertcat(*xs), ca.vertcat(*ys)], ["x", "u"], ["x_next", "y"])

    @property
    def n_states_(self) -> int:
        check_is_fitted(self, "models_")
        return sum(int(m.to_casadi().size1_in(0)) for m in self.models_)

    # ---------------------------------------------------------------------------------------------- saving
    def _get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        check_is_fitted(self, "models_")
        parts, arrays = [], {}
        for i, m in enumerate(self.models_):
            kind = getattr(type(m), "kind", None)
            if kind is None:
                raise TypeError(f"models_[{i}] ({type(m).__name__}) is not a registered model class: it cannot be "
                                "saved")
            meta, arr = m._get_state()
            parts.append({"kind": kind, "module": type(m).__module__, "meta": meta, "arrays": sorted(arr)})
            arrays.update({f"part{i}__{k}": v for k, v in arr.items()})
        return {"parts": parts}, arrays

    @classmethod
    def _from_state(cls, meta: dict, arrays: dict[str, np.ndarray]) -> OutputStack:
        from ident.io import _model_class

        parts = meta["parts"]
        if not isinstance(parts, list) or not parts:
            raise ValueError("'parts' must be a non-empty list")
        models, used = [], set()
        for i, part in enumerate(parts):
            if not isinstance(part, dict) or not isinstance(part.get("kind"), str) or part["kind"] == "output_stack":
                raise ValueError(f"part {i} is not a model description")
            sub_cls = _model_class(f"part {i}", part)
            names = part["arrays"]
            sub = {k: arrays[f"part{i}__{k}"] for k in names}
            used.update(f"part{i}__{k}" for k in names)
            models.append(sub_cls._from_state(part["meta"], sub))
        extra = set(arrays) - used
        if extra:
            raise ValueError(f"arrays {sorted(extra)} belong to no part")
        return cls.from_models(models)
