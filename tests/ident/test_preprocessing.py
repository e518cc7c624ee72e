import numpy as np
import pytest

from ident.base import NotFittedError
from ident.dataset import IODataset
from ident.preprocessing import (
    Normalizer,
    add_input_derivatives,
    arrhenius_transform,
    finite_difference,
    inverse_arrhenius_transform,
    normalize_split,
    transform_temperature,
)


def test_normalizer_uses_estimation_statistics():
    rng = np.random.default_rng(0)
    est = rng.normal([5.0, 500.0], [2.0, 40.0], size=(900, 2))
    val = rng.normal([6.0, 520.0], [2.0, 40.0], size=(300, 2))
    nz = Normalizer().fit(est)
    z = nz.transform(est)
    np.testing.assert_allclose(z.mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(z.std(axis=0), 1.0, atol=1e-12)
    zv = nz.transform(val)
    np.testing.assert_allclose(zv, (val - est.mean(axis=0)) / est.std(axis=0))
    np.testing.assert_allclose(nz.inverse_transform(zv), val)


def test_normalizer_errors():
    x = np.column_stack([np.arange(10.0), np.full(10, 533.97)])
    with pytest.raises(ValueError, match="constant signal: temperature"):
        Normalizer(names=["nox", "temperature"]).fit(x)
    with pytest.raises(NotFittedError):
        Normalizer().transform(x)
    with pytest.raises(ValueError, match="NaN"):
        Normalizer().fit(np.array([[1.0], [np.nan], [2.0]]))


def test_from_stats_paper3_table1():
    nz = Normalizer.from_stats([0.325e-3, 533.97], [0.2667e-3, 48.130])
    np.testing.assert_allclose(nz.transform([[0.325e-3, 533.97 + 48.130]]), [[0.0, 1.0]])


def test_arrhenius_transform():
    t = np.array([450.0, 533.97, 650.0])
    v = arrhenius_transform(t)
    np.testing.assert_allclose(v, np.exp(-1e4 / t))
    np.testing.assert_allclose(inverse_arrhenius_transform(v), t)
    assert np.all(np.diff(v) > 0)
    with pytest.raises(ValueError, match="kelvin"):
        arrhenius_transform([-10.0, 300.0])


def test_finite_differences():
    dt = 0.5
    t = dt * np.arange(20)
    np.testing.assert_allclose(finite_difference(3.0 * t + 1.0, dt), 3.0)
    q = t**2
    d = finite_difference(q, dt, method="central")
    np.testing.assert_allclose(d[1:-1], 2 * t[1:-1])
    back = finite_difference(q, dt)
    np.testing.assert_allclose(back[1:], (q[1:] - q[:-1]) / dt)  # causal
    with pytest.raises(ValueError, match="method"):
        finite_difference(q, dt, method="spline")


def test_dataset_helpers():
    rng = np.random.default_rng(1)
    n = 100
    u = np.column_stack([rng.standard_normal(n), 500 + 30 * rng.standard_normal(n)])
    ds = IODataset(u=u, y=rng.standard_normal(n), dt=0.5, input_names=["urea", "T_in"], input_units=["g/s", "K"])
    d2 = add_input_derivatives(ds, ["urea"])
    assert d2.input_names == ("urea", "T_in", "urea_dot") and d2.input_units[-1] == "(g/s)/s"
    d3 = transform_temperature(ds, "T_in")
    np.testing.assert_allclose(d3.u[:, 1], np.exp(-1e4 / u[:, 1]))
    split = normalize_split(*ds.split(0.75))
    np.testing.assert_allclose(split.estimation.u.mean(axis=0), 0.0, atol=1e-12)
    np.testing.assert_allclose(split.input_normalizer.inverse_transform(split.validation.u), ds.u[75:])


def test_normalizer_argument_errors():
    x = np.column_stack([np.arange(10.0), np.full(10, 533.97)])
    # fewer names than columns: the constant column is still named, by position
    with pytest.raises(ValueError, match="constant signal: column 1"):
        Normalizer(names=["nox"]).fit(x)
    with pytest.raises(ValueError, match="^ddof must be"):
        Normalizer(ddof=10).fit(np.arange(20.0).reshape(10, 2))
    with pytest.raises(ValueError, match="^ddof must be"):
        Normalizer(ddof=0.5).fit(np.arange(20.0).reshape(10, 2))
    with pytest.raises(ValueError, match="positive sd"):
        Normalizer.from_stats([0.0], [np.nan])
    with pytest.raises(ValueError, match="positive sd"):
        Normalizer.from_stats([0.0, 1.0], [1.0])
    with pytest.raises(ValueError, match="^x has 1 samples"):
        Normalizer().fit(np.ones((1, 2)))
