"""Run folders for experiment outputs: ``runs/<name>/<YYYYmmdd-HHMMSS>/``."""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np


def run_folder(name: str, root: str | Path = "runs") -> Path:
    """Create and return ``<root>/<name>/<YYYYmmdd-HHMMSS>/`` (a numeric suffix if it already exists)."""
    base = Path(root) / name / time.strftime("%Y%m%d-%H%M%S")
    path, i = base, 1
    while path.exists():
        path = base.with_name(f"{base.name}-{i}")
        i += 1
    path.mkdir(parents=True)
    return path


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")


def write_json(path: str | Path, obj: Any) -> Path:
    """Write ``obj`` as indented JSON (numpy arrays and scalars converted); create parent folders."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(obj, indent=2, default=_default), encoding="utf-8")
    return path


def save_results(out: Path, filename: str, doc: Any, json_path: str | Path | None = None) -> Path:
    """Write ``doc`` as ``out/filename`` (the run folder's record) and, if given, also to ``json_path`` (the
    ``--json`` argument of every experiment); return the run-folder file."""
    path = write_json(Path(out) / filename, doc)
    if json_path is not None:
        write_json(json_path, doc)
    return path
