"""Every ```python snippet of README.md runs as printed and prints the output the README shows for it."""
from __future__ import annotations

import contextlib
import io

import pytest
from readme_snippets import same_output, snippets

SNIPPETS = snippets()


def test_readme_has_snippets() -> None:
    assert SNIPPETS, "README.md shows no python snippet"


@pytest.mark.parametrize("snippet", SNIPPETS, ids=[f"README.md:{s.line}" for s in SNIPPETS])
def test_readme_snippet_runs_as_printed(snippet, tmp_path, monkeypatch) -> None:
    if snippet.skip_reason:
        pytest.skip(f"README.md:{snippet.line}: {snippet.skip_reason}")
    monkeypatch.chdir(tmp_path)  # a snippet that writes files writes them here
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(snippet.code, f"README.md:{snippet.line}", "exec"), {"__name__": "__readme__"})  # noqa: S102
    if snippet.expected_output is not None:
        assert same_output(out.getvalue(), snippet.expected_output), (
            f"README.md:{snippet.line} printed\n{out.getvalue()}\nbut the README shows\n{snippet.expected_output}")
