"""Hammerstein-Wiener models (Paper IV's M-III..M-V): static input blocks, per-input transfer functions, a static
output block, fitted by simulation-error minimisation with an exact Jacobian from the best linear model."""
from ident.hammerstein_wiener.blocks import (
    Arrhenius,
    DeadZone,
    Identity,
    PiecewiseLinear,
    Polynomial,
    Saturation,
    StaticNonlinearity,
    block_from_dict,
)
from ident.hammerstein_wiener.estimator import HammersteinWiener, hammerstein, select_by_holdout, wiener

__all__ = [
    "Arrhenius",
    "DeadZone",
    "HammersteinWiener",
    "Identity",
    "PiecewiseLinear",
    "Polynomial",
    "Saturation",
    "StaticNonlinearity",
    "block_from_dict",
    "hammerstein",
    "select_by_holdout",
    "wiener",
]
