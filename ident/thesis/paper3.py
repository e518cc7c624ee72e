"""Paper III reproduced on the simulator: RPEM with a 2nd-order chain model, the 9-term (linear) and 16-term
(nonlinear) regressors, Euler against midpoint, beside the published Table 2.

Protocol (Paper III, ALGORITHMS.md sections 1 and 3)
----------------------------------------------------

* Data: 1200 samples at 0.5 s of the hot WHTC from 350 s (Paper IV's segment, :mod:`ident.plant_data`), open-loop
  feedforward dosing at ANR 0.5 times ``1 + e(t)``; first 900 samples (75 %) for estimation, last 300 (25 %)
  for validation. Output: tailpipe NOx (true value, ppm), as Paper III's y1.
* Dosing excitation :data:`EXCITATION`: random steps of the ANR factor in [-0.3, 0.3] held 4-60 s (ANR 0.35 to
  0.65). Paper IV's excitation design (:data:`ident.plant_data.PAPER4_EXCITATION`, ANR 0 to 1) empties and refills
  the NH3 store, a slow state the 2-state chain (x1 = y, x2 = y') cannot hold; the thesis' data came from production
  dosing, which keeps the catalyst in one storage regime. The milder design keeps that regime and still makes the
  urea input independent of the NOx flow. The figures on the records of Paper IV's two designs
  (:data:`ident.plant_data.PAPER4_DESIGNS`) are reported too: ``paper4_excitation_design`` (called
  ``paper4_design`` until 2026-11-24) and ``paper4_production_design`` (the thesis' feedforward dosing without
  excitation, the design of Paper IV's table since 2026-11-24). This table keeps its own design: its RPEM figures
  already pass the thesis' on it, and the production record's are printed beside them.
  This choice was made after trying both designs (and a few others) on this segment; the multi-segment repetition
  below, on windows, cycles and seeds that played no part in it, is the check that it is not a lucky pick.
* Time alignment: a record's output ``y[k]`` is sampled at the *end* of control step k (``(k + 1) dt``), after
  the input ``u[k]`` held over the step; the RPEM's step into sample t uses ``u(t - 1)``, so it is given
  ``(u[k + 1], y[k])`` pairs (one extra sample is simulated so that 1200 outputs remain, the same output samples
  as Paper IV's data). ``--no-align`` pairs ``(u[k], y[k])`` instead (one sample of extra dead time).
* Inputs: u1 inlet NOx [ppm], u2 urea [g/min], u3* = exp(-a / T_in) with a = 1e4 K, u4 exhaust flow [mol/s];
  every signal normalised with the mean and SD of the estimation part (Paper III Table 1 lists the thesis'
  values; ours are in the JSON ``data.table1``). Input derivatives are backward differences inside the RPEM.
* RPEM: 2 states, alpha = 1.5 (Ts = 0.75 s), R(0) = 100 I, Lambda(0) = 0.1, x(0) = (y(0), 0), stability margin
  0.015, output saturated at zero NOx (``-mean/SD`` in normalised units), initial theta from the augmented-state
  Kalman filter (P(0) = 10 I, process noise 50 on x and 0 on theta, measurement noise 3), then passes over the
  estimation data from the previous pass' theta until the estimation FIT stops improving (at most ``--passes``).
  Euler and midpoint start from their own Kalman initialisation (the filter runs the same discretisation).
* FIT: simulated output from ``x(0) = (y(0), 0)``, normalised units, ``100 (1 - |y - yhat| / |y - mean y|)``.

Beyond the thesis
-----------------

* Term selection: backward elimination (:func:`ident.rpem.backward_elimination`, midpoint) from the 16 terms plus
  :data:`EXTRA_TERMS`, one term removed at a time while the validation FIT improves, as Paper III describes. Its
  validation FIT is optimistic (the validation data chose the terms); the repetition gives its honest figure.
* Multi-segment repetition: the four methods (and the selected terms) on independent 600 s windows of the WHTC,
  the WHSC and seeded random cycles (:func:`find_segments`: non-overlapping windows whose validation part stays in
  the estimation part's temperature range), each with its own seed; mean and spread of the validation FIT per
  method and whether "nonlinear beats linear" and "midpoint beats Euler" hold: for both discretisations (resp.
  both regressors) the one-sided Wilcoxon signed-rank test of the paired validation-FIT differences at p < 0.05
  (:func:`ident.thesis.stats.paired_verdict`; until 2026-11-23 a positive median with a majority of wins counted).

Run by ``python -m experiments.reproduce_paper3`` (figures and ``results.json`` in ``runs/reproduce_paper3/``).
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from ident.excitation import ExcitationSignal, RandomSteps
from ident.metrics import fit_percent
from ident.plant_data import (
    PAPER3_TABLE1_MEAN,
    PAPER3_TABLE1_SD,
    PAPER4_BASE_ANR,
    PAPER4_DESIGNS,
    PAPER4_DT_S,
    PAPER4_N_SAMPLES,
    PAPER4_SEGMENT_START_S,
    SIM_INPUT_NAMES,
    excitation_dataset,
)
from ident.preprocessing import ARRHENIUS_A_K, Normalizer, arrhenius_transform
from ident.rpem import SCR_PAPER3_LINEAR_TERMS, SCR_PAPER3_TERMS, RecursivePEM, backward_elimination
from ident.thesis.stats import paired_verdict

#: Paper III Table 2 (validation FIT, percent) and the estimation FIT quoted in its text.
PUBLISHED = {"euler_linear": 40.65, "midpoint_linear": 41.68, "euler_nonlinear": 55.64, "midpoint_nonlinear": 61.54}
PUBLISHED_ESTIMATION = {"linear": 64.52, "nonlinear": 67.31}
METHODS = ("euler_linear", "midpoint_linear", "euler_nonlinear", "midpoint_nonlinear")
TERMS = {"linear": SCR_PAPER3_LINEAR_TERMS, "nonlinear": SCR_PAPER3_TERMS}
N_ESTIMATION_FRACTION = 0.75
ALPHA = 1.5
TEMPERATURE_COLUMN = 2

#: Dosing excitation of this experiment: ANR factor 1 + e, e random steps in [-0.3, 0.3] held 4-60 s.
EXCITATION = RandomSteps(low=-0.3, high=0.3, min_hold_s=4.0, max_hold_s=60.0)

#: Candidates added to the 16 terms for backward elimination: the products the physics suggests (conversion
#: scales the inlet NOx; the rate depends on temperature, residence time and dosing) and the states times inputs.
EXTRA_TERMS = ("u1*u3", "u1*u2", "u1*u4", "x1*u3", "x1*u4", "x2*u4", "u2*u3", "x1*u1")

#: Cycles (and seeds) of the repetition; windows are found by :func:`find_segments`.
REPETITION_CYCLES = (("whtc", 1), ("whsc", 2), ("random", 3), ("random", 4), ("random", 5), ("random", 6))
#: Tolerance of the operating-range rule of :func:`find_segments`, kelvin.
RANGE_TOLERANCE_K = 5.0


def brief(row: dict[str, Any]) -> dict[str, Any]:
    """A method's row without its parameters and simulations."""
    return {k: row[k] for k in ("method", "n_params", "fit_estimation", "fit_validation", "passes")}


