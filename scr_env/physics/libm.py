"""numba's ``exp`` bound to the C library's computation itself, past glibc's compatibility wrapper.

numba compiles ``math.exp`` to LLVM's ``llvm.exp`` and links that to the C library's ``exp`` through its helper
library, which on glibc is linked to ``exp@GLIBC_2.2.5``: a compatibility wrapper that calls the computation
(``__ieee754_exp``, chosen per CPU at load time) and then checks the result for the old SVID error reporting
(``_LIB_VERSION``, ``matherr``). The plant step evaluates about 60 exponentials per plant (nine rate constants per
cell, one per Newton iteration of each cell, the heat exchange, the urea decomposition, the sensor lags), and the
wrapper with its two extra jumps took a third of their time (perf, WHTC, 1024 plants, serial: 9.4 % of the vector
step in the wrapper against 20.3 % in the computation).

:func:`bind_direct_exp` points numba's symbol ``exp`` at glibc's ``__exp_finite`` instead: the same
``__ieee754_exp`` without a wrapper, kept by every glibc since 2.15 for the binaries linked against it. Only the
address changes, not the compiled code, so every result is the same bits (the wrapper returns the computed value
unchanged; it differs only in setting ``errno`` on overflow and underflow, which compiled code never reads):
``tests/scr_env/test_physics.py`` compares it with Python's ``math.exp`` over the whole double range, and plant
rollouts are bit for bit unchanged. Measured on the vector step (1024 plants, WHTC, serial, CPU time on 2 loaded
cores): median 1.98 -> 1.82 ms.

The binding is process-wide (numba has one symbol table): every numba-compiled ``exp`` in the process then enters
glibc directly, with the same values. Where there is no glibc or no such entry, nothing is changed.
"""
from __future__ import annotations

import ctypes
import sys

__all__ = ["bind_direct_exp", "direct_exp_address"]

# symbol versions of __exp_finite: x86_64 and s390x (2.15), the later ports' first glibc (aarch64, ppc64le: 2.17)
_GLIBC_VERSIONS = (b"GLIBC_2.15", b"GLIBC_2.17", b"GLIBC_2.18")
_bound: bool | None = None


def direct_exp_address() -> int | None:
    """Address of glibc's ``__exp_finite`` (a compatibility symbol: ``dlsym`` does not find it, ``dlvsym`` does),
    or None where there is no such entry (not Linux, not glibc, a glibc without it)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        dlvsym = ctypes.CDLL(None).dlvsym
        libm = ctypes.CDLL("libm.so.6")
    except (OSError, AttributeError):  # not glibc (musl has no dlvsym), or no libm.so.6
        return None
    dlvsym.restype = ctypes.c_void_p
    dlvsym.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_char_p]
    for version in _GLIBC_VERSIONS:
        address = dlvsym(libm._handle, b"__exp_finite", version)
        if address:
            return int(address)
    return None


def bind_direct_exp() -> bool:
    """Bind numba's ``exp`` to :func:`direct_exp_address` (module docstring), once per process; True if it is bound
    so. Call it before compiled code is linked: LLVM resolves the symbol when it links a function (also one loaded
    from numba's on-disk cache), so code linked earlier keeps the wrapper (same values, only slower)."""
    global _bound
    if _bound is None:
        address = direct_exp_address()
        if address is not None:
            import llvmlite.binding as ll
            from numba.core.registry import cpu_target

            # numba installs its C math symbols (exp among them) once, when its CPU target context is made; make it
            # now, so that this binding comes after it and stays
            cpu_target.target_context  # noqa: B018
            ll.add_symbol("exp", address)
        _bound = address is not None
    return _bound
