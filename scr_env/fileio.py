"""Atomic file writes and the project's one JSON encoder.

Every file the project writes (run-folder JSON, tables and figures of the experiments, model and policy metadata)
goes through :func:`atomic_path`: the content is written to a temporary file in the destination's own folder,
flushed to disk, and only then moved over the destination with :func:`os.replace` (atomic on POSIX and Windows
for a file in the same folder). A reader sees the previous file or the new one, never a part of either: a full
disk, an interrupt or an exception in the writer leaves the previous file intact and removes the temporary one.

JSON is written with :func:`json_default` (numpy arrays and scalars, paths) and two-space indents, as
:func:`write_json` does.

    from scr_env.fileio import write_json, atomic_path
    write_json("runs/x/result.json", {"nox": np.float64(0.2)})
    with atomic_path("runs/x/figure.png") as tmp:
        fig.savefig(tmp)
"""
from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_path", "atomic_write_bytes", "atomic_write_text", "check_output_file", "check_output_folder",
           "json_default", "to_json", "write_json"]


def json_default(obj: Any) -> Any:
    """The ``default`` hook of :func:`json.dumps` for the project's values: numpy arrays (as lists), numpy scalars
    (as Python numbers) and paths (as strings); ``TypeError`` naming the type for anything else."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"cannot write {type(obj).__name__} as JSON")


def to_json(obj: Any, indent: int | None = 2) -> str:
    """``obj`` as JSON text (:func:`json_default` for numpy values and paths)."""
    return json.dumps(obj, indent=indent, default=json_default)


def _current_umask() -> int:
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _mode_of(path: Path) -> int:
    """Permission bits for the new version of ``path``: the existing file's, else 0666 under the umask."""
    try:
        return path.stat().st_mode & 0o7777
    except OSError:
        return 0o666 & ~_current_umask()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same folder, same suffix) to write to; on success it replaces
    ``path`` atomically, on any exception it is removed and ``path`` is left as it was.

    The parent folder must exist. The temporary file is flushed to disk (``fsync``) before the replace, so a crash
    right after it cannot leave an empty destination."""
    path = Path(path)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        with tmp.open("rb+") as fh:
            os.fsync(fh.fileno())
        # mkstemp makes the file private (0600): give it the mode a plain write would have (the old file's, or
        # the default for new files under the process umask)
        os.chmod(tmp, _mode_of(path))
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (:func:`atomic_path`); return the path."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def atomic_write_text(path: str | os.PathLike, text: str, encoding: str = "utf-8") -> Path:
    """Write ``text`` to ``path`` atomically (:func:`atomic_path`); return the path."""
    return atomic_write_bytes(path, text.encode(encoding))


def write_json(path: str | os.PathLike, obj: Any, indent: int | None = 2) -> Path:
    """Write ``obj`` as JSON (:func:`to_json`) to ``path`` atomically; create missing parent folders.

    The text is built before the file is touched, so an object that cannot be written (``TypeError``) leaves the
    previous file as it was."""
    path = Path(path)
    text = to_json(obj, indent)
    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write_text(path, text)


def _probe(folder: Path) -> None:
    """Create and remove a file in ``folder``: the one test of writability that holds on every file system."""
    fd, name = tempfile.mkstemp(prefix=".write-probe.", dir=folder)
    os.close(fd)
    os.unlink(name)


def check_output_folder(folder: str | os.PathLike, what: str = "output folder") -> Path:
    """``folder`` as a Path if it is an existing, writable folder; otherwise an ``OSError`` subclass whose message
    names ``what`` and the folder (``NotADirectoryError``, ``FileNotFoundError``, ``PermissionError``)."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise NotADirectoryError(f"{what} {folder} exists and is not a folder")
    if not folder.is_dir():
        raise FileNotFoundError(f"{what} {folder} does not exist")
    try:
        _probe(folder)
    except OSError as exc:
        raise PermissionError(f"{what} {folder} is not writable ({exc.strerror or exc})") from None
    return folder


def check_output_file(path: str | os.PathLike, what: str = "output file") -> Path:
    """Check, before a long computation, that ``path`` can be written later: its parent folder exists and is
    writable, and ``path`` itself is not a folder nor a read-only file. Returns ``path``; raises an ``OSError``
    subclass naming ``what`` and the path otherwise (nothing is created)."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{what} {path} is a folder, not a file")
    parent = path.parent
    if not parent.is_dir():
        raise FileNotFoundError(f"{what} {path}: its folder {parent} does not exist")
    check_output_folder(parent, f"the folder of the {what} {path}")
    if path.exists() and not os.access(path, os.W_OK):
        raise PermissionError(f"{what} {path} exists and is read-only")
    return path
