"""Identification for control of the dosing loop (issue 18): the RPEM and Hammerstein-Wiener models the black-box
NMPCs (:mod:`control.blackbox`) run on.

* :func:`identification_records`: control-relevant records (:mod:`ident.control_relevant`) over many random
  cycles (seeds :data:`IDENT_SEEDS`; never the calibration cycles 5-8 nor the held-out WHTC/WHSC).
* :func:`fit_rpem_for_control`: the thesis' polynomial chain ODE (RPEM model class) with two outputs (log NOx slip
  ratio, log NH3) on measured-signal features (stoichiometric surplus, inlet NOx, exp(-a/T), flow), storage-capable
  regressor products, an equation-error start and an optional multi-step prediction-error refinement.
* :func:`fit_hw_for_control`: a two-output Hammerstein-Wiener model (static input blocks, linear dynamics, static
  output blocks) on the same features and outputs, fitted on all records end to end (:func:`concat_records`).
* :func:`hw_linear_export`: its CasADi step and linear part for exact multi-step NMPC stages.
* :func:`filtered_inputs` (``input_filters`` of both fits): first-order low-pass filtered copies of features as
  further model inputs, e.g. the surplus over 300 s: a memory of past over- and under-dosing for models without a
  storage state (a linear filter of a measured signal; the NMPC propagates it, :class:`control.blackbox.BlackBoxModel`).

Black-box boundary (issue 18): no Arrhenius kinetics and no storage balance inside either model; the features are
static transforms of measured signals (exp(-a/T) as in Paper III).
"""
from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import casadi as ca
import numpy as np

from ident.hammerstein_wiener import HammersteinWiener


def concat_records(us: Sequence[np.ndarray], ys: Sequence[np.ndarray], warmup: int = 120
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, y, weights) of the records end to end, weight 0 on each record's first ``warmup`` samples."""
    w = [np.r_[np.zeros(min(warmup, len(u))), np.ones(max(len(u) - warmup, 0))] for u in us]
    return np.vstack(us), np.vstack(ys), np.concatenate(w)


def hw_linear_export(model: HammersteinWiener) -> tuple[ca.Function, np.ndarray, Any]:
    """``(step, A, bfun)`` of a fitted :class:`HammersteinWiener`: ``step(x, z) -> (x_next, y)`` (its
    ``to_casadi``) and the linear part ``x_next = A x + bfun(z)`` (``bfun(z) = B v(z)``, v the input blocks), for
    exact multi-step stages of the NMPC."""
    step = model.to_casadi()
    z = ca.SX.sym("z", model.n_inputs_)
    v = ca.vertcat(*[b.casadi(z[i], p) for i, (b, p) in
                     enumerate(zip(model.input_blocks_, model.input_params_, strict=True))])
    bfun_f = ca.Function("bv", [z], [ca.mtimes(ca.DM(model.B_), v)])
    return step, np.asarray(model.A_, float), lambda zz: bfun_f(zz)


def hw_steady_state(A: np.ndarray, bfun: Any, z: np.ndarray) -> np.ndarray:
    """The state at rest under the held input ``z``: (I - A)^-1 B v(z)."""
    bv = np.asarray(bfun(ca.DM(z))).ravel()
    return np.linalg.solve(np.eye(A.shape[0]) - A, bv)


# ------------------------------------------------------------------------------ the production identification
#: random-cycle seeds of the identification records (calibration cycles are 5-8, held-out cycles the WHTC/WHSC)
IDENT_SEEDS = tuple(range(10, 18))
#: random-cycle seed of the validation record (k-step FIT)
VALIDATION_SEED = 18
#: ramped-mode (WHSC-like, ``random_cycle(kind="ramped_modes")``) cycle seeds of further identification records
#: beside the transient ones; none: the models are identified on transient driving only [chosen, issue 18 fifth
#: round: ``python -m experiments.calibrate_black_box --models rpem hammerstein_wiener --seeds 5 6 7 8 19 20 21 22
#: --duration 600 --ramped-seeds 5 6 7 8 --ramped-duration 1200 --ident-ramped-seeds 10 11 12 13 --configs ...``
#: (calibration cycles only). With the ramped records (24 records) the best design within 8 ppm was RPEM 1.355 g/kWh
#: (upper band 1.5, at 2.56 ppm; 2.5: 1.109 at 21.9) and Hammerstein-Wiener 0.905 (upper band 2.5, at 3.41; its
#: default band 6: 0.699 at 21.2), against 1.249 and 0.756 with the transient records only: not kept]
IDENT_RAMPED_SEEDS: tuple[int, ...] = ()
#: seconds of each ramped-mode identification record
IDENT_RAMPED_DURATION_S = 1200.0
#: the designs of the identification records (:mod:`ident.control_relevant`): open-loop ANR 0.8-1.3 with over-dosing
#: bursts, and the edge-seeking relay around the slip edge
DESIGNS = ("open_loop", "edge_seeking")
#: model inputs: stoichiometric surplus [ppm], inlet NOx [ppm], exp(-a/T) [-], exhaust flow [mol/s]
CONTROL_FEATURES = ("surplus_ppm", "nox_ppm", "exp_t", "flow")
#: scale of each feature into order one for the RPEM's polynomial (ppm -> 1e3 ppm; flow mol/s -> 10 mol/s; the
#: logarithmic spill-over features as the log outputs) [chosen]
RPEM_FEATURE_SCALES: dict[str, float] = {"surplus_ppm": 1e-3, "nox_ppm": 1e-3, "exp_t": 1.0, "flow": 0.1,
                                         "log_deficit": 0.2, "log_excess": 0.2}
