"""Excitation signals for identification experiments, all seeded and with amplitude and spectrum control.

Every generator is a small frozen dataclass whose constructor stores the design (levels, bandwidth, hold times)
and whose ``generate(n_samples, dt, seed=None) -> np.ndarray`` returns a 1-D signal of ``n_samples`` values at
sample time ``dt`` seconds. The same design and seed give the same signal. :func:`generate_multichannel` stacks
several generators into an ``(n_samples, n_channels)`` array with independent, reproducible seeds, which is what a
plant-data rollout uses to perturb a base dosing policy.

Signals are zero-order held between their switching instants, which is the input the midpoint discretisation of
the RPEM models assumes (ALGORITHMS.md, section 1).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

__all__ = ["GBN", "PRBS", "ExcitationSignal", "Multisine", "RandomSteps", "crest_factor", "generate_multichannel"]


class ExcitationSignal(Protocol):
    """Anything with ``generate(n_samples, dt, seed) -> ndarray`` of shape (n_samples,)."""

    def generate(self, n_samples: int, dt: float, seed: int | np.random.SeedSequence | None = None) -> np.ndarray:
        ...


def _check(n_samples: int, dt: float) -> None:
    if int(n_samples) != n_samples or n_samples < 1:
        raise ValueError(f"n_samples must be a positive integer, got {n_samples}")
    if not np.isfinite(dt) or dt <= 0:
        raise ValueError(f"dt must be a positive sample time in seconds, got {dt}")


def _hold_samples(hold_s: float, dt: float, what: str) -> int:
    k = round(hold_s / dt)
    if k < 1:
        raise ValueError(f"{what} = {hold_s} s is shorter than the sample time {dt} s")
    return k


# Feedback taps (1-based) of maximum-length Fibonacci LFSRs, order -> taps (period 2**order - 1).
_LFSR_TAPS = {2: (2, 1), 3: (3, 2), 4: (4, 3), 5: (5, 3), 6: (6, 5), 7: (7, 6), 8: (8, 6, 5, 4), 9: (9, 5),
              10: (10, 7), 11: (11, 9), 12: (12, 11, 10, 4), 13: (13, 12, 11, 8), 14: (14, 13, 12, 2),
              15: (15, 14), 16: (16, 15, 13, 4), 17: (17, 14), 18: (18, 11)}


@dataclass(frozen=True)
class PRBS:
    """Maximum-length pseudo-random binary sequence between two levels.

    The spectrum is flat up to about ``0.44 / clock_period_s`` Hz (first null at ``1 / clock_period_s``), so the
    clock period sets the bandwidth. The seed selects the LFSR's initial register (i.e. a circular shift of the
    sequence).

    Parameters
    ----------
    low, high : float
        The two levels, in the units of the signal.
    clock_period_s : float
        Minimum hold time between possible switches, seconds (a multiple of ``dt`` after rounding).
    order : int
        LFSR order 2..18; the sequence repeats every ``2**order - 1`` clock periods.
    """

    low: float = -1.0
    high: float = 1.0
    clock_period_s: float = 1.0
    order: int = 10

    def generate(self, n_samples: int, dt: float, seed: int | np.random.SeedSequence | None = None) -> np.ndarray:
        _check(n_samples, dt)
        if self.order not in _LFSR_TAPS:
            raise ValueError(f"PRBS order must be in {min(_LFSR_TAPS)}..{max(_LFSR_TAPS)}, got {self.order}")
        hold = _hold_samples(self.clock_period_s, dt, "clock_period_s")
        rng = np.random.default_rng(seed)
        reg = rng.integers(0, 2, size=self.order)
        if not reg.any():  # the all-zero register is the one state that does not cycle
            reg[0] = 1
        taps = np.array(_LFSR_TAPS[self.order]) - 1
        n_bits = -(-n_samples // hold)
        bits = np.empty(n_bits, dtype=bool)
        reg = list(reg)
        for i in range(n_bits):
            bits[i] = reg[-1]
            new = 0
            for t in taps:
                new ^= reg[t]
            reg = [new] + reg[:-1]
        out = np.where(np.repeat(bits, hold)[:n_samples], self.high, self.low)
        return out.astype(float)


@dataclass(frozen=True)
class GBN:
    """Generalised binary noise: a binary signal that switches level with probability ``dt / mean_hold_s`` per
    sample (Tulleken 1990), so hold times are geometric with mean ``mean_hold_s``; the power sits mostly below
    ``1 / (2 pi mean_hold_s)`` Hz. Better than a PRBS for slow processes with long data.

    Parameters
    ----------
    low, high : float
        The two levels.
    mean_hold_s : float
        Mean time between switches, seconds (>= dt).
    """

    low: float = -1.0
    high: float = 1.0
    mean_hold_s: float = 5.0

    def generate(self, n_samples: int, dt: float, seed: int | np.random.SeedSequence | None = None) -> np.ndarray:
        _check(n_samples, dt)
        if self.mean_hold_s < dt:
            raise ValueError(f"mean_hold_s = {self.mean_hold_s} s is shorter than the sample time {dt} s")
        rng = np.random.default_rng(seed)
        p_switch = dt / self.mean_hold_s
        switches = rng.random(n_samples) < p_switch
        switches[0] = False
        state = (np.cumsum(switches) + rng.integers(0, 2)) % 2
        return np.where(state == 1, self.high, self.low).astype(float)


@dataclass(frozen=True)
class RandomSteps:
    """Piecewise-constant signal with uniformly random levels and uniformly random hold times (multi-level: it
    excites the nonlinearity at more than two amplitudes, unlike a binary signal).

    Parameters
    ----------
    low, high : float
        Range of the levels.
    min_hold_s, max_hold_s : float
        Range of the hold times, seconds.
    n_levels : int, optional
        If given, levels are drawn from ``n_levels`` equally spaced values in [low, high] instead of continuously.
    """

    low: float = -1.0
    high: float = 1.0
    min_hold_s: float = 1.0
    max_hold_s: float = 10.0
    n_levels: int | None = None

    def generate(self, n_samples: int, dt: float, seed: int | np.random.SeedSequence | None = None) -> np.ndarray:
        _check(n_samples, dt)
        kmin = _hold_samples(self.min_hold_s, dt, "min_hold_s")
        kmax = max(kmin, round(self.max_hold_s / dt))
        if self.high < self.low:
            raise ValueError(f"high ({self.high}) must be >= low ({self.low})")
        rng = np.random.default_rng(seed)
        out = np.empty(n_samples)
        i = 0
        while i < n_samples:
            k = int(rng.integers(kmin, kmax + 1))
            if self.n_levels is not None:
                level = np.linspace(self.low, self.high, self.n_levels)[rng.integers(0, self.n_levels)]
            else:
                level = rng.uniform(self.low, self.high)
            out[i:i + k] = level
            i += k
        return out


@dataclass(frozen=True)
class Multisine:
    """Sum of sinusoids on a frequency grid with chosen band and RMS value.

    Frequencies are the multiples of ``1 / (n_samples dt)`` (so the signal is periodic over the record and
    leakage-free) that fall in ``[f_min_hz, f_max_hz]``, optionally every ``skip``-th one (odd-multisine style
    gaps reveal nonlinear distortion). Equal amplitudes give a flat spectrum in the band.

    Parameters
    ----------
    rms : float
        RMS value of the (zero-mean) signal.
    f_min_hz, f_max_hz : float
        Excited band, Hz; ``f_max_hz`` defaults to the Nyquist frequency ``1 / (2 dt)``.
    offset : float
        Constant added to the signal (the operating point).
    phases : {"schroeder", "random"}
        Schroeder phases give a low crest factor deterministically; random phases use the seed.
    skip : int
        Keep every ``skip``-th grid frequency (1: all).
    """

    rms: float = 1.0
    f_min_hz: float = 0.0
    f_max_hz: float | None = None
    offset: float = 0.0
    phases: Literal["schroeder", "random"] = "schroeder"
    skip: int = 1

    def frequencies(self, n_samples: int, dt: float) -> np.ndarray:
        """The excited frequencies in Hz for this record length and sample time."""
        _check(n_samples, dt)
        df = 1.0 / (n_samples * dt)
        f_max = 0.5 / dt if self.f_max_hz is None else min(self.f_max_hz, 0.5 / dt)
        k = np.arange(1, n_samples // 2 + 1)
        f = k * df
        f = f[(f >= max(self.f_min_hz, df)) & (f <= f_max * (1 + 1e-12))]
        f = f[:: max(1, int(self.skip))]
        if f.size == 0:
            raise ValueError(f"no frequency of the 1/({n_samples} * {dt}) s grid lies in [{self.f_min_hz}, "
                             f"{f_max}] Hz: widen the band or lengthen the record")
        return f

    def generate(self, n_samples: int, dt: float, seed: int | np.random.SeedSequence | None = None) -> np.ndarray:
        f = self.frequencies(n_samples, dt)
        k = np.arange(1, f.size + 1)
        if self.phases == "schroeder":
            phi = -np.pi * k * (k - 1) / f.size
        elif self.phases == "random":
            phi = np.random.default_rng(seed).uniform(0, 2 * np.pi, f.size)
        else:
            raise ValueError(f"phases must be 'schroeder' or 'random', got {self.phases!r}")
        t = dt * np.arange(n_samples)
        x = np.cos(2 * np.pi * np.outer(t, f) + phi).sum(axis=1)
        x_rms = np.sqrt(np.mean(x**2))
        return self.offset + self.rms * x / x_rms


def crest_factor(x: np.ndarray) -> float:
    """Peak over RMS of the zero-mean part of ``x`` (sqrt(2) for a sine, 1 for a binary signal)."""
    x = np.asarray(x, dtype=float) - np.mean(x)
    return float(np.max(np.abs(x)) / np.sqrt(np.mean(x**2)))


def generate_multichannel(signals: list[ExcitationSignal], n_samples: int, dt: float,
                          seed: int | None = None) -> np.ndarray:
    """Stack several generators into shape (n_samples, len(signals)) with independent child seeds.

    Child seeds come from ``numpy.random.SeedSequence(seed).spawn``, so channel ``i`` is the same whatever the other
    channels are.
    """
    children = np.random.SeedSequence(seed).spawn(len(signals))
    return np.column_stack([s.generate(n_samples, dt, seed=c) for s, c in zip(signals, children, strict=False)])
