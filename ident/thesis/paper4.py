"""Paper IV reproduced on the simulator: linear (M-I, M-II), Wiener (M-III) and Hammerstein-Wiener (M-IV, M-V)
models of the tailpipe NOx, beside the published Table 2.

Protocol (Paper IV, ALGORITHMS.md section 2): :func:`ident.plant_data.whtc_dataset` (1200 samples at 0.5 s from a
hot-WHTC segment, 350-950 s), first 900 samples for estimation, last 300 for validation, every signal normalised with
the estimation statistics. FIT and MSE on the simulated output in normalised units. Estimation figures: x(0)
estimated on the estimation record. Validation figures (``fit_validation``): the model simulated on through all
1200 samples from that x(0), scored on the last 300, so the validation state is the one the estimation data lead to
and no validation output is used (the thesis plots its validation simulation over samples 900-1200 of the one
record). For comparison ``fit_validation_x0_from_validation`` is the MATLAB ``compare`` figure: the validation
record simulated alone from an x(0) fitted to its own measured output (optimistic: 2 states per input absorb slow
errors with the validation output).

Dosing (``--design``, :data:`ident.plant_data.PAPER4_DESIGNS`): the table is the thesis' design, ``production``:
the truck's feedforward dosing (ANR 0.5 times the upstream NOx flow) and no excitation, because the thesis'
simulator was driven by signals measured on an engine running the WHTC, the urea dosing among them (Paper III
section 2; Paper IV section 2.2: urea "related to the NOx input concentration and to the exhaust flow", zero at low
flow or NOx). The ``excitation`` design's table follows it (random ANR steps 0 to 1; beyond the thesis, and until
2026-11-24 the table's design). History, for honesty: the segment and the base ANR were fixed before any fit; M-V's
estimation options and selection rule were revised after the excitation design's earlier tables (the first
reproduction's M-V is :data:`MV_PLAIN`; the rule with the thesis' nk = 1 alone gave 36.4 % carried on; adding nk = 0,
compared on development segments, gave the rule below and 54.2 %). On 2026-11-24, after those tables fell short
of the thesis' 68.05 %, the production design was tried as the one design faithful to the thesis' data, with the
models and the rule unchanged, and adopted; no other design was tried for the table. The nk = 0 candidates are
ours, not the thesis': with the thesis' nk = 1 alone M-V stays below 68.05 % on this record (every nk = 1 candidate
scores 61.3-67.9 % on seed 0).

=====  ==========================================================================================================
M-I    StateSpacePEM, order 2, simulation-error criterion
M-II   OutputError, nb = nf = 2, nk = 1 per input
M-III  Wiener: M-II's structure + output saturation at w_min = -mean(y)/SD(y) (zero NOx), started from M-II
M-IV   Hammerstein-Wiener: temperature through exp(-a/T), a = 1e4 K fixed, normalised; saturation as M-III
M-V    Hammerstein-Wiener: M-IV's (normalised) inputs through continuous piecewise-linear functions with 9, 5, 9, 5
       segments (knots at estimation-data quantiles, values estimated, held constant beyond the estimation range);
       nb = nf = 2; saturation as M-III; the temperature block non-decreasing (catalyst activity rises with
       temperature); started from M-IV with the same delays (fitted first on the same data; identity-like blocks);
       a roughness penalty on the blocks' slope changes.
=====  ==========================================================================================================

M-V's selection rule (estimation data only, :func:`ident.hammerstein_wiener.select_by_holdout`): 12 candidates,
the input delay nk in {1, 0} (the thesis' 1, or 0: our record samples y[k] at the end of the step over which u[k]
is held, and the inlet NOx reaches the tailpipe within one 0.5 s sample) times the roughness weight in {100, 10, 1,
0.1, 0.01, 0}; each is fitted on the first 675 estimation samples and scored by the FIT over samples 675-900 of its
output simulated through the estimation record from an x(0) estimated on the first 675; the best is refitted on all
900. The validation samples are not used by any choice. The candidate set and the rule were compared, under the
excitation design, on 12 other segments (WHSC, random cycles, WHTC 1200-1800 s; none overlapping this segment's
validation window), whose validation parts served as the development data: adding nk = 0 to the candidates raised
the median validation FIT there from 57 to 62 %. Tried there and not adopted (no systematic gain, the spread between
segments dominates): monotone blocks on every input, unit-gain normalisation of the linear block (``unit_gain``), a
steady-state initial condition (``initial="steady"``), blocked 4-fold cross-validation and the estimation cost as
selection criteria, a smoothness grid reaching 1e-4 or 1000.

Results (seed 0, about 30 s for both tables on one core)
-------------------------------------------------------

Production design (the thesis' data): M-V 79.2 % FIT on the estimation data and 78.3 % on the validation data
(thesis: 78.64 and 68.05 %); M-I 66.5 %, M-II 67.9 %, M-III 70.3 %, M-IV 67.4 % (thesis: 40.3, 38.9, 55.7, 61.0 %).
Our linear models do far better than the thesis' on this segment: with the feedforward the urea follows the NOx
flow, the hot catalyst's conversion stays within a narrow band, and the tailpipe NOx is nearly a scaled, lagged copy
of the inlet NOx. Seed 0 (the sensor noise that enters through the feedforward) is a favourable draw, 3rd of 10: over
seeds 0-9 (``--spread-seeds``) M-V's validation FIT has median 69.4 % (66.9 to 79.2 %), 6 of 10 seeds at or above
68.05 %, and M-V beats the better linear model by a median 1.9 points (-1.2 to 11.5; 10.4 on seed 0). The spread is
M-V's delay choice: the hold-out picks nk = 0 on 4 seeds (72.9-79.2 %) and nk = 1 on 6 (66.9-70.0 %);
``--diagnose`` shows the same on seed 0 (every nk = 0 candidate 76.6-79.7 % bar the unpenalised one, 37.5 %; every
nk = 1 candidate 61.3-67.9 %). The linear models hardly move between seeds (M-I 66.4-66.8 %, M-II 67.4-68.8 %).
Whether the thesis' conclusions hold beyond this segment under the production design is
``paper4_multisegment --design production``: over 15 segments they do not (M-V median 66.7 % against 70.1 % for
M-I; README).

Excitation design (beyond the thesis): M-V 69.2 % estimation, 54.2 % validation (67.9 % with the validation x(0) of
MATLAB ``compare``); M-IV 50.9 %, the linear models 48 %. Over seeds 0-9 (each its own excitation and noise) M-V has
median 32.6 % (-15.2 to 54.9 %; compare-style median 58.5 %). What limits it (``--design excitation --diagnose``):

* no M-V candidate reaches 68 %: fitted on the estimation data, the 12 candidates score -297 % to 57.0 %; fitted
  with the validation window in their data (samples 0-1197) they reach only 59-76 % there (70.9 % for the chosen
  one): the ANR steps empty and refill the NH3 store, and an additive sum of per-input blocks cannot make the inlet
  NOx's gain depend on the temperature or the stored NH3;
* the NH3 storage is a slow linear mode (pole about 0.99 on the urea input) whose error accumulates over the 150 s
  of validation data simulated on from the estimation data (fitting the 8 states to the validation output gains 13
  points for M-V);
* tried beyond the thesis and not better: a multiplicative structure (tailpipe NOx = inlet NOx x a slip fraction
  from a Hammerstein-Wiener model of urea, exp(-a/T) and flow): 55.8 % validation; free knots or linear
  extrapolation of the piecewise-linear blocks do not raise the ceiling.

Run by ``python -m experiments.reproduce_paper4`` (figures and ``results.json`` in ``runs/reproduce_paper4/``).
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from ident.dataset import IODataset
from ident.hammerstein_wiener import (
    Arrhenius,
    HammersteinWiener,
    Identity,
    PiecewiseLinear,
    Saturation,
    select_by_holdout,
)
from ident.linear import OutputError, StateSpacePEM
from ident.metrics import compare, fit_percent, mse
from ident.plant_data import (
    PAPER4_DEFAULT_DESIGN,
    PAPER4_N_ESTIMATION,
    PAPER4_N_SAMPLES,
    whtc_dataset,
)
from ident.preprocessing import ARRHENIUS_A_K, Normalizer

#: Paper IV Table 2: estimation FIT %, estimation MSE, validation FIT %, validation MSE.
PUBLISHED = {"M-I": (61.76, 0.156, 40.33, 0.245), "M-II": (68.93, 0.103, 38.92, 0.256),
             "M-III": (75.36, 0.065, 55.67, 0.135), "M-IV": (72.48, 0.081, 61.03, 0.104),
             "M-V": (78.64, 0.049, 68.05, 0.070)}
MODELS = ("M-I", "M-II", "M-III", "M-IV", "M-V")
PWL_SEGMENTS = (9, 5, 9, 5)
TEMPERATURE_COLUMN = 2
#: M-V's estimation options (see :func:`fit_models`).
MV_DEFAULT: dict[str, Any] = {"init": "m4", "smoothness": (0.0, 1e-2, 1e-1, 1.0, 10.0, 100.0), "nk": (1, 0),
                              "monotone": (TEMPERATURE_COLUMN,), "regularization": 1e-3}
#: Fraction of the estimation data (its end) held out to choose M-V's candidate (:func:`select_by_holdout`).
MV_HOLDOUT = 0.25
#: The M-V of the first reproduction (best linear start, no roughness penalty, no monotonicity), for comparison.
MV_PLAIN: dict[str, Any] = {"init": "oe", "smoothness": 0.0, "nk": (1,), "monotone": (),
                             "regularization": 1e-3}


def fit_models(ds: IODataset, n_estimation: int = PAPER4_N_ESTIMATION, output: int = 0,
               models: tuple[str, ...] = MODELS, mv: dict[str, Any] | None = None
               ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Fit M-I..M-V to one output of ``ds`` (inputs in Paper IV's order, temperature in K in column 2).

    ``mv`` overrides M-V's options (:data:`MV_DEFAULT`): ``init`` "oe" (the best linear model through identity
    blocks) or "m4" (M-IV, fitted first on the same estimation data, with identity-like piecewise-linear blocks);
    ``smoothness`` and ``nk`` (sequences: every pair is a candidate, chosen on the last :data:`MV_HOLDOUT` of the
    estimation data by :func:`~ident.hammerstein_wiener.select_by_holdout`); ``monotone`` (input columns whose block
    is constrained non-decreasing); ``regularization`` (ridge toward the identity).

    Returns the table rows and a dict with the normalised records, the models' input records (``u_est``, ``u_val``),
    the fitted models and the simulated outputs for plotting.
    """
    ds = ds.select(outputs=[output])
    est, val = ds.split(index=n_estimation)
    nu = Normalizer(names=ds.input_names).fit(est.u)
    ny = Normalizer(names=ds.output_names).fit(est.y)
    ue, uv = nu.transform(est.u), nu.transform(val.u)
    ye, yv = ny.transform(est.y), ny.transform(val.y)
    w_min = float(-ny.mean_[0] / ny.scale_[0])  # zero NOx in normalised units
    # M-IV's inputs: temperature through the fixed exp(-a/T), normalised with the estimation statistics
    arr = Arrhenius(a=ARRHENIUS_A_K)
    arr.initial_params(est.u[:, TEMPERATURE_COLUMN])

    def v_iv(raw: np.ndarray, norm: np.ndarray) -> np.ndarray:
        out = norm.copy()
        out[:, TEMPERATURE_COLUMN] = arr.value(raw[:, TEMPERATURE_COLUMN], np.array([ARRHENIUS_A_K]))
        return out

    ve, vv = v_iv(est.u, ue), v_iv(val.u, uv)
    # M-IV takes the raw temperature (K) and applies exp(-a/T) inside the model; the other inputs normalised
    he, hv = ue.copy(), uv.copy()
    he[:, TEMPERATURE_COLUMN] = est.u[:, TEMPERATURE_COLUMN]
    hv[:, TEMPERATURE_COLUMN] = val.u[:, TEMPERATURE_COLUMN]
    n_in = ds.n_inputs
    sims: dict[str, Any] = {"y_est": ye[:, 0], "y_val": yv[:, 0], "scale": float(ny.scale_[0]),
                            "mean": float(ny.mean_[0]), "t_est": est.time, "t_val": val.time,
                            "u_est": {}, "u_val": {}}
    rows = []
    fitted: dict[str, Any] = {}
    for name in models:
        t0 = time.perf_counter()
        if name == "M-I":
            model, data = StateSpacePEM(order=2, focus="simulation"), (ue, uv)
        elif name == "M-II":
            model, data = OutputError(nb=2, nf=2, nk=1), (ue, uv)
        elif name == "M-III":
            model = HammersteinWiener(output_block=Saturation(lower=w_min), init_model=fitted.get("M-II"))
            data = (ue, uv)
        elif name == "M-IV":
            blocks = [Identity() for _ in range(n_in)]
            blocks[TEMPERATURE_COLUMN] = Arrhenius(a=ARRHENIUS_A_K)
            model, data = HammersteinWiener(input_blocks=blocks, output_block=Saturation(lower=w_min)), (he, hv)
        elif name == "M-V":
            opt = {**MV_DEFAULT, **(mv or {})}
            segs = PWL_SEGMENTS if n_in == len(PWL_SEGMENTS) else (5,) * n_in
            smooth = [float(x) for x in np.atleast_1d(opt["smoothness"])]
            cands, labels = [], []
            for nk in opt["nk"]:
                pwl = [PiecewiseLinear(n_segments=s, extrapolation="constant", monotone=i in opt["monotone"])
                       for i, s in enumerate(segs)]
                # M-IV is a Wiener model on M-IV's inputs (exp(-a/T) with a fixed): the template fitted inside the fit
                init = HammersteinWiener(output_block=Saturation(lower=w_min), nk=nk) if opt["init"] == "m4" else None
                for lam in sorted(smooth, reverse=True):   # smoother first: ties go to the smoother candidate
                    cands.append(HammersteinWiener(input_blocks=pwl, output_block=Saturation(lower=w_min),
                                                   init_model=init, nk=nk, smoothness=lam,
                                                   regularization=opt["regularization"]))
                    labels.append(f"nk={nk} smoothness={lam:g}")
            if len(cands) > 1:
                model, ho_scores = select_by_holdout(cands, ve, ye, holdout=MV_HOLDOUT)
                chosen = labels[int(np.argmax(ho_scores))]
            else:
                model, ho_scores, chosen = cands[0], [], labels[0]
            data = (ve, vv)
        else:
            raise ValueError(f"unknown model {name!r}")
        if not hasattr(model, "b_"):
            model.fit(data[0], ye)
        fit_s = time.perf_counter() - t0
        fitted[name] = model
        ce, cv0 = compare(model, data[0], ye), compare(model, data[1], yv)
        # the validation output simulated on from the end of the estimation data: x(0) estimated on the estimation
        # record only, the model run through all 1200 samples, scored on the last 300 (no validation output used)
        y_run = np.asarray(model.predict(np.vstack([data[0], data[1]]), y0=ye), dtype=float)[:, :1]
        y_val_hat = y_run[len(ye):]
        fit_v, mse_v = float(fit_percent(yv, y_val_hat)), float(mse(yv, y_val_hat))
        sims[name] = (ce.y_hat[:, 0], y_val_hat[:, 0])
        sims["u_est"][name], sims["u_val"][name] = data
        row = {"model": name, "n_params": int(model.n_params_), "fit_estimation": float(ce.fit),
               "fit_validation": fit_v, "mse_estimation": float(ce.mse), "mse_validation": mse_v,
               "fit_validation_x0_from_validation": float(cv0.fit),
               "mse_validation_x0_from_validation": float(cv0.mse), "fit_time_s": round(fit_s, 2)}
        if name == "M-V":
            row["chosen"] = chosen
            # no hold-out scores with a single candidate: {}
            row["holdout_fit"] = {k: round(v, 2) for k, v in zip(labels, ho_scores, strict=False)}
        if name in PUBLISHED:
            p = PUBLISHED[name]
            row["published"] = {"fit_estimation": p[0], "mse_estimation": p[1], "fit_validation": p[2],
                                "mse_validation": p[3]}
        rows.append(row)
    sims["models"] = fitted
    return rows, sims


