"""Compile the one-source plant of :mod:`scr_env.physics` for numba, for CasADi and for numpy.

The chemistry (:mod:`~scr_env.physics.cell`), the heat balance (:mod:`~scr_env.physics.thermal`) and the dosing
and inlet gas (:mod:`~scr_env.physics.dosing`) are written once, as plain scalar Python. Every backend is built
from the same code objects by rebinding the names the code looks up as globals (``exp``, ``log``, ``sqrt``,
``abs``, ``select``, ``fmin``, ``fmax``, the module constants and the functions they call one another by):

* numba (:data:`cell_balance_nb` and the other ``*_nb``): scalar, fast-math, inlined into the plant kernel;
* CasADi (:func:`casadi_functions`, :func:`casadi_namespace`): on SX/MX expressions, for the model-based
  controllers and :mod:`scr_env.casadi_model`;
* numpy (:func:`numpy_namespace`): element-wise on arrays, for numeric preparation outside the kernel
  (:mod:`control.models`).

Tests (``tests/scr_env/test_casadi_model.py``, ``tests/scr_env/test_single_source.py``) check that they agree.
"""
from __future__ import annotations

import math
import types
from collections.abc import Callable
from functools import cache
from typing import Any

from scr_env.jit import njit
from scr_env.physics import cell as _cell
from scr_env.physics import dosing as _dosing
from scr_env.physics import thermal as _thermal
from scr_env.physics.libm import bind_direct_exp

# the plant's exponentials enter glibc's computation directly: same values, a third less time (scr_env.physics.libm);
# before anything of the plant is compiled or loaded from numba's cache
bind_direct_exp()


def _rebind(func: Callable, namespace: dict[str, Any]) -> Callable:
    return types.FunctionType(func.__code__, namespace, func.__name__, func.__defaults__, func.__closure__)


@njit(inline="always")
def _select_scalar(condition: bool, if_true: float, if_false: float) -> float:
    return if_true if condition else if_false


# The one-source functions, in dependency order (a function may call those before it).
_SOURCES = ("o2_factors", "no_oxidation_equilibrium", "arrhenius_constants", "rate_constants", "cell_state",
            "cell_outlets", "cell_slope", "cell_balance", "decomposition_efficiency")
# The rest of the plant, after the chemistry (dosing calls decomposition_efficiency).
_PLANT_SOURCES = (
    (_thermal, ("gas_solid_exchange", "gas_outlet_temperature", "cell_temperature_step", "cell_temperature_rate")),
    (_dosing, ("actuator_step", "injected_adblue", "urea_decomposition", "flow_per_site", "inlet_nh3_fraction",
               "inlet_nox_fractions", "inlet_conditions")),
)


def _constants() -> dict[str, float]:
    """The module-level constants (upper-case floats) the one-source functions read as globals."""
    return {k: v for mod in (_cell, _thermal, _dosing) for k, v in vars(mod).items()
            if k.isupper() and isinstance(v, float)}


def _compile_all(namespace: dict[str, Any], wrap: Callable[[Callable], Callable]) -> dict[str, Callable]:
    """Rebind every one-source function into ``namespace`` (so calls between them resolve there) and wrap it."""
    out = {}
    namespace.update({k: v for k, v in _constants().items() if k not in namespace})
    sources = [(_cell, name) for name in _SOURCES] + [(mod, name) for mod, names in _PLANT_SOURCES for name in names]
    for module, name in sources:
        func = wrap(_rebind(getattr(module, name), namespace))
        namespace[name] = func
        out[name] = func
    return out


# "__name__" lets numba's on-disk cache re-import the namespace of the rebound functions.
_NUMBA_NS: dict[str, Any] = {"__name__": __name__, "exp": math.exp, "log": math.log, "sqrt": math.sqrt,
                             "select": _select_scalar, "abs": abs, "fmin": min, "fmax": max}
