"""Saving and loading identified models in an open format (JSON + NPZ, never pickle), with a loader that dispatches
on the model's ``kind``.

A saved model is two files side by side: ``<name>.json`` (kind, module, constructor parameters and small learned
values, human-readable) and ``<name>.npz`` (the learned arrays, read with ``allow_pickle=False``).

Registering a model family (RPEM, Hammerstein-Wiener, ...) takes one decorator::

    from ident.io import register_model

    @register_model("rpem")
    class RecursivePEM:
        def _get_state(self) -> tuple[dict, dict[str, np.ndarray]]:
            ...   # (JSON-serialisable dict, arrays by name)

        @classmethod
        def _from_state(cls, meta: dict, arrays: dict[str, np.ndarray]) -> "RecursivePEM":
            ...

        def save(self, path):
            return save_model(self, path)

The class's module is recorded in the JSON, so :func:`load_model` imports it (only modules inside the ``ident``
package) if the kind is not registered yet: ``load_model(path)`` works without importing the family first.
"""
from __future__ import annotations

import importlib
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

__all__ = ["load_model", "register_model", "registered_kinds", "save_model"]

FORMAT_VERSION = 1
_REGISTRY: dict[str, type] = {}
T = TypeVar("T", bound=type)


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


def _paths(path: str | Path) -> tuple[Path, Path]:
    p = Path(path)
    base = p.with_suffix("") if p.suffix.lower() in (".json", ".npz") else p
    return base.parent / (base.name + ".json"), base.parent / (base.name + ".npz")


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


def save_model(model: Any, path: str | Path) -> Path:
    """Write ``model`` as ``<path>.json`` + ``<path>.npz``; return the JSON path.

    ``path`` may end in ``.json``, ``.npz`` or nothing.
    """
    kind = getattr(type(model), "kind", None)
    if kind is None or _REGISTRY.get(kind) is not type(model):
        raise TypeError(f"{type(model).__qualname__} is not registered with ident.io.register_model")
    meta, arrays = model._get_state()
    jpath, npath = _paths(path)
    jpath.parent.mkdir(parents=True, exist_ok=True)
    doc = {"kind": kind, "module": type(model).__module__, "format_version": FORMAT_VERSION,
           "arrays_file": npath.name, "meta": _jsonable(meta)}
    jpath.write_text(json.dumps(doc, indent=2), encoding="utf-8")
    with npath.open("wb") as fh:
        np.savez(fh, **{k: np.asarray(v) for k, v in arrays.items()})
    return jpath


def load_model(path: str | Path) -> Any:
    """Load any registered model saved by :func:`save_model` (dispatch on the JSON's ``"kind"``)."""
    jpath, _ = _paths(path)
    doc = json.loads(jpath.read_text(encoding="utf-8"))
    kind, module = doc.get("kind"), doc.get("module", "")
    if kind not in _REGISTRY and isinstance(module, str) and (module == "ident" or module.startswith("ident.")):
        importlib.import_module(module)
    if kind not in _REGISTRY:
        raise ValueError(f"{jpath}: unknown model kind {kind!r}; registered: {sorted(_REGISTRY)}")
    if doc.get("format_version", 0) > FORMAT_VERSION:
        raise ValueError(f"{jpath} was written by a newer version (format {doc['format_version']})")
    npath = jpath.parent / doc.get("arrays_file", jpath.with_suffix(".npz").name)
    with np.load(npath, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    return _REGISTRY[kind]._from_state(doc["meta"], arrays)
