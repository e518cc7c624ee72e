"""CasADi export of a fitted :class:`~ident.rpem.estimator.RecursivePEM`.

The exported function is ``casadi.Function('step', [x, u], [x_next, y])`` of the discretised model (as
:mod:`ident.base` documents), with ``u`` the *raw* input (input transforms are applied inside) and ``y`` the
(saturated) output at the current state, ``y(t) = sat(x_1(t))``.

Input derivatives. When a regressor uses ``u'``, the exported state is augmented with the previous transformed
input: ``x = (x_model (N), u_prev (m))``, and ``u'(t) = (u(t) - u_prev) / (alpha T)``, the same backward
difference the estimator uses; ``x_next = (x_model(t+1), u(t))``. Without derivative terms ``x = x_model``.
The half step uses the held input value (zero-order hold); a model fitted with ``half_step_input='interpolate'``
is exported with the held value too, since the step function only sees u(t). A model with ``n_substeps = m``
takes m steps of ``Ts / m`` per call. Scaling (``normalize=True``) is inside: ``u`` and ``y`` are in physical units,
the state in the model's (standardised) units; ``y = mean + SD * sat(h(x_1, eta))`` with the output function h.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from ident.rpem.structure import INPUT_TRANSFORMS


def _casadi_transform(name: str, u: Any, a: float) -> Any:
    import casadi as ca

    if name == "exp_neg_inv":
        return ca.exp(-a / u)
    if name == "scale":
        return a * u
    raise ValueError(f"no CasADi form for input transform {name!r} (known: {sorted(INPUT_TRANSFORMS)})")


def _output_function(kind: str, x1: Any, eta: np.ndarray) -> Any:
    """The static output function of :class:`~ident.rpem.estimator.RecursivePEM` (``output``) in CasADi."""
    import casadi as ca

    if kind == "identity":
        return x1
    if kind == "polynomial":
        y = float(eta[0]) + x1
        for i in range(2, len(eta) + 1):
            y = y + float(eta[i - 1]) * x1**i
        return y
    if kind == "abs":
        return float(eta[0]) + ca.fabs(x1)
    if kind == "saturation":
        return ca.fmin(ca.fmax(x1, float(eta[0])), float(eta[1]))
    raise ValueError(f"unknown output function {kind!r}")


def to_casadi(est: Any) -> Any:
    """Build the ``step`` function of a fitted estimator (see module docstring for the state layout)."""
    import casadi as ca

    s = est.structure_
    N, m, d, n = s.n_states, s.n_inputs, s.n_outputs, s.n_chain
    with_prev = s.uses_derivatives
    xs = ca.SX.sym("x", N + (m if with_prev else 0))
    us = ca.SX.sym("u", m)
    xm = xs[:N]
    ut = [us[j] for j in range(m)]
    for j, (name, par) in (est.input_transforms or {}).items():
        ut[int(j) - 1] = _casadi_transform(name, us[int(j) - 1], float(par))
    if est.normalize:
        ut = [(ut[j] - float(est.input_mean_[j])) / float(est.input_scale_[j]) for j in range(m)]
    ts = est.ts_model
    if with_prev:
        du = [(ut[j] - xs[N + j]) / ts for j in range(m)]
    else:
        du = [ca.SX(0) for _ in range(m)]
    theta = np.asarray(est.theta_, dtype=float)

    def rhs(x: Any) -> Any:
        zvars = [x[i] for i in range(N)] + ut + du
        f = [ca.SX(0) for _ in range(d)]
        for j, row in enumerate(s.exponents):
            term = ca.SX(1)
            for v in np.flatnonzero(row):
                term = term * zvars[v] ** int(row[v])
            f[int(s.owner[j])] = f[int(s.owner[j])] + float(theta[j]) * term
        out = []
        for i in range(N):
            out.append(x[i + 1] if (i % n) != n - 1 else f[i // n])
        return ca.vertcat(*out)

    h = ts / int(est.n_substeps_)
    x_next = xm
    for _ in range(int(est.n_substeps_)):
        if est.method == "euler":
            x_next = x_next + h * rhs(x_next)
        else:
            xbar = x_next + 0.5 * h * rhs(x_next)
            x_next = x_next + h * rhs(xbar)
    if with_prev:
        x_next = ca.vertcat(x_next, *ut)
    ys = []
    eta = np.asarray(est.output_params_, dtype=float)
    for k in range(d):
        yk = _output_function(est.output, xm[k * n], eta[k])
        if np.isfinite(est.y_lo_[k]):
            yk = ca.fmax(yk, float(est.y_lo_[k]))
        if np.isfinite(est.y_hi_[k]):
            yk = ca.fmin(yk, float(est.y_hi_[k]))
        if est.normalize:
            yk = float(est.output_mean_[k]) + float(est.output_scale_[k]) * yk
        ys.append(yk)
    return ca.Function("step", [xs, us], [x_next, ca.vertcat(*ys)], ["x", "u"], ["x_next", "y"])
