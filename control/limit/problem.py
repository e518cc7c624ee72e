"""The clairvoyant whole-cycle optimum as an optimal-control problem (:class:`CycleOptimum`).

The dosing that minimises the tailpipe NOx [g/kWh] over a whole drive cycle at a given mean NH3-slip budget [ppm],
knowing the plant and the whole cycle in advance. No causal controller can do better on that plant, so it is the
100 % mark of a normalised score (:func:`gap_to_limit`) and, over several budgets, the NOx-against-slip Pareto
front of the task. The stored front of the hot WHTC and WHSC is read with :func:`stored_limit`.

    from control.limit import CycleOptimum, replay, stored_limit
    problem = CycleOptimum("whtc")                 # the hot WHTC at dt = 0.5 s, as the benchmark runs it
    best = problem.solve(10.0)                     # mean slip <= 10 ppm
    best.tailpipe_nox_g_per_kwh, best.dose_g_s     # the optimum and its dose trajectory [g/s]
    replay("whtc", best.dose_g_s)                  # the environment's KPIs of that dose, open loop
    stored_limit("whtc", 10).replay_tailpipe_nox_g_per_kwh   # the stored figure (never re-solved)

The optimal-control problem (:class:`CycleOptimum`)
    * The plant is the environment's. The cycle, the initial state, the engine work and the KPI weights come from a
      :class:`~scr_env.envs.urea_scr.UreaSCREnv` episode (``reset``, ``disturbance_preview``) and from the
      environment's own KPI accounting (:func:`scr_env.envs.kpis.account_batch`, run on unit tailpipe
      concentrations: the KPIs are linear in them, so this gives the exact weights of its sums). The solid
      temperatures do not depend on the dose (the heat balance has no heat of reaction), so they are taken from one
      zero-dose episode and fixed. The chemistry is the plant's CasADi twin, :class:`scr_env.casadi_model._Plant`
      (the one-source :func:`scr_env.physics.cell.cell_balance`, cells in series in flow order).
    * Decision variables: the AdBlue rate of every control step in [0, the injector limit] g/s (held for
      ``hold_steps`` plant steps; 1 by default) and the NH3 coverage of every cell after every step.
    * Constraints: the kernel's implicit-Euler step of the coverage, ``theta_k+1 - theta_k - dt g(theta_k+1,
      T_k+1, u_k) = 0`` per cell, as equality constraints on the plant's own grid (multiple shooting, one interval
      per control step); the mean-slip budget ``sum_k nh3_k dt / (N dt) <= budget`` (the environment's
      ``mean_nh3_slip_ppm``); optionally the peak, ``nh3_k <= peak`` at every step (``peak_ppm``).
    * Objective: the environment's ``tailpipe_nox_g_per_kwh``, the sum of its accumulator (tailpipe NO + NO2 at the
      end of each step [ppm] x 1e-6 x exhaust flow x M_NO2 x dt) over the positive engine work.
    * Solver: IPOPT with MUMPS (the linear solver the pip ``casadi`` ships) on the sparse NLP, with the NLP's
      functions compiled to C when a C compiler is available (``jit``), else in CasADi's virtual machine (several
      times slower).

Why a warm start in two stages (measured on the hot WHSC and a 600 s segment of the hot WHTC, under load, on the
plant before its NO2 chemistry; on the new plant every budget of both cycles converges, docs/pending/limit.md)
    IPOPT on the multiple-shooting NLP converges slowly from the look-up table's trajectory: 616 iterations on the
    WHTC, more than 1000 on the WHSC, with its inertia correction active most of the time (the problem is not
    convex: the dose enters bilinearly with the coverage, and the coverage of hot downstream cells sits a few 1e-7
    above its bound). So the warm start is made in the reduced space first: the dose alone, the states simulated
    exactly by the plant's kernel, the gradients of the NOx and slip sums by the adjoint of the twin's implicit step
    (:func:`_adjoint`), and IPOPT with a limited-memory quasi-Newton Hessian on that small problem (one variable per
    dose and one constraint). Its dose, states and multipliers (the adjoint states are the multipliers of the
    implicit-step constraints) then start the multiple-shooting NLP with a small barrier parameter, which
    certifies the optimum to IPOPT's tolerance (``polish``). Further budgets start from a solved neighbour.

    Also tried and not kept: the twin's inlet with the injector clamp ``min(max(u, 0), u_max)`` (its kink sits at
    the bounds where the optimal dose lives; IPOPT did not converge; the NLP uses the twin's inlet per g/s times the
    dose, :func:`_dose_linear_twin`, the plant inside the bounds the NLP enforces), the objective unscaled (kept:
    x :data:`OBJECTIVE_SCALE`), scaling the coverages per cell, row scaling by the stiffness, lifting the cell-to-
    cell gas concentrations, log coverages, a smooth clamp of the coverage at 0 without bounds, IPOPT's adaptive
    barrier, its inertia-free curvature test and CasADi's Hessian convexification (all slower or failing). The
    problem has local optima a few tenths of a per cent apart; :func:`pareto_front` keeps the front monotone.

Results are checked by replaying the optimal dose open loop through the environment (:func:`replay`, no sensor
noise: the sensors do not act on the plant); the replayed KPIs are what a controller is compared with.
"""
from __future__ import annotations