RPEM_FEATURE_SCALE = tuple(RPEM_FEATURE_SCALES[f] for f in CONTROL_FEATURES)
#: the spill-over features (:mod:`ident.control_relevant`) an RPEM may add to :data:`CONTROL_FEATURES`
#: (``fit_rpem_for_control(features=CONTROL_FEATURES + SPILL_FEATURES)``)
SPILL_FEATURES = ("log_deficit", "log_excess")
#: outputs: log NOx slip ratio and log NH3 ppm (:mod:`ident.control_relevant`), times this scale [chosen]
RPEM_OUTPUT_SCALE = (0.2, 0.2)
NOX_KIND, NH3_KIND = "logratio", "log"


def identification_records(seeds: Sequence[int] = IDENT_SEEDS, designs: Sequence[str] = DESIGNS,
                           duration_s: float | None = None, cycle: str = "random") -> list[Any]:
    """Control-relevant identification records (:class:`ident.control_relevant.Record`): every design on the random
    cycle of every seed (``"open_loop"``, ``"edge_seeking"``, or ``"overdosing"``: the single open-loop over-dosing
    design of :func:`control.loop.black_box_excitation`, the ablation's "no control-relevant excitation").
    ``cycle``: the random-cycle family (:data:`scr_env.cycles.RANDOM_CYCLES`: ``"random"`` transient driving,
    ``"random_modes"`` WHSC-like ramped modes)."""
    from ident.control_relevant import Record, edge_seeking_record, open_loop_record

    out = []
    for d in designs:
        for s in seeds:
            if d == "open_loop":
                out.append(open_loop_record(int(s), duration_s=duration_s, cycle=cycle))
            elif d == "edge_seeking":
                out.append(edge_seeking_record(int(s), duration_s=duration_s, cycle=cycle))
            elif d == "overdosing":
                from ident.control_relevant import random_family
                from ident.excitation import RandomSteps
                from ident.plant_data import excitation_dataset

                kw = {} if duration_s is None else {"random_cycle_duration_s": float(duration_s)}
                ds = excitation_dataset(random_family(cycle), seed=int(s), base_anr=1.0,
                                        excitation=RandomSteps(-0.9, 1.0, 20.0, 200.0), **kw)
                out.append(Record(u=ds.u, y=ds.y, nh3_sensor=ds.y[:, 1], dt=ds.dt, meta={"kind": d, "seed": int(s)}))
            else:
                raise ValueError(f"designs: unknown design {d!r}; known: open_loop, edge_seeking, overdosing")
    return out


def input_filter_coefficient(tau_s: float, dt: float) -> float:
    """The per-sample gain a of a first-order low-pass with time constant ``tau_s`` [s] sampled every ``dt`` [s]
    (exact for an input held over the sample): ``s+ = s + a (z - s)``, ``a = 1 - exp(-dt / tau_s)``."""
    return float(-np.expm1(-float(dt) / float(tau_s)))


def check_input_filters(input_filters: Sequence[Sequence[Any]], features: Sequence[str]) -> list[tuple[int, float]]:
    """``[(feature, tau_s), ...]`` (the setting ``input_filters``) as ``[(column of the feature, tau_s)]``;
    ValueError naming ``input_filters`` for a feature the model does not have or a time constant that is not > 0."""
    out = []
    for spec in input_filters:
        if isinstance(spec, (str, bytes)) or len(spec) != 2:
            raise ValueError(f"input_filters: each entry is (feature, time constant in s), got {spec!r}")
        name, tau = spec
        if name not in features:
            raise ValueError(f"input_filters: feature {name!r} is not among the model's features {list(features)}")
        if isinstance(tau, bool) or not isinstance(tau, (int, float, np.number)) or not (np.isfinite(tau) and tau > 0):
            raise ValueError(f"input_filters: the time constant of {name!r} must be a number > 0 [s], got {tau!r}")
        out.append((list(features).index(name), float(tau)))
    return out


