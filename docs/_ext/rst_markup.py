"""Griffe extension: render the reStructuredText bits of jaxpose's docstrings as Markdown.

jaxpose's docstrings are Google style with a little reST: cross-reference roles
(``:class:`~jaxpose.optim.Triggs```, ``:func:`solve```, ...) and ``Example::`` literal-block
markers, and Google-style argument entries that document several parameters at once
(``gyro, acc: samples (…, N, 3)``). Roles become code spans showing the name as Sphinx
would (the last component with ``~``); ``::`` at the end of a paragraph becomes ``:`` (the
indented block after it is already a Markdown code block); a grouped entry becomes one
entry per name with the shared description, so griffe can match every name against the
signature. Loaded by mkdocstrings through ``mkdocs.yml``.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|data|attr|obj|exc|const):`(~?)([^`]+)`")


def _name(tilde: str, target: str) -> str:
    name = target.strip().lstrip(".")
    return name.rsplit(".", 1)[-1] if tilde else name


SECTION = re.compile(r"^(\s*)(Args|Arguments|Parameters|Other Parameters):\s*$")
GROUPED = re.compile(r"^(\s*)([A-Za-z_]\w*(?:\s*,\s*[A-Za-z_]\w*)+)\s*(\([^)]*\))?:(.*)$")


def _indent(line: str) -> int:
    return len(line) - len(line.lstrip())


def split_grouped_args(text: str) -> str:
    """``a, b: desc`` inside an Args section → ``a: desc`` and ``b: desc``."""
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    section_indent = None
    while i < len(lines):
        line = lines[i]
        m = SECTION.match(line)
        if m:
            section_indent = len(m.group(1))
            out.append(line)
            i += 1
            continue
        if section_indent is not None and line.strip() and _indent(line) <= section_indent:
            section_indent = None  # left the section
        g = GROUPED.match(line) if section_indent is not None else None
        if g and _indent(line) > section_indent:
            body = [line]
            j = i + 1
            while j < len(lines) and (not lines[j].strip() or _indent(lines[j]) > _indent(line)):
                body.append(lines[j])
                j += 1
            while body and not body[-1].strip():
                body.pop()
                j -= 1
            names = [n.strip() for n in g.group(2).split(",")]
            kind = f" {g.group(3)}" if g.group(3) else ""
            for name in names:
                out.append(f"{g.group(1)}{name}{kind}:{g.group(4)}")
                out.extend(body[1:])
            i = j
            continue
        out.append(line)
        i += 1
    return "\n".join(out)


def convert(text: str) -> str:
    """Roles → code spans; paragraph-final ``::`` → ``:``; grouped Args entries split."""
    text = ROLE.sub(lambda m: f"`{_name(m.group(1), m.group(2))}`", text)
    text = re.sub(r"(\S)::[ \t]*$", r"\1:", text, flags=re.M)
    return split_grouped_args(text)


class RstMarkup(griffe.Extension):
    """Rewrite every loaded docstring with :func:`convert`."""

    def on_object(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = convert(obj.docstring.value)
