"""The SCR catalyst in CasADi symbolic form, for model-based controllers (oracle MPC, estimators).

No piece of the plant is typed again here: the chemistry (:mod:`scr_env.physics.cell`), the heat balance
(:mod:`scr_env.physics.thermal`) and the dosing and inlet gas (:mod:`scr_env.physics.dosing`) come from
:func:`scr_env.physics.backends.casadi_namespace`, the same code objects that the numba plant kernel runs. This
module only wires the cells in series, as :mod:`scr_env.physics.kernel` does; ``tests/scr_env/test_casadi_model.py``
proves the two equal.

State and input (both column vectors):

============  ==========================================================================================
``x``         ``[theta_1 .. theta_N, T_1 .. T_N]``: NH3 coverage per cell [-], solid temperature per cell [K]
``u``         ``[exhaust_flow_mol_s, inlet_temperature_k, inlet_nox_ppm, inlet_no2_fraction, adblue_g_s,
              o2_fraction]`` (the order of :data:`scr_env.physics.kernel.INPUT_FIELDS`)
``y``         ``[tailpipe_no_ppm, tailpipe_no2_ppm, tailpipe_nh3_ppm, tailpipe_n2o_ppm, outlet_temperature_k]``
============  ==========================================================================================

Two forms:

* :func:`catalyst_rhs`: the continuous-time model ``xdot = f(x, u)``, ``y = h(x, u)``, gas phase quasi-steady;
* :func:`catalyst_step`: one control interval. ``method="implicit"`` (default) is the kernel's integrator: implicit
  Euler of the thermal balance (closed form, linear), then implicit Euler of the coverage at the end-of-step
  temperatures, cell by cell in flow order, each cell's implicit equation solved by a CasADi ``rootfinder``
  (Newton) -- differentiable through the implicit function theorem, and equal to :func:`kernel.plant_step` to
  solver tolerance. ``method="rk4"`` integrates :func:`catalyst_rhs` with ``substeps`` explicit RK4 steps: cheaper
  to differentiate and SX-expandable, but explicit, so it needs substeps of about 1/|dg/dtheta| -- the coverage is
  stiff when hot (desorption constants of hundreds of 1/s above 500 C); use it only where that is checked.

Example
-------
>>> from scr_env.params import CatalystParams
>>> from scr_env.casadi_model import catalyst_step
>>> step = catalyst_step(CatalystParams(), dt=0.5)
>>> x_next, y = step([0.2] * 5 + [550.0] * 5, [8.0, 560.0, 800.0, 0.1, 0.5, 0.1])  # doctest: +SKIP
"""
from __future__ import annotations

from typing import Literal

import casadi as ca

from scr_env.params import KINETIC_SLICE, CatalystParams, DosingParams, P, pack
from scr_env.physics.backends import casadi_functions, casadi_namespace
from scr_env.physics.kernel import I_ADBLUE, I_FLOW, I_NO2F, I_NOX, I_TIN, INPUT_FIELDS

OUTPUT_NAMES = ("tailpipe_no_ppm", "tailpipe_no2_ppm", "tailpipe_nh3_ppm", "tailpipe_n2o_ppm", "outlet_temperature_k")
N_INPUTS = len(INPUT_FIELDS)
_KINETIC = KINETIC_SLICE  # packed kinetic parameters, the arguments of rate_constants
_NEWTON_ABSTOL = 1e-14  # -, implicit-Euler residual of a cell relative to the N fed to it (the kernel stops at 1e-7
# and ends on the conservative state, scr_env.physics.kernel._FLUX_TOL; the agreement test allows for that)
_NEWTON_STEPTOL = 1e-16  # -, Newton step on the coverage (stops at the rounding floor)


