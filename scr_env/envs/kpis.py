"""The reward and the episode KPIs, defined once for every environment of the project.

:func:`account_step` is the one definition of what a control step costs and of what an episode accumulates (grams
of tailpipe NOx as NO2, NH3, N2O and AdBlue, ppm-seconds of slip, engine work, the nitrogen balance); it is inlined
into the compiled plant step (:mod:`scr_env.envs.core`), and :func:`account_batch` runs it for environments that
step another model, such as the identified-model surrogates of :mod:`control.rl.surrogate`. :func:`episode_kpis`
turns an accumulator row into the KPIs of PHYSICS.md section 7.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from scr_env.constants import N2O_MOLAR_MASS_G_MOL, NH3_MOLAR_MASS_G_MOL, NO2_MOLAR_MASS_G_MOL
from scr_env.jit import njit
from scr_env.physics.backends import FASTMATH
from scr_env.physics.kernel import (
    I_ADBLUE,
    I_FLOW,
    I_NOX,
    O_N2,
    O_N2O,
    O_NH3,
    O_NH3_INJ,
    O_NO,
    O_NO2,
    O_UREA_N,
)

__all__ = ["N_ACC", "REWARD_TERMS", "RewardWeights", "account_batch", "account_command", "account_commands",
           "account_step", "episode_kpis"]

# reward terms, in the order of the ``terms`` array and of ``info``
REWARD_TERMS = ("nox_cost", "nh3_cost", "adblue_cost")
N_TERMS = len(REWARD_TERMS)

# episode accumulators (per plant), the columns of an accumulator row
# (the last four: total variation [g/s] of the delivered and the commanded AdBlue rate, and their last values)
(A_ENGINE_NOX_G, A_TAILPIPE_NOX_G, A_NH3_PPM_S, A_NH3_PEAK_PPM, A_ADBLUE_G, A_TIME_S, A_WORK_KWH, A_N_IN_MOL,
 A_N_OUT_MOL, A_STORED0_MOL, A_NH3_G, A_N2O_G, A_UREA_N_MOL, A_STEPS, A_ADBLUE_TV, A_ADBLUE_LAST, A_COMMAND_TV,
 A_COMMAND_LAST) = range(18)
N_ACC = 18


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the default economic reward, in grams of AdBlue equivalent per gram of pollutant.

    reward per step = -(nox * tailpipe NOx [g, as NO2] + nh3 * NH3 slip [g] + adblue * AdBlue [g]).
    Defaults [chosen]: one gram of tailpipe NOx costs as much as 20 g AdBlue (ANR = 1 needs about 2 g AdBlue per g
    NOx, so dosing pays clearly), NH3 slip 60 g per g (a slip above a few ppm dominates the cost, as the Euro VI
    10 ppm mean limit demands), AdBlue 1.
    """

    nox: float = 20.0
    nh3: float = 60.0
    adblue: float = 1.0

    def __post_init__(self) -> None:
        for name in ("nox", "nh3", "adblue"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
                raise ValueError(f"reward_weights.{name} must be a non-negative finite number, got {v!r}")

    def as_array(self) -> np.ndarray:
        return np.array([self.nox, self.nh3, self.adblue], dtype=np.float64)


@njit(nogil=True, error_model="numpy", fastmath=set(FASTMATH), inline="always")
def account_step(b, inputs, power_kw, dt, out, weights, terms, reward, acc):
    """Reward of plant ``b`` for one step of ``dt`` seconds, and its episode accumulators.

    Reads row ``b`` of the plant step's held inputs (``inputs``, columns :data:`~scr_env.physics.kernel.
    INPUT_FIELDS`: exhaust flow, engine-out NOx, the AdBlue injected) and of its outputs (``out``, columns
    :data:`~scr_env.physics.kernel.OUTPUT_FIELDS`: tailpipe NO, NO2, NH3, N2O, and for the nitrogen balance the NH3
    reaching the catalyst, the N2 formed and the undecomposed urea), and ``power_kw[b]`` (engine brake power [kW]).
    A model without some of these leaves their columns at zero. Writes ``terms[b]`` (the :data:`REWARD_TERMS`, each
    <= 0), ``reward[b]`` (their sum) and adds to ``acc[b]`` (columns ``A_*``); ``weights[b]`` are the
    :class:`RewardWeights` as an array.
    """
    flow = inputs[b, I_FLOW]
    adblue = min(max(inputs[b, I_ADBLUE], 0.0), 1e9)
    nh3_ppm = out[b, O_NH3]
    n2o_ppm = out[b, O_N2O]
    nox_tail_mol_s = (out[b, O_NO] + out[b, O_NO2]) * 1e-6 * flow
    nh3_tail_mol_s = nh3_ppm * 1e-6 * flow
    nox_g = nox_tail_mol_s * NO2_MOLAR_MASS_G_MOL * dt
    nh3_g = nh3_tail_mol_s * NH3_MOLAR_MASS_G_MOL * dt
    adblue_g = adblue * dt
    t0 = -weights[b, 0] * nox_g
    t1 = -weights[b, 1] * nh3_g
    t2 = -weights[b, 2] * adblue_g
    terms[b, 0] = t0
    terms[b, 1] = t1
    terms[b, 2] = t2
    reward[b] = t0 + t1 + t2
    nox_in_mol_s = inputs[b, I_NOX] * 1e-6 * flow
    if acc[b, A_STEPS] > 0.0:  # chatter: consecutive steps of the episode only (not the jump from "no dosing")
        acc[b, A_ADBLUE_TV] += abs(adblue - acc[b, A_ADBLUE_LAST])
    acc[b, A_ADBLUE_LAST] = adblue
    acc[b, A_ENGINE_NOX_G] += nox_in_mol_s * NO2_MOLAR_MASS_G_MOL * dt
    acc[b, A_TAILPIPE_NOX_G] += nox_g
    acc[b, A_NH3_PPM_S] += nh3_ppm * dt
    acc[b, A_NH3_PEAK_PPM] = max(acc[b, A_NH3_PEAK_PPM], nh3_ppm)
    acc[b, A_ADBLUE_G] += adblue_g
    acc[b, A_TIME_S] += dt
    acc[b, A_WORK_KWH] += max(power_kw[b], 0.0) * dt / 3600.0
    acc[b, A_N_IN_MOL] += (nox_in_mol_s + out[b, O_NH3_INJ]) * dt
    acc[b, A_N_OUT_MOL] += (nox_tail_mol_s + nh3_tail_mol_s + 2.0 * n2o_ppm * 1e-6 * flow
                            + 2.0 * out[b, O_N2]) * dt
    acc[b, A_NH3_G] += nh3_g
    acc[b, A_N2O_G] += n2o_ppm * 1e-6 * flow * N2O_MOLAR_MASS_G_MOL * dt
    acc[b, A_UREA_N_MOL] += out[b, O_UREA_N] * dt
    acc[b, A_STEPS] += 1.0


@njit(nogil=True, error_model="numpy", fastmath=set(FASTMATH))
def account_batch(inputs: np.ndarray, power_kw: np.ndarray, dt: float, out: np.ndarray, weights: np.ndarray,
                  terms: np.ndarray, reward: np.ndarray, acc: np.ndarray) -> None:
    """:func:`account_step` for every plant of a batch: ``inputs`` (B, len(INPUT_FIELDS)), ``power_kw`` (B,),
    ``out`` (B, len(OUTPUT_FIELDS)), ``weights`` and ``terms`` (B, 3), ``reward`` (B,), ``acc`` (B, N_ACC). For
    environments that step another model than the plant kernel (:mod:`control.rl.surrogate`)."""
    for b in range(acc.shape[0]):
        account_step(b, inputs, power_kw, dt, out, weights, terms, reward, acc)


@njit(nogil=True, error_model="numpy", fastmath=set(FASTMATH), inline="always")
def account_command(b, command_g_s, acc):
    """Adds the commanded AdBlue rate [g/s] of plant ``b``'s step to the chatter accumulators of ``acc[b]`` (call
    it before :func:`account_step` of the same step). The command differs from the delivered rate only behind an
    actuator (:mod:`scr_env.actuator`); a model that has none may leave it out, the KPI then equals the delivered
    rate's only if it calls this too."""
    if acc[b, A_STEPS] > 0.0:
        acc[b, A_COMMAND_TV] += abs(command_g_s - acc[b, A_COMMAND_LAST])
    acc[b, A_COMMAND_LAST] = command_g_s


@njit(nogil=True, error_model="numpy", fastmath=set(FASTMATH))
def account_commands(commands_g_s: np.ndarray, acc: np.ndarray) -> None:
    """:func:`account_command` for every plant of a batch (``commands_g_s`` (B,))."""
    for b in range(acc.shape[0]):
        account_command(b, commands_g_s[b], acc)


def episode_kpis(acc: np.ndarray, stored_now_mol: float | None = None) -> dict[str, float]:
    """The emission KPIs of one episode from its accumulator row (PHYSICS.md section 7).

    ``stored_now_mol``: NH3 on the catalyst now [mol], for the nitrogen balance; None for a model without a
    nitrogen balance (a surrogate): then ``n2o_g`` and ``nitrogen_balance_error`` are left out. Ratios with a zero
    denominator (no engine-out NOx, no positive work, no time) are NaN.
    """
    engine_nox = float(acc[A_ENGINE_NOX_G])
    tail_nox = float(acc[A_TAILPIPE_NOX_G])
    work = float(acc[A_WORK_KWH])
    time_s = float(acc[A_TIME_S])
    nan = float("nan")
    kpis = {
        "nox_conversion": 1.0 - tail_nox / engine_nox if engine_nox > 0 else nan,
        "engine_out_nox_g": engine_nox,
        "tailpipe_nox_g": tail_nox,
        "engine_out_nox_g_per_kwh": engine_nox / work if work > 0 else nan,
        "tailpipe_nox_g_per_kwh": tail_nox / work if work > 0 else nan,
        "mean_nh3_slip_ppm": float(acc[A_NH3_PPM_S]) / time_s if time_s > 0 else nan,
        "peak_nh3_slip_ppm": float(acc[A_NH3_PEAK_PPM]),
        "nh3_slip_g": float(acc[A_NH3_G]),
        "n2o_g": float(acc[A_N2O_G]),
        "adblue_g": float(acc[A_ADBLUE_G]),
        "adblue_g_per_kwh": float(acc[A_ADBLUE_G]) / work if work > 0 else nan,
        "engine_work_kwh": work,
        "duration_s": time_s,
        # chatter: total variation of the dose per hour of the episode [g/s per h] (delivered; commanded)
        "adblue_total_variation_g_s_per_h": float(acc[A_ADBLUE_TV]) * 3600.0 / time_s if time_s > 0 else nan,
        "command_total_variation_g_s_per_h": float(acc[A_COMMAND_TV]) * 3600.0 / time_s if time_s > 0 else nan,
    }
    if stored_now_mol is None:
        del kpis["n2o_g"]
        return kpis
    n_in = float(acc[A_N_IN_MOL])
    n_out = float(acc[A_N_OUT_MOL]) + (stored_now_mol - float(acc[A_STORED0_MOL]))
    kpis["nitrogen_balance_error"] = (n_in - n_out) / n_in if n_in > 0 else 0.0
    return kpis
