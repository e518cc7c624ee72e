"""Compile the one-source chemistry of :mod:`scr_env.physics.cell` for numba and for CasADi.

Both backends are built from the same code objects (``cell_balance`` and ``rate_constants``) by rebinding the names
``exp``, ``log``, ``sqrt`` and ``select`` that the code looks up as globals. A test
(``tests/scr_env/test_casadi_model.py``) checks that the two agree on random states and inputs.
"""
from __future__ import annotations

import math
import types
from functools import lru_cache
from typing import Any, Callable

import numba

from scr_env.physics import cell as _cell


def _rebind(func: Callable, namespace: dict[str, Any]) -> Callable:
    return types.FunctionType(func.__code__, namespace, func.__name__, func.__defaults__, func.__closure__)


@numba.njit(inline="always")
def _select_scalar(condition: bool, if_true: float, if_false: float) -> float:
    return if_true if condition else if_false


# "__name__" lets numba's on-disk cache re-import the namespace of the rebound functions.
_NUMBA_NS = {"__name__": __name__, "exp": math.exp, "log": math.log, "sqrt": math.sqrt, "select": _select_scalar}
_JIT = dict(nogil=True, fastmath=False, error_model="numpy", cache=True)

#: numba versions (scalar arguments), used by the compiled plant kernel
cell_balance_nb = numba.njit(**_JIT)(_rebind(_cell.cell_balance, _NUMBA_NS))
rate_constants_nb = numba.njit(**_JIT)(_rebind(_cell.rate_constants, _NUMBA_NS))
decomposition_efficiency_nb = numba.njit(**_JIT)(_rebind(_cell.decomposition_efficiency, _NUMBA_NS))


@lru_cache(maxsize=None)
def casadi_functions() -> tuple[Callable, Callable, Callable]:
    """``(cell_balance, rate_constants, decomposition_efficiency)`` on CasADi SX/MX expressions (lazy import)."""
    import casadi as ca

    ns = {"exp": ca.exp, "log": ca.log, "sqrt": ca.sqrt, "select": ca.if_else}
    return (_rebind(_cell.cell_balance, ns), _rebind(_cell.rate_constants, ns),
            _rebind(_cell.decomposition_efficiency, ns))
