"""Multiple-model identification: local linear models blended by operating region (thesis chapter 7, first
proposal for future work).

The operating space is spanned by scheduling signals, columns of the input (for the SCR: inlet temperature and
exhaust flow), cut into a grid of regions by ``edges``. Region r has a local affine ARX model and a validity
function ``Phi_r(s)`` (normalised Gaussians or products of sigmoid windows; both sum to one everywhere), and the
model output is the validity-weighted blend of the local predictions (a Takagi-Sugeno / local-model-network model):

    yhat(t) = sum_r Phi_r(s(t)) * ( -sum_k a_{r,k} y(t-k) + sum_i sum_k b_{r,i,k} u_i(t-k) + c_r ),  s(t) = u(t)[sched]

* ``local="arx"``: each region's parameters by weighted least squares with weights ``Phi_r`` (local estimation,
  one-step prediction error);
* ``local="oe"``: started from the ARX solution, all parameters jointly minimise the *simulation* error (the past
  outputs in the regressor are the model's own), with the exact Jacobian of a sensitivity recursion.

State (for simulation, k-step prediction and CasADi): ``x(t) = [y(t-1) .. y(t-na), u(t-1) .. u(t-d)]``, the
non-minimal ARX state. Initial state: zero by default; from measured outputs, the system at rest at the first
sample (past outputs = y[0], past inputs = u[0]). Single-output (MISO) models only.

Stability: the OE refinement only accepts parameters whose every local model is stable (the roots of
``1 + a_1 z^-1 + .. + a_na z^-na`` inside the unit circle, :data:`MAX_LOCAL_POLE`); an unstable trial point scores
as a huge residual, so the trust region steps back. Without it, the simulation-error fit could make the local models
of regions that the estimation data visit briefly unstable, the blend staying bounded on the estimation data but
diverging where those regions dominate (seen on Paper IV's WHTC segment: two local poles at 1.21 and 1.31, validation
FIT -76919 %). The bound can be active: on that record one local pole ends at 0.999 (a time constant of about 500 s
at 0.5 s, the data asking for a near-integrating mode), and on the same segment's excitation record the constrained
fit validates at 26.5 % against 29.3 % unconstrained. An unstable ARX start is first pulled inside
(:func:`stabilise_local_denominators`), so the refinement starts feasible. Local stability does not prove the
blend's (switching between stable models can diverge). The refinement keeps its (stabilised) ARX start, with a
``RuntimeWarning``, if it cannot improve on it.
"""
from __future__ import annotations

import itertools
import warnings
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from scipy.optimize import least_squares

from ident.base import BaseEstimator, as_2d, as_vector, check_is_fitted, check_same_length
from ident.io import register_model
from ident.linear._statespace import _per_input, data_columns, validate_fit_data

#: Largest pole magnitude the OE refinement accepts for a local model (stable; at Ts = 0.5 s a time constant of
#: up to about 500 s).
MAX_LOCAL_POLE = 0.999
#: Pole magnitude an unstable pole of the local ARX start is pulled in to before the OE refinement.
STABLE_START_POLE = 0.99


def local_pole_magnitudes(a: np.ndarray) -> np.ndarray:
    """Largest pole magnitude of each local model, from the rows of ``a`` (shape (n_regions, na)): the roots of
    ``z^na + a_1 z^(na-1) + .. + a_na``; ``inf`` for a row with a non-finite coefficient."""
    a = np.atleast_2d(np.asarray(a, dtype=float))
    if a.shape[1] == 0:
        return np.zeros(a.shape[0])
    return np.array([float(np.max(np.abs(np.roots(np.concatenate([[1.0], row]))))) if np.all(np.isfinite(row))
                     else np.inf for row in a])


def stabilise_local_denominators(a: np.ndarray, max_pole: float = STABLE_START_POLE) -> np.ndarray:
    """The rows of ``a`` (local AR coefficients, shape (n_regions, na)) with every pole of magnitude at or above
    :data:`MAX_LOCAL_POLE` moved along its radius to ``max_pole`` (conjugate pairs stay pairs, so the coefficients
    stay real); rows whose poles are all inside are returned unchanged."""
    a = np.array(np.atleast_2d(np.asarray(a, dtype=float)))
    if not 0.0 < max_pole < MAX_LOCAL_POLE:
        raise ValueError(f"max_pole must be in (0, {MAX_LOCAL_POLE}), got {max_pole}")
    if not np.all(np.isfinite(a)):
        raise ValueError("the local AR coefficients must be finite")
    for r, row in enumerate(a):
        if row.size == 0:
            continue
        poles = np.roots(np.concatenate([[1.0], row]))
        mag = np.abs(poles)
        if np.any(mag >= MAX_LOCAL_POLE):
            poles = np.where(mag >= MAX_LOCAL_POLE, poles * (max_pole / np.maximum(mag, 1e-300)), poles)
            a[r] = np.real(np.poly(poles))[1:]
    return a


