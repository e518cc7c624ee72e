"""Calibration of the ``cu_zeolite`` kinetics (run by :mod:`experiments.calibrate_catalyst`; deterministic).

Three parts, each with its source:

1. **The ammonium-nitrate route from the literature** (:func:`nitrate_route`): the NO2 chemistry of the ORNL/CLEERS
   multi-site Cu-SSZ-13 model as implemented in aladshaw3/cats (MIT licence, (c) 2020 Austin Ladshaw, UT-Battelle;
   ``scripts/python/catalyst/updatedSCR/rxns_v7.py`` at a3e697fb51701bcac8bd291036a8266aa3a38c63: its reactions
   r21-r33 and the standard-SCR reactions r13-r17, with the adsorption equilibria r1-r4b and the unaged site
   densities of ``updatedSCR/550C_SCR.py``). Its four sites are lumped onto this model's single site: the rate
   constant per stored NH3 is the mean over the sites weighted by the NH3 each holds at the equilibrium with
   300 ppm NH3 and 5 % H2O (the CLEERS feed); the nitrate consumption constants are weighted by where the nitrate
   forms. Nitrate formation competes with standard SCR for the stored NH3, whose per-site rate this lumped model
   fits on its own storage basis, so it is referred to this model's standard SCR: multiplied by
   lambda(T) = k_std(this model) / k_std(cats, lumped), which keeps the cats ratio of nitrate formation to standard
   SCR. The nitrate's fates (with NO, to NH3 + HNO3, to N2O) are per nitrate molecule and keep the cats rates, so
   the nitrate's lifetime and the amount per catalyst volume are those of cats. Each transferred constant is
   fitted by an Arrhenius law over 150-550 C. No NO2 measurement enters.
2. **The unaged kinetics from our data** (:func:`fit_unaged`): storage (Temkin, with the saturation capacity of
   the cats sites, :data:`CATS_SATURATION_MOL_M3`) to the isotherm file and the measured NH3 uptake of the storage
   steps; standard SCR, the NH3 oxidations, NO oxidation and the two N2O routes to
   the plateaus of ``cleers_cu_ssz13_standard_scr_plateaus.csv`` (Unaged) and the low-temperature sweep.
3. **Ageing** (:func:`fit_ageing`): per measured age, factors of the storage capacity and desorption energy and of
   the reaction pre-exponentials, to that age's plateaus and uptakes, with the losses constrained monotone in age.

The lab model is the one of :mod:`scr_env.lab` (10 cells, GHSV referred to 0 C).
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence

import numpy as np
from scipy.optimize import least_squares

from scr_env import catalyst_data as cd
from scr_env.constants import ATMOSPHERIC_PRESSURE_PA, GAS_CONSTANT_J_MOL_K
from scr_env.lab import LAB_CELLS, STANDARD_TEMPERATURE_K
from scr_env.params import AGEING_TABLE, MAX_AGE_H, CatalystParams, pack
from scr_env.physics.kernel import catalyst_chemistry, solve_coverage

R_CATS = 8.3145  # J/(mol K), the gas constant of cats (arrhenius_rate_const)
R = GAS_CONSTANT_J_MOL_K  # J/(mol K), CODATA 2018
GHSV_STD_PER_H = 60000.0  # 1/h at 0 C, 1 atm (CLEERS)
FLOW_PER_M3 = GHSV_STD_PER_H / 3600.0 * ATMOSPHERIC_PRESSURE_PA / (R * STANDARD_TEMPERATURE_K)  # mol/s per m3 catalyst

# --- the cats v7 numbers used (rxns_v7.py; A in L, mol, min; E in J/mol) --------------------------------------------
#: adsorption equilibria (A, dH [J/mol], dS [J/(mol K)]): K = exp(dS/R) exp(-dH/(R T)) [L/mol]
CATS_EQUILIBRIA = {"r1": (-54547.9, -29.9943), "r2a": (-78073.843, -35.311574), "r2b": (-78064.167, -46.821878),
                   "r3": (-91860.8, -28.9292), "r4a": (-32099.1, -24.2494), "r4b": (-28889.23, -26.674)}
#: Arrhenius (A, E): standard SCR r13 (Z1CuOH-NH3), r14 (Z2Cu-NH3), r15 (Z2Cu-(NH3)2), r16/r17 (ZNH4 with a free
#: Z1CuOH / Z2Cu); nitrate formation r21-r24, nitrate + NO r25-r27, nitrate -> NH3 + NO2 r28-r30, -> N2O r31-r33
CATS_RATES = {
    "r13": (158934896906195, 61217.0869171797), "r14": (276342772543379, 63945.5969171797),
    "r15": (196507053031761, 61752.5369171797), "r16": (5793591205044520, 66563.6369171797),
    "r17": (307766200223700, 48581.6669171797),
    "r21": (13725167148853.1, 75075.4063936518), "r22": (145181130020.463, 53260.3863936518),
    "r23": (15651219976223.6, 77986.1763936518), "r24": (9513150643765.07, 73387.7563936518),
    "r25": (226043372451.468, 53126.0063936518), "r26": (85288248447.6855, 49266.4263936518),
    "r27": (9713469804.52266, 39309.8263936518),
    "r28": (183578.417658479, 56946.0263936518), "r29": (2667072.90885306, 70419.8063936518),
    "r30": (128573.994477963, 55857.3863936518),
    "r31": (28372964.584683, 93110.3563936519), "r32": (7156161.2710666, 83735.8563936518),
    "r33": (18828.095111708, 53546.2763936518),
}
#: unaged site densities [mol/L]: Z1CuOH, Z2Cu, ZH (updatedSCR/550C_SCR.py)
CATS_SITES_UNAGED = (0.052619016, 0.023125746, 0.01632 + 0.003233 + 0.006699)
#: NH3 the unaged cats sites hold at saturation [mol/m3]: Z1CuOH + 2 Z2Cu (Z2Cu-(NH3)2) + ZH, on the volume basis of
#: the isotherm file that the storage is fitted to (so the single site of this model saturates where cats does)
CATS_SATURATION_MOL_M3 = 1000.0 * (CATS_SITES_UNAGED[0] + 2.0 * CATS_SITES_UNAGED[1] + CATS_SITES_UNAGED[2])
CATS_FEED = {"nh3": 300e-6, "h2o": 0.05, "o2": 0.10}  # mole fractions of the lumping state [chosen: CLEERS feed]
NITRATE_FIT_T_C = np.arange(150.0, 551.0, 25.0)  # C, grid of the Arrhenius fits of the transferred constants


def _k(name: str, t_k: float) -> float:
    a, e = CATS_RATES[name]
    return a * math.exp(-e / (R_CATS * t_k))


def cats_site_loading(t_k: float) -> tuple[float, ...]:
    """(q1, q2a, q2b, q3, free Z1CuOH, free Z2Cu) [mol/L] of the unaged cats sites in equilibrium with the lumping
    feed (300 ppm NH3, 5 % H2O) at ``t_k`` [K]."""
    c_tot = ATMOSPHERIC_PRESSURE_PA / (R * t_k) / 1000.0  # mol/L
    c_nh3, c_h2o = CATS_FEED["nh3"] * c_tot, CATS_FEED["h2o"] * c_tot
    kq = {n: math.exp(ds / R_CATS) * math.exp(-dh / (R_CATS * t_k)) for n, (dh, ds) in CATS_EQUILIBRIA.items()}
    o1, o2, o3 = CATS_SITES_UNAGED
    s1 = o1 / (1.0 + kq["r1"] * c_nh3 + kq["r4a"] * c_h2o)
    s2 = o2 / (1.0 + kq["r2a"] * c_nh3 * (1.0 + kq["r2b"] * c_nh3) + kq["r4b"] * c_h2o)
    s3 = o3 / (1.0 + kq["r3"] * c_nh3)
    q2a = kq["r2a"] * s2 * c_nh3
    return kq["r1"] * s1 * c_nh3, q2a, kq["r2b"] * q2a * c_nh3, kq["r3"] * s3 * c_nh3, s1, s2


def cats_lumped_constants(t_k: float) -> dict[str, float]:
    """The cats constants per stored NH3 (per nitrate for its fates) at ``t_k``, in 1/s and per unit mole fraction
    at 1 atm: k_std (at 10 % O2, order 1 in O2 as in cats), k_an, k_an_no, k_an_dec, k_an_n2o."""
    q1, q2a, q2b, q3, s1, s2 = cats_site_loading(t_k)
    c_tot = ATMOSPHERIC_PRESSURE_PA / (R * t_k) / 1000.0
    stored = q1 + q2a + 2.0 * q2b + q3  # mol NH3 per L
    o2 = CATS_FEED["o2"] * c_tot
    std = (_k("r13", t_k) * q1 + _k("r14", t_k) * q2a + _k("r15", t_k) * q2b
           + (_k("r16", t_k) * s1 + _k("r17", t_k) * s2) * q3) * o2
    w = np.array([_k("r21", t_k) * q1, _k("r22", t_k) * q2a + _k("r23", t_k) * q2b, _k("r24", t_k) * q3])
    fates = {f: float(np.dot(w, [_k(r, t_k) for r in rs]) / w.sum())
             for f, rs in (("k_an_no", ("r25", "r26", "r27")), ("k_an_dec", ("r28", "r29", "r30")),
                           ("k_an_n2o", ("r31", "r32", "r33")))}
    return {"k_std": std / stored * c_tot / 60.0, "k_an": w.sum() / stored * c_tot / 60.0,
            "k_an_no": fates["k_an_no"] * c_tot / 60.0, "k_an_dec": fates["k_an_dec"] / 60.0,
            "k_an_n2o": fates["k_an_n2o"] / 60.0}


def nitrate_route(a_std_m3_mol_s: float, e_std_j_mol: float) -> dict[str, float]:
    """Arrhenius (A, E) of the nitrate constants of :class:`CatalystParams` transferred from cats onto a model whose
    standard SCR is ``a_std exp(-e_std / RT) C_NO theta`` (module docstring, part 1), and the fit's worst relative
    error over the grid."""
    out: dict[str, float] = {}
    worst = 0.0
    t_k = NITRATE_FIT_T_C + 273.15
    cats = [cats_lumped_constants(t) for t in t_k]
    c_total = ATMOSPHERIC_PRESSURE_PA / (R * t_k)  # mol/m3
    lam = a_std_m3_mol_s * np.exp(-e_std_j_mol / (R * t_k)) * c_total / np.array([c["k_std"] for c in cats])
    for key, field, per_conc in (("k_an", "an", True), ("k_an_no", "an_no", True), ("k_an_dec", "an_dec", False),
                                 ("k_an_n2o", "an_n2o", False)):
        scale = lam if key == "k_an" else 1.0  # formation referred to our SCR; the nitrate's fates as in cats
        k = scale * np.array([c[key] for c in cats]) / (c_total if per_conc else 1.0)
        unit = "m3_mol_s" if per_conc else "1_s"
        if field == "an_n2o":  # shares the activation energy of nitrate -> NH3 + HNO3 (cell.arrhenius_constants)
            slope = out["e_an_dec_j_mol"]
            icpt = float(np.mean(np.log(k) + slope / (R * t_k)))
        else:
            slope, icpt = np.polyfit(-1.0 / (R * t_k), np.log(k), 1)
            out[f"e_{field}_j_mol"] = float(slope)
        fit = np.exp(icpt - slope / (R * t_k))
        worst = max(worst, float(np.max(np.abs(fit / k - 1.0))))
        out[f"a_{field}_{unit}"] = float(np.exp(icpt))
    out["nitrate_arrhenius_worst_relative_error"] = worst
    return out


# --- the lab sample on packed parameters (fast path of scr_env.lab.steady_state) -----------------------------------
def lab_outlet(p: np.ndarray, capacity: float, t_c: float, nh3_ppm: float = 0.0, no_ppm: float = 0.0,
               no2_ppm: float = 0.0, o2_percent: float = 10.0) -> tuple[float, float, float, float]:
    """Steady (NH3, NO, NO2, N2O) outlet [ppm] of the 10-cell lab sample with packed parameters ``p``."""
    q = FLOW_PER_M3 / (capacity / LAB_CELLS)
    theta = np.zeros(LAB_CELLS)
    r = catalyst_chemistry(theta, np.full(LAB_CELLS, t_c + 273.15), q, nh3_ppm * 1e-6, no_ppm * 1e-6,
                           no2_ppm * 1e-6, o2_percent / 100.0, 0.0, p)
    return r[2] * 1e6, r[0] * 1e6, r[1] * 1e6, r[3] * 1e6


def lab_storage(p: np.ndarray, capacity: float, t_c: float, nh3_ppm: float) -> float:
    """Equilibrium NH3 uptake [mol/m3] with ``nh3_ppm`` at ``t_c`` (no reactions)."""
    from scr_env.params import KINETIC_SLICE
    from scr_env.physics.backends import rate_constants_nb

    t_k = t_c + 273.15
    k = rate_constants_nb(t_k, 0.1, *p[KINETIC_SLICE])
    q = FLOW_PER_M3 / (capacity / LAB_CELLS)
    th, _, _ = solve_coverage(0.0, 0.0, q, nh3_ppm * 1e-6, 0.0, 0.0, (k[0], k[1], k[2]) + (0.0,) * 11)
    return th * capacity


def measured_uptake(temperature_c: float, age_h: float) -> float:
    """NH3 stored [mol/m3] in the storage step (300 ppm NH3, 0.2 % O2) of a run: the integral of inlet minus outlet
    NH3 over the step, less the steady consumption of its last 2 min (NH3 oxidation in 0.2 % O2), times the molar
    flow per catalyst volume."""
    rec = cd.step_records(temperature_c, age_h)
    m = rec["O2_in_percent"] < 1.0
    t_s = rec["time_min"][m] * 60.0
    d = (rec["NH3_in_ppm"] - rec["NH3_out_ppm"])[m] * 1e-6
    d = d - d[-12:].mean()
    return float(np.sum(0.5 * (d[1:] + d[:-1]) * np.diff(t_s)) * FLOW_PER_M3)


@dataclasses.dataclass
class Residual:
    """One calibration residual: label, the model's value from a packed vector, the measurement and its scale."""

    label: str
    model: Callable[[np.ndarray, float], float]
    measured: float
    scale: float

    def __call__(self, p: np.ndarray, capacity: float) -> float:
        return (self.model(p, capacity) - self.measured) / self.scale


