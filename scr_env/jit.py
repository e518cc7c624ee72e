"""numba compilation for the whole project, with an on-disk cache that never writes into the installed package.

Every compiled function of ``scr_env``, ``ident`` and ``control`` is decorated with :func:`njit` from here (not with
``numba.njit(cache=True)``), so one place decides where numba keeps its compiled machine code between processes:

1. ``$NUMBA_CACHE_DIR/scr-dosing``, if the user set ``NUMBA_CACHE_DIR`` (numba's own setting);
2. otherwise the per-user cache directory of this project, ``platformdirs.user_cache_dir("scr-dosing")/numba``
   (Linux: ``$XDG_CACHE_HOME/scr-dosing/numba``, by default ``~/.cache/scr-dosing/numba``; macOS:
   ``~/Library/Caches/scr-dosing/numba``; Windows: ``%LOCALAPPDATA%\\scr-dosing\\Cache\\numba``);
3. if that directory cannot be created or written (a read-only container, no writable home), nothing is cached:
   the functions are compiled in memory in every new process (the first step then takes a few seconds longer),
   and one :class:`NumbaCacheWarning` says so.

numba's default (``cache=True`` alone) writes ``__pycache__/*.nbi|*.nbc`` beside the source files, that is into
site-packages for an installed wheel: it fails on a read-only install without a writable home ("no locator
available") and leaves folders behind after ``pip uninstall``. :func:`cache_directory` tells where the cache is;
deleting that folder is always safe (``make clean`` does it).

numba keys each cached function on its own source file only, not on the files of the functions it calls or inlines
(the plant kernel inlines the chemistry of another file): an edited ``cell.py`` would leave the kernel's stale
machine code in use. So the cache lives in a subfolder named after a fingerprint of every source file of
``scr_env``, ``ident`` and ``control`` (path, size, modification time): any change of the code, an upgrade or an
edit, starts a fresh cache, and folders unused for :data:`PRUNE_AFTER_DAYS` days are deleted.
"""
from __future__ import annotations

import contextlib
import os
import tempfile
import threading
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numba

__all__ = ["APP_NAME", "NumbaCacheWarning", "cache_directory", "clear_cache", "njit"]

APP_NAME = "scr-dosing"  # the distribution name: the per-user cache folder is named after it
PRUNE_AFTER_DAYS = 14.0  # d: cache folders of other source versions unused this long are deleted [chosen]
_PACKAGES = ("scr_env", "ident", "control")  # the packages with compiled code (and what it inlines)


class NumbaCacheWarning(UserWarning):
    """No writable directory for numba's cache: compiled code is not kept between processes."""


_UNSET = object()
_resolved: Any = _UNSET
_lock = threading.Lock()


def _default_directory() -> Path:
    import platformdirs

    return Path(platformdirs.user_cache_dir(APP_NAME, appauthor=False)) / "numba"


def source_fingerprint() -> str:
    """A hash of the path, size and modification time of every ``.py`` file of the compiled packages (module
    docstring): the name of the cache folder of this version of the code."""
    import hashlib
    import importlib.util

    digest = hashlib.sha1()
    for name in _PACKAGES:
        spec = importlib.util.find_spec(name)
        if spec is None or not spec.submodule_search_locations:
            continue
        for root in spec.submodule_search_locations:
            for path in sorted(Path(root).rglob("*.py")):
                try:
                    st = path.stat()
                except OSError:
                    continue
                digest.update(f"{path}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return digest.hexdigest()[:16]


def _prune(base: Path, keep: Path) -> None:
    """Delete the cache folders of other source versions that were not used for PRUNE_AFTER_DAYS (best effort)."""
    import shutil
    import time

    os.utime(keep)  # marks this version's folder as used
    cutoff = time.time() - PRUNE_AFTER_DAYS * 86400.0
    try:
        siblings = list(base.iterdir())
    except OSError:
        return
    for d in siblings:
        try:
            if d != keep and d.is_dir() and d.stat().st_mtime < cutoff:
                shutil.rmtree(d, ignore_errors=True)
        except OSError:
            pass


def _writable(path: Path) -> bool:
    """Whether ``path`` exists (created if need be) as a directory this process can write to."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".write-test-"):
            pass
    except OSError:
        return False
    return True


def cache_directory() -> Path | None:
    """The directory of numba's on-disk cache for this project, or None when nothing is cached (see the module
    docstring for the order of choices). Decided once per process, at the first compiled function's import."""
    global _resolved
    with _lock:
        if _resolved is _UNSET:
            user_dir = numba.config.CACHE_DIR  # NUMBA_CACHE_DIR, read by numba at its import
            # our own subfolder of a user's NUMBA_CACHE_DIR, so pruning never touches other programs' caches
            candidate = Path(user_dir).expanduser() / APP_NAME if user_dir else None
            if candidate is None:
                try:
                    candidate = _default_directory()
                except Exception:  # noqa: BLE001 -- no home directory at all: same as an unwritable one
                    candidate = None
            versioned = None if candidate is None else candidate / source_fingerprint()
            if versioned is not None and _writable(versioned):
                _resolved = versioned.resolve()
                _prune(candidate, versioned)
            else:
                _resolved = None
                where = f"{candidate}" if candidate is not None else "no user cache directory"
                warnings.warn(
                    f"numba's cache directory ({where}) is not writable: compiled code is not cached, so every new "
                    f"process compiles the simulator again (a few seconds before the first step). Set "
                    f"NUMBA_CACHE_DIR to a writable directory to keep it.", NumbaCacheWarning, stacklevel=3)
        return _resolved


@contextlib.contextmanager
def _numba_cache_dir(path: Path) -> Iterator[None]:
    """numba reads ``config.CACHE_DIR`` when a function with ``cache=True`` is decorated (it fixes the function's
    cache locator then), so setting it for the decoration alone directs this project's functions to ``path``
    without changing where other libraries' numba functions are cached."""
    previous = numba.config.CACHE_DIR
    numba.config.CACHE_DIR = str(path)
    try:
        yield
    finally:
        numba.config.CACHE_DIR = previous


def njit(func: Callable | None = None, /, *, cache: bool = True, **options: Any) -> Any:
    """``numba.njit(**options)`` with the project's cache policy (module docstring); use as ``@njit`` or
    ``@njit(nogil=True, ...)``. ``cache=False`` compiles in memory only."""

    def decorate(f: Callable) -> Any:
        directory = cache_directory() if cache else None
        if directory is None:
            return numba.njit(**options)(f)
        with _lock, _numba_cache_dir(directory):
            try:
                return numba.njit(cache=True, **options)(f)
            except RuntimeError:  # no source file to key a cache on (a function typed at a prompt): in memory
                return numba.njit(**options)(f)

    return decorate if func is None else decorate(func)


def clear_cache() -> Path:
    """Delete this project's per-user numba cache (``python -m scr_env.jit --clear``, what ``make clean`` does) and
    return its path. A ``NUMBA_CACHE_DIR`` of the user's is left alone: other programs may share it."""
    import shutil

    directory = _default_directory()
    shutil.rmtree(directory, ignore_errors=True)
    return directory


if __name__ == "__main__":
    import sys

    if sys.argv[1:] == ["--clear"]:
        print(f"removed {clear_cache()}")
    elif sys.argv[1:]:
        sys.exit("usage: python -m scr_env.jit [--clear]")
    else:
        print(cache_directory() or "numba cache disabled (no writable directory)")
