"""GDML expressions: arithmetic over numbers, defined scalars, units and constants.

Evaluated by a whitelisted walk over Python's `ast` (numbers, names, + - * / ^, unary
minus, the functions below), never `eval`; length and nesting are bounded.
"""
from __future__ import annotations

import ast
import math
import re

from ..reading import FormatError

MAX_EXPRESSION_CHARS = 10_000      # one attribute expression
MAX_EXPRESSION_DEPTH = 200         # nesting of one expression's syntax tree
TWO_PI = 2.0 * math.pi

# ---- Units (CLHEP values: mm, rad, ns, MeV, eplus are 1) ----
_e_SI = 1.602176634e-19
_joule = 1e-6 / _e_SI                # electronvolt / e_SI, electronvolt = 1e-6 MeV
_kg = _joule * 1e12                  # joule * s^2 / m^2 with s = 1e9 ns, m = 1e3 mm
UNITS = {
    # length
    "mm": 1.0, "millimeter": 1.0, "cm": 10.0, "centimeter": 10.0, "m": 1000.0, "meter": 1000.0,
    "km": 1e6, "kilometer": 1e6, "um": 1e-3, "micrometer": 1e-3, "nm": 1e-6, "nanometer": 1e-6,
    "angstrom": 1e-7, "fermi": 1e-12, "pc": 3.0856775807e16 * 1000.0, "parsec": 3.0856775807e16 * 1000.0,
    "mm2": 1.0, "cm2": 100.0, "m2": 1e6, "km2": 1e12, "mm3": 1.0, "cm3": 1e3, "m3": 1e9, "km3": 1e18,
    "L": 1e6, "dL": 1e5, "cL": 1e4, "mL": 1e3,
    # angle
    "rad": 1.0, "radian": 1.0, "mrad": 1e-3, "milliradian": 1e-3, "deg": math.pi / 180.0,
    "degree": math.pi / 180.0, "sr": 1.0, "steradian": 1.0,
    # time, energy, mass, amount, temperature, pressure (materials; never geometry)
    "ns": 1.0, "s": 1e9, "ms": 1e6, "us": 1e3, "ps": 1e-3, "second": 1e9,
    "MeV": 1.0, "eV": 1e-6, "keV": 1e-3, "GeV": 1e3, "TeV": 1e6, "PeV": 1e9,
    "joule": _joule, "kg": _kg, "kilogram": _kg, "g": _kg * 1e-3, "gram": _kg * 1e-3, "mg": _kg * 1e-6,
    "mole": 1.0, "mol": 1.0, "kelvin": 1.0, "K": 1.0, "perCent": 0.01, "perThousand": 1e-3,
    "perMillion": 1e-6, "pascal": _joule / 1e9, "bar": 1e5 * _joule / 1e9, "atmosphere": 101325 * _joule / 1e9,
    "eplus": 1.0, "e_SI": _e_SI,
}
_CONSTANTS = {"pi": math.pi, "e": math.e, "twopi": TWO_PI, "halfpi": 0.5 * math.pi, "pi2": math.pi ** 2}
_FUNCTIONS = {
    "sin": (math.sin, 1), "cos": (math.cos, 1), "tan": (math.tan, 1), "asin": (math.asin, 1),
    "acos": (math.acos, 1), "atan": (math.atan, 1), "atan2": (math.atan2, 2), "sinh": (math.sinh, 1),
    "cosh": (math.cosh, 1), "tanh": (math.tanh, 1), "sqrt": (math.sqrt, 1), "exp": (math.exp, 1),
    "log": (math.log, 1), "log10": (math.log10, 1), "pow": (math.pow, 2), "abs": (abs, 1),
    "fabs": (abs, 1), "min": (min, 2), "max": (max, 2),
}


# CLHEP's evaluator reads integers with leading zeros ("005") as decimals; Python's parser
# refuses them. Zeros after a letter, digit, '_' or '.' (names, 1e05, 2.005) are left alone.
_LEADING_ZEROS = re.compile(r"(?<![\w.])0+(?=\d)")


