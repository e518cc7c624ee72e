"""ident.benchmarks.readers: each public benchmark's file format (MAT and CSV, written here as small or synthetic
files of the published layout), the official splits, the shipped Wiener-Hammerstein file, clear errors."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.io import loadmat, savemat

from ident.benchmarks import (
    BenchmarkFileError,
    read_benchmark,
    read_cascaded_tanks,
    read_coupled_drives,
    read_emps,
    read_silverbox,
    read_wiener_hammerstein,
)
from ident.dataset import IODataset


def _write_csv(path: Path, columns: dict[str, np.ndarray]) -> Path:
    n = max(len(v) for v in columns.values())
    with path.open("w") as fh:
        fh.write(",".join(columns) + "\n")
        for t in range(n):
            fh.write(",".join(repr(float(v[t])) if t < len(v) else "" for v in columns.values()) + "\n")
    return path


def test_shipped_wiener_hammerstein_with_the_official_split() -> None:
    raw = loadmat(str(Path(__file__).parents[2] / "ident" / "data" / "benchmarks" / "WienerHammerBenchMark.mat"))
    u, y = raw["uBenchMark"].ravel(), raw["yBenchMark"].ravel()
    b = read_wiener_hammerstein()
    assert b.name == "wiener_hammerstein" and b.split_names == ("estimation", "test")
    assert b.sampling_period == pytest.approx(1 / 51200) and b.initial_window == 50
    est, test = b["estimation"], b["test"]
    assert isinstance(est, IODataset) and len(est) == 100000 and len(test) == 78800
    np.testing.assert_array_equal(est.u[:, 0], u[5200:105200])
    np.testing.assert_array_equal(test.y[:, 0], y[105200:184000])
    assert est.meta["samples"] == [5200, 105200] and test.meta["role"] == "test"
    old = read_wiener_hammerstein(split="sysid2009")
    assert len(old.estimation[0]) == 100000 and len(old.test[0]) == 88000
    np.testing.assert_array_equal(old.test[0].u[:, 0], u[100000:])
    assert read_benchmark("wiener_hammerstein").split_names == b.split_names
    with pytest.raises(ValueError, match="split must be"):
        read_wiener_hammerstein(split="half")


def test_wiener_hammerstein_csv(tmp_path) -> None:
    n = 188000
    u, y = np.sin(np.arange(n) * 1e-3), np.cos(np.arange(n) * 1e-3)
    path = _write_csv(tmp_path / "WienerHammerBenchmark.csv", {"uBenchMark": u, "yBenchMark": y})
    b = read_wiener_hammerstein(tmp_path)   # a folder: the file is found inside
    assert b.sampling_period == pytest.approx(1 / 51200)   # no fs column: the benchmark's 51.2 kHz
    np.testing.assert_allclose(b.test[0].y[:, 0], y[105200:184000])
    assert b.files == (str(path),)


@pytest.mark.parametrize("fmt", ["mat", "csv"])
def test_silverbox_splits(tmp_path, fmt: str) -> None:
    n = 131072
    v1 = np.arange(n, dtype=float)
    v2 = -v1
    if fmt == "mat":   # the published file holds row vectors
        savemat(tmp_path / "SNLS80mV.mat", {"V1": v1[None, :], "V2": v2[None, :]})
    else:
        _write_csv(tmp_path / "SNLS80mV.csv", {"V1": v1, "V2": v2})
    b = read_silverbox(tmp_path / f"SNLS80mV.{fmt}")
    assert b.split_names == ("estimation", "test_multisine", "test_arrow_full", "test_arrow_no_extrapolation")
    assert b.sampling_period == pytest.approx(1 / 610.3515625) and b.initial_window == 50
    est = b["estimation"]
    assert est.u[0, 0] == 40650 and len(est) == 65062                      # first 75 % of 40650..127400
    assert b["test_multisine"].u[0, 0] == 40650 + 65062 and b["test_multisine"].u[-1, 0] == 127399
    assert b["test_arrow_full"].meta["samples"] == [100, 40575]
    assert len(b["test_arrow_no_extrapolation"]) == 32000
    np.testing.assert_array_equal(b["test_arrow_full"].y[:, 0], -v1[100:40575])
    with pytest.raises(KeyError, match="splits"):
        b["validation"]


@pytest.mark.parametrize("fmt", ["mat", "csv"])
def test_cascaded_tanks(tmp_path, fmt: str) -> None:
    rng = np.random.default_rng(0)
    d = {"uEst": rng.uniform(2, 8, 1024), "uVal": rng.uniform(2, 8, 1024), "yEst": rng.uniform(0, 10, 1024),
         "yVal": rng.uniform(0, 10, 1024)}
    if fmt == "mat":   # column vectors and a scalar Ts
        savemat(tmp_path / "dataBenchmark.mat", {**{k: v[:, None] for k, v in d.items()}, "Ts": 4.0})
    else:              # Ts in the first row only
        _write_csv(tmp_path / "dataBenchmark.csv", {**d, "Ts": np.array([4.0])})
    b = read_cascaded_tanks(tmp_path)
    assert b.sampling_period == 4.0 and b.initial_window == 5
    np.testing.assert_allclose(b.estimation[0].u[:, 0], d["uEst"])
    np.testing.assert_allclose(b.test[0].y[:, 0], d["yVal"])
    assert b.estimation[0].input_names == ("pump_voltage",) and b.test[0].meta["variables"] == ["uVal", "yVal"]


@pytest.mark.parametrize("fmt", ["mat", "csv"])
def test_coupled_drives(tmp_path, fmt: str) -> None:
    d = {k: np.arange(500, dtype=float) + 1000 * i for i, k in enumerate(("u11", "u12", "z11", "z12"))}
    if fmt == "mat":
        savemat(tmp_path / "DATAUNIF.MAT", {k: v[:, None] for k, v in d.items()})
    else:
        _write_csv(tmp_path / "DATAUNIF.csv", d)
    b = read_coupled_drives(tmp_path)
    assert b.split_names == ("estimation_low", "estimation_high", "test_low", "test_high")
    assert b.sampling_period == 0.02 and b.initial_window == 4
    assert len(b["estimation_low"]) == 400 and len(b["test_high"]) == 100
    np.testing.assert_array_equal(b["test_high"].y[:, 0], d["z12"][400:])
    np.testing.assert_array_equal(b["estimation_low"].u[:, 0], d["u11"][:400])


def test_emps(tmp_path) -> None:
    for name, n in (("DATA_EMPS.mat", 2000), ("DATA_EMPS_PULSES.mat", 1500)):
        t = np.arange(n) * 1e-3
        savemat(tmp_path / name, {"t": t[:, None], "qm": np.sin(t)[:, None], "vir": np.cos(t)[:, None],
                                  "qg": np.sin(t)[:, None]})
    for where in (tmp_path, tmp_path / "DATA_EMPS.mat"):
        b = read_emps(where)
        assert b.sampling_period == pytest.approx(1e-3) and b.initial_window == 20
        assert len(b.estimation[0]) == 2000 and len(b.test[0]) == 1500
        assert b.test[0].output_units == ("m",) and b.estimation[0].input_units == ("N",)
    (tmp_path / "DATA_EMPS_PULSES.mat").unlink()
    with pytest.raises(FileNotFoundError, match="DATA_EMPS_PULSES.mat"):
        read_emps(tmp_path)


def test_errors_name_the_file(tmp_path) -> None:
    with pytest.raises(FileNotFoundError, match="nowhere.mat"):
        read_silverbox(tmp_path / "nowhere.mat")
    with pytest.raises(FileNotFoundError, match="no Cascaded Tanks data file"):
        read_cascaded_tanks(tmp_path)
    bad = tmp_path / "dataBenchmark.mat"
    savemat(bad, {"uEst": np.ones((10, 1)), "yEst": np.ones((10, 1)), "uVal": np.ones((10, 1)), "Ts": 4.0})
    with pytest.raises(BenchmarkFileError, match=r"dataBenchmark.mat: variable 'yVal' is missing"):
        read_cascaded_tanks(bad)
    savemat(bad, {"uEst": np.ones((10, 1)), "yEst": np.ones((9, 1)), "uVal": np.ones((10, 1)),
                  "yVal": np.ones((10, 1)), "Ts": 4.0})
    with pytest.raises(BenchmarkFileError, match="'uEst' has 10 samples but 'yEst' has 9"):
        read_cascaded_tanks(bad)
    short = _write_csv(tmp_path / "DATAUNIF.csv", {k: np.ones(300) for k in ("u11", "u12", "z11", "z12")})
    with pytest.raises(BenchmarkFileError, match="DATAUNIF.csv: u11 has 300 samples, but the official split needs"):
        read_coupled_drives(short)
    text = tmp_path / "SNLS80mV.csv"
    text.write_text("V1,V2\n1.0,abc\n")
    with pytest.raises(BenchmarkFileError, match=r"SNLS80mV.csv: line 2, column 'V2': 'abc' is not a number"):
        read_silverbox(text)
    text.write_text("V1,V2\n1.0,2.0\n,3.0\n4.0,5.0\n")
    with pytest.raises(BenchmarkFileError, match="'V1' holds a NaN, an empty cell or inf"):
        read_silverbox(text)
    junk = tmp_path / "WienerHammerBenchMark.mat"
    junk.write_bytes(b"not a mat file at all" * 10)
    with pytest.raises(BenchmarkFileError, match="WienerHammerBenchMark.mat: not a readable MATLAB"):
        read_wiener_hammerstein(junk)
    with pytest.raises(BenchmarkFileError, match="unknown file type '.xlsx'"):
        other = tmp_path / "data.xlsx"
        other.write_bytes(b"x")
        read_silverbox(other)
    with pytest.raises(ValueError, match="does not ship"):
        read_benchmark("silverbox")
    with pytest.raises(ValueError, match="unknown benchmark"):
        read_benchmark("f16", tmp_path)
