"""Hammerstein-Wiener models (Paper IV's M-III..M-V, one or several outputs): static input blocks, transfer
functions per (output, input) pair, static output blocks, fitted by simulation-error minimisation with an exact
Jacobian from the best linear model, a data-driven start or random restarts."""
from ident.hammerstein_wiener.blocks import (
    AbsoluteValue,
    Arrhenius,
    DeadZone,
    EvenPolynomial,
    Identity,
    OddPolynomial,
    PiecewiseLinear,
    Polynomial,
    Saturation,
    StaticNonlinearity,
    block_from_dict,
)
from ident.hammerstein_wiener.estimator import HammersteinWiener, hammerstein, select_by_holdout, wiener

__all__ = [
    "AbsoluteValue",
    "Arrhenius",
    "DeadZone",
    "EvenPolynomial",
    "HammersteinWiener",
    "Identity",
    "OddPolynomial",
    "PiecewiseLinear",
    "Polynomial",
    "Saturation",
    "StaticNonlinearity",
    "block_from_dict",
    "hammerstein",
    "select_by_holdout",
    "wiener",
]
