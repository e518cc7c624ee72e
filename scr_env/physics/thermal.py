"""The heat balance of the catalyst cells, written once for every backend.

Like :mod:`scr_env.physics.cell`, these are plain scalar functions that look up ``exp``, ``fmax`` and ``select`` as
module globals; :mod:`scr_env.physics.backends` compiles the same code objects for numba (the plant kernel), CasADi
(:mod:`scr_env.casadi_model`) and numpy (:mod:`control.models`, on arrays). The loop over the cells in flow order
is the caller's (it differs only in how each backend holds a row of cells).

Model (PHYSICS.md section 2): the solid of each cell is one lumped heat capacity C [J/K], exchanging heat with the
gas (G [W/K]) and losing it to ambient (L [W/K]):

    C dT/dt = G (T_gas_in - T) - L (T - T_amb),   G = m cp (1 - exp(-NTU)),   NTU = UA / (m cp)

where m cp = F M c_p [W/K] is the heat capacity flow of the exhaust. G is the exact exchange of a gas stream that
passes a solid at uniform temperature: the gas leaves the cell at ``T + (T_gas_in - T) exp(-NTU)``.
"""
from __future__ import annotations

from math import exp  # rebound per backend (see the module docstring)

from scr_env.constants import EXHAUST_HEAT_CAPACITY_J_KG_K, EXHAUST_MOLAR_MASS_KG_MOL

#: J/(mol K): heat capacity of one mole of exhaust (M c_p, lean diesel exhaust ~ air)
EXHAUST_MOLAR_HEAT_CAPACITY_J_MOL_K = EXHAUST_MOLAR_MASS_KG_MOL * EXHAUST_HEAT_CAPACITY_J_KG_K


def fmax(a, b):  # rebound per backend
    """The larger of two floats (numba: ``max``; CasADi: ``fmax``; numpy: ``maximum``)."""
    return max(a, b)


def select(condition, if_true, if_false):  # rebound per backend
    """``if_true`` where ``condition`` else ``if_false`` (CasADi: ``if_else``; numpy: ``where``)."""
    return if_true if condition else if_false


def gas_solid_exchange(flow_mol_s, ua_w_k):
    """(G [W/K], exp(-NTU) [-]) of one cell: the gas-solid heat exchange at an exhaust flow [mol/s] and the cell's
    convective conductance UA [W/K]. No flow, no exchange (G = 0, and the gas leaves at the solid temperature)."""
    mcp = flow_mol_s * EXHAUST_MOLAR_HEAT_CAPACITY_J_MOL_K  # W/K
    # fmax keeps the dead branch finite for the backends that evaluate both (CasADi, numpy)
    decay = select(mcp > 0.0, exp(-ua_w_k / fmax(mcp, 1e-300)), 0.0)
    return mcp * (1.0 - decay), decay


def gas_outlet_temperature(solid_temperature_k, gas_inlet_temperature_k, decay):
    """Temperature [K] of the gas leaving a cell at solid temperature T, given exp(-NTU) of
    :func:`gas_solid_exchange`."""
    return solid_temperature_k + (gas_inlet_temperature_k - solid_temperature_k) * decay


def cell_temperature_step(solid_temperature_k, gas_inlet_temperature_k, heat_capacity_j_k, coupling_w_k, loss_w_k,
                          ambient_temperature_k, dt_s, decay):
    """One implicit-Euler step of length ``dt_s`` [s] of a cell's heat balance (closed form: it is linear).

    Returns (solid temperature at the end of the step [K], gas temperature leaving the cell [K], which feeds the
    next cell). Unconditionally stable for any dt.
    """
    t_new = ((heat_capacity_j_k * solid_temperature_k
              + dt_s * (coupling_w_k * gas_inlet_temperature_k + loss_w_k * ambient_temperature_k))
             / (heat_capacity_j_k + dt_s * (coupling_w_k + loss_w_k)))
    return t_new, gas_outlet_temperature(t_new, gas_inlet_temperature_k, decay)


def cell_temperature_rate(solid_temperature_k, gas_inlet_temperature_k, heat_capacity_j_k, coupling_w_k, loss_w_k,
                          ambient_temperature_k):
    """dT/dt [K/s] of a cell's solid: the right-hand side of the heat balance (module docstring)."""
    return (coupling_w_k * (gas_inlet_temperature_k - solid_temperature_k)
            - loss_w_k * (solid_temperature_k - ambient_temperature_k)) / heat_capacity_j_k
