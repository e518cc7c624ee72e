"""Input-output data sets for identification: :class:`IODataset`.

A data set is a uniformly sampled multi-input multi-output record: inputs ``u`` of shape ``(n_samples, n_inputs)``,
outputs ``y`` of shape ``(n_samples, n_outputs)``, the sample time ``dt`` in seconds, and one name and one unit per
signal. It slices like an array along time, splits into estimation and validation parts, and saves to CSV or NPZ
(open formats; never pickle).

CSV layout (readable by any CSV tool, e.g. ``pandas.read_csv(path, comment="#")``)::

    # {"format": "ident.IODataset", "version": 1, "dt": 0.5, "inputs": [...], "outputs": [...], ...}
    time_s,inlet_nox,urea,...,tailpipe_nox
    0,...

The first line holds the metadata as JSON after ``# ``; the header row lists ``time_s`` and then the inputs and
outputs in order; values are written with 17 significant digits so a round trip is exact.
"""
from __future__ import annotations

import io
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ident.base import as_2d, check_same_length
from ident.io import atomic_write_bytes

_FORMAT = "ident.IODataset"
_VERSION = 1


def _names(given: Sequence[str] | None, prefix: str, n: int, what: str) -> tuple[str, ...]:
    if given is None:
        return tuple(f"{prefix}{i + 1}" for i in range(n))
    names = tuple(str(s) for s in given)
    if len(names) != n:
        raise ValueError(f"{what} has {len(names)} entries but the data have {n} columns")
    return names