class _Plant:
    """Packed numbers and the symbolic pieces shared by the rhs and the step (one catalyst, one dosing)."""

    def __init__(self, params: CatalystParams, dosing: DosingParams | None) -> None:
        if not isinstance(params, CatalystParams):
            raise TypeError(f"params must be a CatalystParams, got {type(params).__name__}")
        dosing = DosingParams() if dosing is None else dosing
        if not isinstance(dosing, DosingParams):
            raise TypeError(f"dosing must be a DosingParams, got {type(dosing).__name__}")
        self.p = [float(v) for v in pack(params)]
        self.n = params.n_cells
        self.dosing = dosing
        self.cell_balance, self.rate_constants, self.decomposition_efficiency = casadi_functions()
        self.plant = casadi_namespace()  # the heat balance and dosing of scr_env.physics, on CasADi expressions
        self.heat_capacity = self.p[P["heat_capacity_per_cell_j_k"]]
        self.loss = self.p[P["ambient_loss_per_cell_w_k"]]
        self.ambient = self.p[P["ambient_temperature_k"]]

    # --- the plant's one-source pieces, wired cell by cell as in kernel._plant_step_one ---------------------------
    def inlet(self, u: ca.SX | ca.MX) -> tuple:
        """(q [1/s], y_nh3_in, y_no_in, y_no2_in [-]) at the catalyst face (:func:`scr_env.physics.dosing.
        inlet_conditions`)."""
        d = self.dosing
        return self.plant.inlet_conditions(u[I_FLOW], u[I_TIN], u[I_NOX], u[I_NO2F], u[I_ADBLUE], d.max_rate_g_s,
                                           d.decomposition_t50_k, d.decomposition_width_k,
                                           self.p[P["sites_per_cell_mol"]])[:4]

    def thermal(self, u: ca.SX | ca.MX) -> tuple:
        """(G [W/K], exp(-NTU) [-]): gas-solid coupling per cell and the gas temperature decay across a cell."""
        return self.plant.gas_solid_exchange(u[I_FLOW], self.p[P["gas_solid_ua_per_cell_w_k"]])

    def constants(self, temperature_k: ca.SX | ca.MX, o2: ca.SX | ca.MX) -> tuple:
        return self.rate_constants(temperature_k, o2, *self.p[_KINETIC])

    def chemistry(self, theta: list, temps: list, u: ca.SX | ca.MX) -> tuple[list, list]:
        """Per-cell coverage rates g [1/s] and the outlet (y_no, y_no2, y_nh3, y_n2o) [-] at the given states."""
        q, y_nh3, y_no, y_no2 = self.inlet(u)
        y_n2o = 0.0
        g = []
        for j in range(self.n):
            r = self.cell_balance(theta[j], q, y_nh3, y_no, y_no2, *self.constants(temps[j], u[5]))
            g.append(r[0])
            y_nh3, y_no, y_no2 = r[2], r[3], r[4]
            y_n2o = y_n2o + r[5] / q  # N2O formed per site
        return g, [y_no, y_no2, y_nh3, y_n2o]

    def outputs(self, theta: list, temps: list, u: ca.SX | ca.MX) -> tuple[list, ca.SX | ca.MX]:
        """(g per cell, y) at the given states; y as in the module docstring."""
        g, gas = self.chemistry(theta, temps, u)
        _, decay = self.thermal(u)
        t_gas = u[I_TIN]
        for j in range(self.n):
            t_gas = self.plant.gas_outlet_temperature(temps[j], t_gas, decay)
        return g, ca.vertcat(*[c * 1e6 for c in gas], t_gas)

    def temperature_rates(self, temps: list, u: ca.SX | ca.MX) -> list:
        """dT/dt [K/s] per cell (:func:`scr_env.physics.thermal.cell_temperature_rate`), gas in flow order."""
        coupling, decay = self.thermal(u)
        t_gas = u[I_TIN]
        rates = []
        for j in range(self.n):
            rates.append(self.plant.cell_temperature_rate(temps[j], t_gas, self.heat_capacity, coupling, self.loss,
                                                          self.ambient))
            t_gas = self.plant.gas_outlet_temperature(temps[j], t_gas, decay)
        return rates

    def thermal_implicit_euler(self, temps: list, u: ca.SX | ca.MX, dt: float) -> list:
        """End-of-step cell temperatures [K]: the kernel's closed-form implicit Euler
        (:func:`scr_env.physics.thermal.cell_temperature_step`), cells in flow order."""
        coupling, decay = self.thermal(u)
        t_gas = u[I_TIN]
        new = []
        for j in range(self.n):
            t_new, t_gas = self.plant.cell_temperature_step(temps[j], t_gas, self.heat_capacity, coupling, self.loss,
                                                            self.ambient, dt, decay)
            new.append(t_new)
        return new

    def cell_rootfinder(self) -> ca.Function:
        """theta+ of one cell: root of R = (theta - theta_old) / dt - g(theta) for p = [theta_old, inv_dt, q,
        y_nh3_in, y_no_in, y_no2_in, T, o2].

        Three choices make a plain Newton iteration robust and about as exact as the kernel's bracketed one:

        * outside [0, 1] the rates are frozen at the nearest bound (a continuous extension with the same root,
          since g(0) >= 0 >= g(1)), so Newton never evaluates the chemistry where it is undefined;
        * R is divided by the nitrogen fed to the cell per site (inlet flow and stored at the start of the step, a
          constant of the solve, so the iterates are unchanged), making the absolute tolerance a relative one: a
          stiff, nearly empty cell is solved to its flux, not merely to a coverage step;
        * a solve that stalls at the rounding floor (CasADi's line search then reports failure) returns its last
          iterate instead of raising: in an over-loaded hot cell, adsorption and desorption run at 1e5 times the
          throughput and the floor of R is above any fixed tolerance. The agreement with the kernel over the
          whole envelope is what ``tests/scr_env/test_casadi_model.py`` checks.
        """
        th = ca.SX.sym("theta")
        prm = ca.SX.sym("p", 8)
        th_c = ca.fmin(ca.fmax(th, 0.0), 1.0)
        q = prm[2]
        k = self.constants(prm[6], prm[7])
        r = self.cell_balance(th_c, q, prm[3], prm[4], prm[5], *k)
        scale = q * (prm[3] + prm[4] + prm[5]) + prm[0] * prm[1] + 1e-300
        residual = ((th - prm[0]) * prm[1] - r[0]) / scale
        return ca.rootfinder("scr_cell_implicit", "newton", {"x": th, "p": prm, "g": residual},
                             {"abstol": _NEWTON_ABSTOL, "abstolStep": _NEWTON_STEPTOL, "max_iter": 100,
                              "error_on_fail": False})


