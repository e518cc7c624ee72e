"""The model structure shared by the estimator, the Kalman initialisation and the CasADi export.

A :class:`ChainStructure` turns the user-facing description (chain length, term strings, input transforms,
discretisation) into the arrays the numba kernels take, and turns raw input sequences into the per-sample input
rows ``(u, u')`` at the step start and at the half step.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ident.rpem import kernel
from ident.rpem.regressors import format_term, parse_terms

#: Named input transforms (JSON-serialisable as ``[name, parameter]``).
INPUT_TRANSFORMS = {
    # exp(-a / u): the Arrhenius-type temperature input of Paper III (u3* = exp(-a / T_in), a = 1e4 K).
    "exp_neg_inv": lambda u, a: np.exp(-a / u),
    "scale": lambda u, a: a * u,
}


def apply_input_transforms(u: np.ndarray, transforms: Mapping[int, Sequence]) -> np.ndarray:
    """Replace input column j (1-based key) by ``transform(u_j, parameter)``."""
    if not transforms:
        return u
    out = u.copy()
    for j, (name, par) in transforms.items():
        j = int(j)
        if not 1 <= j <= u.shape[1]:
            raise ValueError(f"input_transforms refers to input {j} but u has {u.shape[1]} columns")
        if name not in INPUT_TRANSFORMS:
            raise ValueError(f"unknown input transform {name!r}; known: {sorted(INPUT_TRANSFORMS)}")
        with np.errstate(divide="ignore", over="ignore"):
            out[:, j - 1] = INPUT_TRANSFORMS[name](u[:, j - 1], float(par))
        if not np.all(np.isfinite(out[:, j - 1])):
            raise ValueError(f"input transform {name!r} of input {j} gives NaN or inf (check the input's units)")
    return out


@dataclass
class ChainStructure:
    """Arrays describing ``d`` chains of ``n`` states with polynomial last equations.

    Attributes
    ----------
    n_chain, n_outputs, n_inputs : int
        Chain length n, number of outputs (= chains) d and number of inputs m.
    exponents : (p, N + 2m) int array
        Exponent matrix of all terms over ``(x_1..x_N, u_1..u_m, u'_1..u'_m)``, N = n d.
    owner : (p,) int array
        Chain (output) whose last equation each term belongs to.
    """

    n_chain: int
    n_outputs: int
    n_inputs: int
    exponents: np.ndarray
    owner: np.ndarray

    @classmethod
    def from_terms(cls, n_chain: int, n_outputs: int, n_inputs: int,
                   terms: Sequence[str] | Sequence[Sequence[str]]) -> ChainStructure:
        """Build from one term list (a per-chain template, ``x<i>`` relative to the chain) or one list per output
        (``x<i>`` numbered over all ``n d`` states)."""
        if n_chain < 1:
            raise ValueError(f"n_states must be >= 1, got {n_chain}")
        N = n_chain * n_outputs
        per_output = len(terms) > 0 and not isinstance(terms[0], str)
        blocks, owners = [], []
        if per_output:
            if len(terms) != n_outputs:
                raise ValueError(f"got {len(terms)} term lists for {n_outputs} outputs")
            for k, lst in enumerate(terms):
                E = parse_terms(list(lst), N, n_inputs)
                blocks.append(E)
                owners.append(np.full(len(E), k))
        else:
            E_local = parse_terms(list(terms), n_chain, n_inputs)  # type: ignore[arg-type]
            for k in range(n_outputs):
                E = np.zeros((len(E_local), N + 2 * n_inputs), dtype=np.int64)
                E[:, k * n_chain:(k + 1) * n_chain] = E_local[:, :n_chain]
                E[:, N:] = E_local[:, n_chain:]
                blocks.append(E)
                owners.append(np.full(len(E), k))
        return cls(n_chain, n_outputs, n_inputs, np.vstack(blocks), np.concatenate(owners).astype(np.int64))

    @property
    def n_states(self) -> int:
        return self.n_chain * self.n_outputs

    @property
    def n_params(self) -> int:
        return self.exponents.shape[0]

    @property
    def uses_derivatives(self) -> bool:
        return bool(np.any(self.exponents[:, self.n_states + self.n_inputs:] > 0))

    def term_names(self) -> list[str]:
        """Term strings with global state numbering, in parameter order."""
        return [format_term(r, self.n_states, self.n_inputs) for r in self.exponents]

    def factor_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(fvar, fpow, nf)``: each term's non-zero factors, the form :mod:`ident.rpem.kernel` evaluates."""
        p = self.n_params
        nf = (self.exponents > 0).sum(axis=1).astype(np.int64)
        F = max(1, int(nf.max()))
        fvar = np.zeros((p, F), dtype=np.int64)
        fpow = np.zeros((p, F), dtype=np.int64)
        for j, row in enumerate(self.exponents):
            idx = np.flatnonzero(row)
            fvar[j, :len(idx)] = idx
            fpow[j, :len(idx)] = row[idx]
        return fvar, fpow, nf

    def input_rows(self, u: np.ndarray, ts_model: float, half_step: str,
                   u_prev: np.ndarray | None = None, du_prev: np.ndarray | None = None,
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per-sample input rows ``(u, u')`` for the step *into* each sample.

        ``u'`` is the backward difference ``(u(t) - u(t-1)) / Ts`` on the model's scaled time axis (zero at the
        very first sample). The step into sample t starts from ``(u(t-1), u'(t-1))``; at the half step it uses the
        same held values (``half_step='hold'``, right for zero-order-hold inputs) or ``((u(t-1) + u(t)) / 2,
        u'(t))`` (``'interpolate'``, for samples of a smooth signal). ``u_prev``/``du_prev`` carry the last
        transformed input and derivative over from an earlier call so that online use equals batch use.

        Returns
        -------
        WS, WH : (T, 2m) arrays, and the last ``(u, u')`` to carry over.
        """
        T, m = u.shape
        du = np.empty_like(u)
        if u_prev is None:
            du[0] = 0.0
        else:
            du[0] = (u[0] - u_prev) / ts_model
        du[1:] = np.diff(u, axis=0) / ts_model
        WS = np.empty((T, 2 * m))
        WS[1:, :m] = u[:-1]
        WS[1:, m:] = du[:-1]
        if u_prev is None:
            WS[0, :m] = u[0]
            WS[0, m:] = 0.0
        else:
            WS[0, :m] = u_prev
            WS[0, m:] = du_prev
        if half_step == "hold":
            WH = WS
        elif half_step == "interpolate":
            WH = np.empty_like(WS)
            WH[:, :m] = 0.5 * (WS[:, :m] + u)
            WH[:, m:] = du
            if u_prev is None:
                WH[0] = WS[0]
        else:
            raise ValueError(f"half_step_input must be 'hold' or 'interpolate', got {half_step!r}")
        return np.ascontiguousarray(WS), np.ascontiguousarray(WH), u[-1].copy(), du[-1].copy()


def method_code(method: str) -> int:
    """Kernel code of a discretisation name."""
    codes = {"euler": kernel.EULER, "midpoint": kernel.MIDPOINT}
    if method not in codes:
        raise ValueError(f"method must be 'euler' or 'midpoint', got {method!r}")
    return codes[method]