def filtered_inputs(z: np.ndarray, filters: Sequence[tuple[int, float]], dt: float) -> np.ndarray:
    """(n, len(filters)) low-pass filtered feature columns of one record: for each ``(column i, tau_s)``, the
    first-order filter ``s[0] = z[0, i]`` (at rest), ``s[t] = s[t-1] + a (z[t-1, i] - s[t-1])``
    (:func:`input_filter_coefficient`), so that ``s[t]`` depends on the inputs before t only, as the model's step
    into sample t (the NMPC propagates the same recursion, :class:`control.blackbox.BlackBoxModel`)."""
    from scipy.signal import lfilter

    z = np.asarray(z, float)
    out = np.empty((len(z), len(filters)))
    for c, (i, tau) in enumerate(filters):
        a = input_filter_coefficient(tau, dt)
        out[0, c] = z[0, i]
        if len(z) > 1:
            out[1:, c] = lfilter([a], [1.0, a - 1.0], z[:-1, i], zi=[(1.0 - a) * z[0, i]])[0]
    return out


def model_arrays(records: Sequence[Any], info: dict[str, Any]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per record (model inputs, outputs) of a model described by ``info`` (:func:`fit_rpem_for_control`,
    :func:`fit_hw_for_control`): the features of :func:`control_arrays`, then their ``input_filters`` columns;
    unnormalised."""
    arrs = control_arrays(records, info["features"], info.get("nox_kind", NOX_KIND), info.get("nh3_kind", NH3_KIND))
    filters = check_input_filters(info.get("input_filters", ()), info["features"])
    if not filters:
        return arrs
    return [(np.column_stack([z, filtered_inputs(z, filters, float(r.dt))]), y) for (z, y), r in
            zip(arrs, records, strict=True)]


def control_arrays(records: Sequence[Any], features: Sequence[str] = CONTROL_FEATURES, nox_kind: str = NOX_KIND,
                   nh3_kind: str = NH3_KIND) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per record (features (n, m), outputs (n, 2): NOx and NH3 in the ``nox_kind`` / ``nh3_kind`` representation,
    default log NOx slip ratio and log NH3 ppm), unscaled."""
    from ident.control_relevant import FeatureMap, nh3_output, nox_output

    fm = FeatureMap(tuple(features))
    return [(fm.from_record(r.u), np.column_stack([nox_output(nox_kind, r.y[:, 0], r.u[:, 0]),
                                                   nh3_output(nh3_kind, r.y[:, 1])])) for r in records]


def _check_inputs(n_inputs: int) -> None:
    if isinstance(n_inputs, bool) or not isinstance(n_inputs, (int, np.integer)) \
            or not len(CONTROL_FEATURES) <= n_inputs <= len(CONTROL_FEATURES) + len(SPILL_FEATURES):
        raise ValueError(f"n_inputs must be {len(CONTROL_FEATURES)} (CONTROL_FEATURES) to "
                         f"{len(CONTROL_FEATURES) + len(SPILL_FEATURES)} (with SPILL_FEATURES), got {n_inputs!r}")


def rpem_storage_terms(k: int, n_inputs: int = 4, n_filtered: int = 0) -> list[str]:
    """Candidate regressor of chain ``k`` (1 = NOx, 2 = NH3) of the two-output, one-state-per-chain RPEM: the
    thesis' polynomial in states and inputs extended with products that can express storage (state x input,
    state x input x input, input x input) and derivatives of the exogenous inputs (issue 18); inputs as
    :data:`CONTROL_FEATURES` (u1 surplus, u2 inlet NOx, u3 exp(-a/T), u4 flow). Inputs beyond the fourth (the
    :data:`SPILL_FEATURES`) add themselves, times the own state and times exp(-a/T). The ``n_filtered`` low-pass
    filtered inputs (``input_filters``, numbered after the ``n_inputs`` features) add themselves, times each state,
    times every exogenous input and the temperature's derivative (a surplus accumulated in the past meeting a
    heat-up), times the surplus, squared, and times the own state and exp(-a/T)."""
    _check_inputs(n_inputs)
    if isinstance(n_filtered, bool) or not isinstance(n_filtered, (int, np.integer)) or n_filtered < 0:
        raise ValueError(f"n_filtered must be an integer >= 0, got {n_filtered!r}")
    o, q = f"x{k}", ("x2" if k == 1 else "x1")
    extra = [f"u{j}" for j in range(5, n_inputs + 1)]
    filt = [f"u{j}" for j in range(n_inputs + 1, n_inputs + n_filtered + 1)]
    t = ["1", o, q, "u1", "u2", "u3", "u4", *extra, *filt, f"{o}*{q}", f"{o}^2", f"{q}^2"]
    for x in (o, q):
        t += [f"{x}*u{j}" for j in (1, 2, 3, 4)]
    t += ["u1*u3", "u1*u4", "u2*u3", "u2*u4", "u3*u4", f"{o}*u1*u3", f"{o}*u1*u4", f"{q}*u1*u3"]
    t += ["u3'", "u4'", "u2'", f"{o}*u3'", f"{o}*u4'", f"{o}*u2'"]
    t += [f"{o}*{u}" for u in extra] + [f"{u}*u3" for u in extra]
    for u in filt:
        t += [f"{o}*{u}", f"{q}*{u}", f"{u}*u3", f"{u}*u4", f"{u}*u2", f"{u}*u3'", f"{u}*u1", f"{u}^2",
              f"{o}*{u}*u3"]
    return t


def paper3_terms(k: int, n_inputs: int = 4, n_filtered: int = 0) -> list[str]:
    """The ablation's "no storage regressors": the linear regressor of Paper III per chain (states, inputs, 1);
    the ``n_filtered`` filtered inputs are inputs too."""
    _check_inputs(n_inputs)
    return ["1", f"x{k}", ("x2" if k == 1 else "x1"), *[f"u{j}" for j in range(1, n_inputs + n_filtered + 1)]]


#: numbers of storage terms per chain the term selection tries, beyond Paper III's linear regressor [chosen]
EXTRA_TERM_COUNTS = (0, 2, 4, 6, 9)
#: the multi-step horizon of the term selection [samples of 0.5 s]: 80 s, the NMPC's horizon
SELECTION_HORIZON = 160


def _equation_error(tmpl: Any, recs: Sequence[tuple[np.ndarray, np.ndarray]], k: int
                    ) -> tuple[np.ndarray, np.ndarray]:
    """(Phi, b) of chain k's equation error (Euler difference quotient against the terms at the measured outputs)."""
    s = tmpl.structure_
    E = s.exponents[np.flatnonzero(s.owner == k)]
    A, b = [], []
    for z, y in recs:
        WS, _, _, _ = tmpl._rows(z, carry=False)
        v = np.column_stack([y[:-1], WS[1:]])
        A.append(np.prod(v[:, None, :] ** E[None], axis=2))
        b.append((y[1:, k] - y[:-1, k]) / tmpl.ts_model)
    return np.vstack(A), np.concatenate(b)


def _rpem_ls(terms: list[list[str]], recs: Sequence[tuple[np.ndarray, np.ndarray]], dt: float, ridge: float
             ) -> tuple[Any, np.ndarray]:
    from ident.rpem import RecursivePEM

    tmpl = RecursivePEM(n_states=1, terms=terms, sampling_period=dt, alpha=1.0)
    tmpl._setup(recs[0][0].shape[1], 2)
    theta = np.zeros(tmpl.structure_.n_params)
    for k in range(2):
        A, b = _equation_error(tmpl, recs, k)
        theta[tmpl.structure_.owner == k] = np.linalg.solve(A.T @ A + ridge * len(b) * np.eye(A.shape[1]), A.T @ b)
    return tmpl, theta


def fit_rpem_for_control(records: Sequence[Any], storage_terms: bool = True, validation: Sequence[Any] | None = None,
                         multistep_horizon: int = 0, max_nfev: int = 10, ridge: float = 1e-3,
                         features: Sequence[str] = CONTROL_FEATURES,
                         input_filters: Sequence[Sequence[Any]] = ()) -> tuple[Any, dict[str, Any]]:
    """The RPEM for the NMPC: two one-state chains (log NOx slip ratio, log NH3) on ``features``: the four of
    :data:`CONTROL_FEATURES` first, optionally followed by :data:`SPILL_FEATURES`.

    The regressor of each chain is Paper III's linear one (:func:`paper3_terms`) plus, with ``storage_terms``, the
    storage-capable candidates of :func:`rpem_storage_terms` in the order of the thesis' forward selection
    (orthogonal least squares on the equation error), as many as :data:`EXTRA_TERM_COUNTS` allows with the best
    multi-step prediction FIT over :data:`SELECTION_HORIZON` samples on the ``validation`` records (default: the
    last record; Shook, Mohtadi and Shah 1991: the predictor the NMPC uses). Parameters: ridge equation-error
    estimate, refined with ``multistep_horizon`` > 0 by the multi-step prediction error
    (:func:`ident.rpem.multistep.fit_multistep`). ``input_filters``: ``[(feature, tau_s), ...]``, first-order
    low-pass filtered copies of features added as further inputs (:func:`filtered_inputs`; a linear dynamic
    transform of a measured signal, as the Laguerre-type filtered regressors of black-box identification: a surplus
    dosed minutes ago is the record of what the catalyst may hold, which the one-state chains cannot keep), with
    storage candidates of their own. Returns the fitted
    :class:`~ident.rpem.RecursivePEM` (inputs: scaled features, then the filtered ones) and the JSON-able
    description the NMPC needs."""
    from ident.rpem.multistep import fit_multistep, rpem_from_theta
    from ident.rpem.storage_terms import ols_order

    features = tuple(features)
    n0 = len(CONTROL_FEATURES)
    if features[:n0] != CONTROL_FEATURES or any(f not in SPILL_FEATURES for f in features[n0:]) \
            or len(set(map(str, features))) != len(features):
        raise ValueError(f"features must be {CONTROL_FEATURES} followed by any of {SPILL_FEATURES}, got {features!r}")
    filters = check_input_filters(input_filters, features)
    m, nf = len(features), len(filters)
    zs = np.asarray([RPEM_FEATURE_SCALES[f] for f in features] + [RPEM_FEATURE_SCALES[features[i]] for i, _ in filters])
    ys = np.asarray(RPEM_OUTPUT_SCALE)
    spec = {"features": list(features), "input_filters": [[features[i], tau] for i, tau in filters]}
    recs = [(z * zs, y * ys) for z, y in model_arrays(records, spec)]
    dt = float(records[0].dt)
    base = [paper3_terms(k, m, nf) for k in (1, 2)]
    candidates = [base]
    selection: dict[str, Any] = {}
    if storage_terms:
        full = [rpem_storage_terms(k, m, nf) for k in (1, 2)]
        tmpl, _ = _rpem_ls(full, recs, dt, ridge)
        order = []
        for k in range(2):
            A, b = _equation_error(tmpl, recs, k)
            forced = [full[k].index(t) for t in base[k]]
            order.append([full[k][i] for i in ols_order(A, b, A.shape[1], forced=forced)])
        candidates = [[o[:len(base[k]) + n] for k, o in enumerate(order)] for n in EXTRA_TERM_COUNTS]
    val = list(validation) if validation is not None else list(records[-1:])
    best = None
    for terms in candidates:
        tmpl, theta = _rpem_ls(terms, recs, dt, ridge)
        if multistep_horizon > 0:
            theta = fit_multistep(tmpl, recs, horizon=int(multistep_horizon), theta0=theta, ridge=1e-5,
                                  max_nfev=max_nfev)
        model = rpem_from_theta(tmpl, theta, m + nf, 2)
        info = _rpem_info(terms, zs, ys, multistep_horizon, len(records), features)
        info["input_filters"] = spec["input_filters"]
        score = np.mean([k_step_fit(model.to_casadi(), info, r, SELECTION_HORIZON) for r in val]) if storage_terms \
            else 0.0
        score = float(score) if np.isfinite(score) else -np.inf
        selection[str(len(terms[0]) - len(base[0]))] = score
        if best is None or score > best[0]:
            best = (score, model, info)
    _, model, info = best
    info["selection_kstep_fit_percent"] = selection
    return model, info


def _rpem_info(terms: list[list[str]], zs: np.ndarray, ys: np.ndarray, multistep_horizon: int, n_records: int,
               features: Sequence[str] = CONTROL_FEATURES) -> dict[str, Any]:
    lo = ys * np.log([1e-4, 1e-2]) - 0.2   # log floors of the outputs (ident.control_relevant), a margin below
    hi = ys * np.log([2.0, 5000.0])         # NOx ratio 2, NH3 5000 ppm
    return {"kind": "rpem", "features": list(features), "z_mean": [0.0] * len(zs),
            "z_scale": (1.0 / zs).tolist(), "y_mean": [0.0, 0.0], "y_scale": (1.0 / ys).tolist(),
            "nox_kind": NOX_KIND, "nh3_kind": NH3_KIND, "state_bounds": [lo.tolist(), hi.tolist()],
            "initial_state": (ys * np.log([1.0, 1e-2])).tolist(), "terms": [list(t) for t in terms],
            "multistep_horizon": int(multistep_horizon), "n_records": n_records}


#: output blocks :func:`fit_hw_for_control` knows: ``"identity"``, ``"pwl"`` (piecewise-linear, ``n_out_knots``
#: segments, held constant beyond its outer knots: a spill-over that levels off), ``"saturation"`` (estimated lower
#: limit, started at the output's floor in the data: no slip, full conversion), ``"deadzone"`` (estimated dead zone)
HW_OUTPUT_BLOCKS = ("identity", "pwl", "saturation", "deadzone")


def _hw_output_block(kind: str, n_out_knots: int, floor: float) -> Any:
    from ident.hammerstein_wiener.blocks import DeadZone, Identity, PiecewiseLinear, Saturation

    if kind == "identity":
        return Identity()
    if kind == "pwl":
        return PiecewiseLinear(n_out_knots, extrapolation="constant")
    if kind == "saturation":
        return Saturation(lower=floor, estimate=True)
    if kind == "deadzone":
        return DeadZone(-0.1, 0.1, estimate=True)
    raise ValueError(f"output block {kind!r} unknown; known: {HW_OUTPUT_BLOCKS}")


def fit_hw_for_control(records: Sequence[Any], nb: int = 2, nf: int = 2, n_knots: int = 5, max_nfev: int = 40,
                       output_blocks: Sequence[str] = ("identity", "identity"), n_out_knots: int = 4,
                       nox_kind: str = NOX_KIND, nh3_kind: str = NH3_KIND, surplus_block: str = "identity",
                       features: Sequence[str] = CONTROL_FEATURES, multistep_horizon: int = 0,
                       multistep_nfev: int = 40, static_blocks: bool = True,
                       input_filters: Sequence[Sequence[Any]] = ()) -> tuple[Any, dict[str, Any]]:
    """The Hammerstein-Wiener model for the NMPC: one two-output model (NOx in the ``nox_kind`` representation,
    NH3 in ``nh3_kind``; default log NOx slip ratio, log NH3) on the standardised :data:`CONTROL_FEATURES`,
    piecewise-linear input blocks (``surplus_block`` ``"identity"`` or ``"pwl"`` on the surplus, which enters both
    signs), linear dynamics, output blocks ``output_blocks`` per output (:data:`HW_OUTPUT_BLOCKS`: identity, or a
    static block that can express spill-over), on the records end to end (each record's first minute unweighted).
    ``static_blocks=False``: identity blocks on every input and output, i.e. the *linear* model class on the same
    features and outputs (the loop's linear row and the ablation of the static blocks). ``input_filters``: low-pass
    filtered features as further inputs, as :func:`fit_rpem_for_control` (normalised as their feature, with a
    piecewise-linear input block each). Returns the fitted model and its description."""
    from ident.hammerstein_wiener import HammersteinWiener
    from ident.hammerstein_wiener.blocks import Identity, PiecewiseLinear

    if len(output_blocks) != 2:
        raise ValueError(f"output_blocks: one per output (2), got {list(output_blocks)}")
    features = tuple(features)
    filters = check_input_filters(input_filters, features)
    spec = {"features": list(features), "input_filters": [[features[i], tau] for i, tau in filters],
            "nox_kind": nox_kind, "nh3_kind": nh3_kind}
    arrs = model_arrays(records, spec)
    Z = np.vstack([z[:, :len(features)] for z, _ in arrs])
    zm, zsd = Z.mean(axis=0), Z.std(axis=0)
    zm[0] = 0.0   # the dose feature (first) keeps its zero (no dose, no surplus)
    # a filtered input is normalised as its feature (the NMPC filters the normalised feature)
    zm, zsd = np.r_[zm, [zm[i] for i, _ in filters]], np.r_[zsd, [zsd[i] for i, _ in filters]]
    Uc, Yc, W = concat_records([(z - zm) / zsd for z, _ in arrs], [y for _, y in arrs], warmup=120)
    ym, ysd = Yc.mean(axis=0), Yc.std(axis=0)
    # a saturation starts at the output's floor in the data (no slip, full conversion), normalised
    outs = [_hw_output_block(k, n_out_knots, float((Yc[:, j].min() - ym[j]) / ysd[j]))
            for j, k in enumerate(output_blocks)]
    if surplus_block not in ("identity", "pwl"):
        raise ValueError(f"surplus_block must be 'identity' or 'pwl', got {surplus_block!r}")
    if not static_blocks:
        if any(k != "identity" for k in output_blocks):
            raise ValueError(f"static_blocks=False is the linear model: output_blocks must be identity, got "
                             f"{list(output_blocks)}")
        outs = [Identity(), Identity()]
    blocks = [Identity() if (f.startswith("surplus") and surplus_block == "identity") or not static_blocks
              else PiecewiseLinear(n_knots) for f in features]
    blocks += [PiecewiseLinear(n_knots) if static_blocks else Identity() for _ in filters]
    model = HammersteinWiener(input_blocks=blocks, output_block=outs, nb=nb, nf=nf, nk=1, max_nfev=max_nfev,
                              initial="zero").fit(Uc, (Yc - ym) / ysd, sample_weight=W)
    if multistep_horizon > 0:
        hw_multistep_refine(model, Uc, (Yc - ym) / ysd, W, int(multistep_horizon), multistep_nfev)
    info = {"kind": "hammerstein_wiener", "features": list(features), "z_mean": zm.tolist(),
            "z_scale": zsd.tolist(), "y_mean": ym.tolist(), "y_scale": ysd.tolist(), "nox_kind": nox_kind,
            "nh3_kind": nh3_kind, "nb": nb, "nf": nf, "output_blocks": list(output_blocks),
            "surplus_block": surplus_block, "multistep_horizon": int(multistep_horizon), "n_records": len(records),
            "static_blocks": bool(static_blocks), "input_filters": spec["input_filters"]}
    return model, info


def k_step_fit(step: Any, info: dict[str, Any], record: Any, horizon: int) -> list[float]:
    """FIT [%] of the ``horizon``-step predictions (windows of that length; an RPEM restarted from the measured
    outputs, a Hammerstein-Wiener model from rest) of the exported ``step(x, z)`` on one record, per output (log
    domain); NaN where the predictions diverge."""
    from ident.metrics import fit_percent

    (z, y), = model_arrays([record], info)
    zn = (z - np.asarray(info["z_mean"])) / np.asarray(info["z_scale"])
    nx = int(step.size1_in(0))
    f = step.mapaccum(horizon)
    pred = np.full_like(y, np.nan)
    ym, ysd = np.asarray(info["y_mean"]), np.asarray(info["y_scale"])
    for t0 in range(0, len(z) - horizon, horizon):
        xs = np.zeros(nx)
        if info["kind"] == "rpem":   # the chain states are the outputs: start from the measured ones, then (input
            xs[:y.shape[1]] = (y[t0] - ym) / ysd   # derivatives) the previous input
            xs[y.shape[1]:] = zn[t0][:nx - y.shape[1]]
        _, yy = f(xs, zn[t0:t0 + horizon].T)
        pred[t0:t0 + horizon] = np.asarray(yy).T * ysd + ym
    ok = ~np.isnan(pred[:, 0])
    # a prediction that leaves the float range is a diverged model: FIT NaN (reported, not raised)
    return [float(fit_percent(y[ok, j], pred[ok, j])) if np.all(np.isfinite(pred[ok, j])) else float("nan")
            for j in range(y.shape[1])]


def hw_multistep_refine(model: Any, u: np.ndarray, y: np.ndarray, weights: np.ndarray, horizon: int,
                        max_nfev: int = 40) -> Any:
    """Refit a fitted :class:`HammersteinWiener` in place by the multi-step prediction error of the NMPC's
    predictor (Shook, Mohtadi and Shah 1991): in windows of ``horizon`` samples, the model's output from its own
    (simulated) state plus the output offset measured at the window's start, i.e. the error of the predicted
    *change* ``(y(t0 + j) - y(t0)) - (yhat(t0 + j) - yhat(t0))``, j = 1..horizon, the offset-free NMPC's
    additive output disturbance held over its horizon. Weighted by ``weights`` (per sample, >= 0). Same
    parameters, bounds and Levenberg-Marquardt solver as the fit; never worse than the start on this criterion."""
    from ident.hammerstein_wiener._structure import eta_from_poly
    from ident.linear._lsq import levenberg_marquardt

    u, y = np.asarray(u, float), np.asarray(y, float)
    _, _, st = model._validate(u, y)
    st.blocks = [b.copy() for b in model.input_blocks_]
    st.outs = [b.copy() for b in model.output_blocks_]
    st.p0_in = [np.asarray(p, float) for p in model.input_params_]
    st.p0_out = [np.asarray(p, float) for p in model.output_params_]
    ny, nu = model.n_outputs_, model.n_inputs_
    st.gain = np.full((ny, nu), np.nan)
    bs = [[model.b_[j, i, int(st.nk[j, i]):int(st.nk[j, i] + st.nb[j, i])] for i in range(nu)] for j in range(ny)]
    etas = [[eta_from_poly(model.f_[j, i, :int(st.nf[j, i]) + 1]) for i in range(nu)] for j in range(ny)]
    th0 = st.pack(st.p0_in, bs, etas, st.p0_out)
    n = len(y)
    starts = np.arange(0, n - horizon, horizon)
    t0 = np.repeat(starts, horizon)
    tj = t0 + np.tile(np.arange(1, horizon + 1), len(starts))
    sw = np.sqrt(np.asarray(weights, float)[tj] * np.asarray(weights, float)[t0])
    lo, hi = st.bounds()
    th0 = np.clip(th0, lo, hi)

    def resid(th: np.ndarray) -> np.ndarray:
        e = y - st.simulate(th, u, False)[0]
        return (sw[:, None] * (e[tj] - e[t0])).T.ravel()

    def jac(th: np.ndarray) -> np.ndarray:
        J = st.simulate(th, u, True)[1].reshape(ny, n, -1)
        return np.concatenate([-sw[:, None] * (J[j][tj] - J[j][t0]) for j in range(ny)])

    st.bind(u)
    r0 = float(np.sum(resid(th0) ** 2))
    bounded = bool(np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)))
    res = levenberg_marquardt(resid, jac, th0, bounds=(lo, hi) if bounded else None, max_nfev=max_nfev)
    r1 = float(np.sum(resid(res.x) ** 2))
    st.bind(None)
    if np.isfinite(r1) and r1 < r0:
        model._store(st, res.x)
    return model


