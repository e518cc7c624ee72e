"""Checks of the installation that users hit before any error of ours could explain them.

The distribution ``scr-dosing`` installs four top-level packages: ``scr_env``, ``ident``, ``control`` and
``experiments``. ``control`` is also the import name of python-control (``pip install control``); installed into the
same environment, one overwrites the other's ``control/__init__.py``, and the error that follows
(``ImportError: cannot import name 'LookupTableDosing' from 'control'``) does not say why. :func:`check_control_package`
finds the clash without importing either package: ``import scr_env`` warns (the simulator itself does not need
``control``), and ``import experiments`` raises (every experiment does).
"""
from __future__ import annotations

import importlib.util
import sys
import warnings
from pathlib import Path

__all__ = ["CONTROL_MARKER", "ControlPackageShadowedWarning", "check_control_package"]

#: the line of this project's ``control/__init__.py`` that identifies it
CONTROL_MARKER = "__scr_dosing_package__ = True"

_FIX = ("python-control (pip package 'control') shares the import name 'control' with this project's controller "
        "package and has replaced it in this environment. Fix: use a separate virtual environment for scr-dosing, "
        "or `pip uninstall control` and then reinstall scr-dosing (`pip install --force-reinstall --no-deps "
        "scr-dosing`, or `pip install -e .` in a checkout).")


class ControlPackageShadowedWarning(UserWarning):
    """``import control`` would not import this project's controller package."""


def _control_origin() -> Path | None:
    """The ``__init__.py`` that ``import control`` loads (or has loaded), or None when there is no ``control``."""
    module = sys.modules.get("control")
    if module is not None:
        origin = getattr(module, "__file__", None)
        return Path(origin) if origin else None
    try:
        spec = importlib.util.find_spec("control")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.origin or spec.origin in ("built-in", "frozen"):
        return None
    return Path(spec.origin)


def check_control_package(strict: bool = False) -> bool:
    """Whether ``import control`` gives this project's package. If it gives another one (python-control),
    ``strict`` raises ImportError naming python-control and the fix; otherwise one
    :class:`ControlPackageShadowedWarning` says so. No ``control`` at all (an install without it) is not an error."""
    origin = _control_origin()
    if origin is None:
        return True
    try:
        ours = CONTROL_MARKER in origin.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return True  # unreadable: let the import itself report
    if ours:
        return True
    message = f"`import control` loads {origin}, not scr-dosing's controllers: {_FIX}"
    if strict:
        raise ImportError(message)
    warnings.warn(message, ControlPackageShadowedWarning, stacklevel=3)
    return False