def excitation_text(design: str) -> str:
    exc = PAPER4_DESIGNS[design].excitation
    return repr(exc) if exc is not None else "none (feedforward alone)"


def load_segment(cycle: str = "whtc", seed: int = 0, start_s: float = PAPER4_SEGMENT_START_S,
                 n_samples: int = PAPER4_N_SAMPLES, excitation: ExcitationSignal | None = EXCITATION,
                 base_anr: float = PAPER4_BASE_ANR, align: bool = True) -> dict[str, Any]:
    """Raw inputs (Paper III's u1..u4 in ppm, g/min, K, mol/s) and tailpipe NOx [ppm] of one segment.

    With ``align`` one extra sample is simulated and the pairs are ``(u[k + 1], y[k])`` (see the module docstring),
    so the outputs are the same samples as the unaligned record's.
    """
    extra = 1 if align else 0
    ds = excitation_dataset(cycle, seed=seed, dt=PAPER4_DT_S, base_anr=base_anr, excitation=excitation,
                            start_s=start_s, duration_s=(n_samples + extra) * PAPER4_DT_S, cold_start=False)
    u = ds.u[extra:]
    y = ds.y[:n_samples, :1]
    return {"u": u, "y": y, "dt": ds.dt, "meta": {**ds.meta, "align": align, "n_samples": n_samples}}