def plateau_residuals(age_h: float) -> list[Residual]:
    """Residuals of the five-age plateaus of one age: standard-SCR NOx conversion (scale 0.025) and N2O (1.5 ppm),
    NH3-oxidation NH3 outlet fraction (0.04), NOx formed (5 ppm) and N2O (1.5 ppm), the steady NO2 of the first
    NO-only plateau
    (2.5 ppm + 12.5 %), and the NH3 outlet fraction of the storage step in 0.2 % O2 (0.05); half the acceptance
    tolerances where PHYSICS.md gives one [chosen: fit inside the band]."""
    res: list[Residual] = []
    for r in cd.plateaus():
        if r["age_h"] != age_h:
            continue
        t, o2, nh3, no = r["T_C"], r["O2_in_percent"], r["NH3_in_ppm"], max(r["NO_in_ppm"], 0.0)
        tag = f"{r['kind']}@{t:.0f}C/{age_h:g}h"
        if r["kind"] == "standard_scr":
            def conv(p, c, t=t, nh3=nh3, no=no, o2=o2):
                out = lab_outlet(p, c, t, nh3, no, 0.0, o2)
                return 1.0 - (out[1] + out[2]) / no
            res.append(Residual(tag + " conv", conv, r["NOx_conversion"], 0.025))
            res.append(Residual(tag + " n2o", lambda p, c, t=t, nh3=nh3, no=no, o2=o2:
                                lab_outlet(p, c, t, nh3, no, 0.0, o2)[3], r["N2O_out_ppm"], 1.5))
        elif r["kind"] in ("nh3_oxidation", "nh3_storage"):
            frac = r["NH3_out_ppm"] / nh3
            res.append(Residual(tag + " nh3", lambda p, c, t=t, nh3=nh3, o2=o2:
                                lab_outlet(p, c, t, nh3, 0.0, 0.0, o2)[0] / nh3, frac,
                                0.04 if r["kind"] == "nh3_oxidation" else 0.05))
            if r["kind"] == "nh3_oxidation":
                res.append(Residual(tag + " nox", lambda p, c, t=t, nh3=nh3, o2=o2:
                                    sum(lab_outlet(p, c, t, nh3, 0.0, 0.0, o2)[1:3]),
                                    r["NO_out_ppm"] + r["NO2_out_ppm"], 5.0))
                res.append(Residual(tag + " n2o", lambda p, c, t=t, nh3=nh3, o2=o2:
                                    lab_outlet(p, c, t, nh3, 0.0, 0.0, o2)[3], r["N2O_out_ppm"], 1.5))
        elif r["kind"] == "no_only" and r["first_no_only"]:
            res.append(Residual(tag + " no2", lambda p, c, t=t, no=no, o2=o2:
                                lab_outlet(p, c, t, 0.0, no, 0.0, o2)[2], r["NO2_out_ppm"],
                                2.5 + 0.125 * abs(r["NO2_out_ppm"])))
    return res


