"""Regressor term selection on validation fit (Paper III): backward elimination and forward selection."""
from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ident.rpem.estimator import RecursivePEM


@dataclass
class SelectionResult:
    """Outcome of a term search.

    Attributes
    ----------
    terms : list of str
        Selected terms.
    fit : float
        Validation FIT (percent) of the selected set.
    history : list of (list of str, float)
        Every accepted set with its validation FIT, in order.
    """

    terms: list[str]
    fit: float
    history: list[tuple[list[str], float]] = field(default_factory=list)


def _validation_fit(template: RecursivePEM, terms: Sequence[str], u_est: np.ndarray, y_est: np.ndarray,
                    u_val: np.ndarray, y_val: np.ndarray, theta0: dict[str, float] | None) -> float:
    th0 = None if theta0 is None else [theta0.get(t, 0.0) for t in terms]
    with warnings.catch_warnings():
        # a search fits poor candidates on purpose (a needed term removed): their rejected-update or divergence
        # warnings are not about the model the user gets, whose own fit by the caller still warns; a diverged
        # candidate scores low and is not selected
        warnings.simplefilter("ignore", RuntimeWarning)
        est = template.clone(terms=list(terms), theta0=th0).fit(u_est, y_est)
    return est.score(u_val, y_val)


def backward_elimination(template: RecursivePEM, terms: Sequence[str], u_est: np.ndarray, y_est: np.ndarray,
                         u_val: np.ndarray, y_val: np.ndarray, min_terms: int = 1,
                         keep: Sequence[str] = (), theta0: dict[str, float] | None = None) -> SelectionResult:
    """Remove one term at a time (the removal with the best validation FIT) while the validation FIT improves.

    Parameters
    ----------
    template : RecursivePEM
        Unfitted estimator whose settings every candidate uses (its ``terms``/``theta0`` are overridden).
    terms : sequence of str
        Starting term set (single-output template form).
    u_est, y_est, u_val, y_val : numpy.ndarray
        Estimation and validation data.
    min_terms : int
        Never go below this many terms.
    keep : sequence of str
        Terms that are never removed.
    theta0 : dict, optional
        Initial parameter per term name (missing terms start at 0).
    """
    current = list(terms)
    best = _validation_fit(template, current, u_est, y_est, u_val, y_val, theta0)
    history = [(list(current), best)]
    while len(current) > min_terms:
        trials = [(t, _validation_fit(template, [c for c in current if c != t], u_est, y_est, u_val, y_val, theta0))
                  for t in current if t not in keep]
        if not trials:
            break
        term, fit = max(trials, key=lambda tf: tf[1])
        if not fit > best:
            break
        current.remove(term)
        best = fit
        history.append((list(current), best))
    return SelectionResult(current, best, history)


def forward_selection(template: RecursivePEM, candidates: Sequence[str], u_est: np.ndarray, y_est: np.ndarray,
                      u_val: np.ndarray, y_val: np.ndarray, start: Sequence[str] = (), max_terms: int | None = None,
                      theta0: dict[str, float] | None = None) -> SelectionResult:
    """Add one candidate at a time (the addition with the best validation FIT) while the validation FIT improves.

    ``start`` must be non-empty (a model needs at least one term); see :func:`backward_elimination` for the
    other arguments.
    """
    current = list(start)
    if not current:
        raise ValueError("forward_selection needs a non-empty start set")
    best = _validation_fit(template, current, u_est, y_est, u_val, y_val, theta0)
    history = [(list(current), best)]
    pool = [c for c in candidates if c not in current]
    while pool and (max_terms is None or len(current) < max_terms):
        trials = [(t, _validation_fit(template, current + [t], u_est, y_est, u_val, y_val, theta0)) for t in pool]
        term, fit = max(trials, key=lambda tf: tf[1])
        if not fit > best:
            break
        current.append(term)
        pool.remove(term)
        best = fit
        history.append((list(current), best))
    return SelectionResult(current, best, history)
