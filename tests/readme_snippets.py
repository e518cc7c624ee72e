"""The ```python snippets of README.md and the outputs the README shows for them (shared by the README tests).

A snippet is run as printed. If the next fenced block after it (only blank lines between) is a ```text block, that
is its expected output, compared line by line after stripping trailing blanks. A snippet preceded by the line
``<!-- readme-test: skip (reason) -->`` is not run (say why in the comment, e.g. "trains for minutes").
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_FENCE = re.compile(r"^```(\w*)\s*$")


@dataclass(frozen=True)
class Snippet:
    code: str
    expected_output: str | None
    line: int  # 1-based line of the opening fence in README.md
    skip_reason: str | None


def snippets(readme: Path = ROOT / "README.md") -> list[Snippet]:
    """Every ```python block of the README, in order, with its expected output and skip mark."""
    lines = readme.read_text(encoding="utf-8").splitlines()
    blocks: list[tuple[str, int, int, str]] = []  # (language, first line index, closing index, body)
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if m:
            j = i + 1
            while j < len(lines) and not lines[j].startswith("```"):
                j += 1
            blocks.append((m.group(1), i, j, "\n".join(lines[i + 1:j]) + "\n"))
            i = j + 1
        else:
            i += 1
    out = []
    for k, (lang, start, end, body) in enumerate(blocks):
        if lang != "python":
            continue
        expected = None
        if k + 1 < len(blocks) and blocks[k + 1][0] == "text" and \
                all(not ln.strip() for ln in lines[end + 1:blocks[k + 1][1]]):
            expected = blocks[k + 1][3]
        skip = None
        prev = next((ln for ln in reversed(lines[:start]) if ln.strip()), "")
        m = re.match(r"<!--\s*readme-test:\s*skip\s*(.*?)\s*-->", prev.strip())
        if m:
            skip = m.group(1) or "marked skip"
        out.append(Snippet(body, expected, start + 1, skip))
    return out


def same_output(actual: str, expected: str) -> bool:
    def norm(text: str) -> list[str]:
        return [ln.rstrip() for ln in text.strip("\n").splitlines()]

    return norm(actual) == norm(expected)