def uptake_residuals(age_h: float, scale: float = 0.25) -> list[Residual]:
    """Equilibrium storage at 300 ppm against the measured uptake of each storage step of one age (relative)."""
    res = []
    for t in (250.0, 300.0, 350.0, 400.0, 450.0):
        meas = measured_uptake(t, age_h)
        res.append(Residual(f"uptake@{t:.0f}C/{age_h:g}h", lambda p, c, t=t: lab_storage(p, c, t, 300.0), meas,
                            scale * meas))
    return res


def unaged_lab_residuals() -> list[Residual]:
    """Residuals of the earlier unaged data: low-temperature sweep (standard SCR conversion 0.025 and slip 12.5 ppm,
    fast SCR conversion 0.035), the steady NH3-oxidation steps at 400-550 C (15 ppm), the isotherm file at 300 ppm
    (10 % relative) and at 100 and 1000 ppm (20 %)."""
    res: list[Residual] = []
    for r in cd.rows(cd.LOW_T_SWEEP):
        t, nox, nh3 = float(r["T_mid_C"]), float(r["NOx_in_ppm"]), float(r["NH3_in_ppm"])
        if r["case"] == "NOSCR":
            res.append(Residual(f"lowT std@{t:.0f}", lambda p, c, t=t, nox=nox, nh3=nh3:
                                1.0 - sum(lab_outlet(p, c, t, nh3, nox)[1:3]) / nox, float(r["NOx_conversion"]),
                                0.025))
            res.append(Residual(f"lowT slip@{t:.0f}", lambda p, c, t=t, nox=nox, nh3=nh3:
                                lab_outlet(p, c, t, nh3, nox)[0], float(r["NH3_out_ppm"]), 12.5))
        else:
            res.append(Residual(f"lowT fast@{t:.0f}", lambda p, c, t=t, nox=nox, nh3=nh3:
                                1.0 - sum(lab_outlet(p, c, t, nh3, nox / 2, nox / 2)[1:3]) / nox,
                                float(r["NOx_conversion"]), 0.035))
    last = {float(r["T_C"]): r for r in cd.rows(cd.NH3_OXIDATION_STEPS)}
    for t in (400.0, 500.0, 550.0):
        nh3 = float(last[t]["NH3_in_ppm"])
        res.append(Residual(f"ox-step@{t:.0f}", lambda p, c, t=t, nh3=nh3: lab_outlet(p, c, t, nh3)[0],
                            float(last[t]["NH3_out_ppm"]), 15.0))
    for r in cd.rows(cd.ISOTHERMS):
        t, ppm = float(r["T_C"]), float(r["NH3_ppm"])
        meas = float(r["q_total_molL"]) * 1000.0
        if 150.0 <= t <= 450.0:
            res.append(Residual(f"isotherm {ppm:.0f}ppm@{t:.0f}", lambda p, c, t=t, ppm=ppm: lab_storage(p, c, t, ppm),
                                meas, (0.1 if ppm == 300.0 else 0.2) * meas))
    return res


