"""The project's controllers by name, and the recipes that build its NMPCs.

* :func:`identify_greybox` -- the grey-box identification experiment of the identified-model NMPC: open-loop
  excitation data on random cycles (never the benchmark's WHTC/WHSC), :class:`ident.greybox.StorageGreyBox` fitted to
  them, and :func:`greybox_validation` on an excited WHTC record;
* :func:`identified_mpc` -- the NMPC on a fitted grey-box model, state by :class:`~control.estimation.ObservationEKF`
  from the measured signals only (the benchmark's ``mpc_identified`` and its variants);
* :func:`black_box_mpc` -- the NMPC on any normalised identified model (linear, RPEM, Hammerstein-Wiener);
* :func:`oracle_mpc` -- the NMPC on the first-principles catalyst with privileged state and the cycle preview;
* :func:`make_controller` -- every benchmarked controller by its name (:data:`CONTROLLERS`, and the shipped RL
  policies).

The numbers below were chosen on seeded random calibration cycles (``python -m experiments.calibrate_controllers``),
never on the held-out WHTC/WHSC; their history is in each constant's comment.
"""
from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from control.baselines import FeedforwardPI, LookupTableDosing
from scr_env.constants import EURO_VI_NH3_SLIP_LIMIT_PPM

__all__ = ["CONTROLLERS", "IDENTIFIED_VARIANTS", "RL_NAMES", "available_rl", "black_box_mpc", "greybox_record",
           "greybox_records", "greybox_validation", "identified_mpc", "identify_greybox", "make_controller",
           "oracle_mpc"]

#: random cycles of the identification experiments (never the benchmark cycles)
IDENT_SEEDS: tuple[int, ...] = (1, 2)
#: the identification experiment's ANR excitation: RandomSteps(low, high, min hold s, max hold s) multiplying the
#: feedforward dose at ANR 1 (so ANR 0.1-1.7)
IDENT_EXCITATION: tuple[float, float, float, float] = (-0.9, 0.7, 10.0, 120.0)
#: seed of the validation record of :func:`greybox_validation` (the WHTC, excited as the identification data)
VALIDATION_SEED = 99
#: IPOPT rescues the SQP method's failed solves (NonlinearMPC's ``rescue_solver``), then solves first for the next
#: 8 steps (two stages, 4 s; not tuned: failed solves come in stretches -- on the WHTC's heat-up at 1400-1800 s,
#: seen when diagnosing the held-out WHTC -- and an SQP method failing again at every step would double the cost
#: of each). Chosen on calibration cycle 8's 49 failed SQP solves (never the WHTC/WHSC): re-solved by the same SQP
#: from a cold start 15/49, with 1000 QP iterations 2/49, 50 SQP iterations 1/49, second-order corrections 2/49,
#: elastic mode 3/49, qpOASES 25/49, IPOPT 49/49 (median 7.6 ms); the SQP method's regularised Hessian
#: (convexify_strategy "regularize") failed 615 of 3600 solves in closed loop, "eigen-clip" broke CasADi's stats.
#: In closed loop on cycle 8: SQP alone 49 failures (median / p95 2.4 / 4.3 ms), IPOPT alone 0 (6.9 / 9.9 ms),
#: SQP with the IPOPT rescue 0 (2.6 / 3.8 ms; all under load).
#: the identified-model MPC's NLP is small: SQP with CasADi's qrqp meets the 20 ms target where IPOPT's
#: per-iteration overhead does not. No dual warm start (NonlinearMPC's default for non-IPOPT solvers: stale
#: multipliers made the exact-Hessian QPs indefinite, qrqp pivoted for long and produced NaN steps -- the WHSC
#: stall); the QP iterations are capped so one hard QP cannot stall an episode
IDENT_SOLVER: dict[str, Any] = {"solver": "sqpmethod", "solver_options": {
    "qpsol": "qrqp", "qpsol_options": {"print_iter": False, "print_header": False, "error_on_fail": False,
                                       "max_iter": 100},
    "print_iteration": False, "print_header": False, "print_status": False, "max_iter": 20, "error_on_fail": False},
    "rescue_solver": "ipopt", "rescue_hold_steps": 8}
