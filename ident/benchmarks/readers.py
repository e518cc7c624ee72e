"""Readers for the standard files of the public nonlinear system-identification benchmarks (nonlinearbenchmark.org),
with their official estimation and test splits.

Nothing is downloaded: the user fetches the archives from nonlinearbenchmark.org and passes the path of a data file
(or of the folder that holds it). Only the Wiener-Hammerstein benchmark ships with this package
(``ident/data/benchmarks``, see its PROVENANCE.md), so :func:`read_wiener_hammerstein` needs no path.

Every reader returns a :class:`BenchmarkData`: the estimation and test records as :class:`~ident.dataset.IODataset`
(inputs ``u`` (N, 1), outputs ``y`` (N, 1), sample time ``dt``, names and units; ``meta`` says which file, which
variables and which samples), the sampling period and the split names. A file that is missing raises
``FileNotFoundError`` naming it; a file that is not in the expected format (not a MAT/CSV file, a variable or column
missing, non-numeric or non-finite values, a record too short for the official split) raises
:class:`BenchmarkFileError` naming the file and what is wrong.

The splits are those of the benchmarks' official data loader, the ``nonlinear_benchmarks`` Python package of Gerben
Beintema (github.com/GerbenBeintema/nonlinear_benchmarks, ``nonlinear_benchmarks/benchmarks.py``), which
nonlinearbenchmark.org names as its data loader; sample ranges below are 0-based, end exclusive, as in Python.
``initial_window`` is the number of samples at the start of each test record that the loader lets a model use to
set its initial state (its ``state_initialization_window_length``); report test errors after it.

==========================  ==============================  =========================================================
benchmark (reader)          file(s), variables              official split
==========================  ==============================  =========================================================
Silverbox                   ``SNLS80mV.mat`` (V1 input,     estimation: samples 40650 .. 40650 + 65062 (the first 75 %
(:func:`read_silverbox`)    V2 output, volts) or            of the multisine part 40650..127400); test:
                            ``SNLS80mV.csv`` (columns V1,   ``test_multisine`` (the remaining 25 %),
                            V2); fs = 10 MHz / 2^14         ``test_arrow_full`` (100..40575, the "arrow": a filtered
                            = 610.35 Hz                     noise of growing amplitude, which extrapolates beyond the
                                                            estimation amplitudes), ``test_arrow_no_extrapolation``
                                                            (its first 32000 samples); initial window 50
Wiener-Hammerstein          ``WienerHammerBenchMark.mat``   ``split="nonlinearbenchmark"`` (default, the loader's):
(:func:`read_wiener_        (uBenchMark, yBenchMark, fs)    samples 5200..184000, of which the first 100000 are the
hammerstein`)               or ``.csv`` (columns            estimation and the remaining 78800 the test record;
                            uBenchMark, yBenchMark, fs      initial window 50. ``split="sysid2009"``: the benchmark
                            optional); fs = 51200 Hz        description's 0..100000 estimation, 100000..188000 test
Cascaded Tanks              ``dataBenchmark.mat`` (uEst,    estimation: uEst/yEst (1024 samples); test: uVal/yVal
(:func:`read_cascaded_      yEst, uVal, yVal, Ts) or        (1024 samples); initial window 5. Input: pump voltage
tanks`)                     ``dataBenchmark.csv`` (same     (V), output: lower-tank level sensor (V); Ts = 4 s
                            column names)
Coupled electric drives     ``DATAUNIF.MAT`` (u11, z11;     two records of 500 samples (u11/z11 the lower input
(:func:`read_coupled_       u12, z12) or ``DATAUNIF.csv``   amplitude, u12/z12 the higher), each split at 400:
drives`)                    (same column names); Ts =       ``estimation_low``/``estimation_high`` the first 400,
                            20 ms                           ``test_low``/``test_high`` the last 100; initial window 4
EMPS                        ``DATA_EMPS.mat`` and           estimation: DATA_EMPS, test: DATA_EMPS_PULSES (whole
(:func:`read_emps`)         ``DATA_EMPS_PULSES.mat``        records); input vir (motor force, N), output qm (measured
                            (qm, vir, t, qg)                position, m); Ts from t; initial window 20
==========================  ==============================  =========================================================

References (cite the benchmark, not this reader):

* Silverbox, Coupled Electric Drives: T. Wigren and J. Schoukens, "Three free data sets for development and
  benchmarking in nonlinear system identification", European Control Conference 2013, pp. 2933-2938; T. Wigren and
  M. Schoukens, "Coupled electric drives data set and reference models", Technical Report 2017-024, Uppsala
  University, 2017.
* Wiener-Hammerstein: J. Schoukens, J. A. K. Suykens and L. Ljung, "Wiener-Hammerstein benchmark", 15th IFAC
  Symposium on System Identification (SYSID 2009), Saint-Malo.
* Cascaded Tanks: M. Schoukens, P. Mattson, T. Wigren and J.-P. Noel, "Cascaded tanks benchmark combining soft and
  hard nonlinearities", Workshop on Nonlinear System Identification Benchmarks, Brussels, 2016.
* EMPS: A. Janot, M. Gautier and M. Brunot, "Data set and reference models of EMPS", Workshop on Nonlinear System
  Identification Benchmarks, Eindhoven, 2019.
"""
from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from ident.dataset import IODataset