def _residual_vector(res: Sequence[Residual], p: np.ndarray, capacity: float) -> np.ndarray:
    return np.array([r(p, capacity) for r in res])


# --- part 2: unaged ------------------------------------------------------------------------------------------------
#: fitted unaged fields: (field, transform) with "log" for pre-exponentials and capacities, "kj" for energies
UNAGED_FIELDS: tuple[tuple[str, str], ...] = (
    ("a_des_1_s", "log"), ("e_des_j_mol", "kj"), ("temkin_gamma", "lin"),
    ("a_std_m3_mol_s", "log"), ("e_std_j_mol", "kj"), ("a_n2o_m3_mol_s", "log"),
    ("a_ox_1_s", "log"), ("e_ox_j_mol", "kj"), ("a_ox_no_1_s", "log"), ("e_ox_no_j_mol", "kj"),
    ("a_ox_n2o_1_s", "log"), ("a_no_ox_m3_mol_s", "log"), ("e_no_ox_j_mol", "kj"),
    ("o2_order_ox", "lin"),
)
_BOUNDS = {"temkin_gamma": (0.0, 0.99), "o2_order_ox": (0.0, 1.5)}


def _encode(cat: CatalystParams, fields: Sequence[tuple[str, str]]) -> np.ndarray:
    out = []
    for f, kind in fields:
        v = getattr(cat, f)
        out.append(math.log(v) if kind == "log" else v / 1e3 if kind == "kj" else v)
    return np.array(out)


