"""A grey-box NH3-storage model identified from open-loop excitation data, for the identified-model MPC.

The linear models of :mod:`ident.linear` fit the SCR poorly (negative simulation fit on a WHTC validation set:
the plant is bilinear in coverage and NOx and Arrhenius in temperature). This is the classic control-oriented SCR
model instead [lit: Upadhyay and Van Nieuwstadt 2006; Schaer et al. 2006], with its parameters *identified* by
simulation-error least squares (CasADi AD Jacobians, scipy ``least_squares``) from the signals of
:mod:`ident.plant_data` data sets only: inputs [inlet NOx ppm, urea g/min, inlet T K, exhaust flow mol/s],
outputs [tailpipe NOx ppm, NH3 ppm, NOx sensor ppm]. It satisfies :class:`ident.base.DynamicModel`
(``predict``, ``to_casadi() -> Function('step', [x, u], [x_next, y])``); it lives in :mod:`ident` with the other
identified models.

Structure (n_cells CSTRs in series sharing one lumped solid temperature; gas quasi-steady):

    T+ = (C T + dt F cp T_in) / (C + dt F cp)                               (thermal inertia, implicit Euler)
    y_NH3,out = (q y_NH3,in + k_des e^(g theta) theta) / (q + k_ads (1 - theta)),   q = F n / Omega
    y_NOx,out = q y_NOx,in / (q + k_scr theta)
    dtheta/dt = k_ads y_NH3,out (1 - theta) - k_des e^(g theta) theta - k_scr theta y_NOx,out - k_ox theta
    theta+ = theta + dt g / max(1 - dt dg/dtheta, 1)                          (linearly implicit Euler: stiff-safe)
    sensor = a NOx + b NH3                                                     (fitted afterwards, linear)

with Arrhenius constants k(T) = A exp(-E / (R T)) and the urea decomposition eta(T_in) = logistic(T_in - t50).
Initial guess: textbook Cu-zeolite magnitudes; 11 parameters (log multipliers and shifts) are identified. The
state is x = [theta_1 .. theta_n, T]; :meth:`StorageGreyBox.initial_state` starts empty at the inlet temperature.

Signals (time-major arrays, one row per sample of ``dt``):

| argument | shape | columns |
|---|---|---|
| ``u`` | (n, 4) | inlet NOx ppm, urea g/min, inlet temperature K, exhaust flow mol/s |
| ``y`` | (n, 3) | tailpipe NOx ppm, tailpipe NH3 ppm, NOx sensor ppm |
| ``predict(u)`` | (n, 3) | as ``y`` |

Input checks (``ValueError`` naming the argument, before any work): the shapes above, equal lengths of ``u`` and
``y``, finite values, at least one sample per record and :data:`MIN_FIT_SAMPLES` in all. A constant input column is
allowed (unlike the linear models' ``ident.linear._statespace.validate_fit_data``: a step test at fixed flow is
legitimate here, and the bounded least squares stays well posed). ``fit`` is atomic: the fitted attributes
(``params_``, ``cost_``, ``sensor_gains_``) are assigned together after the whole identification succeeded, so a
failed refit leaves a fitted model as it was. Before ``fit`` (or :meth:`StorageGreyBox.from_params`),
``predict``/``to_casadi``/... raise :class:`ident.base.NotFittedError`. ``save(path)`` / ``StorageGreyBox.load(path)``
write and read the fitted model in :mod:`ident.io`'s open format (kind ``"storage_greybox"``).
"""
from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np
from scipy.optimize import least_squares

from ident.base import BaseEstimator, as_2d, check_is_fitted, check_same_length
from ident.io import register_model
from scr_env.constants import (
    ATMOSPHERIC_PRESSURE_PA,
    EXHAUST_HEAT_CAPACITY_J_KG_K,
    EXHAUST_MOLAR_MASS_KG_MOL,
    GAS_CONSTANT_J_MOL_K,
    NH3_PER_UREA,
    SECONDS_PER_MINUTE,
    UREA_MOLAR_MASS_KG_MOL,
)

