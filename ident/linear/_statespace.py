"""Shared machinery of the linear models: every one of them is realised as a discrete-time state-space model

    x(t+1) = A x(t) + B u(t) + K e(t)
    y(t)   = C x(t) + D u(t) + e(t)

(``K`` = 0 for output-error structures), so simulation, k-step prediction, initial-state estimation, frequency
responses, CasADi export and saving are written once here.

Initial state (documented choice, used by every linear model):

* ``predict(u)`` starts from x(0) = 0 (data normalised to zero mean make this the natural default);
* ``predict(u, y0=Y)`` with measured outputs ``Y`` of shape (n0, n_outputs) starts from the x(0) that best explains
  ``Y`` given ``u[:n0]`` in least squares (:meth:`initial_state`), like MATLAB ``compare``'s estimated initial
  condition; give ``y0=y`` (the whole record) for the most accurate estimate;
* ``predict(u, x0=x)`` starts from a given state.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ident.base import BaseEstimator, as_2d, as_vector, check_is_fitted, check_not_constant, check_same_length
from ident.linear._kernels import sensitivity_outputs, state_sequence


def data_columns(u: Any, y: Any, model: str = "model") -> tuple[int, int]:
    """Numbers of input and output columns of estimation data, for setting up a model's orders before
    :func:`validate_fit_data` checks the data in full; raises ``ValueError`` naming ``u`` or ``y`` for a wrong
    shape, NaN/inf, no samples or no columns."""
    u = as_2d("u", u)
    y = as_2d("y", y)
    for name, a, signal in (("u", u, "input"), ("y", y, "output")):
        if a.shape[1] == 0:
            raise ValueError(f"{name} has no columns: the {model} needs at least one {signal} signal")
    return u.shape[1], y.shape[1]


def validate_fit_data(u: Any, y: Any, n_params: int, max_lag: int = 0, model: str = "model"
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Check estimation data and return float arrays (N, nu), (N, ny).

    Raises ``ValueError`` naming the argument and the problem: NaN/inf, no samples or no columns, mismatched lengths,
    a constant input column (to within 1e-12 relative: it carries no information and makes the regression
    singular), an output column that is exactly constant over all samples (``"y is constant ..."``: it carries no
    information about the dynamics; see :func:`ident.base.check_not_constant`, which also refuses a non-finite
    variance), or too few samples for the number of parameters per output. ``model`` names the estimator in the
    messages. Every estimator of :mod:`ident.linear`, the Hammerstein-Wiener and the multiple-model estimators
    validate their data here.
    """
    u = as_2d("u", u)
    y = as_2d("y", y)
    n = check_same_length(u=u, y=y)
    check_not_constant("y", y, model, "output")
    if u.shape[1] == 0:
        raise ValueError(f"u has no columns: the {model} needs at least one input signal")
    const = np.flatnonzero(np.ptp(u, axis=0) <= 1e-12 * np.maximum(1.0, np.abs(u).max(axis=0)))
    if const.size:
        raise ValueError(f"u is constant in column(s) {const.tolist()}: a constant input carries no information "
                         f"for identifying the {model} (remove it or excite it)")
    check_not_constant("u", u, model, "input")
    if n - max_lag < n_params + 1:
        raise ValueError(f"too few samples for the model order: {n} samples, but the {model}, with {n_params} "
                         f"parameters per output and {max_lag} lags, needs more than {n_params + max_lag + 1}")
    return u, y


