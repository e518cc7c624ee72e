"""The :class:`RecursivePEM` estimator: recursive prediction error identification of a restricted black-box
nonlinear ODE model with a static output nonlinearity (Wigren 2006; thesis Papers I-III, ALGORITHMS.md section 1)."""
from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ident.base import BaseEstimator, as_2d, check_is_fitted, check_not_constant, check_positive_int, check_same_length
from ident.io import register_model
from ident.metrics import fit_percent
from ident.rpem import kernel
from ident.rpem.kalman_init import DEFAULT_KALMAN_OPTIONS, ekf_initial_theta, ekf_state_estimates, kalman_options
from ident.rpem.regressors import polynomial_terms
from ident.rpem.start import equation_error_thetas, time_scale, unfold_candidates, unfold_sign
from ident.rpem.structure import INPUT_TRANSFORMS, ChainStructure, apply_input_transforms, method_code

#: Static output functions ``y = h(x1, eta)``: name -> kernel code.
OUTPUT_FUNCTIONS = {"identity": kernel.OUT_IDENTITY, "polynomial": kernel.OUT_POLYNOMIAL, "abs": kernel.OUT_ABS,
                    "saturation": kernel.OUT_SATURATION}
#: The automatic choices for fitting a record of your own, ``RecursivePEM(n_states=..., sampling_period=T,
#: **AUTO_SETTINGS)``: standardised signals, the time scale and the sub-steps from an ARX model, data-driven starts,
#: the half-step input, the pass mode and the initial Hessian scale R0 chosen on the inner hold-out, up to 30 passes
#: keeping the best.
AUTO_SETTINGS: dict[str, Any] = {"normalize": True, "alpha": "auto", "n_substeps": "auto", "init": "auto",
                                 "half_step_input": "auto", "pass_mode": "auto", "n_passes": 30, "keep": "best",
                                 "refit": True, "R0": "auto"}
#: The thesis' initial Hessian scale R(0) = R0 I (Papers I-III); ``R0="auto"`` uses it before a fit resolves it
#: (``partial_fit`` from scratch).
R0_DEFAULT = 100.0
#: ``R0="auto"``: the candidates tried on the inner hold-out, the middle one first. R0 weighs the start against the
#: data (R(t) = R0 I + the information of the samples seen). The thesis' 100 suits its unscaled signals and starts
#: from zero or from an EKF; with standardised signals (parameters of order one) and a data-driven start it lets the
#: first samples of a pass, while the model state and its sensitivities are still in their start-up transient, throw
#: a good start away (measured on the simulated cascaded tanks and on 2048 samples of the simulated Duffing
#: oscillator: the passes then fell below their start; README "The weight of the start"). The grid spans the two
#: decades above it.
R0_GRID = (1e3, 1e4, 1e5)
#: Largest number of integration sub-steps per sample.
MAX_SUBSTEPS = 50
#: ``n_substeps="auto"``: the fastest estimated mode turns by at most this angle (rad) per sub-step.
SUBSTEP_ANGLE_RAD = 0.25
#: ``pass_mode="continue"`` with the automatic choices stops once the hold-out FIT has changed by less than
#: PLATEAU_FIT points over the last PLATEAU_PASSES passes (converged).
PLATEAU_PASSES = 5
PLATEAU_FIT = 0.05
#: Fraction of rejected updates (and of samples on the state bound) above which ``fit`` warns.
WARN_REJECTED_FRACTION = 0.5
WARN_BOUND_FRACTION = 0.01
_MAX_DIM = 10_000  # bound on states, inputs, outputs and terms read from a file (a damaged count must not allocate)


def _real(name: str, value: Any, low: float = -math.inf, high: float = math.inf, low_open: bool = False,
          high_open: bool = False, allow_inf: bool = False) -> float:
    """``value`` as a float in the given range, or ``ValueError`` naming ``name`` (NaN, inf, strings, bools)."""
    ok = False
    v = math.nan
    if not isinstance(value, (bool, np.bool_)) and not isinstance(value, str):
        try:
            v = float(value)
            ok = (math.isfinite(v) or (allow_inf and not math.isnan(v)))
        except (TypeError, ValueError, OverflowError):
            ok = False
    if ok:
        ok = (v > low if low_open else v >= low) and (v < high if high_open else v <= high)
    if not ok:
        lb = "(" if low_open else "["
        hb = ")" if high_open else "]"
        raise ValueError(f"{name} must be a finite number in {lb}{low:g}, {high:g}{hb}, got {value!r}")
    return v


