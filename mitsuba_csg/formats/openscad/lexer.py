"""Tokens of OpenSCAD's `.csg` text."""
from __future__ import annotations

import math
import re

from .source import Source


_TOKEN = re.compile(r"""
    (?P<space>[ \t\r\n\f\v]+|//[^\n]*|/\*.*?\*/)
  | (?P<num>(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?)
  | (?P<id>[A-Za-z_$][A-Za-z0-9_]*)
  | (?P<str>"(?:[^"\\\n]|\\.)*")
  | (?P<punct>[()\[\]{};,=#%!*:+-])
  | (?P<bad>/\*|"|.)
""", re.VERBOSE | re.DOTALL)
_NUMBER_TAIL = re.compile(r"[A-Za-z0-9_.]")
_ESCAPES = {"n": "\n", "t": "\t", "r": "\r", '"': '"', "\\": "\\"}
_ESCAPE = re.compile(r"\\(x[0-9A-Fa-f]{2}|u[0-9A-Fa-f]{4}|U[0-9A-Fa-f]{6}|.)", re.DOTALL)
KEYWORDS = {"true": True, "false": False, "undef": None, "inf": math.inf, "nan": math.nan}
EOF = "<end of file>"


def _unescape(m: re.Match) -> str:
    e = m.group(1)
    if e[0] in "xuU" and len(e) > 1:
        code = int(e[1:], 16)
        return chr(code) if code <= 0x10FFFF else "\ufffd"
    return _ESCAPES.get(e, e)


def tokens(src: Source):
    """(kind, value, offset) triples: kind is 'num', 'id', 'str', a punctuation character, or EOF."""
    text = src.text
    for m in _TOKEN.finditer(text):
        kind = m.lastgroup
        if kind == "space":
            continue
        pos, s = m.start(), m.group()
        if kind == "num":
            if _NUMBER_TAIL.match(text, m.end()):
                tail = re.match(r"[A-Za-z0-9_.+-]*", text[m.end():m.end() + 40]).group()
                src.fail(pos, f"malformed number {s + tail!r}")
            yield ("num", float(s), pos)
        elif kind == "id":
            yield ("id", s, pos)
        elif kind == "str":
            yield ("str", _ESCAPE.sub(_unescape, s[1:-1]), pos)
        elif kind == "punct":
            yield (s, s, pos)
        elif s == "/*":
            src.fail(pos, "unterminated comment /* ... (no closing */)")
        elif s == '"':
            src.fail(pos, "unterminated string (no closing \" on this line)")
        else:
            src.fail(pos, f"unexpected character {s!r}")
    yield (EOF, None, len(text))


def describe_token(tok) -> str:
    kind, value, _ = tok
    if kind == EOF:
        return "the end of the file"
    if kind == "num":
        return f"the number {value:g}"
    if kind == "str":
        return "a string"
    return repr(value)
