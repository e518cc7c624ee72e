"""Recursive prediction error method (RPEM) on restricted black-box nonlinear ODE models (thesis Papers I-III)."""
from ident.rpem.estimator import AUTO_SETTINGS, OUTPUT_FUNCTIONS, R0_GRID, RecursivePEM
from ident.rpem.parametric import ParametricRPEM
from ident.rpem.regressors import (
    PAPER2_TERMS,
    SCR_PAPER3_LINEAR_TERMS,
    SCR_PAPER3_TERMS,
    parse_terms,
    polynomial_terms,
)
from ident.rpem.search import StructureSearch
from ident.rpem.selection import backward_elimination, forward_selection

__all__ = [
    "AUTO_SETTINGS",
    "OUTPUT_FUNCTIONS",
    "PAPER2_TERMS",
    "R0_GRID",
    "SCR_PAPER3_LINEAR_TERMS",
    "SCR_PAPER3_TERMS",
    "ParametricRPEM",
    "RecursivePEM",
    "StructureSearch",
    "backward_elimination",
    "forward_selection",
    "parse_terms",
    "polynomial_terms",
]
