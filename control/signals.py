"""How an identified model's signals relate to the controller's physical ones: the input map and the normalisation.

An identified model of :mod:`ident` works on the signals of its identification data, normalised as
``z = (x - mean) / scale`` (:class:`ident.preprocessing.Normalizer`). The NMPC's model adapter
(:class:`control.models.IdentifiedModelAdapter`) and the state estimator
(:class:`control.estimation.ObservationEKF`) both translate between those and the physical signals of the loop --
the AdBlue dose [g/s] and the measured engine-out disturbance ``d = (flow mol/s, inlet T K, NOx ppm, NO2 fraction)``
-- through one :class:`ModelSignals`.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from scr_env.constants import ADBLUE_UREA_MASS_FRACTION, SECONDS_PER_MINUTE

__all__ = ["ModelSignals", "plant_data_inputs", "urea_g_min"]


def urea_g_min(adblue_g_s: Any) -> Any:
    """Urea [g/min] in an AdBlue dose [g/s] (floats, numpy arrays or CasADi symbols).

    The factor is :data:`scr_env.constants.UREA_G_MIN_PER_ADBLUE_G_S`; it is applied as two products (seconds per
    minute, then the urea mass fraction), the arithmetic the benchmarked controllers were calibrated with (one
    product by 19.5 rounds differently in the last bit for about a third of the doses)."""
    return adblue_g_s * SECONDS_PER_MINUTE * ADBLUE_UREA_MASS_FRACTION


def plant_data_inputs(adblue_g_s: Any, d: Any) -> list:
    """Physical inputs of :mod:`ident.plant_data` models from the dose [g/s] and the disturbance ``d``: inlet NOx
    ppm, urea g/min (:func:`urea_g_min`), inlet temperature K, exhaust flow mol/s."""
    return [d[2], urea_g_min(adblue_g_s), d[1], d[0]]


@dataclass(frozen=True)
class ModelSignals:
    """The signals of an identified model (module docstring).

    Parameters
    ----------
    input_mean, input_scale, output_mean, output_scale : normalisation of the identification data
        (``Normalizer.mean_`` / ``scale_``); zeros and ones for a model on physical signals (the grey-box).
    input_map : ``f(adblue_g_s, d) -> list`` of the model's physical inputs (works on CasADi symbols and floats);
        default :func:`plant_data_inputs`.
    """

    input_mean: Sequence[float]
    input_scale: Sequence[float]
    output_mean: Sequence[float]
    output_scale: Sequence[float]
    input_map: Callable[[Any, Any], list] | None = None

    def __post_init__(self) -> None:
        for name in ("input_mean", "input_scale", "output_mean", "output_scale"):
            a = np.asarray(getattr(self, name), dtype=float).ravel()
            if a.size == 0 or not np.all(np.isfinite(a)):
                raise ValueError(f"{name} must be finite numbers, got {getattr(self, name)!r}")
            if name.endswith("scale") and np.any(a == 0.0):
                raise ValueError(f"{name} must not contain zeros (it divides the signals), got {a.tolist()}")
            object.__setattr__(self, name, a)
        if len(self.input_mean) != len(self.input_scale):
            raise ValueError(f"input_mean and input_scale differ in length ({len(self.input_mean)} and "
                             f"{len(self.input_scale)})")
        if len(self.output_mean) != len(self.output_scale):
            raise ValueError(f"output_mean and output_scale differ in length ({len(self.output_mean)} and "
                             f"{len(self.output_scale)})")

    @classmethod
    def physical(cls, n_inputs: int = 4, n_outputs: int = 3,
                 input_map: Callable[[Any, Any], list] | None = None) -> ModelSignals:
        """No normalisation (mean 0, scale 1): a model identified on physical signals."""
        return cls(np.zeros(n_inputs), np.ones(n_inputs), np.zeros(n_outputs), np.ones(n_outputs), input_map)

    @property
    def n_inputs(self) -> int:
        return len(self.input_mean)

    def inputs(self, adblue_g_s: Any, d: Any) -> list:
        """The model's normalised inputs from the dose [g/s] and the disturbance ``d`` (symbols or numbers)."""
        phys = (self.input_map or plant_data_inputs)(adblue_g_s, d)
        return [(phys[i] - self.input_mean[i]) / self.input_scale[i] for i in range(len(phys))]

    def output_to_physical(self, value: Any, index: int) -> Any:
        """Model output ``index`` in physical units."""
        return value * self.output_scale[index] + self.output_mean[index]

    def output_to_model(self, value: Any, index: int) -> Any:
        """A physical reading of model output ``index`` in the model's normalised units."""
        return (value - self.output_mean[index]) / self.output_scale[index]