import itertools
import os
import shutil
import tempfile
import time
import warnings
import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from control.limit.common import (
    DEFAULT_BUDGETS_PPM,
    REFERENCE_BUDGET_PPM,
    LimitResult,
    _count,
    _plant_kwargs,
    _positive,
    make_env,
    replay,
)
from scr_env.cycles import ExhaustTrace
from scr_env.jit import njit

#: dual-infeasibility test stalled on the small per-step gradients]
OBJECTIVE_SCALE = 100.0
#: measured on the WHSC (module docstring)]
REDUCED_ITERATIONS = (600, 300)
#: the virtual machine loses on a 1000-step problem]
JIT_MIN_STEPS = 1000


def _lookup_table_dose(env: Any, seed: int = 0) -> np.ndarray:
    """The look-up table's dose trajectory [g/s] in ``env`` (reset with ``seed`` and run to the end)."""
    from control.baselines import LookupTableDosing

    obs, _ = env.reset(seed=seed)
    lut = LookupTableDosing(max_rate_g_s=env.max_rate_g_s)
    lut.attach(env)
    dose = np.empty(env.trace.n_steps)
    act = np.zeros(1)
    for k in range(dose.size):
        act[0] = dose[k] = lut.dose_g_s(obs)
        obs, *_ = env.step(act)
    return dose