def quantile_edges(s: np.ndarray, n_regions: int) -> np.ndarray:
    """Grid edges putting the same number of samples of ``s`` in each of ``n_regions`` intervals (equally spaced
    edges between min and max instead if ``s`` takes few distinct values, so the edges stay increasing)."""
    s = np.asarray(s, dtype=float)
    if not np.all(np.isfinite(s)) or np.ptp(s) == 0:
        raise ValueError("the scheduling signal must be finite and not constant")
    edges = np.quantile(s, np.linspace(0.0, 1.0, n_regions + 1))
    if np.any(np.diff(edges) <= 1e-12 * np.ptp(s)):
        edges = np.linspace(s.min(), s.max(), n_regions + 1)
    return edges


def _sigmoid(z: Any, lib: Any) -> Any:
    return 1.0 / (1.0 + lib.exp(-z))


def validity_functions(s: Sequence[Any], edges: Sequence[np.ndarray], kind: str, width: float, lib: Any = np
                       ) -> list[Any]:
    """Normalised validity of every region (grid order: last scheduling variable fastest).

    ``s`` is one value or array per scheduling variable; ``lib`` is ``numpy`` or ``casadi`` (same formulas, so
    the CasADi export is the numpy model).
    """
    per_dim = []
    for sd, e in zip(s, edges, strict=False):
        e = np.asarray(e, dtype=float)
        w = np.diff(e)
        if kind == "gaussian":
            c = 0.5 * (e[:-1] + e[1:])
            per_dim.append([lib.exp(-0.5 * ((sd - c[j]) / (width * w[j])) ** 2) for j in range(len(w))])
        elif kind == "sigmoid":
            tau = width * float(w.min()) / 4.0
            # window j = sigma((s - e_j)/tau) - sigma((s - e_{j+1})/tau), outer edges at -inf/+inf: telescopes to 1
            lo = [1.0] + [_sigmoid((sd - e[j]) / tau, lib) for j in range(1, len(e) - 1)]
            hi = lo[1:] + [0.0]
            per_dim.append([lo[j] - hi[j] for j in range(len(w))])
        else:
            raise ValueError(f"validity must be 'gaussian' or 'sigmoid', got {kind!r}")
    mus = [_prod(combo) for combo in itertools.product(*per_dim)]
    if kind == "sigmoid":
        return mus
    total = mus[0]
    for m in mus[1:]:
        total = total + m
    return [m / total for m in mus]


def _prod(items: Sequence[Any]) -> Any:
    out = items[0]
    for it in items[1:]:
        out = out * it
    return out


