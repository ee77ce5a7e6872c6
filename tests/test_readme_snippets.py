"""Every Python snippet of the README runs on its own (fresh namespace, its own imports),
from the repository root so ``../shared/data`` paths resolve; the getting-started page runs
in order."""

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


def test_getting_started_page_runs_in_order():
    """docs/getting-started.md's snippets build on each other: run them in one namespace."""
    text = (ROOT / "docs" / "getting-started.md").read_text("utf-8")
    namespace = {"__name__": "__getting_started__"}
    for i, code in enumerate(re.findall(r"```python\n(.*?)```", text, re.S)):
        exec(compile(code, f"getting-started.md snippet {i}", "exec"), namespace)
    assert namespace["g"].shape == (6,) and namespace["J"].shape == (3, 6)