R_GAS = GAS_CONSTANT_J_MOL_K  # J/(mol K)
_CP_MOL = EXHAUST_MOLAR_MASS_KG_MOL * EXHAUST_HEAT_CAPACITY_J_KG_K  # J/(mol K) exhaust
_UREA_G_MOL = UREA_MOLAR_MASS_KG_MOL * 1000.0  # g/mol (60.06)
#: initial guess (textbook magnitudes for a Cu-zeolite brick of a 12 L engine; not the simulator's numbers)
_NOMINAL = {"omega_mol": 8.0, "a_ads": 3.0e4, "a_des": 3.0e8, "e_des": 95e3, "gamma": 0.9, "a_scr": 2.0e8,
            "e_scr": 65e3, "a_ox": 1.0e6, "e_ox": 110e3, "heat_j_k": 5.0e4, "t50_k": 450.0}
N_PARAMS = 11
#: columns of the input and output signals (module docstring)
N_INPUTS, N_OUTPUTS = 4, 3
#: samples a fit needs in all: more than N_PARAMS, so that even the NOx residuals alone outnumber the parameters
MIN_FIT_SAMPLES = N_PARAMS + 1
#: most cells in series: the symbolic model grows with the cell count (a bound, so a damaged file or a typo such as
#: n_cells=1e6 gets a clear error instead of building a graph for hours); the thesis-scale models use 1 to 5
MAX_N_CELLS = 100
_T_MIN_K = 200.0  # lower end of the temperatures the model is evaluated at (guards 1/T; far below any exhaust)


