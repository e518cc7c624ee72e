"""scr_env.fileio: atomic writes (a full disk or a failed replace leaves the previous file intact), the one JSON
encoder, and the output checks made before a long run."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from scr_env import fileio
from scr_env.fileio import atomic_path, atomic_write_text, check_output_file, check_output_folder, write_json


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def test_json_encoder_writes_numpy_values_and_paths(tmp_path) -> None:
    doc = {"a": np.arange(3), "b": np.float32(0.5), "c": np.int64(7), "d": Path("x/y"), "e": [np.bool_(True)]}
    path = write_json(tmp_path / "sub" / "r.json", doc)   # parent folders are created
    assert json.loads(path.read_text()) == {"a": [0, 1, 2], "b": 0.5, "c": 7, "d": "x/y", "e": [True]}
    with pytest.raises(TypeError, match="cannot write object as JSON"):
        write_json(path, {"x": object()})
    assert json.loads(path.read_text())["c"] == 7   # the failed write left the previous file
    assert _leftovers(path.parent) == []


def test_a_failed_replace_leaves_the_previous_file_and_no_temporary(tmp_path, monkeypatch) -> None:
    path = atomic_write_text(tmp_path / "table.txt", "good\n")

    def broken(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(fileio.os, "replace", broken)
    with pytest.raises(OSError, match="No space"):
        write_json(path, {"new": 1})
    monkeypatch.undo()
    assert path.read_text() == "good\n" and _leftovers(tmp_path) == []


def test_an_exception_in_the_writer_leaves_the_previous_file(tmp_path) -> None:
    path = atomic_write_text(tmp_path / "fig.png", "old")
    with pytest.raises(KeyboardInterrupt), atomic_path(path) as tmp:   # an interrupt half-way through a figure
        tmp.write_text("half a fig")
        raise KeyboardInterrupt
    assert path.read_text() == "old" and _leftovers(tmp_path) == []


def test_a_full_disk_leaves_the_previous_good_json(tmp_path) -> None:
    """A small RLIMIT_FSIZE in a subprocess: the second, larger write fails (EFBIG, as a full disk fails), and the
    first JSON is still there, whole."""
    path = tmp_path / "result.json"
    script = textwrap.dedent(f"""
        import resource, signal, sys
        from scr_env.fileio import write_json
        write_json({str(path)!r}, {{"run": 1, "ok": True}})
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)   # EFBIG instead of being killed
        resource.setrlimit(resource.RLIMIT_FSIZE, (4096, 4096))
        try:
            write_json({str(path)!r}, {{"run": 2, "big": list(range(100000))}})
        except OSError as exc:
            print("refused", exc.errno)
            sys.exit(0)
        sys.exit(3)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=False,
                          cwd=Path(__file__).resolve().parents[2])
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("refused")
    assert json.loads(path.read_text()) == {"run": 1, "ok": True}
    assert _leftovers(tmp_path) == []


def test_output_checks_name_the_problem(tmp_path) -> None:
    assert check_output_file(tmp_path / "new.json") == tmp_path / "new.json"
    with pytest.raises(FileNotFoundError, match="does not exist"):
        check_output_file(tmp_path / "missing" / "r.json", "--json file")
    with pytest.raises(IsADirectoryError, match="is a folder"):
        check_output_file(tmp_path, "--json file")
    with pytest.raises(NotADirectoryError, match="not a folder"):
        check_output_folder(atomic_write_text(tmp_path / "f", "x"))
    if os.geteuid() != 0:   # root writes anywhere: the permission checks cannot be exercised
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        try:
            with pytest.raises(PermissionError, match="not writable"):
                check_output_file(ro / "r.json", "--json file")
        finally:
            ro.chmod(0o700)


def test_an_unwritable_folder_is_refused_before_any_work(tmp_path, monkeypatch) -> None:
    def denied(folder):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr(fileio, "_probe", denied)
    with pytest.raises(PermissionError, match=r"run folder .* is not writable"):
        check_output_folder(tmp_path, "run folder")
    with pytest.raises(PermissionError, match="--json file"):
        check_output_file(tmp_path / "r.json", "--json file")


def test_new_files_get_the_usual_permissions_and_old_ones_keep_theirs(tmp_path) -> None:
    mask = os.umask(0o022)
    try:
        path = atomic_write_text(tmp_path / "a.txt", "x")
        assert path.stat().st_mode & 0o777 == 0o644   # not the 0600 of a temporary file
        path.chmod(0o640)
        atomic_write_text(path, "y")
        assert path.stat().st_mode & 0o777 == 0o640
    finally:
        os.umask(mask)