def _decode(x: np.ndarray, cat: CatalystParams, fields: Sequence[tuple[str, str]]) -> CatalystParams:
    ch = {}
    for v, (f, kind) in zip(x, fields, strict=True):
        ch[f] = float(math.exp(v) if kind == "log" else v * 1e3 if kind == "kj" else v)
    return dataclasses.replace(cat, **ch)


def with_nitrate(cat: CatalystParams) -> CatalystParams:
    """``cat`` with the nitrate route transferred from cats onto its standard SCR (part 1)."""
    nr = nitrate_route(cat.a_std_m3_mol_s, cat.e_std_j_mol)
    return dataclasses.replace(cat, **{k: v for k, v in nr.items() if k.startswith(("a_", "e_"))})


def fit_unaged(start: CatalystParams, rounds: int = 2, verbose: bool = False) -> tuple[CatalystParams, dict]:
    """Fit :data:`UNAGED_FIELDS` to the unaged residuals; the nitrate route follows the standard SCR (re-derived
    between rounds)."""
    res = unaged_lab_residuals() + plateau_residuals(0.0) + uptake_residuals(0.0)
    cat = with_nitrate(start)
    lo = [(_BOUNDS[f][0] if f in _BOUNDS else 5.0 if k == "kj" else -60.0) for f, k in UNAGED_FIELDS]
    hi = [(_BOUNDS[f][1] if f in _BOUNDS else 400.0 if k == "kj" else 100.0) for f, k in UNAGED_FIELDS]
    fit = None
    for _ in range(rounds):
        base = cat

        def fun(x: np.ndarray, base: CatalystParams = base) -> np.ndarray:
            c = _decode(x, base, UNAGED_FIELDS)
            return _residual_vector(res, pack(c), c.storage_capacity_effective_mol_m3)

        x0 = np.clip(_encode(cat, UNAGED_FIELDS), np.array(lo) + 1e-9, np.array(hi) - 1e-9)
        fit = least_squares(fun, x0, bounds=(lo, hi), loss="soft_l1", f_scale=2.0, x_scale="jac",
                            max_nfev=400, verbose=2 if verbose else 0)
        cat = with_nitrate(_decode(fit.x, base, UNAGED_FIELDS))
    final = _residual_vector(res, pack(cat), cat.storage_capacity_effective_mol_m3)
    return cat, {"residuals": {r.label: float(v) for r, v in zip(res, final, strict=True)},
                 "rms_scaled_residual": float(np.sqrt(np.mean(final ** 2))), "nfev": int(fit.nfev)}