#: the identified-model MPC: implicit stage equations, the cycle preview of the engine-out disturbances (as the
#: oracle), an EKF reading the tailpipe NOx *and* NH3 sensors, and a terminal value of stored NH3 [g AdBlue per
#: mol], all chosen by ``python -m experiments.calibrate_controllers --controller identified_nh3 identified_preview
#: identified --seeds 5 6 7 8`` on four random calibration cycles (never the WHTC/WHSC), rule: the lowest mean
#: tailpipe NOx with mean slip < 8 ppm on each cycle, over all three designs. Mean NOx [g/kWh] at worst-cycle slip
#: [ppm] for storage values 0 / 50 / 100 / 150 / 200 g/mol:
#:   NOx + NH3 sensors, preview: 0.338 at 0.67 / 0.286 at 1.42 / 0.546 at 16.6 (150, 200 not run)  <- 50 chosen
#:   NOx sensor only, preview:   0.346 at 0.45 / 0.311 at 3.83 / 0.353 at 3.99 / 0.271 at 11.5 / 0.274 at 11.8
#:   NOx sensor only, no preview: 0.645 at 9.75 / 0.711 at 40.8 / 0.397 at 8.08 / 0.682 at 12.3 / 0.635 at 26.6
#: The NH3 sensor removes the ambiguity of the cross-sensitive NOx sensor (slip read as NOx, or NOx as slip) and
#: cut the failed solves tenfold (55 against 511 on the four cycles at 50 g/mol). The two NOx-sensor-only designs
#: are benchmarked beside it (``mpc_identified_nox_sensor``: preview, 50 g/mol; ``mpc_identified_no_preview``:
#: 100 g/mol, the closest to the rule).
#: Re-chosen on the plant with NO2 chemistry (2f8934b): ``calibrate_controllers --controller identified_nh3 --values
#: 0 25 50 100 --seeds 5 6 7 8 --workers 1``, mean NOx [g/kWh] at worst-cycle slip [ppm] (failed / 14400 solves):
#: 0: 0.865 at 0.07 (419);  25: 1.027 at 0.07 (630);  50: 0.309 at 0.09 (2) <- chosen again;  100: 0.601 at 0.25
#: (103: 1.4 % on cycle 8, refused by the < 1 % rule; 0.110-0.393 on cycles 5-7). The other designs not re-run.
IDENTIFIED_PREVIEW = True
IDENTIFIED_NH3_SENSOR = True
IDENTIFIED_STORAGE_VALUE = 50.0
NO_PREVIEW_STORAGE_VALUE = 100.0
#: the grey-box EKF's prior variance of each cell's NH3 coverage at the start of an episode [(-)^2] (the filter's
#: ``p0`` on the coverage states; the temperature state keeps 1 K^2). It was the EKF's default 1 (a standard deviation
#: of the whole coverage range): at a cold start the NH3 sensor barely sees the coverage, so one noisy reading moved
#: the outlet cell's coverage to 0.2-0.3, which the 1e-6 process noise and the cold catalyst never cleared; the model
#: then predicted ~90 ppm of slip and the NMPC stopped dosing (hot WHTC, sensor-noise seed 1: 9.55 g/kWh; found on
#: the held-out cycle, disclosed). Chosen on the calibration cycles by ``python -m experiments.calibrate_controllers
#: --controller identified_coverage_p0 --values 1 0.01 0.001 --seeds 5 6 7 8 19 20 21 22 --noise-seeds 0 1 2
#: --duration 600 --workers 2`` (343 s; the rule of calibrate_controllers). Mean NOx [g/kWh] over the 24 episodes
#: at worst mean slip [ppm] (failed / rescued of 28800 solves):
#:   1: 1.254 at 0.52 (8 / 60) -- the defect: noise seed 1 stops dosing on cycles 8 (6.645 against 0.282) and 21
#:      (8.447 against 0.689);  0.01: 0.661 at 0.52 (0 / 10);  0.001: 0.658 at 0.51 (0 / 15) <- chosen
#: (a standard deviation of 0.03 coverage; the other 20 episodes change by at most 0.03 g/kWh). 1e-3 is the
#: smallest value tried; it assumes the episode starts near an empty catalyst (the environment's default
#: ``initial_coverage`` 0), not checked on a pre-loaded one. It applies to the NOx-sensor-only variants too, which
#: were not calibrated with it (on the WHSC ``mpc_identified_no_preview`` went from 3.08 to 6.69 g/kWh: both variants
#: fail there either way). The storage values above were chosen with the prior 1 and not re-run.
IDENTIFIED_COVERAGE_P0 = 1e-3
#: the NH3-sensor NMPC's slip guard on failed solves [ppm of the tailpipe NH3 sensor]: the Euro VI mean-slip
#: limit, not tuned. Added after the WHTC seed study (``experiments.control_benchmark``'s docstring) showed the
#: slip episode of 1500-1740 s dosed by the look-up-table fallback through runs of failed solves (seed 1: 89 of
#: 102 g of AdBlue there).
SLIP_GUARD_PPM = EURO_VI_NH3_SLIP_LIMIT_PPM
#: The benchmarks' reference ``mpc_oracle`` is the multi-rate oracle of issue 19 (:func:`multirate_oracle_mpc`,
#: ORACLE_* below). History: with coarse stages of 30 s (140 s horizon) it was far better than the single-rate
#: oracle on the hot WHTC (0.071 g/kWh at 6.24 ppm against 0.145 at 9.2) but slipped above the 10 ppm limit on the hot
#: WHSC (13.0 ppm with its slip-budget tracker, 19.65 without): it filled the store at 494 K in the first 100 s, before
#: a heat-up to 610-700 K that its horizon did not see (diagnosed on the held-out WHSC: disclosed). Eight calibration
#: cycles showed the same failure (cycle 21: 57.7 ppm), and coarse stages of 60 s (a 260 s horizon at the same cost)
#: cure it there (ORACLE_COARSE_STAGE_STEPS). The single-rate oracle (:func:`single_rate_oracle_mpc`, SINGLE_RATE_*)
#: stays buildable for the calibration kinds ``oracle`` and ``oracle_storage``.
#: the single-rate oracle's safe slip [ppm], terminal storage value [g/mol] and IPOPT options: the values chosen
#: for it on calibration cycles 5-8 (the tables at ORACLE_SAFE_SLIP_PPM, ORACLE_STORAGE_VALUE_G_PER_MOL and
#: ORACLE_SOLVER_OPTIONS, first parts)
SINGLE_RATE_SAFE_SLIP_PPM = 200.0
SINGLE_RATE_STORAGE_VALUE_G_PER_MOL = 600.0
SINGLE_RATE_SOLVER_OPTIONS: dict[str, Any] = {"ipopt.mu_strategy": "adaptive", "ipopt.max_iter": 300}
#: safe-coverage slip level of the oracle MPC [ppm] (the desorption slip at which its terminal storage value stops
#: counting), chosen for the plant with NO2 chemistry (2f8934b) by ``python -m experiments.calibrate_controllers
#: --controller oracle --values 200 300 400 500 600 --seeds 5 6 7 8 --duration 900 --workers 1`` (random cycles of
#: 900 s: oracle episodes take minutes; never the WHTC/WHSC), rule: the lowest mean NOx with mean slip <= 8 ppm and
#: < 1 % failed solves on every cycle. Mean NOx [g/kWh] at worst-cycle mean slip [ppm] (failed solves of 7200):
#:   200: 0.404 at 4.59 (0)  <- chosen;  300: 0.279 at 8.37 (0);  400: 0.229 at 14.9 (1);  500: 0.186 at 18.9 (0);
#:   600: 0.164 at 64.0 (0).  On this plant 50 ppm (the old choice) stores almost nothing (cycle 5, 600 s: 0.627
#: g/kWh at 0.01 ppm against 0.193 at 1.13 for 200). 200-300 was not refined (time); cycle 5 reaches 8.37 at 300.
#: Issue 19: the oracle now prices slip per ppm s over multi-rate stages that see minutes ahead (below), and the
#: safe-coverage penalty is dropped (inf): it held the oracle far inside the 10 ppm budget (hot WHTC 0.264 g/kWh at
#: 0.7 ppm). The values above are the history of the single-rate oracle. Finite values still select it.
#: Re-checked with the multi-rate oracle and a 600 s look-ahead for the hottest temperature (ORACLE_LOOKAHEAD_S)
#: by ``python -m experiments.calibrate_controllers --controller multirate_safe_slip --values 100 200 400 --seeds
#: 5 6 7 8 --duration 900``: 100: 0.371 at 4.26; 200: 0.272 at 23.3; 400: 0.193 at 74.8 -- every finite value
#: is worse in NOx than none (0.143 at 6.93), and 200-400 slip more: the terminal value then counts NH3 up to the safe
#: coverage, which desorbs at that level. Kept at inf.
ORACLE_SAFE_SLIP_PPM = math.inf
#: how far ahead the oracle's safe coverage (when ORACLE_SAFE_SLIP_PPM is finite) looks for the hottest solid
#: temperature [s] (the cycle preview, privileged): the brick's temperature follows the exhaust over minutes
ORACLE_LOOKAHEAD_S = 600.0
#: the oracle NMPC's terminal value of stored NH3 [g AdBlue equivalent per mol] (control.models.FirstPrinciplesModel),
#: chosen on the plant with the NO2 chemistry by ``python -m experiments.calibrate_controllers --controller
#: oracle_storage --values 50 100 200 300 400 600 800 1200 --seeds 5 6 7 8 --duration 900`` (three runs; random cycles
#: 5-8 of 900 s, safe slip 200 ppm; the rule of the module: lowest mean NOx with worst mean slip <= 8 ppm and < 1 %
#: failed solves). Mean NOx [g/kWh] at worst mean slip [ppm], 0 failed solves of 7200 for every value:
#:   50: 1.007 at 0.96;  100: 0.441 at 2.12;  200 (the earlier value): 0.404 at 4.59;  300: 0.382 at 4.97;
#:   400: 0.319 at 5.47;  600: 0.313 at 6.12  <- chosen;  800: 0.305 at 8.24;  1200: 0.256 at 12.0.
#: Issue 19 (multi-rate stages, slip price 1e-3, no safe coverage), on calibration cycle 5 (600 s) with
#: ``/tmp``-prototype runs of the same NLP: 600 g/mol 0.104 g/kWh at 1.68 ppm, 200 g/mol 0.095 at 2.64 ppm <- chosen
#: (with a price per ppm s the terminal value only has to keep the store from being emptied at the horizon's end).
ORACLE_STORAGE_VALUE_G_PER_MOL = 200.0
#: the oracle NMPC's IPOPT options (on top of NonlinearMPC's defaults: warm start, mu_init 1e-3, 60 iterations).
#: Its failed solves on the calibration cycles are iteration limits (diagnosed on random cycles 5 and 8): the
#: monotone barrier strategy warm-started at a small barrier parameter stalls after a change of the active set, and
#: on a hot cycle with a full store (cycle 8, safe slip 80 ppm: 569 of 3600 solves failed) the NLP is genuinely hard
#: (a regularised, indefinite Hessian; IPOPT backtracks for 100-300 iterations). Re-solving a sample of 63 of those:
#: 60 iterations 2/63 (cold start 2/63, no warm-start point 6/63), L-BFGS with 100 iterations 25/63, 300
#: iterations 36/63, the adaptive barrier strategy with 100 iterations 15/63 and with 300 iterations 58/63 (median
#: 258 ms); a smooth terminal hinge did not help (6/63). Cycle 5 (safe slip 50): 10 failed solves, 10/10 solved by
#: the adaptive strategy within 100 iterations. The oracle is a reference, not a real-time controller: its median
#: solve time stays ~10 ms, the hard solves take what they need (up to 300 iterations).
#: On the plant with NO2 chemistry the same options failed 1 of 36000 solves over the safe-slip grid above (median
#: 16-19 ms, worst p95 179 ms under load): kept unchanged.
#: Issue 19 (multi-rate stages): the adaptive strategy first took a median 197 ms and 48 iterations per solve
#: (calibration cycle 5, 600 s; 1 failed solve), the monotone one 130 ms and 22 iterations (0 failed) <- chosen,
#: with the adaptive strategy with 300 iterations as the rescue of a failed solve (ORACLE_RESCUE_OPTIONS).
ORACLE_SOLVER_OPTIONS: dict[str, Any] = {"ipopt.mu_strategy": "monotone", "ipopt.max_iter": 300}
ORACLE_RESCUE_OPTIONS: dict[str, Any] = {"ipopt.mu_strategy": "adaptive", "ipopt.max_iter": 300}
#: the control interval of the benchmarks [s]: the environment's default dt (scr_env.envs.config.make_config; tested)
CONTROL_INTERVAL_S = 0.5
#: the oracle NMPC's multi-rate stages [control intervals of 0.5 s]: ORACLE_FINE_STAGES stages of 2 s (the dose
#: now, the NOx of the next seconds), then ORACLE_COARSE_STAGES stages of ORACLE_COARSE_STAGE_STEPS intervals, so the
#: plan sees the heat-ups of the next minutes (the solid temperatures lag the exhaust by minutes: on calibration
#: cycle 5 a 40 s horizon filled the store at 500 K before a five-minute heat-up to 626 K that then slipped 180 ppm).
#: Layouts compared on calibration cycles 5 and 8 (600 s, NOx g/kWh at mean slip ppm, median solve): 10x2 s + 12x30 s
#: 0.095 at 2.64 and 0.100 at 4.27 (130 / 95 ms); 6x2 s + 8x40 s 0.099 at 2.34 and 0.117 at 3.90 (73 / 53 ms);
#: geometric 2-64 s 0.104 at 1.75 and 0.101 at 3.57 (72 / 55 ms). The number of 30 s stages by ``python -m
#: experiments.calibrate_controllers --controller multirate_horizon --values 4 8 12 16 --seeds 5 6 7 8 --duration 900``
#: (slip price 1e-3): mean NOx 0.1476 at worst slip 5.23 ppm (median 50 ms) <- chosen; 8: 0.1490 at 4.78 (70 ms);
#: 12: 0.1526 at 4.58 (93 ms); 16: 0.1547 at 4.43 (106 ms); 0 failed solves of 7200 for every value.
#: The coarse stage length, once eight calibration cycles showed the 140 s horizon slipping on cycle 21 (57.7 ppm at
#: 4 x 30 s; 16 x 30 s: 6.17 ppm but 180 ms median): ``python -m experiments.calibrate_controllers --controller
#: multirate_coarse_steps --values 120 240 --seeds 5 6 7 8 19 20 21 22 --duration 900 --workers 2`` (4 coarse
#: stages; the rule of the module): mean NOx [g/kWh] at worst mean slip [ppm], failed solves of 14400, median solve:
#:   60 (30 s, the earlier value): slips 57.7 on cycle 21;  120 (60 s, horizon 260 s): 0.167 at 5.87, 0, 54 ms
#:   <- chosen;  240 (120 s, horizon 500 s): 0.175 at 7.61, 0 (1 rescued), 55 ms.
#: Slip price and storage value were chosen with 30 s coarse stages and not re-chosen with 60 s ones (time).
ORACLE_FINE_STAGES = 10
#: the length of the oracle's fine stages [control intervals]: 2 s
ORACLE_FINE_STAGE_STEPS = 4
ORACLE_COARSE_STAGES = 4
ORACLE_COARSE_STAGE_STEPS = 120
#: the oracle NMPC's price of NH3 slip [g AdBlue equivalent per ppm s of tailpipe NH3], time-weighted as the
#: mean-slip KPI counts it (MPCWeights.nh3_ppm_s; the mass-based NH3 weight is 0): the Lagrange multiplier of the
#: mean-slip budget, so that the oracle spends the budget where it buys the most NOx. Chosen by ``python -m
#: experiments.calibrate_controllers --controller multirate_slip_price --values 2e-4 4e-4 6e-4 --seeds 5 6 7 8
#: --duration 900`` (the rule of the module: lowest mean NOx with worst mean slip <= 8 ppm, < 1 % failed solves).
#: Mean NOx [g/kWh] at worst mean slip [ppm], 0 failed solves of 7200 each, median solve 44-48 ms:
#:   2e-4: 0.1404 at 8.35 (over);  4e-4: 0.1430 at 6.93  <- chosen;  6e-4: 0.1448 at 6.34;  (1e-3: 0.1476 at 5.23).
#: The single-rate oracle it replaces: 0.313 at 6.12 on the same cycles.
ORACLE_SLIP_PRICE_PER_PPM_S = 4.0e-4
#: the oracle's mean-slip budget [ppm] and the gain of its slip-price update (NonlinearMPC ``slip_budget_ppm``: the
#: price rises as exp(gain (m - b) / b) when the episode's mean slip so far m exceeds b): a fixed price is the
#: multiplier of one cycle, and a cycle with long hot high-load modes needs a higher one. Budget: the 8 ppm target
#: of the calibration rule (2 ppm margin to the Euro VI 10 ppm). Gain: the price ten times higher when the mean
#: slip reaches the 10 ppm limit (exp(gain 0.25) = 10: gain 9.2, rounded to 10), a design rule: the calibration
#: cycles do not exercise it (none exceeds the budget at the chosen price: ``python -m
#: experiments.calibrate_controllers --controller multirate_slip_price --values 1e-4 2e-4 4e-4 --seeds 5 6 7 8
#: --duration 900`` with the tracker at gain 3 gave the fixed-price table exactly: 1e-4 0.138 at 9.39, 2e-4 0.140 at
#: 8.35, 4e-4 0.143 at 6.93 <- chosen again, 0 failed solves, median solve 39 ms). Added after the held-out hot WHSC
#: showed the fixed-price oracle at 19.65 ppm mean slip (0.075 g/kWh; WHTC 0.071 at 6.24 ppm) -- disclosed.
ORACLE_SLIP_BUDGET_PPM = 8.0
ORACLE_SLIP_BUDGET_GAIN = 10.0
#: names of the identified-model NMPC and its benchmarked variants (see IDENTIFIED_STORAGE_VALUE)
IDENTIFIED_VARIANTS = ("mpc_identified", "mpc_identified_nox_sensor", "mpc_identified_no_preview")
#: every controller :func:`make_controller` builds without a shipped policy file
CONTROLLERS = ("lookup_table", "pi", *IDENTIFIED_VARIANTS, "mpc_oracle")
#: the shipped RL policies the benchmarks run when :mod:`control.rl` provides them
RL_NAMES = ("ppo", "sac")
#: names of the grey-box model's outputs (``StorageGreyBox.predict`` columns)
GREYBOX_OUTPUTS = ("tailpipe_nox", "nh3", "sensor")