def _numeric(name: str, a: Any) -> np.ndarray:
    """``a`` as a float array, or ValueError naming ``name`` (ragged lists, strings, None)."""
    if a is None:
        raise ValueError(f"{name} must be a numeric array, got None")
    try:
        return np.asarray(a, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric array: {exc}") from None


@register_model("storage_greybox")
class StorageGreyBox(BaseEstimator):
    """Grey-box SCR storage model (module docstring), scikit-learn style.

    Parameters
    ----------
    n_cells : cells in series.
    dt : sample time [s].
    max_nfev : least-squares evaluations.
    nh3_weight : weight of the NH3 residual relative to NOx (both divided by their data SD).

    Fitted attributes: ``params_`` (N_PARAMS), ``cost_``, ``sensor_gains_`` (a, b of sensor = a NOx + b NH3).
    """

    def __init__(self, n_cells: int = 2, dt: float = 0.5, max_nfev: int = 40, nh3_weight: float = 2.0) -> None:
        self.n_cells = n_cells
        self.dt = dt
        self.max_nfev = max_nfev
        self.nh3_weight = nh3_weight

    # --- the model, symbolic in the parameters ------------------------------------------------------------------
    def _kinetics(self, t: ca.SX, u: ca.SX, p: ca.SX) -> tuple:
        """Inlet mole fractions and the gas balance of a cell at solid temperature ``t`` [K] under inputs ``u``:
        ``(y_nh3_in, y_nox_in, gas)`` with ``gas(theta, y_nh3_in, y_nox_in) -> (dtheta/dt, y_nh3_out, y_nox_out)``."""
        nom, n = _NOMINAL, int(self.n_cells)
        omega = nom["omega_mol"] * ca.exp(p[0])
        gamma = nom["gamma"] * ca.exp(p[4])
        e_des = nom["e_des"] * (1 + p[3])
        e_scr = nom["e_scr"] * (1 + p[6])
        t50 = nom["t50_k"] + 10.0 * p[9]
        e_ox = nom["e_ox"] * (1 + p[10])
        nox_ppm, urea_g_min, t_in, flow = u[0], u[1], u[2], ca.fmax(u[3], 1e-3)
        c_tot = ATMOSPHERIC_PRESSURE_PA / (R_GAS * t)
        k_ads = nom["a_ads"] * ca.exp(p[1]) * c_tot
        k_des = nom["a_des"] * ca.exp(p[2]) * ca.exp(-e_des / (R_GAS * t))
        eg = gamma * e_des / (R_GAS * t)
        k_scr = nom["a_scr"] * ca.exp(p[5]) * ca.exp(-e_scr / (R_GAS * t))
        k_ox = nom["a_ox"] * ca.exp(p[7]) * ca.exp(-e_ox / (R_GAS * t))
        eta = 1.0 / (1.0 + ca.exp(-(t_in - t50) / 10.0))
        y_nh3 = eta * ca.fmax(urea_g_min, 0) / SECONDS_PER_MINUTE / _UREA_G_MOL * NH3_PER_UREA / flow
        y_nox = ca.fmax(nox_ppm, 0) * 1e-6
        q = flow * n / omega

        def gas(theta, y_nh3_in, y_nox_in):
            r_des = k_des * ca.exp(eg * theta) * theta
            yn = (q * y_nh3_in + r_des) / (q + k_ads * (1 - theta))
            yx = q * y_nox_in / (q + k_scr * theta)
            g = k_ads * yn * (1 - theta) - r_des - k_scr * theta * yx - k_ox * theta
            return g, yn, yx

        return y_nh3, y_nox, gas

    def _temperature(self, t_old: ca.SX, u: ca.SX, p: ca.SX, dt: float) -> ca.SX:
        """Solid temperature after ``dt`` [s] (implicit Euler of the linear heat balance, exact form)."""
        heat = _NOMINAL["heat_j_k"] * ca.exp(p[8])
        flow = ca.fmax(u[3], 1e-3)
        return (heat * t_old + dt * flow * _CP_MOL * ca.fmax(u[2], _T_MIN_K)) / (heat + dt * flow * _CP_MOL)

    def _step_expr(self, x: ca.SX, u: ca.SX, p: ca.SX) -> tuple[ca.SX, ca.SX]:
        n, dt = int(self.n_cells), float(self.dt)
        # the state enters clipped to its physical range: identical on it (identification never leaves it), but an
        # NLP iterate outside the box (an SQP step from an unsolved QP) must not reach the pole of the gas balance
        # at theta > 1 or 1 / T at T <= 0, whose NaN derivatives stop the solver ("NaN detected for grad_f_x")
        t = self._temperature(ca.fmax(x[n], _T_MIN_K), u, p, dt)
        y_nh3, y_nox, gas = self._kinetics(t, u, p)
        th = ca.SX.sym("th")
        xs = []
        for j in range(n):
            g_th = gas(th, y_nh3, y_nox)[0]
            th0 = ca.fmin(ca.fmax(x[j], 0.0), 1.0)
            dg = ca.substitute(ca.jacobian(g_th, th), th, th0)
            g0 = gas(th0, y_nh3, y_nox)[0]
            th_new = ca.fmin(ca.fmax(th0 + dt * g0 / ca.fmax(1 - dt * dg, 1.0), 0.0), 1.0)
            xs.append(th_new)
            _, y_nh3, y_nox = gas(th_new, y_nh3, y_nox)
        return ca.vertcat(*xs, t), ca.vertcat(y_nox * 1e6, y_nh3 * 1e6)

    def step_expression(self, x: ca.SX, u: ca.SX, p: ca.SX) -> tuple[ca.SX, ca.SX]:
        """The explicit step over ``dt`` (the one :meth:`to_casadi` exports) as CasADi expressions of the state
        ``x`` (n_cells + 1), the inputs ``u`` (4) and the parameters ``p`` (N_PARAMS, symbolic or numeric):
        ``(x_next, y)`` with y = [tailpipe NOx ppm, NH3 ppm]. Needs no fit: for models whose parameters are
        re-estimated online (:mod:`control.adaptive`)."""
        self._check_settings()
        return self._step_expr(x, u, p)

    def implicit_stage(self, x_next: ca.SX, x: ca.SX, u: ca.SX, h: float) -> tuple[ca.SX, ca.SX]:
        """The model over a stage of ``h`` seconds (input held) as smooth implicit-Euler equations, for an NLP whose
        variables include the end state ``x_next``: ``(residual, y)``, residual zero when ``x_next`` is the
        implicit-Euler end state of ``x`` (coverage rows in coverage units, the temperature row in units of
        100 K), y = [tailpipe NOx ppm, NH3 ppm] at the end of the stage.

        Unlike :meth:`to_casadi`'s explicit step (a linearly implicit Euler step clipped to [0, 1]), these
        equations have no kinks: the NLP's bounds keep the coverage in [0, 1], and an SQP method converges on them
        where the clipped step's zero gradients make it stall."""
        check_is_fitted(self, "params_")
        n, p = int(self.n_cells), ca.DM(self.params_)
        t_next = x_next[n]
        res_t = (t_next - self._temperature(x[n], u, p, float(h))) / 100.0
        y_nh3, y_nox, gas = self._kinetics(t_next, u, p)
        res = []
        for j in range(n):
            g, y_nh3, y_nox = gas(x_next[j], y_nh3, y_nox)
            res.append(x_next[j] - x[j] - h * g)
        return ca.vertcat(*res, res_t), ca.vertcat(y_nox * 1e6, y_nh3 * 1e6)

    def _step_function(self) -> ca.Function:
        """``Function('step_p', [x, u, p], [x_next, y])`` (y = tailpipe NOx, NH3 ppm), symbolic in the parameters."""
        n = int(self.n_cells)
        x, u, p = ca.SX.sym("x", n + 1), ca.SX.sym("u", 4), ca.SX.sym("p", N_PARAMS)
        xn, y = self._step_expr(x, u, p)
        return ca.Function("step_p", [x, u, p], [xn, y])

    def _functions(self) -> None:
        self._fp = self._step_function()

    def _check_settings(self) -> None:
        n, dt = self.n_cells, self.dt
        try:
            ok = not isinstance(n, bool) and int(n) == n and 1 <= n <= MAX_N_CELLS
        except (TypeError, ValueError, OverflowError):
            ok = False
        if not ok:
            raise ValueError(f"n_cells must be an integer from 1 to {MAX_N_CELLS} (cells in series), got {n!r}")
        try:
            ok = not isinstance(dt, bool) and np.isfinite(float(dt)) and float(dt) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"dt must be a positive number of seconds, got {dt!r}")

    @staticmethod
    def _check_records(u: Any, y: Any) -> list[tuple[np.ndarray, np.ndarray]]:
        """The (u, y) records of :meth:`fit`, validated (module docstring): float arrays (n, 4), (n, 3)."""
        if y is None:
            if isinstance(u, np.ndarray) or not isinstance(u, (list, tuple)):
                raise ValueError("y is required: fit(u, y) with u (n, 4) and y (n, 3), or fit(records) with a list "
                                 "of (u, y) records")
            raw = list(u)
            if not raw:
                raise ValueError("records is empty: fit needs at least one (u, y) record")
        else:
            raw = [(u, y)]
        records = []
        for i, rec in enumerate(raw):
            tag = "" if y is not None else f" of record {i}"
            if y is None and (not isinstance(rec, (list, tuple)) or len(rec) != 2):
                raise ValueError(f"records[{i}] must be a (u, y) pair, got {type(rec).__name__}")
            ur = as_2d(f"u{tag}", _numeric(f"u{tag}", rec[0]), n_columns=N_INPUTS)
            yr = as_2d(f"y{tag}", _numeric(f"y{tag}", rec[1]), n_columns=N_OUTPUTS)
            check_same_length(**{f"u{tag}": ur, f"y{tag}": yr})
            records.append((ur, yr))
        total = sum(r[0].shape[0] for r in records)
        if total < MIN_FIT_SAMPLES:
            raise ValueError(f"too few samples to identify {N_PARAMS} parameters: {total} in all, at least "
                             f"{MIN_FIT_SAMPLES} are needed")
        return records

    # --- fitting ------------------------------------------------------------------------------------------------
    def fit(self, u: np.ndarray | list, y: np.ndarray | None = None) -> StorageGreyBox:
        """Identify from inputs ``u`` (n, 4) and outputs ``y`` (n, 3) (the :mod:`ident.plant_data` signals, module
        docstring); a list of (u, y) records may be given as ``u`` with ``y=None``.

        The data are checked first (``ValueError`` naming the argument: shape, columns, lengths, NaN/inf, too few
        samples); the fitted attributes are set only when the whole identification succeeded."""
        self._check_settings()
        records = self._check_records(u, y)
        fp = self._step_function()
        n = int(self.n_cells)
        p = ca.SX.sym("p", N_PARAMS)
        res = []
        for ur, yr in records:
            sim = fp.mapaccum("sim", ur.shape[0], [0], [0])
            x0 = np.r_[np.zeros(n), ur[0, 2]]
            _, ys = sim(x0, ur.T, ca.repmat(p, 1, ur.shape[0]))
            s_nox = max(float(np.std(yr[:, 0])), 1.0)
            s_nh3 = max(float(np.std(yr[:, 1])), 1.0)
            res.append(ca.vec((ys[0, :].T - yr[:, 0]) / s_nox))
            res.append(self.nh3_weight * ca.vec((ys[1, :].T - yr[:, 1]) / s_nh3))
        r = ca.vertcat(*res)
        fr = ca.Function("r", [p], [r])
        fj = ca.Function("j", [p], [ca.jacobian(r, p)])
        sol = least_squares(lambda v: np.asarray(fr(v)).ravel(), np.zeros(N_PARAMS),
                            jac=lambda v: np.asarray(fj(v)), bounds=(-5.0 * np.ones(N_PARAMS), 5.0 * np.ones(N_PARAMS)),
                            max_nfev=self.max_nfev, x_scale=1.0)
        params = sol.x
        # sensor = a NOx + b NH3, linear least squares on the simulated outputs
        A, b = [], []
        for ur, yr in records:
            ys = self._simulate(fp, params, ur)
            A.append(ys[:, :2])
            b.append(yr[:, 2])
        sensor_gains = np.linalg.lstsq(np.vstack(A), np.concatenate(b), rcond=None)[0]
        if not (np.all(np.isfinite(params)) and np.all(np.isfinite(sensor_gains))):
            raise FloatingPointError("the identification gave non-finite parameters; the model is left unchanged")
        self._fp, self.params_, self.cost_, self.sensor_gains_ = fp, params, float(sol.cost), sensor_gains
        return self

    @property
    def storage_capacity_mol(self) -> float:
        """Identified NH3 storage capacity of the brick [mol]."""
        check_is_fitted(self, "params_")
        return float(_NOMINAL["omega_mol"] * np.exp(self.params_[0]))

    @classmethod
    def from_params(cls, params: np.ndarray, sensor_gains: np.ndarray, n_cells: int = 2,
                    dt: float = 0.5) -> StorageGreyBox:
        """A fitted model from identified numbers (``params_``, ``sensor_gains_``), e.g. read back from JSON."""
        m = cls(n_cells=n_cells, dt=dt)
        m._check_settings()
        params = np.asarray(params, dtype=np.float64)
        sensor_gains = np.asarray(sensor_gains, dtype=np.float64)
        if params.shape != (N_PARAMS,) or not np.all(np.isfinite(params)):
            raise ValueError(f"params must be {N_PARAMS} finite numbers, got shape {params.shape}: {params.tolist()}")
        if sensor_gains.shape != (2,) or not np.all(np.isfinite(sensor_gains)):
            raise ValueError(f"sensor_gains must be 2 finite numbers (a, b of sensor = a NOx + b NH3), got shape "
                             f"{sensor_gains.shape}: {sensor_gains.tolist()}")
        m._functions()
        m.params_ = params
        m.sensor_gains_ = sensor_gains
        return m

    # --- saving (ident.io: JSON + NPZ, no pickle) -----------------------------------------------------------------
    def _get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
        check_is_fitted(self, "params_")
        meta = {"n_cells": int(self.n_cells), "dt": float(self.dt), "max_nfev": int(self.max_nfev),
                "nh3_weight": float(self.nh3_weight)}
        if hasattr(self, "cost_"):
            meta["cost"] = float(self.cost_)
        return meta, {"params": self.params_, "sensor_gains": self.sensor_gains_}

    @classmethod
    def _from_state(cls, meta: dict, arrays: dict[str, np.ndarray]) -> StorageGreyBox:
        m = cls.from_params(arrays["params"], arrays["sensor_gains"], n_cells=meta["n_cells"], dt=meta["dt"])
        m.max_nfev, m.nh3_weight = int(meta.get("max_nfev", m.max_nfev)), float(meta.get("nh3_weight", m.nh3_weight))
        if "cost" in meta:
            m.cost_ = float(meta["cost"])
        return m

    def desorption_ppm(self, theta: ca.SX, t_k: ca.SX, flow_mol_s: float) -> ca.SX:
        """NH3 [ppm] that a cell at coverage ``theta`` and solid temperature ``t_k`` desorbs into NH3- and NOx-free
        gas at ``flow_mol_s`` (the identified model's gas balance with no inlet NH3; symbolic or numeric)."""
        check_is_fitted(self, "params_")
        nom, p, n = _NOMINAL, self.params_, int(self.n_cells)
        # clipped to the physical range, as in the step: NLP iterates outside the box must not reach the pole of
        # the gas balance at theta > 1 or 1 / T at T <= 0 (NaN gradients of the terminal cost)
        theta = ca.fmin(ca.fmax(theta, 0.0), 1.0)
        t_k = ca.fmax(t_k, _T_MIN_K)
        omega = nom["omega_mol"] * np.exp(p[0])
        e_des = nom["e_des"] * (1 + p[3])
        eg = nom["gamma"] * np.exp(p[4]) * e_des / (R_GAS * t_k)
        k_ads = nom["a_ads"] * np.exp(p[1]) * ATMOSPHERIC_PRESSURE_PA / (R_GAS * t_k)
        k_des = nom["a_des"] * np.exp(p[2]) * ca.exp(-e_des / (R_GAS * t_k))
        q = max(float(flow_mol_s), 1e-3) * n / omega
        return 1e6 * k_des * ca.exp(eg * theta) * theta / (q + k_ads * (1 - theta))

    # --- the DynamicModel protocol -----------------------------------------------------------------------------
    def to_casadi(self) -> ca.Function:
        """``Function('step', [x, u], [x_next, y])``, y = [tailpipe NOx ppm, NH3 ppm, sensor ppm] (physical units)."""
        check_is_fitted(self, "params_")
        n = int(self.n_cells)
        x, u = ca.SX.sym("x", n + 1), ca.SX.sym("u", 4)
        xn, y = self._step_expr(x, u, ca.DM(self.params_))
        a, b = self.sensor_gains_
        return ca.Function("step", [x, u], [xn, ca.vertcat(y, a * y[0] + b * y[1])], ["x", "u"], ["x_next", "y"])

    def initial_state(self, u: np.ndarray, y: np.ndarray | None = None) -> np.ndarray:
        """Empty storage at the first inlet temperature of ``u`` ((n, 4) or one row of 4 inputs)."""
        u = _numeric("u", u)
        u = as_2d("u", u[None, :] if u.ndim == 1 else u, n_columns=N_INPUTS)
        return np.r_[np.zeros(int(self.n_cells)), float(u[0, 2])]

    @staticmethod
    def _simulate(fp: ca.Function, params: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Free run (n, 2) of the step ``fp`` with ``params`` from the empty storage at the first inlet temperature."""
        n = fp.size1_in(0) - 1
        f = fp.mapaccum("sim", u.shape[0], [0], [0])
        _, ys = f(np.r_[np.zeros(n), float(u[0, 2])], u.T, np.tile(params[:, None], (1, u.shape[0])))
        return np.asarray(ys).T

    def predict(self, u: np.ndarray, y0: np.ndarray | None = None) -> np.ndarray:
        """Free-run simulation (n, 3) [tailpipe NOx ppm, NH3 ppm, sensor ppm] from :meth:`initial_state` for inputs
        ``u`` (n, 4) (module docstring); ``y0`` is not used (the initial state comes from ``u``).

        ``NotFittedError`` before :meth:`fit`; ``ValueError`` naming ``u`` for a wrong shape or NaN/inf."""
        check_is_fitted(self, "params_")
        u = _numeric("u", u)
        if u.ndim != 2:
            raise ValueError(f"u must be a (n_samples, {N_INPUTS}) array [inlet NOx ppm, urea g/min, inlet temperature "
                             f"K, exhaust flow mol/s], got shape {np.shape(u)}")
        u = as_2d("u", u, n_columns=N_INPUTS)
        if not hasattr(self, "_fp"):
            self._functions()
        ys = self._simulate(self._fp, self.params_, u)
        return np.column_stack([ys, ys @ self.sensor_gains_])