__all__ = [
    "BENCHMARK_READERS",
    "BenchmarkData",
    "BenchmarkFileError",
    "read_benchmark",
    "read_cascaded_tanks",
    "read_coupled_drives",
    "read_emps",
    "read_silverbox",
    "read_wiener_hammerstein",
]

#: Silverbox sampling frequency: 10 MHz / 2^14 (Wigren and Schoukens 2013), in Hz.
SILVERBOX_FS_HZ = 1.0e7 / 2**14
#: Wiener-Hammerstein benchmark sampling frequency (Schoukens, Suykens and Ljung 2009), in Hz.
WIENER_HAMMERSTEIN_FS_HZ = 51200.0
#: Coupled electric drives sampling period (Wigren and Schoukens 2017: 50 Hz), in s.
COUPLED_DRIVES_TS_S = 0.02


class BenchmarkFileError(ValueError):
    """A benchmark file exists but is not in the expected format (the message names the file and the problem)."""


@dataclass(frozen=True)
class BenchmarkData:
    """A public benchmark read from its files, with its official estimation and test splits.

    Attributes
    ----------
    name : str
        Short name (``"silverbox"``, ``"wiener_hammerstein"``, ``"cascaded_tanks"``, ``"coupled_drives"``,
        ``"emps"``).
    estimation, test : tuple of IODataset
        The estimation and the test records, in the order of ``estimation_names`` and ``test_names``. Each record's
        ``meta`` holds ``benchmark``, ``split``, ``role``, ``file``, ``variables`` and ``samples`` (start, stop of
        the 0-based, end-exclusive range of the source record).
    estimation_names, test_names : tuple of str
        The split names.
    sampling_period : float
        Sample time in seconds.
    initial_window : int
        Samples at the start of each test record the official protocol lets a model use to set its state.
    files : tuple of str
        The files read.
    reference : str
        The benchmark's citation.
    split_source : str
        Where the split is defined.
    """

    name: str
    estimation: tuple[IODataset, ...]
    test: tuple[IODataset, ...]
    estimation_names: tuple[str, ...]
    test_names: tuple[str, ...]
    sampling_period: float
    initial_window: int
    files: tuple[str, ...]
    reference: str
    split_source: str = "nonlinear_benchmarks (G. Beintema), nonlinear_benchmarks/benchmarks.py"
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def split_names(self) -> tuple[str, ...]:
        """Every split name, estimation first."""
        return self.estimation_names + self.test_names

    def __getitem__(self, split: str) -> IODataset:
        """The record of one split by name."""
        for names, records in ((self.estimation_names, self.estimation), (self.test_names, self.test)):
            if split in names:
                return records[names.index(split)]
        raise KeyError(f"{self.name} has no split {split!r}; splits: {list(self.split_names)}")

    def __repr__(self) -> str:
        parts = ", ".join(f"{n}: {len(r)}" for n, r in zip(self.split_names, self.estimation + self.test,
                                                           strict=True))
        return f"BenchmarkData({self.name!r}, Ts={self.sampling_period:g} s, {parts})"