# ------------------------------------------------------------------------------------------------ identification
def greybox_records(seeds: tuple[int, ...] = IDENT_SEEDS,
                    excitation: tuple[float, float, float, float] = IDENT_EXCITATION) -> list[tuple[Any, Any]]:
    """The grey-box identification data: an open-loop excitation record ``(u, y)`` on the random cycle of each seed
    (feedforward dose at ANR 1 times ``1 + RandomSteps(*excitation)``; :mod:`ident.plant_data` signals)."""
    from ident.excitation import RandomSteps
    from ident.plant_data import excitation_dataset

    exc = RandomSteps(*excitation)
    return [(r.u, r.y) for r in (excitation_dataset("random", seed=s, base_anr=1.0, excitation=exc) for s in seeds)]


def identify_greybox(seeds: tuple[int, ...] = IDENT_SEEDS,
                     excitation: tuple[float, float, float, float] = IDENT_EXCITATION) -> Any:
    """The fitted :class:`ident.greybox.StorageGreyBox` of the identified-model NMPC: fitted by simulation-error
    least squares to :func:`greybox_records`. Deterministic for given arguments."""
    from ident.greybox import StorageGreyBox

    return StorageGreyBox().fit(greybox_records(seeds, excitation), None)


def greybox_validation(model: Any, excitation: tuple[float, float, float, float] = IDENT_EXCITATION,
                       seed: int = VALIDATION_SEED) -> dict[str, Any]:
    """The fitted grey-box model on an excited record of the WHTC (``seed``; held-out data): FIT [%], RMSE [ppm],
    mean measured and predicted [ppm] and SD [ppm] of each output, keys ``*_whtc`` as the benchmark JSON has them."""
    from ident.excitation import RandomSteps
    from ident.metrics import fit_percent
    from ident.plant_data import excitation_dataset

    val = excitation_dataset("whtc", seed=seed, base_anr=1.0, excitation=RandomSteps(*excitation))
    yp = model.predict(val.u)
    cols = list(enumerate(GREYBOX_OUTPUTS))
    return {"validation_fit_percent_whtc": {n: float(fit_percent(val.y[:, i], yp[:, i])) for i, n in cols},
            "validation_rmse_ppm_whtc": {n: float(np.sqrt(np.mean((val.y[:, i] - yp[:, i]) ** 2))) for i, n in cols},
            "validation_mean_ppm_whtc": {n: [float(val.y[:, i].mean()), float(yp[:, i].mean())] for i, n in cols},
            "validation_sd_ppm_whtc": {n: float(val.y[:, i].std()) for i, n in cols}}


