"""The regressor language of the RPEM model: monomials of states, inputs and input derivatives.

A term is a product of factors written as a string, for example ``"x1*u2"``, ``"u1'"``, ``"x2^2*u1"`` or ``"1"``:

=========  ==========================================================================================
factor     meaning
=========  ==========================================================================================
``x<i>``   state i of the model (1-based; in a MIMO model states are numbered across all chains)
``u<j>``   input j (1-based), *after* the estimator's input transform (e.g. ``u3`` = exp(-a/T_in))
``u<j>'``  time derivative of input j, a backward difference on the model's (scaled) time axis
``^k``     integer power of the preceding factor
``1``      the constant term
=========  ==========================================================================================

Factors are joined by ``*`` (spaces are ignored). Internally a term list is an integer exponent matrix ``E`` of
shape ``(n_terms, n_vars)`` over the variable vector ``z = (x_1..x_N, u_1..u_m, u'_1..u'_m)``, the form the
compiled kernel evaluates.
"""
from __future__ import annotations

import itertools
import re
from collections.abc import Sequence

import numpy as np

__all__ = [
    "PAPER2_TERMS",
    "SCR_PAPER3_LINEAR_TERMS",
    "SCR_PAPER3_TERMS",
    "format_term",
    "parse_term",
    "parse_terms",
    "polynomial_terms",
]

#: Paper II (simulated example and Wiener-Hammerstein benchmark): phi = (1, u, x2, x2 u, x1, x1 u, x1 x2, x1 x2 u).
PAPER2_TERMS: tuple[str, ...] = ("1", "u1", "x2", "x2*u1", "x1", "x1*u1", "x1*x2", "x1*x2*u1")

#: Paper III's final 16-term SCR regressor (u1 inlet NOx, u2 urea, u3 = exp(-a/T_in), u4 exhaust flow).
SCR_PAPER3_TERMS: tuple[str, ...] = (
    "u4'", "u2'", "u1'", "u4", "u3", "u2", "u1", "x2", "x1",
    "u3*u4'", "u2*u4'", "u2*u3*u4", "u1*u1'*u2'", "u1*u3*u1'", "x2*u1", "x1*u2",
)

#: Paper III's linear model: the first 9 terms of :data:`SCR_PAPER3_TERMS`.
SCR_PAPER3_LINEAR_TERMS: tuple[str, ...] = SCR_PAPER3_TERMS[:9]

_FACTOR = re.compile(r"^([xu])(\d+)('?)(?:\^(\d+))?$")


def parse_term(term: str, n_states: int, n_inputs: int) -> np.ndarray:
    """Exponent row of one term over ``z = (x, u, u')``.

    Parameters
    ----------
    term : str
        A product such as ``"x1*u2^2*u1'"``; ``"1"`` is the constant.
    n_states, n_inputs : int
        Sizes of the model, to validate indices.

    Returns
    -------
    numpy.ndarray
        Integer exponents, shape ``(n_states + 2 * n_inputs,)``.
    """
    row = np.zeros(n_states + 2 * n_inputs, dtype=np.int64)
    text = term.replace(" ", "")
    if text == "1":
        return row
    if not text:
        raise ValueError("empty term")
    for factor in text.split("*"):
        m = _FACTOR.match(factor)
        if m is None:
            raise ValueError(f"cannot parse factor {factor!r} of term {term!r} (expected x<i>, u<j>, u<j>' or ^k)")
        kind, idx, prime, power = m.group(1), int(m.group(2)), m.group(3), int(m.group(4) or 1)
        if kind == "x":
            if prime:
                raise ValueError(f"state derivatives are not regressors (term {term!r}); use the next state")
            if not 1 <= idx <= n_states:
                raise ValueError(f"term {term!r} uses x{idx} but the model has {n_states} states")
            row[idx - 1] += power
        else:
            if not 1 <= idx <= n_inputs:
                raise ValueError(f"term {term!r} uses u{idx} but the model has {n_inputs} inputs")
            offset = n_states + (n_inputs if prime else 0)
            row[offset + idx - 1] += power
    return row


def parse_terms(terms: Sequence[str], n_states: int, n_inputs: int) -> np.ndarray:
    """Exponent matrix of a term list; duplicates are rejected because they make theta unidentifiable."""
    if len(terms) == 0:
        raise ValueError("the term list is empty")
    rows = np.array([parse_term(t, n_states, n_inputs) for t in terms], dtype=np.int64)
    seen: dict[tuple[int, ...], str] = {}
    for t, r in zip(terms, rows, strict=False):
        key = tuple(int(v) for v in r)
        if key in seen:
            raise ValueError(f"terms {seen[key]!r} and {t!r} are the same monomial")
        seen[key] = t
    return rows


def format_term(row: np.ndarray, n_states: int, n_inputs: int) -> str:
    """Inverse of :func:`parse_term` (canonical spelling)."""
    names = [f"x{i + 1}" for i in range(n_states)] + [f"u{j + 1}" for j in range(n_inputs)]
    names += [f"u{j + 1}'" for j in range(n_inputs)]
    parts = [n if int(k) == 1 else f"{n}^{int(k)}" for n, k in zip(names, row, strict=False) if k > 0]
    return "*".join(parts) if parts else "1"


def polynomial_terms(
    n_states: int,
    n_inputs: int,
    max_degrees: Sequence[int] | int = 1,
    total_degree: int | None = None,
    derivative_inputs: Sequence[int] = (),
) -> list[str]:
    """All monomials within per-variable degree limits (and optionally a total-degree limit).

    Parameters
    ----------
    n_states, n_inputs : int
        Model sizes.
    max_degrees : int or sequence of int
        Largest power of each variable, in the order ``x_1..x_N, u_1..u_m`` followed by one entry per
        ``derivative_inputs`` item; an int applies to all. Paper III's full polynomial (2 states, 4 inputs,
        3 derivatives, every degree 1) has ``2**9 = 512`` terms.
    total_degree : int, optional
        Largest total degree of a monomial (``None``: no limit).
    derivative_inputs : sequence of int
        1-based indices of inputs whose derivative ``u<j>'`` is a variable.

    Returns
    -------
    list of str
        Term strings, constant first, ordered by total degree.
    """
    names = [f"x{i + 1}" for i in range(n_states)] + [f"u{j + 1}" for j in range(n_inputs)]
    names += [f"u{j}'" for j in derivative_inputs]
    if isinstance(max_degrees, (int, np.integer)):
        degs = [int(max_degrees)] * len(names)
    else:
        degs = [int(d) for d in max_degrees]
        if len(degs) != len(names):
            raise ValueError(f"max_degrees has {len(degs)} entries for {len(names)} variables {names}")
    combos = [c for c in itertools.product(*(range(d + 1) for d in degs))
              if total_degree is None or sum(c) <= total_degree]
    combos.sort(key=lambda c: (sum(c), [-v for v in c]))
    terms = []
    for c in combos:
        parts = [n if k == 1 else f"{n}^{k}" for n, k in zip(names, c, strict=False) if k > 0]
        terms.append("*".join(parts) if parts else "1")
    return terms
