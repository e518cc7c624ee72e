"""Linear models: ARX, output-error (M-II), subspace (N4SID) and state-space PEM (M-I).

All share :class:`~ident.linear._statespace.LinearStateSpaceModel` (simulation, k-step prediction, initial-state
estimation, frequency response, CasADi export, JSON + NPZ saving).
"""
from ident.linear._statespace import LinearStateSpaceModel, simulate_ss
from ident.linear.arx import ARX
from ident.linear.oe import OutputError
from ident.linear.pem import StateSpacePEM
from ident.linear.statespace import StateSpaceModel
from ident.linear.subspace import N4SID

__all__ = [
           "ARX",
           "N4SID",
           "LinearStateSpaceModel",
           "OutputError",
           "StateSpaceModel",
           "StateSpacePEM",
           "simulate_ss",
]