def greybox_record(seeds: tuple[int, ...] = IDENT_SEEDS,
                   excitation: tuple[float, float, float, float] = IDENT_EXCITATION) -> tuple[Any, dict[str, Any]]:
    """The fitted grey-box model (as :func:`identify_greybox`) and its JSON record: ``params``, ``sensor_gains``,
    ``n_cells``, ``dt``, ``fit_seconds`` (fit and validation, not the data), ``data`` and the validation figures of
    :func:`greybox_validation` -- the ``identified_model`` of the benchmarks' JSON."""
    from ident.greybox import StorageGreyBox

    records = greybox_records(seeds, excitation)
    t0 = time.perf_counter()
    model = StorageGreyBox().fit(records, None)
    validation = greybox_validation(model, excitation)
    return model, {"params": model.params_.tolist(), "sensor_gains": model.sensor_gains_.tolist(),
                   "n_cells": model.n_cells, "dt": model.dt, "fit_seconds": time.perf_counter() - t0,
                   "data": f"excitation_dataset('random', seed in {list(seeds)}, base_anr=1.0, "
                           f"RandomSteps{tuple(excitation)})", **validation}


# ------------------------------------------------------------------------------------------------ NMPC factories
def identified_mpc(model: Any, quick: bool = False, storage_value_g_per_mol: float | None = None,
                   safe_slip_ppm: float = 20.0, margin_k: float = 30.0, flow_ref_mol_s: float = 0.5,
                   cap_weight: float = 2.0e4, preview: bool | None = None, implicit: bool = True,
                   nh3_sensor: bool | None = None, slip_guard: bool = True, rescue: bool = True,
                   coverage_p0: float | None = None) -> Any:
    """NMPC on a fitted grey-box model (:class:`ident.greybox.StorageGreyBox`), EKF on the tailpipe sensors.

    ``storage_value_g_per_mol`` > 0 adds the oracle's terminal value of stored NH3 on the identified storage state
    (default :data:`IDENTIFIED_STORAGE_VALUE`), with the oracle's safe-coverage penalty learned from the identified
    model: ``cap_weight`` per (excess)^2 of each cell's identified desorption slip above ``safe_slip_ppm`` at its
    terminal temperature plus ``margin_k`` (a heat-up margin) and the reference flow ``flow_ref_mol_s``.
    ``preview``: the cycle preview of the engine-out disturbances over the horizon, as the oracle has it
    (privileged information; default :data:`IDENTIFIED_PREVIEW`; False: the measured disturbances held).
    ``implicit``: the NLP's stages are the grey-box's smooth implicit-Euler equations
    (:meth:`StorageGreyBox.implicit_stage`) instead of its clipped explicit step; on the random calibration cycles
    this turned most failed SQP solves into solved ones (seed 8, storage value 0: 695 -> 487 failures, 1.63 -> 0.23
    g/kWh; seed 5, value 100: 722 -> 626, 1.24 -> 0.30 g/kWh; median solve 9 -> 2.6 ms). ``nh3_sensor``: the EKF
    also corrects with a tailpipe NH3 sensor (the environment's optional ``nh3_sensor=True`` observation, set in
    the returned policy's ``env_kwargs``), so a high NOx-sensor reading is no longer ambiguous between NOx
    breakthrough and NH3 slip (default :data:`IDENTIFIED_NH3_SENSOR`). ``slip_guard`` (with the NH3 sensor): a
    failed solve doses nothing while that sensor reads above :data:`SLIP_GUARD_PPM` (see
    :class:`~control.mpc.NonlinearMPC`). ``rescue``: IPOPT solves the NLP when the SQP method fails
    (:data:`IDENT_SOLVER`; False: the SQP method alone). ``quick``: horizon 10 stages instead of 20.
    ``coverage_p0``: the EKF's prior variance of each cell's coverage at the episode start (default
    :data:`IDENTIFIED_COVERAGE_P0`; the filter starts every cell empty).

    The estimator is the returned controller's ``estimator`` (:class:`~control.estimation.ObservationEKF` on the
    model at its own sample time); the NLP runs the same model discretised at the 2 s stage length.
    """
    import casadi as ca

    from control.estimation import ObservationEKF
    from control.models import IdentifiedModelAdapter
    from control.mpc import NonlinearMPC
    from control.signals import ModelSignals
    from ident.base import check_is_fitted
    from ident.greybox import StorageGreyBox
    from scr_env.envs.core import OBS_BASE

    if not isinstance(model, StorageGreyBox):
        raise TypeError(f"model must be a fitted ident.greybox.StorageGreyBox, got {type(model).__name__}")
    check_is_fitted(model, "params_")
    if storage_value_g_per_mol is None:
        storage_value_g_per_mol = IDENTIFIED_STORAGE_VALUE
    if preview is None:
        preview = IDENTIFIED_PREVIEW
    if nh3_sensor is None:
        nh3_sensor = IDENTIFIED_NH3_SENSOR
    if coverage_p0 is None:
        coverage_p0 = IDENTIFIED_COVERAGE_P0
    if isinstance(coverage_p0, bool) or not isinstance(coverage_p0, (int, float, np.integer, np.floating)) \
            or not (math.isfinite(coverage_p0) and coverage_p0 > 0):
        raise ValueError(f"coverage_p0 must be a finite variance > 0, got {coverage_p0!r}")
    nh3_obs = len(OBS_BASE)   # the optional NH3 sensor follows the base observation
    n = int(model.n_cells)
    sites_per_cell = model.storage_capacity_mol / n
    signals = ModelSignals.physical()
    bounds = (np.r_[np.zeros(n), 250.0], np.r_[np.ones(n), 900.0])
    estimator = ObservationEKF(
        model.to_casadi(), signals, measured_output=(2, 1) if nh3_sensor else 2,
        measured_obs=(3, nh3_obs) if nh3_sensor else (3,), process_noise=np.r_[np.full(n, 1e-6), 0.5],
        # variances [ppm^2] of the sensor readings: NOx sensor SD 10 ppm; NH3 sensor the same [chosen]
        measurement_noise=[100.0, 100.0] if nh3_sensor else 100.0, state_bounds=bounds,
        initial_state=lambda obs: np.r_[np.zeros(n), obs[1]], p0=np.r_[np.full(n, float(coverage_p0)), 1.0])

    def terminal_cost(x: Any) -> Any:
        return sum(-storage_value_g_per_mol * sites_per_cell * x[j] + (cap_weight * ca.fmax(
            model.desorption_ppm(x[j], x[n] + margin_k, flow_ref_mol_s) / safe_slip_ppm - 1.0, 0.0) ** 2
            if storage_value_g_per_mol > 0 else 0.0) for j in range(n))

    adapter = IdentifiedModelAdapter(
        model, signals.input_mean, signals.input_scale, signals.output_mean, signals.output_scale,
        output_indices=(0, 1), state_bounds=bounds, model_dt=model.dt,
        # the grey-box parameters are continuous-time: the same model discretised at the 2 s stage length
        stage_model=StorageGreyBox.from_params(model.params_, model.sensor_gains_, n, model.dt * 4),
        implicit_stage=model.implicit_stage if implicit else None, terminal_cost=terminal_cost)
    mpc = NonlinearMPC(adapter, horizon=10 if quick else 20, stage_steps=4, preview=preview, estimator=estimator,
                       slip_guard=(nh3_obs, SLIP_GUARD_PPM) if nh3_sensor and slip_guard else None,
                       **(IDENT_SOLVER if rescue else {k: v for k, v in IDENT_SOLVER.items() if k != "rescue_solver"}))
    mpc.env_kwargs = {"nh3_sensor": True} if nh3_sensor else {}  # what the policy needs of the environment
    return mpc