# ------------------------------------------------------------------------------------------------ file access
def _resolve(path: str | Path, names: Sequence[str], benchmark: str) -> Path:
    """The data file: ``path`` itself, or the first of ``names`` (any case) inside the folder ``path`` or one of
    its sub-folders (the archives unpack into a folder of their own)."""
    p = Path(path).expanduser()
    if p.is_file():
        return p
    if p.is_dir():
        wanted = {n.lower() for n in names}
        for cand in sorted(p.rglob("*")):
            if cand.is_file() and cand.name.lower() in wanted:
                return cand
        raise FileNotFoundError(f"{p}: no {benchmark} data file in this folder (looked for {', '.join(names)})")
    raise FileNotFoundError(f"{p}: no such file or folder ({benchmark} data: {', '.join(names)})")


def _load(path: Path) -> dict[str, np.ndarray]:
    """Variables of a MATLAB v5 ``.mat`` file or the columns of a CSV file with a header row, as float arrays."""
    suffix = path.suffix.lower()
    if suffix == ".mat":
        from scipy.io import loadmat

        try:
            raw = loadmat(str(path))
        except NotImplementedError as err:   # MATLAB v7.3 (HDF5)
            raise BenchmarkFileError(f"{path}: a MATLAB v7.3 (HDF5) file, which this reader does not read; save it "
                                     f"as MATLAB v5 (save -v7) or CSV") from err
        except (ValueError, TypeError, OSError) as err:
            raise BenchmarkFileError(f"{path}: not a readable MATLAB .mat file ({err})") from err
        out = {}
        for k, v in raw.items():
            if k.startswith("__"):
                continue
            try:
                out[k] = np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                continue   # strings, structs: not signals
        return out
    if suffix in (".csv", ".txt"):
        return _load_csv(path)
    raise BenchmarkFileError(f"{path}: unknown file type {path.suffix!r} (expected .mat or .csv)")


def _load_csv(path: Path) -> dict[str, np.ndarray]:
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as err:
        raise BenchmarkFileError(f"{path}: not a readable text CSV file ({err})") from err
    rows = [r for r in rows if r and any(c.strip() for c in r)]
    if len(rows) < 2:
        raise BenchmarkFileError(f"{path}: a CSV file needs a header row and data rows, found {len(rows)} rows")
    header = [c.strip().strip('"') for c in rows[0]]
    cols: dict[str, list[float]] = {h: [] for h in header}
    for line, row in enumerate(rows[1:], start=2):
        if len(row) > len(header):
            raise BenchmarkFileError(f"{path}: line {line} has {len(row)} fields but the header has {len(header)}")
        for h, cell in zip(header, list(row) + [""] * (len(header) - len(row)), strict=True):
            cell = cell.strip()
            if not cell:
                cols[h].append(np.nan)   # a shorter column (e.g. Ts in the first row only)
                continue
            try:
                cols[h].append(float(cell))
            except ValueError as err:
                raise BenchmarkFileError(f"{path}: line {line}, column {h!r}: {cell!r} is not a number") from err
    return {h: np.asarray(v, dtype=float) for h, v in cols.items()}


def _signal(data: dict[str, np.ndarray], name: str, path: Path) -> np.ndarray:
    """Variable or column ``name`` as a 1-D signal; trailing empty CSV cells dropped; every value finite."""
    if name not in data:
        found = ", ".join(sorted(data)) or "none"
        raise BenchmarkFileError(f"{path}: variable {name!r} is missing (found: {found})")
    a = np.asarray(data[name], dtype=float)
    if a.ndim > 2 or (a.ndim == 2 and min(a.shape) != 1):
        raise BenchmarkFileError(f"{path}: variable {name!r} has shape {a.shape}, expected a vector")
    a = a.reshape(-1)
    last = np.flatnonzero(~np.isnan(a))
    a = a[:last[-1] + 1] if last.size else a[:0]
    if a.size == 0:
        raise BenchmarkFileError(f"{path}: variable {name!r} is empty")
    if not np.all(np.isfinite(a)):
        bad = int(np.argmax(~np.isfinite(a)))
        raise BenchmarkFileError(f"{path}: variable {name!r} holds a NaN, an empty cell or inf (first at sample "
                                 f"{bad})")
    return a


