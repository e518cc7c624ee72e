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


@dataclass(frozen=True)
class CatalystParams:
    """A lumped single-site NH3-SCR catalyst brick (Olsson et al. 2008 type kinetics, PHYSICS.md section 2).

    Rates are per storage site; theta is the NH3 coverage in [0, 1]; gas concentrations C in mol/m3;
    pre-exponentials A in the units given, activation energies E in J/mol. The kinetic numbers of ``cu_zeolite``
    come from ``lumped_cu_ssz13_params.txt`` (fitted to the CLEERS Cu-SSZ-13 lab data shipped in
    ``scr_env/data/catalyst``) unless marked otherwise.
    """

    name: str = "cu_zeolite"
    # --- geometry and storage --------------------------------------------------------------------------------
    volume_m3: float = 0.034  # m3 of catalyst brick, 12 L engine [lit: Willems and Cloudt 2011, zeolite SCR]
    n_cells: int = 5  # axial CSTR cells [chosen: PHYSICS.md allows 5-10; 5 keeps the vector env fast]
    storage_capacity_mol_m3: float = 253.5  # mol NH3 sites per m3 catalyst [data: lumped_cu_ssz13_params.txt]
    # --- NH3 adsorption / Temkin desorption -----------------------------------------------------------------
    a_ads_m3_mol_s: float = 1.0e3  # m3/(mol s), not activated [data: lumped fit, "chosen fast"]
    a_des_1_s: float = 2.984e8  # 1/s [data: lumped fit]
    e_des_j_mol: float = 92.66e3  # J/mol at zero coverage [data: lumped fit]
    temkin_gamma: float = 0.95  # - , E_des = E_des0 (1 - gamma theta) [data: lumped fit, at its bound]
    # --- standard SCR: 4 NH3* + 4 NO + O2 -> 4 N2 + 6 H2O (Eley-Rideal, first order in NO) ---------------------
    a_std_m3_mol_s: float = 6.717e6  # m3/(mol s) [data: lumped fit]
    e_std_j_mol: float = 66.95e3  # J/mol [data: lumped fit]
    # --- fast SCR: 2 NH3* + NO + NO2 -> 2 N2 + 3 H2O ----------------------------------------------------------
    a_fast_m6_mol2_s: float = 1.378e19  # m6/(mol2 s) [fitted: experiments.calibrate_catalyst, FastSCR plateaus]
    e_fast_j_mol: float = 149.15e3  # J/mol [fitted: experiments.calibrate_catalyst]
    # --- NO2 SCR: 4 NH3* + 3 NO2 -> 3.5 N2 + 6 H2O (rate per NO2) ------------------------------------------------
    a_no2_m3_mol_s: float = 1.0e6  # m3/(mol s) [chosen: slower than standard SCR, Olsson et al. 2008 ratio]
    e_no2_j_mol: float = 70.0e3  # J/mol [chosen, Olsson et al. 2008 order of magnitude]
    # --- NH3 oxidation to N2: 4 NH3* + 3 O2 -> 2 N2 + 6 H2O (O2 lumped at 10 %) ---------------------------------
    a_ox_1_s: float = 7.103e5  # 1/s [data: lumped fit]
    e_ox_j_mol: float = 107.85e3  # J/mol [data: lumped fit]
    # --- NH3 oxidation to NO (high temperature): 4 NH3* + 5 O2 -> 4 NO + 6 H2O --------------------------------
    a_ox_no_1_s: float = 2.834e13  # 1/s [fitted: experiments.calibrate_catalyst, NH3-only steps 400-550 C]
    e_ox_no_j_mol: float = 225.98e3  # J/mol [fitted: experiments.calibrate_catalyst]
    # --- N2O formation: 2 NH3* + 2 NO + 3/2 O2 -> 2 N2O + 3 H2O (rate per N2O, first order in NO) ------------------
    a_n2o_m3_mol_s: float = 3.347e4  # m3/(mol s) [fitted: experiments.calibrate_catalyst, standard-SCR N2O]
    e_n2o_j_mol: float = 60.0e3  # J/mol [chosen: see experiments.calibrate_catalyst]
    # --- oxygen dependence (rates are given at the lab's 10 % O2) -----------------------------------------------
    o2_reference_fraction: float = 0.10  # mole fraction of the lab data [data: CLEERS protocol]
    o2_order_std: float = 0.5  # - [chosen: half order in O2 for standard SCR, Olsson et al. 2008]
    o2_order_ox: float = 1.0  # - [chosen: first order for the NH3 oxidations]
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
    # --- ageing (1 = fresh): multiplies storage capacity and the SCR/oxidation pre-exponentials ----------------
    storage_retention: float = 1.0  # - [see aged()]
    activity_retention: float = 1.0  # - [see aged()]

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "name":
                continue
            if not isinstance(v, (int, float)) or not math.isfinite(v):
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
        for name in ("storage_retention", "activity_retention"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ValueError(f"CatalystParams.{name} must be in (0, 1], got {getattr(self, name)!r}")

    @property
    def sites_mol(self) -> float:
        """NH3 storage sites of the whole brick [mol] (capacity after ageing)."""
        return self.volume_m3 * self.storage_capacity_mol_m3 * self.storage_retention

    @property
    def heat_capacity_j_k(self) -> float:
        """Heat capacity of the solid of the whole brick [J/K]."""
        return (self.volume_m3 * (1.0 - self.open_frontal_area) * self.solid_density_kg_m3
                * self.solid_heat_capacity_j_kg_k)

    def replace(self, **changes: float) -> CatalystParams:
        """A copy with some fields changed (validated)."""
        return dataclasses.replace(self, **changes)


# Order of the packed parameter vector used by the compiled kernel (see pack()).
PACKED_FIELDS: tuple[str, ...] = (
    "n_cells", "sites_per_cell_mol", "heat_capacity_per_cell_j_k", "gas_solid_ua_per_cell_w_k",
    "ambient_loss_per_cell_w_k", "ambient_temperature_k",
    "a_ads", "a_des", "e_des", "temkin_gamma",
    "a_std", "e_std", "a_fast", "e_fast", "a_no2", "e_no2", "a_ox", "e_ox", "a_ox_no", "e_ox_no", "a_n2o", "e_n2o",
    "o2_reference_fraction", "o2_order_std", "o2_order_ox",
)
P = {name: i for i, name in enumerate(PACKED_FIELDS)}  # index of each packed parameter


def pack(params: CatalystParams) -> np.ndarray:
    """Pack a catalyst into the float64 vector the compiled kernel reads (order: :data:`PACKED_FIELDS`).

    Ageing is applied here: capacity times ``storage_retention``, SCR and oxidation pre-exponentials times
    ``activity_retention``.
    """
    n = params.n_cells
    v_cell = params.volume_m3 / n
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
        "e_des": params.e_des_j_mol,
        "temkin_gamma": params.temkin_gamma,
        "a_std": params.a_std_m3_mol_s * act,
        "e_std": params.e_std_j_mol,
        "a_fast": params.a_fast_m6_mol2_s * act,
        "e_fast": params.e_fast_j_mol,
        "a_no2": params.a_no2_m3_mol_s * act,
        "e_no2": params.e_no2_j_mol,
        "a_ox": params.a_ox_1_s * act,
        "e_ox": params.e_ox_j_mol,
        "a_ox_no": params.a_ox_no_1_s * act,
        "e_ox_no": params.e_ox_no_j_mol,
        "a_n2o": params.a_n2o_m3_mol_s * act,
        "e_n2o": params.e_n2o_j_mol,
        "o2_reference_fraction": params.o2_reference_fraction,
        "o2_order_std": params.o2_order_std,
        "o2_order_ox": params.o2_order_ox,
    }
    return np.array([values[k] for k in PACKED_FIELDS], dtype=np.float64)


