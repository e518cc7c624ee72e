"""Fitting and exporting the black-box model classes for the dosing NMPC (issue 18, research prototype).

* :func:`fit_hw_outputs`: one Hammerstein-Wiener model per output (Paper IV's structure) fitted on many records
  at once (concatenated; the first ``warmup`` samples of each record carry zero weight, so the joins between
  records do not enter the criterion).
* :func:`hw_stack_export`: the stacked models as one ``Function('step', [x, z], [x_next, y])`` whose output blocks
  may be smoothed (a saturation ``max(w, lo)`` becomes ``lo + softplus(w - lo)``: the NMPC sees a gradient below
  the saturation), and the linear part ``(A, z -> B v(z))`` for exact multi-step stages.
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import casadi as ca
import numpy as np
from scipy.linalg import block_diag

from ident.hammerstein_wiener import HammersteinWiener, Saturation


def concat_records(us: Sequence[np.ndarray], ys: Sequence[np.ndarray], warmup: int = 120
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, y, weights) of the records end to end, weight 0 on each record's first ``warmup`` samples."""
    w = [np.r_[np.zeros(min(warmup, len(u))), np.ones(max(len(u) - warmup, 0))] for u in us]
    return np.vstack(us), np.vstack(ys), np.concatenate(w)


def fit_hw_outputs(u: np.ndarray, y: np.ndarray, weights: np.ndarray, templates: Sequence[HammersteinWiener]
                   ) -> list[HammersteinWiener]:
    """Fit ``templates[i]`` (unfitted) on output column i; returns the fitted models."""
    return [t.fit(u, y[:, [i]], sample_weight=weights) for i, t in enumerate(templates)]


def _smooth_output(block: Any, w: Any, p: np.ndarray, eps: float) -> Any:
    if isinstance(block, Saturation) and eps > 0:
        lo, hi = block._limits(np.asarray(p, dtype=float))
        out = w
        if np.isfinite(lo):
            d = out - lo
            out = lo + 0.5 * (d + ca.sqrt(d * d + eps * eps))
        if np.isfinite(hi):
            d = hi - out
            out = hi - 0.5 * (d + ca.sqrt(d * d + eps * eps))
        return out
    return block.casadi(w, p)


def hw_stack_export(models: Sequence[HammersteinWiener], smooth_eps: float = 0.0
                    ) -> tuple[ca.Function, np.ndarray, Any]:
    """``(step, A, bfun)`` of the stacked models (states in model order): ``step(x, z) -> (x_next, y)``,
    ``x_next = A x + bfun(z)``."""
    nz = int(models[0].n_inputs_)
    z = ca.SX.sym("z", nz)
    As, Bv, ys = [], [], []
    sizes = [m.n_states_ for m in models]
    x = ca.SX.sym("x", int(sum(sizes)))
    k = 0
    for m, n in zip(models, sizes):
        v = ca.vertcat(*[b.casadi(z[i], p) for i, (b, p) in enumerate(zip(m.input_blocks_, m.input_params_))])
        As.append(m.A_)
        Bv.append(ca.mtimes(ca.DM(m.B_), v))
        w = ca.mtimes(ca.DM(m.C_), x[k:k + n]) + ca.mtimes(ca.DM(m.D_), v)
        ys.append(_smooth_output(m.output_block_, w, m.output_params_, smooth_eps))
        k += n
    A = block_diag(*As)
    bv = ca.vertcat(*Bv)
    step = ca.Function("step", [x, z], [ca.mtimes(ca.DM(A), x) + bv, ca.vertcat(*ys)], ["x", "z"], ["x_next", "y"])
    bfun_f = ca.Function("bv", [z], [bv])
    return step, A, lambda zz: bfun_f(zz)


def hw_steady_state(A: np.ndarray, bfun: Any, z: np.ndarray) -> np.ndarray:
    """The state at rest under the held input ``z``: (I - A)^-1 B v(z)."""
    bv = np.asarray(bfun(ca.DM(z))).ravel()
    return np.linalg.solve(np.eye(A.shape[0]) - A, bv)
