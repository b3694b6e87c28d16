"""Volumes placed many times by one element: `<replicavol>`, `<divisionvol>`, `<paramvol>`.

Each is expanded into its copies, as Geant4 navigates them: a list of (local placement
matrix, the copy's solid or None for the placed volume's own solid).

* `replicavol` (`G4PVReplica`): copy i of N along a Cartesian axis sits at
  -width (N - 1) / 2 + i width (Geant4 ignores the offset there); around phi it is turned by
  offset + width (i + 1/2). The replicated volume keeps its own solid. Radial replicas are
  not read.
* `divisionvol` (`G4PVDivision`): the mother's solid cut into slices along an axis, each
  slice the copy's solid (the divided volume's own solid is replaced, as
  `G4VDivisionParameterisation` does). Boxes divided along x, y or z are read: slice i spans
  [-d + offset + i w, -d + offset + (i + 1) w] of the mother's half length d, where the width
  w comes from `number` ((2 d - offset) / number), from `width` (then number = floor((2 d -
  offset) / w)), or from both.
* `paramvol` (`G4GDMLParameterisation`): each `<parameters>` gives a copy's position,
  rotation (a frame rotation, as for a physvol) and dimensions (`box_dimensions`, ...),
  which name the solid's GDML attributes (a tube's `InR`, `OutR`, `hz`, `StartPhi`,
  `DeltaPhi` are `rmin`, `rmax`, `z`, `startphi`, `deltaphi`).
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np

from ...model.primitives import Box
from .defines import affine, placement, rotation_matrix

MAX_COPIES = 1_000_000      # copies made by one replica, division or parameterisation

_AXES = {"kXAxis": 0, "kYAxis": 1, "kZAxis": 2, "kRho": "rho", "kPhi": "phi"}
# <X_dimensions> of a parameterisation -> (solid element, attribute renames)
_DIMENSIONS = {
    "box_dimensions": ("box", {}), "trd_dimensions": ("trd", {}), "trap_dimensions": ("trap", {}),
    "tube_dimensions": ("tube", {"InR": "rmin", "OutR": "rmax", "hz": "z", "StartPhi": "startphi",
                                 "DeltaPhi": "deltaphi"}),
    "cone_dimensions": ("cone", {}), "sphere_dimensions": ("sphere", {}), "orb_dimensions": ("orb", {}),
    "torus_dimensions": ("torus", {}), "ellipsoid_dimensions": ("ellipsoid", {}),
    "para_dimensions": ("para", {}),
}


def _count(doc, el, text, what) -> int:
    try:
        n = doc.expressions.integer(text)
    except Exception as e:          # FormatError with the bare message
        doc.fail(el, f"{what}: {e}")
    if not 0 <= n <= MAX_COPIES:
        doc.fail(el, f"{what}: expected 0..{MAX_COPIES} copies, got {n}")
    return n


def _translation(axis: int, value: float) -> np.ndarray:
    offset = np.zeros(3)
    offset[axis] = value
    return affine(np.eye(3), offset)


def replica_copies(doc, el):
    """(target reference element, [(matrix, None)]) of a <replicavol>."""
    number = _count(doc, el, el.get("number", ""), "number")
    along = el.find("replicate_along_axis")
    if along is None:
        doc.fail(el, "needs <replicate_along_axis>")
    direction = along.find("direction")
    if direction is None:
        doc.fail(along, "needs <direction x|y|z|rho|phi=\"1\"/>")
    axes = [a for a in ("x", "y", "z", "rho", "phi") if direction.get(a) is not None
            and doc.number(direction, a) == 1.0]
    if len(axes) != 1:
        doc.fail(direction, "needs exactly one of x, y, z, rho, phi set to 1")
    width = _quantity(doc, along, "width")
    offset = _quantity(doc, along, "offset", 0.0)
    if width <= 0:
        doc.fail(along, f"<width>: must be > 0, got {width:g}")
    axis = axes[0]
    if axis == "rho":
        doc.unsupported(el, "radial replicas (<direction rho=\"1\"/>) are not supported")
        return []
    if axis == "phi":
        copies = []
        for i in range(number):
            turn = offset + width * (i + 0.5)
            c, s = math.cos(turn), math.sin(turn)
            copies.append((affine(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.zeros(3)), None))
        return copies
    k = "xyz".index(axis)
    return [(_translation(k, -width * 0.5 * (number - 1) + width * i), None) for i in range(number)]


def _quantity(doc, parent, tag, default=None) -> float:
    q = parent.find(tag)
    if q is None:
        if default is None:
            doc.fail(parent, f"needs <{tag} value=\"...\" unit=\"...\"/>")
        return default
    unit = doc.unit(q, "unit", "mm")
    return doc.number(q, "value", None, unit)


def division_copies(doc, el, mother_solid_el):
    """[(matrix, slice solid)] of a <divisionvol> in a volume whose solid is `mother_solid_el`."""
    axis = _AXES.get(el.get("axis", ""))
    if axis is None:
        doc.fail(el, f"axis: expected one of {', '.join(_AXES)}, got {el.get('axis')!r}")
    if mother_solid_el.tag != "box" or axis in ("rho", "phi"):
        doc.unsupported(el, f"a division of a <{mother_solid_el.tag}> along {el.get('axis')} is not supported "
                            f"(boxes along kXAxis, kYAxis, kZAxis are)")
        return []
    unit = doc.unit(el, "unit", "mm")
    number = _count(doc, el, el.get("number", "0"), "number")
    width = doc.number(el, "width", 0.0, unit)
    offset = doc.number(el, "offset", 0.0, unit)
    lunit = doc.unit(mother_solid_el, "lunit", "mm")
    size = np.array([doc.number(mother_solid_el, a, None, lunit) for a in "xyz"])
    full = size[axis]
    if width < 0 or offset < 0 or offset >= full:
        doc.fail(el, f"needs width >= 0 and 0 <= offset < the mother's length {full:g}")
    if number > 0 and width == 0:
        width = (full - offset) / number
    elif number == 0 and width > 0:
        number = _count(doc, el, repr(int((full - offset) / width)), "number")   # as Geant4 rounds
    elif number == 0:
        doc.fail(el, "needs number or width")
    if offset + number * width > full * (1 + 1e-9):
        doc.fail(el, f"{number} slices of {width:g} from offset {offset:g} do not fit in the mother's "
                     f"length {full:g}")
    slab = size.copy()
    slab[axis] = width
    solid = Box(slab)
    return [(_translation(axis, -0.5 * full + offset + (i + 0.5) * width), solid) for i in range(number)]


def parameterised_copies(doc, solids, el):
    """[(matrix, copy solid)] of a <paramvol>."""
    ncopies = _count(doc, el, el.get("ncopies", ""), "ncopies")
    block = el.find("parameterised_position_size")
    if block is None:
        doc.fail(el, "needs <parameterised_position_size>")
    copies = []
    for parameters in block.findall("parameters"):
        dims = [child for child in parameters if child.tag.endswith("_dimensions")]
        if len(dims) != 1:
            doc.fail(parameters, "needs exactly one <..._dimensions> element")
        known = _DIMENSIONS.get(dims[0].tag)
        if known is None:
            doc.unsupported(dims[0], f"<{dims[0].tag}> is not supported (supported: {', '.join(_DIMENSIONS)})")
            return []
        tag, renames = known
        solid_el = ET.Element(tag, {renames.get(k, k): v for k, v in dims[0].attrib.items()})
        doc.lines[id(solid_el)] = doc.lines.get(id(dims[0]))
        solid = solids.build(solid_el)
        if solid is None:
            return []
        t, r, _ = placement(doc, parameters)
        # G4GDMLParameterisation sets the rotation as the frame's (physvol convention).
        copies.append((affine(rotation_matrix(r).T, t), solid))
    if len(copies) != ncopies:
        doc.fail(el, f"ncopies={ncopies} but {len(copies)} <parameters> are given")
    return copies