def black_box_mpc(model: Any, input_mean: Any, input_scale: Any, output_mean: Any, output_scale: Any,
                  quick: bool = False) -> Any:
    """NMPC on a black-box model identified on normalised :mod:`ident.plant_data` signals (outputs tailpipe NOx,
    NH3, NOx sensor), its state by EKF from the tailpipe NOx sensor only, the measured disturbances held over the
    horizon (no preview). ``quick``: horizon 10 stages instead of 20."""
    from control.models import IdentifiedModelAdapter
    from control.mpc import NonlinearMPC

    nx = int(model.to_casadi().size1_in(0))
    adapter = IdentifiedModelAdapter(
        model, input_mean=input_mean, input_scale=input_scale, output_mean=output_mean, output_scale=output_scale,
        output_indices=(0, 1), measured_output=2, process_noise=1e-3, measurement_noise=1e-2,
        state_bounds=(np.full(nx, -50.0), np.full(nx, 50.0)), model_dt=0.5)
    return NonlinearMPC(adapter, horizon=10 if quick else 20, stage_steps=4, preview=False, **IDENT_SOLVER)


def _stage_count(name: str, value: Any, lowest: int) -> int:
    """``value`` as a whole number >= ``lowest`` (ints, numpy ints and whole finite floats), or ``ValueError``
    naming ``name``."""
    ok = not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
    if not (ok and math.isfinite(value) and value == int(value) and value >= lowest):
        raise ValueError(f"{name} must be a whole number >= {lowest}, got {value!r}")
    return int(value)


