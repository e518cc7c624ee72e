"""The common shape of every identified model in :mod:`ident`.

Every estimator derives from :class:`BaseEstimator` and follows scikit-learn conventions (the constructor stores its
arguments as given, ``fit`` validates and returns ``self``, learned attributes end in ``_``). The base gives, from the
constructor's signature and nothing else:

* ``get_params()`` / ``set_params(**params)`` (nested ``block__name`` keys for parameters that are
  estimators themselves), ``clone(**overrides)`` (an unfitted copy) and ``repr`` (the arguments that differ from their
  defaults), as scikit-learn's ``BaseEstimator`` does;
* ``save(path)`` / ``Class.load(path)`` in the one open format of :mod:`ident.io` (JSON + NPZ, never pickle), with
  one error type, :class:`ident.io.ModelFileError`, for any bad file.

Once fitted, a model satisfies :class:`DynamicModel`:

* ``predict(u, y0=None)`` simulates the model's output from an input sequence (free run, not one-step-ahead),
* ``predict_k_step(u, y, k)`` gives k-step-ahead predictions when measured outputs are available,
* ``to_casadi()`` exports the discrete-time step ``x+ = f(x, u)``, ``y = h(x, u)`` as a ``casadi.Function`` named
  ``"step"`` with inputs ``(x, u)`` and outputs ``(x_next, y)``, so that MPC can use any identified model,
* ``initial_state(u, y)`` returns the state from which ``predict`` starts for these data.

Arrays are time-major: ``u`` has shape ``(n_samples, n_inputs)``, ``y`` has shape ``(n_samples, n_outputs)``.
Using a model before ``fit`` raises :class:`NotFittedError`.
"""
from __future__ import annotations

import copy
import inspect
from pathlib import Path
from typing import Any, Protocol, TypeVar, runtime_checkable

import numpy as np
from typing_extensions import Self

E = TypeVar("E", bound="BaseEstimator")


class NotFittedError(ValueError, AttributeError):
    """Raised when a fitted-only method (``predict``, ``to_casadi``, ``save``, ...) is called before ``fit``.

    It subclasses both ``ValueError`` and ``AttributeError``, as scikit-learn's ``NotFittedError`` does, so code that
    probes with ``hasattr`` or catches either keeps working.
    """


class BaseEstimator:
    """Parameters, cloning, ``repr`` and persistence for every estimator of :mod:`ident`.

    Subclasses list their parameters as explicit keyword arguments of ``__init__`` (no ``*args``/``**kwargs``) and
    store each one unchanged in an attribute of the same name. Persistence needs ``_get_state`` and
    ``_from_state`` and a registration with :func:`ident.io.register_model` (see there).
    """

    @classmethod
    def _get_param_names(cls) -> list[str]:
        init = cls.__init__
        if init is object.__init__:
            return []
        params = [p for p in inspect.signature(init).parameters.values() if p.name != "self"]
        for p in params:
            if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
                raise TypeError(f"{cls.__name__}.__init__ must list its parameters explicitly (no *args/**kwargs), "
                                "so that get_params/clone can introspect them")
        return [p.name for p in params]

    def get_params(self, deep: bool = False) -> dict[str, Any]:
        """Constructor arguments as stored, so that ``type(est)(**est.get_params())`` rebuilds an equal estimator.

        With ``deep=True`` (scikit-learn's default, not ours), arguments that are estimators also contribute their
        own parameters as ``name__sub`` entries.
        """
        out: dict[str, Any] = {}
        for name in self._get_param_names():
            value = getattr(self, name)
            out[name] = value
            if deep and isinstance(value, BaseEstimator):
                out.update({f"{name}__{k}": v for k, v in value.get_params(deep=True).items()})
        return out

    def set_params(self, **params: Any) -> Self:
        """Set constructor arguments (``name__sub`` reaches into an argument that is an estimator); returns self.

        Raises ``ValueError`` naming an unknown parameter and listing the valid ones.
        """
        valid = self._get_param_names()
        nested: dict[str, dict[str, Any]] = {}
        for key, value in params.items():
            name, _, sub = key.partition("__")
            if name not in valid:
                raise ValueError(f"invalid parameter {name!r} for {type(self).__name__}; valid parameters: {valid}")
            if sub:
                nested.setdefault(name, {})[sub] = value
            else:
                setattr(self, name, value)
        for name, sub_params in nested.items():
            inner = getattr(self, name)
            if not isinstance(inner, BaseEstimator):
                raise ValueError(f"parameter {name!r} of {type(self).__name__} is not an estimator, so "  # noqa: TRY004
                                 f"{sorted(sub_params)} cannot be set inside it")
            inner.set_params(**sub_params)
        return self

    def clone(self, **overrides: Any) -> Self:
        """An unfitted copy with the same constructor arguments (deep copies; estimators are cloned), optionally
        with some replaced by ``overrides``."""
        params = {k: _clone_param(v) for k, v in self.get_params(deep=False).items()}
        unknown = set(overrides) - set(params)
        if unknown:
            raise ValueError(f"invalid parameter(s) {sorted(unknown)} for {type(self).__name__}; valid parameters: "
                             f"{list(params)}")
        params.update(overrides)
        return type(self)(**params)

    def __repr__(self) -> str:
        sig = inspect.signature(type(self).__init__)
        shown = []
        for name in self._get_param_names():
            value = getattr(self, name, None)
            default = sig.parameters[name].default
            if default is not inspect.Parameter.empty and _same(value, default):
                continue
            shown.append(f"{name}={value!r}")
        return f"{type(self).__name__}({', '.join(shown)})"

    # ---------------------------------------------------------------------------------------------- persistence
    def save(self, path: str | Path) -> Path:
        """Write the fitted model as ``<path>.json`` + its arrays file (:func:`ident.io.save_model`, atomic; never
        pickle); returns the JSON path."""
        from ident.io import save_model

        return save_model(self, path)

    @classmethod
    def load(cls, path: str | Path) -> Self:
        """Read a model written by :meth:`save` (:func:`ident.io.load_model`); raises
        :class:`ident.io.ModelFileError` if the file is damaged or holds another class."""
        from ident.io import load_model

        return load_model(path, expected=cls)


def _clone_param(value: Any) -> Any:
    if isinstance(value, BaseEstimator):
        return value.clone()
    if isinstance(value, (list, tuple)) and any(isinstance(v, BaseEstimator) for v in value):
        return type(value)(_clone_param(v) for v in value)
    return copy.deepcopy(value)


def _same(value: Any, default: Any) -> bool:
    """``value`` equals the constructor default (arrays compared element-wise; anything odd counts as different)."""
    if value is default:
        return True
    try:
        if isinstance(value, np.ndarray) or isinstance(default, np.ndarray):
            return bool(np.array_equal(value, default))
        return bool(value == default) and type(value) is type(default)
    except Exception:  # noqa: BLE001  (an uncomparable value is shown)
        return False


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