def _scalar(data: dict[str, np.ndarray], name: str, path: Path, default: float | None = None,
            unit: str = "s") -> float:
    """A positive scalar (a sampling period or frequency): the variable's first finite value, or ``default``."""
    if name not in data:
        if default is None:
            raise BenchmarkFileError(f"{path}: variable {name!r} is missing (found: {', '.join(sorted(data))})")
        return float(default)
    vals = np.asarray(data[name], dtype=float).reshape(-1)
    vals = vals[np.isfinite(vals)]
    if vals.size == 0 or not vals[0] > 0:
        raise BenchmarkFileError(f"{path}: {name!r} must hold a positive value in {unit}, got {data[name]!r}")
    return float(vals[0])


def _pair(data: dict[str, np.ndarray], u_name: str, y_name: str, path: Path) -> tuple[np.ndarray, np.ndarray]:
    u, y = _signal(data, u_name, path), _signal(data, y_name, path)
    if u.size != y.size:
        raise BenchmarkFileError(f"{path}: {u_name!r} has {u.size} samples but {y_name!r} has {y.size}")
    return u, y


def _need(n: int, stop: int, path: Path, what: str) -> None:
    if n < stop:
        raise BenchmarkFileError(f"{path}: {what} has {n} samples, but the official split needs {stop}")


def _record(benchmark: str, split: str, role: str, u: np.ndarray, y: np.ndarray, start: int, stop: int, dt: float,
            path: Path, variables: tuple[str, str], names: tuple[str, str], units: tuple[str, str]) -> IODataset:
    return IODataset(u=u[start:stop], y=y[start:stop], dt=dt, input_names=(names[0],), output_names=(names[1],),
                     input_units=(units[0],), output_units=(units[1],), t0=start * dt,
                     meta={"benchmark": benchmark, "split": split, "role": role, "file": str(path),
                           "variables": list(variables), "samples": [int(start), int(stop)]})


# ---------------------------------------------------------------------------------------------------- readers
def read_silverbox(path: str | Path) -> BenchmarkData:
    """The Silverbox (an electronic Duffing oscillator) from ``SNLS80mV.mat`` or ``SNLS80mV.csv`` (or a folder
    holding it, e.g. the unpacked ``SilverboxFiles``); splits in the module docstring."""
    p = _resolve(path, ("SNLS80mV.mat", "SNLS80mV.csv"), "Silverbox")
    data = _load(p)
    u, y = _pair(data, "V1", "V2", p)
    _need(u.size, 127400, p, "V1")
    dt = 1.0 / SILVERBOX_FS_HZ
    ms0, ms1 = 40650, 127400
    cut = ms0 + int((ms1 - ms0) * 0.75)
    kw = {"dt": dt, "path": p, "variables": ("V1", "V2"), "names": ("V1", "V2"), "units": ("V", "V")}
    est = _record("silverbox", "estimation", "estimation", u, y, ms0, cut, **kw)
    tests = (_record("silverbox", "test_multisine", "test", u, y, cut, ms1, **kw),
             _record("silverbox", "test_arrow_full", "test", u, y, 100, 40575, **kw),
             _record("silverbox", "test_arrow_no_extrapolation", "test", u, y, 100, 100 + 32000, **kw))
    return BenchmarkData("silverbox", (est,), tests, ("estimation",),
                         ("test_multisine", "test_arrow_full", "test_arrow_no_extrapolation"), dt, 50, (str(p),),
                         "T. Wigren and J. Schoukens, Three free data sets for development and benchmarking in "
                         "nonlinear system identification, ECC 2013, pp. 2933-2938")


