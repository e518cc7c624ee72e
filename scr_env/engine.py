"""Engine-out conditions of a generic Euro VI heavy-duty diesel and the thermal path to the SCR inlet.

This module turns an engine operating point (speed, torque) into the disturbance inputs of the SCR catalyst
(PHYSICS.md section 4): exhaust mass and molar flow, engine-out temperature, engine-out NOx and its NO2 share.
It then carries the exhaust temperature through the lumped thermal masses of the DOC and the DPF, and the NO2/NOx
ratio through the DOC's NO oxidation.

The engine is a documented smooth parametric model of a generic 12.8 L, ~330 kW engine, **not** a specific product.
Its three calibration anchors are public heavy-duty figures [lit: LiU engine map, PHYSICS.md section 4]:

==============================  ===========  ================  ===============  ================
operating point                 power [kW]   exhaust [kg/s]    NOx [ppm]        model gives
==============================  ===========  ================  ===============  ================
1900 rpm, 1663 Nm (rated)       ~331         0.516             ~1040            exact (closed form)
1000 rpm, 2115 Nm (peak torque) ~221         0.237             ~2035            exact (closed form)
 700 rpm,    0 Nm (idle-like)       0         0.059              ~190           exact (closed form)
==============================  ===========  ================  ===============  ================

How the coefficients were obtained (closed form, three equations in three unknowns per model, done once offline;
the numbers are reproduced in ``tests/scr_env/test_engine.py``):

* exhaust mass flow ``m = n (a_n + a_np P+) + a_p P+`` (n in rpm, P+ = max(P, 0) in kW). The 700 rpm / 0 Nm point
  fixes ``a_n = 0.059 / 700``; the two loaded points then give a 2x2 linear system for ``a_p`` and ``a_np``.
  The form reads as "naturally aspirated pumping plus boost that grows with fuelled power, more so at high speed".
* NOx ``ppm = c_idle * phi + c_load * bmep+ * (max(n, n_idle) / 1000 rpm) ** (-k)``, with ``phi`` the fuelled
  fraction (1 at zero or positive torque, 0 at full drag). The zero-torque point fixes ``c_idle = 190 ppm``, the
  1000 rpm point ``c_load``, the 1900 rpm point the speed exponent ``k``: NOx concentration rises with load (bmep)
  and falls with speed (less residence time at high temperature), as in measured heavy-duty maps.

Functions are pure, vectorised over numpy arrays, and take an :class:`EngineParams` explicitly.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from scr_env.constants import (
    AMBIENT_TEMPERATURE_K,
    EXHAUST_HEAT_CAPACITY_J_KG_K,
    EXHAUST_MOLAR_MASS_KG_MOL,
    GAS_CONSTANT_J_MOL_K,
)

__all__ = [
    "EngineParams",
    "aftertreatment_temperatures",
    "doc_no2_fraction",
    "engine_out",
    "full_load_torque_nm",
    "motoring_torque_nm",
    "reference_speeds",
]

_RPM_TO_RAD_S = math.pi / 30.0  # (rad/s) per rpm


def _anchor_fit() -> tuple[float, float, float, float, float, float]:
    """Closed-form calibration of the flow and NOx models to the three LiU anchor points (see module docstring).

    Returns ``(a_n, a_p, a_np, c_idle, c_load, k)``. Kept as a function so that the test suite can check that
    the literal coefficients in :class:`EngineParams` are its output.
    """
    displacement_m3 = 0.0128
    n1, t1, m1, x1 = 1900.0, 1663.0, 0.516, 1040.0  # rpm, Nm, kg/s, ppm [lit: LiU engine map]
    n2, t2, m2, x2 = 1000.0, 2115.0, 0.237, 2035.0
    n0, m0, x0 = 700.0, 0.059, 190.0
    p1 = n1 * t1 * _RPM_TO_RAD_S / 1e3
    p2 = n2 * t2 * _RPM_TO_RAD_S / 1e3
    a_n = m0 / n0
    a = np.array([[p1, n1 * p1], [p2, n2 * p2]])
    b = np.array([m1 - a_n * n1, m2 - a_n * n2])
    a_p, a_np = np.linalg.solve(a, b)
    bmep1 = 4.0 * math.pi * t1 / displacement_m3 / 1e5
    bmep2 = 4.0 * math.pi * t2 / displacement_m3 / 1e5
    c_idle = x0
    c_load = (x2 - c_idle) / bmep2  # the speed factor (n2 / 1000 rpm) ** -k is 1 at n2 = 1000 rpm
    k = -math.log((x1 - c_idle) / (c_load * bmep1)) / math.log(n1 / 1000.0)
    return float(a_n), float(a_p), float(a_np), float(c_idle), float(c_load), float(k)


@dataclass(frozen=True)
class EngineParams:
    """A generic 12.8 L, ~330 kW Euro VI heavy-duty diesel with DOC and DPF (PHYSICS.md section 4).

    All curves are tuples (hashable, so traces can be cached per parameter set). Units are in the field names or
    the comments; every number carries its source or a "[chosen]" reason.
    """

    name: str = "generic_12p8l_330kw"
    displacement_m3: float = 0.0128  # m3 [chosen: generic 12.8 L six-cylinder, the LiU/Scania class of engine]
    # --- GTR No. 4 reference speeds (denormalisation of WHTC/WHSC) ------------------------------------------------
    # The example values of a public study (data/cycles/PROVENANCE.md); kept for comparability with it. Our own
    # full-load curve gives n_lo ~ 829, n_pref ~ 1291, n_hi ~ 2300 rpm by the GTR definitions (see reference_speeds()).
    idle_speed_rpm: float = 500.0  # rpm [data: PROVENANCE.md example]
    n_lo_rpm: float = 815.0  # rpm, lowest speed at 55 % of P_max [data: PROVENANCE.md example]
    n_pref_rpm: float = 1418.0  # rpm, 51 % of the torque integral [data: PROVENANCE.md example]
    n_hi_rpm: float = 2301.0  # rpm, highest speed at 70 % of P_max [data: PROVENANCE.md example]
    # --- full-load torque curve ------------------------------------------------------------------------------------
    # Plateau 2150 Nm from 900 to 1400 rpm ("about 2100-2150 Nm between 650 and 1400 rpm", PROVENANCE.md), constant
    # power ~331 kW from 1700 to 1900 rpm so that 1900 rpm / 1663 Nm is the rated point [lit: LiU anchor], governor
    # droop to 70 % of P_max at n_hi ~ 2300 rpm and cut-off at 2400 rpm [chosen]. The "1880 Nm at 2000 rpm" of
    # PROVENANCE.md would mean 394 kW, which contradicts both n_lo = 815 rpm and the 331 kW anchor; not used.
    full_load_speed_rpm: tuple[float, ...] = (
        500.0, 600.0, 700.0, 800.0, 900.0, 1000.0, 1400.0, 1500.0, 1600.0, 1700.0, 1800.0, 1900.0, 2000.0, 2100.0,
        2200.0, 2300.0, 2400.0,
    )
    full_load_torque_nm: tuple[float, ...] = (
        1000.0, 1350.0, 1700.0, 2080.0, 2150.0, 2150.0, 2150.0, 2100.0, 1975.0, 1860.0, 1755.0, 1663.0, 1555.0,
        1400.0, 1190.0, 960.0, 0.0,
    )  # Nm [chosen, see above; low-speed torque limited by turbo lag / smoke limit]
    # --- motoring (drag) torque curve: friction + pumping, FMEP ~ 0.9 to 2.7 bar [lit: Heywood 1988, ch. 13] ---------
    motoring_speed_rpm: tuple[float, ...] = (500.0, 1000.0, 1500.0, 2000.0, 2400.0)
    motoring_torque_nm: tuple[float, ...] = (-95.0, -130.0, -175.0, -230.0, -280.0)  # Nm [chosen, see above]
    # --- exhaust mass flow m = n (a_n + a_np P+) + a_p P+ [kg/s]; closed-form fit to LiU anchors (_anchor_fit) -----
    flow_a_n_kg_s_rpm: float = 8.428571428571429e-05  # kg/s per rpm [fit: 0.059 kg/s at 700 rpm, 0 Nm]
    flow_a_p_kg_s_kw: float = 2.606578802e-04  # kg/s per kW [fit]
    flow_a_np_kg_s_rpm_kw: float = 4.288522886e-07  # kg/s per (rpm kW) [fit]
    # --- engine-out NOx ppm = c_idle phi + c_load bmep+ (n/1000)^-k; closed-form fit to LiU anchors -------------------
    nox_idle_ppm: float = 190.0  # ppm [fit: 700 rpm, 0 Nm]
    nox_load_ppm_per_bar: float = 88.85586610  # ppm/bar [fit: 1000 rpm, 2115 Nm -> 2035 ppm]
    nox_speed_exponent: float = 0.8328477964  # - [fit: 1900 rpm, 1663 Nm -> 1040 ppm]
    nox_floor_ppm: float = 1.0  # ppm at full fuel cut [chosen: keeps ratios finite; residual NOx purged on fuel cut]
    # --- engine-out NO2/NOx = f_lo + (f_hi - f_lo) exp(-bmep+/bmep_scale): 3 to 16 % [lit: PHYSICS.md section 4] -----
    no2_fraction_high_load: float = 0.03  # - at high load [lit: PHYSICS.md, 3 %]
    no2_fraction_low_load: float = 0.16  # - at zero load and motoring [lit: PHYSICS.md, 16 %]
    no2_fraction_bmep_scale_bar: float = 4.0  # bar [chosen: NO2 share falls within the first third of the load range]
    # --- engine-out (turbine-out) temperature T = T_amb + dT_0 + xi Q_fuel / (m cp) ---------------------------------
    # Q_fuel = indicated power / eta_ind; the indicated power is brake power + friction (the drag curve), so fuel is
    # zero at full drag and continuous through zero torque. Gives ~415 K at idle, ~705 K at rated power and
    # ~835 K at peak torque, typical turbine-out values of heavy-duty diesels [lit: Heywood 1988, ch. 6 and 14].
    # xi was then tuned (0.25-0.30 tried) so that the hot-WHTC SCR inlet spans ~490-670 K, mean ~570 K, close to
    # the thesis WHTC data (mean 534 K, SD 48 K, ~470-670 K; Paper III Table 1).
    indicated_efficiency: float = 0.45  # - [chosen: typical heavy-duty indicated efficiency 0.45 to 0.50]
    exhaust_energy_fraction: float = 0.27  # - of fuel power leaving as sensible heat after the turbine [chosen]
    exhaust_temperature_offset_k: float = 60.0  # K above ambient with no fuel (compression work, hot walls) [chosen]
    # --- DOC and DPF lumped thermal masses ---------------------------------------------------------------------------
    # DOC 10.5 L cordierite (~5.8 kg at ~550 kg/m3, cp ~1000 J/(kg K)) + ~6 kg can, cones and mat at ~500 J/(kg K).
    doc_heat_capacity_j_k: float = 9.0e3  # J/K [chosen, see above]
    # DPF 25 L cordierite wall-flow (~17.5 kg incl. ash at ~700 kg/m3) + ~17 kg can, cones, mat and mixing pipe.
    dpf_heat_capacity_j_k: float = 26.0e3  # J/K [chosen, see above]
    # Gas-to-solid conductance: laminar channels, Nu ~ 3.6, h ~ 160 W/(m2 K), ~28 m2 DOC / ~50 m2 DPF wetted area;
    # flow-independent h A gives NTU = hA / (m cp) >> 1 at all flows, i.e. the gas leaves near the solid temperature.
    doc_gas_conductance_w_k: float = 4.5e3  # W/K [chosen, see above]
    dpf_gas_conductance_w_k: float = 8.0e3  # W/K [chosen, see above]
    # Loss to ambient through an insulated silencer box, 10-20 W/(m2 K) on ~0.4 / ~0.8 m2 of can and pipe.
    doc_ambient_conductance_w_k: float = 6.0  # W/K [chosen]
    dpf_ambient_conductance_w_k: float = 12.0  # W/K [chosen; includes the mixing pipe to the SCR]
    ambient_temperature_k: float = AMBIENT_TEMPERATURE_K  # K [chosen: 25 C test cell, scr_env.constants]
    # Hot start: a warm aftertreatment after the 10 min soak that follows the cold WHTC (GTR No. 4). Solids start at
    # max(this value, steady state of the first operating point).
    hot_start_temperature_k: float = 500.0  # K [chosen: ~227 C, hot-WHTC SCR inlet ~470-500 K in the thesis data]
    # --- DOC NO oxidation: NO + 1/2 O2 <-> NO2 ----------------------------------------------------------------------
    # Outlet NO2/NOx approaches min(thermodynamic equilibrium, a practical ceiling) with a Damkoehler number that
    # is Arrhenius in the DOC temperature and inversely proportional to the flow. Pt DOCs give 20 to 50 % NO2/NOx
    # in their active window (~250-400 C), kinetically limited below ~200 C and equilibrium-limited above ~400 C
    # [lit: Russell and Epling 2011, Catal. Rev. 53:337-423; Katare et al. 2007, Ind. Eng. Chem. Res. 46:2445].
    doc_no2_ceiling: float = 0.50  # - [lit: upper end of 20-50 % for an aged, HC-inhibited Pt/Pd DOC]
    doc_no_ox_activation_j_mol: float = 80.0e3  # J/mol [lit: Mulla et al. 2006, J. Catal. 241:389, Pt ~ 80 kJ/mol]
    doc_no_ox_damkoehler_ref: float = 0.7  # - at 250 C and 5 mol/s [chosen: half-way to the ceiling, ~30 % NO2/NOx]
    doc_no_ox_reference_temperature_k: float = 523.15  # K (250 C) [chosen]
    doc_no_ox_reference_flow_mol_s: float = 5.0  # mol/s [chosen: mid-range exhaust flow]
    exhaust_o2_mole_fraction: float = 0.10  # - [chosen: typical lean diesel exhaust, PHYSICS.md 10 % O2]
    # NO + 1/2 O2 -> NO2 standard enthalpy and entropy [lit: NIST-JANAF tables, 298 K, taken T-independent]
    no_ox_enthalpy_j_mol: float = -57.19e3  # J/mol
    no_ox_entropy_j_mol_k: float = -73.28  # J/(mol K)

    def __post_init__(self) -> None:
        for speeds, torques, label in (
            (self.full_load_speed_rpm, self.full_load_torque_nm, "full_load"),
            (self.motoring_speed_rpm, self.motoring_torque_nm, "motoring"),
        ):
            if len(speeds) != len(torques) or len(speeds) < 2:
                raise ValueError(f"{label}_speed_rpm and {label}_torque_nm must have the same length >= 2")
            if np.any(np.diff(np.asarray(speeds)) <= 0.0):
                raise ValueError(f"{label}_speed_rpm must be strictly increasing")
        if np.any(np.asarray(self.motoring_torque_nm) >= 0.0):
            raise ValueError("motoring_torque_nm must be negative (drag)")
        if not self.idle_speed_rpm < self.n_lo_rpm < self.n_pref_rpm < self.n_hi_rpm:
            raise ValueError("reference speeds must satisfy idle_speed_rpm < n_lo_rpm < n_pref_rpm < n_hi_rpm")
        for name in ("doc_heat_capacity_j_k", "dpf_heat_capacity_j_k", "doc_gas_conductance_w_k",
                     "dpf_gas_conductance_w_k", "ambient_temperature_k", "displacement_m3"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be positive")

    @property
    def max_speed_rpm(self) -> float:
        """Highest speed of the full-load curve [rpm] (governor cut-off)."""
        return float(self.full_load_speed_rpm[-1])


def _as_float_array(x: ArrayLike, name: str) -> np.ndarray:
    arr = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite")
    return arr


def full_load_torque_nm(params: EngineParams, speed_rpm: ArrayLike) -> np.ndarray:
    """Full-load (maximum) brake torque, linear interpolation of the curve, zero outside it.

    Parameters
    ----------
    params : EngineParams
    speed_rpm : array_like
        Engine speed [rpm].

    Returns
    -------
    numpy.ndarray
        Maximum torque [Nm], same shape as ``speed_rpm``.
    """
    n = _as_float_array(speed_rpm, "speed_rpm")
    return np.interp(n, params.full_load_speed_rpm, params.full_load_torque_nm, left=params.full_load_torque_nm[0],
                     right=0.0)


def motoring_torque_nm(params: EngineParams, speed_rpm: ArrayLike) -> np.ndarray:
    """Motoring (drag) torque, negative, linear interpolation of the curve, end values held.

    Parameters
    ----------
    params : EngineParams
    speed_rpm : array_like
        Engine speed [rpm].

    Returns
    -------
    numpy.ndarray
        Drag torque [Nm] (< 0), same shape as ``speed_rpm``.
    """
    n = _as_float_array(speed_rpm, "speed_rpm")
    return np.interp(n, params.motoring_speed_rpm, params.motoring_torque_nm)


def reference_speeds(params: EngineParams) -> dict[str, float]:
    """GTR No. 4 reference speeds computed from the full-load curve (for checking the curve, not used elsewhere).

    Returns
    -------
    dict
        ``p_max_kw``, ``n_lo_rpm`` (lowest speed at 55 % of P_max), ``n_hi_rpm`` (highest at 70 %), ``n_95h_rpm``
        (highest at 95 %) and ``n_pref_rpm`` (51 % of the torque integral from idle to n_95h).
    """
    n = np.linspace(params.idle_speed_rpm, params.max_speed_rpm, 20001)
    t = full_load_torque_nm(params, n)
    p = t * n * _RPM_TO_RAD_S / 1e3
    p_max = float(p.max())
    n_lo = float(n[np.argmax(p >= 0.55 * p_max)])
    n_hi = float(n[np.nonzero(p >= 0.70 * p_max)[0][-1]])
    n_95h = float(n[np.nonzero(p >= 0.95 * p_max)[0][-1]])
    integral = np.concatenate([[0.0], np.cumsum(0.5 * (t[1:] + t[:-1]) * np.diff(n))])
    n_pref = float(n[np.argmax(integral >= 0.51 * np.interp(n_95h, n, integral))])
    return {"p_max_kw": p_max, "n_lo_rpm": n_lo, "n_hi_rpm": n_hi, "n_95h_rpm": n_95h, "n_pref_rpm": n_pref}


def engine_out(params: EngineParams, speed_rpm: ArrayLike, torque_nm: ArrayLike) -> dict[str, np.ndarray]:
    """Engine-out exhaust conditions at given operating points (quasi-static maps).

    Parameters
    ----------
    params : EngineParams
    speed_rpm : array_like
        Engine speed [rpm], > 0. Speeds below idle are treated as idle for the NOx speed factor.
    torque_nm : array_like
        Brake torque [Nm]; negative when motored (fuel is cut progressively down to the drag curve).

    Returns
    -------
    dict of numpy.ndarray (broadcast shape of the inputs)
        ``exhaust_mass_flow_kg_s`` [kg/s], ``exhaust_flow_mol_s`` [mol/s] (M = 28.9 g/mol, lean exhaust ~ air),
        ``engine_out_temperature_k`` [K] (turbine outlet), ``nox_ppm`` [mole ppm], ``no2_fraction_engine_out`` [-]
        (NO2/NOx), ``power_kw`` [kW] (brake power, negative when motored).

    Raises
    ------
    ValueError
        If speed or torque is not finite, or a speed is not positive.
    """
    n, t = np.broadcast_arrays(_as_float_array(speed_rpm, "speed_rpm"), _as_float_array(torque_nm, "torque_nm"))
    if np.any(n <= 0.0):
        raise ValueError("speed_rpm must be positive")
    omega = n * _RPM_TO_RAD_S  # rad/s
    power_kw = t * omega / 1e3
    p_pos = np.maximum(power_kw, 0.0)
    mass_flow = n * (params.flow_a_n_kg_s_rpm + params.flow_a_np_kg_s_rpm_kw * p_pos) + params.flow_a_p_kg_s_kw * p_pos
    flow_mol = mass_flow / EXHAUST_MOLAR_MASS_KG_MOL

    drag = motoring_torque_nm(params, n)  # < 0
    # Fuelled fraction of the friction: 1 at zero or positive torque, 0 at full drag (fuel cut).
    fuelled = np.clip(1.0 - t / drag, 0.0, 1.0)
    indicated_kw = np.maximum(power_kw - drag * omega / 1e3, 0.0)  # brake + friction power [kW]
    fuel_power_w = indicated_kw * 1e3 / params.indicated_efficiency
    temperature = (
        params.ambient_temperature_k
        + params.exhaust_temperature_offset_k
        + params.exhaust_energy_fraction * fuel_power_w / (mass_flow * EXHAUST_HEAT_CAPACITY_J_KG_K)
    )

    bmep_pos_bar = np.maximum(4.0 * math.pi * t / params.displacement_m3 / 1e5, 0.0)
    speed_factor = (np.maximum(n, params.idle_speed_rpm) / 1000.0) ** (-params.nox_speed_exponent)
    nox = params.nox_idle_ppm * fuelled + params.nox_load_ppm_per_bar * bmep_pos_bar * speed_factor
    nox = np.maximum(nox, params.nox_floor_ppm)
    no2 = params.no2_fraction_high_load + (params.no2_fraction_low_load - params.no2_fraction_high_load) * np.exp(
        -bmep_pos_bar / params.no2_fraction_bmep_scale_bar
    )
    return {
        "exhaust_mass_flow_kg_s": mass_flow,
        "exhaust_flow_mol_s": flow_mol,
        "engine_out_temperature_k": temperature,
        "nox_ppm": nox,
        "no2_fraction_engine_out": no2,
        "power_kw": power_kw,
    }


def _initial_pair(initial_temperature_k: float | tuple[float, float] | ArrayLike) -> tuple[float, float]:
    arr = np.atleast_1d(np.asarray(initial_temperature_k, dtype=np.float64))
    if arr.size == 1:
        arr = np.repeat(arr, 2)
    if arr.size != 2 or not np.all(np.isfinite(arr)) or np.any(arr <= 0.0):
        raise ValueError("initial_temperature_k must be one positive temperature or a (doc, dpf) pair, in K")
    return float(arr[0]), float(arr[1])


def aftertreatment_temperatures(
    params: EngineParams,
    time_s: ArrayLike,
    engine_out_temperature_k: ArrayLike,
    exhaust_mass_flow_kg_s: ArrayLike,
    initial_temperature_k: float | tuple[float, float],
) -> tuple[np.ndarray, np.ndarray]:
    """Exhaust temperature after the DOC and after the DPF (= SCR inlet), two lumped thermal masses in series.

    Each brick is one solid temperature ``T_s`` with heat capacity ``C``, gas-to-solid conductance ``hA`` and a loss
    ``UA`` to ambient::

        C dT_s/dt = eps m cp (T_in - T_s) - UA (T_s - T_amb),   eps = 1 - exp(-hA / (m cp))
        T_out     = T_s + (1 - eps) (T_in - T_s)

    The time constant ``C / (eps m cp + UA)`` is ~15-40 s at high flow and ~150-450 s at idle. Inputs are held
    constant over each sample interval and the linear ODE is integrated exactly (exponential of the interval), so the
    scheme is unconditionally stable and exact for piecewise-constant inputs at any step.

    Parameters
    ----------
    params : EngineParams
    time_s : array_like, shape (n,)
        Sample times [s], non-decreasing.
    engine_out_temperature_k : array_like, shape (n,)
        Turbine-outlet exhaust temperature [K].
    exhaust_mass_flow_kg_s : array_like, shape (n,)
        Exhaust mass flow [kg/s], >= 0.
    initial_temperature_k : float or (float, float)
        Solid temperature of DOC and DPF at ``time_s[0]`` [K]; one value for both or a (doc, dpf) pair.

    Returns
    -------
    doc_out_k, scr_inlet_k : numpy.ndarray, shape (n,)
        Gas temperature after the DOC and after the DPF (the SCR inlet) [K] at each sample time.
    """
    time = _as_float_array(time_s, "time_s").ravel()
    t_in = _as_float_array(engine_out_temperature_k, "engine_out_temperature_k").ravel()
    mdot = _as_float_array(exhaust_mass_flow_kg_s, "exhaust_mass_flow_kg_s").ravel()
    if not (time.size == t_in.size == mdot.size):
        raise ValueError("time_s, engine_out_temperature_k and exhaust_mass_flow_kg_s must have the same length")
    if np.any(np.diff(time) < 0.0):
        raise ValueError("time_s must be non-decreasing")
    if np.any(mdot < 0.0):
        raise ValueError("exhaust_mass_flow_kg_s must be non-negative")
    doc_solid, dpf_solid = _initial_pair(initial_temperature_k)
    n = time.size
    if n == 0:
        return np.empty(0), np.empty(0)
    t_amb = params.ambient_temperature_k
    mcp = mdot * EXHAUST_HEAT_CAPACITY_J_KG_K  # W/K
    with np.errstate(divide="ignore"):
        eps_doc = -np.expm1(-params.doc_gas_conductance_w_k / mcp)  # -> 1 as the flow -> 0
        eps_dpf = -np.expm1(-params.dpf_gas_conductance_w_k / mcp)
    g_doc = eps_doc * mcp  # effective gas-solid conductance [W/K]
    g_dpf = eps_dpf * mcp
    ua_doc = params.doc_ambient_conductance_w_k
    ua_dpf = params.dpf_ambient_conductance_w_k
    dt = np.append(np.diff(time), 0.0)
    # Per-interval decay factors (vectorised); only the scalar recurrence stays in the Python loop.
    decay_doc = np.exp(-(g_doc + ua_doc) * dt / params.doc_heat_capacity_j_k).tolist()
    decay_dpf = np.exp(-(g_dpf + ua_dpf) * dt / params.dpf_heat_capacity_j_k).tolist()
    den_doc = (g_doc + ua_doc).tolist()
    den_dpf = (g_dpf + ua_dpf).tolist()
    g_doc_l, g_dpf_l = g_doc.tolist(), g_dpf.tolist()
    e_doc_l, e_dpf_l = eps_doc.tolist(), eps_dpf.tolist()
    t_in_l = t_in.tolist()
    doc_out = [0.0] * n
    scr_in = [0.0] * n
    for k in range(n):
        tin = t_in_l[k]
        t_doc = doc_solid + (1.0 - e_doc_l[k]) * (tin - doc_solid)
        t_dpf = dpf_solid + (1.0 - e_dpf_l[k]) * (t_doc - dpf_solid)
        doc_out[k] = t_doc
        scr_in[k] = t_dpf
        eq_doc = (g_doc_l[k] * tin + ua_doc * t_amb) / den_doc[k] if den_doc[k] > 0.0 else doc_solid
        eq_dpf = (g_dpf_l[k] * t_doc + ua_dpf * t_amb) / den_dpf[k] if den_dpf[k] > 0.0 else dpf_solid
        doc_solid = eq_doc + (doc_solid - eq_doc) * decay_doc[k]
        dpf_solid = eq_dpf + (dpf_solid - eq_dpf) * decay_dpf[k]
    return np.asarray(doc_out), np.asarray(scr_in)


def steady_state_solid_temperatures(
    params: EngineParams, engine_out_temperature_k: float, exhaust_mass_flow_kg_s: float
) -> tuple[float, float]:
    """Steady-state DOC and DPF solid temperatures [K] at a constant operating point (heat in = loss to ambient)."""
    mcp = float(exhaust_mass_flow_kg_s) * EXHAUST_HEAT_CAPACITY_J_KG_K
    if mcp <= 0.0:
        return params.ambient_temperature_k, params.ambient_temperature_k
    t_amb = params.ambient_temperature_k
    g_doc = -math.expm1(-params.doc_gas_conductance_w_k / mcp) * mcp
    g_dpf = -math.expm1(-params.dpf_gas_conductance_w_k / mcp) * mcp
    t_doc_s = (g_doc * engine_out_temperature_k + params.doc_ambient_conductance_w_k * t_amb) / (
        g_doc + params.doc_ambient_conductance_w_k
    )
    eps_doc = g_doc / mcp
    t_doc_gas = t_doc_s + (1.0 - eps_doc) * (engine_out_temperature_k - t_doc_s)
    t_dpf_s = (g_dpf * t_doc_gas + params.dpf_ambient_conductance_w_k * t_amb) / (
        g_dpf + params.dpf_ambient_conductance_w_k
    )
    return float(t_doc_s), float(t_dpf_s)


def doc_no2_fraction(
    params: EngineParams,
    doc_temperature_k: ArrayLike,
    exhaust_flow: ArrayLike,
    no2_fraction_in: ArrayLike,
) -> np.ndarray:
    """NO2/NOx after the DOC (NO + 1/2 O2 <-> NO2 over Pt), quasi-steady.

    The outlet ratio relaxes from the inlet ratio towards ``min(f_eq(T), ceiling)`` with conversion
    ``1 - exp(-Da)``, ``Da = Da_ref exp(-Ea/R (1/T - 1/T_ref)) F_ref / F``::

        f_eq = K sqrt(y_O2) / (1 + K sqrt(y_O2)),   K = exp(-dH/(R T) + dS/R)  [atm^-1/2]

    This gives the textbook shape: little NO2 below ~180 C (kinetic limit), 20-50 % NO2/NOx in the active window
    (~250-400 C), falling again above ~400 C as the equilibrium moves back to NO
    [lit: Russell and Epling 2011, Catal. Rev. 53:337; Katare et al. 2007, Ind. Eng. Chem. Res. 46:2445].
    NOx in total is unchanged by the DOC; passive soot oxidation by NO2 in the DPF is neglected [chosen].

    Parameters
    ----------
    params : EngineParams
    doc_temperature_k : array_like
        DOC temperature [K].
    exhaust_flow : array_like
        Exhaust molar flow [mol/s], > 0 (values are floored at 1e-3 mol/s).
    no2_fraction_in : array_like
        NO2/NOx at the DOC inlet [-], in [0, 1].

    Returns
    -------
    numpy.ndarray
        NO2/NOx at the DOC outlet [-], in [0, 1].
    """
    temp = _as_float_array(doc_temperature_k, "doc_temperature_k")
    flow = np.maximum(_as_float_array(exhaust_flow, "exhaust_flow"), 1e-3)
    f_in = np.clip(_as_float_array(no2_fraction_in, "no2_fraction_in"), 0.0, 1.0)
    if np.any(temp <= 0.0):
        raise ValueError("doc_temperature_k must be positive")
    r = GAS_CONSTANT_J_MOL_K
    k_eq = np.exp(-params.no_ox_enthalpy_j_mol / (r * temp) + params.no_ox_entropy_j_mol_k / r)
    ks = k_eq * math.sqrt(params.exhaust_o2_mole_fraction)
    f_eq = ks / (1.0 + ks)
    # Formation stops at the practical ceiling (never below the inlet ratio); decomposition only down to f_eq.
    target = np.minimum(f_eq, np.maximum(params.doc_no2_ceiling, f_in))
    arrhenius = np.exp(
        np.clip(
            -params.doc_no_ox_activation_j_mol / r * (1.0 / temp - 1.0 / params.doc_no_ox_reference_temperature_k),
            -700.0,
            50.0,
        )
    )
    damkoehler = params.doc_no_ox_damkoehler_ref * arrhenius * params.doc_no_ox_reference_flow_mol_s / flow
    return f_in + (target - f_in) * (-np.expm1(-damkoehler))