def aged(params: CatalystParams, severity: float) -> CatalystParams:
    """The catalyst after hydrothermal ageing of the given severity in [0, 1] (0 fresh, 1 end of life).

    End of life loses 40 % of the NH3 storage capacity and 50 % of the activity [chosen: the order of the losses
    reported for Cu-zeolites after severe hydrothermal ageing, e.g. Luo et al. 2015, SAE 2015-01-1022; a linear
    path in between].
    """
    if not (isinstance(severity, (int, float)) and 0.0 <= severity <= 1.0):
        raise ValueError(f"severity must be a number in [0, 1], got {severity!r}")
    return dataclasses.replace(
        params,
        storage_retention=params.storage_retention * (1.0 - 0.4 * severity),
        activity_retention=params.activity_retention * (1.0 - 0.5 * severity),
    )


def randomised(params: CatalystParams, rng: np.random.Generator, spread: float = 0.2) -> CatalystParams:
    """Domain randomisation: storage capacity, SCR/oxidation pre-exponentials and volume scaled by independent
    log-uniform factors within +/- ``spread`` (a fraction, e.g. 0.2 for +/-20 %)."""
    if not 0.0 <= spread < 1.0:
        raise ValueError(f"spread must be in [0, 1), got {spread!r}")

    def f() -> float:
        return float(np.exp(rng.uniform(np.log(1 - spread), np.log(1 + spread))))

    return dataclasses.replace(
        params,
        storage_capacity_mol_m3=params.storage_capacity_mol_m3 * f(),
        a_std_m3_mol_s=params.a_std_m3_mol_s * f(),
        a_fast_m6_mol2_s=params.a_fast_m6_mol2_s * f(),
        a_ox_1_s=params.a_ox_1_s * f(),
        volume_m3=params.volume_m3 * f(),
    )


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


