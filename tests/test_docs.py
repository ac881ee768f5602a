"""The code of the README, the getting-started page and the missing-readings guide runs
and prints what they show.

Every ```python block followed by an "Output:" block is run (in a fresh namespace, in a
temporary folder) and its printed lines are compared with the documented ones: words
exactly, numbers to the precision they are printed with.
"""

import contextlib
import io
import pathlib
import re
import warnings

import pytest

ROOT = pathlib.Path(__file__).parent.parent
PAGES = [
    ROOT / "README.md",
    ROOT / "docs" / "getting_started.md",
    ROOT / "docs" / "guide" / "missing.md",
]
NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:e[-+]?\d+)?")


def _examples(path):
    text = path.read_text()
    pattern = re.compile(r"```python\n(.*?)```\s*\n\s*Output:\s*\n\s*```\n(.*?)```", re.S)
    return [(code, out) for code, out in pattern.findall(text)]


CASES = [(p, i, c, o) for p in PAGES for i, (c, o) in enumerate(_examples(p))]


def _same_line(got: str, expected: str) -> bool:
    if NUMBER.sub("#", got).split() != NUMBER.sub("#", expected).split():
        return False
    for a, b in zip(NUMBER.findall(got), NUMBER.findall(expected), strict=True):
        decimals = len(b.split("e")[0].split(".")[1]) if "." in b else 0
        _, _, exponent = b.lower().partition("e")
        scale = 10.0 ** (int(exponent) if exponent else 0)
        if abs(float(a) - float(b)) > 1.5 * 10.0**-decimals * scale:
            return False
    return True


def test_every_page_has_examples():
    assert all(_examples(p) for p in PAGES)


@pytest.mark.parametrize(("page", "index", "code", "expected"), CASES,
                         ids=[f"{p.name}-{i}" for p, i, _, _ in CASES])  # fmt: skip
def test_documented_output(page, index, code, expected, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    out = io.StringIO()
    with contextlib.redirect_stdout(out), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        exec(compile(code, f"{page.name}-{index}", "exec"), {"__name__": "__main__"})
    got = [line for line in out.getvalue().splitlines() if line.strip()]
    want = [line for line in expected.splitlines() if line.strip()]
    assert len(got) == len(want), out.getvalue()
    for g, w in zip(got, want, strict=True):
        assert _same_line(g, w), (g, w)
