"""The built wheel works from a read-only install with no writable home: the user's first contact (issue 23).

Builds the wheel from the sources, installs it (``--no-deps``) into a fresh virtual environment whose other
packages come from this environment through a path file (nothing heavy is downloaded), makes its site-packages and
the home directory read-only, and runs the README's environment snippet there from an empty folder. numba then has
nowhere to cache: the snippet must run all the same, warn once (``NumbaCacheWarning``), print what the README shows,
and write nothing into site-packages. A second run with a writable home must cache under the home, not in
site-packages. As root (a container), read-only is a read-only bind mount in a private mount namespace (``unshare``);
where that is not possible the write checks still run.
"""
from __future__ import annotations

import importlib.metadata
import json
import os
import shutil
import site
import stat
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

import pytest
from readme_snippets import ROOT, same_output, snippets

pytestmark = pytest.mark.slow

_CHILD = textwrap.dedent("""
    import contextlib, io, json, os, sys, warnings
    site_dir, code = sys.argv[1], sys.argv[2]
    warnings.simplefilter("always")
    out = io.StringIO()
    with warnings.catch_warnings(record=True) as caught, contextlib.redirect_stdout(out):
        import scr_env
        exec(compile(code, "README.md", "exec"), {"__name__": "__readme__"})
    try:
        with open(os.path.join(site_dir, "probe.txt"), "w") as f:
            f.write("x")
        site_writable = True
        os.remove(os.path.join(site_dir, "probe.txt"))
    except OSError:
        site_writable = False
    from scr_env.jit import cache_directory
    print(json.dumps({"file": scr_env.__file__, "stdout": out.getvalue(), "site_writable": site_writable,
                      "cache": str(cache_directory()),
                      "warnings": [w.category.__name__ for w in caught]}))
""")
_ONE_STEP = textwrap.dedent("""
    import gymnasium as gym, numpy as np, scr_env
    env = gym.make("scr_env/UreaSCR-v0")
    env.reset(seed=0)
    env.step(np.zeros(1, dtype=np.float32))
""")


def _setuptools_new_enough() -> bool:
    try:
        major = int(importlib.metadata.version("setuptools").split(".")[0])
    except (importlib.metadata.PackageNotFoundError, ValueError):
        return False
    return major >= 77


def _build_wheel(work: Path) -> Path:
    src = work / "src"
    ignore = shutil.ignore_patterns("__pycache__", "*.nbi", "*.nbc", "*.pyc", "runs", "*.egg-info", "build")
    src.mkdir()
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, src / name)
    for pkg in ("scr_env", "ident", "control", "experiments"):
        shutil.copytree(ROOT / pkg, src / pkg, ignore=ignore)
    cmd = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", str(work / "dist"), str(src)]
    if _setuptools_new_enough():  # build with this environment's setuptools: no download
        cmd.insert(4, "--no-build-isolation")
    subprocess.run(cmd, check=True, timeout=600, capture_output=True)
    wheels = list((work / "dist").glob("scr_dosing-*.whl"))
    assert len(wheels) == 1
    return wheels[0]


def _venv(work: Path, wheel: Path) -> tuple[Path, Path]:
    venv = work / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=300)
    python = venv / ("Scripts/python.exe" if os.name == "nt" else "bin/python")
    purelib = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  check=True, capture_output=True, text=True).stdout.strip())
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-compile", "--quiet", "--target",
                    str(purelib), str(wheel)], check=True, timeout=600)
    # the dependencies: this environment's site-packages as a plain path (its own .pth files, such as an editable
    # install of this checkout, are not processed from there)
    (purelib / "shared_dependencies.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    return python, purelib


def _listing(path: Path) -> set[str]:
    return {str(p.relative_to(path)) for p in path.rglob("*")}


def _can_bind_read_only() -> bool:
    if os.geteuid() != 0 or shutil.which("unshare") is None or shutil.which("mount") is None:
        return False
    with tempfile.TemporaryDirectory() as d:
        script = f"mount --bind {d} {d} && mount -o remount,bind,ro {d} {d} && ! touch {d}/x 2>/dev/null"
        probe = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, timeout=60, check=False)
    return probe.returncode == 0


def _run(python: Path, purelib: Path, home: Path, cwd: Path, code: str, read_only: bool) -> dict:
    env = {k: v for k, v in os.environ.items()
           if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME", "PYTHONPATH", "PYTHONHOME")}
    env.update(HOME=str(home), PYTHONNOUSERSITE="1", NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1")
    cmd = [str(python), "-c", _CHILD, str(purelib), code]
    if read_only and os.geteuid() == 0:
        mounts = " && ".join(f'mount --bind "{p}" "{p}" && mount -o remount,bind,ro "{p}" "{p}"'
                             for p in (purelib, home))
        cmd = ["unshare", "-m", "sh", "-c", f'{mounts} && exec "$@"', "sh", *cmd]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=cwd, timeout=900, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_wheel_runs_the_readme_snippet_from_a_read_only_install() -> None:
    snippet = next(s for s in snippets() if "gym.make(" in s.code)
    with tempfile.TemporaryDirectory(prefix="scr-dosing-install-") as tmp:
        work = Path(tmp)
        os.chmod(work, 0o755)
        wheel = _build_wheel(work)
        python, purelib = _venv(work, wheel)
        home, cwd = work / "home", work / "elsewhere"
        home.mkdir()
        cwd.mkdir()
        before = _listing(purelib)
        bind = _can_bind_read_only()
        if not bind and os.geteuid() != 0:
            for p in (purelib, home):
                for q in [p, *p.rglob("*")]:
                    q.chmod(q.stat().st_mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))
        try:
            r = _run(python, purelib, home, cwd, snippet.code, read_only=True)
        finally:
            for p in (purelib, home):
                for q in [p, *p.rglob("*")]:
                    q.chmod(q.stat().st_mode | stat.S_IWUSR)
        assert Path(r["file"]).is_relative_to(purelib)  # the wheel's code, not the checkout's
        if snippet.expected_output is not None:
            assert same_output(r["stdout"], snippet.expected_output), r["stdout"]
        assert _listing(purelib) == before and not any(home.iterdir())
        if bind or os.geteuid() != 0:  # really read-only: no cache anywhere, said once
            assert not r["site_writable"]
            assert r["cache"] == "None" and r["warnings"].count("NumbaCacheWarning") == 1, r
        # a writable home: the cache goes there, still nothing into site-packages
        r = _run(python, purelib, home, cwd, _ONE_STEP, read_only=False)
        assert Path(r["cache"]).is_relative_to(home) and any(Path(r["cache"]).rglob("*.nbi"))
        assert "NumbaCacheWarning" not in r["warnings"]
        assert _listing(purelib) == before