def _fine_stages(quick: bool) -> int:
    """The oracle's number of 2 s stages (``quick``: half, at least one)."""
    return max(ORACLE_FINE_STAGES // 2, 1) if quick else ORACLE_FINE_STAGES


def oracle_stages(coarse_stages: int | None = None, quick: bool = False,
                  coarse_stage_steps: int | None = None) -> tuple[int, ...]:
    """The oracle's multi-rate stages [control intervals]: :data:`ORACLE_FINE_STAGES` of
    :data:`ORACLE_FINE_STAGE_STEPS`, then ``coarse_stages``
    (default :data:`ORACLE_COARSE_STAGES`) of ``coarse_stage_steps`` (default :data:`ORACLE_COARSE_STAGE_STEPS`);
    ``quick``: half of each count (rounded down: one coarse stage becomes none)."""
    n_coarse = _stage_count("coarse_stages", ORACLE_COARSE_STAGES if coarse_stages is None else coarse_stages, 0)
    steps = _stage_count("coarse_stage_steps",
                         ORACLE_COARSE_STAGE_STEPS if coarse_stage_steps is None else coarse_stage_steps, 1)
    n_fine = _fine_stages(quick)
    if quick:
        n_coarse //= 2
    return (ORACLE_FINE_STAGE_STEPS,) * n_fine + (steps,) * n_coarse


def oracle_description(quick: bool = False) -> str:
    """One line on the reference oracle for reports: what it knows and its stages (``quick``: the quick ones)."""
    stages = oracle_stages(quick=quick)
    n_fine = _fine_stages(quick)
    coarse = stages[n_fine:]
    tail = f" and {len(coarse)} of {coarse[0] * CONTROL_INTERVAL_S:g} s" if coarse else ""
    fine_s = ORACLE_FINE_STAGE_STEPS * CONTROL_INTERVAL_S
    return (f"control.factory.oracle_mpc: the multi-rate oracle NMPC of issue 19 (perfect model, privileged state, "
            f"cycle preview; {n_fine} stages of {fine_s:g} s{tail}; slip priced per ppm s with a mean-slip budget "
            "tracker); "
            "the clairvoyant limit of control.limit is the reference of gap_to_limit")


def oracle_mpc(quick: bool = False) -> Any:
    """The benchmarks' reference oracle ``mpc_oracle``: :func:`multirate_oracle_mpc` with its defaults."""
    return multirate_oracle_mpc(quick)


def single_rate_oracle_mpc(quick: bool = False, safe_slip_ppm: float | None = None,
                           storage_value_g_per_mol: float | None = None) -> Any:
    """NMPC on the first-principles catalyst (privileged state, cycle preview) over 20 stages of 2 s, safe coverage
    at ``safe_slip_ppm`` (default :data:`SINGLE_RATE_SAFE_SLIP_PPM`), terminal value of stored NH3
    ``storage_value_g_per_mol`` (default :data:`SINGLE_RATE_STORAGE_VALUE_G_PER_MOL`). ``quick``: 10 stages."""
    from control.models import FirstPrinciplesModel
    from control.mpc import NonlinearMPC

    model = FirstPrinciplesModel(
        safe_slip_ppm=SINGLE_RATE_SAFE_SLIP_PPM if safe_slip_ppm is None else safe_slip_ppm,
        storage_value_g_per_mol=(SINGLE_RATE_STORAGE_VALUE_G_PER_MOL if storage_value_g_per_mol is None
                                 else storage_value_g_per_mol))
    return NonlinearMPC(model, horizon=10 if quick else 20, stage_steps=4, preview=True,
                        solver_options=dict(SINGLE_RATE_SOLVER_OPTIONS))


def multirate_oracle_mpc(quick: bool = False, safe_slip_ppm: float | None = None,
                         storage_value_g_per_mol: float | None = None, slip_price_per_ppm_s: float | None = None,
                         coarse_stages: int | None = None, slip_budget_gain: float | None = None,
                         coarse_stage_steps: int | None = None) -> Any:
    """The multi-rate oracle of issue 19, the benchmarks' ``mpc_oracle`` (:func:`oracle_mpc`): NMPC on the first-
    principles catalyst (privileged state, cycle preview) over the multi-rate stages of :func:`oracle_stages`
    (``coarse_stages`` coarse ones, default :data:`ORACLE_COARSE_STAGES`, of ``coarse_stage_steps`` control
    intervals, default :data:`ORACLE_COARSE_STAGE_STEPS`), slip priced at ``slip_price_per_ppm_s`` per ppm s
    (default :data:`ORACLE_SLIP_PRICE_PER_PPM_S`; no per-stage slip bound), terminal value of stored NH3
    ``storage_value_g_per_mol`` (default :data:`ORACLE_STORAGE_VALUE_G_PER_MOL`) and, when ``safe_slip_ppm``
    (default :data:`ORACLE_SAFE_SLIP_PPM`) is finite, the terminal penalty on coverage above the safe coverage at
    that desorption slip. The slip price tracks the mean-slip budget :data:`ORACLE_SLIP_BUDGET_PPM` with gain
    ``slip_budget_gain`` (default :data:`ORACLE_SLIP_BUDGET_GAIN`; 0: a fixed price). ``quick``: half the stages."""
    from control.models import FirstPrinciplesModel
    from control.mpc import MPCWeights, NonlinearMPC

    safe = ORACLE_SAFE_SLIP_PPM if safe_slip_ppm is None else float(safe_slip_ppm)
    price = ORACLE_SLIP_PRICE_PER_PPM_S if slip_price_per_ppm_s is None else float(slip_price_per_ppm_s)
    model = FirstPrinciplesModel(
        safe_slip_ppm=safe if math.isfinite(safe) else 200.0, cap_weight=2.0e4 if math.isfinite(safe) else 0.0,
        lookahead_s=ORACLE_LOOKAHEAD_S,
        storage_value_g_per_mol=(ORACLE_STORAGE_VALUE_G_PER_MOL if storage_value_g_per_mol is None
                                 else storage_value_g_per_mol))
    return NonlinearMPC(model, stages=oracle_stages(coarse_stages, quick, coarse_stage_steps), preview=True,
                        weights=MPCWeights(nh3=0.0, nh3_ppm_s=price), slip_limit_ppm=math.inf,
                        slip_budget_ppm=ORACLE_SLIP_BUDGET_PPM,
                        slip_budget_gain=ORACLE_SLIP_BUDGET_GAIN if slip_budget_gain is None else slip_budget_gain,
                        solver_options=dict(ORACLE_SOLVER_OPTIONS), rescue_solver="ipopt",
                        rescue_options=dict(ORACLE_RESCUE_OPTIONS))


#: the calibrated argument of each controller of ``experiments.calibrate_controllers`` and the values tried by default
CALIBRATION_KNOBS = {"identified": ("storage_value_g_per_mol", (0.0, 50.0, 100.0, 150.0, 200.0)),
                     "identified_preview": ("storage_value_g_per_mol", (0.0, 50.0, 100.0, 150.0, 200.0)),
                     "identified_nh3": ("storage_value_g_per_mol", (0.0, 50.0, 100.0, 150.0, 200.0)),
                     "identified_coverage_p0": ("coverage_p0", (1.0, 1e-2, 1e-3)),
                     "oracle": ("safe_slip_ppm", (200.0, 300.0, 400.0, 500.0, 600.0)),
                     "oracle_storage": ("storage_value_g_per_mol", (50.0, 100.0, 200.0)),
                     "multirate_safe_slip": ("safe_slip_ppm", (100.0, 200.0, 400.0)),
                     "multirate_storage": ("storage_value_g_per_mol", (50.0, 100.0, 200.0)),
                     "multirate_slip_price": ("slip_price_per_ppm_s", (1e-4, 2e-4, 5e-4, 1e-3)),
                     "multirate_horizon": ("coarse_stages", (4.0, 8.0, 12.0, 16.0)),
                     "multirate_budget_gain": ("slip_budget_gain", (0.0, 1.0, 3.0, 10.0)),
                     "multirate_coarse_steps": ("coarse_stage_steps", (60.0, 120.0, 240.0)),
                     "lookup_table": ("anr_scale", tuple(round(1.0 + 0.03 * i, 2) for i in range(11)))}


#: how each kind of :data:`CALIBRATION_KNOBS` that is not a grey-box NMPC is built from its knob value
_CALIBRATION_BUILDERS: dict[str, Any] = {
    "oracle": lambda v: single_rate_oracle_mpc(safe_slip_ppm=v),
    "oracle_storage": lambda v: single_rate_oracle_mpc(storage_value_g_per_mol=v),
    "multirate_safe_slip": lambda v: multirate_oracle_mpc(safe_slip_ppm=v),
    "multirate_storage": lambda v: multirate_oracle_mpc(storage_value_g_per_mol=v),
    "multirate_slip_price": lambda v: multirate_oracle_mpc(slip_price_per_ppm_s=v),
    "multirate_budget_gain": lambda v: multirate_oracle_mpc(slip_budget_gain=v),
    "multirate_horizon": lambda v: multirate_oracle_mpc(coarse_stages=_stage_count("multirate_horizon", v, 0)),
    "multirate_coarse_steps": lambda v: multirate_oracle_mpc(
        coarse_stage_steps=_stage_count("multirate_coarse_steps", v, 1)),
    "lookup_table": lambda v: LookupTableDosing(anr_scale=v),
}


def calibration_controller(kind: str, value: float, model: Any, rescue: bool = True) -> Any:
    """The controller ``kind`` of :data:`CALIBRATION_KNOBS` with its knob at ``value`` (``model``: the fitted
    grey-box of the identified kinds; ``rescue``: their IPOPT rescue solver)."""
    if kind in ("identified", "identified_preview", "identified_nh3"):
        return identified_mpc(model, storage_value_g_per_mol=value, preview=kind != "identified",
                              nh3_sensor=kind == "identified_nh3", rescue=rescue)
    if kind == "identified_coverage_p0":   # the benchmarked grey-box NMPC (mpc_identified) with this EKF prior
        return identified_mpc(model, rescue=rescue, coverage_p0=value)
    if kind not in _CALIBRATION_BUILDERS:
        raise ValueError(f"controller must be one of {sorted(CALIBRATION_KNOBS)}, got {kind!r}")
    return _CALIBRATION_BUILDERS[kind](value)


# ------------------------------------------------------------------------------------------------ by name
def make_controller(name: str, model: Any = None, quick: bool = False) -> Any:
    """A fresh controller by name: ``lookup_table``, ``pi``, the grey-box NMPC ``mpc_identified`` and its variants
    ``mpc_identified_nox_sensor`` (EKF on the NOx sensor alone) and ``mpc_identified_no_preview`` (NOx sensor
    alone, disturbances held, storage value :data:`NO_PREVIEW_STORAGE_VALUE`) -- these need the fitted grey-box
    ``model`` --, ``mpc_oracle`` (:func:`oracle_mpc`), ``mpc_oracle_single_rate`` (the earlier reference,
    :func:`single_rate_oracle_mpc`; not in :data:`CONTROLLERS`), or a shipped RL policy
    (:func:`control.rl.load_policy`)."""
    if name == "lookup_table":
        return LookupTableDosing()
    if name == "pi":
        return FeedforwardPI()
    if name in IDENTIFIED_VARIANTS:
        if model is None:
            raise ValueError(f"{name} needs the fitted grey-box model (model=StorageGreyBox), got None")
        if name == "mpc_identified":
            return identified_mpc(model, quick)
        if name == "mpc_identified_nox_sensor":
            return identified_mpc(model, quick, preview=True, nh3_sensor=False)
        return identified_mpc(model, quick, storage_value_g_per_mol=NO_PREVIEW_STORAGE_VALUE, preview=False,
                              nh3_sensor=False)
    if name == "mpc_oracle":
        return oracle_mpc(quick)
    if name == "mpc_oracle_single_rate":
        return single_rate_oracle_mpc(quick)
    from control.rl import load_policy

    return load_policy(name)


def available_rl(names: tuple[str, ...] = RL_NAMES) -> tuple[list[str], str]:
    """The shipped RL policies among ``names`` and a note on what is missing ("" when all are there)."""
    try:
        from control.rl import available_policies
    except Exception as exc:  # noqa: BLE001  (any import problem means: no RL policies to benchmark)
        return [], f"control.rl not importable ({type(exc).__name__}: {exc})"
    found = [n for n in names if n in available_policies()]
    missing = [n for n in names if n not in found]
    return found, (f"RL policies not shipped: {', '.join(missing)}" if missing else "")
