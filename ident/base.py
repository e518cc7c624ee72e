"""The common shape of every identified model in :mod:`ident`.

Every estimator follows scikit-learn conventions (constructor stores its arguments, ``fit`` validates and returns
``self``, learned attributes end in ``_``) and, once fitted, satisfies :class:`DynamicModel`:

* ``predict(u, y0=None)`` simulates the model's output from an input sequence (free run, not one-step-ahead),
* ``predict_k_step(u, y, k)`` gives k-step-ahead predictions when measured outputs are available,
* ``to_casadi()`` exports the discrete-time step ``x+ = f(x, u)``, ``y = h(x, u)`` as a ``casadi.Function`` named
  ``"step"`` with inputs ``(x, u)`` and outputs ``(x_next, y)``, so that MPC can use any identified model,
* ``initial_state(u, y)`` returns the state from which ``predict`` starts for these data,
* ``save(path)`` / ``load(path)`` in an open format (JSON + NPZ, never pickle).

Arrays are time-major: ``u`` has shape ``(n_samples, n_inputs)``, ``y`` has shape ``(n_samples, n_outputs)``.
"""
from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import numpy as np


class NotFittedError(RuntimeError):
    """Raised when ``predict`` or ``to_casadi`` is called on an estimator that has not been fitted."""


@runtime_checkable
class DynamicModel(Protocol):
    """The protocol every fitted model of :mod:`ident` satisfies."""

    def predict(self, u: np.ndarray, y0: np.ndarray | None = None) -> np.ndarray:
        """Simulated output, shape ``(n_samples, n_outputs)``."""
        ...

    def to_casadi(self) -> Any:
        """``casadi.Function('step', [x, u], [x_next, y])``."""
        ...


def check_is_fitted(estimator: object, attribute: str) -> None:
    """Raise :class:`NotFittedError` naming the estimator if ``attribute`` is missing."""
    if not hasattr(estimator, attribute):
        raise NotFittedError(
            f"this {type(estimator).__name__} is not fitted yet: call fit(...) before using it"
        )


def as_2d(name: str, a: Any, n_columns: int | None = None, min_rows: int = 1) -> np.ndarray:
    """Validate a time-major signal array and return it as float64 with shape ``(n, m)``.

    Raises ``ValueError`` naming ``name`` for NaN/inf, wrong dimensionality, wrong column count or too few rows.
    """
    arr = np.asarray(a, dtype=float)
    if arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2:
        raise ValueError(f"{name} must be a 1-D or 2-D (n_samples, n_signals) array, got shape {arr.shape}")
    if n_columns is not None and arr.shape[1] != n_columns:
        raise ValueError(f"{name} must have {n_columns} columns, got {arr.shape[1]}")
    if arr.shape[0] < min_rows:
        raise ValueError(f"{name} has {arr.shape[0]} samples; at least {min_rows} are needed")
    if not np.all(np.isfinite(arr)):
        bad = int(np.argmax(~np.isfinite(arr).all(axis=1)))
        raise ValueError(f"{name} contains NaN or inf (first at sample {bad})")
    return arr


def check_not_constant(name: str, a: np.ndarray, model: str = "model", signal: str = "output") -> None:
    """Refuse a signal that carries no information about the dynamics.

    ``a`` is a validated ``(n_samples, n_signals)`` array (see :func:`as_2d`). Raises ``ValueError`` naming ``name``
    and the column(s) (``model`` is used as "the <model>"):

    * ``"<name> has no columns"`` if it holds no signal at all;
    * ``"<name> has a non-finite variance ..."`` if a column's values are so large that its variance overflows;
    * ``"<name> is constant ..."`` if a column is *exactly* constant over all samples (a constant output carries
      no information about the dynamics; an all-zero one is the common case).

    Only a column constant over the whole record is refused: a signal that is constant over part of it (an NH3 slip
    that is zero most of the time) is fine. ``model`` names the estimator in the message, ``signal`` says what the
    array is (``"output"``, ``"input"``).
    """
    if a.shape[1] == 0:
        raise ValueError(f"{name} has no columns: the {model} needs at least one {signal} signal")
    if a.shape[0] == 0:
        return
    with np.errstate(over="ignore", invalid="ignore"):
        var = a.var(axis=0)
    bad = np.flatnonzero(~np.isfinite(var))
    if bad.size:
        raise ValueError(f"{name} has a non-finite variance in column(s) {bad.tolist()} (values up to "
                         f"{np.abs(a[:, bad]).max():.3g} overflow): rescale it before identifying the {model}")
    const = np.flatnonzero(np.all(a == a[:1], axis=0))
    if const.size:
        values = ", ".join(f"{v:g}" for v in a[0, const])
        raise ValueError(f"{name} is constant in column(s) {const.tolist()} (value {values} at all {a.shape[0]} "
                         f"samples): a constant {signal} carries no information about the dynamics, so the {model} "
                         "cannot be identified from it")


def as_vector(name: str, a: Any, size: int, what: str = "values") -> np.ndarray:
    """Validate a fixed-size vector such as an initial state and return it as float64 of shape ``(size,)``.

    Raises ``ValueError`` naming ``name`` for a wrong number of elements or NaN/inf.
    """
    arr = np.asarray(a, dtype=float)
    if arr.size != size:
        raise ValueError(f"{name} must have {size} {what}, got shape {arr.shape}")
    arr = arr.reshape(size)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf")
    return arr


def check_positive_int(name: str, value: Any, minimum: int = 1, what: str = "") -> int:
    """Return ``value`` as an int, or raise ``ValueError`` naming ``name`` if it is not an integer >= ``minimum``."""
    try:
        ok = int(value) == value and value >= minimum
    except (TypeError, ValueError):
        ok = False
    if not ok:
        kind = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
        raise ValueError(f"{name} must be {kind}{' ' + what if what else ''}, got {value}")
    return int(value)


def check_same_length(**arrays: np.ndarray) -> int:
    """Raise ``ValueError`` if the named arrays do not have the same number of samples; return that number."""
    lengths = {k: len(v) for k, v in arrays.items()}
    if len(set(lengths.values())) > 1:
        desc = ", ".join(f"{k}: {n}" for k, n in lengths.items())
        raise ValueError(f"signals have mismatched lengths ({desc})")
    return next(iter(lengths.values()))
