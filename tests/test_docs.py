"""The documentation site builds with ``mkdocs build --strict`` (any warning fails: broken
links, missing pages, docstrings griffe cannot parse), and every page is in the nav.

The build is skipped when the ``docs`` extra is not installed (``pip install -e ".[docs]"``).
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"


def _docs_installed() -> bool:
    return all(
        importlib.util.find_spec(m) is not None
        for m in ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python")
    )


def _nav_pages() -> set[str]:
    text = (ROOT / "mkdocs.yml").read_text(encoding="utf-8")
    nav = text[text.index("\nnav:") :]
    return set(re.findall(r"([\w./-]+\.md)\s*$", nav, flags=re.M))


def test_every_page_is_in_the_nav():
    pages = {
        p.relative_to(DOCS).as_posix()
        for p in DOCS.rglob("*.md")
        if not p.relative_to(DOCS).as_posix().startswith("_")
    }
    nav = _nav_pages()
    assert pages - nav == set(), f"pages missing from the nav in mkdocs.yml: {pages - nav}"
    assert nav - pages == set(), f"nav entries without a page: {nav - pages}"


def test_rst_markup_extension():
    """The griffe extension that renders the docstrings' reST bits as Markdown."""
    sys.path.insert(0, str(DOCS / "_ext"))
    try:
        from rst_markup import convert
    finally:
        sys.path.pop(0)
    assert convert("see :class:`~jaxpose.optim.Triggs`") == "see `Triggs`"
    assert convert(":meth:`EKF.run` and :mod:`.camera`") == "`EKF.run` and `camera`"
    assert convert("Example::\n\n    x = 1") == "Example:\n\n    x = 1"
    grouped = "Args:\n    a, b (int): shared\n        more.\n    c: own\n\nReturns:\n    x, y: kept"
    assert convert(grouped) == (
        "Args:\n    a (int): shared\n        more.\n    b (int): shared\n        more.\n"
        "    c: own\n\nReturns:\n    x, y: kept"
    )


@pytest.mark.skipif(not _docs_installed(), reason='needs the docs extra: pip install ".[docs]"')
def test_docs_build_strict(tmp_path):
    site = tmp_path / "site"
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
    )
    log = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"mkdocs build --strict failed:\n{log[-6000:]}"
    assert "WARNING" not in log, log[-6000:]
    api = (site / "api" / "optim" / "index.html").read_text(encoding="utf-8")
    assert 'id="jaxpose.optim.least_squares"' in api  # the reference is generated
    assert (site / "conventions" / "index.html").is_file()
    assert (site / "pypose-migration" / "index.html").is_file()