def diagnose_mv(ds: IODataset, mv: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Why M-V's validation FIT is what it is: for every candidate of M-V's selection (each (nk, smoothness) pair of
    ``mv``/:data:`MV_DEFAULT`),

    * ``fit_validation``: the candidate fitted on the 900 estimation samples and scored as the table's M-V (the
      figure the selection rule could reach with a perfect choice; it uses the validation output, so it is a
      diagnostic, never a selection criterion);
    * ``fit_validation_ceiling``: the candidate fitted on samples 0 to N-3 (the whole record but the last two, which
      :func:`fit_models` keeps as its validation part), validation window included, and scored on samples 900 to N-3:
      about what the structure can do there when it has seen the window (FIT is invariant to the normalisation).
    """
    opt = {**MV_DEFAULT, **(mv or {})}
    n_all = len(ds)
    out = []
    for nk in opt["nk"]:
        for lam in sorted((float(x) for x in np.atleast_1d(opt["smoothness"])), reverse=True):
            one = {**opt, "nk": (nk,), "smoothness": (lam,)}
            rows, _ = fit_models(ds, models=("M-V",), mv=one)
            _, sims = fit_models(ds, n_estimation=n_all - 2, models=("M-V",), mv=one)
            y, y_hat = sims["y_est"], sims["M-V"][0]
            ceiling = float(fit_percent(y[PAPER4_N_ESTIMATION:], y_hat[PAPER4_N_ESTIMATION:]))
            out.append({"nk": nk, "smoothness": lam, "fit_estimation": rows[0]["fit_estimation"],
                        "fit_validation": rows[0]["fit_validation"], "fit_validation_ceiling": ceiling})
    return out


def seed_spread(seeds: list[int], models: tuple[str, ...] = MODELS, design: str = PAPER4_DEFAULT_DESIGN
                ) -> dict[str, Any]:
    """The table over other seeds of the same data design and segment (each seed draws its own sensor noise and,
    under the excitation design, its own dosing excitation): per model, the validation FIT (carried on, and MATLAB
    ``compare``-style) per seed, with the median, min and max. How much of one table is the draw."""
    if not seeds:
        raise ValueError("seeds must name at least one seed")
    per_seed, chosen = {}, {}
    for seed in seeds:
        rows, _ = fit_models(whtc_dataset(seed=int(seed), design=design)[:PAPER4_N_SAMPLES], models=models)
        per_seed[int(seed)] = {r["model"]: (r["fit_validation"], r["fit_validation_x0_from_validation"])
                               for r in rows}
        chosen[int(seed)] = next((r["chosen"] for r in rows if r["model"] == "M-V"), None)
    out: dict[str, Any] = {"seeds": [int(s) for s in seeds], "design": design, "models": {}}
    if "M-V" in models:
        out["mv_chosen"] = [chosen[s] for s in out["seeds"]]
    for m in models:
        carried = np.array([per_seed[s][m][0] for s in out["seeds"]])
        comp = np.array([per_seed[s][m][1] for s in out["seeds"]])
        out["models"][m] = {"fit_validation": carried.tolist(), "fit_validation_x0_from_validation": comp.tolist(),
                            "median": float(np.median(carried)), "min": float(carried.min()),
                            "max": float(carried.max()), "median_x0_from_validation": float(np.median(comp)),
                            "max_x0_from_validation": float(comp.max())}
    return out