# --- part 3: ageing ------------------------------------------------------------------------------------------------
#: factors that only decrease with age (losses); the others (NH3 -> NO, the N2O routes) may rise
MONOTONE_LOSSES = ("storage", "e_des_shift_j_mol", "activity_200c", "activity_550c", "no_ox")


def _ageing_layout(ages: Sequence[float]) -> tuple[list[str], list[float], list[float], list[float]]:
    keys = list(AGEING_TABLE[0.0])
    lo, hi, x0 = [], [], []
    for _ in ages:
        for key in keys:
            if key in MONOTONE_LOSSES:
                lo.append(0.0), hi.append(5.0), x0.append(0.02)
            elif key.endswith("_j_mol"):
                lo.append(-30.0), hi.append(30.0), x0.append(0.0)
            else:
                lo.append(-5.0), hi.append(5.0), x0.append(0.0)
    return keys, lo, hi, x0


def _ageing_table(x: np.ndarray, ages: Sequence[float], keys: Sequence[str]) -> dict[float, dict[str, float]]:
    """The ageing table of a parameter vector: losses as cumulative non-negative log-decrements between
    consecutive ages (monotone by construction), energy shifts in kJ/mol, other factors as log-factors."""
    n_k = len(keys)
    out = {0.0: dict(AGEING_TABLE[0.0])}
    cum = np.zeros(n_k)
    for i, a in enumerate(ages):
        xi = x[i * n_k:(i + 1) * n_k]
        row = {}
        for j, key in enumerate(keys):
            if key in MONOTONE_LOSSES:
                cum[j] += xi[j]
                row[key] = float(-cum[j] * 1e3) if key.endswith("_j_mol") else float(math.exp(-cum[j]))
            elif key.endswith("_j_mol"):
                row[key] = float(xi[j] * 1e3)
            else:
                row[key] = float(math.exp(xi[j]))
        out[a] = row
    return out


