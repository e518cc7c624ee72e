"""numba's cache: a per-user directory (or NUMBA_CACHE_DIR), never the package folders, versioned by the sources,
and compiling without a cache, with one warning, when nothing is writable (scr_env.jit)."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import scr_env
from scr_env import jit

ROOT = Path(scr_env.__file__).resolve().parents[1]
# a small compiled function of the project, so the check is quick
_COMPILE = textwrap.dedent("""
    import warnings, json
    warnings.simplefilter("always")
    with warnings.catch_warnings(record=True) as w:
        import numpy as np
        from scr_env.jit import cache_directory
        from scr_env.params import CatalystParams, pack
        from scr_env.physics.kernel import thermal_trajectory
        out = thermal_trajectory(np.full(5, 300.0), np.full(3, 5.0), np.full(3, 600.0), pack(CatalystParams()), 0.5)
    assert out.shape == (3, 5) and np.all(out[:, 0] > 300.0)
    print(json.dumps({"dir": str(cache_directory()), "warnings": [x.category.__name__ for x in w]}))
""")


def _package_cache_files() -> set[Path]:
    return {p for pkg in ("scr_env", "ident", "control") for p in (ROOT / pkg).rglob("*.nb[ic]")}


def _run(env: dict[str, str]) -> dict:
    import json

    full = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
    full.update(env)
    full["PYTHONPATH"] = str(ROOT)
    proc = subprocess.run([sys.executable, "-c", _COMPILE], capture_output=True, text=True, env=full, timeout=300,
                          cwd=str(ROOT), check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_cache_goes_to_numba_cache_dir_versioned_and_never_beside_the_sources(tmp_path) -> None:
    before = _package_cache_files()
    r = _run({"NUMBA_CACHE_DIR": str(tmp_path)})
    directory = Path(r["dir"])
    assert directory.parent == tmp_path / "scr-dosing" and directory.name == jit.source_fingerprint()
    assert any(directory.rglob("*.nbi")) and any(directory.rglob("*.nbc"))
    assert _package_cache_files() == before  # nothing written into the package folders
    assert "NumbaCacheWarning" not in r["warnings"]


def test_default_cache_is_the_per_user_cache_directory(tmp_path) -> None:
    r = _run({"XDG_CACHE_HOME": str(tmp_path), "HOME": str(tmp_path)})
    if sys.platform.startswith("linux"):
        assert Path(r["dir"]).is_relative_to(tmp_path / "scr-dosing" / "numba")
    assert not Path(r["dir"]).is_relative_to(ROOT)


def test_nothing_writable_compiles_without_cache_and_warns_once(tmp_path) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("not a directory")
    before = _package_cache_files()
    r = _run({"NUMBA_CACHE_DIR": str(blocker / "cache"), "HOME": str(blocker / "home")})
    assert r["dir"] == "None"
    assert r["warnings"].count("NumbaCacheWarning") == 1
    assert _package_cache_files() == before


def test_fingerprint_follows_every_source_file(tmp_path, monkeypatch) -> None:
    pkg = tmp_path / "fakepkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "mod.py").write_text("x = 1\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(jit, "_PACKAGES", ("fakepkg",))
    first = jit.source_fingerprint()
    (pkg / "mod.py").write_text("x = 22\n")
    assert jit.source_fingerprint() != first


def test_clear_cache_removes_only_the_project_folder(tmp_path, monkeypatch) -> None:
    target = tmp_path / "scr-dosing" / "numba"
    (target / "abc").mkdir(parents=True)
    monkeypatch.setattr(jit, "_default_directory", lambda: target)
    assert jit.clear_cache() == target and not target.exists() and (tmp_path / "scr-dosing").exists()