def simulate_ss(A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, u: np.ndarray,
                x0: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Free-run simulation; returns (y, x) with y of shape (N, ny) and states x of shape (N + 1, n)."""
    n = A.shape[0]
    x = np.zeros(n) if x0 is None else np.asarray(x0, dtype=float).reshape(n)
    X = state_sequence(np.ascontiguousarray(A, dtype=float), np.ascontiguousarray(u @ B.T, dtype=float), x)
    return X[:-1] @ C.T + u @ D.T, X


def spectral_radius(A: np.ndarray) -> float:
    """Largest absolute eigenvalue of the square matrix ``A`` (0.0 for an empty 0 x 0 matrix).

    A discrete-time system ``x+ = A x`` is asymptotically stable exactly when this is below 1.
    """
    return float(np.max(np.abs(np.linalg.eigvals(A)))) if A.size else 0.0


def stabilize(A: np.ndarray, max_radius: float = 0.999) -> np.ndarray:
    """Reflect eigenvalues outside the circle of radius ``max_radius`` inside it (lambda -> r^2 / conj(lambda)),
    keeping A real; the frequency-response magnitude shape is kept, only the unstable modes' phase changes."""
    lam, V = np.linalg.eig(A)
    bad = np.abs(lam) > max_radius
    if not bad.any():
        return A
    lam = lam.copy()
    lam[bad] = max_radius**2 / np.conj(lam[bad])
    return np.real(V @ np.diag(lam) @ np.linalg.inv(V))


def random_stable_poles(n: int, rng: np.random.Generator, max_time_constant: float) -> np.ndarray:
    """``n`` random discrete-time poles for a random stable start: complex-conjugate pairs (and one real pole when
    ``n`` is odd) with time constants ``tau`` log-uniform between 1 and ``max_time_constant`` samples (radius
    ``exp(-1 / tau)``), the pairs at angles uniform in [0, pi/2) (at most four samples per period)."""
    tau_max = max(float(max_time_constant), 1.5)
    poles: list[complex] = []
    while len(poles) < n:
        r = float(np.exp(-1.0 / np.exp(rng.uniform(0.0, np.log(tau_max)))))
        if n - len(poles) == 1:
            poles.append(complex(r, 0.0))
        else:
            angle = float(rng.uniform(0.0, np.pi / 2))
            poles += [r * np.exp(1j * angle), r * np.exp(-1j * angle)]
    return np.asarray(poles)


def random_stable_poly(n: int, rng: np.random.Generator, max_time_constant: float) -> np.ndarray:
    """A random monic polynomial in q^-1 of order ``n`` with the poles of :func:`random_stable_poles`."""
    return np.real(np.poly(random_stable_poles(n, rng, max_time_constant))) if n else np.ones(1)


def random_stable_ss(n: int, rng: np.random.Generator, max_time_constant: float) -> np.ndarray:
    """A random stable real ``A`` (n x n) with the poles of :func:`random_stable_poles`, in real block-diagonal form
    (2 x 2 rotation-scaling blocks for the complex pairs) turned by a random orthogonal similarity."""
    lam = random_stable_poles(n, rng, max_time_constant)
    A = np.zeros((n, n))
    k = 0
    while k < n:
        if abs(lam[k].imag) > 0 and k + 1 < n:
            a, b = lam[k].real, abs(lam[k].imag)
            A[k:k + 2, k:k + 2] = [[a, -b], [b, a]]
            k += 2
        else:
            A[k, k] = lam[k].real
            k += 1
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    return Q @ A @ Q.T


def ss_sensitivities(A: np.ndarray, B: np.ndarray, C: np.ndarray, D: np.ndarray, K: np.ndarray | None,
                     u: np.ndarray, y: np.ndarray | None, x0: np.ndarray, free: dict[str, bool]
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Output of the (predictor) state-space model and its exact derivative with respect to the free parameters.

    The model is ``x+ = A x + B u + K (y - C x - D u)``, ``yhat = C x + D u`` (K = None: simulation). Parameters are
    ordered ``vec(A), vec(B), vec(C)``, then ``vec(D)``, ``vec(K)``, ``x0`` if ``free`` says so (row-major vec).
    The sensitivity S = dx/dtheta follows ``S+ = (A - K C) S + G(t) - K H(t)``, G and H being the explicit
    derivatives of the state and output equations, so the Jacobian is exact, not a finite difference.

    Returns
    -------
    yhat : ndarray, shape (N, ny)
    J : ndarray, shape (N, ny, n_params)
    """
    n, nu = B.shape
    ny = C.shape[0]
    N = u.shape[0]
    use_k = K is not None
    Abar = A - K @ C if use_k else A
    Bbar = B - K @ D if use_k else B
    # the simulation of the predictor: inputs u and (if K) the measured y
    drive = u @ Bbar.T + (y @ K.T if use_k else 0.0)
    X = state_sequence(np.ascontiguousarray(Abar, dtype=float), np.ascontiguousarray(drive, dtype=float),
                       np.asarray(x0, dtype=float))[:-1]
    yhat = X @ C.T + u @ D.T
    sizes = [("A", n * n), ("B", n * nu), ("C", ny * n)]
    if free.get("D"):
        sizes.append(("D", ny * nu))
    if free.get("K"):
        sizes.append(("K", n * ny))
    if free.get("x0"):
        sizes.append(("x0", n))
    off: dict[str, int] = {}
    p = 0
    for name, s in sizes:
        off[name] = p
        p += s
    G = np.zeros((N, n, p))
    H = np.zeros((N, ny, p))
    for r in range(n):
        G[:, r, off["A"] + r * n: off["A"] + (r + 1) * n] = X
        G[:, r, off["B"] + r * nu: off["B"] + (r + 1) * nu] = u
    for i in range(ny):
        H[:, i, off["C"] + i * n: off["C"] + (i + 1) * n] = X
        if "D" in off:
            H[:, i, off["D"] + i * nu: off["D"] + (i + 1) * nu] = u
    if "K" in off:
        assert y is not None
        E = y - yhat
        for r in range(n):
            G[:, r, off["K"] + r * ny: off["K"] + (r + 1) * ny] = E
    if use_k:
        G -= np.einsum("ij,tjp->tip", K, H)
    S = np.zeros((n, p))
    if "x0" in off:
        S[:, off["x0"]:off["x0"] + n] = np.eye(n)
    J = sensitivity_outputs(np.ascontiguousarray(Abar, dtype=float), np.ascontiguousarray(C, dtype=float), G, S)
    J += H
    return yhat, J


class LinearStateSpaceModel(BaseEstimator):
    """Base of all linear models: subclasses set ``A_, B_, C_, D_`` (and ``K_``, the innovation gain used by
    :meth:`predict_k_step`; zero for output-error models) in ``fit``.

    Subclasses list extra learned arrays in ``_saved_arrays`` and JSON-able learned values in ``_saved_meta``.
    """

    _saved_arrays: tuple[str, ...] = ()
    _saved_meta: tuple[str, ...] = ()

    @property
    def n_states_(self) -> int:
        check_is_fitted(self, "A_")
        return self.A_.shape[0]

    @property
    def n_inputs_(self) -> int:
        check_is_fitted(self, "A_")
        return self.B_.shape[1]

    @property
    def n_outputs_(self) -> int:
        check_is_fitted(self, "A_")
        return self.C_.shape[0]

    @property
    def n_params_(self) -> int:
        """Number of estimated parameters (free coefficients of the structure, not of the realisation)."""
        check_is_fitted(self, "A_")
        return int(self._n_params())

    def _n_params(self) -> int:
        return self.A_.size + self.B_.size + self.C_.size + self.D_.size

    def state_space(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The realisation (A, B, C, D) used for simulation."""
        check_is_fitted(self, "A_")
        return self.A_, self.B_, self.C_, self.D_

    def _u(self, u: Any) -> np.ndarray:
        check_is_fitted(self, "A_")
        return as_2d("u", u, n_columns=self.n_inputs_)

    # ------------------------------------------------------------------------------------- simulation
    def initial_state(self, u: Any, y: Any) -> np.ndarray:
        """The x(0) minimising the simulation error ``||y - yhat(x0)||`` over the given samples (least squares;
        the minimum-norm solution where the data do not determine it).

        Parameters
        ----------
        u : array_like, shape (n0, n_inputs)
        y : array_like, shape (n0, n_outputs)
        """
        u = self._u(u)
        y = as_2d("y", y, n_columns=self.n_outputs_)
        n0 = check_same_length(u=u, y=y)
        A, B, C, D = self.state_space()
        y_zero, _ = simulate_ss(A, B, C, D, u)
        # observability matrix rows C A^t, built iteratively; clip the horizon where A^t has died out anyway
        obs = np.empty((n0, C.shape[0], A.shape[0]))
        m = C.copy()
        for t in range(n0):
            obs[t] = m
            m = m @ A
        x0, *_ = np.linalg.lstsq(obs.reshape(-1, A.shape[0]), (y - y_zero).ravel(), rcond=None)
        return x0

    def predict(self, u: Any, y0: Any = None, *, x0: Any = None) -> np.ndarray:
        """Simulated (free-run) output, shape (N, n_outputs).

        Parameters
        ----------
        u : array_like, shape (N, n_inputs)
        y0 : array_like, shape (n0, n_outputs) or (n_outputs,), optional
            Measured outputs at the start of the record; x(0) is then estimated from them and ``u[:n0]``
            (:meth:`initial_state`). Default: x(0) = 0.
        x0 : array_like, shape (n_states,), optional
            Explicit initial state (takes precedence over ``y0``).
        """
        u = self._u(u)
        if x0 is not None:
            x0 = as_vector("x0", x0, self.n_states_, "values (one per state)")
        elif y0 is not None:
            y0 = as_2d("y0", np.atleast_1d(y0)[None, :] if np.ndim(y0) == 1 and self.n_outputs_ > 1 else y0,
                       n_columns=self.n_outputs_)
            n0 = min(len(y0), len(u))
            x0 = self.initial_state(u[:n0], y0[:n0])
        y, _ = simulate_ss(*self.state_space(), u, x0)
        return y

    def predict_k_step(self, u: Any, y: Any, k: int) -> np.ndarray:
        """k-step-ahead predictions ``yhat(t | t-k)``, shape (N, n_outputs).

        The predictor filter ``x(t+1|t) = A x + B u + K (y - C x - D u)`` runs over the measured data from the
        least-squares initial state; each prediction then propagates ``k - 1`` steps without measurements. Samples
        t < k are predicted from x(0) alone. For output-error models (K = 0) every k gives the simulated output.
        """
        u = self._u(u)
        y = as_2d("y", y, n_columns=self.n_outputs_)
        N = check_same_length(u=u, y=y)
        if int(k) != k or k < 1:
            raise ValueError(f"k must be a positive integer number of steps, got {k}")
        A, B, C, D = self.state_space()
        K = getattr(self, "K_", None)
        x0 = self.initial_state(u, y)
        if K is None or not np.any(K):
            return simulate_ss(A, B, C, D, u, x0)[0]
        # one-step predictor states Z[t] = x(t | t-1), Z[0] = x0
        Abar, Bbar = A - K @ C, B - K @ D
        drive = u @ Bbar.T + y @ K.T
        Z = np.empty((N, A.shape[0]))
        x = x0
        for t in range(N):
            Z[t] = x
            x = Abar @ x + drive[t]
        bu = u @ B.T
        # x(t | t-j) = A x(t-1 | t-j) + B u(t-1): vectorised over t, looped over the horizon
        for _ in range(int(k) - 1):
            Znew = Z.copy()
            Znew[1:] = Z[:-1] @ A.T + bu[:-1]
            Znew[0] = x0
            Z = Znew
        return Z @ C.T + u @ D.T

    def freqresp(self, omega: Any) -> np.ndarray:
        """Frequency response ``C (e^{jw} I - A)^{-1} B + D`` at ``omega`` rad/sample, shape (len, ny, nu)."""
        A, B, C, D = self.state_space()
        w = np.atleast_1d(np.asarray(omega, dtype=float))
        eye = np.eye(A.shape[0])
        return np.stack([C @ np.linalg.solve(np.exp(1j * wi) * eye - A, B) + D for wi in w])

    def dcgain(self) -> np.ndarray:
        """Static gain, shape (ny, nu)."""
        return np.real(self.freqresp(0.0)[0])

    # -------------------------------------------------------------------------------------------- export
    def to_casadi(self) -> Any:
        """``casadi.Function('step', [x, u], [x_next, y])`` of the simulation model (K not included)."""
        import casadi as ca

        A, B, C, D = self.state_space()
        x = ca.SX.sym("x", A.shape[0])
        u = ca.SX.sym("u", B.shape[1])
        x_next = ca.mtimes(ca.DM(A), x) + ca.mtimes(ca.DM(B), u)
        y = ca.mtimes(ca.DM(C), x) + ca.mtimes(ca.DM(D), u)
        return ca.Function("step", [x, u], [x_next, y], ["x", "u"], ["x_next", "y"])

    # -------------------------------------------------------------------------------------------- saving
    def _get_state(self) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
        check_is_fitted(self, "A_")
        arrays = {k: getattr(self, k) for k in ("A_", "B_", "C_", "D_", "K_", "x0_") + self._saved_arrays
                  if getattr(self, k, None) is not None}
        meta = {"params": self.get_params(), "learned": {k: getattr(self, k) for k in self._saved_meta}}
        return meta, arrays

    @classmethod
    def _from_state(cls, meta: dict[str, Any], arrays: dict[str, np.ndarray]) -> LinearStateSpaceModel:
        params = {k: tuple(v) if isinstance(v, list) else v for k, v in meta["params"].items()}
        obj = cls(**params)
        for k, v in arrays.items():
            setattr(obj, k, v)
        for k, v in meta.get("learned", {}).items():
            setattr(obj, k, v)
        return obj


def _per_input(value: Any, n_inputs: int, name: str) -> np.ndarray:
    """Broadcast an order (int or one per input) to an int array of length n_inputs."""
    arr = np.atleast_1d(np.asarray(value))
    if arr.size == 1:
        arr = np.repeat(arr, n_inputs)
    if arr.size != n_inputs:
        raise ValueError(f"{name} has {arr.size} entries but the data have {n_inputs} inputs")
    if np.any(arr < 0) or np.any(arr != np.round(arr)):
        raise ValueError(f"{name} must hold non-negative integers, got {arr.tolist()}")
    return arr.astype(int)


def tf_to_ss(num: np.ndarray, den: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """SISO ``num(q^-1) / den(q^-1)`` (coefficients of q^0, q^-1, ...; den[0] = 1) to an observable-canonical
    realisation. The state dimension is ``max(len(num), len(den)) - 1``."""
    L = max(len(num), len(den))
    b = np.zeros(L)
    a = np.zeros(L)
    b[:len(num)] = num
    a[:len(den)] = den
    b = b / a[0]
    a = a / a[0]
    n = L - 1
    d = b[0]
    if n == 0:
        return np.zeros((0, 0)), np.zeros((0, 1)), np.zeros((1, 0)), np.array([[d]])
    # observable canonical form of y = sum b_k u(t-k) - sum a_k y(t-k)
    A = np.zeros((n, n))
    A[:, 0] = -a[1:]
    A[:-1, 1:] = np.eye(n - 1)
    B = (b[1:] - a[1:] * d).reshape(n, 1)
    C = np.zeros((1, n))
    C[0, 0] = 1.0
    return A, B, C, np.array([[d]])