@register_model("multiple_model")
class MultipleModel(BaseEstimator):
    """Local affine ARX/OE models blended by validity functions of scheduling inputs.

    Parameters
    ----------
    scheduling : sequence of int
        Input columns spanning the operating space (e.g. inlet temperature and exhaust flow).
    edges : sequence of array_like
        Grid edges per scheduling column, increasing, in the units of the data given to ``fit``; ``len(e) - 1``
        regions per column (see :func:`quantile_edges`).
    local : {"arx", "oe"}
        Estimation of the local models (see module docstring).
    na, nb, nk : int (nb, nk also one per input)
        Orders of every local model.
    validity : {"gaussian", "sigmoid"}
        Shape of the validity functions.
    width : float
        Overlap: Gaussian SD, or sigmoid transition length, in units of the region width.
    ridge : float
        Regularisation of the local least squares (regions with few samples stay well posed).
    max_nfev : int
        Iteration budget of the OE refinement.

    Attributes
    ----------
    theta_ : ndarray, shape (n_regions, na + sum(nb) + 1)
        Local parameters ``[a_1..a_na, b (per input, by lag), c]``.
    """

    def __init__(self, scheduling: Sequence[int], edges: Sequence[Sequence[float]], local: Literal["arx", "oe"] = "arx",
                 na: int = 2, nb: int | tuple[int, ...] = 2, nk: int | tuple[int, ...] = 1,
                 validity: Literal["gaussian", "sigmoid"] = "gaussian", width: float = 0.5, ridge: float = 1e-4,
                 max_nfev: int = 100) -> None:
        self.scheduling = scheduling
        self.edges = edges
        self.local = local
        self.na = na
        self.nb = nb
        self.nk = nk
        self.validity = validity
        self.width = width
        self.ridge = ridge
        self.max_nfev = max_nfev

    # ------------------------------------------------------------------------------------------ helpers
    def _setup(self, nu: int) -> None:
        self._nb = _per_input(self.nb, nu, "nb")
        self._nk = _per_input(self.nk, nu, "nk")
        self._d = int(max(np.max(np.where(self._nb > 0, self._nk + self._nb - 1, 0)), 0))
        if len(self.scheduling) != len(self.edges):
            raise ValueError("give one edge array per scheduling column")
        for c in self.scheduling:
            if not 0 <= int(c) < nu:
                raise ValueError(f"scheduling column {c} is not an input column (n_inputs = {nu})")
        for e in self.edges:
            e = np.asarray(e, dtype=float)
            if e.ndim != 1 or e.size < 2 or np.any(np.diff(e) <= 0) or not np.all(np.isfinite(e)):
                raise ValueError(f"edges must be increasing finite arrays with at least two values, got {e}")

    def _phi(self, u: np.ndarray) -> np.ndarray:
        s = [u[:, int(c)] for c in self.scheduling]
        return np.column_stack(validity_functions(s, self.edges, self.validity, self.width))

    def _lagged_inputs(self, u: np.ndarray, u_past: np.ndarray) -> np.ndarray:
        """Input part of the regressor, shape (N, sum nb); ``u_past`` (d, nu) holds u(-1) .. u(-d)."""
        ext = np.vstack([u_past[::-1], u]) if self._d else u
        d = self._d
        N = u.shape[0]
        cols = []
        for i in range(u.shape[1]):
            cols += [ext[d - k:d - k + N, i] for k in range(self._nk[i], self._nk[i] + self._nb[i])]
        return np.column_stack(cols) if cols else np.zeros((N, 0))

    @property
    def n_regions_(self) -> int:
        return int(np.prod([len(e) - 1 for e in self.edges]))

    @property
    def n_params_(self) -> int:
        check_is_fitted(self, "theta_")
        return int(self.theta_.size)

    @property
    def n_states_(self) -> int:
        check_is_fitted(self, "theta_")
        return int(self.na) + self._d * self.n_inputs_

    # ---------------------------------------------------------------------------------------------- fit
    def fit(self, u: Any, y: Any) -> MultipleModel:
        nu_data, _ = data_columns(u, y, "multiple model")
        self._setup(nu_data)
        na = int(self.na)
        p_loc = na + int(self._nb.sum()) + 1
        u, y = validate_fit_data(u, y, self.n_regions_ * p_loc, max(na, self._d), "multiple model")
        if y.shape[1] != 1:
            raise ValueError(f"MultipleModel is single-output (MISO); y has {y.shape[1]} columns")
        if self.local not in ("arx", "oe"):
            raise ValueError(f"local must be 'arx' or 'oe', got {self.local!r}")
        self.n_inputs_ = u.shape[1]
        yv = y[:, 0]
        N = len(yv)
        lag = max(na, self._d)
        Phi = self._phi(u)
        ulag = self._lagged_inputs(u, np.zeros((self._d, u.shape[1])))
        yreg = np.column_stack([-yv[lag - k:N - k] for k in range(1, na + 1)]) if na else np.zeros((N - lag, 0))
        X = np.column_stack([yreg, ulag[lag:], np.ones(N - lag)])
        target = yv[lag:]
        theta = np.zeros((Phi.shape[1], p_loc))
        scale = np.maximum(X.std(axis=0), 1e-12)
        scale[-1] = 1.0
        for r in range(Phi.shape[1]):
            w = Phi[lag:, r]
            sw = np.sqrt(w)[:, None]
            lhs = np.vstack([X * sw, np.diag(np.sqrt(self.ridge * max(w.sum(), 1.0)) * scale)])
            rhs = np.concatenate([target * sw[:, 0], np.zeros(p_loc)])
            theta[r], *_ = np.linalg.lstsq(lhs, rhs, rcond=None)
        self.theta_ = theta
        if self.local == "oe":
            self._refine_oe(u, yv)
        return self

    def _refine_oe(self, u: np.ndarray, yv: np.ndarray) -> None:
        x0 = self._rest_state(u, yv[:1, None])
        shape = self.theta_.shape
        big = 1e3 * np.sqrt(np.mean(yv**2) + 1.0)

        na = int(self.na)

        def stable(th: np.ndarray) -> bool:
            return bool(np.all(local_pole_magnitudes(th.reshape(shape)[:, :na]) < MAX_LOCAL_POLE))

        def resid(th: np.ndarray) -> np.ndarray:
            if not stable(th):
                return np.full(len(yv), big)
            self.theta_ = th.reshape(shape)
            yh = self._simulate(u, x0)
            r = yv - yh
            return r if np.all(np.isfinite(r)) and np.max(np.abs(r)) < 1e6 else np.full(len(yv), big)

        def jac(th: np.ndarray) -> np.ndarray:
            self.theta_ = th.reshape(shape)
            _, J = self._simulate(u, x0, jac=True)
            return np.nan_to_num(-J)

        start = self.theta_.copy()
        start[:, :na] = stabilise_local_denominators(start[:, :na])
        th0 = start.ravel()
        c0 = float(np.mean(resid(th0) ** 2))
        res = least_squares(resid, th0, jac=jac, method="trf", x_scale="jac", max_nfev=self.max_nfev)
        c1 = float(np.mean(resid(res.x) ** 2))
        if c1 <= c0 and stable(res.x):
            self.theta_ = res.x.reshape(shape)
        else:
            warnings.warn("MultipleModel: the OE refinement did not improve on its (stabilised) ARX start; the "
                          "start is kept", RuntimeWarning, stacklevel=3)
            self.theta_ = start

    # ------------------------------------------------------------------------------------------ simulation
    def _split_state(self, x0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        na = int(self.na)
        return x0[:na], x0[na:].reshape(self._d, self.n_inputs_)

    def _rest_state(self, u: np.ndarray, y0: np.ndarray) -> np.ndarray:
        return np.concatenate([np.full(int(self.na), float(y0[0, 0])), np.tile(u[0], self._d)])

    def _blend(self, u: np.ndarray, u_past: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        na = int(self.na)
        Phi = self._phi(u)
        ulag = self._lagged_inputs(u, u_past)
        a_eff = Phi @ self.theta_[:, :na]                      # (N, na)
        g = np.einsum("tr,tr->t", Phi, ulag @ self.theta_[:, na:-1].T) + Phi @ self.theta_[:, -1]
        return Phi, ulag, a_eff, g

    def _simulate(self, u: np.ndarray, x0: np.ndarray, jac: bool = False) -> Any:
        na = int(self.na)
        y_past, u_past = self._split_state(x0)
        Phi, ulag, a_eff, g = self._blend(u, u_past)
        N = u.shape[0]
        yh = np.empty(N)
        hist = list(y_past)  # hist[k-1] = y(t-k)
        for t in range(N):
            yh[t] = g[t] - sum(a_eff[t, k] * hist[k] for k in range(na))
            hist = [yh[t], *hist[:-1]] if na else hist
        if not jac:
            return yh
        # d yhat(t) / d theta_r = Phi_r(t) [ -yhat(t-k) .., ulag(t), 1 ] - sum_k a_eff(t,k) d yhat(t-k) / d theta
        ypast = np.column_stack([np.concatenate([y_past[k - 1::-1], yh])[:N] for k in range(1, na + 1)]) \
            if na else np.zeros((N, 0))
        reg = np.column_stack([-ypast, ulag, np.ones(N)])
        direct = (Phi[:, :, None] * reg[:, None, :]).reshape(N, -1)
        J = np.empty_like(direct)
        for t in range(N):
            j = direct[t].copy()
            for k in range(1, min(na, t) + 1):
                j -= a_eff[t, k - 1] * J[t - k]
            J[t] = j
        return yh, J

    def initial_state(self, u: Any, y: Any) -> np.ndarray:
        """State at rest at the first sample: past outputs y[0], past inputs u[0]."""
        check_is_fitted(self, "theta_")
        u = as_2d("u", u, n_columns=self.n_inputs_)
        y = as_2d("y", y, n_columns=1)
        return self._rest_state(u, y)

    def predict(self, u: Any, y0: Any = None, *, x0: Any = None) -> np.ndarray:
        """Simulated output, shape (N, 1); ``y0`` (measured outputs, first row used) sets the rest state, else
        the state is zero."""
        check_is_fitted(self, "theta_")
        u = as_2d("u", u, n_columns=self.n_inputs_)
        if x0 is None:
            if y0 is not None:
                y0a = as_2d("y0", np.atleast_1d(np.asarray(y0, dtype=float)).reshape(-1, 1))
                x0 = self.initial_state(u, y0a[:1])
            else:
                x0 = np.zeros(self.n_states_)
        return self._simulate(u, as_vector("x0", x0, self.n_states_, "values (one per state)"))[:, None]

    def predict_k_step(self, u: Any, y: Any, k: int) -> np.ndarray:
        """``yhat(t | t-k)``: k-step-ahead predictions with measured outputs up to t - k, shape (N, 1)."""
        check_is_fitted(self, "theta_")
        u = as_2d("u", u, n_columns=self.n_inputs_)
        y = as_2d("y", y, n_columns=1)
        N = check_same_length(u=u, y=y)
        if int(k) != k or k < 1:
            raise ValueError(f"k must be a positive integer number of steps, got {k}")
        na = int(self.na)
        x0 = self._rest_state(u, y)
        y_past, u_past = self._split_state(x0)
        _, _, a_eff, g = self._blend(u, u_past)
        meas = np.concatenate([y_past[::-1], y[:, 0]])  # meas[na + t] = y(t)
        preds: list[np.ndarray] = []
        for j in range(1, int(k) + 1):
            yreg = np.empty((N, na))
            for lag in range(1, na + 1):
                if lag >= j:
                    yreg[:, lag - 1] = meas[na - lag:na - lag + N]
                else:
                    src = preds[j - lag - 1]  # P_{j-lag}
                    col = np.empty(N)
                    col[lag:] = src[:N - lag]
                    col[:lag] = meas[na - lag:na]  # before the record: rest values
                    yreg[:, lag - 1] = col
            preds.append(g - np.einsum("tk,tk->t", a_eff, yreg))
        return preds[-1][:, None]

    def local_validity(self, u: Any) -> np.ndarray:
        """Validity of every region at every sample, shape (N, n_regions)."""
        check_is_fitted(self, "theta_")
        return self._phi(as_2d("u", u, n_columns=self.n_inputs_))

    # ---------------------------------------------------------------------------------------------- export
    def to_casadi(self) -> Any:
        """``casadi.Function('step', [x, u], [x_next, y])`` with x = [y(t-1)..y(t-na), u(t-1)..u(t-d)]."""
        import casadi as ca

        check_is_fitted(self, "theta_")
        na, d, nu = int(self.na), self._d, self.n_inputs_
        x = ca.SX.sym("x", na + d * nu)
        u = ca.SX.sym("u", nu)
        s = [u[int(c)] for c in self.scheduling]
        phi = validity_functions(s, self.edges, self.validity, self.width, lib=ca)
        ulags = [u] + [x[na + (k - 1) * nu:na + k * nu] for k in range(1, d + 1)]
        reg = [-x[k] for k in range(na)]
        for i in range(nu):
            reg += [ulags[k][i] for k in range(self._nk[i], self._nk[i] + self._nb[i])]
        reg.append(1.0)
        regv = ca.vertcat(*reg)
        y = 0
        for r in range(self.theta_.shape[0]):
            y = y + phi[r] * ca.dot(ca.DM(self.theta_[r]), regv)
        parts = ([y] + [x[k] for k in range(na - 1)]) if na else []
        if d:
            parts += [u] + [x[na + k * nu:na + (k + 1) * nu] for k in range(d - 1)]
        x_next = ca.vertcat(*parts) if parts else ca.SX(0, 1)
        return ca.Function("step", [x, u], [x_next, y], ["x", "u"], ["x_next", "y"])

    # ---------------------------------------------------------------------------------------------- saving
    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        check_is_fitted(self, "theta_")
        return {"params": self.get_params(), "n_inputs": self.n_inputs_}, {"theta_": self.theta_}

    @classmethod
    def _from_state(cls, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> MultipleModel:
        p = dict(meta["params"])
        for k in ("nb", "nk"):
            if isinstance(p[k], list):
                p[k] = tuple(p[k])
        obj = cls(**p)
        obj._setup(int(meta["n_inputs"]))
        obj.n_inputs_ = int(meta["n_inputs"])
        obj.theta_ = arrays["theta_"]
        return obj