def _symbols(n: int, kind: type) -> tuple:
    return kind.sym("x", 2 * n), kind.sym("u", N_INPUTS)


def catalyst_rhs(params: CatalystParams, dosing: DosingParams | None = None) -> ca.Function:
    """Continuous-time catalyst model ``Function('scr_rhs', [x, u], [xdot, y])`` (SX; layouts in the module doc).

    ``xdot[:N]`` is d theta / dt of :func:`scr_env.physics.cell.cell_balance` per cell, each cell fed the previous
    cell's quasi-steady outlet; ``xdot[N:]`` the solid temperature rates [K/s]; ``y`` the outlet at ``x``.
    ``dosing`` sets the urea decomposition curve and the injector limit (default :class:`DosingParams`).
    """
    plant = _Plant(params, dosing)
    x, u = _symbols(plant.n, ca.SX)
    theta = [x[j] for j in range(plant.n)]
    temps = [x[plant.n + j] for j in range(plant.n)]
    g, y = plant.outputs(theta, temps, u)
    xdot = ca.vertcat(*g, *plant.temperature_rates(temps, u))
    return ca.Function("scr_rhs", [x, u], [xdot, y], ["x", "u"], ["xdot", "y"])


def catalyst_step(params: CatalystParams, dt: float, method: Literal["implicit", "rk4"] = "implicit",
                  substeps: int = 1, dosing: DosingParams | None = None) -> ca.Function:
    """One control interval ``Function('scr_step', [x, u], [x_next, y])``, inputs held; ``y`` at the end of the step.

    Parameters
    ----------
    params : the catalyst (its packed, aged numbers are baked in as constants).
    dt : step length [s], > 0.
    method : ``"implicit"`` (default) -- the kernel's integrator, equal to :func:`kernel.plant_step` to the
        rootfinder tolerance when ``substeps == 1`` (an MX function with one scalar Newton rootfinder per cell);
        ``"rk4"`` -- explicit RK4 of :func:`catalyst_rhs` (SX, cheap, but explicit: stiff when hot, see module doc).
    substeps : integrator steps of ``dt / substeps`` per interval.
    dosing : urea decomposition and injector limit (default :class:`DosingParams`).
    """
    try:
        dt = float(dt)
    except (TypeError, ValueError):
        raise ValueError(f"dt must be a positive number, got {dt!r}") from None
    if not dt > 0.0 or dt == float("inf"):
        raise ValueError(f"dt must be a positive finite number [s], got {dt!r}")
    if method not in ("implicit", "rk4"):
        raise ValueError(f"method must be 'implicit' or 'rk4', got {method!r}")
    if isinstance(substeps, bool) or int(substeps) != substeps or substeps < 1:
        raise ValueError(f"substeps must be a positive integer, got {substeps!r}")
    plant = _Plant(params, dosing)
    n, h = plant.n, dt / int(substeps)

    if method == "rk4":
        rhs = catalyst_rhs(params, dosing)
        x, u = _symbols(n, ca.SX)
        xk = x
        for _ in range(int(substeps)):
            k1 = rhs(xk, u)[0]
            k2 = rhs(xk + 0.5 * h * k1, u)[0]
            k3 = rhs(xk + 0.5 * h * k2, u)[0]
            k4 = rhs(xk + h * k3, u)[0]
            xk = xk + h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        y = rhs(xk, u)[1]
        return ca.Function("scr_step", [x, u], [xk, y], ["x", "u"], ["x_next", "y"])

    solve_cell = plant.cell_rootfinder()
    x, u = _symbols(n, ca.MX)
    theta = [x[j] for j in range(n)]
    temps = [x[n + j] for j in range(n)]
    for _ in range(int(substeps)):
        temps = plant.thermal_implicit_euler(temps, u, h)
        q, y_nh3, y_no, y_no2 = plant.inlet(u)
        new = []
        for j in range(n):
            th = solve_cell(theta[j], ca.vertcat(theta[j], 1.0 / h, q, y_nh3, y_no, y_no2, temps[j], u[5]))
            new.append(th)
            # the next cell is fed this cell's outlet at its end-of-step coverage (block-triangular implicit Euler)
            r = plant.cell_balance(th, q, y_nh3, y_no, y_no2, *plant.constants(temps[j], u[5]))
            y_nh3, y_no, y_no2 = r[2], r[3], r[4]
        theta = new
    _, y = plant.outputs(theta, temps, u)
    return ca.Function("scr_step", [x, u], [ca.vertcat(*theta, *temps), y], ["x", "u"], ["x_next", "y"])
