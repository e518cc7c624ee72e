"""Seeded simulators of the kinds of system the public nonlinear benchmarks hold (nonlinearbenchmark.org).

The measured benchmark files are not ours to ship (only the Wiener-Hammerstein benchmark is, in
``ident/data/benchmarks``), so the estimators are tested on simulated systems *of the same kind*: the same
structure, sampling period, excitation and record lengths as the public data sets, with parameters of our own choice
(stated below; they are not fitted to the measurements). Each simulator integrates the continuous-time system finely
(classical Runge-Kutta, several sub-steps per sample, input known between samples), adds measurement noise and
returns a :class:`SimulatedBenchmark`: an estimation and a validation :class:`~ident.dataset.IODataset` (different
input realisations) and the sampling period.

================================  ======================================================================================
function                          system (benchmark of the same kind)
================================  ======================================================================================
:func:`duffing_oscillator`        ``m y'' + d y' + k1 y + k3 y^3 = u``, band-limited random-phase odd multisine input,
                                  fs = 610.35 Hz (the Silverbox electronic Duffing oscillator, Wigren and Schoukens
                                  2013)
:func:`cascaded_tanks`            two tanks in cascade, Torricelli outflows, the upper tank overflowing into the
                                  lower one; pump voltage zero-order held, T = 4 s, 1024 samples per record (Cascaded
                                  Tanks, Schoukens, Mattson, Wigren and Noel 2016)
:func:`coupled_drives`            third-order drive (belt resonance and motor lag) whose pulse-counter speed sensor
                                  ignores the sign, ``y = |v|``; PRBS voltage input, T = 20 ms (Coupled Electric
                                  Drives, Wigren and Schoukens 2017)
================================  ======================================================================================

Every function takes ``seed`` (one integer gives the whole data set: inputs and noise) and the record lengths; the
same arguments give the same arrays bit for bit. The estimation and validation inputs are independent realisations of
the same excitation design, as in the public data sets. ``SIMULATED_BENCHMARKS`` maps a short name to each function.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numba import njit

from ident.base import check_positive_int
from ident.dataset import IODataset

__all__ = [
    "SIMULATED_BENCHMARKS",
    "SimulatedBenchmark",
    "cascaded_tanks",
    "coupled_drives",
    "duffing_oscillator",
    "simulated_benchmark",
]


@dataclass(frozen=True)
class SimulatedBenchmark:
    """An estimation and a validation record of one simulated system.

    Attributes
    ----------
    name : str
        Short name (a key of :data:`SIMULATED_BENCHMARKS`).
    estimation, validation : IODataset
        The two records (independent input realisations, the same system and noise level).
    sampling_period : float
        Sampling period T in seconds (also ``estimation.dt``).
    description : str
        One line saying what the system is.
    meta : dict
        The true system parameters, the excitation, the seed and the noise level.
    """

    name: str
    estimation: IODataset
    validation: IODataset
    sampling_period: float
    description: str
    meta: dict[str, Any] = field(default_factory=dict)


def _rk4(rhs: Callable[[np.ndarray, float, float], np.ndarray], x0: np.ndarray, u_fine: np.ndarray, h: float,
         n_sub: int, project: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """Integrate ``dx/dt = rhs(x, u, t)`` with ``n_sub`` RK4 sub-steps of ``h`` per sample.

    ``u_fine`` holds the input on the half-sub-step grid: ``u_fine[2 * k]`` at the start of sub-step k and
    ``u_fine[2 * k + 1]`` at its middle (length ``2 * n_steps + 1``). Returns the state at every sample
    (``n_steps / n_sub + 1`` rows, the first one ``x0``). ``project`` maps a state back into its admissible set
    after every sub-step (the tank overflow).
    """
    n_steps = (len(u_fine) - 1) // 2
    n_samples = n_steps // n_sub
    out = np.empty((n_samples + 1, len(x0)))
    x = np.array(x0, dtype=float)
    out[0] = x
    for k in range(n_steps):
        ua, um, ub = u_fine[2 * k], u_fine[2 * k + 1], u_fine[2 * k + 2]
        k1 = rhs(x, ua)
        k2 = rhs(x + 0.5 * h * k1, um)
        k3 = rhs(x + 0.5 * h * k2, um)
        k4 = rhs(x + h * k3, ub)
        x = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        if project is not None:
            x = project(x)
        if (k + 1) % n_sub == 0:
            out[(k + 1) // n_sub] = x
    return out


def _periodic_multisine(rng: np.random.Generator, n_samples: int, dt: float, f_max_hz: float, rms: float,
                        oversample: int, odd: bool) -> tuple[np.ndarray, np.ndarray]:
    """A random-phase multisine of period ``n_samples dt`` with flat amplitude up to ``f_max_hz``.

    Returns the signal at the samples and on a grid ``oversample`` times finer (the exact band-limited signal
    between samples: the spectrum is zero above ``f_max_hz``, so the fine grid is its inverse FFT).
    """
    n_lines = n_samples // 2
    k = np.arange(1, n_lines + 1)
    f = k / (n_samples * dt)
    excited = f <= f_max_hz
    if odd:
        excited &= (k % 2) == 1
    spectrum = np.zeros(n_samples * oversample // 2 + 1, dtype=complex)
    phases = rng.uniform(0.0, 2.0 * np.pi, int(excited.sum()))
    spectrum[k[excited]] = np.exp(1j * phases)
    fine = np.fft.irfft(spectrum, n=n_samples * oversample)
    scale = rms / np.sqrt(np.mean(fine[::oversample] ** 2))
    fine = fine * scale
    return fine[::oversample].copy(), fine


def _check_lengths(n_estimation: int, n_validation: int, minimum: int) -> tuple[int, int]:
    ne = check_positive_int("n_estimation", n_estimation, minimum=minimum, what="samples")
    nv = check_positive_int("n_validation", n_validation, minimum=minimum, what="samples")
    return ne, nv


# ------------------------------------------------------------------------------------------ Duffing oscillator
#: Duffing oscillator parameters (chosen to resemble the Silverbox: a lightly damped electronic resonator near
#: 60 Hz with a hardening cubic spring; y and u in volts, time in seconds).
DUFFING_PARAMETERS = {"natural_frequency_hz": 60.0, "damping_ratio": 0.05, "cubic_stiffness_per_v2": 4.0,
                      "input_rms_v": 0.04, "f_max_hz": 200.0, "noise_sd_v": 2e-4}
SILVERBOX_SAMPLING_PERIOD_S = 2.0**14 / 1.0e7  # 1.6384 ms: fs = 10 MHz / 2^14 = 610.35 Hz (Silverbox)


@njit(cache=True)
def _duffing_rk4(u_fine: np.ndarray, h: float, n_sub: int, w0: float, zeta: float, c: float) -> np.ndarray:
    """:func:`_rk4` for the Duffing oscillator, compiled (its records are long); returns the states at samples."""
    n_steps = (len(u_fine) - 1) // 2
    out = np.empty((n_steps // n_sub + 1, 2))
    x, v = 0.0, 0.0
    out[0, 0], out[0, 1] = x, v
    w2, dmp = w0 * w0, 2.0 * zeta * w0
    for k in range(n_steps):
        ua, um, ub = u_fine[2 * k], u_fine[2 * k + 1], u_fine[2 * k + 2]
        a1 = w2 * (ua - x - c * x**3) - dmp * v
        x2, v2 = x + 0.5 * h * v, v + 0.5 * h * a1
        a2 = w2 * (um - x2 - c * x2**3) - dmp * v2
        x3, v3 = x + 0.5 * h * v2, v + 0.5 * h * a2
        a3 = w2 * (um - x3 - c * x3**3) - dmp * v3
        x4, v4 = x + h * v3, v + h * a3
        a4 = w2 * (ub - x4 - c * x4**3) - dmp * v4
        x = x + (h / 6.0) * (v + 2.0 * v2 + 2.0 * v3 + v4)
        v = v + (h / 6.0) * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
        if (k + 1) % n_sub == 0:
            out[(k + 1) // n_sub, 0], out[(k + 1) // n_sub, 1] = x, v
    return out


def duffing_oscillator(seed: int = 0, n_estimation: int = 16384, n_validation: int = 8192) -> SimulatedBenchmark:
    """A Duffing oscillator excited by a band-limited random-phase odd multisine (Silverbox-like).

    ``y'' + 2 zeta w0 y' + w0^2 (y + c y^3) = w0^2 u`` with ``w0 = 2 pi 60 rad/s``, ``zeta = 0.05`` and
    ``c = 4 V^-2`` (:data:`DUFFING_PARAMETERS`): unit static gain, a resonance near 60 Hz that hardens with the
    amplitude. The input is an odd random-phase multisine (every odd line of the record's frequency grid up to
    200 Hz, RMS 40 mV), one period per record, applied in steady state (one period is run before the record);
    between samples it is the exact band-limited signal, so *interpolating* the input at a half step is right
    here and holding it is wrong. Output: ``y`` plus white noise of 0.2 mV SD. Sampling period 1.6384 ms
    (610.35 Hz, the Silverbox's). Each record is one period of its own multisine realisation.
    """
    ne, nv = _check_lengths(n_estimation, n_validation, 16)
    p = DUFFING_PARAMETERS
    dt = SILVERBOX_SAMPLING_PERIOD_S
    w0 = 2.0 * np.pi * p["natural_frequency_hz"]
    zeta, c = p["damping_ratio"], p["cubic_stiffness_per_v2"]
    n_sub = 8
    rng = np.random.default_rng(seed)

    records = []
    for n in (ne, nv):
        u, fine = _periodic_multisine(rng, n, dt, p["f_max_hz"], p["input_rms_v"], 2 * n_sub, odd=True)
        # two periods back to back: the first settles the transient, the second is the (steady-state) record
        u_fine = np.concatenate([fine, fine, fine[:1]])
        x = _duffing_rk4(u_fine, dt / n_sub, n_sub, w0, zeta, c)[n:2 * n]
        y = x[:, 0] + p["noise_sd_v"] * rng.standard_normal(n)
        records.append(IODataset(u=u, y=y, dt=dt, input_names=("u",), output_names=("y",), input_units=("V",),
                                 output_units=("V",), meta={"system": "duffing_oscillator", "seed": seed}))
    return SimulatedBenchmark("duffing_oscillator", records[0], records[1], dt,
                              "Duffing oscillator (hardening cubic spring) under a band-limited odd multisine",
                              {"parameters": dict(p), "sampling_period_s": dt, "seed": seed,
                               "input": "odd random-phase multisine, one period per record, steady state"})


# --------------------------------------------------------------------------------------------- cascaded tanks
#: Cascaded tanks (levels in V of the level sensors, 0..10 V; flows per unit of pump voltage; time in s). The
#: upper tank overflows at 10 V and part of the overflow falls into the lower tank (the benchmark's hard
#: nonlinearity); the Torricelli outflows are its soft nonlinearity.
TANKS_PARAMETERS = {"k1": 0.055, "k2": 0.05, "k3": 0.06, "k4": 0.03, "overflow_to_lower": 0.5, "level_max_v": 10.0,
                    "input_mean_v": 5.5, "input_rms_v": 1.2, "f_max_hz": 0.0144, "noise_sd_v": 0.02}
TANKS_SAMPLING_PERIOD_S = 4.0


def cascaded_tanks(seed: int = 0, n_estimation: int = 1024, n_validation: int = 1024) -> SimulatedBenchmark:
    """Two water tanks in cascade with overflow (Cascaded Tanks benchmark-like).

    ``dh1/dt = -k1 sqrt(h1) + k4 u``, ``dh2/dt = k2 sqrt(h1) - k3 sqrt(h2) + rho q_over``, ``y = h2 + e``, levels
    in volts of the level sensors (0..10 V). When the upper tank is full (h1 = 10 V) it overflows: its level stays
    at 10 V and the fraction ``rho = 0.5`` of the excess inflow falls into the lower tank (which also overflows at
    10 V). Parameters in :data:`TANKS_PARAMETERS`. The pump voltage ``u`` is a random-phase multisine up to
    0.0144 Hz around 5.5 V (RMS 1.2 V), *zero-order held* over each 4 s sample (a DAC), so holding the input at a
    half step is right here. Both records start from the same state, the equilibrium at the mean input, as the
    benchmark's records start from one unknown state. Measurement noise 20 mV SD. 1024 samples per record.
    """
    ne, nv = _check_lengths(n_estimation, n_validation, 16)
    p = TANKS_PARAMETERS
    dt = TANKS_SAMPLING_PERIOD_S
    k1, k2, k3, k4, rho, hmax = (p[k] for k in ("k1", "k2", "k3", "k4", "overflow_to_lower", "level_max_v"))
    n_sub = 8
    rng = np.random.default_rng(seed)

    def rhs(x: np.ndarray, u: float) -> np.ndarray:
        s1, s2 = np.sqrt(max(x[0], 0.0)), np.sqrt(max(x[1], 0.0))
        inflow = k4 * max(u, 0.0)
        d1 = inflow - k1 * s1
        over = 0.0
        if x[0] >= hmax and d1 > 0.0:
            over, d1 = d1, 0.0
        return np.array([d1, k2 * s1 - k3 * s2 + rho * over])

    def project(x: np.ndarray) -> np.ndarray:
        return np.clip(x, 0.0, hmax)

    h1_eq = min((k4 * p["input_mean_v"] / k1) ** 2, hmax)
    x0 = np.array([h1_eq, min((k2 / k3) ** 2 * h1_eq, hmax)])
    records = []
    for n in (ne, nv):
        u, _ = _periodic_multisine(rng, n, dt, p["f_max_hz"], p["input_rms_v"], 1, odd=False)
        u = np.clip(u + p["input_mean_v"], 0.0, 10.0)
        u_fine = np.concatenate([np.repeat(u, 2 * n_sub), u[-1:]])  # zero-order hold between samples
        x = _rk4(rhs, x0, u_fine, dt / n_sub, n_sub, project)[:n]
        y = x[:, 1] + p["noise_sd_v"] * rng.standard_normal(n)
        records.append(IODataset(u=u, y=y, dt=dt, input_names=("pump",), output_names=("level",),
                                 input_units=("V",), output_units=("V",),
                                 meta={"system": "cascaded_tanks", "seed": seed,
                                       "overflow_fraction": float(np.mean(x[:, 0] >= hmax - 1e-9))}))
    return SimulatedBenchmark("cascaded_tanks", records[0], records[1], dt,
                              "two cascaded tanks with Torricelli outflows and overflow of the upper tank",
                              {"parameters": dict(p), "sampling_period_s": dt, "seed": seed,
                               "initial_state_v": x0.tolist(),
                               "input": "random-phase multisine, zero-order hold"})


# ------------------------------------------------------------------------------------- coupled electric drives
#: Drive with a belt resonance and a motor lag; speed in m/s of the belt at the pulley, input in V.
DRIVES_PARAMETERS = {"gain_m_s_per_v": 1.8, "resonance_hz": 1.8, "damping_ratio": 0.25, "motor_time_constant_s": 0.15,
                     "input_amplitude_v": 1.0, "clock_samples": 4, "noise_sd_m_s": 0.02}
DRIVES_SAMPLING_PERIOD_S = 0.02


def coupled_drives(seed: int = 0, n_estimation: int = 2000, n_validation: int = 1000) -> SimulatedBenchmark:
    """A drive whose speed sensor ignores the sign (Coupled Electric Drives-like): ``y = |v| + e``.

    The belt speed ``v`` follows the input voltage through a motor lag and a belt resonance,
    ``V(s) / U(s) = K w^2 / ((s^2 + 2 zeta w s + w^2)(tau s + 1))`` with ``K = 1.8 m/s/V``, ``w = 2 pi 1.8 rad/s``,
    ``zeta = 0.25`` and ``tau = 0.15 s`` (:data:`DRIVES_PARAMETERS`). The pulse-counter sensor measures the speed
    without its sign, the benchmark's static output nonlinearity, which makes every linear model useless. Input: a
    zero-mean PRBS of +-1 V with a clock of 4 samples, zero-order held over each 20 ms sample. Noise 0.02 m/s SD.
    The public data sets hold 500 samples per record; these records are longer by default (2000 for estimation,
    1000 for validation) so that a recursive estimator sees the resonance often enough: pass ``n_estimation=300,
    n_validation=200`` for the public split's size.
    """
    ne, nv = _check_lengths(n_estimation, n_validation, 16)
    p = DRIVES_PARAMETERS
    dt = DRIVES_SAMPLING_PERIOD_S
    K, w = p["gain_m_s_per_v"], 2.0 * np.pi * p["resonance_hz"]
    zeta, tau = p["damping_ratio"], p["motor_time_constant_s"]
    n_sub = 8
    rng = np.random.default_rng(seed)

    def rhs(x: np.ndarray, u: float) -> np.ndarray:
        # x = (motor torque state m, speed v, dv/dt a): tau m' = K u - m; v'' + 2 zeta w v' + w^2 v = w^2 m
        return np.array([(K * u - x[0]) / tau, x[2], w * w * (x[0] - x[1]) - 2.0 * zeta * w * x[2]])

    from ident.excitation import PRBS

    amp = p["input_amplitude_v"]
    prbs = PRBS(low=-amp, high=amp, clock_period_s=p["clock_samples"] * dt, order=12)
    records = []
    for n in (ne, nv):
        u = prbs.generate(n, dt, seed=int(rng.integers(2**31)))
        u_fine = np.concatenate([np.repeat(u, 2 * n_sub), u[-1:]])
        x = _rk4(rhs, np.zeros(3), u_fine, dt / n_sub, n_sub)[:n]
        y = np.abs(x[:, 1]) + p["noise_sd_m_s"] * rng.standard_normal(n)
        records.append(IODataset(u=u, y=y, dt=dt, input_names=("voltage",), output_names=("speed",),
                                 input_units=("V",), output_units=("m/s",),
                                 meta={"system": "coupled_drives", "seed": seed}))
    return SimulatedBenchmark("coupled_drives", records[0], records[1], dt,
                              "drive with a belt resonance; the speed sensor ignores the sign (y = |v|)",
                              {"parameters": dict(p), "sampling_period_s": dt, "seed": seed,
                               "input": "zero-mean PRBS, zero-order hold"})


SIMULATED_BENCHMARKS: dict[str, Callable[..., SimulatedBenchmark]] = {
    "duffing_oscillator": duffing_oscillator,
    "cascaded_tanks": cascaded_tanks,
    "coupled_drives": coupled_drives,
}


def simulated_benchmark(name: str, seed: int = 0, **lengths: int) -> SimulatedBenchmark:
    """The simulated benchmark ``name`` (a key of :data:`SIMULATED_BENCHMARKS`) with ``seed``; ``lengths`` are
    ``n_estimation`` / ``n_validation``."""
    if name not in SIMULATED_BENCHMARKS:
        raise ValueError(f"unknown simulated benchmark {name!r}; known: {sorted(SIMULATED_BENCHMARKS)}")
    return SIMULATED_BENCHMARKS[name](seed=seed, **lengths)
