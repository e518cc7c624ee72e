"""Saving and loading identified models: one open format (JSON + NPZ, never pickle), one loader for every model
class, one error type (:class:`ModelFileError`) for any bad file.

A saved model is two files side by side::

    <name>.json                 format version, kind, module, constructor parameters and small learned values,
                                the arrays' names, shapes and dtypes, and the SHA-256 of the arrays file
    <name>.<sha256[:16]>.npz    the learned arrays (numbers only, read with ``allow_pickle=False``)

Writes are atomic: the arrays file gets a new, content-addressed name, each file is written to a temporary file in
the same folder, flushed to disk and renamed into place (``os.replace``), the arrays file first, the JSON last. An
interrupted save (a crash, a full disk, an exception between the two writes) therefore leaves either the old pair or
the new pair, never a mixture: the JSON names exactly the arrays file it was written with, and that file's hash is
checked on load. The old arrays file is deleted only after the new JSON is in place.

Loading checks, before any model code sees the data, and raises :class:`ModelFileError` naming the file:

* the JSON is valid UTF-8 JSON, at most :data:`MAX_JSON_BYTES`, an object with the keys ``format_version``,
  ``kind``, ``meta`` and ``arrays_file``; the format version is one this code reads (:data:`READABLE_VERSIONS`);
* ``arrays_file`` is a plain file name in the JSON's folder (no path: ``../x.npz`` or ``/tmp/x.npz`` are refused);
* the arrays file has the recorded SHA-256, holds exactly the recorded arrays with the recorded shapes and dtypes,
  at most :data:`MAX_ARRAY_BYTES` in all, every array real and numeric (no object, string or complex arrays) and every
  float finite (no NaN or inf);
* then the model class rebuilds itself (``_from_state``) and checks every array's shape against its own structure
  (an RPEM file with one term too many, or a ``theta`` one entry short, is refused); any error it raises is reported
  as a :class:`ModelFileError` naming the file.

Format version 1 (written before the hash and the array table existed, arrays in ``<name>.npz``) is still read,
with every check but the hash and the table.

Registering a model family takes one decorator (the class derives from :class:`ident.base.BaseEstimator`, which
gives ``save``/``load``)::

    @register_model("rpem")
    class RecursivePEM(BaseEstimator):
        def _get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
            ...   # (JSON-serialisable dict, arrays by name); raise NotFittedError if not fitted

        @classmethod
        def _from_state(cls, meta: dict, arrays: dict[str, np.ndarray]) -> "RecursivePEM":
            ...   # rebuild; raise ValueError on anything inconsistent

The class's module is recorded in the JSON, so :func:`load_model` imports it (only modules inside the ``ident``
package) if the kind is not registered yet: ``load_model(path)`` works in a fresh process without importing the
family first.
"""
from __future__ import annotations

import contextlib
import hashlib
import importlib
import io
import json
import os
import tempfile
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

__all__ = [
    "FORMAT_VERSION",
    "ModelFileError",
    "atomic_write_bytes",
    "load_model",
    "register_model",
    "registered_kinds",
    "save_model",
]

#: Version written by :func:`save_model`.
FORMAT_VERSION = 2
#: Versions :func:`load_model` reads.
READABLE_VERSIONS = (1, 2)
#: Largest JSON file read (bytes): model metadata is small; a larger file is not a model.
MAX_JSON_BYTES = 64 * 2**20
#: Largest total size of the arrays of one model (bytes, uncompressed).
MAX_ARRAY_BYTES = 2 * 2**30
_FORMAT = "ident.model"
_REGISTRY: dict[str, type] = {}
#: Where the built-in kinds live (used when a file's recorded module is missing or moved).
_BUILTIN_MODULES = ("ident.rpem.estimator", "ident.linear", "ident.multiple_model", "ident.greybox",
                    "ident.hammerstein_wiener", "ident.stack")
T = TypeVar("T", bound=type)


class ModelFileError(ValueError):
    """A model file that cannot be loaded: damaged, tampered, of an unknown format version or kind, or holding
    another class than asked for. The message names the file."""


def register_model(kind: str) -> Callable[[T], T]:
    """Class decorator: make ``load_model`` rebuild files whose ``"kind"`` is ``kind`` with this class.

    The class needs ``_get_state(self) -> (meta: dict, arrays: dict[str, ndarray])`` and the classmethod
    ``_from_state(meta, arrays)``; its ``kind`` class attribute is set to ``kind``.
    """
    def deco(cls: T) -> T:
        if kind in _REGISTRY and _REGISTRY[kind] is not cls and \
                _REGISTRY[kind].__qualname__ != cls.__qualname__:
            raise ValueError(f"model kind {kind!r} is already registered to {_REGISTRY[kind].__qualname__}")
        for attr in ("_get_state", "_from_state"):
            if not hasattr(cls, attr):
                raise TypeError(f"{cls.__qualname__} needs a {attr} method to be registered")
        cls.kind = kind  # type: ignore[attr-defined]
        _REGISTRY[kind] = cls
        return cls
    return deco