def read_wiener_hammerstein(path: str | Path | None = None, split: str = "nonlinearbenchmark") -> BenchmarkData:
    """The Wiener-Hammerstein benchmark from ``WienerHammerBenchMark.mat`` or ``.csv`` (default: the copy shipped in
    ``ident/data/benchmarks``). ``split``: ``"nonlinearbenchmark"`` (the official loader's) or ``"sysid2009"`` (the
    benchmark description's); see the module docstring."""
    if split not in ("nonlinearbenchmark", "sysid2009"):
        raise ValueError(f"split must be 'nonlinearbenchmark' or 'sysid2009', got {split!r}")
    if path is None:
        path = Path(str(resources.files("ident") / "data" / "benchmarks" / "WienerHammerBenchMark.mat"))
    p = _resolve(path, ("WienerHammerBenchMark.mat", "WienerHammerBenchMark.csv", "WienerHammerBenchmark.csv"),
                 "Wiener-Hammerstein")
    data = _load(p)
    u, y = _pair(data, "uBenchMark", "yBenchMark", p)
    fs = _scalar(data, "fs", p, default=WIENER_HAMMERSTEIN_FS_HZ, unit="Hz")
    dt = 1.0 / fs
    if split == "nonlinearbenchmark":
        (e0, e1), (t0, t1), window, source = (5200, 105200), (105200, 184000), 50, \
            "nonlinear_benchmarks (G. Beintema), nonlinear_benchmarks/benchmarks.py"
    else:
        (e0, e1), (t0, t1), window, source = (0, 100000), (100000, 188000), 0, \
            "Schoukens, Suykens and Ljung, Wiener-Hammerstein benchmark, SYSID 2009"
    _need(u.size, t1, p, "uBenchMark")
    kw = {"dt": dt, "path": p, "variables": ("uBenchMark", "yBenchMark"), "names": ("u", "y"), "units": ("V", "V")}
    return BenchmarkData("wiener_hammerstein", (_record("wiener_hammerstein", "estimation", "estimation", u, y, e0, e1,
                                                        **kw),),
                         (_record("wiener_hammerstein", "test", "test", u, y, t0, t1, **kw),), ("estimation",),
                         ("test",), dt, window, (str(p),),
                         "J. Schoukens, J. A. K. Suykens and L. Ljung, Wiener-Hammerstein benchmark, SYSID 2009",
                         split_source=source, meta={"split": split})


def read_cascaded_tanks(path: str | Path) -> BenchmarkData:
    """The Cascaded Tanks from ``dataBenchmark.mat`` or ``dataBenchmark.csv`` (or a folder holding it, e.g. the
    unpacked ``CascadedTanksFiles``); splits in the module docstring."""
    p = _resolve(path, ("dataBenchmark.mat", "dataBenchmark.csv"), "Cascaded Tanks")
    data = _load(p)
    ue, ye = _pair(data, "uEst", "yEst", p)
    uv, yv = _pair(data, "uVal", "yVal", p)
    dt = _scalar(data, "Ts", p)
    kw = {"dt": dt, "path": p, "names": ("pump_voltage", "level"), "units": ("V", "V")}
    est = _record("cascaded_tanks", "estimation", "estimation", ue, ye, 0, ue.size, variables=("uEst", "yEst"), **kw)
    test = _record("cascaded_tanks", "test", "test", uv, yv, 0, uv.size, variables=("uVal", "yVal"), **kw)
    return BenchmarkData("cascaded_tanks", (est,), (test,), ("estimation",), ("test",), dt, 5, (str(p),),
                         "M. Schoukens, P. Mattson, T. Wigren and J.-P. Noel, Cascaded tanks benchmark combining soft "
                         "and hard nonlinearities, Workshop on Nonlinear System Identification Benchmarks, 2016")


