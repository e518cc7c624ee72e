"""Identification data from the SCR simulator.

* :func:`whtc_dataset`: PLACEHOLDER until the ``scr_env`` rollout exists (the environment owner fills it in).
* :func:`synthetic_scr_dataset`: a small hand-written SCR-like surrogate (NH3 coverage state, Arrhenius-type
  temperature dependence, flow-dependent residence time) used to develop and test the identification code
  meanwhile. It is *not* the project's simulator and its figures must not be reported as such.

Signals, in Paper III/IV's order: inputs inlet NOx, urea (AdBlue) dosing, inlet temperature (K), exhaust flow;
outputs tailpipe NOx (the environment adds NH3 slip and the cross-sensitive NOx sensor reading). The surrogate's
units are in :data:`INPUT_UNITS`; the environment's rollout sets its own names and units in the data set.
"""
from __future__ import annotations

import numpy as np

from ident.dataset import IODataset
from ident.excitation import GBN, RandomSteps

#: Paper IV's protocol: 1200 samples at 0.5 s, first 900 for estimation.
PAPER4_N_SAMPLES = 1200
PAPER4_DT_S = 0.5
PAPER4_N_ESTIMATION = 900

INPUT_NAMES = ("inlet_nox_ppm", "urea_dosing_ml_h", "inlet_temperature_k", "exhaust_flow_kg_s")
INPUT_UNITS = ("ppm", "ml/h", "K", "kg/s")


def whtc_dataset(seed: int = 0) -> IODataset:
    """Paper IV's data set from the environment: a WHTC segment of 1200 samples at Ts = 0.5 s.

    To be written by the ``scr_env`` owner: roll the environment out over the WHTC under a base dosing policy plus
    excitation (e.g. ``ident.excitation.RandomSteps`` / ``GBN`` on the dosing command, generated with
    ``generate(n_samples, dt, seed)``), and return an :class:`~ident.dataset.IODataset` with inputs
    ``(inlet NOx, urea/AdBlue dosing, inlet temperature [K], exhaust flow)`` and outputs
    ``(tailpipe NOx, NH3 slip, NOx sensor reading)``, names and units set, ``meta`` recording cycle, segment,
    policy and seed.
    """
    # PLACEHOLDER: needs the scr_env rollout (ident issue 4 leaves this to the environment owner).
    raise NotImplementedError("needs scr_env rollout")


def synthetic_scr_dataset(seed: int = 0, n_samples: int = PAPER4_N_SAMPLES, dt: float = PAPER4_DT_S,
                          noise_ppm: float = 2.0) -> IODataset:
    """An SCR-like surrogate data set for developing identification code (not the project's simulator).

    Model (explicit Euler at ``dt``): NH3 coverage ``theta`` in [0, 1] fills with dosing and empties by reaction and
    desorption; NOx conversion ``eta = 1 - exp(-k(T) theta tau)`` with ``k(T) ~ exp(-E/T)`` and residence time
    ``tau ~ 1 / flow``; a first-order sensor lag on the tailpipe NOx. Inputs are WHTC-like random steps.

    Returns
    -------
    IODataset
        Inputs as :data:`INPUT_NAMES`; one output ``tailpipe_nox_ppm``.
    """
    ss = np.random.SeedSequence(seed)
    s = ss.spawn(6)
    load = RandomSteps(0.0, 1.0, 2.0, 20.0).generate(n_samples, dt, s[0])
    # engine-out NOx, temperature and flow follow the load with their own lags and noise-like variations
    nox_in = 150 + 700 * load + 60 * GBN(-1, 1, 4.0).generate(n_samples, dt, s[1])
    temp_target = 480 + 160 * load
    flow = 0.05 + 0.25 * load + 0.02 * GBN(-1, 1, 3.0).generate(n_samples, dt, s[2])
    dosing = np.clip(RandomSteps(0.0, 1.0, 2.0, 15.0).generate(n_samples, dt, s[3]) * (0.4 + load), 0, None)
    rng = np.random.default_rng(s[4])
    temp = np.empty(n_samples)
    theta = np.empty(n_samples)
    y_true = np.empty(n_samples)
    T, th, y_s = float(temp_target[0]), 0.3, 0.0
    for t in range(n_samples):
        T += dt / 20.0 * (temp_target[t] - T)  # exhaust thermal lag ~ 20 s
        k = 2.0e5 * np.exp(-4500.0 / T)
        tau = 0.02 / flow[t]
        eta = 1.0 - np.exp(-k * th * tau)
        consumed = 2e-4 * eta * nox_in[t] * flow[t] * 10
        desorb = 1e-3 * th * np.exp(-(700.0 - T) / 60.0)
        th = float(np.clip(th + dt * (0.3 * dosing[t] * (1 - th) - consumed - desorb), 0.0, 1.0))
        nox_out = nox_in[t] * (1.0 - eta)
        y_s += dt / 1.5 * (nox_out - y_s)  # sensor lag ~ 1.5 s
        temp[t], theta[t], y_true[t] = T, th, y_s
    y = y_true + noise_ppm * rng.standard_normal(n_samples)
    u = np.column_stack([nox_in, dosing * 100.0, temp, flow])
    return IODataset(u=u, y=y, dt=dt, input_names=INPUT_NAMES, output_names=("tailpipe_nox_ppm",),
                     input_units=INPUT_UNITS, output_units=("ppm",),
                     meta={"source": "ident.plant_data.synthetic_scr_dataset (surrogate, not scr_env)",
                           "seed": seed})
