"""GDML's <define> section (scalars in document order, named positions, rotations, scales)
and placements: the (translation, rotation, scale) of a boolean operand or a physvol.

Rotations follow Geant4 (`G4GDMLReadDefine::GetRotationMatrix`): R = Rz(z) Ry(y) Rx(x),
right-handed and active; see the package docstring for who applies R and who R^-1.
"""
from __future__ import annotations

import math
import re

import numpy as np

from ..reading import FormatError


def rotation_matrix(angles) -> np.ndarray:
    """R = Rz(z) Ry(y) Rx(x) for GDML rotation angles (radians), right-handed and active."""
    x, y, z = angles
    cx, sx, cy, sy, cz, sz = math.cos(x), math.sin(x), math.cos(y), math.sin(y), math.cos(z), math.sin(z)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def affine(linear: np.ndarray, offset) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = linear
    m[:3, 3] = offset
    return m


def read_defines(doc, section):
    for el in section:
        tag = el.tag
        if tag in ("constant", "variable", "quantity", "expression"):
            name = el.get("name")
            if not name or not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", name):
                doc.fail(el, f"a {tag} needs a name made of letters, digits and '_', got {name!r}")
            if name in doc.expressions.scalars:
                doc.fail(el, f"{name!r} is defined twice")
            try:
                if tag == "expression":
                    value = doc.expressions.evaluate(el.text or "")
                else:
                    attr = "value"
                    value = doc.number(el, attr)
                    if tag == "quantity" and el.get("unit") is not None:
                        value *= doc.unit(el, "unit", "1")
            except FormatError as e:
                value = e if str(e).startswith(doc.source) else FormatError(f"{doc.where(el)}: {e}")
            doc.expressions.scalars[name] = value
            if tag == "variable":
                doc.variables.add(name)
        elif tag in doc.vectors:
            name = el.get("name")
            if not name:
                doc.fail(el, f"a <{tag}> in <define> needs a name")
            if name in doc.vectors[tag]:
                doc.fail(el, f"{tag} {name!r} is defined twice")
            doc.vectors[tag][name] = el
        elif tag == "matrix":
            _read_matrix(doc, el)
        else:
            doc.fail(el, f"unknown define element <{tag}>")


def _read_matrix(doc, el):
    """A <matrix>'s elements become constants (`m[i,j]` in expressions). Optical property
    tables are matrices too: a value that fails to evaluate is an error only where it is used."""
    name = el.get("name")
    if not name or not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", name):
        doc.fail(el, f"a matrix needs a name made of letters, digits and '_', got {name!r}")
    words = (el.get("values") or "").split()
    coldim = el.get("coldim", "1")
    try:
        coldim_value = doc.expressions.integer(coldim)
        values = [doc.expressions.evaluate(w) for w in words]
        doc.expressions.define_matrix(name, coldim_value, values)
    except FormatError as e:
        deferred = FormatError(f"{doc.where(el)}: {e}")
        for k in range(len(words)):
            doc.expressions.scalars.setdefault(f"{name}_{k}", deferred)


def vector(doc, el, kind: str) -> np.ndarray:
    """x, y, z of a <position>/<rotation>/<scale> element, in mm / rad / 1."""
    if kind == "scale":
        return np.array([doc.number(el, a, 1.0) for a in "xyz"])
    default = "mm" if kind == "position" else "rad"
    stray = "lunit" if kind == "position" else "aunit"
    if el.get("unit") is None and el.get(stray) is not None:
        # Geant4 (G4GDMLReadDefine::VectorRead) reads only `unit` here; we place what it places.
        doc.warn(el, f'{stray}="{el.get(stray)}" is not read on a <{el.tag}> (Geant4 reads only unit=); '
                     f"its values are in {default}")
    unit = doc.unit(el, "unit", default)
    return np.array([doc.number(el, a, 0.0, unit) for a in "xyz"])


def vector_ref(doc, el, kind: str) -> np.ndarray:
    name = el.get("ref")
    if not name:
        doc.fail(el, "needs a ref attribute")
    target = doc.vectors[kind].get(name)
    if target is None:
        doc.fail(el, f"refers to undefined {kind} {name!r}")
    return vector(doc, target, kind)


def placement(doc, el, prefix: str = ""):
    """(translation, rotation angles, scale) from inline or referenced children of `el`."""
    found = {"position": np.zeros(3), "rotation": np.zeros(3), "scale": np.ones(3)}
    for child in el:
        tag = child.tag
        for kind in found:
            if tag == prefix + kind:
                found[kind] = vector(doc, child, kind)
            elif tag == prefix + kind + "ref":
                found[kind] = vector_ref(doc, child, kind)
    return found["position"], found["rotation"], found["scale"]
