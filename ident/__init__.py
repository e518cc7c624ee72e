"""ident: system identification for the SCR dosing simulator (datasets, preprocessing, metrics, linear and
multiple-model identification; RPEM and Hammerstein-Wiener models in their own subpackages)."""
from ident.base import DynamicModel, NotFittedError
from ident.dataset import IODataset
from ident.excitation import GBN, PRBS, Multisine, RandomSteps, generate_multichannel
from ident.greybox import StorageGreyBox
from ident.io import load_model, register_model, save_model
from ident.linear import ARX, N4SID, OutputError, StateSpaceModel, StateSpacePEM
from ident.metrics import Comparison, compare, fit_percent, mse, nrmse, rms
from ident.multiple_model import MultipleModel, quantile_edges
from ident.preprocessing import Normalizer, arrhenius_transform, finite_difference, normalize_split
from ident.rpem import RecursivePEM

__all__ = [
    "ARX",
    "GBN",
    "N4SID",
    "PRBS",
    "Comparison",
    "DynamicModel",
    "IODataset",
    "MultipleModel",
    "Multisine",
    "Normalizer",
    "NotFittedError",
    "OutputError",
    "RandomSteps",
    "RecursivePEM",
    "StateSpaceModel",
    "StateSpacePEM",
    "StorageGreyBox",
    "arrhenius_transform",
    "compare",
    "finite_difference",
    "fit_percent",
    "generate_multichannel",
    "load_model",
    "mse",
    "normalize_split",
    "nrmse",
    "quantile_edges",
    "register_model",
    "rms",
    "save_model",
]
