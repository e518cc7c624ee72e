"""State-space prediction-error / simulation-error refinement (Paper IV's M-I, MATLAB ``pem`` on a state-space
model of order 2).

Starting from the subspace estimate (:class:`~ident.linear.subspace.N4SID`) or a given linear model of the same
order, all entries of (A, B, C[, D][, K][, x0]) are refined by ``scipy.optimize.least_squares`` on

* ``focus="simulation"``: the simulation error ``y - yhat`` with K = 0 (output-error criterion; what Paper IV
  describes: "minimization of the quadratic error between the measured output and the estimated output"), or
* ``focus="prediction"``: the one-step prediction error of the innovation-form predictor (classical PEM).

The Jacobian is exact (sensitivity recursion, :func:`~ident.linear._statespace.ss_sensitivities`). The full
parametrisation is redundant by the n^2 similarity transforms; the Levenberg-Marquardt damping handles that.

Initial state: ``estimate_x0=True`` makes x0 a parameter (stored as ``x0_``, the estimation record's initial
state); ``False`` fixes x0 = 0.

Several starts: the criterion has local minima (lightly damped modes whose frequencies the start misplaces, slow
modes a short subspace horizon cannot see), so the refinement runs from several starts and keeps the lowest
criterion on the estimation data: N4SID at each of ``horizon`` (default: ``max(2 order, 10)`` and twice that), plus
``n_random_starts`` random stable models (a random stable A with time constants up to a tenth of the record, a
random C, and the least-squares B, D, x0 for them; see :func:`~ident.linear._statespace.random_stable_ss`), seeded
by ``random_state``. ``start_costs_`` lists every start's criterion before and after its refinement. A given
``init`` model is the only start.

Stability: a step to an unstable A (simulation) or A - K C (prediction) gets a large residual and is rejected; if
the optimum is nonetheless unstable the eigenvalues are reflected (:func:`~ident.linear._statespace.stabilize`) and
the result is kept only if it is at least as good as the start. The refinement never returns a model worse on the
criterion than its start.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from scipy.optimize import least_squares

from ident.io import register_model
from ident.linear._kernels import state_sequence
from ident.linear._statespace import (
    LinearStateSpaceModel,
    data_columns,
    random_stable_ss,
    spectral_radius,
    ss_sensitivities,
    stabilize,
    validate_fit_data,
)
from ident.linear.statespace import StateSpaceModel
from ident.linear.subspace import N4SID, refine_bd_x0


@register_model("ss_pem")
class StateSpacePEM(LinearStateSpaceModel):
    """State-space model of given order refined by prediction- or simulation-error minimisation.

    Parameters
    ----------
    order : int
        State dimension (Paper IV: 2).
    feedthrough : bool
        Estimate D.
    focus : {"simulation", "prediction"}
        Criterion (see module docstring).
    estimate_x0 : bool
        Estimate the initial state x0 with the parameters (True) or fix x0 = 0.
    horizon : int or sequence of int, optional
        Horizon(s) of the subspace starts (see :class:`N4SID`); default ``max(2 order, 10)`` and twice that.
    max_nfev : int
        Iteration budget of each start's refinement.
    init : LinearStateSpaceModel, optional
        A fitted linear model of the same order to start from instead of the subspace and random starts.
    n_random_starts : int
        Random stable starts in addition to the subspace ones (module docstring).
    random_state : int or None
        Seed of the random starts (None: fresh entropy, not reproducible).

    Attributes
    ----------
    A_, B_, C_, D_, K_, x0_ : ndarray
    cost_ : float
        Final mean squared error of the criterion on the estimation data.
    initial_cost_ : float
        The same for the best start (the lowest before refinement), so ``cost_ <= initial_cost_``.
    start_ : str
        The start the kept model came from (``"n4sid(horizon=10)"``, ``"random 1"``, ``"init"``).
    start_costs_ : list of dict
        Per start: ``start``, ``initial_cost`` and ``cost`` (after refinement; inf when its refinement failed).
    """

    _saved_meta = ("cost_", "initial_cost_")

    def __init__(self, order: int = 2, feedthrough: bool = False,
                 focus: Literal["simulation", "prediction"] = "simulation",
                 estimate_x0: bool = True, horizon: int | Sequence[int] | None = None,
                 max_nfev: int = 200, init: LinearStateSpaceModel | None = None, n_random_starts: int = 2,
                 random_state: int | None = 0) -> None:
        self.order = order
        self.feedthrough = feedthrough
        self.focus = focus
        self.estimate_x0 = estimate_x0
        self.horizon = horizon
        self.max_nfev = max_nfev
        self.init = init
        self.n_random_starts = n_random_starts
        self.random_state = random_state

    def _pack(self, A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, K: np.ndarray, x0: np.ndarray
              ) -> np.ndarray:
        parts = [A.ravel(), B.ravel(), C.ravel()]
        if self.feedthrough:
            parts.append(D.ravel())
        if self.focus == "prediction":
            parts.append(K.ravel())
        if self.estimate_x0:
            parts.append(x0)
        return np.concatenate(parts)

    def _unpack(self, th: np.ndarray, n: int, nu: int, ny: int) -> tuple[np.ndarray, ...]:
        o = 0

        def take(shape: tuple[int, int]) -> np.ndarray:
            nonlocal o
            size = shape[0] * shape[1]
            out = th[o:o + size].reshape(shape)
            o += size
            return out

        A, B, C = take((n, n)), take((n, nu)), take((ny, n))
        D = take((ny, nu)) if self.feedthrough else np.zeros((ny, nu))
        K = take((n, ny)) if self.focus == "prediction" else np.zeros((n, ny))
        x0 = th[o:o + n] if self.estimate_x0 else np.zeros(n)
        return A, B, C, D, K, x0

    def _horizons(self, n: int) -> list[int]:
        if self.horizon is None:
            h0 = max(2 * n, 10)
            return [h0, 2 * h0]
        hs = [self.horizon] if np.ndim(self.horizon) == 0 else list(self.horizon)
        if not hs:
            raise ValueError("horizon must be an integer, a non-empty sequence of them, or None")
        for h in hs:
            if int(h) != h or h < 1:
                raise ValueError(f"horizon must hold positive integers, got {self.horizon!r}")
        return sorted({int(h) for h in hs})

    def _starts(self, u: np.ndarray, y: np.ndarray, n: int, pred: bool
                ) -> list[tuple[str, tuple[np.ndarray, ...]]]:
        """(label, (A, B, C, D, K)) of every start (module docstring); subspace starts that fail are skipped."""
        nu, ny = u.shape[1], y.shape[1]
        if self.init is not None:
            A, B, C, D = (np.array(m, dtype=float) for m in self.init.state_space())
            if A.shape[0] != n:
                raise ValueError(f"init model has order {A.shape[0]}, expected {n}")
            if B.shape[1] != nu or C.shape[0] != ny:
                raise ValueError(f"init model has {B.shape[1]} inputs and {C.shape[0]} outputs, but the data have "
                                 f"u with {nu} and y with {ny} columns")
            K = np.array(getattr(self.init, "K_", np.zeros((n, ny))), dtype=float) if pred else np.zeros((n, ny))
            return [("init", (A, B, C, D, K))]
        starts: list[tuple[str, tuple[np.ndarray, ...]]] = []
        errors: list[str] = []
        for h in self._horizons(n):
            try:
                m = N4SID(order=n, horizon=h, feedthrough=self.feedthrough, estimate_k=pred).fit(u, y)
            except ValueError as err:
                errors.append(f"horizon {h}: {err}")
                continue
            starts.append((f"n4sid(horizon={h})", (m.A_, m.B_, m.C_, m.D_, m.K_)))
        if int(self.n_random_starts) != self.n_random_starts or self.n_random_starts < 0:
            raise ValueError(f"n_random_starts must be a non-negative integer, got {self.n_random_starts!r}")
        rng = np.random.default_rng(self.random_state)
        for k in range(int(self.n_random_starts)):
            A = random_stable_ss(n, rng, max(10.0, u.shape[0] / 10.0))
            C = rng.standard_normal((ny, n))
            B, D, _ = refine_bd_x0(A, C, u, y, self.feedthrough)
            starts.append((f"random {k + 1}", (A, B, C, D, np.zeros((n, ny)))))
        if not starts:
            raise ValueError("no start for the state-space refinement: " + "; ".join(errors))
        return starts

    def fit(self, u: Any, y: Any) -> StateSpacePEM:
        n = int(self.order)
        if n < 1 or n != self.order:
            raise ValueError(f"order must be a positive integer, got {self.order}")
        if self.focus not in ("simulation", "prediction"):
            raise ValueError(f"focus must be 'simulation' or 'prediction', got {self.focus!r}")
        nu, _ = data_columns(u, y, f"state-space model of order {n}")
        n_par = n * n + n * nu + n + n * self.feedthrough * nu + (n if self.focus == "prediction" else 0) + n
        u, y = validate_fit_data(u, y, n_par, 0, f"state-space model of order {n}")
        pred = self.focus == "prediction"
        results = []
        for label, start in self._starts(u, y, n, pred):
            th, cost, cost0, nfev = self._refine(u, y, n, pred, *start)
            results.append((cost, cost0, label, th, nfev))
        best = min(results, key=lambda r: (r[0], r[1]))
        cost, _, label, th, nfev = best
        ny = y.shape[1]
        self.A_, self.B_, self.C_, self.D_, self.K_, self.x0_ = (np.array(m) for m in
                                                                 self._unpack(th, n, nu, ny))
        self.cost_ = cost
        self.initial_cost_ = float(min(r[1] for r in results))
        self.nfev_ = nfev
        self.start_ = label
        self.start_costs_ = [{"start": r[2], "initial_cost": r[1], "cost": r[0]} for r in results]
        return self

    def _refine(self, u: np.ndarray, y: np.ndarray, n: int, pred: bool, A: np.ndarray, B: np.ndarray,
                C: np.ndarray, D: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, float, float, int]:
        """Refine one start; returns (theta, cost, cost at the start, evaluations). Never worse than the start."""
        nu, ny = u.shape[1], y.shape[1]
        if not self.feedthrough:
            D = np.zeros((ny, nu))
        if not pred:
            K = np.zeros((n, ny))
        # x0 of the start model; a throw-away model so a failing fit leaves self unfitted
        x0 = StateSpaceModel(A, B, C, D).initial_state(u, y) if self.estimate_x0 else np.zeros(n)
        free = {"D": bool(self.feedthrough), "K": pred, "x0": self.estimate_x0}
        y_arg = y if pred else None
        big = 1e3 * np.sqrt(np.mean(y**2) + 1.0)

        def unstable(A: np.ndarray, C: np.ndarray, K: np.ndarray) -> bool:
            return spectral_radius(A - K @ C if pred else A) >= 1.0

        def resid(th: np.ndarray) -> np.ndarray:
            A, B, C, D, K, x0 = self._unpack(th, n, nu, ny)
            if unstable(A, C, K):
                return np.full(y.size, big)
            yhat, _ = self._sim(A, B, C, D, K, u, y_arg, x0)
            r = (y - yhat).ravel()
            return r if np.all(np.isfinite(r)) else np.full(y.size, big)

        def jac(th: np.ndarray) -> np.ndarray:
            A, B, C, D, K, x0 = self._unpack(th, n, nu, ny)
            _, J = ss_sensitivities(A, B, C, D, K if pred else None, u, y_arg, x0, free)
            J = -J.reshape(-1, J.shape[2])
            return np.nan_to_num(J, nan=0.0, posinf=0.0, neginf=0.0)

        th0 = self._pack(A, B, C, D, K, x0)
        cost0 = float(np.mean(resid(th0) ** 2))
        if not np.isfinite(cost0):
            return th0, np.inf, np.inf, 1
        res = least_squares(resid, th0, jac=jac, method="lm", x_scale="jac", max_nfev=self.max_nfev,
                            ftol=1e-10, xtol=1e-10, gtol=1e-10)
        th = res.x
        A, B, C, D, K, x0 = self._unpack(th, n, nu, ny)
        if unstable(A, C, K):
            A = stabilize(A)
            th = self._pack(A, B, C, D, K, x0)
        cost = float(np.mean(resid(th) ** 2))
        if not cost <= cost0:
            th, cost = th0, cost0
        return th, cost, cost0, int(res.nfev)

    @staticmethod
    def _sim(A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, K: np.ndarray, u: np.ndarray,
             y: np.ndarray | None, x0: np.ndarray) -> tuple[np.ndarray, None]:
        Abar = A - K @ C if y is not None else A
        drive = u @ (B - K @ D if y is not None else B).T + (y @ K.T if y is not None else 0.0)
        X = state_sequence(np.ascontiguousarray(Abar, dtype=float), np.ascontiguousarray(drive, dtype=float),
                           np.asarray(x0, dtype=float))[:-1]
        return X @ C.T + u @ D.T, None

    def _n_params(self) -> int:
        n, nu, ny = self.A_.shape[0], self.B_.shape[1], self.C_.shape[0]
        # identifiable parameters (canonical form): the n^2 similarity directions do not count
        return n * (ny + nu) + (ny * nu if self.feedthrough else 0) + (n * ny if self.focus == "prediction" else 0)

    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        meta, arrays = super()._get_state()
        meta["params"]["init"] = None  # the start model is not part of the result
        return meta, arrays
