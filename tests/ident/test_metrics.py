import numpy as np
import pytest

from ident.dataset import IODataset
from ident.linear import ARX, StateSpaceModel
from ident.metrics import compare, fit_percent, mse, nrmse


def system() -> StateSpaceModel:
    return StateSpaceModel(A=[[0.8, 0.2], [0.0, 0.5]], B=[[1.0], [0.5]], C=[[1.0, 0.0]])


def test_compare_perfect_model_and_x0():
    rng = np.random.default_rng(0)
    u = rng.standard_normal((200, 1))
    m = system()
    y = m.predict(u, x0=[3.0, -1.0])  # the record starts away from rest
    res = compare(m, u, y)
    assert res.fit == pytest.approx(100.0, abs=1e-6)
    assert res.mse == pytest.approx(0.0, abs=1e-12)
    zero = compare(m, u, y, initial="zero")
    assert zero.fit < 100.0
    assert set(res.as_dict()) == {"fit", "mse", "nrmse", "k"}


def test_compare_definitions_and_dataset():
    rng = np.random.default_rng(1)
    u = rng.standard_normal((300, 1))
    y = system().predict(u) + 0.1 * rng.standard_normal((300, 1))
    ds = IODataset(u=u, y=y, dt=0.5)
    m = ARX(2, 2, 1).fit(u, y)
    res = compare(m, ds)
    yh = m.predict(u, y0=y)
    assert res.fit == pytest.approx(fit_percent(y, yh))
    assert res.mse == pytest.approx(mse(y, yh))
    assert res.nrmse == pytest.approx(nrmse(y, yh))
    assert res.fit == pytest.approx(100 * (1 - np.linalg.norm(y - yh) / np.linalg.norm(y - y.mean())))


def test_compare_k_step_between_one_step_and_simulation():
    rng = np.random.default_rng(2)
    u = rng.standard_normal((500, 1))
    e = 0.3 * rng.standard_normal(500)
    y = np.zeros(500)
    for t in range(2, 500):  # ARX data: equation noise, so one-step prediction beats simulation
        y[t] = 1.2 * y[t - 1] - 0.5 * y[t - 2] + u[t - 1, 0] + e[t]
    m = ARX(2, 1, 1).fit(u, y)
    f1, f5, fs = (compare(m, u, y, k=k).fit for k in (1, 5, None))
    assert f1 > f5 > fs - 1.0
    with pytest.raises(ValueError, match="k must be"):
        compare(m, u, y, k=0)