def find_segments(cycles: Sequence[tuple[str, int]] = REPETITION_CYCLES, n_samples: int = PAPER4_N_SAMPLES,
                  max_segments: int = 10, step_s: float = 50.0) -> list[tuple[str, float, int]]:
    """Non-overlapping windows whose validation part stays in the estimation part's temperature range.

    The rule looks at the inlet temperature only (it does not depend on the dosing), never at a model: a
    validation part hotter or colder than anything in the estimation part tests extrapolation of exp(-a/T), which
    a 75/25 split of one record is not meant to (Paper III chose its split "to capture all NOx dynamics" in the
    estimation data). WHTC windows overlapping the main segment (350-950 s) are skipped. Windows are taken in
    time order per cycle, at most ``max_segments`` in all.
    """
    n_est = round(N_ESTIMATION_FRACTION * n_samples)
    width = (n_samples + 1) * PAPER4_DT_S
    main = (PAPER4_SEGMENT_START_S, PAPER4_SEGMENT_START_S + width)
    found: list[tuple[str, float, int]] = []
    for cycle, seed in cycles:
        temp = excitation_dataset(cycle, seed=seed, dt=PAPER4_DT_S, base_anr=PAPER4_BASE_ANR, excitation=None,
                                  cold_start=False).u[:, TEMPERATURE_COLUMN]
        next_free = 0.0
        for start in np.arange(0.0, len(temp) * PAPER4_DT_S - width + 1e-9, step_s):
            if start < next_free or (cycle == "whtc" and start < main[1] and start + width > main[0]):
                continue
            i0 = round(start / PAPER4_DT_S)
            est, val = temp[i0 + 1:i0 + 1 + n_est], temp[i0 + 1 + n_est:i0 + 1 + n_samples]
            if val.min() >= est.min() - RANGE_TOLERANCE_K and val.max() <= est.max() + RANGE_TOLERANCE_K:
                found.append((cycle, float(start), int(seed)))
                next_free = start + width
                if len(found) >= max_segments:
                    return found
    return found


def normalise(u: np.ndarray, y: np.ndarray, n_est: int) -> dict[str, Any]:
    """u3 -> exp(-a/T_in), then every signal scaled with the estimation part's mean and SD."""
    v = u.copy()
    v[:, TEMPERATURE_COLUMN] = arrhenius_transform(u[:, TEMPERATURE_COLUMN], ARRHENIUS_A_K)
    nu = Normalizer(names=SIM_INPUT_NAMES).fit(v[:n_est])
    ny = Normalizer(names=("tailpipe_nox_ppm",)).fit(y[:n_est])
    return {"U": nu.transform(v), "Y": ny.transform(y), "y_min": float(-ny.mean_[0] / ny.scale_[0]),
            "u_stats": nu.to_dict(), "y_stats": ny.to_dict(), "n_est": n_est}


def estimator(terms: Sequence[str], method: str, y_min: float, passes: int) -> RecursivePEM:
    """Paper III's RPEM set-up (module docstring)."""
    return RecursivePEM(n_states=2, terms=list(terms), sampling_period=PAPER4_DT_S, alpha=ALPHA, method=method,
                        stability_margin=0.015, theta0=np.zeros(len(terms)), R0=100.0, Lambda0=0.1,
                        output_limits=(y_min, np.inf), init="kalman",
                        kalman_options={"p0": 10.0, "q_state": 50.0, "q_theta": 0.0, "r": 3.0},
                        n_passes=passes)


def fit_one(terms: Sequence[str], method: str, d: dict[str, Any], passes: int) -> tuple[RecursivePEM, dict, tuple]:
    U, Y, ne = d["U"], d["Y"], d["n_est"]
    t0 = time.perf_counter()
    est = estimator(terms, method, d["y_min"], passes).fit(U[:ne], Y[:ne])
    y_est = est.predict(U[:ne], Y[0])[:, 0]
    y_val = est.predict(U[ne:], Y[ne])[:, 0]
    row = {"n_params": len(est.terms_), "fit_estimation": float(fit_percent(Y[:ne, 0], y_est)),
           "fit_validation": float(fit_percent(Y[ne:, 0], y_val)), "passes": max(1, len(est.pass_fits_)),
           "rejected_updates_last_pass": int(est.n_rejected_), "terms": list(est.terms_),
           "theta": est.theta_.tolist(), "theta_kalman_init": est.theta_init_.tolist(),
           "fit_time_s": round(time.perf_counter() - t0, 2)}
    return est, row, (y_est, y_val)


def fit_methods(d: dict[str, Any], passes: int) -> tuple[list[dict[str, Any]], dict[str, tuple]]:
    """The four rows of Table 2 on one normalised segment; also the simulated outputs per method."""
    rows, sims = [], {}
    for name in METHODS:
        method, kind = name.split("_")
        _, row, sim = fit_one(TERMS[kind], method, d, passes)
        row = {"method": name, **row, "published_fit_validation": PUBLISHED[name],
               "published_fit_estimation": PUBLISHED_ESTIMATION[kind]}
        rows.append(row)
        sims[name] = sim
    return rows, sims


