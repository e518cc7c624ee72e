"""Run folders for experiment outputs: ``runs/<name>/<YYYYmmdd-HHMMSS>/``, written atomically.

An experiment calls :func:`run_folder` first, with its ``--json`` path: the folder is created and both are checked
for writing (:func:`scr_env.fileio.check_output_folder`, :func:`~scr_env.fileio.check_output_file`) before the long
run starts, so a read-only folder or a mistyped path fails at once with an error naming it, not with a raw
``OSError`` after an hour. Every file then goes through :mod:`scr_env.fileio`'s atomic writes (a temporary file in
the same folder, then ``os.replace``): a full disk or an interrupt leaves the previous good file intact.
"""
from __future__ import annotations

import platform
import subprocess
import time
from importlib import metadata
from pathlib import Path
from typing import Any

from scr_env.fileio import atomic_path, atomic_write_text, check_output_file, check_output_folder, write_json

__all__ = ["environment", "run_folder", "save_results", "write_figure", "write_json", "write_text"]

#: the distributions whose versions an experiment records (:func:`environment`): the NMPC figures depend on
#: CasADi's solvers at the level of a ppm of slip (the same Hammerstein-Wiener NMPC on calibration cycle 21:
#: 8.84 ppm with casadi 3.8.2, 9.66 ppm with 3.7.2; README, eighth round)
RECORDED_PACKAGES = ("casadi", "numpy", "scipy", "gymnasium", "numba", "torch", "stable-baselines3")


def run_folder(name: str, root: str | Path = "runs", json_path: str | Path | None = None,
               folder: str | Path | None = None) -> Path:
    """Create and return ``<root>/<name>/<YYYYmmdd-HHMMSS>/`` (a numeric suffix if it already exists), or
    ``folder`` if given (an experiment's ``--out``; it may exist), checked writable; ``json_path`` (the
    experiment's ``--json``), if given, is checked too (its folder exists and is writable, it is not a folder).
    ``OSError`` subclasses naming the folder or the file otherwise."""
    if json_path is not None:
        check_output_file(json_path, "--json file")
    if folder is not None:
        folder = Path(folder)
        if not folder.exists():
            folder.mkdir(parents=True)
        return check_output_folder(folder, "output folder")
    base = Path(root) / name / time.strftime("%Y%m%d-%H%M%S")
    path, i = base, 1
    while True:   # mkdir without exist_ok claims the name: two runs started in the same second get two folders
        try:
            path.mkdir(parents=True)
            break
        except FileExistsError:
            path = base.with_name(f"{base.name}-{i}")
            i += 1
        except OSError as exc:
            raise type(exc)(exc.errno, f"cannot create the run folder {path}: {exc.strerror}") from None
    return check_output_folder(path, "run folder")


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; return the path."""
    return atomic_write_text(path, text)


def write_figure(fig: Any, path: str | Path, dpi: int = 110) -> Path:
    """Save a matplotlib figure atomically (it replaces ``path`` only once fully written; the format from the
    suffix, PNG without one) and close it; return ``path``."""
    from control.plots import pyplot

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".").lower() or "png")
    pyplot().close(fig)
    return path


def save_results(out: Path, filename: str, doc: Any, json_path: str | Path | None = None) -> Path:
    """Write ``doc`` as ``out/filename`` (the run folder's record) and, if given, also to ``json_path`` (the
    ``--json`` argument of every experiment); return the run-folder file. Both writes are atomic."""
    path = write_json(Path(out) / filename, doc)
    if json_path is not None:
        write_json(json_path, doc)
    return path


def environment() -> dict[str, Any]:
    """What a figure was computed with, for the experiments' JSON (key ``environment``): the Python version, the
    versions of :data:`RECORDED_PACKAGES` (None if not installed) and the git commit of the working tree (None
    outside a git checkout; ``"<hash>+dirty"`` with uncommitted changes). The figures are deterministic for given
    seeds only with the same versions."""
    packages: dict[str, str | None] = {}
    for name in RECORDED_PACKAGES:
        try:
            packages[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            packages[name] = None
    return {"python": platform.python_version(), "packages": packages, "git_commit": _git_commit()}


def _git_commit() -> str | None:
    """The commit of the checkout holding this file, None if there is none (an installed package, no git)."""
    here = Path(__file__).resolve().parent
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], check=False, cwd=here, capture_output=True, text=True,
                              timeout=10)
        if head.returncode != 0:
            return None
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], check=False,
                               cwd=here, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return None
    commit = head.stdout.strip()
    return commit + ("+dirty" if dirty.returncode == 0 and dirty.stdout.strip() else "")