def registered_kinds() -> dict[str, str]:
    """Registered kinds and the qualified names of their classes."""
    return {k: f"{c.__module__}.{c.__qualname__}" for k, c in _REGISTRY.items()}


def _base(path: str | Path) -> Path:
    p = Path(path)
    return p.with_suffix("") if p.suffix.lower() in (".json", ".npz") else p


def _json_path(path: str | Path) -> Path:
    b = _base(path)
    return b.parent / (b.name + ".json")


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` atomically: a temporary file in the same folder, flushed to disk, then
    ``os.replace``. On any error the temporary file is removed and ``path`` is left as it was."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    with contextlib.suppress(OSError):  # make the rename itself durable (POSIX; not possible everywhere)
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


def _check_arrays(arrays: dict[str, np.ndarray], where: str) -> None:
    """Every array real, numeric and finite (floats); raises ValueError naming ``where`` and the array."""
    for name, a in arrays.items():
        if a.dtype.kind not in "biuf":
            raise ValueError(f"{where}: array {name!r} has dtype {a.dtype} (only real numbers are allowed)")
        if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise ValueError(f"{where}: array {name!r} contains NaN or inf")


def save_model(model: Any, path: str | Path) -> Path:
    """Write ``model`` as ``<path>.json`` + ``<path>.<hash>.npz`` atomically (module docstring); return the JSON
    path. ``path`` may end in ``.json``, ``.npz`` or nothing; its folder is created if needed.

    Raises ``TypeError`` for an unregistered class, :class:`ident.base.NotFittedError` for an unfitted model and
    ``ValueError`` for arrays that could not be read back (NaN, inf, objects, complex numbers). Nothing is written
    unless the whole model could be serialised.
    """
    kind = getattr(type(model), "kind", None)
    if kind is None or _REGISTRY.get(kind) is not type(model):
        raise TypeError(f"{type(model).__qualname__} is not registered with ident.io.register_model")
    meta, arrays = model._get_state()
    arrays = {str(k): np.asarray(v) for k, v in arrays.items()}
    _check_arrays(arrays, f"cannot save {type(model).__name__}")
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    data = buf.getvalue()
    digest = hashlib.sha256(data).hexdigest()
    base = _base(path)
    jpath = base.parent / (base.name + ".json")
    arrays_name = f"{base.name}.{digest[:16]}.npz"
    doc = {"format": _FORMAT, "format_version": FORMAT_VERSION, "kind": kind, "module": type(model).__module__,
           "class": type(model).__qualname__, "arrays_file": arrays_name, "arrays_sha256": digest,
           "arrays": {k: {"shape": list(a.shape), "dtype": a.dtype.str} for k, a in arrays.items()},
           "meta": _jsonable(meta)}
    text = json.dumps(doc, indent=2)
    jpath.parent.mkdir(parents=True, exist_ok=True)
    old_arrays = _previous_arrays_file(jpath)
    atomic_write_bytes(jpath.parent / arrays_name, data)
    atomic_write_bytes(jpath, text.encode("utf-8"))
    if old_arrays is not None and old_arrays.name != arrays_name:
        with contextlib.suppress(OSError):
            old_arrays.unlink()
    return jpath


def _previous_arrays_file(jpath: Path) -> Path | None:
    """The arrays file the JSON at ``jpath`` names now (to delete after a re-save), if it is a sound name."""
    try:
        doc = json.loads(jpath.read_text(encoding="utf-8"))
        name = doc["arrays_file"]
        return jpath.parent / _plain_name(name) if isinstance(name, str) else None
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _plain_name(name: str) -> str:
    """``name`` if it is a bare file name (no folder part, not '.' or '..'); else ValueError."""
    if not name or name in (".", "..") or "/" in name or "\\" in name or os.sep in name or \
            (os.altsep and os.altsep in name) or Path(name).is_absolute() or "\x00" in name:
        raise ValueError(f"arrays_file must be a file name beside the JSON, got {name!r}")
    return name


def _read_doc(jpath: Path) -> dict[str, Any]:
    if not jpath.is_file():
        raise FileNotFoundError(f"no model file {jpath}")
    size = jpath.stat().st_size
    if size > MAX_JSON_BYTES:
        raise ModelFileError(f"{jpath}: {size} bytes is too large for a model file (limit {MAX_JSON_BYTES})")
    try:
        doc = json.loads(jpath.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise ModelFileError(f"{jpath} is not a model file: not UTF-8 text ({exc.reason} at byte {exc.start})") \
            from None
    except json.JSONDecodeError as exc:
        raise ModelFileError(f"{jpath} is not a model file: invalid JSON ({exc.msg} at line {exc.lineno}, column "
                             f"{exc.colno})") from None
    except RecursionError:
        raise ModelFileError(f"{jpath} is not a model file: JSON nested too deeply") from None
    if not isinstance(doc, dict):
        raise ModelFileError(f"{jpath} is not a model file: the JSON holds a {type(doc).__name__}, not an object")
    version = doc.get("format_version")
    if isinstance(version, bool) or not isinstance(version, int):
        raise ModelFileError(f"{jpath} is not a model file of ident: no integer 'format_version' (got {version!r})")
    if version not in READABLE_VERSIONS:
        raise ModelFileError(f"{jpath} has model format version {version}, which this version of ident cannot read "
                             f"(it reads versions {list(READABLE_VERSIONS)})")
    for key, typ in (("kind", str), ("meta", dict), ("arrays_file", str)):
        if key == "arrays_file" and version == 1 and key not in doc:
            continue
        if not isinstance(doc.get(key), typ):
            raise ModelFileError(f"{jpath}: the model file needs {key!r} as a {typ.__name__}, got "
                                 f"{type(doc.get(key)).__name__}")
    return doc


def _model_class(jpath: Path, doc: dict[str, Any]) -> type:
    kind, module = doc["kind"], doc.get("module", "")
    if kind not in _REGISTRY and isinstance(module, str) and (module == "ident" or module.startswith("ident.")):
        with contextlib.suppress(ImportError):
            importlib.import_module(module)
    if kind not in _REGISTRY:  # a module that moved (or a file written elsewhere): the built-in families
        for name in _BUILTIN_MODULES:
            with contextlib.suppress(ImportError):
                importlib.import_module(name)
    if kind not in _REGISTRY:
        raise ModelFileError(f"{jpath}: unknown model kind {kind!r}; registered kinds: {sorted(_REGISTRY)}")
    return _REGISTRY[kind]


def _read_arrays(jpath: Path, doc: dict[str, Any]) -> dict[str, np.ndarray]:
    version = doc["format_version"]
    try:
        name = _plain_name(doc.get("arrays_file", jpath.with_suffix(".npz").name))
    except ValueError as exc:
        raise ModelFileError(f"{jpath}: {exc}") from None
    npath = jpath.parent / name
    if not npath.is_file():
        raise ModelFileError(f"{jpath}: its arrays file {name} is missing (copy both files of a model together)")
    data = npath.read_bytes() if npath.stat().st_size <= MAX_ARRAY_BYTES + 2**20 else None
    if data is None:
        raise ModelFileError(f"{jpath}: its arrays file {name} is larger than {MAX_ARRAY_BYTES} bytes")
    spec: dict[str, Any] | None = None
    if version >= 2:
        digest = doc.get("arrays_sha256")
        spec = doc.get("arrays")
        if not isinstance(digest, str) or not isinstance(spec, dict):
            raise ModelFileError(f"{jpath}: the model file needs 'arrays_sha256' and 'arrays'")
        if hashlib.sha256(data).hexdigest() != digest:
            raise ModelFileError(f"{jpath}: its arrays file {name} does not match the SHA-256 recorded in the JSON "
                                 "(changed or damaged after the save)")
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            total = sum(info.file_size for info in zf.infolist())
        if total > MAX_ARRAY_BYTES:
            raise ModelFileError(f"{jpath}: its arrays file {name} unpacks to {total} bytes (limit {MAX_ARRAY_BYTES})")
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except ModelFileError:
        raise
    except Exception as exc:  # noqa: BLE001  (zip, npy header and pickle refusals all mean a damaged file)
        raise ModelFileError(f"{jpath}: its arrays file {name} cannot be read ({type(exc).__name__}: {exc})") \
            from None
    if spec is not None:
        if set(spec) != set(arrays):
            raise ModelFileError(f"{jpath}: its arrays file holds {sorted(arrays)}, the JSON lists {sorted(spec)}")
        for k, a in arrays.items():
            entry = spec[k]
            if not isinstance(entry, dict) or list(a.shape) != entry.get("shape") or a.dtype.str != entry.get("dtype"):
                raise ModelFileError(f"{jpath}: array {k!r} has shape {list(a.shape)} and dtype {a.dtype.str}, the "
                                     f"JSON records {entry!r}")
    try:
        _check_arrays(arrays, str(jpath))
    except ValueError as exc:
        raise ModelFileError(str(exc)) from None
    return arrays


def load_model(path: str | Path, expected: type | None = None) -> Any:
    """Load any registered model saved by :func:`save_model` (dispatch on the JSON's ``"kind"``).

    ``path`` may end in ``.json``, ``.npz`` or nothing. ``expected``: a class the model must be an instance of.
    Raises ``FileNotFoundError`` if the JSON does not exist and :class:`ModelFileError` (a ``ValueError``) naming
    the file for anything wrong with it (module docstring).
    """
    jpath = _json_path(path)
    doc = _read_doc(jpath)
    cls = _model_class(jpath, doc)
    arrays = _read_arrays(jpath, doc)
    try:
        model = cls._from_state(doc["meta"], arrays)
    except ModelFileError:
        raise
    except (ValueError, TypeError, KeyError, IndexError, AttributeError, OverflowError) as exc:
        what = f"missing entry {exc}" if isinstance(exc, KeyError) else str(exc)
        raise ModelFileError(f"{jpath}: not a valid {cls.__name__} file: {what}") from None
    if expected is not None and not isinstance(model, expected):
        raise ModelFileError(f"{jpath} holds a {type(model).__name__}, not a {expected.__name__}")
    return model
