"""The experiments are thin scripts (issue 22): no class defined in experiments/, no experiment importing another
experiment (the shared infrastructure _runs and sweep excepted), about 200 lines at most."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

EXPERIMENTS = Path(__file__).resolve().parents[2] / "experiments"
#: shared infrastructure of the experiments, not experiments themselves
INFRASTRUCTURE = {"__init__", "_runs", "sweep"}
MAX_LINES = 200
SCRIPTS = sorted(p for p in EXPERIMENTS.glob("*.py") if p.stem not in INFRASTRUCTURE)


def _imported_modules(tree: ast.AST) -> set[str]:
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
            if node.module == "experiments":
                out |= {f"experiments.{a.name}" for a in node.names}
    return out


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: p.stem)
def test_experiment_is_a_thin_script(path: Path) -> None:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    classes = [n.name for n in ast.walk(tree) if isinstance(n, ast.ClassDef)]
    assert not classes, f"{path.name} defines classes {classes}: library code belongs in control/ident/scr_env"
    others = {m for m in _imported_modules(tree) if m.startswith("experiments.")
              and m.split(".")[1] not in INFRASTRUCTURE}
    assert not others, f"{path.name} imports other experiments {sorted(others)}"
    n = len(path.read_text(encoding="utf-8").splitlines())
    assert n <= MAX_LINES, f"{path.name} has {n} lines (> {MAX_LINES}): it holds library code"


def test_there_are_experiments() -> None:
    assert {"control_benchmark", "identify_then_control", "demo"} <= {p.stem for p in SCRIPTS}