def fit_all(start: CatalystParams, verbose: bool = False) -> tuple[CatalystParams, dict[float, dict[str, float]], dict]:
    """Joint fit of the unaged kinetics (:data:`UNAGED_FIELDS`) and the per-age factors to every residual (the
    nitrate route re-derived from the standard SCR at every evaluation)."""
    ages = [a for a in cd.AGES_H if a > 0.0]
    keys, lo_a, hi_a, x0_a = _ageing_layout(ages)
    res0 = unaged_lab_residuals() + plateau_residuals(0.0) + uptake_residuals(0.0)
    res = {a: plateau_residuals(a) + uptake_residuals(a) for a in ages}
    lo_u = [(_BOUNDS[f][0] if f in _BOUNDS else 5.0 if k == "kj" else -60.0) for f, k in UNAGED_FIELDS]
    hi_u = [(_BOUNDS[f][1] if f in _BOUNDS else 400.0 if k == "kj" else 100.0) for f, k in UNAGED_FIELDS]
    x0_u = np.clip(_encode(start, UNAGED_FIELDS), np.array(lo_u) + 1e-9, np.array(hi_u) - 1e-9)
    n_u = len(UNAGED_FIELDS)

    def split(x: np.ndarray) -> tuple[CatalystParams, dict[float, dict[str, float]]]:
        return with_nitrate(_decode(x[:n_u], start, UNAGED_FIELDS)), _ageing_table(x[n_u:], ages, keys)

    def fun(x: np.ndarray) -> np.ndarray:
        cat, tab = split(x)
        out = [_residual_vector(res0, pack(cat), cat.storage_capacity_effective_mol_m3)]
        for a in ages:
            c = cat.replace(age_h=a)
            out.append(_residual_vector(res[a], pack(c, tab), cat.storage_capacity_mol_m3 * tab[a]["storage"]))
        return np.concatenate(out)

    fit = least_squares(fun, np.concatenate([x0_u, x0_a]), bounds=(lo_u + lo_a, hi_u + hi_a), loss="soft_l1",
                        f_scale=2.0, x_scale="jac", max_nfev=800, verbose=2 if verbose else 0)
    cat, tab = split(fit.x)
    final = fun(fit.x)
    labels = [r.label for r in res0] + [r.label for a in ages for r in res[a]]
    return cat, tab, {"residuals": dict(zip(labels, map(float, final), strict=True)),
                      "rms_scaled_residual": float(np.sqrt(np.mean(final ** 2))), "nfev": int(fit.nfev),
                      "status": fit.message}


assert MAX_AGE_H == max(cd.AGES_H)
