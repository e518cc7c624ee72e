"""Static nonlinearities of block-oriented models: value, derivatives and a CasADi version of each.

Every block maps a signal ``x`` (shape (N,)) to ``v = g(x; p)`` with parameters ``p`` (shape (n_params,)) and gives

* ``value(x, p)``, ``dx(x, p)`` = dg/dx (N,), ``dp(x, p)`` = dg/dp (N, n_params) for the exact Jacobian of the
  simulation-error fit,
* ``casadi(x, p)`` the same function on CasADi symbols (for ``to_casadi``),
* ``initial_params(x)``: the starting parameters for data ``x`` (identity-like where possible), which may also set
  data-dependent constants (knots, normalisation) once, before the fit,
* ``fit_params(x, target)``: the parameters whose ``g(x)`` is closest to ``target`` in least squares, for blocks
  linear in their parameters (``linear_in_params()``; bounds honoured) and the absolute value (its offset), else
  None: the data-driven starts of the estimator,
* ``random_params(x, rng)``: parameters for a random restart (a random mix of a line and a parabola over the data
  range, fitted by ``fit_params``; the initial parameters for blocks it cannot fit),
* ``to_dict()`` / :func:`block_from_dict` for saving (JSON).

``even`` marks blocks that are even functions (``g(c - x) = g(c + x)`` about a centre ``c``): through them the best
linear approximation of a system driven by a symmetric signal is zero, so a fit started from the linear model
cannot find them; the estimator then tries random restarts (see
:class:`~ident.hammerstein_wiener.HammersteinWiener`, ``n_restarts``).

``estimate`` says whether the parameters are estimated (True) or held at their given or initial values.

=====================  ==============================================================  =========================
block                  g(x; p)                                                         parameters
=====================  ==============================================================  =========================
:class:`Identity`      x                                                               none
:class:`Arrhenius`     (exp(-a / x) - m) / s, x a temperature in K; m, s fixed at       a (K)
                       ``initial_params`` from the data (Paper IV's normalised v3)
:class:`PiecewiseLinear`  continuous, linear between knots, linear or constant         values at knots (+ knots),
                       extrapolation; knots at data quantiles or given; optionally     or first value and
                       non-decreasing (``monotone``)                                   increments >= 0
:class:`Saturation`    min(max(x, lower), upper)                                       lower, upper
:class:`DeadZone`      x - upper above upper, x - lower below lower, 0 between         lower, upper
:class:`Polynomial`    sum_k c_k x^k, k = 0..degree                                    c_0..c_degree
:class:`OddPolynomial` sum_k c_k x^(2k+1), k = 0..(degree-1)/2 (odd: g(-x) = -g(x))   c_0..c_(degree-1)/2
:class:`EvenPolynomial` sum_k c_k (x - centre)^(2k), k = 0..degree/2 (even about the      c_0..c_degree/2
                       given centre)
:class:`AbsoluteValue` |x - centre| + offset (a sign-insensitive sensor)               centre, offset
=====================  ==============================================================  =========================
"""
from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["AbsoluteValue", "Arrhenius", "DeadZone", "EvenPolynomial", "Identity", "OddPolynomial",
           "PiecewiseLinear", "Polynomial", "Saturation", "StaticNonlinearity", "block_from_dict"]

_BLOCKS: dict[str, type[StaticNonlinearity]] = {}


def _register(cls: type[StaticNonlinearity]) -> type[StaticNonlinearity]:
    _BLOCKS[cls.__name__] = cls
    return cls


