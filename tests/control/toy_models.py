"""Toy prediction models shared by the NonlinearMPC tests (tests are not a package: imported as ``toy_models``, as
``readme_snippets`` is)."""
from __future__ import annotations

import numpy as np

from control.models import IdentifiedModelAdapter
from ident.greybox import StorageGreyBox

#: an observation of the environment's base layout (flow, inlet T, engine-out NOx, NOx sensor, dose)
OBS = np.array([500.0, 550.0, 6.0, 30.0, 0.0], dtype=np.float32)


def toy_greybox_adapter() -> IdentifiedModelAdapter:
    """A two-cell grey-box storage model with zero parameters as an MPC prediction model (EKF on one output)."""
    m = StorageGreyBox.from_params(np.zeros(11), np.array([0.95, 1.0]), n_cells=2)
    return IdentifiedModelAdapter(m, np.zeros(4), np.ones(4), np.zeros(3), np.ones(3), measurement_noise=100.0,
                                  process_noise=np.array([1e-6, 1e-6, 0.5]),
                                  state_bounds=(np.array([0, 0, 250.0]), np.array([1, 1, 900.0])),
                                  initial_state=lambda obs: np.array([0.0, 0.0, obs[1]]))