# ------------------------------------------------------------------------------- online adaptation of the RPEM
def rpem_parametric_functions(model: Any) -> dict[str, ca.Function]:
    """CasADi functions of a fitted for-control RPEM (:func:`fit_rpem_for_control`: one-state chains, so every model
    state is an output; inputs the scaled features) with its parameters ``theta`` as an input, for online
    adaptation (:mod:`control.online_rpem`):

    * ``step``: ``(x, z, theta) -> (x_next, y)``, equal to ``model.to_casadi()`` at ``theta = model.theta_`` (same
      state layout: the chain states, then the previous input when a regressor uses an input derivative);
    * ``regressor``: ``(y, z, z_prev) -> Phi`` (n_outputs, n_params): the right-hand side is linear in theta,
      ``dx/dt = Phi(x, z, z') theta``, evaluated at the chain states ``y`` with ``z' = (z - z_prev) / Ts``;
    * ``jacobian``: ``(y, z, z_prev, theta) -> d(dx/dt)/dx`` of the chain states (the linearisation whose
      eigenvalues the RPEM's stability projection checks).
    """
    from ident.rpem.multistep import chain_rhs

    s = model.structure_
    if s.n_chain != 1 or model.normalize or model.input_transforms or model.output != "identity":
        raise ValueError("rpem_parametric_functions needs the for-control RPEM: one-state chains, identity output, "
                         "no normalisation or input transforms (fit_rpem_for_control)")
    N, m = s.n_states, s.n_inputs
    ts = float(model.ts_model)
    prev = bool(s.uses_derivatives)
    x = ca.SX.sym("x", N + (m if prev else 0))
    z = ca.SX.sym("z", m)
    th = ca.SX.sym("theta", s.n_params)
    du = (z - x[N:]) / ts if prev else ca.SX.zeros(m)
    w = ca.vertcat(z, du)
    h = ts / int(model.n_substeps_)
    xn = x[:N]
    for _ in range(int(model.n_substeps_)):
        if model.method == "euler":
            xn = xn + h * chain_rhs(s, xn, w, th)
        else:
            xn = xn + h * chain_rhs(s, xn + 0.5 * h * chain_rhs(s, xn, w, th), w, th)
    y = []
    for k in range(s.n_outputs):
        yk = x[k]
        if np.isfinite(model.y_lo_[k]):
            yk = ca.fmax(yk, float(model.y_lo_[k]))
        if np.isfinite(model.y_hi_[k]):
            yk = ca.fmin(yk, float(model.y_hi_[k]))
        y.append(yk)
    step = ca.Function("step", [x, z, th], [ca.vertcat(xn, z) if prev else xn, ca.vertcat(*y)],
                       ["x", "z", "theta"], ["x_next", "y"])
    ys = ca.SX.sym("y", N)
    zp = ca.SX.sym("z_prev", m)
    wr = ca.vertcat(z, (z - zp) / ts)
    rhs = chain_rhs(s, ys, wr, th)
    regressor = ca.Function("regressor", [ys, z, zp], [ca.jacobian(rhs, th)], ["y", "z", "z_prev"], ["Phi"])
    jacobian = ca.Function("jacobian", [ys, z, zp, th], [ca.jacobian(rhs, ys)], ["y", "z", "z_prev", "theta"],
                           ["dfdx"])
    return {"step": step, "regressor": regressor, "jacobian": jacobian}
