"""Errors raised by the file readers."""

from __future__ import annotations

import os

__all__ = ["FormatError"]


class FormatError(ValueError):
    """A malformed input file.

    The message reads ``"FILE:LINE: what was expected, what was found"``; the parts are also
    available as the attributes ``path``, ``line`` (1-based) and ``message``.
    """

    def __init__(self, path: str | os.PathLike[str] | None, line: int, message: str):
        self.path = "<unknown>" if path is None else os.fspath(path)
        self.line = int(line)
        self.message = message
        super().__init__(f"{self.path}:{self.line}: {message}")

    def __reduce__(self):  # keep pickling (multiprocessing, pytest-xdist) working
        return (type(self), (self.path, self.line, self.message))
