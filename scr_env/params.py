"""Parameters of the SCR plant as frozen dataclasses, with units and sources, and the named presets.

The physics functions take these objects (or their packed float arrays, for the compiled kernel) as explicit
arguments; nothing is mutated. Ageing and domain randomisation produce new parameter objects
(:func:`aged`, :func:`randomised`).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, fields

import numpy as np

from scr_env.constants import AMBIENT_TEMPERATURE_K
from scr_env.physics.cell import SCR_FACTOR_ANCHORS_K


@dataclass(frozen=True)
class CatalystParams:
    """A lumped single-site NH3-SCR catalyst brick (PHYSICS.md section 2; the reactions of
    :mod:`scr_env.physics.cell`).

    Rates are per storage site; theta is the NH3 coverage in [0, 1]; gas concentrations C in mol/m3;
    pre-exponentials A in the units given, activation energies E in J/mol. Rates are given at the lab's 10 % O2.
    The kinetics of ``cu_zeolite`` are calibrated by :mod:`experiments.calibrate_catalyst` (deterministic, printed
    there with its residuals): storage, standard SCR, the NH3 oxidations, NO oxidation and the N2O routes to the
    CLEERS Cu-SSZ-13 lab data shipped in ``scr_env/data/catalyst``; the NO2 chemistry (the ammonium-nitrate route)
    from the ORNL/CLEERS multi-site model (aladshaw3/cats ``rxns_v7.py``) lumped onto this single site.

    ``age_h`` is the hydrothermal ageing of the CLEERS samples in hours (0, 2, 4, 8, 16 measured; in between
    interpolated, :data:`AGEING_TABLE`); ``storage_retention`` and ``activity_retention`` are further free
    multipliers (1 = as calibrated) for studies of other ageing paths.
    """

    name: str = "cu_zeolite"
    # --- geometry and storage --------------------------------------------------------------------------------
    volume_m3: float = 0.034  # m3 of catalyst brick, 12 L engine [lit: Willems and Cloudt 2011, zeolite SCR]
    n_cells: int = 5  # axial CSTR cells [chosen: PHYSICS.md allows 5-10; 5 keeps the vector env fast]
    storage_capacity_mol_m3: float = 125.12  # mol NH3 sites per m3 catalyst, unaged [fitted: calibrate_catalyst]
    # --- NH3 adsorption / Temkin desorption -----------------------------------------------------------------
    a_ads_m3_mol_s: float = 1000  # m3/(mol s), not activated [chosen: fast, adsorption is never rate limiting]
    a_des_1_s: float = 2.0731e7  # 1/s [fitted: calibrate_catalyst]
    e_des_j_mol: float = 80465  # J/mol at zero coverage [fitted: calibrate_catalyst]
    temkin_gamma: float = 0.39901  # - , E_des = E_des0 (1 - gamma theta) [fitted: calibrate_catalyst]
    # --- standard SCR: 4 NH3* + 4 NO + O2 -> 4 N2 + 6 H2O (Eley-Rideal, first order in NO) ---------------------
    a_std_m3_mol_s: float = 1.4724e7  # m3/(mol s) [fitted: calibrate_catalyst]
    e_std_j_mol: float = 67894  # J/mol [fitted: calibrate_catalyst]
    # --- N2O from NH3* + NO: 2 NH3* + 2 NO + 3/2 O2 -> 2 N2O + 3 H2O (rate per N2O) ---------------------------------
    a_n2o_m3_mol_s: float = 207221  # m3/(mol s) [fitted: calibrate_catalyst]; its E is e_std_j_mol (cell.py)
    # --- NH3 oxidation to N2: 4 NH3* + 3 O2 -> 2 N2 + 6 H2O (rate per NH3) -------------------------------------
    a_ox_1_s: float = 222.1  # 1/s [fitted: calibrate_catalyst]
    e_ox_j_mol: float = 59923  # J/mol [fitted: calibrate_catalyst]
    # --- NH3 oxidation to NO (high temperature): 4 NH3* + 5 O2 -> 4 NO + 6 H2O (rate per NH3) --------------------
    a_ox_no_1_s: float = 1.3704e10  # 1/s [fitted: calibrate_catalyst]
    e_ox_no_j_mol: float = 167844  # J/mol [fitted: calibrate_catalyst]
    # --- NH3 oxidation to N2O (high temperature): 2 NH3* + 2 O2 -> N2O + 3 H2O (rate per NH3) ---------------------
    a_ox_n2o_1_s: float = 3.70508e6  # 1/s [fitted: calibrate_catalyst]; its E is e_ox_no_j_mol (cell.py)
    # --- NO oxidation NO + 1/2 O2 <-> NO2 on sites free of NH3 (reverse from the equilibrium, cell.py) ------------
    a_no_ox_m3_mol_s: float = 50.699  # m3/(mol s) at 10 % O2 [fitted: calibrate_catalyst, NO-only plateaus]
    e_no_ox_j_mol: float = 39189  # J/mol [fitted: calibrate_catalyst]
    # --- ammonium nitrate route (fast SCR, NO2-SCR, N2O from nitrate) -------------------------------------------
    # 2 NH3* + 2 NO2 -> NH4NO3* + N2 + H2O (per nitrate); NH4NO3* + NO -> N2 + NO2 + 2 H2O; NH4NO3* -> NH3* + NO2
    # (+ H2O, O2); NH4NO3* -> N2O + 2 H2O. [lit: aladshaw3/cats rxns_v7.py r21-r33, lumped over its sites and
    # referred to this model's standard-SCR rate: calibrate_catalyst.nitrate_route]
    a_an_m3_mol_s: float = 5.8691e8  # m3/(mol s)
    e_an_j_mol: float = 81538  # J/mol
    a_an_no_m3_mol_s: float = 246944  # m3/(mol s)
    e_an_no_j_mol: float = 41549  # J/mol
    a_an_dec_1_s: float = 2855.4  # 1/s
    e_an_dec_j_mol: float = 57419  # J/mol
    a_an_n2o_1_s: float = 585.79  # 1/s; its E is e_an_dec_j_mol (cell.py)
    # --- oxygen dependence (rates are given at the lab's 10 % O2) -----------------------------------------------
    o2_reference_fraction: float = 0.10  # mole fraction of the lab data [data: CLEERS protocol]
    o2_order_std: float = 0.5  # - [chosen: half order in O2 for standard SCR, Olsson et al. 2008]
    o2_order_ox: float = 0.60314  # - NH3 oxidations and the O2-taking N2O route [fitted: 0.2 % O2 plateaus]
    # --- thermal: lumped solid per cell, convective exchange with the gas, loss to ambient ----------------------
    solid_density_kg_m3: float = 2600.0  # kg/m3 cordierite/zeolite [lit: LiU 2018]
    solid_heat_capacity_j_kg_k: float = 1464.0  # J/(kg K) [lit: LiU 2018]
    open_frontal_area: float = 0.63  # - void fraction [lit: LiU 2018]
    # h * GSA per m3 brick: Nu = 3.0 laminar channel flow, k_gas 0.045 W/(m K), d_h 1.1 mm -> h = 123 W/(m2 K);
    # GSA 2790 m2/m3 for 400 cpsi / 6.5 mil [lit: Hayes and Kolaczkowski 1997, typical monolith] -> 3.4e5 W/(m3 K)
    gas_solid_htc_w_m3_k: float = 3.4e5
    # Loss to ambient of the insulated can: a bare can of 0.41 m2 with 250 W/(m2 K) [lit: LiU 2018] would lose about
    # 100 W/K, which would cool an idling brick far below measured temperatures; an insulated double-wall can
    # loses a few tens of W/K [chosen: 20 W/K for the 34 L brick, scaled with volume].
    ambient_loss_w_k_m3: float = 20.0 / 0.034
    ambient_temperature_k: float = AMBIENT_TEMPERATURE_K
    # --- ageing ---------------------------------------------------------------------------------------------------
    age_h: float = 0.0  # h of hydrothermal ageing as the CLEERS samples (0 to MAX_AGE_H) [data: AGEING_TABLE]
    storage_retention: float = 1.0  # - further multiplier of the storage capacity [see aged()]
    activity_retention: float = 1.0  # - further multiplier of every reaction's pre-exponential [see aged()]

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "name":
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"CatalystParams.{f.name} must be a finite number, got {v!r}")
            if v < 0:
                raise ValueError(f"CatalystParams.{f.name} must be non-negative, got {v!r}")
        if int(self.n_cells) != self.n_cells or self.n_cells < 1 or self.n_cells > 50:
            raise ValueError(f"CatalystParams.n_cells must be an integer in [1, 50], got {self.n_cells!r}")
        if self.volume_m3 <= 0 or self.storage_capacity_mol_m3 <= 0:
            raise ValueError("CatalystParams.volume_m3 and storage_capacity_mol_m3 must be positive")
        if not 0.0 <= self.temkin_gamma < 1.0:
            raise ValueError(f"CatalystParams.temkin_gamma must be in [0, 1), got {self.temkin_gamma!r}")
        if not 0.0 < self.open_frontal_area < 1.0:
            raise ValueError("CatalystParams.open_frontal_area must be in (0, 1)")
        if not 0.0 < self.o2_reference_fraction <= 1.0:
            raise ValueError(f"CatalystParams.o2_reference_fraction must be in (0, 1], got "
                             f"{self.o2_reference_fraction!r}")
        check_age_h(self.age_h, "CatalystParams.age_h")
        for name in ("storage_retention", "activity_retention"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ValueError(f"CatalystParams.{name} must be in (0, 1], got {getattr(self, name)!r}")

    @property
    def storage_capacity_effective_mol_m3(self) -> float:
        """NH3 storage sites per m3 catalyst after ageing (``age_h`` and ``storage_retention``) [mol/m3]."""
        return self.storage_capacity_mol_m3 * ageing_factors(self.age_h)["storage"] * self.storage_retention

    @property
    def sites_mol(self) -> float:
        """NH3 storage sites of the whole brick [mol] (capacity after ageing)."""
        return self.volume_m3 * self.storage_capacity_effective_mol_m3

    @property
    def heat_capacity_j_k(self) -> float:
        """Heat capacity of the solid of the whole brick [J/K]."""
        return (self.volume_m3 * (1.0 - self.open_frontal_area) * self.solid_density_kg_m3
                * self.solid_heat_capacity_j_kg_k)

    def replace(self, **changes: float) -> CatalystParams:
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)


# --- ageing: per-age factors of the CLEERS five-age data --------------------------------------------------------------
#: hours of hydrothermal ageing of the oldest CLEERS sample; older catalysts are outside the data
MAX_AGE_H = 16.0
#: Factors of the unaged kinetics per sample age [h] (1 = unaged): "storage" multiplies the storage capacity,
#: "e_des_shift_j_mol" is added to the desorption energy (ageing removes the strongest sites first);
#: "activity_200c" and "activity_550c" multiply standard SCR, the N2O route of NH3* + NO and the nitrate route (the
#: same sites) at 200 and 550 C, log-linear in 1/T in between and held outside (so never above 1 where both are
#: at most 1; :func:`scr_env.physics.cell.arrhenius_constants`); the others multiply a reaction's pre-exponential.
#: [fitted: experiments.calibrate_catalyst on cleers_cu_ssz13_standard_scr_plateaus.csv and the NH3 uptake of the
#: storage steps of cleers_cu_ssz13_isothermal_steps.csv; losses constrained monotone in age]
AGEING_TABLE: dict[float, dict[str, float]] = {
    0.0: {"storage": 1.0, "e_des_shift_j_mol": 0.0, "activity_200c": 1.0, "activity_550c": 1.0, "n2o": 1.0,
        "ox": 1.0, "ox_no": 1.0, "ox_n2o": 1.0, "no_ox": 1.0},
    2.0: {"storage": 1.0, "e_des_shift_j_mol": -2876.9, "activity_200c": 1.0, "activity_550c": 0.4545, "n2o": 1.332,
        "ox": 0.7843, "ox_no": 0.7616, "ox_n2o": 51.07, "no_ox": 0.8774},
    4.0: {"storage": 1.0, "e_des_shift_j_mol": -4430.1, "activity_200c": 1.0, "activity_550c": 0.4545, "n2o": 1.377,
        "ox": 0.8785, "ox_no": 0.9208, "ox_n2o": 74.37, "no_ox": 0.8774},
    8.0: {"storage": 1.0, "e_des_shift_j_mol": -5424.2, "activity_200c": 1.0, "activity_550c": 0.4545, "n2o": 1.376,
        "ox": 0.8551, "ox_no": 1.1, "ox_n2o": 97.33, "no_ox": 0.8774},
    16.0: {"storage": 0.9958, "e_des_shift_j_mol": -5680.5, "activity_200c": 1.0, "activity_550c": 0.4545,
        "n2o": 1.368, "ox": 0.8948, "ox_no": 1.273, "ox_n2o": 117.1, "no_ox": 0.8774},
}
AGEING_FACTORS: tuple[str, ...] = tuple(AGEING_TABLE[0.0])
#: temperatures [K] where the "activity_200c" / "activity_550c" factors hold (scr_env.physics.cell.SCR_FACTOR_ANCHORS_K)
ACTIVITY_ANCHORS_K = SCR_FACTOR_ANCHORS_K


def check_age_h(age_h: object, name: str = "age_h") -> float:
    """``age_h`` as a float in [0, MAX_AGE_H] hours; ValueError naming ``name`` otherwise."""
    if isinstance(age_h, (bool, np.bool_)) or not isinstance(age_h, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a number of hours in [0, {MAX_AGE_H:g}], got {age_h!r}")  # noqa: TRY004 (ValueError for every bad age)
    v = float(age_h)
    if not math.isfinite(v) or not 0.0 <= v <= MAX_AGE_H:
        raise ValueError(f"{name} must be a number of hours of hydrothermal ageing in [0, {MAX_AGE_H:g}] (the "
                         f"range of the CLEERS samples), got {age_h!r}")
    return v


def ageing_factors(age_h: float, table: dict[float, dict[str, float]] | None = None) -> dict[str, float]:
    """The factors of :data:`AGEING_TABLE` at ``age_h`` hours: piecewise linear in age between the measured ages,
    in the logarithm of the multipliers (so a loss compounds) and linear in the energy shift."""
    table = AGEING_TABLE if table is None else table
    age = check_age_h(age_h)
    ages = sorted(table)
    if age in table:
        return dict(table[age])
    hi = next(a for a in ages if a > age)
    lo = max(a for a in ages if a < age)
    w = (age - lo) / (hi - lo)
    out = {}
    for key in table[lo]:
        a, b = table[lo][key], table[hi][key]
        if key.endswith("_j_mol"):
            out[key] = a + w * (b - a)
        else:
            out[key] = math.exp(math.log(a) + w * (math.log(b) - math.log(a)))
    return out


# Order of the packed parameter vector used by the compiled kernel (see pack()). The kinetic block from "a_ads" to
# "o2_order_ox" is the argument list of scr_env.physics.cell.rate_constants after the temperature and O2.
PACKED_FIELDS: tuple[str, ...] = (
    "n_cells", "sites_per_cell_mol", "heat_capacity_per_cell_j_k", "gas_solid_ua_per_cell_w_k",
    "ambient_loss_per_cell_w_k", "ambient_temperature_k",
    "a_ads", "a_des", "e_des", "temkin_gamma",
    "a_std", "e_std", "a_n2o", "a_ox", "e_ox", "a_ox_no", "e_ox_no", "a_ox_n2o", "a_no_ox", "e_no_ox",
    "a_an", "e_an", "a_an_no", "e_an_no", "a_an_dec", "e_an_dec", "a_an_n2o", "scr_log_factor_low",
    "scr_log_factor_high", "o2_reference_fraction", "o2_order_std", "o2_order_ox",
)
P = {name: i for i, name in enumerate(PACKED_FIELDS)}  # index of each packed parameter
#: the packed kinetic parameters, in the argument order of scr_env.physics.cell.rate_constants
KINETIC_SLICE = slice(P["a_ads"], P["o2_order_ox"] + 1)


def pack(params: CatalystParams, table: dict[float, dict[str, float]] | None = None) -> np.ndarray:
    """Pack a catalyst into the float64 vector the compiled kernel reads (order: :data:`PACKED_FIELDS`).

    Ageing is applied here: the factors of :func:`ageing_factors` at ``age_h`` (from ``table``, default
    :data:`AGEING_TABLE`), then capacity times ``storage_retention`` and every reaction's pre-exponential times
    ``activity_retention``.
    """
    n = params.n_cells
    v_cell = params.volume_m3 / n
    age = ageing_factors(params.age_h, table)
    act = params.activity_retention
    values = {
        "n_cells": float(n),
        "sites_per_cell_mol": params.sites_mol / n,
        "heat_capacity_per_cell_j_k": params.heat_capacity_j_k / n,
        "gas_solid_ua_per_cell_w_k": params.gas_solid_htc_w_m3_k * v_cell,
        "ambient_loss_per_cell_w_k": params.ambient_loss_w_k_m3 * v_cell,
        "ambient_temperature_k": params.ambient_temperature_k,
        "a_ads": params.a_ads_m3_mol_s,
        "a_des": params.a_des_1_s,
        "e_des": params.e_des_j_mol + age["e_des_shift_j_mol"],
        "temkin_gamma": params.temkin_gamma,
        "a_std": params.a_std_m3_mol_s * act,
        "e_std": params.e_std_j_mol,
        "a_n2o": params.a_n2o_m3_mol_s * act * age["n2o"],
        "a_ox": params.a_ox_1_s * act * age["ox"],
        "e_ox": params.e_ox_j_mol,
        "a_ox_no": params.a_ox_no_1_s * act * age["ox_no"],
        "e_ox_no": params.e_ox_no_j_mol,
        "a_ox_n2o": params.a_ox_n2o_1_s * act * age["ox_n2o"],
        "a_no_ox": params.a_no_ox_m3_mol_s * act * age["no_ox"],
        "e_no_ox": params.e_no_ox_j_mol,
        "a_an": params.a_an_m3_mol_s * act,
        "e_an": params.e_an_j_mol,
        "a_an_no": params.a_an_no_m3_mol_s * act,
        "e_an_no": params.e_an_no_j_mol,
        "a_an_dec": params.a_an_dec_1_s * act,
        "e_an_dec": params.e_an_dec_j_mol,
        "a_an_n2o": params.a_an_n2o_1_s * act,
        "scr_log_factor_low": math.log(age["activity_200c"]),
        "scr_log_factor_high": math.log(age["activity_550c"]),
        "o2_reference_fraction": params.o2_reference_fraction,
        "o2_order_std": params.o2_order_std,
        "o2_order_ox": params.o2_order_ox,
    }
    return np.array([values[k] for k in PACKED_FIELDS], dtype=np.float64)


def aged(params: CatalystParams, severity: float | None = None, *, age_h: float | None = None) -> CatalystParams:
    """The catalyst after hydrothermal ageing: ``age_h`` hours as the CLEERS samples (0 to :data:`MAX_AGE_H`), or a
    ``severity`` in [0, 1] (0 fresh, 1 the 16 h sample: ``age_h = 16 severity``). Exactly one of the two.

    The losses of storage capacity and activity come from the five-age data (:data:`AGEING_TABLE`). The result's
    ``age_h`` replaces the input's (ageing is a state of the catalyst, not an increment).
    """
    if (severity is None) == (age_h is None):
        raise ValueError("aged() takes exactly one of severity (in [0, 1]) and age_h (hours)")
    if severity is not None:
        if isinstance(severity, bool) or not (isinstance(severity, (int, float)) and 0.0 <= severity <= 1.0):
            raise ValueError(f"severity must be a number in [0, 1], got {severity!r}")
        age_h = MAX_AGE_H * float(severity)
    return dataclasses.replace(params, age_h=check_age_h(age_h))


def randomised(params: CatalystParams, rng: np.random.Generator, spread: float = 0.2,
               age_h_range: tuple[float, float] | None = None) -> CatalystParams:
    """Domain randomisation: storage capacity, SCR/oxidation pre-exponentials and volume scaled by independent
    log-uniform factors within +/- ``spread`` (a fraction, e.g. 0.2 for +/-20 %); with ``age_h_range = (lo, hi)``
    also the catalyst age, uniform in [lo, hi] hours (drawn after the factors, so the factors of a seed do not
    depend on it)."""
    if not 0.0 <= spread < 1.0:
        raise ValueError(f"spread must be in [0, 1), got {spread!r}")
    if age_h_range is not None:
        lo, hi = check_age_range(age_h_range)

    def f() -> float:
        return float(np.exp(rng.uniform(np.log(1 - spread), np.log(1 + spread))))

    out = dataclasses.replace(
        params,
        storage_capacity_mol_m3=params.storage_capacity_mol_m3 * f(),
        a_std_m3_mol_s=params.a_std_m3_mol_s * f(),
        a_an_m3_mol_s=params.a_an_m3_mol_s * f(),
        a_ox_1_s=params.a_ox_1_s * f(),
        volume_m3=params.volume_m3 * f(),
    )
    if age_h_range is not None:
        out = dataclasses.replace(out, age_h=float(rng.uniform(lo, hi)) if hi > lo else lo)
    return out


def check_age_range(age_h_range: object, name: str = "age_h_range") -> tuple[float, float]:
    """``(lo, hi)`` hours with 0 <= lo <= hi <= MAX_AGE_H; ValueError naming ``name`` otherwise."""
    if not isinstance(age_h_range, (tuple, list)) or len(age_h_range) != 2:
        raise ValueError(f"{name} must be a pair (lo, hi) of hours in [0, {MAX_AGE_H:g}], got {age_h_range!r}")
    lo = check_age_h(age_h_range[0], f"{name}[0]")
    hi = check_age_h(age_h_range[1], f"{name}[1]")
    if lo > hi:
        raise ValueError(f"{name} must have lo <= hi, got {age_h_range!r}")
    return lo, hi


PRESETS: dict[str, CatalystParams] = {
    # Cu-SSZ-13 kinetics calibrated to the CLEERS lab data, on a 34 L brick for a 12-13 L engine.
    "cu_zeolite": CatalystParams(),
}


def catalyst_preset(name: str | CatalystParams) -> CatalystParams:
    """Resolve a preset name (or pass a :class:`CatalystParams` through)."""
    if isinstance(name, CatalystParams):
        return name
    if not isinstance(name, str) or name not in PRESETS:
        raise ValueError(f"unknown catalyst preset {name!r}; choose one of {sorted(PRESETS)} or pass CatalystParams")
    return PRESETS[name]


@dataclass(frozen=True)
class DosingParams:
    """AdBlue injection and urea decomposition upstream of the SCR (PHYSICS.md section 3)."""

    max_rate_g_s: float = 3.0  # g/s AdBlue, injector limit for a ~330 kW engine [chosen: PHYSICS.md "a few g/s"]
    # Urea decomposition efficiency eta(T) = 1 / (1 + exp(-(T - T50) / width)) of the SCR inlet temperature:
    # incomplete below roughly 180-200 C [lit, low authority: PHYSICS.md 3]; 50 % at 180 C [chosen].
    decomposition_t50_k: float = 453.15  # K
    decomposition_width_k: float = 10.0  # K [chosen: complete (> 99 %) above about 225 C]

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not math.isfinite(v) or v <= 0:
                raise ValueError(f"DosingParams.{f.name} must be a positive finite number, got {v!r}")


@dataclass(frozen=True)
class SensorParams:
    """What the controller measures (PHYSICS.md section 5)."""

    # Tailpipe NOx sensor reading = NO + 0.9 NO2 + k NH3 [lit: CSM sensor FAQ; k ~ 0.6-1.0 by sensor]
    nox_sensor_no2_gain: float = 0.9
    nox_sensor_nh3_gain: float = 1.0
    nox_sensor_time_constant_s: float = 1.0  # s, first-order lag [lit: PHYSICS.md 5, ~1 s]
    nox_sensor_noise_ppm: float = 2.0  # ppm standard deviation [chosen: typical +/-10 ppm accuracy band]
    upstream_nox_noise_ppm: float = 5.0  # ppm [chosen]
    temperature_time_constant_s: float = 3.0  # s, thermocouple lag [chosen]
    temperature_noise_k: float = 0.5  # K [chosen]
    flow_noise_fraction: float = 0.02  # relative noise of the ECU exhaust-flow estimate [chosen]
    nh3_sensor_time_constant_s: float = 1.0  # s [chosen]
    nh3_sensor_noise_ppm: float = 1.0  # ppm [chosen]

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not math.isfinite(v) or v < 0:
                raise ValueError(f"SensorParams.{f.name} must be a non-negative finite number, got {v!r}")

    def noiseless(self) -> SensorParams:
        """The same sensors without noise (lags kept)."""
        return dataclasses.replace(self, nox_sensor_noise_ppm=0.0, upstream_nox_noise_ppm=0.0,
                                   temperature_noise_k=0.0, flow_noise_fraction=0.0, nh3_sensor_noise_ppm=0.0)