def read_coupled_drives(path: str | Path) -> BenchmarkData:
    """The coupled electric drives from ``DATAUNIF.MAT`` or ``DATAUNIF.csv`` (or a folder holding it); the output is
    the pulley speed from a pulse counter that ignores the sign of the speed; splits in the module docstring."""
    p = _resolve(path, ("DATAUNIF.MAT", "DATAUNIF.csv"), "coupled electric drives")
    data = _load(p)
    dt = COUPLED_DRIVES_TS_S
    est, test = [], []
    for level, (un, yn) in (("low", ("u11", "z11")), ("high", ("u12", "z12"))):
        u, y = _pair(data, un, yn, p)
        _need(u.size, 401, p, un)
        kw = {"dt": dt, "path": p, "variables": (un, yn), "names": ("voltage", "speed"), "units": ("V", "")}
        est.append(_record("coupled_drives", f"estimation_{level}", "estimation", u, y, 0, 400, **kw))
        test.append(_record("coupled_drives", f"test_{level}", "test", u, y, 400, u.size, **kw))
    return BenchmarkData("coupled_drives", tuple(est), tuple(test), ("estimation_low", "estimation_high"),
                         ("test_low", "test_high"), dt, 4, (str(p),),
                         "T. Wigren and M. Schoukens, Coupled electric drives data set and reference models, "
                         "Technical Report 2017-024, Uppsala University, 2017")


def read_emps(path: str | Path) -> BenchmarkData:
    """The electro-mechanical positioning system from ``DATA_EMPS.mat`` (estimation) and ``DATA_EMPS_PULSES.mat``
    (test): ``path`` is a folder holding both, or the estimation file with the test file beside it. The system runs
    in closed loop (a position controller; input vir, the motor force in N, output qm, the position in m)."""
    p = Path(path).expanduser()
    est_path = _resolve(p, ("DATA_EMPS.mat",), "EMPS")
    test_path = _resolve(est_path.parent, ("DATA_EMPS_PULSES.mat",), "EMPS (test record)") if p.is_file() else \
        _resolve(p, ("DATA_EMPS_PULSES.mat",), "EMPS (test record)")
    records, dts = [], []
    for role, fp in (("estimation", est_path), ("test", test_path)):
        data = _load(fp)
        u, y = _pair(data, "vir", "qm", fp)
        t = _signal(data, "t", fp)
        if t.size != u.size or t.size < 2:
            raise BenchmarkFileError(f"{fp}: 't' has {t.size} samples but 'vir' has {u.size}")
        steps = np.diff(t)
        dt = float(np.median(steps))
        if not dt > 0 or np.max(np.abs(steps - dt)) > 1e-6 * dt + 1e-12:
            raise BenchmarkFileError(f"{fp}: the time vector 't' is not uniformly increasing")
        dts.append(dt)
        records.append(_record("emps", role, role, u, y, 0, u.size, dt, fp, ("vir", "qm"), ("force", "position"),
                               ("N", "m")))
    if abs(dts[0] - dts[1]) > 1e-9 * dts[0]:
        raise BenchmarkFileError(f"{test_path}: sampling period {dts[1]:g} s differs from {est_path}'s {dts[0]:g} s")
    return BenchmarkData("emps", (records[0],), (records[1],), ("estimation",), ("test",), dts[0], 20,
                         (str(est_path), str(test_path)),
                         "A. Janot, M. Gautier and M. Brunot, Data set and reference models of EMPS, Workshop on "
                         "Nonlinear System Identification Benchmarks, 2019")


#: Reader of each benchmark by short name.
BENCHMARK_READERS: dict[str, Callable[..., BenchmarkData]] = {
    "silverbox": read_silverbox,
    "wiener_hammerstein": read_wiener_hammerstein,
    "cascaded_tanks": read_cascaded_tanks,
    "coupled_drives": read_coupled_drives,
    "emps": read_emps,
}


def read_benchmark(name: str, path: str | Path | None = None, **options: Any) -> BenchmarkData:
    """Read benchmark ``name`` (a key of :data:`BENCHMARK_READERS`) from ``path`` (a file or a folder; optional for
    the shipped Wiener-Hammerstein benchmark); ``options`` go to the reader (``split`` for Wiener-Hammerstein)."""
    if name not in BENCHMARK_READERS:
        raise ValueError(f"unknown benchmark {name!r}; known: {sorted(BENCHMARK_READERS)}")
    if path is None:
        if name != "wiener_hammerstein":
            raise ValueError(f"the {name} benchmark does not ship with this package: give the path of its file "
                             "(download it from nonlinearbenchmark.org)")
        return read_wiener_hammerstein(**options)
    return BENCHMARK_READERS[name](path, **options)