def short(text: str, limit: int = 60) -> str:
    """`text` on one line, cut to `limit` characters, for messages."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[:limit - 3] + "..."


class Expressions:
    """The scalars of a document's <define> section and the evaluator that reads them."""

    def __init__(self):
        self.scalars: dict[str, object] = {}     # name -> float, or FormatError deferred until used

    def evaluate(self, text: str) -> float:
        """A GDML expression's value; FormatError with a bare message (callers add the place)."""
        s = text.strip()
        if not s:
            raise FormatError("empty expression")
        if len(s) > MAX_EXPRESSION_CHARS:
            raise FormatError(f"expression longer than {MAX_EXPRESSION_CHARS} characters")
        if "**" in s:
            raise FormatError(f"bad expression {short(s)!r}: '**' is not GDML; use '^'")
        if "[" in s or "]" in s:
            s = self.solve_brackets(s)
        try:
            tree = ast.parse(_LEADING_ZEROS.sub("", s).replace("^", "**"), mode="eval")
        except (SyntaxError, ValueError, RecursionError, MemoryError, OverflowError):
            raise FormatError(f"bad expression {short(s)!r}") from None
        try:
            value = self._walk(tree.body, 0)
        except FormatError:
            raise
        except RecursionError:
            raise FormatError(f"expression {short(s)!r} is nested too deeply") from None
        except (ZeroDivisionError, OverflowError, ValueError) as e:
            raise FormatError(f"expression {short(s)!r}: {e}") from None
        if not math.isfinite(value):
            raise FormatError(f"expression {short(s)!r} is not finite")
        return value

    def _walk(self, node, depth: int) -> float:
        if depth > MAX_EXPRESSION_DEPTH:
            raise FormatError(f"expression nested more than {MAX_EXPRESSION_DEPTH} deep")
        if isinstance(node, ast.Constant):
            v = node.value
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise FormatError(f"{v!r} is not a number")
            return float(v)
        if isinstance(node, ast.Name):
            return self.lookup(node.id)
        if isinstance(node, ast.BinOp):
            a, b = self._walk(node.left, depth + 1), self._walk(node.right, depth + 1)
            op = type(node.op)
            if op is ast.Add:
                r = a + b
            elif op is ast.Sub:
                r = a - b
            elif op is ast.Mult:
                r = a * b
            elif op is ast.Div:
                r = a / b
            elif op is ast.Pow:
                r = math.pow(a, b)
            else:
                raise FormatError(f"operator {type(node.op).__name__} is not allowed")
            if not math.isfinite(r):
                raise FormatError("a result is not finite (overflow)")
            return r
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            v = self._walk(node.operand, depth + 1)
            return -v if isinstance(node.op, ast.USub) else v
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and not node.keywords:
            fn = _FUNCTIONS.get(node.func.id)
            if fn is None:
                raise FormatError(f"unknown function {node.func.id!r}")
            if len(node.args) != fn[1] or any(isinstance(a, ast.Starred) for a in node.args):
                raise FormatError(f"{node.func.id} takes {fn[1]} argument(s), got {len(node.args)}")
            r = float(fn[0](*(self._walk(a, depth + 1) for a in node.args)))
            if not math.isfinite(r):
                raise FormatError(f"{node.func.id}(...) is not finite")
            return r
        raise FormatError(f"{type(node).__name__} is not allowed in an expression")

    def integer(self, text: str) -> int:
        """An expression that must have a whole value (loop bounds, matrix indices)."""
        value = self.evaluate(text)
        if value != int(value):
            raise FormatError(f"{short(text)!r} must have a whole value, got {value:g}")
        return int(value)

    def solve_brackets(self, text: str) -> str:
        """Geant4's `SolveBrackets`: `m[i,j]` names the element `m_<i-1>_<j-1>`, each index an
        integer expression counted from 1 (matrix elements; names generated inside loops)."""
        out, pos = [], 0
        while True:
            open_ = text.find("[", pos)
            close = text.find("]", pos)
            if open_ < 0 and close < 0:
                return "".join(out) + text[pos:]
            if open_ < 0 or close < open_ or "[" in text[open_ + 1:close]:
                raise FormatError(f"bracket mismatch in {short(text)!r}")
            out.append(text[pos:open_])
            for index in text[open_ + 1:close].split(","):
                out.append(f"_{self.integer(index) - 1}")
            pos = close + 1

    def define_matrix(self, name: str, coldim: int, values: list[float]):
        """A <matrix>'s elements as constants, named as Geant4's `DefineMatrix` names them."""
        if not values or coldim < 1 or len(values) % coldim:
            raise FormatError(f"matrix {name!r}: {len(values)} values do not fill rows of {coldim}")
        if coldim == 1 or coldim == len(values):
            for i, v in enumerate(values):
                self.scalars[f"{name}_{i}"] = v
        else:
            for k, v in enumerate(values):
                self.scalars[f"{name}_{k // coldim}_{k % coldim}"] = v

    def lookup(self, name: str) -> float:
        if name in self.scalars:
            v = self.scalars[name]
            if isinstance(v, FormatError):
                raise FormatError(f"{name!r} could not be evaluated: {v}")
            return v
        if name in UNITS:
            return UNITS[name]
        if name in _CONSTANTS:
            return _CONSTANTS[name]
        raise FormatError(f"undefined name {name!r} (constants must be defined before they are used)")