def _as_float(value: Any) -> float:
    """``float(value)``, or NaN if it is not a number (so the caller's message names the argument)."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return float("nan")


@dataclass(frozen=True, eq=False)  # own __eq__: fields hold arrays
class IODataset:
    """A uniformly sampled MIMO input-output record.

    Parameters
    ----------
    u : array_like, shape (n_samples, n_inputs) or (n_samples,)
        Input signals, in the units given by ``input_units``.
    y : array_like, shape (n_samples, n_outputs) or (n_samples,)
        Output signals, in the units given by ``output_units``.
    dt : float
        Sample time in seconds (> 0).
    input_names, output_names : sequence of str, optional
        Signal names (default ``u1, u2, ...`` and ``y1, y2, ...``); must be unique across inputs and outputs.
    input_units, output_units : sequence of str, optional
        Units of each signal (default ``""``, i.e. unknown or dimensionless).
    t0 : float
        Time of the first sample in seconds (kept through slicing so plots line up).
    meta : dict
        Free JSON-serialisable metadata (e.g. cycle name, seed, base policy).

    Raises
    ------
    ValueError
        NaN/inf values, mismatched lengths, a non-positive or non-finite ``dt``, a non-finite ``t0``, or
        wrong/duplicate names.
    """

    u: np.ndarray
    y: np.ndarray
    dt: float
    input_names: tuple[str, ...] | None = None
    output_names: tuple[str, ...] | None = None
    input_units: tuple[str, ...] | None = None
    output_units: tuple[str, ...] | None = None
    t0: float = 0.0
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        u = as_2d("u", self.u)
        y = as_2d("y", self.y)
        check_same_length(u=u, y=y)
        dt, t0 = _as_float(self.dt), _as_float(self.t0)
        if not np.isfinite(dt) or dt <= 0:
            raise ValueError(f"dt must be a positive sample time in seconds, got {self.dt!r}")
        if not np.isfinite(t0):
            raise ValueError(f"t0 must be a finite time in seconds, got {self.t0!r}")
        inames = _names(self.input_names, "u", u.shape[1], "input_names")
        onames = _names(self.output_names, "y", y.shape[1], "output_names")
        all_names = inames + onames
        if len(set(all_names)) != len(all_names) or "time_s" in all_names:
            raise ValueError(f"signal names must be unique and not 'time_s', got {list(all_names)}")
        iunits = _names(self.input_units or [""] * u.shape[1], "", u.shape[1], "input_units")
        ounits = _names(self.output_units or [""] * y.shape[1], "", y.shape[1], "output_units")
        u.setflags(write=False)
        y.setflags(write=False)
        # frozen dataclass: object.__setattr__ is the documented way to normalise fields in __post_init__
        for k, v in {"u": u, "y": y, "dt": dt, "input_names": inames, "output_names": onames, "input_units": iunits,
                         "output_units": ounits, "t0": t0, "meta": dict(self.meta)}.items():
            object.__setattr__(self, k, v)

    # ----------------------------------------------------------------------------------------------- shape
    @property
    def n_samples(self) -> int:
        """Number of samples."""
        return self.u.shape[0]

    @property
    def n_inputs(self) -> int:
        """Number of input signals."""
        return self.u.shape[1]

    @property
    def n_outputs(self) -> int:
        """Number of output signals."""
        return self.y.shape[1]

    @property
    def time(self) -> np.ndarray:
        """Sample times in seconds, shape (n_samples,)."""
        return self.t0 + self.dt * np.arange(self.n_samples)

    def __len__(self) -> int:
        return self.n_samples

    def __repr__(self) -> str:
        return (f"IODataset(n_samples={self.n_samples}, dt={self.dt} s, inputs={list(self.input_names)}, "
                f"outputs={list(self.output_names)})")

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, IODataset):
            return NotImplemented
        return (np.array_equal(self.u, other.u) and np.array_equal(self.y, other.y) and self.dt == other.dt
                and self.input_names == other.input_names and self.output_names == other.output_names
                and self.input_units == other.input_units and self.output_units == other.output_units
                and self.t0 == other.t0 and self.meta == other.meta)

    __hash__ = None  # type: ignore[assignment]  # equality by value of arrays: not hashable

    # ----------------------------------------------------------------------------------------- slicing
    def _replace(self, **changes: Any) -> IODataset:
        kw = {"u": self.u, "y": self.y, "dt": self.dt, "input_names": self.input_names,
              "output_names": self.output_names,
                  "input_units": self.input_units, "output_units": self.output_units, "t0": self.t0, "meta": self.meta}
        kw.update(changes)
        return IODataset(**kw)

    def __getitem__(self, index: slice | int) -> IODataset:
        """Time slice. Only contiguous slices with step 1 keep a uniform sample time; a step ``k`` > 1 decimates
        without filtering and multiplies ``dt`` by ``k``."""
        if isinstance(index, (int, np.integer)):
            index = slice(int(index), int(index) + 1 if int(index) != -1 else None)
        if not isinstance(index, slice):
            raise TypeError("IODataset supports time slices only, e.g. ds[100:400]")
        start, stop, step = index.indices(self.n_samples)
        if step <= 0:
            raise ValueError("slice step must be positive")
        if stop <= start:
            raise ValueError(f"slice {index} of a data set with {self.n_samples} samples is empty")
        return self._replace(u=self.u[start:stop:step], y=self.y[start:stop:step], dt=self.dt * step,
                             t0=self.t0 + start * self.dt)

    def split(self, fraction: float | None = None, *, index: int | None = None) -> tuple[IODataset, IODataset]:
        """Split into (estimation, validation) parts at a sample index or a fraction of the length.

        Parameters
        ----------
        fraction : float, optional
            Fraction of samples in the estimation part, 0 < fraction < 1 (e.g. 0.75 gives Paper IV's 900/300).
        index : int, optional
            First sample of the validation part (exclusive end of the estimation part). Give exactly one of
            ``fraction`` and ``index``.
        """
        if (fraction is None) == (index is None):
            raise ValueError("give exactly one of fraction and index")
        if fraction is not None:
            if not 0.0 < fraction < 1.0:
                raise ValueError(f"fraction must be in (0, 1), got {fraction}")
            index = round(fraction * self.n_samples)
        assert index is not None
        if index < 0:
            index += self.n_samples
        if not 0 < index < self.n_samples:
            raise ValueError(f"split index {index} leaves an empty part (n_samples = {self.n_samples})")
        return self[:index], self[index:]

    def select(self, inputs: Sequence[int | str] | None = None,
               outputs: Sequence[int | str] | None = None) -> IODataset:
        """A data set with a subset of the signals, by position or name (e.g. one output for a MISO model)."""
        def idx(sel: Sequence[int | str] | None, names: tuple[str, ...], what: str) -> list[int]:
            if sel is None:
                return list(range(len(names)))
            out = []
            for s in sel:
                if isinstance(s, str):
                    if s not in names:
                        raise ValueError(f"no {what} named {s!r}; have {list(names)}")
                    out.append(names.index(s))
                else:
                    out.append(int(s))
            return out
        ii = idx(inputs, self.input_names, "input")
        oo = idx(outputs, self.output_names, "output")
        return self._replace(u=self.u[:, ii], y=self.y[:, oo],
                             input_names=[self.input_names[i] for i in ii],
                             output_names=[self.output_names[i] for i in oo],
                             input_units=[self.input_units[i] for i in ii],
                             output_units=[self.output_units[i] for i in oo])

    def with_signals(self, u: np.ndarray | None = None, y: np.ndarray | None = None, **changes: Any) -> IODataset:
        """A copy with replaced signal arrays (same shape unless names are changed too) or other fields."""
        kw: dict[str, Any] = dict(changes)
        if u is not None:
            kw["u"] = u
        if y is not None:
            kw["y"] = y
        return self._replace(**kw)

    # ------------------------------------------------------------------------------------------ saving
    def _meta_json(self) -> dict[str, Any]:
        return {"format": _FORMAT, "version": _VERSION, "dt": self.dt, "t0": self.t0,
                "inputs": list(self.input_names), "outputs": list(self.output_names),
                "input_units": list(self.input_units), "output_units": list(self.output_units),
                "meta": self.meta}

    def to_csv(self, path: str | Path) -> Path:
        """Write the data set as CSV with a JSON metadata comment line (see module docstring)."""
        path = Path(path)
        header = ",".join(("time_s",) + self.input_names + self.output_names)
        data = np.column_stack([self.time, self.u, self.y])
        buf = io.StringIO()
        buf.write("# " + json.dumps(self._meta_json()) + "\n")
        buf.write(header + "\n")
        np.savetxt(buf, data, delimiter=",", fmt="%.17g")
        atomic_write_bytes(path, buf.getvalue().encode("utf-8"))  # a failed write leaves the old file
        return path

    @classmethod
    def from_csv(cls, path: str | Path) -> IODataset:
        """Read a data set written by :meth:`to_csv`."""
        path = Path(path)
        with path.open("r", encoding="utf-8") as fh:
            first = fh.readline()
            if not first.startswith("# "):
                raise ValueError(f"{path} has no '# {{...}}' metadata line: not an IODataset CSV")
            meta = json.loads(first[2:])
            header = fh.readline().strip().split(",")
            data = np.loadtxt(fh, delimiter=",", ndmin=2)
        ni, no = len(meta["inputs"]), len(meta["outputs"])
        if header != ["time_s"] + meta["inputs"] + meta["outputs"] or data.shape[1] != 1 + ni + no:
            raise ValueError(f"{path}: header does not match the metadata line")
        return cls._from_meta(meta, data[:, 1:1 + ni], data[:, 1 + ni:])

    @classmethod
    def _from_meta(cls, meta: dict[str, Any], u: np.ndarray, y: np.ndarray) -> IODataset:
        if meta.get("format") != _FORMAT:
            raise ValueError(f"not an IODataset file (format = {meta.get('format')!r})")
        return cls(u=u, y=y, dt=meta["dt"], input_names=meta["inputs"], output_names=meta["outputs"],
                   input_units=meta["input_units"], output_units=meta["output_units"], t0=meta.get("t0", 0.0),
                   meta=meta.get("meta", {}))

    def to_npz(self, path: str | Path) -> Path:
        """Write the data set as NPZ: arrays ``u``, ``y`` and the metadata as a JSON string (no pickled objects)."""
        path = Path(path)
        buf = io.BytesIO()
        np.savez_compressed(buf, u=self.u, y=self.y, meta_json=np.array(json.dumps(self._meta_json())))
        atomic_write_bytes(path, buf.getvalue())  # a failed write leaves the old file
        return path

    @classmethod
    def from_npz(cls, path: str | Path) -> IODataset:
        """Read a data set written by :meth:`to_npz` (``allow_pickle=False``)."""
        with np.load(Path(path), allow_pickle=False) as z:
            meta = json.loads(str(z["meta_json"]))
            return cls._from_meta(meta, z["u"], z["y"])

    def save(self, path: str | Path) -> Path:
        """Save as CSV or NPZ according to the file suffix (``.csv`` or ``.npz``)."""
        suffix = Path(path).suffix.lower()
        if suffix == ".csv":
            return self.to_csv(path)
        if suffix == ".npz":
            return self.to_npz(path)
        raise ValueError(f"unknown data set file type {suffix!r}: use .csv or .npz")

    @classmethod
    def load(cls, path: str | Path) -> IODataset:
        """Load a CSV or NPZ file written by :meth:`save`."""
        suffix = Path(path).suffix.lower()
        if suffix == ".csv":
            return cls.from_csv(path)
        if suffix == ".npz":
            return cls.from_npz(path)
        raise ValueError(f"unknown data set file type {suffix!r}: use .csv or .npz")
