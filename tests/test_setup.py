"""The README opens with the two set-up commands, and CI runs the second one verbatim."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    block = re.search(r"```bash\n(.*?)```", text, re.S)
    assert block and text.index(block.group(0)) < text.index("\n## "), "commands come first"
    return [ln.strip() for ln in block.group(1).splitlines() if ln.strip()]


def test_readme_opens_with_the_two_commands():
    demo, tests = _readme_commands()
    assert demo.startswith("pip install -e . && jaxpose demo")
    assert "pytest" in tests and '"not slow"' in tests


def test_ci_runs_the_readme_test_command():
    _, tests = _readme_commands()
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert any(line.strip().endswith(tests) for line in ci.splitlines()), ci