def select_terms(d: dict[str, Any], passes: int, extra: Sequence[str] = EXTRA_TERMS) -> dict[str, Any]:
    """Backward elimination (midpoint) from the 16 terms plus ``extra`` on the validation FIT (Paper III)."""
    U, Y, ne = d["U"], d["Y"], d["n_est"]
    candidates = list(SCR_PAPER3_TERMS) + [t for t in extra if t not in SCR_PAPER3_TERMS]
    template = estimator(candidates, "midpoint", d["y_min"], passes)
    t0 = time.perf_counter()
    res = backward_elimination(template, candidates, U[:ne], Y[:ne], U[ne:], Y[ne:], min_terms=2)
    _, row, sim = fit_one(res.terms, "midpoint", d, passes)
    return {"method": "midpoint_selected", "candidates": candidates, "criterion": "validation FIT (Paper III)",
            "history": [{"n_terms": len(t), "fit_validation": float(f),
                         "removed": [c for c in prev if c not in t]}
                        for (prev, _), (t, f) in zip([(candidates, 0.0)] + res.history[:-1], res.history, strict=True)],
            **row, "search_time_s": round(time.perf_counter() - t0, 1), "_sim": sim}


def repeat_segments(segments: Sequence[tuple[str, float, int]], n_samples: int, passes: int, align: bool,
                    selected_terms: Sequence[str] | None) -> dict[str, Any]:
    """Table 2 (and the selected terms) on each segment; per-method mean/SD/min/max and the two verdicts."""
    per_segment = []
    n_est = round(N_ESTIMATION_FRACTION * n_samples)
    for cycle, start, seed in segments:
        seg = load_segment(cycle, seed, start, n_samples, align=align)
        try:
            d = normalise(seg["u"], seg["y"], n_est)
        except ValueError as exc:  # a constant output (e.g. full conversion) cannot be normalised
            per_segment.append({"cycle": cycle, "start_s": start, "seed": seed, "error": str(exc)})
            continue
        rows, _ = fit_methods(d, passes)
        fits = {r["method"]: r["fit_validation"] for r in rows}
        est_fits = {r["method"]: r["fit_estimation"] for r in rows}
        if selected_terms is not None:
            _, row, _ = fit_one(selected_terms, "midpoint", d, passes)
            fits["midpoint_selected"] = row["fit_validation"]
            est_fits["midpoint_selected"] = row["fit_estimation"]
        per_segment.append({"cycle": seg["meta"]["cycle"], "start_s": start, "seed": seed,
                            "fit_validation": fits, "fit_estimation": est_fits})
    ok = [s for s in per_segment if "fit_validation" in s]
    names = list(ok[0]["fit_validation"]) if ok else list(METHODS)
    summary = {}
    for m in names:
        v = np.array([s["fit_validation"][m] for s in ok], dtype=float)
        e = np.array([s["fit_estimation"][m] for s in ok], dtype=float)
        summary[m] = {"mean": float(np.mean(v)), "sd": float(np.std(v, ddof=1)) if len(v) > 1 else 0.0,
                      "median": float(np.median(v)), "min": float(np.min(v)), "max": float(np.max(v)),
                      "n_negative": int(np.sum(v < 0)), "mean_fit_estimation": float(np.mean(e))}

    def verdict(better: str, worse: str) -> dict[str, Any]:
        # paired ranks, not the mean: one diverging simulation (FIT of -1e5 %) would decide a mean
        v = paired_verdict([s["fit_validation"][better] - s["fit_validation"][worse] for s in ok])
        return {"median_difference": v["median_diff"], "mean_difference": v["mean_diff"], "wins": v["wins"],
                "segments": v["n"], "p_wilcoxon": v["p_wilcoxon"], "verdict": v["verdict"],
                "holds": v["verdict"] == "holds"}

    verdicts = {
        "nonlinear_beats_linear": {"midpoint": verdict("midpoint_nonlinear", "midpoint_linear"),
                                   "euler": verdict("euler_nonlinear", "euler_linear")},
        "midpoint_beats_euler": {"linear": verdict("midpoint_linear", "euler_linear"),
                                 "nonlinear": verdict("midpoint_nonlinear", "euler_nonlinear")},
    }
    for v in verdicts.values():
        v["holds"] = all(x["holds"] for x in v.values())
    return {"segments": per_segment, "summary": summary, "verdicts": verdicts, "n_samples": n_samples,
            "n_estimation": n_est, "excitation": repr(EXCITATION), "base_anr": PAPER4_BASE_ANR}


def table1(u: np.ndarray, y: np.ndarray, n_est: int) -> dict[str, Any]:
    """Mean and SD of the raw estimation signals beside Paper III's Table 1."""
    names = list(SIM_INPUT_NAMES) + ["tailpipe_nox_ppm"]
    x = np.column_stack([u[:n_est], y[:n_est]])
    return {n: {"mean": float(x[:, i].mean()), "sd": float(x[:, i].std()), "paper_mean": PAPER3_TABLE1_MEAN[n],
                "paper_sd": PAPER3_TABLE1_SD[n]} for i, n in enumerate(names)}