def _kpi_weights(env: Any, drive: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(g/kWh of tailpipe NOx per ppm at each step, ppm of mean slip per ppm at each step, engine work [kWh]):
    the environment's own KPI accounting (:func:`scr_env.envs.kpis.account_batch`) run on 1 ppm of tailpipe NO and
    of NH3 at every step. ``drive``: the environment's drive table (flow, inlet T, NOx, NO2 share, power, O2)."""
    from scr_env.envs import kpis
    from scr_env.physics import kernel as K

    n = drive.shape[0]
    inputs = np.zeros((n, len(K.INPUT_FIELDS)))
    inputs[:, K.I_FLOW], inputs[:, K.I_TIN], inputs[:, K.I_NOX] = drive[:, 0], drive[:, 1], drive[:, 2]
    inputs[:, K.I_NO2F], inputs[:, K.I_O2] = drive[:, 3], drive[:, 5]
    power = np.ascontiguousarray(drive[:, 4])
    per = {}
    for name, col in (("nox", K.O_NO), ("nh3", K.O_NH3)):
        out = np.zeros((n, len(K.OUTPUT_FIELDS)))
        out[:, col] = 1.0
        acc = np.zeros((n, kpis.N_ACC))
        kpis.account_batch(inputs, power, env.dt, out, np.zeros((n, 3)), np.zeros((n, 3)), np.zeros(n), acc)
        per[name] = acc
    work = float(per["nox"][:, kpis.A_WORK_KWH].sum())
    time_s = float(per["nh3"][:, kpis.A_TIME_S].sum())
    return per["nox"][:, kpis.A_TAILPIPE_NOX_G] / work, per["nh3"][:, kpis.A_NH3_PPM_S] / time_s, work


# ------------------------------------------------------------------------------------------------------ the twin
def _dose_linear_twin(catalyst: Any, dosing: Any, packed: np.ndarray | None = None) -> Any:
    """:class:`scr_env.casadi_model._Plant` whose inlet is linear in the dose: the twin's own inlet at 1 g/s, times
    the dose. Inside [0, injector limit] that is the plant's inlet exactly; it drops the clamp whose kink at the
    bounds stalls IPOPT (module docstring). ``packed``: the packed parameters of the episode's catalyst (the
    environment's ``catalyst_params_array``: after ageing and randomisation), which replace those of
    ``catalyst``."""
    import casadi as ca

    from scr_env.casadi_model import _Plant

    class _DoseLinearTwin(_Plant):
        def inlet(self, u: Any) -> tuple:
            q, y_nh3_per_g_s, y_no, y_no2 = super().inlet(ca.vertcat(u[0], u[1], u[2], u[3], 1.0, u[5]))
            return q, y_nh3_per_g_s * u[4], y_no, y_no2

    twin = _DoseLinearTwin(catalyst, dosing)
    if packed is not None:
        if len(packed) != len(twin.p):
            raise ValueError(f"packed catalyst parameters: {len(packed)} values, the twin has {len(twin.p)}")
        twin.p = [float(v) for v in packed]
    return twin


def _compiler() -> str | None:
    """A C compiler for CasADi's generated code, or None."""
    for cc in (os.environ.get("CC"), "gcc", "cc", "clang"):
        if cc and shutil.which(cc):
            return cc
    return None


@njit(nogil=True, error_model="numpy")
def _adjoint(a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of sums of stage functions through the implicit step, by the adjoint recursion.

    With ``R_k(theta_k+1, theta_k, u_k) = theta_k+1 - theta_k - dt g = 0`` and sums ``sum_k h_k(theta_k+1, u_k)``:
    ``a`` (N, n, n) dR_k/dtheta_k+1 (lower triangular: cells in flow order), ``b`` (N, n) dR_k/du_k, ``c`` (N, m, n)
    dh_k/dtheta_k+1 and ``d`` (N, m) dh_k/du_k for m sums. Returns the gradients with respect to every u_k (N, m)
    and the adjoint states lambda_k (N, m, n), the multipliers of R_k = 0 (Lagrangian sum h + lambda^T R), from
    ``lambda_k^T a_k = lambda_k+1^T - c_k`` backwards (dR_k+1/dtheta_k+1 = -I).
    """
    n_steps, n = b.shape
    m = c.shape[1]
    grad = np.empty((n_steps, m))
    lam = np.zeros((n_steps, m, n))
    nxt = np.zeros((m, n))
    x = np.zeros(n)
    for k in range(n_steps - 1, -1, -1):
        for i in range(m):
            for j in range(n - 1, -1, -1):  # a_k^T is upper triangular: back substitution
                s = nxt[i, j] - c[k, i, j]
                for r in range(j + 1, n):
                    s -= a[k, r, j] * x[r]
                x[j] = s / a[k, j, j]
            g = d[k, i]
            for j in range(n):
                lam[k, i, j] = x[j]
                nxt[i, j] = x[j]
                g += x[j] * b[k, j]
            grad[k, i] = g
    return grad, lam


# ----------------------------------------------------------------------------------------------------- the NLP
class CycleOptimum:
    """The whole-cycle optimal-control problem of one cycle (module docstring): built once, solved at any budget.

    Parameters
    ----------
    cycle : ``"whtc"``, ``"whsc"``, a CSV path or an :class:`~scr_env.cycles.ExhaustTrace` (the environment's
        ``cycle``); the environment's hot start unless ``env_kwargs`` says otherwise.
    env_kwargs : plant arguments of the environment (:data:`PLANT_ARGUMENTS`: ``catalyst``, ``dt`` (0.5 s),
        ``ageing``, ``age_h``, ``randomize``, ``dosing``, ``cold_start``, ``initial_coverage``).
    seed : the reset seed of the episode whose plant is optimised (matters with ``randomize`` or an ``age_h``
        range, which draw the episode's catalyst at reset); the replay uses it too.
    hold_steps : plant steps over which each dose is held (1: a dose per control step).
    peak_ppm : also bound the tailpipe NH3 of every step [ppm] (None: the mean slip only). With a peak bound the
        reduced-space warm start is skipped (it handles one constraint); IPOPT starts from the look-up table.
    jit : compile the NLP's functions to C (None: if a C compiler is found and the cycle has at least
        :data:`JIT_MIN_STEPS` steps; False: CasADi's virtual machine).
    max_iter, tol : IPOPT's iteration limit and tolerance of the multiple-shooting NLP.
    reduced_iterations : IPOPT iterations of the reduced-space warm start (from the look-up table, from a
        neighbouring budget); 0 skips it.
    print_level : IPOPT's output (0 quiet, 5 an iteration log).
    ipopt_options : further IPOPT options of the multiple-shooting NLP (without the ``ipopt.`` prefix).
    """

    def __init__(self, cycle: str | os.PathLike | ExhaustTrace = "whtc", *,
                 env_kwargs: Mapping[str, Any] | None = None, hold_steps: int = 1, peak_ppm: float | None = None,
                 jit: bool | None = None, max_iter: int = 3000, tol: float = 1e-8,
                 reduced_iterations: tuple[int, int] = REDUCED_ITERATIONS, print_level: int = 0,
                 ipopt_options: Mapping[str, Any] | None = None, seed: int = 0) -> None:
        from scr_env.envs import core
        from scr_env.envs.config import O2_FRACTION
        from scr_env.physics import kernel as K

        self.hold_steps = _count("hold_steps", hold_steps)
        self.peak_ppm = None if peak_ppm is None else _positive("peak_ppm", peak_ppm)
        self.max_iter = _count("max_iter", max_iter)
        self.tol = _positive("tol", tol)
        if not isinstance(reduced_iterations, (tuple, list)) or len(reduced_iterations) != 2:
            raise ValueError(f"reduced_iterations must be a pair of iteration counts, got {reduced_iterations!r}")
        self.reduced_iterations = tuple(_count("reduced_iterations", v, 0) for v in reduced_iterations)
        self.print_level = _count("print_level", print_level, 0)
        self.ipopt_options = dict(ipopt_options or {})
        self.env_kwargs = _plant_kwargs(env_kwargs)
        self.cycle = cycle
        self.seed = _count("seed", seed, 0)
        self._env = env = make_env(cycle, self.env_kwargs)
        env.reset(seed=self.seed)
        self.trace: ExhaustTrace = env.trace
        self.name = str(env.trace.name)
        self.dt = float(env.dt)
        self.n_steps = n = int(env.trace.n_steps)
        self.n_cells = int(env.config.catalyst.n_cells)
        self.max_rate_g_s = float(env.max_rate_g_s)
        self.initial_coverage = env.state["nh3_coverage"].copy()
        self.initial_temperature_k = env.state["temperature_k"].copy()
        self.drive_table = core.drive_table(env.trace, O2_FRACTION)  # the environment's: flow, T, NOx, NO2, P, O2
        self.drive = env.disturbance_preview(n)
        # the solid temperatures after every step do not depend on the dose: one zero-dose episode
        temps = np.empty((n, self.n_cells))
        zero = np.zeros(1)
        for k in range(n):
            env.step(zero)
            temps[k] = env.state["temperature_k"]
        self.temperature_k = temps
        self.nox_weight, self.slip_weight, self.engine_work_kwh = _kpi_weights(env, self.drive_table)
        if not (self.engine_work_kwh > 0 and np.all(np.isfinite(self.nox_weight))):
            raise ValueError(f"cycle {self.name!r} has no positive engine work: tailpipe NOx in g/kWh is undefined")
        # the plant kernel's arrays for the exact simulations of the reduced-space warm start
        self._kernel_inputs = np.zeros((n, len(K.INPUT_FIELDS)))
        for col, src in ((K.I_FLOW, 0), (K.I_TIN, 1), (K.I_NOX, 2), (K.I_NO2F, 3), (K.I_O2, 5)):
            self._kernel_inputs[:, col] = self.drive_table[:, src]
        self._cat = np.ascontiguousarray(env.catalyst_params_array[None, :])
        self._aux = np.ascontiguousarray(K.pack_aux(env.config.dosing, env.config.sensors)[None, :])
        self.jit = (_compiler() is not None and n >= JIT_MIN_STEPS) if jit is None else bool(jit)
        self._functions: dict[str, Any] = {}
        self._lut_dose: np.ndarray | None = None
        self._cache: dict[str, Any] = {}
        self._build()

    # --- construction ----------------------------------------------------------------------------------------
    def _build(self) -> None:
        import casadi as ca

        from scr_env.envs.config import O2_FRACTION

        n, N, h = self.n_cells, self.n_steps, self.hold_steps
        twin = _dose_linear_twin(self._env.config.effective_catalyst, self._env.config.dosing, self._cat[0])
        tho, thn = ca.SX.sym("theta", n), ca.SX.sym("theta_next", n)
        u, temps, d = ca.SX.sym("adblue_g_s"), ca.SX.sym("temperature_k", n), ca.SX.sym("drive", 4)
        g, y = twin.outputs([thn[j] for j in range(n)], [temps[j] for j in range(n)],
                            ca.vertcat(d[0], d[1], d[2], d[3], u, O2_FRACTION))
        # the kernel's implicit Euler step of each cell's coverage, at the end-of-step temperatures
        residual = ca.vertcat(*[thn[j] - tho[j] - self.dt * g[j] for j in range(n)])
        out = ca.vertcat(y[0] + y[1], y[2])  # tailpipe NOx and NH3 [ppm] at the end of the step
        stage = ca.Function("limit_stage", [tho, thn, u, temps, d], [residual, out[0], out[1]])
        self._stage_jacobian = ca.Function(
            "limit_stage_jac", [tho, thn, u, temps, d],
            [ca.jacobian(residual, thn), ca.jacobian(residual, u), ca.jacobian(out, thn), ca.jacobian(out, u)]
        ).map(N, "serial")
        self.n_doses = m = -(-N // h)
        X, U = ca.MX.sym("X", n, N), ca.MX.sym("U", m)
        theta0, T, D = ca.MX.sym("theta0", n), ca.MX.sym("T", n, N), ca.MX.sym("D", 4, N)
        Wn, Ws = ca.MX.sym("Wnox", N), ca.MX.sym("Wslip", N)
        u_steps = U[[k // h for k in range(N)]] if h > 1 else U
        R, nox, nh3 = stage.map(N, "serial")(ca.horzcat(theta0, X[:, :N - 1]), X, u_steps.T, T, D)
        cons = [ca.vec(R), ca.mtimes(nh3, Ws)]
        if self.peak_ppm is not None:
            cons.append(nh3.T)
        w, p = ca.vertcat(ca.vec(X), U), ca.vertcat(theta0, ca.vec(T), ca.vec(D), Wn, Ws)
        self._nlp = {"x": w, "p": p, "f": OBJECTIVE_SCALE * ca.mtimes(nox, Wn), "g": ca.vertcat(*cons)}
        self._outputs = ca.Function("limit_outputs", [w, p], [nox.T, nh3.T, u_steps])
        self._p = np.concatenate([self.initial_coverage, self.temperature_k.ravel(), self.drive.ravel(),
                                  self.nox_weight, self.slip_weight])
        self._nx, self._ng = int(w.numel()), int(self._nlp["g"].numel())
        self._lbx = np.r_[np.zeros(n * N), np.zeros(m)]
        self._ubx = np.r_[np.ones(n * N), np.full(m, self.max_rate_g_s)]

    def _options(self, warm: bool) -> dict[str, Any]:
        opts: dict[str, Any] = {"print_time": False, "ipopt.print_level": self.print_level, "ipopt.sb": "yes",
                                "ipopt.tol": self.tol, "ipopt.max_iter": self.max_iter, "ipopt.linear_solver": "mumps",
                                "ipopt.print_frequency_iter": 25}
        if warm:  # a primal-dual start near the optimum: a small barrier and tiny pushes keep IPOPT near it
            opts.update({"ipopt.warm_start_init_point": "yes", "ipopt.mu_init": 1e-6,
                         "ipopt.warm_start_bound_push": 1e-9, "ipopt.warm_start_mult_bound_push": 1e-9,
                         "ipopt.warm_start_slack_bound_push": 1e-9})
        opts.update({f"ipopt.{k}": v for k, v in self.ipopt_options.items()})
        return opts

    def _solver(self, warm: bool) -> Any:
        """IPOPT on the multiple-shooting NLP (``warm``: the warm-start options). With ``jit`` its functions are
        generated as C and compiled once; both solvers load that library."""
        import casadi as ca

        key = "warm" if warm else "cold"
        if key not in self._functions:
            if self.jit and "compiled" not in self._functions:
                self._functions["compiled"] = self._compile()
            compiled = self._functions.get("compiled")
            nlp = compiled[0] if compiled is not None else self._nlp
            self._functions[key] = ca.nlpsol(f"limit_{key}", "ipopt", nlp, self._options(warm))
        return self._functions[key]

    def prepare(self) -> None:
        """Build the solvers now (with ``jit``: generate and compile the NLP's C code, about a minute) rather than
        at the first solve."""
        self._solver(True)
        self._solver(False)
        self._jacobians()

    def _jacobians(self) -> Any:
        compiled = self._functions.get("compiled") if self.jit else None
        if self.jit and "compiled" not in self._functions:
            compiled = self._functions["compiled"] = self._compile()
        return compiled[1] if compiled is not None else self._stage_jacobian

    def _compile(self) -> tuple[Any, Any] | None:
        """(the NLP's functions, the stage Jacobians) generated as C and compiled with the system compiler; None
        and a warning if there is no compiler or it fails (CasADi's virtual machine then runs them)."""
        import casadi as ca

        cc = _compiler()
        if cc is None:
            warnings.warn("no C compiler found: the limit's NLP runs in CasADi's virtual machine (several times "
                          "slower); set CC, or pass jit=False to silence this", RuntimeWarning, stacklevel=4)
            return None
        folder = tempfile.mkdtemp(prefix="scr_limit_")
        # the compiled libraries live in ``folder`` until this problem is collected
        weakref.finalize(self, shutil.rmtree, folder, True)  # the folder goes with the problem (no cleanup by CasADi)
        here = os.getcwd()
        opts = {"compiler": cc, "flags": ["-O1"], "directory": folder, "cleanup": False}
        try:
            proto = ca.nlpsol("limit_nlp", "ipopt", self._nlp, {"print_time": False})
            os.chdir(folder)  # CasADi's code generation writes to the working directory
            try:
                proto.generate_dependencies("limit_nlp.c")
                self._stage_jacobian.generate("limit_jac.c")
            finally:
                os.chdir(here)
            nlp = ca.Importer(os.path.join(folder, "limit_nlp.c"), "shell", opts)
            jac = ca.external(self._stage_jacobian.name(), ca.Importer(os.path.join(folder, "limit_jac.c"),
                                                                        "shell", opts))
            return nlp, jac
        except Exception as exc:  # noqa: BLE001  (any compiler failure: run uncompiled, and say so)
            warnings.warn(f"compiling the limit's NLP failed ({type(exc).__name__}: {exc}); it runs in CasADi's "
                          "virtual machine", RuntimeWarning, stacklevel=4)
            return None

    # --- the plant and the reduced space ------------------------------------------------------------------------
    def lookup_table_dose(self) -> np.ndarray:
        """The look-up table's dose trajectory [g/s] on this cycle (the first warm start)."""
        if self._lut_dose is None:
            self._lut_dose = _lookup_table_dose(make_env(self.cycle, self.env_kwargs), self.seed)
        return self._lut_dose.copy()

    def per_step(self, doses: np.ndarray) -> np.ndarray:
        """The NLP's held doses as one AdBlue rate per plant step [g/s]."""
        return np.repeat(np.asarray(doses, dtype=np.float64), self.hold_steps)[:self.n_steps]

    def held(self, dose_g_s: np.ndarray) -> np.ndarray:
        """A dose per plant step as the NLP's held doses (the mean over each hold)."""
        d = np.asarray(dose_g_s, dtype=np.float64)
        h = self.hold_steps
        return np.add.reduceat(d, np.arange(0, d.size, h)) / np.diff(np.r_[np.arange(0, d.size, h), d.size])

    def simulate(self, dose_g_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(coverages after every step (steps x cells), tailpipe NOx [ppm], NH3 [ppm]) of a dose per step, by the
        plant kernel (:func:`scr_env.physics.kernel.plant_step`, what the environment steps)."""
        from scr_env.physics import kernel as K

        n, N = self.n_cells, self.n_steps
        theta = self.initial_coverage[None, :].copy()
        temps = self.initial_temperature_k[None, :].copy()
        sens, noise = np.zeros((1, K.N_SENSOR_STATES)), np.zeros((1, K.N_NOISE))
        out = np.zeros((1, len(K.OUTPUT_FIELDS)))
        inputs = self._kernel_inputs.copy()
        inputs[:, K.I_ADBLUE] = dose_g_s
        cov, nox, nh3 = np.empty((N, n)), np.empty(N), np.empty(N)
        step, dt, cat, aux = K.plant_step, self.dt, self._cat, self._aux
        for k in range(N):
            step(theta, temps, sens, inputs[k:k + 1], dt, cat, aux, noise, out)
            cov[k] = theta[0]
            nox[k] = out[0, K.O_NO] + out[0, K.O_NO2]
            nh3[k] = out[0, K.O_NH3]
        return cov, nox, nh3

    def _reduced(self, doses: np.ndarray, gradient: bool) -> dict[str, Any]:
        """NOx [g/kWh] and mean slip [ppm] of the held doses, and with ``gradient`` their gradients and the adjoint
        states (cached for the last doses)."""
        key = doses.tobytes()
        c = self._cache.get(key)
        if c is not None and (not gradient or "gradient" in c):
            return c
        dose = self.per_step(doses)
        cov, nox, nh3 = self.simulate(dose)
        c = {"nox": float(nox @ self.nox_weight), "slip": float(nh3 @ self.slip_weight), "coverage": cov}
        if gradient:
            n, N = self.n_cells, self.n_steps
            before = np.vstack([self.initial_coverage, cov[:-1]])
            a, b, cj, dj = (np.asarray(v) for v in self._jacobians()(before.T, cov.T, dose[None, :],
                                                                      self.temperature_k.T, self.drive.T))
            w = np.column_stack([self.nox_weight, self.slip_weight])
            grad, lam = _adjoint(np.ascontiguousarray(a.reshape(n, N, n).transpose(1, 0, 2)),
                                 np.ascontiguousarray(b.T),
                                 np.ascontiguousarray(cj.reshape(2, N, n).transpose(1, 0, 2)) * w[:, :, None],
                                 np.ascontiguousarray(dj.T) * w)
            c["gradient"] = np.add.reduceat(grad, np.arange(0, N, self.hold_steps), axis=0)
            c["adjoint"] = lam
        self._cache = {key: c}
        return c

    def _reduced_solve(self, budget: float, doses0: np.ndarray, iterations: int) -> tuple[np.ndarray, float, int]:
        """IPOPT (limited-memory quasi-Newton) on the doses alone: (doses, slip multiplier, iterations)."""
        import casadi as ca

        problem = self
        m = self.n_doses

        class _Sums(ca.Callback):
            def __init__(self) -> None:
                ca.Callback.__init__(self)
                self.construct("limit_reduced", {"enable_fd": False})

            def get_n_in(self) -> int:
                return 1

            def get_n_out(self) -> int:
                return 1

            def get_sparsity_in(self, i: int) -> Any:
                return ca.Sparsity.dense(m, 1)

            def get_sparsity_out(self, i: int) -> Any:
                return ca.Sparsity.dense(2, 1)

            def eval(self, arg: list) -> list:
                c = problem._reduced(np.asarray(arg[0]).ravel(), False)
                return [ca.DM([c["nox"], c["slip"]])]

            def has_jacobian(self) -> bool:
                return True

            def get_jacobian(self, name: str, inames: list, onames: list, opts: dict) -> Any:
                self._jac = _SumsJacobian(name)
                return self._jac

        class _SumsJacobian(ca.Callback):
            def __init__(self, name: str) -> None:
                ca.Callback.__init__(self)
                self.construct(name, {})

            def get_n_in(self) -> int:
                return 2

            def get_n_out(self) -> int:
                return 1

            def get_sparsity_in(self, i: int) -> Any:
                return ca.Sparsity.dense(m, 1) if i == 0 else ca.Sparsity.dense(2, 1)

            def get_sparsity_out(self, i: int) -> Any:
                return ca.Sparsity.dense(2, m)

            def eval(self, arg: list) -> list:
                return [ca.DM(problem._reduced(np.asarray(arg[0]).ravel(), True)["gradient"].T)]

        sums = _Sums()
        U = ca.MX.sym("U", m)
        s = sums(U)
        opts = {"print_time": False, "ipopt.print_level": self.print_level, "ipopt.sb": "yes",
                "ipopt.hessian_approximation": "limited-memory", "ipopt.limited_memory_max_history": 50,
                "ipopt.max_iter": iterations, "ipopt.tol": self.tol, "ipopt.print_frequency_iter": 25}
        solver = ca.nlpsol("limit_reduced", "ipopt", {"x": U, "f": OBJECTIVE_SCALE * s[0], "g": s[1]}, opts)
        sol = solver(x0=np.clip(doses0, 0.0, self.max_rate_g_s), lbx=0.0, ubx=self.max_rate_g_s, lbg=-np.inf,
                     ubg=budget)
        return np.asarray(sol["x"]).ravel(), float(sol["lam_g"]), int(solver.stats().get("iter_count", 0))

    # --- solving ---------------------------------------------------------------------------------------------
    def solve(self, budget_ppm: float, warm_start: LimitResult | np.ndarray | None = None,
              peak_ppm: float | None = None, replay_dose: bool = True) -> LimitResult:
        """The optimum at a mean-slip budget [ppm].

        ``warm_start``: None (the look-up table's trajectory), a dose per plant step [g/s], or a
        :class:`LimitResult` of this problem (a neighbouring budget: its dose, and its primal-dual solution when the
        reduced-space stage is skipped). ``peak_ppm``: the peak bound of this solve (a problem built with one only;
        default the problem's). ``replay_dose``: replay the optimal dose through the environment (``replay``).
        """
        budget = _positive("budget_ppm", budget_ppm)
        if peak_ppm is not None and self.peak_ppm is None:
            raise ValueError("peak_ppm: this problem has no peak bound; build it with CycleOptimum(peak_ppm=...)")
        peak = None if self.peak_ppm is None else _positive("peak_ppm", self.peak_ppm if peak_ppm is None
                                                            else peak_ppm)
        n, N = self.n_cells, self.n_steps
        neighbour = warm_start if isinstance(warm_start, LimitResult) else None
        if neighbour is not None:
            dose0, origin = neighbour.dose_g_s, f"solution at {neighbour.budget_ppm:g} ppm"
        elif warm_start is None:
            dose0, origin = self.lookup_table_dose(), "look-up table"
        else:
            dose0, origin = np.asarray(warm_start, dtype=np.float64).ravel(), "given dose"
        if dose0.size != N or not np.all(np.isfinite(dose0)):
            raise ValueError(f"warm_start must be None, a LimitResult of this problem or a finite dose per step "
                             f"({N} values)")
        doses = self.held(np.clip(dose0, 0.0, self.max_rate_g_s))
        iterations = self.reduced_iterations[0 if neighbour is None else 1] if peak is None else 0
        args: dict[str, Any] = {"p": self._p, "lbx": self._lbx, "ubx": self._ubx,
                                "lbg": np.r_[np.zeros(n * N), -np.inf, np.full(N if peak else 0, -np.inf)],
                                "ubg": np.r_[np.zeros(n * N), budget, np.full(N if peak else 0, peak or 0.0)]}
        t0, c0 = time.perf_counter(), time.process_time()
        reduced_its, reduced_nox, warm = 0, float("nan"), False
        if iterations > 0:  # the reduced-space warm start: doses, states and multipliers
            doses, mu, reduced_its = self._reduced_solve(budget, doses, iterations)
            c = self._reduced(doses, True)
            reduced_nox = c["nox"]
            lam = OBJECTIVE_SCALE * c["adjoint"][:, 0, :] + mu * c["adjoint"][:, 1, :]
            zu = -(OBJECTIVE_SCALE * c["gradient"][:, 0] + mu * c["gradient"][:, 1])
            args.update(x0=np.r_[c["coverage"].ravel(), doses], lam_g0=np.r_[lam.ravel(), mu, np.zeros(
                N if peak else 0)], lam_x0=np.r_[np.zeros(n * N), zu])
            warm = True
        elif neighbour is not None and neighbour.primal_dual is not None \
                and neighbour.primal_dual[0].size == self._nx and neighbour.primal_dual[1].size == self._ng:
            args.update(x0=neighbour.primal_dual[0], lam_g0=neighbour.primal_dual[1], lam_x0=neighbour.primal_dual[2])
            warm = True
        else:
            cov = self.simulate(self.per_step(doses))[0]
            args["x0"] = np.r_[np.clip(cov, 0.0, 1.0).ravel(), doses]
        solver = self._solver(warm)
        sol = solver(**args)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        st = solver.stats()
        x = np.asarray(sol["x"]).ravel()
        nox, nh3, dose = (np.asarray(v).ravel() for v in self._outputs(x, self._p))
        dose = np.clip(dose, 0.0, self.max_rate_g_s)  # IPOPT relaxes bounds by 1e-8: the injector's range
        res = LimitResult(
            cycle=self.name, budget_ppm=budget, tailpipe_nox_g_per_kwh=float(nox @ self.nox_weight),
            mean_nh3_slip_ppm=float(nh3 @ self.slip_weight), peak_nh3_slip_ppm=float(np.max(nh3)),
            adblue_g=float(np.sum(dose) * self.dt), dose_g_s=dose, status=str(st.get("return_status", "")),
            success=bool(st.get("success", False)), iterations=int(st.get("iter_count", 0)) + reduced_its,
            solve_time_s=wall, solve_cpu_s=cpu, reduced_iterations=reduced_its,
            reduced_tailpipe_nox_g_per_kwh=reduced_nox, peak_ppm=peak, hold_steps=self.hold_steps, dt=self.dt,
            warm_start=origin,
            primal_dual=(x, np.asarray(sol["lam_g"]).ravel(), np.asarray(sol["lam_x"]).ravel()))
        if replay_dose:
            res = replace(res, replay=_kpi_floats(replay(self.cycle, dose, self.env_kwargs, seed=self.seed)))
        return res


def _kpi_floats(kpis: Mapping[str, Any]) -> dict[str, float]:
    return {k: float(v) for k, v in kpis.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


def pareto_front(problem: CycleOptimum, budgets_ppm: Sequence[float] = DEFAULT_BUDGETS_PPM,
                 first_ppm: float | None = REFERENCE_BUDGET_PPM,
                 progress: Callable[[LimitResult], None] | None = None) -> dict[float, LimitResult]:
    """The optimum at every budget [ppm], each budget warm-started from its neighbour.

    The first budget solved is ``first_ppm`` (from the look-up table; default 10 ppm when it is among the budgets,
    else the largest), then the larger budgets in increasing and the smaller ones in decreasing order, each from the
    previous solution. A larger budget never needs more NOx than a smaller one (whose solution is feasible for it):
    where a local optimum says otherwise, the larger budget is solved again from the smaller one's solution and the
    better of the two kept. ``progress(result)`` is called after every solve.
    """
    budgets = sorted({_positive("budgets_ppm", b) for b in budgets_ppm})
    if not budgets:
        raise ValueError("budgets_ppm must hold at least one budget")
    first = first_ppm if first_ppm in budgets else budgets[-1]
    i0 = budgets.index(first)
    out: dict[float, LimitResult] = {}

    def run(b: float, start: LimitResult | None) -> LimitResult:
        r = problem.solve(b, warm_start=start)
        if progress is not None:
            progress(r)
        return r

    out[first] = run(first, None)
    for seq in (budgets[i0 + 1:], budgets[:i0][::-1]):
        prev = out[first]
        for b in seq:
            prev = out[b] = run(b, prev)
    for lo, hi in itertools.pairwise(budgets):  # in increasing budget order, so a repair carries upwards
        if out[hi].tailpipe_nox_g_per_kwh > out[lo].tailpipe_nox_g_per_kwh * (1.0 + 1e-6) or not out[hi].success:
            again = run(hi, out[lo])
            if again.success and again.tailpipe_nox_g_per_kwh < out[hi].tailpipe_nox_g_per_kwh:
                out[hi] = again
    return {b: out[b] for b in budgets}