class StaticNonlinearity:
    """Base class: subclasses implement ``value``, ``dx``, ``dp``, ``casadi``, ``initial_params``."""

    estimate: bool = False
    #: True for blocks that are even functions about a centre (see the module docstring).
    even: bool = False

    def n_params(self) -> int:
        raise NotImplementedError

    def initial_params(self, x: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def value(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def dx(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def dp(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def casadi(self, x: Any, p: np.ndarray) -> Any:
        raise NotImplementedError

    def n_free(self) -> int:
        """Number of estimated parameters."""
        return self.n_params() if self.estimate else 0

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of the parameters (default: unbounded)."""
        return np.full(self.n_params(), -np.inf), np.full(self.n_params(), np.inf)

    def scaled_params(self, p: np.ndarray, c: float) -> np.ndarray | None:
        """Parameters of ``c * g(x; p)`` for ``c > 0``, or None when the block cannot be scaled by its parameters
        (used by the estimator's ``unit_gain`` normalisation)."""
        return None

    def roughness_matrix(self) -> np.ndarray | None:
        """A matrix ``R`` (n_rough, n_params) whose ``R @ p`` measures the block's departure from a straight line
        (penalised by the estimator's ``smoothness``), or None when the block has no such measure."""
        return None

    def linear_in_params(self) -> bool:
        """True when ``g(x; p) = Phi(x) p`` with ``Phi`` independent of ``p`` (then ``dp(x, p) = Phi(x)``)."""
        return False

    def fit_params(self, x: np.ndarray, target: np.ndarray) -> np.ndarray | None:
        """Least-squares parameters with ``g(x; p)`` closest to ``target`` (within :meth:`bounds`), or None when the
        block is not linear in its parameters. Data-dependent constants (knots) are placed on ``x`` if not set yet."""
        if not self.linear_in_params():
            return None
        x, target = _x(x), _x(target)
        p0 = self.initial_params(x)   # idempotent; places the knots of a piecewise-linear block
        phi = self.dp(x, p0)
        lo, hi = self.bounds()
        if np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)):
            from scipy.optimize import lsq_linear

            return np.asarray(lsq_linear(phi, target, bounds=(lo, hi)).x, dtype=float)
        return np.linalg.lstsq(phi, target, rcond=None)[0]

    def random_params(self, x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Parameters for a random restart: :meth:`fit_params` to ``m + s (a z + b (z^2 - 1))`` over the data
        (``z = (x - m) / s``, m and s the mean and SD of x, a and b standard normal), i.e. a random mix of a line and
        a parabola (an odd block keeps the line, an even one the parabola); the initial parameters for blocks it
        cannot fit."""
        x = _x(x)
        p0 = self.initial_params(x)
        m, s = float(np.mean(x)), float(np.std(x))
        if s <= 0:
            return p0
        z = (x - m) / s
        a, b = rng.standard_normal(2)
        p = self.fit_params(x, m + s * (a * z + b * (z * z - 1.0)))
        return p0 if p is None else p

    def to_dict(self) -> dict[str, Any]:
        return {"type": type(self).__name__, **{k: _plain(v) for k, v in vars(self).items()}}

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v!r}" for k, v in vars(self).items())
        return f"{type(self).__name__}({args})"

    def copy(self) -> StaticNonlinearity:
        return copy.deepcopy(self)


def _plain(v: Any) -> Any:
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, tuple):
        return list(v)
    return v


def block_from_dict(d: dict[str, Any]) -> StaticNonlinearity:
    """Rebuild a block written by ``to_dict``."""
    d = dict(d)
    kind = d.pop("type")
    if kind not in _BLOCKS:
        raise ValueError(f"unknown static block {kind!r}; known: {sorted(_BLOCKS)}")
    obj = _BLOCKS[kind].__new__(_BLOCKS[kind])
    for k, v in d.items():
        setattr(obj, k, np.asarray(v, dtype=float) if isinstance(v, list) else v)
    return obj


def _x(x: Any) -> np.ndarray:
    return np.asarray(x, dtype=float).reshape(-1)


@_register
class Identity(StaticNonlinearity):
    """``g(x) = x`` (no parameters)."""

    def __init__(self) -> None:
        self.estimate = False

    def n_params(self) -> int:
        return 0

    def initial_params(self, x: np.ndarray) -> np.ndarray:
        return np.zeros(0)

    def value(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return _x(x).copy()

    def dx(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return np.ones_like(_x(x))

    def dp(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return np.zeros((_x(x).size, 0))

    def casadi(self, x: Any, p: np.ndarray) -> Any:
        return x


@_register
class Arrhenius(StaticNonlinearity):
    """``g(T) = (exp(-a / T) - m) / s``: the reaction-rate temperature dependence, normalised (Paper IV's v3).

    Parameters
    ----------
    a : float
        Activation temperature in K (Paper IV: 1e4, fixed).
    estimate : bool
        Estimate ``a``.
    offset, scale : float, optional
        ``m`` and ``s``; by default the mean and SD of ``exp(-a / T)`` over the estimation data, computed once by
        ``initial_params`` and then held (so the normalisation does not move with ``a``).
    """

    def __init__(self, a: float = 1.0e4, estimate: bool = False, offset: float | None = None,
                 scale: float | None = None) -> None:
        self.a = a
        self.estimate = estimate
        self.offset = offset
        self.scale = scale

    def n_params(self) -> int:
        return 1

    def initial_params(self, x: np.ndarray) -> np.ndarray:
        x = _x(x)
        if np.any(x <= 0) or not np.all(np.isfinite(x)):
            raise ValueError("Arrhenius block: the input must be a positive temperature in kelvin")
        e = np.exp(-self.a / x)
        if self.offset is None:
            self.offset = float(e.mean())
        if self.scale is None:
            sd = float(e.std())
            if sd <= 0:
                raise ValueError("Arrhenius block: exp(-a/T) is constant on these data (constant temperature?)")
            self.scale = sd
        return np.array([float(self.a)])

    def value(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return (np.exp(-p[0] / _x(x)) - self.offset) / self.scale

    def dx(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        x = _x(x)
        return np.exp(-p[0] / x) * p[0] / x**2 / self.scale

    def dp(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        x = _x(x)
        return (-np.exp(-p[0] / x) / x / self.scale)[:, None]

    def casadi(self, x: Any, p: np.ndarray) -> Any:
        import casadi as ca

        return (ca.exp(-float(p[0]) / x) - self.offset) / self.scale


@_register
class PiecewiseLinear(StaticNonlinearity):
    """Continuous piecewise-linear function with ``n_segments`` segments; beyond the outer knots linear
    (``extrapolation="linear"``, MATLAB ``pwlinear``'s choice) or constant (``"constant"``: the function is held at
    its end values, so inputs outside the estimation range are not extrapolated along a slope no data supported).

    Parametrised by its values at the ``n_segments + 1`` knots (starting as the identity), plus the knots themselves
    when ``estimate_knots``; with ``monotone`` by the first value and the ``n_segments`` increments between
    consecutive knot values, bounded below by 0 (a non-decreasing function, e.g. a reaction rate that rises with
    temperature). Knots default to equally spaced quantiles of the estimation data (so each segment holds
    about the same number of samples; the outer segments extend to infinity), or are given.

    Parameters
    ----------
    n_segments : int
        Number of segments (>= 1; Paper IV's M-V: 9, 5, 9, 5).
    knots : sequence of float, optional
        ``n_segments + 1`` increasing knots; default from data quantiles.
    estimate : bool
        Estimate the values at the knots.
    estimate_knots : bool
        Estimate the knots too (the fit keeps them increasing by rejecting steps that reorder them).
    extrapolation : {"linear", "constant"}
        Behaviour beyond the outer knots.
    monotone : bool
        Constrain the function to be non-decreasing (increments parametrisation with bounds; fixed knots only).

    ``roughness_matrix`` gives the changes of slope at the inner knots (zero for a straight line), which the
    estimator's ``smoothness`` penalises.
    """

    def __init__(self, n_segments: int = 5, knots: Sequence[float] | None = None, estimate: bool = True,
                 estimate_knots: bool = False, extrapolation: str = "linear", monotone: bool = False) -> None:
        self.n_segments = n_segments
        self.knots = knots
        self.estimate = estimate
        self.estimate_knots = estimate_knots
        self.extrapolation = extrapolation
        self.monotone = monotone

    def _monotone(self) -> bool:
        return bool(getattr(self, "monotone", False))

    def _cum(self) -> np.ndarray:
        """T with values = T @ (v_0, d_1, ..., d_K) for the monotone parametrisation."""
        k = self._k()
        T = np.tril(np.ones((k, k)))
        return T

    def _k(self) -> int:
        return int(self.n_segments) + 1

    def n_params(self) -> int:
        return self._k() * (2 if self.estimate_knots else 1)

    def n_free(self) -> int:
        return self.n_params() if (self.estimate or self.estimate_knots) else 0

    def initial_params(self, x: np.ndarray) -> np.ndarray:
        if int(self.n_segments) != self.n_segments or self.n_segments < 1:
            raise ValueError(f"n_segments must be a positive integer, got {self.n_segments}")
        if self.extrapolation not in ("linear", "constant"):
            raise ValueError(f"extrapolation must be 'linear' or 'constant', got {self.extrapolation!r}")
        if self._monotone() and self.estimate_knots:
            raise ValueError("PiecewiseLinear: monotone is implemented for fixed knots only (estimate_knots=False)")
        if self.knots is None:
            knots = np.quantile(_x(x), np.linspace(0.0, 1.0, self._k()))
            if np.any(np.diff(knots) <= 0):
                lo, hi = float(np.min(x)), float(np.max(x))
                if hi <= lo:
                    raise ValueError("PiecewiseLinear: the input is constant, knots cannot be placed")
                knots = np.linspace(lo, hi, self._k())
            self.knots = knots
        knots = np.asarray(self.knots, dtype=float)
        if knots.size != self._k() or np.any(np.diff(knots) <= 0):
            raise ValueError(f"PiecewiseLinear needs {self._k()} strictly increasing knots, got {knots.tolist()}")
        self.knots = knots
        if self._monotone():
            return np.concatenate([knots[:1], np.diff(knots)])
        return np.concatenate([knots, knots]) if self.estimate_knots else knots.copy()

    def _split(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k = self._k()
        if self.estimate_knots:
            return p[:k], p[k:]
        p = np.asarray(p, dtype=float)
        return np.asarray(self.knots, dtype=float), (np.cumsum(p) if self._monotone() else p)

    def linear_in_params(self) -> bool:
        return not self.estimate_knots

    def scaled_params(self, p: np.ndarray, c: float) -> np.ndarray | None:
        p = np.asarray(p, dtype=float).copy()
        if self.estimate_knots:
            p[self._k():] *= c   # the values; the knots stay
        else:
            p *= c               # values, or first value and increments (monotone): both linear in the values
        return p

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = super().bounds()
        if self._monotone():
            lo[1:] = 0.0
        return lo, hi

    def roughness_matrix(self) -> np.ndarray | None:
        if self.estimate_knots or self.knots is None or self.n_segments < 2:
            return None
        knots = np.asarray(self.knots, dtype=float)
        k = knots.size
        slopes = np.diff(np.eye(k), axis=0) / np.diff(knots)[:, None]   # (K-1, K): slopes from values
        R = np.diff(slopes, axis=0)                                      # (K-2, K): slope changes
        return R @ self._cum() if self._monotone() else R

    def _segment(self, x: np.ndarray, knots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Segment index j (0..K-2) of each sample (outer segments extended) and position t in it (may be < 0
        or > 1 in the extrapolated ends)."""
        j = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, knots.size - 2)
        t = (x - knots[j]) / (knots[j + 1] - knots[j])
        if getattr(self, "extrapolation", "linear") == "constant":
            t = np.clip(t, 0.0, 1.0)
        return j, t

    def value(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        x = _x(x)
        knots, vals = self._split(p)
        j, t = self._segment(x, knots)
        return vals[j] + t * (vals[j + 1] - vals[j])

    def dx(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        x = _x(x)
        knots, vals = self._split(p)
        j, _t = self._segment(x, knots)
        inside = (x >= knots[0]) & (x <= knots[-1]) if self.extrapolation == "constant" else True
        return np.where(inside, (vals[j + 1] - vals[j]) / (knots[j + 1] - knots[j]), 0.0)

    def dp(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        x = _x(x)
        knots, vals = self._split(p)
        k = knots.size
        j, t = self._segment(x, knots)
        rows = np.arange(x.size)
        dv = np.zeros((x.size, k))
        dv[rows, j] = 1.0 - t
        dv[rows, j + 1] += t
        if self._monotone():
            return dv @ self._cum()
        if not self.estimate_knots:
            return dv
        # v = vals_j + (x - k_j) / (k_{j+1} - k_j) * dvals
        h = knots[j + 1] - knots[j]
        slope = (vals[j + 1] - vals[j]) / h
        if self.extrapolation == "constant":  # held end values do not move with the knots
            slope = np.where((x >= knots[0]) & (x <= knots[-1]), slope, 0.0)
        dk = np.zeros((x.size, k))
        dk[rows, j] = -slope + slope * t          # d/dk_j: -(slope) + (x-k_j) slope / h
        dk[rows, j + 1] += -slope * t             # d/dk_{j+1}: -(x - k_j) slope / h
        return np.concatenate([dk, dv], axis=1)

    def casadi(self, x: Any, p: np.ndarray) -> Any:
        import casadi as ca

        knots, vals = self._split(np.asarray(p, dtype=float))
        slopes = np.diff(vals) / np.diff(knots)
        if self.extrapolation == "constant":
            x = ca.fmin(ca.fmax(x, float(knots[0])), float(knots[-1]))
        # v = vals_0 + s_0 (x - k_0) + sum_j (s_j - s_{j-1}) max(x - k_j, 0): exact, linear beyond both ends
        out = float(vals[0]) + float(slopes[0]) * (x - float(knots[0]))
        for j in range(1, slopes.size):
            out = out + float(slopes[j] - slopes[j - 1]) * ca.fmax(x - float(knots[j]), 0.0)
        return out


@_register
class Saturation(StaticNonlinearity):
    """``g(x) = min(max(x, lower), upper)``; ``-inf`` / ``inf`` leave a side open (Paper IV's output block:
    ``lower = w_min = -mean(y) / SD(y)``, no upper limit).

    Parameters
    ----------
    lower, upper : float
        Limits (``lower < upper``).
    estimate : bool
        Estimate the finite limits.
    """

    def __init__(self, lower: float = -np.inf, upper: float = np.inf, estimate: bool = False) -> None:
        self.lower = lower
        self.upper = upper
        self.estimate = estimate

    def _finite(self) -> list[int]:
        return [i for i, v in enumerate((self.lower, self.upper)) if np.isfinite(v)]

    def n_params(self) -> int:
        return len(self._finite())

    def initial_params(self, x: np.ndarray) -> np.ndarray:
        if not float(self.lower) < float(self.upper):
            raise ValueError(f"Saturation needs lower < upper, got {self.lower}, {self.upper}")
        lim = (float(self.lower), float(self.upper))
        return np.array([lim[i] for i in self._finite()])

    def _limits(self, p: np.ndarray) -> tuple[float, float]:
        lim = [float(self.lower), float(self.upper)]
        for i, v in zip(self._finite(), p, strict=False):
            lim[i] = float(v)
        return lim[0], lim[1]

    def value(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        lo, hi = self._limits(p)
        return np.clip(_x(x), lo, hi)

    def dx(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        lo, hi = self._limits(p)
        x = _x(x)
        return ((x > lo) & (x < hi)).astype(float)

    def dp(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        lo, hi = self._limits(p)
        x = _x(x)
        cols = {0: (x <= lo).astype(float), 1: (x >= hi).astype(float)}
        return np.column_stack([cols[i] for i in self._finite()]) if self._finite() else np.zeros((x.size, 0))

    def casadi(self, x: Any, p: np.ndarray) -> Any:
        import casadi as ca

        lo, hi = self._limits(np.asarray(p, dtype=float))
        out = x
        if np.isfinite(lo):
            out = ca.fmax(out, lo)
        if np.isfinite(hi):
            out = ca.fmin(out, hi)
        return out


@_register
class DeadZone(StaticNonlinearity):
    """``g(x) = x - upper`` for x > upper, ``x - lower`` for x < lower, 0 in between (``lower <= upper``)."""

    def __init__(self, lower: float = -0.1, upper: float = 0.1, estimate: bool = False) -> None:
        self.lower = lower
        self.upper = upper
        self.estimate = estimate

    def n_params(self) -> int:
        return 2

    def initial_params(self, x: np.ndarray) -> np.ndarray:
        if not float(self.lower) <= float(self.upper):
            raise ValueError(f"DeadZone needs lower <= upper, got {self.lower}, {self.upper}")
        return np.array([float(self.lower), float(self.upper)])

    def value(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        x = _x(x)
        return np.where(x > p[1], x - p[1], np.where(x < p[0], x - p[0], 0.0))

    def dx(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        x = _x(x)
        return ((x > p[1]) | (x < p[0])).astype(float)

    def dp(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        x = _x(x)
        return np.column_stack([-(x < p[0]).astype(float), -(x > p[1]).astype(float)])

    def casadi(self, x: Any, p: np.ndarray) -> Any:
        import casadi as ca

        return ca.fmax(x - float(p[1]), 0.0) + ca.fmin(x - float(p[0]), 0.0)


@_register
class Polynomial(StaticNonlinearity):
    """``g(x) = sum_k c_k x^k`` for k = 0..degree, starting as the identity (c_1 = 1) unless ``coefficients``."""

    def __init__(self, degree: int = 3, coefficients: Sequence[float] | None = None, estimate: bool = True) -> None:
        self.degree = degree
        self.coefficients = coefficients
        self.estimate = estimate

    def n_params(self) -> int:
        return int(self.degree) + 1

    def initial_params(self, x: np.ndarray) -> np.ndarray:
        if int(self.degree) != self.degree or self.degree < 1:
            raise ValueError(f"degree must be a positive integer, got {self.degree}")
        if self.coefficients is not None:
            c = np.asarray(self.coefficients, dtype=float)
            if c.size != self.n_params():
                raise ValueError(f"need {self.n_params()} coefficients, got {c.size}")
            return c.copy()
        c = np.zeros(self.n_params())
        c[1] = 1.0
        return c

    def value(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return np.polynomial.polynomial.polyval(_x(x), p)

    def dx(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return np.polynomial.polynomial.polyval(_x(x), np.polynomial.polynomial.polyder(p))

    def dp(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return np.vander(_x(x), self.n_params(), increasing=True)

    def linear_in_params(self) -> bool:
        return True

    def scaled_params(self, p: np.ndarray, c: float) -> np.ndarray | None:
        return np.asarray(p, dtype=float) * c

    def casadi(self, x: Any, p: np.ndarray) -> Any:
        out = 0.0
        for c in np.asarray(p, dtype=float)[::-1]:  # Horner
            out = out * x + float(c)
        return out


def _check_degree(degree: Any, parity: int, name: str) -> int:
    """``degree`` as an int >= 1 of the given parity (0 even, 1 odd), or a ValueError naming the block."""
    try:
        ok = int(degree) == degree and degree >= 1 and int(degree) % 2 == parity
    except (TypeError, ValueError):
        ok = False
    if not ok:
        kind = "an even integer >= 2" if parity == 0 else "an odd integer >= 1"
        raise ValueError(f"{name}: degree must be {kind}, got {degree!r}")
    return int(degree)


@_register
class OddPolynomial(StaticNonlinearity):
    """``g(x) = sum_k c_k x^(2k+1)`` for k = 0..(degree-1)/2: an odd function (``g(-x) = -g(x)``, no offset), e.g. a
    symmetric saturation-like or cubic characteristic; starts as the identity (c_0 = 1) unless ``coefficients``.

    Parameters
    ----------
    degree : int
        Odd degree (>= 1; 3 gives ``c_0 x + c_1 x^3``).
    coefficients : sequence of float, optional
        ``(degree + 1) / 2`` starting coefficients.
    estimate : bool
        Estimate the coefficients.
    """

    def __init__(self, degree: int = 3, coefficients: Sequence[float] | None = None, estimate: bool = True) -> None:
        self.degree = degree
        self.coefficients = coefficients
        self.estimate = estimate

    def n_params(self) -> int:
        return (int(self.degree) + 1) // 2

    def _powers(self) -> np.ndarray:
        return 2 * np.arange(self.n_params()) + 1

    def initial_params(self, x: np.ndarray) -> np.ndarray:
        _check_degree(self.degree, 1, "OddPolynomial")
        if self.coefficients is not None:
            c = np.asarray(self.coefficients, dtype=float).reshape(-1)
            if c.size != self.n_params():
                raise ValueError(f"OddPolynomial of degree {self.degree} needs {self.n_params()} coefficients, got "
                                 f"{c.size}")
            return c.copy()
        c = np.zeros(self.n_params())
        c[0] = 1.0
        return c

    def linear_in_params(self) -> bool:
        return True

    def value(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return self.dp(x, p) @ np.asarray(p, dtype=float)

    def dx(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        x = _x(x)
        k = self._powers()
        return (x[:, None] ** (k - 1) * k) @ np.asarray(p, dtype=float)

    def dp(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return _x(x)[:, None] ** self._powers()

    def scaled_params(self, p: np.ndarray, c: float) -> np.ndarray | None:
        return np.asarray(p, dtype=float) * c

    def casadi(self, x: Any, p: np.ndarray) -> Any:
        out = 0.0
        x2 = x * x
        for c in np.asarray(p, dtype=float)[::-1]:  # Horner in x^2, times x
            out = out * x2 + float(c)
        return out * x


@_register
class EvenPolynomial(StaticNonlinearity):
    """``g(x) = sum_k c_k (x - centre)^(2k)`` for k = 0..degree/2: an even function about a given centre (a
    square-law detector, a sensor that sees only the magnitude of its signal); starts as ``(x - centre)^2`` unless
    ``coefficients``. An even block cannot start as the identity: see ``n_restarts`` of the estimator.

    Parameters
    ----------
    degree : int
        Even degree (>= 2; 2 gives ``c_0 + c_1 (x - centre)^2``).
    coefficients : sequence of float, optional
        ``degree / 2 + 1`` starting coefficients.
    centre : float
        The symmetry point, held fixed (normalised signals: 0).
    estimate : bool
        Estimate the coefficients.
    """

    even = True

    def __init__(self, degree: int = 2, coefficients: Sequence[float] | None = None, centre: float = 0.0,
                 estimate: bool = True) -> None:
        self.degree = degree
        self.coefficients = coefficients
        self.centre = centre
        self.estimate = estimate

    def n_params(self) -> int:
        return int(self.degree) // 2 + 1

    def _powers(self) -> np.ndarray:
        return 2 * np.arange(self.n_params())

    def initial_params(self, x: np.ndarray) -> np.ndarray:
        _check_degree(self.degree, 0, "EvenPolynomial")
        if not np.isfinite(float(self.centre)):
            raise ValueError(f"EvenPolynomial: centre must be finite, got {self.centre!r}")
        if self.coefficients is not None:
            c = np.asarray(self.coefficients, dtype=float).reshape(-1)
            if c.size != self.n_params():
                raise ValueError(f"EvenPolynomial of degree {self.degree} needs {self.n_params()} coefficients, "
                                 f"got {c.size}")
            return c.copy()
        c = np.zeros(self.n_params())
        c[1] = 1.0
        return c

    def linear_in_params(self) -> bool:
        return True

    def value(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return self.dp(x, p) @ np.asarray(p, dtype=float)

    def dx(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        z = _x(x) - float(self.centre)
        k = self._powers()[1:]
        return (z[:, None] ** (k - 1) * k) @ np.asarray(p, dtype=float)[1:]

    def dp(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        z = _x(x) - float(self.centre)
        return z[:, None] ** self._powers()

    def casadi(self, x: Any, p: np.ndarray) -> Any:
        z = x - float(self.centre)
        z2 = z * z
        out = 0.0
        for c in np.asarray(p, dtype=float)[::-1]:  # Horner in (x - centre)^2
            out = out * z2 + float(c)
        return out


@_register
class AbsoluteValue(StaticNonlinearity):
    """``g(x) = |x - centre| + offset``: a sensor that ignores the sign of what it measures (a pulse-counting speed
    sensor: Wigren and Schoukens' coupled electric drives, output ``|x_1|``). An even block: see ``n_restarts`` of
    the estimator. At ``x = centre`` the derivative is taken as 0 (a subgradient).

    Parameters
    ----------
    centre, offset : float
        Starting values (or fixed values when ``estimate`` is False).
    estimate : bool
        Estimate centre and offset.
    """

    even = True

    def __init__(self, centre: float = 0.0, offset: float = 0.0, estimate: bool = True) -> None:
        self.centre = centre
        self.offset = offset
        self.estimate = estimate

    def n_params(self) -> int:
        return 2

    def initial_params(self, x: np.ndarray) -> np.ndarray:
        p = np.array([float(self.centre), float(self.offset)])
        if not np.all(np.isfinite(p)):
            raise ValueError(f"AbsoluteValue: centre and offset must be finite, got {p.tolist()}")
        return p

    def fit_params(self, x: np.ndarray, target: np.ndarray) -> np.ndarray | None:
        """The offset that best maps ``x`` to ``target`` for the given centre (the offset enters linearly)."""
        x, target = _x(x), _x(target)
        c = float(self.centre)
        return np.array([c, float(np.mean(target - np.abs(x - c)))])

    def random_params(self, x: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Centre drawn about the median of the data (SD: half the data's SD), offset 0."""
        x = _x(x)
        return np.array([float(np.median(x)) + 0.5 * float(np.std(x)) * float(rng.standard_normal()), 0.0])

    def value(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return np.abs(_x(x) - p[0]) + p[1]

    def dx(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        return np.sign(_x(x) - p[0])

    def dp(self, x: np.ndarray, p: np.ndarray) -> np.ndarray:
        x = _x(x)
        return np.column_stack([-np.sign(x - p[0]), np.ones_like(x)])

    def casadi(self, x: Any, p: np.ndarray) -> Any:
        import casadi as ca

        return ca.fabs(x - float(p[0])) + float(p[1])
