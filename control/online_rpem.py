"""Online adaptation of the loop's RPEM while its NMPC runs (issue 18: the purpose of a recursive method).

The for-control RPEM (:func:`ident.for_control.fit_rpem_for_control`) is the thesis' polynomial chain ODE with
one-state chains, so its right-hand side is linear in the parameters and every state is a measured output:
``dy/dt = Phi(y, z, z') theta``. :class:`OnlineRPEM` re-estimates a few of its parameters (by default the
constant and the dose -- stoichiometric surplus -- term of the NOx chain: the local offset and gain of the dose's
effect, what the NMPC acts through) from the measured signals at every window of ``window_steps`` control
intervals, by the integral form of the equation error over the window,

    y(t) - y(t - W) = sum over the window of Ts Phi(y_i, z_i, z'_i) theta,

(y_i the state at the start of each interval, z_i that interval's input: the Euler equation error the model was
identified with, :func:`ident.for_control.fit_rpem_for_control`, summed over the window),

with the measured outputs (tailpipe NOx = NOx sensor - NH3 sensor, the sensor being cross-sensitive; both
low-pass filtered over ``filter_s``) in the model's units and the applied inputs. The estimator is recursive least
squares with *regularised* exponential forgetting (Kulhavy and Zarrop, Int. J. Control 58:905, 1993): the
information decays towards the prior's (the identified parameters, with ``prior_sd``), not towards zero, so the
covariance cannot wind up when the loop is not exciting (IDENT_FOR_CONTROL.md, trap "adaptation windup") and the
estimate returns to the identified model when the data say nothing. Two safeguards, as the issue asks:

* stability projection (the RPEM's rule, :mod:`ident.rpem`): a candidate whose linearisation at the current point
  has an eigenvalue with real part above ``-margin_per_s`` is rejected (``n_rejected_``), unless the parameters in
  use are outside that set there too and the candidate is no further outside (it moves the estimate back);
* fallback to the last good parameters: before each update the parameters in use are scored on the new window
  against the identified ones; when their summed squared window error over the last ``fallback_windows`` windows
  exceeds ``fallback_ratio`` times the identified model's, the estimate returns to the identified parameters and
  the recursion restarts from the prior (``n_fallbacks_``).

Closed-loop caveat (IDENT_FOR_CONTROL.md, "closed-loop data bias"): the dose is computed from the measurements, so
the equation error is consistent only as far as the noise is white after the filter; the prior and the fallback
bound what a bias can do.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["ADAPTED_TERMS", "OnlineRPEM"]

#: the adapted parameters: (chain, term) pairs -- chain 0 the NOx output, 1 the NH3 output -- by default the NOx
#: chain's constant and dose (surplus, u1) terms [chosen: the NH3 chain's measured output, log(NH3 + 0.01 ppm),
#: is dominated by the 1 ppm sensor noise while the catalyst does not slip, which is most of the time]
ADAPTED_TERMS: tuple[tuple[int, str], ...] = ((0, "1"), (0, "u1"))


class OnlineRPEM:
    """Online adaptation of a fitted for-control RPEM (module docstring).

    Parameters
    ----------
    model : the fitted :class:`~ident.rpem.RecursivePEM` of :func:`ident.for_control.fit_rpem_for_control`.
    terms : the adapted (chain, term name) pairs (:data:`ADAPTED_TERMS`); term names as the model's structure
        writes them per chain (``"1"``, ``"u1"``, ``"x1*u4"``, ...).
    forgetting : forgetting factor per window, lambda in (0, 1]: memory of about ``window_steps / (1 - lambda)``
        control intervals.
    window_steps : control intervals per update window.
    prior_sd : prior standard deviation of each adapted parameter, relative to ``max(|theta0|, prior_floor)``.
    prior_floor : floor of the parameter scale [model units].
    noise_sd : standard deviation of the window's output change per chain [model units] (the weight of the data
        against the prior).
    margin_per_s : stability margin of the projection [1/s].
    fallback_ratio, fallback_windows : the fallback rule (module docstring).
    min_nox_ppm : windows in which the measured tailpipe NOx falls below this are not used [ppm] (read by the
        NMPC's model, :class:`control.blackbox.BlackBoxModel`, which passes ``informative``): the log slip ratio of
        a reading near zero is the sensor's noise (2 ppm), floored, not the plant's conversion [chosen: 5 times that
        noise].
    """

    def __init__(self, model: Any, terms: Sequence[tuple[int, str]] = ADAPTED_TERMS, forgetting: float = 0.98,
                 window_steps: int = 10, prior_sd: float = 0.5, prior_floor: float = 0.05,
                 noise_sd: Sequence[float] | float = 0.01, margin_per_s: float = 1e-4, fallback_ratio: float = 1.5,
                 fallback_windows: int = 12, min_nox_ppm: float = 10.0) -> None:
        from ident.for_control import rpem_parametric_functions

        if not 0.0 < float(forgetting) <= 1.0:
            raise ValueError(f"forgetting must be in (0, 1], got {forgetting!r}")
        if isinstance(window_steps, bool) or int(window_steps) != window_steps or window_steps < 1:
            raise ValueError(f"window_steps must be a whole number >= 1, got {window_steps!r}")
        for name, v in (("prior_sd", prior_sd), ("prior_floor", prior_floor), ("fallback_ratio", fallback_ratio)):
            if not np.isfinite(v) or v <= 0:
                raise ValueError(f"{name} must be a finite number > 0, got {v!r}")
        fns = rpem_parametric_functions(model)
        self._regressor, self._jacobian = fns["regressor"], fns["jacobian"]
        self.step_function = fns["step"]
        s = model.structure_
        self.n_outputs = int(s.n_outputs)
        names = s.term_names()
        owner = np.asarray(s.owner, int)
        idx = []
        for chain, term in terms:
            hits = [j for j in range(len(names)) if owner[j] == int(chain) and names[j] == term]
            if not hits:
                have = sorted({f"({int(owner[j])}, {names[j]!r})" for j in range(len(names))})
                raise ValueError(f"terms: ({chain}, {term!r}) is not a term of the model; it has {', '.join(have)}")
            idx.append(hits[0])
        self.adapted_ = np.asarray(idx, int)
        self.fixed_ = np.setdiff1d(np.arange(len(names)), self.adapted_)
        self.theta0 = np.asarray(model.theta_, float).copy()
        self.ts = float(model.ts_model)
        self.forgetting = float(forgetting)
        self.window_steps = int(window_steps)
        self.margin_per_s = float(margin_per_s)
        self.fallback_ratio = float(fallback_ratio)
        self.fallback_windows = int(fallback_windows)
        self.min_nox_ppm = float(min_nox_ppm)
        scale = np.maximum(np.abs(self.theta0[self.adapted_]), float(prior_floor)) * float(prior_sd)
        self.R0_ = np.diag(1.0 / scale ** 2)
        self.noise_sd = np.broadcast_to(np.asarray(noise_sd, float), (self.n_outputs,)).copy()
        if not np.all(np.isfinite(self.noise_sd)) or np.any(self.noise_sd <= 0):
            raise ValueError(f"noise_sd must be finite numbers > 0, got {noise_sd!r}")
        self.reset()

    def reset(self) -> None:
        """The identified parameters and the prior's information; empty window; counters to zero."""
        self.theta_ = self.theta0.copy()
        self._R = self.R0_.copy()
        self._r = self.R0_ @ self.theta0[self.adapted_]
        self._y: list[np.ndarray] = []
        self._phi: list[np.ndarray] = []
        self._z_prev: np.ndarray | None = None
        self._errors: list[tuple[float, float]] = []
        self._informative = True
        self.n_skipped_ = 0
        self.n_updates_ = 0
        self.n_rejected_ = 0
        self.n_fallbacks_ = 0

    def observe(self, y: np.ndarray, z: np.ndarray, informative: bool = True) -> np.ndarray:
        """One control interval: the measured outputs ``y`` now (model units) and the model input ``z`` over the
        interval that led here; updates at the end of each window, unless a sample of the window was not
        ``informative`` (then the window is skipped, ``n_skipped_``). Returns the parameters to use now."""
        y = np.asarray(y, float).reshape(self.n_outputs)
        z = np.asarray(z, float).ravel()
        if not (np.all(np.isfinite(y)) and np.all(np.isfinite(z))):
            self._y, self._phi, self._z_prev = [], [], None   # a non-finite reading: restart the window
            return self.theta_
        if self._y:   # the step from the last sample to this one: its state, this interval's input (Euler)
            zp = z if self._z_prev is None else self._z_prev
            self._phi.append(np.asarray(self._regressor(self._y[-1], z, zp), float))
        self._y.append(y)
        self._z_prev = z
        self._informative = self._informative and bool(informative)
        if len(self._phi) >= self.window_steps:
            if self._informative:
                self._update(z, zp)
            else:
                self.n_skipped_ += 1
            self._y, self._phi, self._informative = self._y[-1:], [], bool(informative)
        return self.theta_

    def _update(self, z: np.ndarray, zp: np.ndarray) -> None:
        dy = self._y[-1] - self._y[0]
        Phi = self.ts * np.sum(self._phi, axis=0)                   # (n_outputs, n_params)
        w = 1.0 / self.noise_sd
        # fallback: the parameters in use against the identified ones, on this (new) window
        e_use = float(np.sum((w * (dy - Phi @ self.theta_)) ** 2))
        e_0 = float(np.sum((w * (dy - Phi @ self.theta0)) ** 2))
        self._errors = (self._errors + [(e_use, e_0)])[-self.fallback_windows:]
        if len(self._errors) == self.fallback_windows:
            s_use, s_0 = (sum(e[i] for e in self._errors) for i in (0, 1))
            if s_use > self.fallback_ratio * s_0:
                self.theta_ = self.theta0.copy()
                self._R, self._r = self.R0_.copy(), self.R0_ @ self.theta0[self.adapted_]
                self._errors = []
                self.n_fallbacks_ += 1
                return
        A = w[:, None] * Phi[:, self.adapted_]
        b = w * (dy - Phi[:, self.fixed_] @ self.theta_[self.fixed_])
        lam = self.forgetting
        R = lam * self._R + (1.0 - lam) * self.R0_ + A.T @ A
        r = lam * self._r + (1.0 - lam) * (self.R0_ @ self.theta0[self.adapted_]) + A.T @ b
        try:
            cand = np.linalg.solve(R, r)
        except np.linalg.LinAlgError:
            self.n_rejected_ += 1
            return
        theta = self.theta_.copy()
        theta[self.adapted_] = cand
        if not np.all(np.isfinite(cand)) or self._abscissa(theta, z, zp) > max(-self.margin_per_s,
                                                                                self._abscissa(self.theta_, z, zp)):
            self.n_rejected_ += 1
            return
        self._R, self._r, self.theta_ = R, r, theta
        self.n_updates_ += 1

    def _abscissa(self, theta: np.ndarray, z: np.ndarray, zp: np.ndarray) -> float:
        """Largest real part of the eigenvalues of the linearisation at the current point [1/s] (inf if not finite)."""
        J = np.asarray(self._jacobian(self._y[-1], z, zp, theta), float)
        return float(np.max(np.linalg.eigvals(J).real)) if np.all(np.isfinite(J)) else float("inf")

    def stats(self) -> dict[str, float]:
        """Updates, rejected candidates, fallbacks, and the largest relative change of an adapted parameter."""
        d = np.abs(self.theta_[self.adapted_] - self.theta0[self.adapted_]) / np.maximum(
            np.abs(self.theta0[self.adapted_]), 1e-12)
        return {"adaptation_updates": float(self.n_updates_), "adaptation_rejected": float(self.n_rejected_),
                "adaptation_skipped": float(self.n_skipped_),
                "adaptation_fallbacks": float(self.n_fallbacks_), "adaptation_max_rel_change": float(d.max())}
