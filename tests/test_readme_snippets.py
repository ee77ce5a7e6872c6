"""Every Python snippet of the README runs on its own (fresh namespace, its own imports),
from the repository root so ``../shared/data`` paths resolve."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SNIPPETS = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text("utf-8"), re.S)


def test_readme_has_snippets():
    assert len(SNIPPETS) >= 5


@pytest.mark.parametrize("index", range(len(SNIPPETS)))
def test_readme_snippet_runs_alone(index, monkeypatch):
    code = SNIPPETS[index]
    for path in re.findall(r"\"(\.\./shared/[^\"]+)\"", code):
        if not (ROOT / path).exists():
            pytest.skip(f"reference data {path} not present")
    monkeypatch.chdir(ROOT)
    exec(compile(code, f"README.md snippet {index}", "exec"), {"__name__": "__readme__"})
    assert os.getcwd() == str(ROOT)
