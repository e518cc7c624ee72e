"""The parametrisation of a (MIMO) Hammerstein-Wiener model and its simulation with the exact Jacobian.

    v_i(t)  = g_i(u_i(t); p_i)                           i = 1..n_inputs    (one static block per input)
    w_j(t)  = sum_i B_ji(q) / F_ji(q) v_i(t)             j = 1..n_outputs   (one transfer function per pair)
    y_j(t)  = h_j(w_j(t); p_hj)                                              (one static block per output)

The parameter vector is ``[free p_i for every input] + [b_ji (free), eta_ji for j, then i] + [free p_hj for every
output]`` (for one output the layout of the single-output model). ``F_ji`` is parametrised by reflection
coefficients ``tanh(eta)`` (always stable). A pair ``(j, i)`` with a unit static gain (``gain[j, i] = +-1``) has
its last numerator coefficient fixed by ``sum(b) = gain * F(1)``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

from ident.hammerstein_wiener.blocks import StaticNonlinearity
from ident.linear.oe import _KAPPA_MAX, poly_from_reflection, reflection_from_poly, stabilize_poly


def shift(x: np.ndarray, k: int) -> np.ndarray:
    """``x`` delayed by ``k`` samples along axis 0, zeros shifted in."""
    out = np.zeros_like(x)
    if k < len(x):
        out[k:] = x[:len(x) - k]
    return out


def eta_from_poly(f: np.ndarray) -> np.ndarray:
    """The ``eta`` (arctanh of the reflection coefficients) of a monic polynomial, stabilised first."""
    if len(f) <= 1:
        return np.zeros(0)
    f = stabilize_poly(np.asarray(f, dtype=float), 0.999)
    return np.arctanh(np.clip(reflection_from_poly(f), -_KAPPA_MAX, _KAPPA_MAX))


@dataclass
class Structure:
    """Working copies of the blocks, the orders and the fixed values of one fit."""

    blocks: list[StaticNonlinearity]
    outs: list[StaticNonlinearity]
    nb: np.ndarray              # (ny, nu)
    nf: np.ndarray              # (ny, nu)
    nk: np.ndarray              # (ny, nu)
    steady: bool
    p0_in: list[np.ndarray] = field(default_factory=list)
    p0_out: list[np.ndarray] = field(default_factory=list)
    gain: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))   # (ny, nu), nan where free
    _bound: np.ndarray | None = field(default=None, repr=False)
    _basis: dict[int, np.ndarray] = field(default_factory=dict, repr=False)

    def bind(self, u: np.ndarray | None) -> None:
        """Precompute, for the input array ``u`` of a fit, the basis ``Phi_i(u_i)`` of every free input block that is
        linear in its parameters (``g = Phi p``, ``dg/dp = Phi``): the simulations of that fit (called with this very
        array) then skip the blocks' evaluation. ``None`` drops the cache."""
        self._bound, self._basis = u, {}
        if u is not None:
            for i, blk in enumerate(self.blocks):
                if blk.n_free() and blk.linear_in_params():
                    self._basis[i] = np.ascontiguousarray(blk.dp(u[:, i], self.p0_in[i]))

    def _input(self, i: int, u: np.ndarray, p: np.ndarray, jac: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """(v_i, dv_i/dp_i or None) of input block i."""
        blk = self.blocks[i]
        if u is self._bound and i in self._basis:
            phi = self._basis[i]
            return phi @ p, (phi if jac else None)
        return blk.value(u[:, i], p), (blk.dp(u[:, i], p) if jac and blk.n_free() else None)

    @property
    def nu(self) -> int:
        return len(self.blocks)

    @property
    def ny(self) -> int:
        return len(self.outs)

    def n_in_free(self) -> int:
        return sum(b.n_free() for b in self.blocks)

    def n_out_free(self) -> int:
        return sum(b.n_free() for b in self.outs)

    def n_lin(self, j: int, i: int) -> int:
        """Free linear parameters of pair (j, i): numerator (one less with a unit gain) and denominator."""
        return int(self.nb[j, i]) - int(np.isfinite(self.gain[j, i])) + int(self.nf[j, i])

    def n_theta(self) -> int:
        return self.n_in_free() + sum(self.n_lin(j, i) for j in range(self.ny) for i in range(self.nu)) + \
            self.n_out_free()

    def slices(self) -> tuple[list[slice], list[list[slice]], list[slice]]:
        """Positions in theta of each input block's free parameters, each pair's linear parameters and each
        output block's free parameters."""
        o = 0
        s_in = []
        for b in self.blocks:
            s_in.append(slice(o, o + b.n_free()))
            o += b.n_free()
        s_lin = []
        for j in range(self.ny):
            row = []
            for i in range(self.nu):
                row.append(slice(o, o + self.n_lin(j, i)))
                o += self.n_lin(j, i)
            s_lin.append(row)
        s_out = []
        for b in self.outs:
            s_out.append(slice(o, o + b.n_free()))
            o += b.n_free()
        return s_in, s_lin, s_out

    def static_index(self) -> np.ndarray:
        """Indices in theta of the free static parameters (input blocks, then output blocks)."""
        s_in, _, s_out = self.slices()
        idx = [np.arange(s.start, s.stop) for s in s_in + s_out]
        return np.concatenate(idx).astype(int) if idx else np.zeros(0, dtype=int)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        lo, hi = np.full(self.n_theta(), -np.inf), np.full(self.n_theta(), np.inf)
        s_in, _, s_out = self.slices()
        for blk, s in zip(self.blocks + self.outs, s_in + s_out, strict=True):
            if blk.n_free():
                lo[s], hi[s] = blk.bounds()
        return lo, hi

    # ----------------------------------------------------------------------------------------- (un)packing
    def unpack(self, theta: np.ndarray) -> tuple[list[np.ndarray], list[list[np.ndarray]], list[list[np.ndarray]],
                                                 list[np.ndarray]]:
        """theta -> (input params, b[j][i], eta[j][i], output params), fixed values filled in."""
        s_in, s_lin, s_out = self.slices()
        p_in = [theta[s] if b.n_free() else p0 for b, s, p0 in zip(self.blocks, s_in, self.p0_in, strict=True)]
        p_out = [theta[s] if b.n_free() else p0 for b, s, p0 in zip(self.outs, s_out, self.p0_out, strict=True)]
        bs: list[list[np.ndarray]] = []
        etas: list[list[np.ndarray]] = []
        for j in range(self.ny):
            brow, erow = [], []
            for i in range(self.nu):
                th = theta[s_lin[j][i]]
                g = self.gain[j, i]
                nb_free = int(self.nb[j, i]) - int(np.isfinite(g))
                b, eta = th[:nb_free], th[nb_free:]
                if np.isfinite(g):   # unit static gain: sum(b) = g F(1)
                    f_sum = max(float(np.sum(poly_from_reflection(np.tanh(eta))[0])), 1e-12)
                    b = np.append(b, g * f_sum - np.sum(b))
                brow.append(b)
                erow.append(eta)
            bs.append(brow)
            etas.append(erow)
        return p_in, bs, etas, p_out

    def pack(self, p_in: list[np.ndarray], bs: list[list[np.ndarray]], etas: list[list[np.ndarray]],
             p_out: list[np.ndarray]) -> np.ndarray:
        """Inverse of :meth:`unpack` (a constrained pair's last numerator coefficient is dropped)."""
        parts: list[np.ndarray] = [np.asarray(p, dtype=float)
                                   for b, p in zip(self.blocks, p_in, strict=True) if b.n_free()]
        for j in range(self.ny):
            for i in range(self.nu):
                b = np.asarray(bs[j][i], dtype=float)
                parts += [b[:-1] if np.isfinite(self.gain[j, i]) else b, np.asarray(etas[j][i], dtype=float)]
        parts += [np.asarray(p, dtype=float) for b, p in zip(self.outs, p_out, strict=True) if b.n_free()]
        return np.concatenate(parts) if parts else np.zeros(0)

    # ---------------------------------------------------------------------------------------- simulation
    def linear_outputs(self, theta: np.ndarray, u: np.ndarray) -> np.ndarray:
        """w, shape (N, ny): the linear block's outputs."""
        p_in, bs, etas, _ = self.unpack(theta)
        v = np.column_stack([blk.value(u[:, i], p_in[i]) for i, blk in enumerate(self.blocks)])
        w = np.zeros((u.shape[0], self.ny))
        for j in range(self.ny):
            for i in range(self.nu):
                w[:, j] += self._filter(bs[j][i], etas[j][i], j, i, v[:, i])[0]
        return w

    def _filter(self, b: np.ndarray, eta: np.ndarray, j: int, i: int, x: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        """``B/F`` applied to x (steady start: at rest at x(0)); returns (output, num, f, gain, x0)."""
        f = poly_from_reflection(np.tanh(eta))[0]
        num = np.concatenate([np.zeros(int(self.nk[j, i])), b])
        x0 = float(x[0]) if self.steady else 0.0
        gain = float(np.sum(b)) / max(float(np.sum(f)), 1e-12)   # F(1) > 0 for a stable F
        return lfilter(num, f, x - x0) + gain * x0, num, f, gain, x0

    def simulate(self, theta: np.ndarray, u: np.ndarray, jac: bool, out: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        """Outputs (N, ny) and, with ``jac``, d yhat / d theta of shape (ny * N, n_theta), outputs stacked
        (output-major: rows j * N .. (j + 1) * N - 1 belong to output j), written into the first ny * N rows of
        ``out`` when given (which is then returned whole)."""
        p_in, bs, etas, p_out = self.unpack(theta)
        N = u.shape[0]
        s_in, s_lin, s_out = self.slices()
        vd = [self._input(i, u, p_in[i], jac) for i in range(self.nu)]
        v = [x[0] for x in vd]
        dps = [x[1] for x in vd]
        Y = np.empty((N, self.ny))
        J = None
        if jac:
            if out is None:
                out = np.zeros((self.ny * N, self.n_theta()))
            else:
                out[:self.ny * N] = 0.0
            J = out[:self.ny * N].reshape(self.ny, N, self.n_theta())
        for j in range(self.ny):
            w = np.zeros(N)
            for i in range(self.nu):
                wi, num, f, gain, v0 = self._filter(bs[j][i], etas[j][i], j, i, v[i])
                w += wi
                if not jac:
                    continue
                assert J is not None
                Jj = J[j]
                if dps[i] is not None:
                    dp = dps[i]
                    dp0 = dp[:1] if self.steady else np.zeros((1, dp.shape[1]))
                    Jj[:, s_in[i]] = lfilter(num, f, (dp - dp0).T, axis=-1).T + gain * dp0
                self._linear_columns(Jj[:, s_lin[j][i]], bs[j][i], etas[j][i], j, i, v[i], wi, f, gain, v0)
            blk = self.outs[j]
            Y[:, j] = blk.value(w, p_out[j])
            if jac:
                assert J is not None
                J[j] *= blk.dx(w, p_out[j])[:, None]   # only input and pair (j, .) columns are non-zero so far
                if blk.n_free():
                    J[j][:, s_out[j]] = blk.dp(w, p_out[j])
        return Y, out

    def _linear_columns(self, out: np.ndarray, b: np.ndarray, eta: np.ndarray, j: int, i: int, v: np.ndarray,
                        wi: np.ndarray, f: np.ndarray, gain: float, v0: float) -> None:
        """Fill ``out`` (N, n_lin(j, i)) with d w_j / d (b free, eta) of pair (j, i)."""
        nb, nf, nk = int(self.nb[j, i]), int(self.nf[j, i]), int(self.nk[j, i])
        f_sum = max(float(np.sum(f)), 1e-12)
        _, df_dk = poly_from_reflection(np.tanh(eta))
        vf = lfilter([1.0], f, v - v0)
        N = len(vf)
        g = self.gain[j, i]
        n_db = nb - int(np.isfinite(g))
        for k in range(n_db):
            d = nk + k
            out[d:, k] = vf[:N - d] if d < N else 0.0
        if v0:
            out[:, :n_db] += v0 / f_sum
        last = None
        if np.isfinite(g):   # b_last = g F(1) - sum(other b): chain its column into the free ones
            last = shift(vf, nk + nb - 1) + v0 / f_sum
            out[:, :n_db] -= last[:, None]
        if nf:
            wf = lfilter([1.0], f, wi - gain * v0)   # the filtered part (the steady offset: below)
            dw_df = np.zeros((len(wf), nf))
            for k in range(1, nf + 1):
                dw_df[k:, k - 1] = -wf[:len(wf) - k]
            if v0:
                dw_df -= gain * v0 / f_sum       # d(G v0)/df_k, dF(1)/df_k = 1
            d_eta = dw_df @ df_dk[1:]
            if last is not None:
                d_eta = d_eta + last[:, None] * (g * df_dk.sum(axis=0))[None, :]
            out[:, n_db:] = d_eta * (1.0 - np.tanh(eta) ** 2)
