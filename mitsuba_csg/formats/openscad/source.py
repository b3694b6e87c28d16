"""The file being read: its name and text, turning offsets into 'line L, column C' for every
message and warning."""
from __future__ import annotations

import bisect
import re
import warnings

from ..reading import FormatError


class OpenSCADWarning(UserWarning):
    """Something OpenSCAD also drops or ignores (a degenerate solid, an unknown argument, a skipped node)."""


class Source:
    """The file name and text, turning offsets into 'line L, column C' for messages."""

    def __init__(self, name: str, text: str):
        self.name, self.text = name, text
        self._line_starts = None

    def where(self, pos: int) -> str:
        if self._line_starts is None:
            self._line_starts = [0] + [m.end() for m in re.finditer("\n", self.text)]
        line = bisect.bisect_right(self._line_starts, pos)
        return f"line {line}, column {pos - self._line_starts[line - 1] + 1}"

    def line(self, pos: int) -> int:
        self.where(0)
        return bisect.bisect_right(self._line_starts, pos)

    def fail(self, pos: int, message: str):
        raise FormatError(f"{self.name}: {self.where(pos)}: {message}")

    def warn(self, pos: int, message: str):
        warnings.warn(f"{self.name}: {self.where(pos)}: {message}", OpenSCADWarning, stacklevel=4)
