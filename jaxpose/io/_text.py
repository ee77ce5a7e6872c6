"""Text helpers shared by the readers and writers: decoding, the number-token character
rule, and the writers' refusal of non-finite rows.

The file formats are plain ASCII: numbers are ASCII digits with an optional sign, point and
exponent. Python's ``int``/``float`` (and numpy's string conversion) also accept ``1_0`` and
non-ASCII digits such as ``١٢`` or ``１２``, and ``str.split`` separates on non-ASCII spaces;
the readers reject those with a :class:`~jaxpose.io.FormatError` instead of reading a value the
file does not spell.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np

__all__ = ["describe_bad_char", "first_bad_char", "read_text", "refuse_nonfinite_rows"]


def refuse_nonfinite_rows(arr: np.ndarray, argname: str, reader: str,
                          label: Callable[[int], str] | None = None) -> None:
    """Raise ``ValueError`` naming the first row of ``arr`` (n, k) with a NaN or Inf: a
    writer refuses what its ``reader`` would reject (``label(k)`` describes row k)."""
    bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
    if bad.size:
        k = int(bad[0])
        where = f" ({label(k)})" if label is not None else ""
        raise ValueError(f"{argname}: row {k}{where} is not finite: {arr[k].tolist()}; "
                         f"{reader} would reject the file")


def read_text(path: str | os.PathLike[str]) -> str:
    """The file's text: UTF-8, a leading byte-order mark dropped, invalid bytes replaced by
    U+FFFD (which no number accepts, so the reader reports them with their line). Line ends
    are kept as they are: lines are counted at ``\n`` (as editors and ``grep -n`` do), and a
    ``\r`` is whitespace."""
    with open(path, encoding="utf-8-sig", errors="replace", newline="") as fh:
        return fh.read()


def first_bad_char(s: str) -> int:
    """Index of the first character of ``s`` that no number token may contain (a non-ASCII
    character or ``_``), or -1 when there is none."""
    if s.isascii() and "_" not in s:
        return -1
    for k, ch in enumerate(s):
        if ch == "_" or not ch.isascii():
            return k
    return -1  # pragma: no cover - the fast path above covers it


def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def describe_bad_char(s: str, k: int) -> tuple[int, str]:
    """``(field, text)`` for the bad character ``s[k]``: the 0-based index of the
    whitespace-separated token holding it, and a phrase ``"found ..."`` for the message."""
    ch = s[k]
    if ch.isspace():
        return len(s[:k].split()), f"found the non-ASCII space U+{ord(ch):04X} between values"
    lo, hi = k, k + 1
    while lo > 0 and not s[lo - 1].isspace():
        lo -= 1
    while hi < len(s) and not s[hi].isspace():
        hi += 1
    tok = s[lo:hi]
    if ch == "\ufffd":
        why = "bytes that are not valid UTF-8"
    elif ch == "_" and _is_number(tok.replace("_", "")):
        why = "'_' digit separators are not part of the format"
    elif ch == "_":  # a word such as VERTEX_SE2 (a g2o file given as BAL)
        why = "not a number"
    elif ch == "\ufeff":
        why = "a byte-order mark U+FEFF inside the file"
    else:
        why = f"non-ASCII character U+{ord(ch):04X}; numbers use ASCII digits"
    return len(s[:lo].split()), f"found {tok!r} ({why})"
