import numpy as np
import pytest

from ident.dataset import IODataset


def make(n: int = 40) -> IODataset:
    rng = np.random.default_rng(0)
    return IODataset(u=rng.standard_normal((n, 2)), y=rng.standard_normal((n, 1)) * 1e-3, dt=0.5,
                     input_names=["urea", "temperature"], output_names=["nox"], input_units=["g/s", "K"],
                     output_units=["ppm"], meta={"cycle": "WHTC", "seed": 3})


def test_shapes_and_time():
    ds = make()
    assert (ds.n_samples, ds.n_inputs, ds.n_outputs) == (40, 2, 1)
    assert len(ds) == 40
    np.testing.assert_allclose(ds.time[:3], [0.0, 0.5, 1.0])


def test_slicing_keeps_time_and_units():
    ds = make()
    part = ds[10:20]
    assert part.n_samples == 10
    assert part.t0 == pytest.approx(5.0)
    np.testing.assert_array_equal(part.u, ds.u[10:20])
    assert part.input_units == ds.input_units
    dec = ds[::2]
    assert dec.dt == pytest.approx(1.0) and dec.n_samples == 20
    with pytest.raises(ValueError, match="empty"):
        ds[30:10]


def test_split_fraction_and_index():
    ds = make(1200)
    est, val = ds.split(0.75)
    assert (est.n_samples, val.n_samples) == (900, 300)
    assert val.t0 == pytest.approx(450.0)
    est2, val2 = ds.split(index=900)
    assert est2 == est and val2 == val
    with pytest.raises(ValueError):
        ds.split(1.5)
    with pytest.raises(ValueError):
        ds.split(0.5, index=3)


def test_select_by_name():
    ds = make()
    sub = ds.select(inputs=["temperature"])
    assert sub.input_names == ("temperature",)
    np.testing.assert_array_equal(sub.u[:, 0], ds.u[:, 1])


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_round_trip(tmp_path, suffix):
    ds = make()[5:25]
    path = ds.save(tmp_path / f"data{suffix}")
    back = IODataset.load(path)
    assert back == ds
    np.testing.assert_array_equal(back.u, ds.u)  # exact, not approximate


def test_csv_is_readable_as_plain_csv(tmp_path):
    ds = make()
    path = ds.to_csv(tmp_path / "d.csv")
    data = np.loadtxt(path, delimiter=",", skiprows=2)
    np.testing.assert_array_equal(data[:, 1:3], ds.u)


def test_bad_data():
    u = np.ones((10, 1))
    with pytest.raises(ValueError, match="NaN"):
        IODataset(u=np.r_[u[:-1], [[np.nan]]], y=u, dt=1.0)
    with pytest.raises(ValueError, match="mismatched lengths"):
        IODataset(u=u, y=u[:5], dt=1.0)
    with pytest.raises(ValueError, match="dt"):
        IODataset(u=u, y=u, dt=0.0)
    with pytest.raises(ValueError, match="unique"):
        IODataset(u=u, y=u, dt=1.0, input_names=["a"], output_names=["a"])
    with pytest.raises(ValueError, match="file type"):
        IODataset(u=u, y=u, dt=1.0).save("x.txt")


def test_bad_time_arguments_are_named():
    u = np.ones((10, 1))
    with pytest.raises(ValueError, match="^dt must be a positive sample time.*'a'"):
        IODataset(u=u, y=u, dt="a")
    with pytest.raises(ValueError, match="^dt must be"):
        IODataset(u=u, y=u, dt=np.inf)
    with pytest.raises(ValueError, match="^t0 must be a finite time"):
        IODataset(u=u, y=u, dt=1.0, t0=np.nan)
    with pytest.raises(ValueError, match="^t0 must be a finite time"):
        IODataset(u=u, y=u, dt=1.0, t0="later")
    with pytest.raises(ValueError, match="^u has 0 samples"):
        IODataset(u=np.zeros((0, 1)), y=np.zeros((0, 1)), dt=1.0)
    with pytest.raises(ValueError, match="^y must be a 1-D or 2-D"):
        IODataset(u=u, y=np.ones((10, 1, 1)), dt=1.0)
    # a data set may hold constant signals (a step test at fixed flow); estimators decide whether they can use them
    assert IODataset(u=u, y=np.zeros(10), dt=1.0).n_samples == 10
