"""The :class:`RecursivePEM` estimator: recursive prediction error identification of a restricted black-box
nonlinear ODE model (Wigren 2006; thesis Papers I-III, ALGORITHMS.md section 1)."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ident.base import BaseEstimator, as_2d, check_is_fitted, check_not_constant, check_positive_int, check_same_length
from ident.io import register_model
from ident.metrics import fit_percent
from ident.rpem import kernel
from ident.rpem.kalman_init import ekf_initial_theta, ekf_state_estimates, kalman_options
from ident.rpem.regressors import polynomial_terms
from ident.rpem.structure import ChainStructure, apply_input_transforms, method_code


@register_model("rpem")
class RecursivePEM(BaseEstimator):
    """Recursive prediction error method on an n-state chain model with a polynomial right-hand side.

    Model (continuous time, per output k; a MIMO model is one chain per output)::

        dx_i/dt = x_{i+1}   (i < n),     dx_n/dt = phi(x, u, u')^T theta_k,     y_k = sat(x_1)

    discretised with Euler or the midpoint rule on the scaled sampling period ``Ts = alpha * T``. The parameters
    follow the Gauss-Newton recursion of ALGORITHMS.md section 1 with the gain from a forgetting factor
    ``lambda(t) = rate * lambda(t-1) + (1 - rate) * final`` (``final = 1``: the gain decays like 1/t;
    ``final < 1``: a tracking estimator for a drifting plant). Each candidate update is projected onto the
    model set DM: it is refused (theta keeps its previous value) unless, at the current state and input, the
    continuous-time linearisation ``dF/dx`` has every eigenvalue with real part below ``-stability_margin`` (in
    the model's scaled time) and the discretised step's Jacobian has spectral radius below 1. The state and the
    sensitivities are clipped to ``state_bound`` and ``sensitivity_bound``, so the recursion cannot diverge.

    Parameters
    ----------
    n_states : int
        Chain length n (states per output).
    terms : sequence of str, or one sequence per output, optional
        Regressor terms (see :mod:`ident.rpem.regressors`); a single list is a per-chain template in which
        ``x<i>`` is the chain's own state i. ``None``: all monomials within ``max_degrees``/``total_degree``.
    max_degrees, total_degree, derivative_inputs
        Passed to :func:`ident.rpem.regressors.polynomial_terms` when ``terms`` is ``None``.
    input_transforms : mapping, optional
        ``{j: (name, parameter)}`` replaces input j (1-based) before anything else, e.g.
        ``{3: ("exp_neg_inv", 1e4)}`` for Paper III's ``u3* = exp(-a / T_in)`` (T_in in K).
    sampling_period : float
        Data sampling period T in s.
    alpha : float
        Sampling-period scaling factor (Paper I); the model runs on ``Ts = alpha * T``. theta then describes the
        system on a time axis stretched by alpha.
    method : {"midpoint", "euler"}
        Discretisation.
    half_step_input : {"hold", "interpolate"}
        Input used at the midpoint half step: the held value (zero-order-hold inputs, the default) or the mean of
        two samples (samples of a smooth signal).
    stability_margin : float
        delta of the model set DM (a real-part margin on the scaled time axis; see above).
    theta0 : array_like, optional
        Initial parameters (zeros if omitted).
    R0, Lambda0 : float
        Initial Hessian scale ``R(0) = R0 I`` and noise covariance ``Lambda(0) = Lambda0 I``.
    forgetting_initial, forgetting_rate, forgetting_final : float
        lambda(0), the rate and the limit of the forgetting factor.
    output_limits : (float, float) or sequence of them, optional
        Output saturation (lower, upper) per output, lower < upper (either may be infinite); the gradient is zero
        where it is active.
    state_bound, sensitivity_bound : float
        Saturations of the state and of dx/dtheta.
    init : {"given", "kalman"}
        Start ``fit`` from ``theta0`` or from the augmented-state EKF of Brus and Wigren started at ``theta0``.
    kalman_options : dict, optional
        ``p0``, ``q_state``, ``q_theta``, ``r``, ``n_passes`` for the EKF (defaults: Paper III's 10, 50, 0, 3, 1).
    n_passes : int
        Largest number of passes of ``fit`` over the data (a positive integer); passes stop once the simulation fit
        stops improving by more than ``pass_tol`` percent, and the best pass is kept. Each pass restarts the state,
        R, Lambda and the gain from their initial values and theta from the previous pass.
    pass_tol : float
        Required improvement of the FIT (percent, >= 0) to continue passing.
    """

    def __init__(
        self,
        n_states: int = 2,
        terms: Sequence[str] | Sequence[Sequence[str]] | None = None,
        max_degrees: int | Sequence[int] = 1,
        total_degree: int | None = None,
        derivative_inputs: Sequence[int] = (),
        input_transforms: Mapping[int, Sequence] | None = None,
        sampling_period: float = 1.0,
        alpha: float = 1.0,
        method: str = "midpoint",
        half_step_input: str = "hold",
        stability_margin: float = 0.015,
        theta0: Sequence[float] | None = None,
        R0: float = 100.0,
        Lambda0: float = 0.1,
        forgetting_initial: float = 0.999,
        forgetting_rate: float = 0.999,
        forgetting_final: float = 1.0,
        output_limits: Sequence | None = None,
        state_bound: float = 1e4,
        sensitivity_bound: float = 1e6,
        init: str = "given",
        kalman_options: dict | None = None,
        n_passes: int = 1,
        pass_tol: float = 0.0,
    ) -> None:
        self.n_states = n_states
        self.terms = terms
        self.max_degrees = max_degrees
        self.total_degree = total_degree
        self.derivative_inputs = derivative_inputs
        self.input_transforms = input_transforms
        self.sampling_period = sampling_period
        self.alpha = alpha
        self.method = method
        self.half_step_input = half_step_input
        self.stability_margin = stability_margin
        self.theta0 = theta0
        self.R0 = R0
        self.Lambda0 = Lambda0
        self.forgetting_initial = forgetting_initial
        self.forgetting_rate = forgetting_rate
        self.forgetting_final = forgetting_final
        self.output_limits = output_limits
        self.state_bound = state_bound
        self.sensitivity_bound = sensitivity_bound
        self.init = init
        self.kalman_options = kalman_options
        self.n_passes = n_passes
        self.pass_tol = pass_tol

    # ------------------------------------------------------------------ set-up
    @property
    def ts_model(self) -> float:
        """Scaled sampling period ``alpha * T`` in model time units."""
        return float(self.alpha) * float(self.sampling_period)

    def _validate_params(self) -> None:
        check_positive_int("n_states", self.n_states, what="number of states per output")
        if not (self.state_bound > 0 and self.sensitivity_bound > 0):
            raise ValueError(f"state_bound and sensitivity_bound must be positive, got {self.state_bound} and "
                             f"{self.sensitivity_bound}")
        if not (self.sampling_period > 0 and self.alpha > 0):
            raise ValueError("sampling_period and alpha must be positive")
        if not 0 <= self.stability_margin < 1:
            raise ValueError(f"stability_margin must be in [0, 1), got {self.stability_margin}")
        if not (0 < self.forgetting_initial <= 1 and 0 <= self.forgetting_rate <= 1 and 0 < self.forgetting_final <= 1):
            raise ValueError("forgetting factors must lie in (0, 1]")
        if self.init not in ("given", "kalman"):
            raise ValueError(f"init must be 'given' or 'kalman', got {self.init!r}")
        if self.half_step_input not in ("hold", "interpolate"):
            raise ValueError(f"half_step_input must be 'hold' or 'interpolate', got {self.half_step_input!r}")
        if self.R0 <= 0 or self.Lambda0 <= 0:
            raise ValueError("R0 and Lambda0 must be positive")
        method_code(self.method)

    def _setup(self, n_inputs: int, n_outputs: int) -> None:
        self._validate_params()
        terms = self.terms
        if terms is None:
            terms = polynomial_terms(self.n_states, n_inputs, self.max_degrees, self.total_degree,
                                     self.derivative_inputs)
        self.structure_ = ChainStructure.from_terms(int(self.n_states), n_outputs, n_inputs, terms)
        self.n_inputs_ = n_inputs
        self.n_outputs_ = n_outputs
        self.terms_ = self.structure_.term_names()
        self._factors = self.structure_.factor_arrays()
        lo = np.full(n_outputs, -np.inf)
        hi = np.full(n_outputs, np.inf)
        if self.output_limits is not None:
            lim = np.asarray(self.output_limits, dtype=float)
            if lim.size % 2 or lim.size == 0 or (lim.ndim > 1 and lim.shape[-1] != 2):
                raise ValueError(f"output_limits must be one (lower, upper) pair or one pair per output, got "
                                 f"{self.output_limits!r}")
            lim = lim.reshape(-1, 2)
            if len(lim) == 1:
                lim = np.repeat(lim, n_outputs, axis=0)
            if len(lim) != n_outputs:
                raise ValueError(f"output_limits has {len(lim)} pairs for {n_outputs} outputs")
            bad = np.flatnonzero(np.isnan(lim).any(axis=1) | ~(lim[:, 0] < lim[:, 1]))
            if bad.size:
                raise ValueError(f"output_limits must be (lower, upper) pairs with lower < upper and no NaN, got "
                                 f"{lim[bad[0]].tolist()} for output {int(bad[0])}")
            lo, hi = lim[:, 0].copy(), lim[:, 1].copy()
        self.y_lo_, self.y_hi_ = lo, hi

    def _cfg(self, update: bool) -> np.ndarray:
        cfg = np.zeros(kernel.N_CF)
        cfg[kernel.CF_TS] = self.ts_model
        cfg[kernel.CF_METHOD] = method_code(self.method)
        cfg[kernel.CF_LAM_RATE] = self.forgetting_rate
        cfg[kernel.CF_LAM_INF] = self.forgetting_final
        cfg[kernel.CF_MARGIN] = self.stability_margin
        cfg[kernel.CF_XMAX] = self.state_bound
        cfg[kernel.CF_SMAX] = self.sensitivity_bound
        cfg[kernel.CF_UPDATE] = 1.0 if update else 0.0
        return cfg

    def _initial_theta(self) -> np.ndarray:
        p = self.structure_.n_params
        if self.theta0 is None:
            return np.zeros(p)
        th = np.asarray(self.theta0, dtype=float).ravel()
        if th.shape != (p,) or not np.all(np.isfinite(th)):
            raise ValueError(f"theta0 must be {p} finite values (one per term: {self.terms_}), got {th.shape}")
        return th.copy()

    def _reset_recursion(self, theta: np.ndarray) -> None:
        """Start a pass: x(0) = (y(0), 0, ...) at the next sample, S = 0, R = R0 I, Lambda = Lambda0 I."""
        p, N, d = self.structure_.n_params, self.structure_.n_states, self.structure_.n_outputs
        self.theta_ = np.array(theta, dtype=float)
        self.P_ = np.eye(p) / float(self.R0)
        self.Lambda_ = float(self.Lambda0) * np.eye(d)
        self.x_ = np.zeros(N)
        self.sensitivity_ = np.zeros((N, p))
        self._st = np.zeros(kernel.N_ST)
        self._st[kernel.ST_GAMMA] = 1.0
        self._st[kernel.ST_LAMBDA] = self.forgetting_initial
        self._u_prev: np.ndarray | None = None
        self._du_prev: np.ndarray | None = None
        self.n_samples_seen_ = 0
        self.n_rejected_ = 0

    # ------------------------------------------------------------------ data handling
    def _validate(self, u: Any, y: Any | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        n_u = getattr(self, "n_inputs_", None)
        u2 = as_2d("u", u, n_u)
        y2 = None
        if y is not None:
            y2 = as_2d("y", y, getattr(self, "n_outputs_", None))
            check_same_length(u=u2, y=y2)
        return u2, y2

    def _rows(self, u: np.ndarray, carry: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        ut = apply_input_transforms(u, self.input_transforms or {})
        if carry:
            return self.structure_.input_rows(ut, self.ts_model, self.half_step_input, self._u_prev, self._du_prev)
        return self.structure_.input_rows(ut, self.ts_model, self.half_step_input)

    def _run(self, u: np.ndarray, y: np.ndarray, update: bool = True) -> np.ndarray:
        WS, WH, self._u_prev, self._du_prev = self._rows(u, carry=True)
        fvar, fpow, nf = self._factors
        yhat = np.empty_like(y)
        kernel.rpem_run(WS, WH, np.ascontiguousarray(y), self.theta_, self.P_, self.Lambda_, self.x_,
                        self.sensitivity_, self._st, self._cfg(update), self.y_lo_, self.y_hi_, fvar, fpow, nf,
                        self.structure_.owner, self.structure_.n_chain, yhat)
        self.n_samples_seen_ = int(self._st[kernel.ST_COUNT])
        self.n_rejected_ = int(self._st[kernel.ST_REJECTED])
        self.gain_ = float(self._st[kernel.ST_GAMMA])
        self.forgetting_ = float(self._st[kernel.ST_LAMBDA])
        return yhat

    # ------------------------------------------------------------------ estimation
    def fit(self, u: Any, y: Any) -> RecursivePEM:
        """Estimate theta by (repeated) recursive passes over a dataset.

        Raises ``ValueError`` naming the argument for NaN/inf, mismatched lengths, an output column constant over
        all samples (``"y is constant ..."``: it carries no information about the dynamics; an output constant over
        part of the record is fine), ``n_passes`` < 1 or bad ``output_limits``. :meth:`partial_fit` and
        :meth:`update` process samples online and do not refuse a constant stretch.

        Parameters
        ----------
        u : array_like, shape (n_samples, n_inputs)
            Input sequence (raw units; ``input_transforms`` are applied here).
        y : array_like, shape (n_samples, n_outputs)
            Measured output sequence.

        Returns
        -------
        RecursivePEM
            self, with ``theta_``, ``terms_``, ``pass_fits_`` (simulation FIT after each pass, percent) and the
            state of the recursion after the last pass (``P_``, ``Lambda_``, ``x_``, ``sensitivity_``).
        """
        u2, y2 = self._fresh_validate(u, y)
        n_passes = check_positive_int("n_passes", self.n_passes, what="number of passes over the data")
        if not (np.isfinite(self.pass_tol) and self.pass_tol >= 0):
            raise ValueError(f"pass_tol must be a finite non-negative FIT improvement in percent, got {self.pass_tol}")
        check_not_constant("y", y2, "RPEM model", "output")
        self._setup(u2.shape[1], y2.shape[1])
        theta = self._initial_theta()
        if self.init == "kalman":
            WS, WH, _, _ = self._rows(u2, carry=False)
            theta = ekf_initial_theta(self.structure_, self._cfg(False), WS, WH, y2, theta, self.kalman_options)
        self.theta_init_ = theta.copy()
        self.pass_fits_: list[float] = []
        best_fit, best_theta = -np.inf, theta
        for _ in range(n_passes):
            self._reset_recursion(theta)
            self._run(u2, y2)
            theta = self.theta_.copy()
            if n_passes == 1:
                best_theta = theta
                break
            fit = self._sim_fit(u2, y2, theta)
            self.pass_fits_.append(fit)
            if fit > best_fit + self.pass_tol:
                best_fit, best_theta = fit, theta
            else:
                break
        self.theta_ = best_theta.copy()
        return self

    def _fresh_validate(self, u: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        # fit() starts over, so the sizes of an earlier fit must not constrain the new data.
        u2 = as_2d("u", u)
        y2 = as_2d("y", y)
        check_same_length(u=u2, y=y2)
        return u2, y2

    def _sim_fit(self, u: np.ndarray, y: np.ndarray, theta: np.ndarray) -> float:
        yhat = self._simulate(u, y[0], theta)
        if not np.all(np.isfinite(yhat)):
            return -np.inf
        return float(np.mean(np.atleast_1d(fit_percent(y, yhat))))

    def partial_fit(self, u: Any, y: Any) -> RecursivePEM:
        """Continue the recursion over new samples (online use; the first call starts from ``theta0``)."""
        if not hasattr(self, "theta_"):
            u2, y2 = self._validate(u, y)
            self._setup(u2.shape[1], y2.shape[1])
            self.theta_init_ = self._initial_theta()
            self._reset_recursion(self.theta_init_)
        else:
            u2, y2 = self._validate(u, y)
        self.last_prediction_ = self._run(u2, y2)[-1].copy()
        return self

    def update(self, u_t: Any, y_t: Any) -> np.ndarray:
        """Process one sample; returns the one-step prediction ``yhat(t | theta(t-1))`` made before updating."""
        u_row = np.atleast_1d(np.asarray(u_t, dtype=float))[None, :]
        y_row = np.atleast_1d(np.asarray(y_t, dtype=float))[None, :]
        self.partial_fit(u_row, y_row)
        return self.last_prediction_

    def reset_state(self) -> RecursivePEM:
        """Restart the model state (x from the next output sample) keeping theta, R and Lambda."""
        check_is_fitted(self, "theta_")
        self._st[kernel.ST_STARTED] = 0.0
        self._u_prev = None
        self._du_prev = None
        return self

    # ------------------------------------------------------------------ using the model
    def initial_state(self, u: Any, y: Any) -> np.ndarray:
        """State ``x(0) = (y(0), 0, ...)`` per chain from which :meth:`predict` starts for these data."""
        check_is_fitted(self, "theta_")
        _, y2 = self._validate(u, y)
        x0 = np.zeros(self.structure_.n_states)
        x0[np.arange(self.n_outputs_) * self.structure_.n_chain] = y2[0]
        return x0

    def _simulate(self, u: np.ndarray, y0: np.ndarray, theta: np.ndarray) -> np.ndarray:
        WS, WH, _, _ = self._rows(u, carry=False)
        s = self.structure_
        x0 = np.zeros(s.n_states)
        x0[np.arange(s.n_outputs) * s.n_chain] = y0
        yhat = np.empty((len(u), s.n_outputs))
        X = np.empty((len(u), s.n_states))
        fvar, fpow, nf = self._factors
        kernel.simulate(WS, WH, theta, x0, self._cfg(False), self.y_lo_, self.y_hi_, fvar, fpow, nf, s.owner,
                        s.n_chain, s.n_outputs, yhat, X)
        return yhat

    def predict(self, u: Any, y0: Any | None = None) -> np.ndarray:
        """Simulated (free-run) output, shape ``(n_samples, n_outputs)``, from ``x(0) = (y0, 0, ...)``.

        ``y0`` defaults to zero output. Input derivatives start at zero at the first sample.
        """
        check_is_fitted(self, "theta_")
        u2, _ = self._validate(u)
        if y0 is None:
            y0v = np.zeros(self.n_outputs_)
        else:
            y0v = np.atleast_1d(np.asarray(y0, dtype=float)).ravel()
            if y0v.shape != (self.n_outputs_,) or not np.all(np.isfinite(y0v)):
                raise ValueError(f"y0 must be {self.n_outputs_} finite values, got {y0v}")
        return self._simulate(u2, y0v, self.theta_)

    def predict_k_step(self, u: Any, y: Any, k: int) -> np.ndarray:
        """k-step-ahead prediction ``yhat(t | t - k)``.

        The state at t - k is the estimate of a state-only extended Kalman filter with theta fixed (process and
        measurement noise from ``kalman_options``); the model is then run k steps on the known inputs. The first
        k samples hold the free-run simulation from ``y(0)``. ``k`` must be a positive integer (as for the linear
        and Hammerstein-Wiener models); ``y`` must have as many samples as ``u``.
        """
        check_is_fitted(self, "theta_")
        u2, y2 = self._validate(u, y)
        if int(k) != k or k < 1:
            raise ValueError(f"k must be a positive integer number of steps, got {k}")
        s = self.structure_
        opts = kalman_options(self.kalman_options)
        WS, WH, _, _ = self._rows(u2, carry=False)
        cfg = self._cfg(False)
        Xf = ekf_state_estimates(s, cfg, WS, WH, y2, self.theta_, float(opts["q_state"]), float(opts["r"]))
        yfree = self._simulate(u2, y2[0], self.theta_)
        yhat = np.empty_like(y2)
        fvar, fpow, nf = self._factors
        kernel.k_step_predict(WS, WH, Xf, self.theta_, int(k), cfg, self.y_lo_, self.y_hi_, fvar, fpow, nf,
                              s.owner, s.n_chain, s.n_outputs, yfree, yhat)
        return yhat

    def score(self, u: Any, y: Any) -> float:
        """Simulation FIT in percent (mean over outputs), simulated from ``y(0)``."""
        check_is_fitted(self, "theta_")
        u2, y2 = self._validate(u, y)
        return self._sim_fit(u2, y2, self.theta_)

    def to_casadi(self) -> Any:
        """``casadi.Function('step', [x, u], [x_next, y])`` of the discretised model; see
        :func:`ident.rpem.export.to_casadi` for how input derivatives enter."""
        check_is_fitted(self, "theta_")
        from ident.rpem.export import to_casadi

        return to_casadi(self)

    # ------------------------------------------------------------------ persistence (ident.io, JSON + NPZ)
    def _get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        check_is_fitted(self, "theta_")
        params = self.get_params()
        # Terms are saved as one list per output with global state numbering, which reloads to the same structure.
        names = np.array(self.terms_, dtype=object)
        params["terms"] = [[str(t) for t in names[self.structure_.owner == k]] for k in range(self.n_outputs_)]
        params["theta0"] = None if self.theta0 is None else [float(v) for v in np.ravel(self.theta0)]
        params["input_transforms"] = ({str(k): [str(v[0]), float(v[1])] for k, v in self.input_transforms.items()}
                                      if self.input_transforms else None)
        params["derivative_inputs"] = [int(v) for v in self.derivative_inputs]
        if self.output_limits is not None:
            params["output_limits"] = np.asarray(self.output_limits, dtype=float).tolist()
        meta = {"params": params, "n_inputs": self.n_inputs_, "n_outputs": self.n_outputs_}
        arrays = {"theta": self.theta_, "P": self.P_, "Lambda": self.Lambda_, "x": self.x_,
                  "sensitivity": self.sensitivity_, "st": self._st, "theta_init": self.theta_init_}
        return meta, arrays

    @classmethod
    def _from_state(cls, meta: dict, arrays: dict[str, np.ndarray]) -> RecursivePEM:
        params = dict(meta["params"])
        if params.get("input_transforms"):
            params["input_transforms"] = {int(k): tuple(v) for k, v in params["input_transforms"].items()}
        est = cls(**params)
        est._setup(int(meta["n_inputs"]), int(meta["n_outputs"]))
        est._reset_recursion(arrays["theta"])
        est.P_ = arrays["P"].copy()
        est.Lambda_ = arrays["Lambda"].copy()
        est.x_ = arrays["x"].copy()
        est.sensitivity_ = arrays["sensitivity"].copy()
        est._st = arrays["st"].astype(float).copy()
        est.theta_init_ = arrays["theta_init"].copy()
        # The carried-over input is not saved: the next partial_fit restarts x from its first output sample.
        est._st[kernel.ST_STARTED] = 0.0
        est.n_samples_seen_ = int(est._st[kernel.ST_COUNT])
        est.n_rejected_ = int(est._st[kernel.ST_REJECTED])
        return est