# inline="always": numba does not inline across its compiled functions by itself, and a call of the cell chemistry per
# Newton iteration (13 doubles in, an 11-tuple out through memory) cost about a seventh of the plant step.
# LLVM fast-math flags of every compiled plant function: fused multiply-add, reciprocal multiplication, reassociation
# and sign-blind zeros. Not "nnan"/"ninf": the kernel tests for non-finite values (actions, solver fall-backs), and
# those flags would let LLVM assume them away. Measured on the 1024-plant WHTC vector step (2 cores): 572 -> 505 us
# (threaded), 1010 -> 860 us (serial). Results change at rounding level only: WHTC nitrogen balance error 1.5e-14
# (3e-15 without the flags), agreement with CasADi's exact implicit step unchanged (coverage 3.8e-7, outlets 1.3e-6
# relative, set by the Newton tolerance), and the serial and threaded steps stay bitwise equal (tests).
# Closed loops move within their sensor-noise spread: the identified NMPC on the WHTC over reset seeds 0-5, 3.2-4.6
# ppm mean slip with the flags, 3.2-4.8 without (experiments/control_benchmark.py, --seeds).
# numba's disk cache keys on each function's own source file: after changing FASTMATH, clear the cache
# (python -m scr_env.jit --clear, or touch the files of scr_env/physics and scr_env/envs/core.py), or stale machine
# code keeps running.
FASTMATH = frozenset({"contract", "arcp", "reassoc", "nsz"})
_JIT = {"nogil": True, "fastmath": set(FASTMATH), "error_model": "numpy", "inline": "always"}
# Not inlined: what runs at most once per cell and step (the slope only where a Newton step is taken, the outlets,
# the rate constants) and the combined cell_balance (tests, lab): inlining them into both plant kernels (serial and
# parallel) made the cold first step 5 s longer (12 -> 17 s, a new process with an empty cache, 2 loaded cores) for
# no measurable gain; cell_state, in the Newton loop, stays inlined (745 ns per plant step either way on WHTC states,
# 805 ns with it called).
_NOT_INLINED = ("cell_slope", "cell_outlets", "cell_balance", "arrhenius_constants")


def _wrap_nb(func: Callable) -> Callable:
    return njit(**dict(_JIT, inline="never" if func.__name__ in _NOT_INLINED else "always"))(func)


_NB = _compile_all(_NUMBA_NS, _wrap_nb)

#: numba versions (scalar arguments), used by the compiled plant kernel
cell_balance_nb = _NB["cell_balance"]
cell_state_nb = _NB["cell_state"]
cell_slope_nb = _NB["cell_slope"]
cell_outlets_nb = _NB["cell_outlets"]
no_oxidation_equilibrium_nb = _NB["no_oxidation_equilibrium"]
rate_constants_nb = _NB["rate_constants"]
arrhenius_constants_nb = _NB["arrhenius_constants"]
o2_factors_nb = _NB["o2_factors"]
decomposition_efficiency_nb = _NB["decomposition_efficiency"]
gas_solid_exchange_nb = _NB["gas_solid_exchange"]
gas_outlet_temperature_nb = _NB["gas_outlet_temperature"]
cell_temperature_step_nb = _NB["cell_temperature_step"]
inlet_conditions_nb = _NB["inlet_conditions"]
actuator_step_nb = _NB["actuator_step"]


@cache
def casadi_namespace() -> types.SimpleNamespace:
    """Every one-source function (chemistry, heat balance, dosing) on CasADi SX/MX expressions, as attributes
    named as in their modules (lazy import of CasADi)."""
    import casadi as ca

    ns: dict[str, Any] = {"exp": ca.exp, "log": ca.log, "sqrt": ca.sqrt, "select": ca.if_else, "abs": ca.fabs,
                          "fmin": ca.fmin, "fmax": ca.fmax}
    return types.SimpleNamespace(**_compile_all(ns, lambda f: f))


def casadi_functions() -> tuple[Callable, Callable, Callable]:
    """``(cell_balance, rate_constants, decomposition_efficiency)`` on CasADi SX/MX expressions (lazy import)."""
    ns = casadi_namespace()
    return ns.cell_balance, ns.rate_constants, ns.decomposition_efficiency


@cache
def numpy_namespace() -> types.SimpleNamespace:
    """Every one-source function on numpy arrays (element-wise, broadcasting), as attributes named as in their
    modules. Same arithmetic as the other backends, without the kernel's fast-math flags."""
    import numpy as np

    ns: dict[str, Any] = {"exp": np.exp, "log": np.log, "sqrt": np.sqrt, "select": np.where, "abs": np.abs,
                          "fmin": np.minimum, "fmax": np.maximum}
    return types.SimpleNamespace(**_compile_all(ns, lambda f: f))
