"""The README's "fit your own data" example runs as written (docs/pending/ident.md until it is folded into the
README)."""
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _example() -> str:
    for doc in (ROOT / "docs" / "pending" / "ident.md", ROOT / "README.md"):
        if doc.exists():
            text = doc.read_text(encoding="utf-8")
            at = text.find("Fit your own data")
            if at >= 0:
                m = re.search(r"```python\n(.*?)```", text[at:], re.DOTALL)
                if m:
                    return m.group(1)
    raise AssertionError("no 'Fit your own data' python example in docs/pending/ident.md or README.md")


def test_fit_your_own_data_example_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(_example(), "fit-your-own-data", "exec"), namespace)  # noqa: S102 (our own documentation)
    out = capsys.readouterr().out
    rpem_fit, linear_fit = (float(v) for v in re.findall(r"FIT (-?[\d.]+) %", out)[:1] +
                            re.findall(r"OE (-?[\d.]+) %", out)[:1])
    assert rpem_fit > linear_fit
    assert (tmp_path / "my_model.json").exists()
    val = namespace["val"]
    assert (namespace["same"].predict(val.u, val.y) == namespace["model"].predict(val.u, val.y)).all()