@register_model("rpem")
class RecursivePEM(BaseEstimator):
    """Recursive prediction error method on an n-state chain model with a polynomial right-hand side.

    Model (continuous time, per output k; a MIMO model is one chain per output)::

        dx_i/dt = x_{i+1}   (i < n),     dx_n/dt = phi(x, u, u')^T theta_k,     y_k = sat(h(x_1, eta_k))

    discretised with Euler or the midpoint rule on the scaled sampling period ``Ts = alpha * T`` (optionally in
    ``n_substeps`` steps per sample). ``h`` is the static output function (the thesis' RPEM with a static output
    nonlinearity): the identity, a polynomial, an absolute value or a saturation, its parameters eta estimated
    jointly with theta by the same recursion; ``sat`` is the fixed ``output_limits``. The parameters follow the
    Gauss-Newton recursion of ALGORITHMS.md section 1 with the gain from a forgetting factor
    ``lambda(t) = rate * lambda(t-1) + (1 - rate) * final`` (``final = 1``: the gain decays like 1/t;
    ``final < 1``: a tracking estimator for a drifting plant). Each candidate update is projected onto the
    model set DM: it is refused (theta keeps its previous value) unless, at the current state and input, the
    continuous-time linearisation ``dF/dx`` has every eigenvalue with real part below ``-stability_margin`` and the
    discretised step's Jacobian has spectral radius below 1. Where the current estimate is itself outside DM at that
    point, that rule would refuse every step and freeze the estimate there (theta = 0, the start when no
    ``theta0`` is given, is a chain of integrators, outside DM everywhere; a nonlinear model may be outside DM at some
    operating points only); there a candidate is accepted if it is no further outside DM than the current
    estimate (neither ``max Re eig(dF/dx) + delta`` nor the step's spectral radius above 1 grows), so the
    estimate moves towards DM. Inside DM the rule is the thesis' one. ``theta = 0`` itself sits on the stability
    edge, where almost every small step makes the continuous-time or the discretised model less stable: from it the
    estimate stays nearly frozen and ``fit`` warns (start from data, ``init="auto"``, or from a stable ``theta0``).
    The state and the sensitivities are clipped to
    ``state_bound`` and ``sensitivity_bound``, so the recursion cannot diverge numerically.

    Units of the stability margin: the model runs on scaled time (``alpha`` model time units per second), so the
    margin ``delta`` in model time is ``delta * alpha`` in 1/s of physical time (:attr:`stability_margin_per_s_`).
    Paper II's ``delta = 0.015`` with ``alpha = 1.5`` is 0.0225 1/s; 0.025 with ``alpha = 2500`` (the
    Wiener-Hammerstein benchmark) is 62.5 1/s.

    Fitting your own data: ``RecursivePEM(n_states=2, total_degree=3, sampling_period=T, **AUTO_SETTINGS)``
    (:data:`AUTO_SETTINGS`: ``normalize=True, alpha="auto", n_substeps="auto", init="auto",
    half_step_input="auto", pass_mode="auto", R0="auto", n_passes=30, keep="best", refit=True``) standardises the
    signals, takes the time scale and the sub-steps from a linear fit, starts from data-driven estimates and keeps the
    best choices and pass on an inner hold-out. The defaults of the class are the thesis' settings (``alpha=1``,
    one step per sample, ``theta0`` as given, the held input, passes that restart, ``R0=100``), which the
    reproductions of Papers II and III use.

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
    alpha : float or "auto"
        Sampling-period scaling factor (Paper I); the model runs on ``Ts = alpha * T``, so theta describes the
        system on a time axis stretched by alpha. ``"auto"``: the characteristic frequency (rad/s) of an ARX model
        of order n fitted to the estimation data, so that one model time unit is the system's own time scale and
        theta is of order one (resolved value in ``alpha_``).
    method : {"midpoint", "euler"}
        Discretisation.
    half_step_input : {"hold", "interpolate", "auto"}
        Input at the midpoint half step (and between sub-steps). ``"hold"`` (default) keeps the sample's value:
        right for zero-order-hold inputs (commanded steps, PRBS, dosing commands, anything a DAC holds between
        samples). ``"interpolate"`` takes the linear interpolation between samples: right for samples of a smooth,
        band-limited signal (a multisine measured by an anti-aliased acquisition). The wrong choice costs accuracy
        (on a Duffing oscillator under a multisine, hold gives several times the error). ``"auto"`` fits both and
        keeps the one with the smaller error on the inner hold-out (resolved value in ``half_step_input_``).
    stability_margin : float
        delta of the model set DM, in model time (see above; ``stability_margin_per_s_`` in 1/s).
    theta0 : array_like, optional
        Initial parameters (zeros if omitted).
    R0, Lambda0 : float
        Initial Hessian scale ``R(0) = R0 I`` and noise covariance ``Lambda(0) = Lambda0 I`` (positive, finite).
        R0 is the weight of the start against the data: a small R0 lets the first samples of a pass move theta far
        from its start, a large one keeps the estimate near the start for longer (in ``"restart"`` passes, a ridge
        towards it). ``R0="auto"``: chosen on the inner hold-out among :data:`R0_GRID` (1e3, 1e4, 1e5), first the
        middle value with every half-step input and pass mode, then the others with the chosen half-step input and
        every pass mode (resolved value in ``R0_``).
    forgetting_initial, forgetting_rate, forgetting_final : float
        lambda(0), the rate and the limit of the forgetting factor (in (0, 1], rate in [0, 1]).
    output_limits : (float, float) or sequence of them, optional
        Output saturation (lower, upper) per output, lower < upper (either may be infinite), in the output's units;
        the gradient is zero where it is active.
    state_bound, sensitivity_bound : float
        Saturations of the state and of dx/dtheta (in the model's units: normalised if ``normalize``).
    init : {"given", "kalman", "auto"}
        Start from ``theta0``; from the augmented-state EKF of Brus and Wigren started at ``theta0``; or
        (``"auto"``) from the best of several data-driven starts: equation-error least squares on
        state-variable-filtered derivatives at three filter bandwidths, with all terms or the linear ones only,
        and ``theta0`` if given, each scored by its simulation fit on the estimation part.
    kalman_options : dict, optional
        ``p0``, ``q_state``, ``q_theta``, ``r``, ``n_passes`` for the EKF (defaults: Paper III's 10, 50, 0, 3, 1).
    n_passes : int
        Largest number of passes of ``fit`` over the data (a positive integer); passes stop once the fit (see
        ``keep``) stops improving by more than ``pass_tol`` percent (for three passes in a row with the automatic
        choices; ``pass_mode="continue"`` runs them all). Each pass restarts the state and (see ``pass_mode``) R,
        Lambda and the gain.
    pass_tol : float
        Required improvement of the FIT (percent, >= 0) to continue passing.
    output : {"identity", "polynomial", "abs", "saturation"}
        Static output function h of x1 (parameters eta per output, estimated with theta; ``output_params_``):
        ``"identity"``: y = x1; ``"polynomial"``: y = eta_0 + x1 + eta_2 x1^2 + ... + eta_q x1^q with q =
        ``output_degree`` (the linear coefficient is 1 because the chain fixes no scale of x); ``"abs"``: y = eta_0
        + |x1|, for a sensor that ignores the sign (a speed from a pulse counter); ``"saturation"``: y = min(max(x1,
        eta_0), eta_1) with estimated limits. With ``init="auto"`` the starts are data driven: eta_0 from the
        output's floor and a sign-unfolded output for ``"abs"``, the data range for ``"saturation"``.
    output_degree : int
        Degree q >= 2 of the polynomial output function.
    normalize : bool
        Standardise the (transformed) inputs and the outputs with the estimation data's mean and SD before
        identification; theta, eta and the states then refer to the standardised signals, while ``predict``,
        ``to_casadi`` and saved models take and give physical units.
    n_substeps : int or "auto"
        Integration sub-steps per sample (1: the thesis' single step). ``"auto"``: enough sub-steps that the
        fastest mode of the ARX model turns by at most 0.25 rad per sub-step (resolved value in ``n_substeps_``):
        one step per sample is accurate only well below the Nyquist frequency.
    keep : {"best", "last"}
        Which pass (and, with the automatic choices, which start and half-step input) to keep: the best simulation
        fit on the inner hold-out (``"best"``) or the last pass.
    holdout : float, optional
        Fraction of the record, at its end, held out to score passes and automatic choices (in [0, 0.5)); the
        recursion runs on the rest. 0: score on the estimation data itself (the thesis' passes "until the fit stops
        improving"). ``None`` (default): 0.2 when an automatic choice is asked for (``init``, ``half_step_input``
        or ``pass_mode`` "auto", or ``n_restarts`` > 0), else 0. Records shorter than 100 samples are never split.
    pass_mode : {"restart", "continue", "auto"}
        ``"restart"`` (the thesis): every pass restarts R, Lambda and the gain from their initial values, keeping
        only theta. ``"continue"``: a pass restarts the state only and the recursion goes on, the gain still
        decreasing like one over all samples seen, so that repeated passes converge to the minimum of the
        simulation error as an off-line prediction error method would: better for short records (a few thousand
        samples or less). ``"auto"``: both, keeping the better on the inner hold-out (resolved value in
        ``pass_mode_``).
    n_restarts : int
        Extra starts drawn at random around the best start (theta and eta perturbed by 30 % of their size plus
        0.1), each run through the passes and scored on the hold-out: a way out of a local minimum.
    random_state : int
        Seed of the restarts.
    refit : bool
        After the choices on the inner hold-out (start, half-step input, pass mode, number of passes), run the
        chosen recipe once more over the *whole* record, hold-out included, and return that model (``refit_`` says
        whether it was kept: it is, unless its simulation fit over the whole record is worse than the chosen
        model's, a sign that the recursion went astray). The hold-out then served only to choose; on short records
        the extra 20 % of data matter (on the simulated cascaded tanks, 1024 samples, about +2 FIT points).
        ``holdout_fit_`` stays the chosen model's hold-out score, an honest out-of-sample figure. Default False
        (the thesis); True in :data:`AUTO_SETTINGS`.
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
        alpha: float | str = 1.0,
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
        output: str = "identity",
        output_degree: int = 3,
        normalize: bool = False,
        n_substeps: int | str = 1,
        keep: str = "best",
        holdout: float | None = None,
        n_restarts: int = 0,
        pass_mode: str = "restart",
        random_state: int = 0,
        refit: bool = False,
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
        self.output = output
        self.output_degree = output_degree
        self.normalize = normalize
        self.n_substeps = n_substeps
        self.keep = keep
        self.holdout = holdout
        self.n_restarts = n_restarts
        self.pass_mode = pass_mode
        self.random_state = random_state
        self.refit = refit

    # ------------------------------------------------------------------ settings
    @property
    def ts_model(self) -> float:
        """Scaled sampling period ``alpha * T`` in model time units (with the resolved ``alpha_`` once fitted)."""
        return float(getattr(self, "alpha_", self.alpha if not isinstance(self.alpha, str) else 1.0)) * \
            float(self.sampling_period)

    @property
    def stability_margin_per_s_(self) -> float:
        """The stability margin in physical units, 1/s: ``stability_margin * alpha``."""
        check_is_fitted(self, "theta_")
        return float(self.stability_margin) * float(self.alpha_)

    def _validate_params(self) -> None:
        """Every constructor argument checked (ValueError naming it): finite numbers in range, known options."""
        check_positive_int("n_states", self.n_states, what="number of states per output")
        if int(self.n_states) > 50:
            raise ValueError(f"n_states must be at most 50, got {self.n_states}")
        _real("sampling_period", self.sampling_period, 0.0, low_open=True)
        if not (isinstance(self.alpha, str) and self.alpha == "auto"):
            if isinstance(self.alpha, str):
                raise ValueError(f"alpha must be a positive number or 'auto', got {self.alpha!r}")
            _real("alpha", self.alpha, 0.0, low_open=True)
        _real("stability_margin", self.stability_margin, 0.0, 1.0, high_open=True)
        if not (isinstance(self.R0, str) and self.R0 == "auto"):
            if isinstance(self.R0, str):
                raise ValueError(f"R0 must be a positive number or 'auto', got {self.R0!r}")
            _real("R0", self.R0, 0.0, low_open=True)
        _real("Lambda0", self.Lambda0, 0.0, low_open=True)
        _real("forgetting_initial", self.forgetting_initial, 0.0, 1.0, low_open=True)
        _real("forgetting_rate", self.forgetting_rate, 0.0, 1.0)
        _real("forgetting_final", self.forgetting_final, 0.0, 1.0, low_open=True)
        _real("state_bound", self.state_bound, 0.0, low_open=True)
        _real("sensitivity_bound", self.sensitivity_bound, 0.0, low_open=True)
        _real("pass_tol", self.pass_tol, 0.0)
        if self.holdout is not None:
            _real("holdout", self.holdout, 0.0, 0.5, high_open=True)
        check_positive_int("n_restarts", self.n_restarts, minimum=0, what="number of random restarts")
        check_positive_int("output_degree", self.output_degree, minimum=2, what="(degree of the output polynomial)")
        if int(self.output_degree) > 9:
            raise ValueError(f"output_degree must be at most 9, got {self.output_degree}")
        if not (isinstance(self.n_substeps, str) and self.n_substeps == "auto"):
            if isinstance(self.n_substeps, str):
                raise ValueError(f"n_substeps must be a positive integer or 'auto', got {self.n_substeps!r}")
            check_positive_int("n_substeps", self.n_substeps, what="(integration sub-steps per sample)")
            if int(self.n_substeps) > MAX_SUBSTEPS:
                raise ValueError(f"n_substeps must be at most {MAX_SUBSTEPS}, got {self.n_substeps}")
        for name, value, options in (("init", self.init, ("given", "kalman", "auto")),
                                     ("half_step_input", self.half_step_input, ("hold", "interpolate", "auto")),
                                     ("output", self.output, tuple(OUTPUT_FUNCTIONS)),
                                     ("keep", self.keep, ("best", "last")),
                                     ("pass_mode", self.pass_mode, ("restart", "continue", "auto")),
                                     ("method", self.method, ("midpoint", "euler"))):
            if not isinstance(value, str) or value not in options:
                raise ValueError(f"{name} must be one of {list(options)}, got {value!r}")
        for name in ("normalize", "refit"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")  # noqa: TRY004
        if isinstance(self.random_state, bool) or not isinstance(self.random_state, (int, np.integer)):
            raise ValueError(f"random_state must be an integer seed, got {self.random_state!r}")  # noqa: TRY004
        for j, spec in (self.input_transforms or {}).items():
            if isinstance(j, bool) or int(j) != j or int(j) < 1:
                raise ValueError(f"input_transforms keys must be 1-based input numbers, got {j!r}")
            if not isinstance(spec, (list, tuple)) or len(spec) != 2 or spec[0] not in INPUT_TRANSFORMS:
                raise ValueError(f"input_transforms[{j}] must be (name, parameter) with a name in "
                                 f"{sorted(INPUT_TRANSFORMS)}, got {spec!r}")
            _real(f"input_transforms[{j}] parameter", spec[1])
        kalman_options(self.kalman_options)
        for key, val in (self.kalman_options or {}).items():
            if key == "n_passes":
                check_positive_int("kalman_options['n_passes']", val)
            else:
                _real(f"kalman_options[{key!r}]", val, 0.0, low_open=key in ("r",))
        method_code(self.method)

    def _q(self) -> int:
        """Output-function parameters per output."""
        return {"identity": 0, "polynomial": int(self.output_degree), "abs": 1, "saturation": 2}[self.output]

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
            try:
                lim = np.asarray(self.output_limits, dtype=float)
            except (TypeError, ValueError):
                raise ValueError(f"output_limits must be (lower, upper) pairs of numbers, got "
                                 f"{self.output_limits!r}") from None
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
        self._limits_phys = (lo, hi)
        self._set_scaling(np.zeros(n_inputs), np.ones(n_inputs), np.zeros(n_outputs), np.ones(n_outputs))
        if not hasattr(self, "alpha_"):
            self.alpha_ = 1.0 if isinstance(self.alpha, str) else float(self.alpha)
        if not hasattr(self, "n_substeps_"):
            self.n_substeps_ = 1 if isinstance(self.n_substeps, str) else int(self.n_substeps)
        if not hasattr(self, "half_step_input_"):
            self.half_step_input_ = "hold" if self.half_step_input == "auto" else self.half_step_input

    def _set_scaling(self, u_mean: np.ndarray, u_scale: np.ndarray, y_mean: np.ndarray, y_scale: np.ndarray) -> None:
        self.input_mean_, self.input_scale_ = np.asarray(u_mean, float), np.asarray(u_scale, float)
        self.output_mean_, self.output_scale_ = np.asarray(y_mean, float), np.asarray(y_scale, float)
        lo, hi = self._limits_phys
        with np.errstate(invalid="ignore"):
            self.y_lo_ = (lo - self.output_mean_) / self.output_scale_
            self.y_hi_ = (hi - self.output_mean_) / self.output_scale_

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
        cfg[kernel.CF_SUBSTEPS] = self.n_substeps_
        cfg[kernel.CF_OUT_TYPE] = OUTPUT_FUNCTIONS[self.output]
        cfg[kernel.CF_OUT_Q] = self._q()
        return cfg

    def _initial_theta(self) -> np.ndarray:
        p = self.structure_.n_params
        if self.theta0 is None:
            return np.zeros(p)
        try:
            th = np.asarray(self.theta0, dtype=float).ravel()
        except (TypeError, ValueError):
            raise ValueError(f"theta0 must be {p} finite numbers (one per term: {self.terms_})") from None
        if th.shape != (p,) or not np.all(np.isfinite(th)):
            raise ValueError(f"theta0 must be {p} finite values (one per term: {self.terms_}), got shape {th.shape}"
                             + ("" if th.shape != (p,) else " with NaN or inf"))
        return th.copy()

    def _default_eta(self) -> np.ndarray:
        d, q = self.n_outputs_, self._q()
        eta = np.zeros((d, q))
        if self.output == "saturation":
            eta[:, 0], eta[:, 1] = -1e3, 1e3
        return eta

    def _r0(self) -> float:
        """The initial Hessian scale in use: the resolved ``R0_`` (``R0="auto"``) or ``R0``."""
        r0 = getattr(self, "R0_", None)
        if r0 is None:
            r0 = R0_DEFAULT if isinstance(self.R0, str) else float(self.R0)
        return float(r0)

    def _reset_recursion(self, theta: np.ndarray, eta: np.ndarray | None = None) -> None:
        """Start a pass: x(0) = (y(0), 0, ...) at the next sample, S = 0, R = R0 I, Lambda = Lambda0 I."""
        p, N, d = self.structure_.n_params, self.structure_.n_states, self.structure_.n_outputs
        self.theta_ = np.array(theta, dtype=float)
        self.output_params_ = self._default_eta() if eta is None else np.array(eta, dtype=float).reshape(d, -1)
        ptot = p + self.output_params_.size
        self.P_ = np.eye(ptot) / self._r0()
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
        self.n_bound_hits_ = 0
        self.gain_ = 1.0
        self.forgetting_ = float(self.forgetting_initial)

    # ------------------------------------------------------------------ data handling
    def _validate(self, u: Any, y: Any | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        n_u = getattr(self, "n_inputs_", None)
        u2 = as_2d("u", u, n_u)
        y2 = None
        if y is not None:
            y2 = as_2d("y", y, getattr(self, "n_outputs_", None))
            check_same_length(u=u2, y=y2)
        return u2, y2

    def _u_model(self, u: np.ndarray) -> np.ndarray:
        """Inputs as the model sees them: transformed, then scaled."""
        ut = apply_input_transforms(u, self.input_transforms or {})
        if self.normalize:
            ut = (ut - self.input_mean_) / self.input_scale_
        return ut

    def _y_model(self, y: np.ndarray) -> np.ndarray:
        return (y - self.output_mean_) / self.output_scale_ if self.normalize else y

    def _y_phys(self, y: np.ndarray) -> np.ndarray:
        return y * self.output_scale_ + self.output_mean_ if self.normalize else y

    def _rows(self, um: np.ndarray, carry: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Input rows of already transformed/scaled inputs ``um``."""
        if carry:
            return self.structure_.input_rows(um, self.ts_model, self.half_step_input_, self._u_prev, self._du_prev)
        return self.structure_.input_rows(um, self.ts_model, self.half_step_input_)

    def _params_vector(self) -> np.ndarray:
        return np.concatenate([self.theta_, self.output_params_.ravel()])

    def _run(self, um: np.ndarray, ym: np.ndarray, update: bool = True) -> np.ndarray:
        WS, WH, self._u_prev, self._du_prev = self._rows(um, carry=True)
        fvar, fpow, nf = self._factors
        yhat = np.empty_like(ym)
        params = self._params_vector()
        kernel.rpem_run(WS, WH, np.ascontiguousarray(ym), params, self.P_, self.Lambda_, self.x_,
                        self.sensitivity_, self._st, self._cfg(update), self.y_lo_, self.y_hi_, fvar, fpow, nf,
                        self.structure_.owner, self.structure_.n_chain, yhat)
        p = self.structure_.n_params
        self.theta_ = params[:p].copy()
        self.output_params_ = params[p:].reshape(self.n_outputs_, -1).copy()
        self.n_samples_seen_ = int(self._st[kernel.ST_COUNT])
        self.n_rejected_ = int(self._st[kernel.ST_REJECTED])
        self.n_bound_hits_ = int(self._st[kernel.ST_BOUND_HITS])
        self.gain_ = float(self._st[kernel.ST_GAMMA])
        self.forgetting_ = float(self._st[kernel.ST_LAMBDA])
        return yhat

    # ------------------------------------------------------------------ estimation
    def fit(self, u: Any, y: Any) -> RecursivePEM:
        """Estimate theta (and the output function's eta) by recursive passes over a dataset.

        Raises ``ValueError`` naming the argument for NaN/inf, mismatched lengths, an output column constant over
        all samples (``"y is constant ..."``: it carries no information about the dynamics; an output constant over
        part of the record is fine), any constructor argument out of range or non-finite (``R0=nan``,
        ``alpha=inf``, ``n_passes`` < 1, bad ``output_limits``, ...) and inputs whose scale overflows.
        :meth:`partial_fit` and :meth:`update` process samples online and do not refuse a constant stretch.

        After ``fit``: ``theta_``, ``output_params_``, ``terms_``; ``pass_fits_`` (simulation FIT of each pass of
        the kept run, percent, on the hold-out or the estimation data), ``n_rejected_`` / ``n_updates_`` (updates
        refused by the projection onto DM in the kept pass, and all updates) and ``n_bound_hits_`` (samples at
        which the recursion's simulated state hit ``state_bound``); the resolved automatic choices ``alpha_``,
        ``half_step_input_``, ``n_substeps_``, ``pass_mode_``, ``R0_`` with ``choice_scores_`` (the hold-out FIT of
        each half-step/pass-mode pair tried, keyed ``"hold/restart"``; with ``R0="auto"`` those pairs use the middle
        R0 of the grid and the other R0 values add keys such as ``"interpolate/continue/R0=1000"``),
        ``holdout_fit_`` (None without a hold-out) and ``time_scale_rad_s_`` (the ARX characteristic frequency, when
        it was needed); and the recursion's state after the kept pass (``P_``,
        ``Lambda_``, ``x_``, ``sensitivity_``). A ``RuntimeWarning`` says when most updates were rejected or the
        fitted model's simulation of the estimation data sits on its state bound (a diverged model).
        """
        u2, y2 = self._fresh_validate(u, y)
        n_passes = check_positive_int("n_passes", self.n_passes, what="number of passes over the data")
        self._validate_params()
        check_not_constant("y", y2, "RPEM model", "output")
        for attr in ("alpha_", "n_substeps_", "half_step_input_", "R0_"):
            self.__dict__.pop(attr, None)
        self._setup(u2.shape[1], y2.shape[1])
        ut = apply_input_transforms(u2, self.input_transforms or {})
        peak = np.max(np.abs(ut), axis=0)
        bad = np.flatnonzero(peak > 1e150)  # squares (variance, regressors) of such values overflow
        if bad.size:
            raise ValueError(f"u has a non-finite variance in column(s) {bad.tolist()} (values up to "
                             f"{peak[bad].max():.3g} overflow, after input_transforms): rescale it before "
                             "identifying the RPEM model")
        if self.normalize:
            sd_u = ut.std(axis=0)
            self._set_scaling(ut.mean(axis=0), np.where(sd_u > 0, sd_u, 1.0), y2.mean(axis=0), y2.std(axis=0))
            ut = (ut - self.input_mean_) / self.input_scale_
        um, ym = ut, self._y_model(y2)
        if not (np.all(np.isfinite(um)) and np.all(np.isfinite(ym))):
            raise ValueError("u or y overflows after scaling: rescale the signals")
        self._resolve_time_scale(um, ym)
        N = len(ym)
        autos = (self.init == "auto" or self.half_step_input == "auto" or self.pass_mode == "auto"
                 or int(self.n_restarts) > 0)
        self._autos = autos
        frac = (0.2 if autos else 0.0) if self.holdout is None else float(self.holdout)
        n_hold = round(frac * N) if N >= 100 else 0
        tuned = self.keep == "best" and (n_passes > 1 or autos)
        split = N - n_hold if (tuned and n_hold > 0) else N
        self._start_cache: dict[str, list] = {}
        modes = ["hold", "interpolate"] if self.half_step_input == "auto" else [self.half_step_input_]
        pass_modes = ["restart", "continue"] if self.pass_mode == "auto" else [self.pass_mode]
        auto_r0 = isinstance(self.R0, str)
        best: dict[str, Any] | None = None
        self.choice_scores_: dict[str, float] = {}

        def attempt(mode: str, pmode: str, r0: float) -> None:
            nonlocal best
            self.half_step_input_, self.pass_mode_, self.R0_ = mode, pmode, r0
            result = self._fit_mode(um, ym, split, n_passes, tuned)
            result["R0"] = r0
            self.choice_scores_[f"{mode}/{pmode}" + (f"/R0={r0:g}" if r0 != r0_first else "")] = result["score"]
            if best is None or result["score"] > best["score"]:
                best = result

        r0_first = R0_GRID[len(R0_GRID) // 2] if auto_r0 else float(self.R0)
        for mode in modes:
            for pmode in pass_modes:
                attempt(mode, pmode, r0_first)
        if auto_r0:  # the other R0 values with the chosen half-step input (the input between samples, not R0's)
            assert best is not None
            for r0 in R0_GRID:
                if r0 != r0_first:
                    for pmode in pass_modes:
                        attempt(best["mode"], pmode, r0)
        assert best is not None
        self.half_step_input_ = best["mode"]
        self.pass_mode_ = best["pass_mode"]
        self.R0_ = best["R0"]
        for k, v in best["state"].items():
            setattr(self, k, v)
        self.pass_fits_ = best["pass_fits"]
        self._kept_sim_hits = float(best.get("sim_hits", 0.0))
        del self._start_cache
        self.theta_init_ = best["start"][0]
        self.holdout_fit_ = best["score"] if split < N else None
        self.refit_ = bool(self.refit and split < N and tuned) and self._refit_whole(um, ym, best)
        self._warn_if_diverged(um, ym)
        return self

    def _refit_whole(self, um: np.ndarray, ym: np.ndarray, best: dict[str, Any]) -> bool:
        """Run the chosen recipe (start, pass mode, number of passes of ``best``) over the whole record; keep the
        result unless its simulation fit over the whole record is below the chosen model's. Returns whether the
        refitted model was kept (the estimator holds it then; else it holds ``best`` unchanged)."""
        N = len(ym)
        kept = {k: getattr(self, k) for k in best["state"]}
        kept_hits = self._kept_sim_hits
        score_kept = self._score(um, ym, N, self.theta_, self.output_params_)
        if best.get("start_index", 0) == 0 and self.init == "auto":
            theta, eta = self._starts(um, ym)[0]  # the data-driven start, now from the whole record
        else:
            theta, eta = best["start"]
        theta, eta = theta.copy(), eta.copy()
        n_kept = int(best.get("kept_passes", 0))
        self._reset_recursion(theta, eta)
        for k in range(n_kept):
            if k > 0 and self.pass_mode_ == "restart":
                self._reset_recursion(theta, eta)
            elif k > 0:  # continue: restart the model state only
                self._st[kernel.ST_STARTED] = 0.0
                self._u_prev = self._du_prev = None
            self._run(um, ym)
            theta, eta = self.theta_.copy(), self.output_params_.copy()
        self.n_updates_ = self.n_samples_seen_
        score_refit = self._score(um, ym, N, theta, eta)
        if np.isfinite(score_refit) and score_refit >= score_kept:
            self._kept_sim_hits = float(self._last_sim_hits)
            return True
        for k, v in kept.items():
            setattr(self, k, v)
        self._kept_sim_hits = kept_hits
        return False

    def _resolve_time_scale(self, um: np.ndarray, ym: np.ndarray) -> None:
        """``alpha_`` and ``n_substeps_`` from the ARX time scale when they are "auto"."""
        need = self.alpha == "auto" or self.n_substeps == "auto" or self.init == "auto"
        self.time_scale_rad_s_ = None
        if not need:
            return
        n = int(self.n_states)
        scales = [time_scale(um, self._chain_output(ym)[:, k], n, float(self.sampling_period))
                  for k in range(self.n_outputs_)]
        wc = float(np.exp(np.mean([np.log(s[0]) for s in scales])))
        wmax = float(max(s[1] for s in scales))
        self.time_scale_rad_s_ = wc
        if self.alpha == "auto":
            self.alpha_ = wc
        if self.n_substeps == "auto":
            self.n_substeps_ = int(min(MAX_SUBSTEPS, max(1, math.ceil(wmax * float(self.sampling_period)
                                                                       / SUBSTEP_ANGLE_RAD))))

    def _chain_output(self, ym: np.ndarray, unfold: bool = True) -> np.ndarray:
        """The chains' first states as the data show them (the inverse of the output function, roughly)."""
        if self.output == "abs":
            floor = np.quantile(ym, 0.005, axis=0)
            return np.column_stack([unfold_sign(ym[:, k], floor[k]) if unfold else ym[:, k] - floor[k]
                                    for k in range(ym.shape[1])])
        return ym

    def _starts(self, um: np.ndarray, ym: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Candidate starts (theta, eta) for the passes on the estimation part ``um``, ``ym``."""
        theta0 = self._initial_theta()
        eta0 = self._default_eta()
        if self.output == "saturation":
            span = ym.max(axis=0) - ym.min(axis=0)
            eta0[:, 0], eta0[:, 1] = ym.min(axis=0) - 0.05 * span, ym.max(axis=0) + 0.05 * span
        if self.init == "given":
            return [(theta0, eta0)]
        if self.init == "kalman":
            WS, WH, _, _ = self._rows(um, carry=False)
            th = ekf_initial_theta(self.structure_, self._cfg(False), WS, WH, ym, theta0, self.kalman_options,
                                   eta=eta0.ravel())
            return [(th, eta0)]
        cands: list[tuple[np.ndarray, np.ndarray]] = []
        if self.theta0 is not None:
            cands.append((theta0, eta0))
        ts = self.ts_model
        unit = float(self.alpha_) / (self.time_scale_rad_s_ or float(self.alpha_))  # model time per system time
        hold = self.half_step_input_ == "hold"
        variants = [(True, eta0)]
        if self.output == "abs":
            floor = np.quantile(ym, 0.005, axis=0)
            eta_abs = eta0.copy()
            eta_abs[:, 0] = floor
            variants = [(True, eta_abs), (False, eta_abs)]
        elif self.output == "polynomial":
            eta0 = eta0.copy()
        for unfold, eta in variants:
            z = self._chain_output(ym, unfold) if self.output == "abs" else ym
            for lam in (0.5, 1.0, 2.0):
                cands.extend((th, eta) for th in equation_error_thetas(self.structure_, um, z, lam / unit, ts, hold))
        if self.output != "identity":
            # output-error starts: the same chain with the identity output fitted, by this estimator's own passes,
            # to the chain output the data show; for "abs" to each of several sign-unfolded versions of the output
            eta_pre = variants[0][1]
            if self.output == "abs":
                per_output = [unfold_candidates(ym[:, k], eta_pre[k, 0], um, int(self.n_states))
                              for k in range(self.n_outputs_)]
                targets = [np.column_stack([c[min(i, len(c) - 1)] for c in per_output])
                           for i in range(max(len(c) for c in per_output))]
            else:
                targets = [ym]
            pre = self.clone(output="identity", init="auto", half_step_input=self.half_step_input_,
                             alpha=float(self.alpha_), n_substeps=int(self.n_substeps_), normalize=False,
                             output_limits=None, keep="best", n_restarts=0, theta0=None, pass_mode="continue",
                             R0=self._r0(),
                             n_passes=min(10, int(self.n_passes)), refit=False)
            for z in targets:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    pre.fit(um, z)
                cands.append((pre.theta_.copy(), eta_pre))
        if not cands:
            cands.append((theta0, eta0))
        scored = [(self._sim_fit(um, ym, th, eta), i) for i, (th, eta) in enumerate(cands)]
        scored.sort(key=lambda s: -s[0])
        return [cands[scored[0][1]]]

    def _fit_mode(self, um: np.ndarray, ym: np.ndarray, split: int, n_passes: int, tuned: bool) -> dict[str, Any]:
        """Starts and passes for the current half-step mode; the best (start, pass) on the hold-out."""
        u_fit, y_fit = um[:split], ym[:split]
        cache = self.__dict__.setdefault("_start_cache", {})
        if self.half_step_input_ not in cache:  # the starts do not depend on the pass mode
            cache[self.half_step_input_] = self._starts(u_fit, y_fit)
        starts = [(th.copy(), eta.copy()) for th, eta in cache[self.half_step_input_]]
        self.theta_init_ = starts[0][0].copy()
        rng = np.random.default_rng(int(self.random_state))
        for _ in range(int(self.n_restarts)):
            th, eta = starts[0]
            th_r = th + (0.3 * np.abs(th) + 0.1) * rng.standard_normal(th.shape)
            eta_r = eta + (0.3 * np.abs(eta) + 0.1) * rng.standard_normal(eta.shape)
            if self.output == "saturation":
                eta_r = np.sort(eta_r, axis=1)
            starts.append((th_r, eta_r))
        best: dict[str, Any] | None = None
        for i, start in enumerate(starts):
            result = self._passes(um, ym, split, n_passes, start, tuned)
            result["start_index"] = i
            if best is None or result["score"] > best["score"]:
                best = result
        assert best is not None
        return best

    def _passes(self, um: np.ndarray, ym: np.ndarray, split: int, n_passes: int,
                start: tuple[np.ndarray, np.ndarray], tuned: bool) -> dict[str, Any]:
        theta, eta = start[0].copy(), start[1].copy()
        u_fit, y_fit = um[:split], ym[:split]
        best: dict[str, Any] = {"score": -np.inf, "mode": self.half_step_input_, "pass_mode": self.pass_mode_,
                                "start": (theta.copy(), eta.copy()), "pass_fits": [], "state": None}
        fits: list[float] = []
        stale = 0
        if tuned and self._autos:
            # with the automatic choices the start itself is a candidate: passes that diverge from a good start
            # must not replace it
            self._reset_recursion(theta, eta)
            self._keep(best, self._score(um, ym, split, theta, eta), self._snapshot(), 0)
        # the thesis' passes stop at the first pass that does not improve; with the automatic choices, after three;
        # "continue" converges slowly and may sit below its start (or dip below its own best) for many passes before
        # it climbs, so it runs until it converges (the hold-out FIT stays within PLATEAU_FIT points over
        # PLATEAU_PASSES passes; automatic choices) or until n_passes
        patience = (1 if not self._autos else 3) if self.pass_mode_ == "restart" else n_passes
        for k in range(n_passes):
            if k == 0 or self.pass_mode_ == "restart":
                self._reset_recursion(theta, eta)
            else:  # continue the recursion: restart the model state only
                self._st[kernel.ST_STARTED] = 0.0
                self._u_prev = self._du_prev = None
            self._run(u_fit, y_fit)
            theta, eta = self.theta_.copy(), self.output_params_.copy()
            state = self._snapshot()
            if not tuned and self.keep == "last":
                self._keep(best, self._score(um, ym, split, theta, eta), state, k + 1)
                fits.append(best["score"])
                continue
            if n_passes == 1 and not tuned:
                best.update(score=-np.inf, state=state, sim_hits=0.0, kept_passes=1)
                break
            fit = self._score(um, ym, split, theta, eta)
            fits.append(fit)
            if fit > best["score"] + float(self.pass_tol) or best["state"] is None:
                self._keep(best, fit, state, k + 1)
                stale = 0
            else:
                stale += 1
                if stale >= patience:
                    break
            if self._autos and self.pass_mode_ == "continue" and len(fits) > PLATEAU_PASSES and \
                    abs(fits[-1] - fits[-1 - PLATEAU_PASSES]) < PLATEAU_FIT:
                break  # converged: the hold-out FIT has not moved over the last passes
        best["pass_fits"] = fits
        if best["state"] is None:
            best["state"] = self._snapshot()
        return best

    def _snapshot(self) -> dict[str, Any]:
        return {"theta_": self.theta_.copy(), "output_params_": self.output_params_.copy(), "P_": self.P_.copy(),
                "Lambda_": self.Lambda_.copy(), "x_": self.x_.copy(), "sensitivity_": self.sensitivity_.copy(),
                "_st": self._st.copy(), "_u_prev": self._u_prev, "_du_prev": self._du_prev,
                "n_samples_seen_": self.n_samples_seen_, "n_rejected_": self.n_rejected_,
                "n_bound_hits_": self.n_bound_hits_, "n_updates_": self.n_samples_seen_,
                "gain_": self.gain_, "forgetting_": self.forgetting_}

    def _keep(self, best: dict[str, Any], score: float, state: dict[str, Any], n_passes: int) -> None:
        best.update(score=score, state=state, sim_hits=getattr(self, "_last_sim_hits", 0.0), kept_passes=n_passes)

    def _score(self, um: np.ndarray, ym: np.ndarray, split: int, theta: np.ndarray, eta: np.ndarray) -> float:
        """Simulation FIT (mean over outputs) on the hold-out ``[split:]``, or on all data if there is none; the
        simulation runs over the whole record from ``(y(0), 0, ...)`` (its fraction of samples on the state bound
        is kept in ``_last_sim_hits``)."""
        yhat, hits = self._simulate(um, self._x_start(ym[0], eta), theta, eta)
        self._last_sim_hits = hits / max(len(ym), 1)
        if not np.all(np.isfinite(yhat)) or hits > WARN_BOUND_FRACTION * len(ym):
            return -np.inf
        sl = slice(split, None) if split < len(ym) else slice(None)
        return float(np.mean(np.atleast_1d(fit_percent(ym[sl], yhat[sl]))))

    def _warn_if_diverged(self, um: np.ndarray, ym: np.ndarray) -> None:
        n_updates = max(int(self.n_updates_), 1)
        if self.n_rejected_ > WARN_REJECTED_FRACTION * n_updates:
            warnings.warn(f"RecursivePEM: {self.n_rejected_} of {n_updates} parameter updates were rejected by the "
                          "projection onto the model set DM (each would have made the model's linearisation at the "
                          "current state and input less stable than stability_margin allows), so the estimate moved "
                          "little from its start; try normalize=True, alpha='auto' and init='auto' (AUTO_SETTINGS), "
                          "or a smaller stability_margin", RuntimeWarning, stacklevel=3)
        # the recursion's own simulation (the model state it propagates) on the state bound: counted by the kernel,
        # so this check costs nothing; a fit that scored its passes also checked the kept model's free run
        n_seen = max(int(self.n_samples_seen_), 1)
        hits = max(int(self.n_bound_hits_) / n_seen, self._kept_sim_hits) * len(ym)
        if hits > WARN_BOUND_FRACTION * len(ym):
            warnings.warn(f"RecursivePEM: the model's simulation sits on its state bound ({self.state_bound:g}) at "
                          f"{100.0 * hits / len(ym):.1f} % of the samples: the model diverged; try normalize=True, "
                          "alpha='auto', init='auto', keep='best' with n_passes > 1", RuntimeWarning, stacklevel=3)

    def _fresh_validate(self, u: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
        # fit() starts over, so the sizes of an earlier fit must not constrain the new data.
        u2 = as_2d("u", u)
        y2 = as_2d("y", y)
        check_same_length(u=u2, y=y2)
        return u2, y2

    def _x_start(self, y0m: np.ndarray, eta: np.ndarray) -> np.ndarray:
        """``(y(0), 0, ...)`` per chain in model units (less the offset of a polynomial or |x| output)."""
        s = self.structure_
        x0 = np.zeros(s.n_states)
        off = eta[:, 0] if self.output in ("polynomial", "abs") else 0.0
        x0[np.arange(s.n_outputs) * s.n_chain] = y0m - off
        return x0

    def _sim_fit(self, um: np.ndarray, ym: np.ndarray, theta: np.ndarray, eta: np.ndarray | None = None) -> float:
        eta = self.output_params_ if eta is None else eta
        yhat, _ = self._simulate(um, self._x_start(ym[0], eta), theta, eta)
        if not np.all(np.isfinite(yhat)):
            return -np.inf
        return float(np.mean(np.atleast_1d(fit_percent(ym, yhat))))

    def partial_fit(self, u: Any, y: Any) -> RecursivePEM:
        """Continue the recursion over new samples (online use; the first call starts from ``theta0``, with no
        scaling and the hold input, as automatic choices need a whole record)."""
        if not hasattr(self, "theta_"):
            u2, y2 = self._validate(u, y)
            self._setup(u2.shape[1], y2.shape[1])
            self.theta_init_ = self._initial_theta()
            self._reset_recursion(self.theta_init_)
        else:
            u2, y2 = self._validate(u, y)
        self.last_prediction_ = self._y_phys(self._run(self._u_model(u2), self._y_model(y2))[-1]).copy()
        self.n_updates_ = self.n_samples_seen_
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
    def _simulate(self, um: np.ndarray, x0: np.ndarray, theta: np.ndarray,
                  eta: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        """Free run in model units from ``x0``; returns the outputs and the number of samples on the bound."""
        WS, WH, _, _ = self._rows(um, carry=False)
        s = self.structure_
        eta = self.output_params_ if eta is None else eta
        yhat = np.empty((len(um), s.n_outputs))
        X = np.empty((len(um), s.n_states))
        fvar, fpow, nf = self._factors
        hits = kernel.simulate(WS, WH, np.ascontiguousarray(theta, dtype=float),
                               np.ascontiguousarray(eta, dtype=float).ravel(), np.asarray(x0, dtype=float),
                               self._cfg(False), self.y_lo_, self.y_hi_, fvar, fpow, nf, s.owner, s.n_chain,
                               s.n_outputs, yhat, X)
        return yhat, int(hits)

    def initial_state(self, u: Any, y: Any, n_samples: int | None = None) -> np.ndarray:
        """The state x(0) that best explains the first samples of a record, in the model's units.

        Least squares on the free-run simulation error over the first ``n_samples`` samples (default: the first 200
        or the whole record if shorter), started from ``(y(0), 0, ...)`` (and its mirror image for an ``"abs"``
        output) per chain. ``predict(u, y0=y)`` uses it.
        """
        from scipy.optimize import least_squares

        check_is_fitted(self, "theta_")
        u2, y2 = self._validate(u, y)
        n0 = len(y2) if n_samples is None else check_positive_int("n_samples", n_samples)
        n0 = max(2, min(len(y2), 200 if n_samples is None else n0))
        um, ym = self._u_model(u2[:n0]), self._y_model(y2[:n0])
        guess = self._x_start(ym[0], self.output_params_)
        guesses = [guess]
        if self.output == "abs":
            mirror = guess.copy()
            mirror[np.arange(self.n_outputs_) * self.structure_.n_chain] *= -1.0
            guesses.append(mirror)
        scale = np.maximum(np.std(ym, axis=0).mean(), 1e-9)

        def residual(x0: np.ndarray) -> np.ndarray:
            yh, _ = self._simulate(um, x0, self.theta_)
            r = (yh - ym).ravel() / scale
            return np.where(np.isfinite(r), r, 1e6)

        best_x, best_cost = guess, np.inf
        bound = float(self.state_bound)
        for g in guesses:
            g = np.clip(g, -0.99 * bound, 0.99 * bound)
            try:
                sol = least_squares(residual, g, bounds=(-bound, bound), max_nfev=50 * (len(g) + 1))
            except (ValueError, FloatingPointError):
                continue
            if np.isfinite(sol.cost) and sol.cost < best_cost:
                best_x, best_cost = sol.x, sol.cost
        return np.asarray(best_x, dtype=float)

    def predict(self, u: Any, y0: Any | None = None, *, x0: Any | None = None) -> np.ndarray:
        """Simulated (free-run) output, shape ``(n_samples, n_outputs)``, in the output's units.

        The initial state: ``x0`` (model units, one value per state) if given; else from measured outputs ``y0``:
        one value per output (``y0`` of shape ``(n_outputs,)``, or one sample) starts at ``(y0, 0, ...)`` as in the
        thesis, while a series (shape ``(n0, n_outputs)`` with ``n0 > 1``, e.g. the whole measured record) gives
        the least-squares estimate of :meth:`initial_state` from its first samples; ``None``: zero output and
        state. Input derivatives start at zero at the first sample.
        """
        check_is_fitted(self, "theta_")
        u2, _ = self._validate(u)
        um = self._u_model(u2)
        s = self.structure_
        if x0 is not None:
            x = np.asarray(x0, dtype=float).ravel() if np.ndim(x0) else np.array([x0], dtype=float)
            if x.shape != (s.n_states,) or not np.all(np.isfinite(x)):
                raise ValueError(f"x0 must be {s.n_states} finite values (the model's states), got shape "
                                 f"{np.shape(x0)}")
        elif y0 is None:
            x = np.zeros(s.n_states)
        else:
            y0a = np.asarray(y0, dtype=float)
            d = self.n_outputs_
            if y0a.ndim == 0 or (y0a.ndim == 1 and y0a.size == d) or (y0a.ndim == 2 and y0a.shape[0] == 1):
                y0v = y0a.ravel()
                if y0v.shape != (d,) or not np.all(np.isfinite(y0v)):
                    raise ValueError(f"y0 must be {d} finite values (one initial output per output) or a measured "
                                     f"series of shape (n0, {d}), got shape {y0a.shape}")
                x = self._x_start(self._y_model(y0v), self.output_params_)
            else:
                y0s = y0a[:, None] if y0a.ndim == 1 else y0a
                if y0s.ndim != 2 or y0s.shape[1] != d:
                    raise ValueError(f"y0 must be {d} finite values or a measured series of shape (n0, {d}), got "
                                     f"shape {y0a.shape}")
                n0 = min(len(y0s), len(u2))
                x = self.initial_state(u2[:n0], as_2d("y0", y0s[:n0]))
        yhat, _ = self._simulate(um, x, self.theta_)
        return self._y_phys(yhat)

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
        um, ym = self._u_model(u2), self._y_model(y2)
        WS, WH, _, _ = self._rows(um, carry=False)
        cfg = self._cfg(False)
        eta = self.output_params_.ravel()
        x_start = self._x_start(ym[0], self.output_params_)
        Xf = ekf_state_estimates(s, cfg, WS, WH, ym, self.theta_, float(opts["q_state"]), float(opts["r"]),
                                 eta=eta, x0=x_start)
        yfree, _ = self._simulate(um, x_start, self.theta_)
        yhat = np.empty_like(ym)
        fvar, fpow, nf = self._factors
        kernel.k_step_predict(WS, WH, Xf, self.theta_, eta if eta.size else np.zeros(1), int(k), cfg, self.y_lo_,
                              self.y_hi_, fvar, fpow, nf, s.owner, s.n_chain, s.n_outputs, yfree, yhat)
        return self._y_phys(yhat)

    def score(self, u: Any, y: Any) -> float:
        """Simulation FIT in percent (mean over outputs), simulated from ``(y(0), 0, ...)``."""
        check_is_fitted(self, "theta_")
        u2, y2 = self._validate(u, y)
        return self._sim_fit(self._u_model(u2), self._y_model(y2), self.theta_)

    def to_casadi(self) -> Any:
        """``casadi.Function('step', [x, u], [x_next, y])`` of the discretised model in physical input and output
        units; see :func:`ident.rpem.export.to_casadi` for how input derivatives enter."""
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
        if self.kalman_options is not None:
            params["kalman_options"] = {str(k): float(v) for k, v in self.kalman_options.items()}
        meta = {"params": params, "n_inputs": self.n_inputs_, "n_outputs": self.n_outputs_,
                "resolved": {"alpha": float(self.alpha_), "n_substeps": int(self.n_substeps_),
                             "half_step_input": self.half_step_input_, "R0": self._r0()}}
        arrays = {"theta": self.theta_, "output_params": self.output_params_, "P": self.P_, "Lambda": self.Lambda_,
                  "x": self.x_, "sensitivity": self.sensitivity_, "st": self._st, "theta_init": self.theta_init_,
                  "input_mean": self.input_mean_, "input_scale": self.input_scale_,
                  "output_mean": self.output_mean_, "output_scale": self.output_scale_}
        return meta, arrays

    @classmethod
    def _from_state(cls, meta: dict, arrays: dict[str, np.ndarray]) -> RecursivePEM:
        """Rebuild, checking every array against the structure the metadata describe (ValueError otherwise)."""
        params = dict(meta["params"])
        if params.get("input_transforms"):
            params["input_transforms"] = {int(k): tuple(v) for k, v in params["input_transforms"].items()}
        n_inputs, n_outputs = meta["n_inputs"], meta["n_outputs"]
        for name, v in (("n_inputs", n_inputs), ("n_outputs", n_outputs)):
            if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= _MAX_DIM:
                raise ValueError(f"{name} must be an integer in [1, {_MAX_DIM}], got {v!r}")
        est = cls(**params)
        resolved = meta.get("resolved", {})
        est.alpha_ = _real("resolved alpha", resolved.get("alpha", 1.0 if isinstance(est.alpha, str) else est.alpha),
                           0.0, low_open=True)
        est.n_substeps_ = check_positive_int("resolved n_substeps", resolved.get(
            "n_substeps", 1 if isinstance(est.n_substeps, str) else est.n_substeps))
        if est.n_substeps_ > MAX_SUBSTEPS:
            raise ValueError(f"resolved n_substeps must be at most {MAX_SUBSTEPS}")
        hs = resolved.get("half_step_input", "hold" if est.half_step_input == "auto" else est.half_step_input)
        if hs not in ("hold", "interpolate"):
            raise ValueError(f"resolved half_step_input must be 'hold' or 'interpolate', got {hs!r}")
        est.half_step_input_ = hs
        est.R0_ = _real("resolved R0", resolved.get("R0", R0_DEFAULT if isinstance(est.R0, str) else est.R0), 0.0,
                        low_open=True)
        est._setup(n_inputs, n_outputs)
        s = est.structure_
        if s.n_params > _MAX_DIM or s.n_states > _MAX_DIM:
            raise ValueError(f"{s.n_params} terms and {s.n_states} states are more than a model file may hold")
        p, N, d, q = s.n_params, s.n_states, s.n_outputs, est._q()
        st = arrays["st"]
        if st.shape == (kernel.N_ST - 1,):  # written before the bound-hit counter existed
            st = np.r_[st, 0.0]
        eta = arrays.get("output_params", np.zeros((d, 0)))
        expected = {"theta": (p,), "P": (p + d * q, p + d * q), "Lambda": (d, d), "x": (N,), "sensitivity": (N, p),
                    "st": (kernel.N_ST,), "theta_init": (p,), "output_params": (d, q),
                    "input_mean": (n_inputs,), "input_scale": (n_inputs,), "output_mean": (d,), "output_scale": (d,)}
        got = {**arrays, "st": st, "output_params": eta}
        for name, shape in expected.items():
            a = got.get(name)
            if a is None:
                if name.startswith(("input_", "output_m", "output_s")):
                    continue  # written before scaling existed: identity scaling
                raise ValueError(f"array {name!r} is missing")
            if a.shape != shape:
                raise ValueError(f"array {name!r} has shape {a.shape}, the model's structure ({p} terms, {N} states, "
                                 f"{d} outputs) needs {shape}")
            if a.dtype.kind != "f" or not np.all(np.isfinite(a)):
                raise ValueError(f"array {name!r} must hold finite floats")
        for name in ("input_scale", "output_scale"):
            if name in arrays and not np.all(arrays[name] > 0):
                raise ValueError(f"array {name!r} must be positive")
        if not (np.all(np.isfinite(arrays["Lambda"])) and np.all(np.diag(arrays["Lambda"]) > 0)):
            raise ValueError("array 'Lambda' must have a positive diagonal")
        if "input_mean" in arrays:
            est._set_scaling(arrays["input_mean"], arrays["input_scale"], arrays["output_mean"],
                             arrays["output_scale"])
        est._reset_recursion(arrays["theta"], eta)
        est.P_ = arrays["P"].astype(float).copy()
        est.Lambda_ = arrays["Lambda"].astype(float).copy()
        est.x_ = arrays["x"].astype(float).copy()
        est.sensitivity_ = arrays["sensitivity"].astype(float).copy()
        est._st = st.astype(float).copy()
        est.theta_init_ = arrays["theta_init"].astype(float).copy()
        # The carried-over input is not saved: the next partial_fit restarts x from its first output sample.
        est._st[kernel.ST_STARTED] = 0.0
        est.n_samples_seen_ = int(est._st[kernel.ST_COUNT])
        est.n_updates_ = est.n_samples_seen_
        est.n_rejected_ = int(est._st[kernel.ST_REJECTED])
        est.n_bound_hits_ = int(est._st[kernel.ST_BOUND_HITS])
        return est


__all__ = ["AUTO_SETTINGS", "OUTPUT_FUNCTIONS", "R0_GRID", "RecursivePEM"]
_ = DEFAULT_KALMAN_OPTIONS  # re-exported for users reading the defaults next to the estimator
