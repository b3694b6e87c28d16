"""Checks of user-given numbers, shared by the primitives and every file reader.

Each check returns the value (a float, or an int) or raises `ValueProblem`, whose message
says what is wrong but not where: the caller names the place (a parameter such as
`Sphere.radius`, a JSON path, a GDML element and attribute). `describe` spells the
offending value the way the caller's users write it (JSON literals, GDML numbers).
"""
from __future__ import annotations

import math

import numpy as np

from ..errors import ModelError


class ValueProblem(ModelError):
    """A value that fails a check; the message has no place in it."""


def plain(value) -> str:
    """A value as Python users write it: numbers in %g, anything else by its kind."""
    if isinstance(value, (bool, np.bool_)):
        return repr(bool(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value)) if abs(int(value)) < 10 ** 30 else "a huge integer"
    if isinstance(value, (float, np.floating)):
        return f"{float(value):g}"
    return repr(value) if isinstance(value, str) else f"a {type(value).__name__}"


def number(value, describe=plain) -> float:
    """A finite float; bools are not numbers."""
    if type(value) is float and math.isfinite(value):      # the common case, first
        return value
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueProblem(f"expected a number, got {describe(value)}")
    try:
        v = float(value)
    except OverflowError:
        raise ValueProblem("must be finite, got an integer beyond the float range") from None
    if not math.isfinite(v):
        raise ValueProblem(f"must be finite, got {describe(v)}")
    return v


def positive(value, describe=plain) -> float:
    v = number(value, describe)
    if v <= 0:
        raise ValueProblem(f"must be > 0, got {describe(value)}")
    return v


def nonnegative(value, describe=plain) -> float:
    v = number(value, describe)
    if v < 0:
        raise ValueProblem(f"must be >= 0, got {describe(value)}")
    return v


def integer(value, lo: int, hi: int, describe=plain) -> int:
    """An int in lo..hi; floats and bools are refused."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
        raise ValueProblem(f"expected an integer in {lo}..{hi}, got {describe(value)}")
    return int(value)


def checked(check, value, what: str, *args):
    """`check(value, *args)`, with a failure raised as ModelError("what: problem")."""
    try:
        return check(value, *args)
    except ValueProblem as e:
        raise ModelError(f"{what}: {e}") from None
