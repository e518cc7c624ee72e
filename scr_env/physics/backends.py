"""Compile the one-source chemistry of :mod:`scr_env.physics.cell` for numba and for CasADi.

Both backends are built from the same code objects (``cell_balance`` and ``rate_constants``) by rebinding the names
``exp``, ``log``, ``sqrt`` and ``select`` that the code looks up as globals. A test
(``tests/scr_env/test_casadi_model.py``) checks that the two agree on random states and inputs.
"""
from __future__ import annotations

import math
import types
from collections.abc import Callable
from functools import cache
from typing import Any

import numba

from scr_env.physics import cell as _cell


def _rebind(func: Callable, namespace: dict[str, Any]) -> Callable:
    return types.FunctionType(func.__code__, namespace, func.__name__, func.__defaults__, func.__closure__)


@numba.njit(inline="always")
def _select_scalar(condition: bool, if_true: float, if_false: float) -> float:
    return if_true if condition else if_false


# The one-source functions, in dependency order (a function may call those before it).
_SOURCES = ("o2_factors", "no_oxidation_equilibrium", "arrhenius_constants", "rate_constants", "cell_state",
            "cell_outlets", "cell_slope", "cell_balance", "decomposition_efficiency")


# the numeric module constants of cell.py (thermodynamic data, iteration counts), visible to both backends
_CONSTANTS = {k: v for k, v in vars(_cell).items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


def _compile_all(namespace: dict[str, Any], wrap: Callable[[Callable], Callable]) -> dict[str, Callable]:
    """Rebind every one-source function into ``namespace`` (so calls between them resolve there) and wrap it."""
    namespace.update(_CONSTANTS)
    out = {}
    for name in _SOURCES:
        func = wrap(_rebind(getattr(_cell, name), namespace))
        namespace[name] = func
        out[name] = func
    return out


# "__name__" lets numba's on-disk cache re-import the namespace of the rebound functions.
_NUMBA_NS: dict[str, Any] = {"__name__": __name__, "exp": math.exp, "log": math.log, "sqrt": math.sqrt,
                             "select": _select_scalar, "abs": abs}
# inline="always": numba does not inline across its compiled functions by itself, and a call of cell_balance per
# Newton iteration (13 doubles in, an 11-tuple out through memory) cost about a seventh of the plant step.
# LLVM fast-math flags of every compiled plant function: fused multiply-add, reciprocal multiplication, reassociation
# and sign-blind zeros. Not "nnan"/"ninf": the kernel tests for non-finite values (actions, solver fall-backs), and
# those flags would let LLVM assume them away. Measured on the 1024-plant WHTC vector step (2 cores): 572 -> 505 us
# (threaded), 1010 -> 860 us (serial). Results change at rounding level only: WHTC nitrogen balance error 1.5e-14
# (3e-15 without the flags), agreement with CasADi's exact implicit step unchanged (coverage 3.8e-7, outlets 1.3e-6
# relative, set by the Newton tolerance), and the serial and threaded steps stay bitwise equal (tests).
# Closed loops move within their sensor-noise spread: the identified NMPC on the WHTC over reset seeds 0-5, 3.2-4.6
# ppm mean slip with the flags, 3.2-4.8 without (experiments/control_benchmark.py, --seeds).
# numba's disk cache keys on each function's own source file: after changing FASTMATH, delete the *.nbi/*.nbc
# files under scr_env/ (or touch cell.py, kernel.py and core.py), or stale machine code keeps running.
FASTMATH = frozenset({"contract", "arcp", "reassoc", "nsz"})
_JIT = {"nogil": True, "fastmath": set(FASTMATH), "error_model": "numpy", "cache": True, "inline": "always"}
# Not inlined: what runs at most once per cell and step (the slope only where a Newton step is taken, the outlets,
# the rate constants) and the combined cell_balance (tests, lab): inlining them into both plant kernels (serial and
# parallel) made the cold first step 5 s longer (12 -> 17 s, a new process with an empty cache, 2 loaded cores) for
# no measurable gain; cell_state, in the Newton loop, stays inlined (745 ns per plant step either way on WHTC states,
# 805 ns with it called).
_NOT_INLINED = ("cell_slope", "cell_outlets", "cell_balance", "arrhenius_constants")


def _wrap_nb(func: Callable) -> Callable:
    opts = dict(_JIT)
    if func.__name__ in _NOT_INLINED:
        opts["inline"] = "never"
    return numba.njit(**opts)(func)


_NB = _compile_all(_NUMBA_NS, _wrap_nb)

#: numba versions (scalar arguments), used by the compiled plant kernel
cell_balance_nb = _NB["cell_balance"]
cell_state_nb = _NB["cell_state"]
cell_slope_nb = _NB["cell_slope"]
cell_outlets_nb = _NB["cell_outlets"]
rate_constants_nb = _NB["rate_constants"]
arrhenius_constants_nb = _NB["arrhenius_constants"]
o2_factors_nb = _NB["o2_factors"]
decomposition_efficiency_nb = _NB["decomposition_efficiency"]
no_oxidation_equilibrium_nb = _NB["no_oxidation_equilibrium"]


@cache
def casadi_functions() -> tuple[Callable, Callable, Callable]:
    """``(cell_balance, rate_constants, decomposition_efficiency)`` on CasADi SX/MX expressions (lazy import)."""
    import casadi as ca

    ns: dict[str, Any] = {"exp": ca.exp, "log": ca.log, "sqrt": ca.sqrt, "select": ca.if_else, "abs": ca.fabs}
    fns = _compile_all(ns, lambda f: f)
    return fns["cell_balance"], fns["rate_constants"], fns["decomposition_efficiency"]
