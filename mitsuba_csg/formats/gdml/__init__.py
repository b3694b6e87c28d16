"""Geant4 GDML files (`.gdml`): defines, solids, structure and setup as a CSG model.

    load(path, *, solid=None, depth=None, show_world=None, on_unsupported="error") -> Node
    loads(text, source="<string>", *, base_dir=None, **same) -> Node

Output units are **millimetres** (Geant4's internal length unit); angles are read in radians
unless `aunit`/`unit` says otherwise. Without `solid`, the result is the placed scene: the
union of every placed logical volume below the world (the world itself with `show_world=True`,
or by default when nothing is placed in it: a file of one volume shows that volume), each one its GDML solid moved to its world placement and named with its
material (the `materialref`, with Geant4's `0x...` pointer suffix stripped). Daughters are not
subtracted from their mothers: for opaque rendering the outermost level is what one sees, so
`depth=k` keeps the volumes at most k placement levels below the world (the world's daughters
are depth 1; an assembly is transparent, its contents count as daughters of the volume that
places it, as in Geant4). `solid="name"` gives one GDML solid in its own frame, no material.

What is read
------------
* `<define>`: constant, variable, quantity, expression (scalars, in document order as Geant4
  evaluates them), position, rotation, scale, matrix (elements as `m[i,j]`). Attribute values are
  arithmetic over numbers, defined scalars, units (mm cm m km um nm angstrom deg rad mrad ...),
  pi/e, `+ - * / ^` and sin cos tan asin acos atan atan2 sqrt exp log log10 pow abs min max;
  evaluated by a whitelisted `ast` walker, never `eval`.
* Solids: box, tube, cutTube, cone, sphere, orb, torus, polycone, polyhedra (zplane rmax is
  the apothem), trd, trap, para, tet, ellipsoid, eltube, elcone, union, subtraction,
  intersection, multiUnion, scaledSolid, paraboloid and hype (quadric leaves); tessellated and xtru
  as triangle-mesh leaves. Phi segments are intersections with (or, above 180 degrees,
  subtractions of) convex wedges; rmin holes are subtracted cones/spheres/tori extended past
  the caps so no faces coincide; theta cuts are cones with their apex at the centre.
* `<loop>`s (`loops`), and volumes placed many times by one element: replicavol,
  divisionvol, paramvol (`replicas`), expanded into copies as Geant4 places them.
* genericPolycone, genericPolyhedra (exact frusta), reflectedSolid; arb8 and the twisted
  solids as swept-polygon meshes (`twisted`). Not read: `physvol file=`, radial replicas,
  divisions of other solids than boxes. `on_unsupported="error"` raises a
  FormatError naming the element and its name; `"skip"` warns (UserWarning) and leaves the solid
  out, together with every boolean built from it and every volume made of it.

Transform conventions (Geant4 10/11, `G4GDMLReadDefine::GetRotationMatrix`): a `<rotation>`
x, y, z builds R = Rz(z) Ry(y) Rx(x) (CLHEP `rotateX` then `rotateY` then `rotateZ`, each a
left multiplication, right-handed and active). `G4GDMLReadSolids::BooleanRead` builds
`G4Transform3D(R, t)` for `second` (and for `firstposition/firstrotation`, multiUnion nodes):
the operand moves by x' = R x + t. `G4GDMLReadStructure::PhysvolRead` builds
`G4Transform3D(R.inverse(), t) * G4Scale3D(s)`: a daughter moves by x' = R^-1 (s x) + t; the
GDML rotation of a physvol is the frame rotation, i.e. the inverse of the object rotation.

Files are untrusted input: every problem is a `FormatError` whose message starts with the
source and the line and element, e.g. `det.gdml: line 12: <tube name="t1">: rmax: must be > 0`.
XML is parsed by expat with a DOCTYPE policy: internal entities are allowed but may not refer
to other entities (the entity-expansion bomb pattern) and are size-bounded; external entities
(`<!ENTITY m SYSTEM "materials.xml">`, Geant4's G01 example) are read only from files in the
document's directory or below it, never from the network; parameter entities and external DTDs
are not read. Element counts, text size, nesting and placement counts are bounded.
"""
from __future__ import annotations

import os

import numpy as np

from ...model.nodes import Node
from ..reading import FormatError, read_model_bytes
from .document import Document
from .expressions import UNITS
from .solids import Solids
from .structure import PlacedVolume, placed_volumes, scene
from .xml_reader import MAX_FILE_BYTES, parse_xml

__all__ = ["FormatError", "PlacedVolume", "UNITS", "load", "loads", "volumes"]

# ---- Entry points ----

_OPTIONS = ("solid", "depth", "show_world", "on_unsupported")


def _check_options(depth, on_unsupported, source):
    if on_unsupported not in ("error", "skip"):
        raise FormatError(f"{source}: on_unsupported must be 'error' or 'skip', got {on_unsupported!r}")
    if depth is not None and (isinstance(depth, bool) or not isinstance(depth, (int, np.integer)) or depth < 0):
        raise FormatError(f"{source}: depth must be None or an integer >= 0, got {depth!r}")


def loads(text, source: str = "<string>", *, base_dir: str | None = None, solid: str | None = None,
          depth: int | None = None, show_world: bool | None = None, on_unsupported: str = "error") -> Node:
    """Read a GDML document from a string or bytes; see the module docstring. Lengths in mm."""
    _check_options(depth, on_unsupported, source)
    data = text.encode("utf-8") if isinstance(text, str) else bytes(text)
    if len(data) > MAX_FILE_BYTES:
        raise FormatError(f"{source}: larger than {MAX_FILE_BYTES} bytes")
    root, lines = parse_xml(data, source, base_dir)
    doc = Document(root, lines, source, on_unsupported)
    solids = Solids(doc)
    if solid is not None:
        if solid not in doc.solid_elements:
            raise FormatError(f"{source}: no solid named {solid!r}" +
                              (f"; solids: {', '.join(list(doc.solid_elements)[:20])}"
                               if doc.solid_elements else "; the document defines no solids"))
        node = solids.solid(solid, root)
        if node is None:
            raise FormatError(f"{source}: solid {solid!r} is not supported and was skipped")
        return node
    return scene(doc, solids, depth, show_world)


def volumes(path, *, depth: int | None = None, show_world: bool | None = None,
            on_unsupported: str = "error") -> list[PlacedVolume]:
    """The placed volumes of a GDML file one by one (`PlacedVolume`: solid, placement level with
    the world's daughters at 1, volume name, colour), in pre-order: what `load` unites, for
    per-volume work such as drawing mothers see-through or hiding volumes by name."""
    path = os.fspath(path)
    _check_options(depth, on_unsupported, path)
    data, _ = read_model_bytes(path, MAX_FILE_BYTES)
    source = os.path.basename(path) or path
    root, lines = parse_xml(data, source, os.path.dirname(os.path.abspath(path)))
    doc = Document(root, lines, source, on_unsupported)
    return placed_volumes(doc, Solids(doc), depth, show_world)


def load(path, *, solid: str | None = None, depth: int | None = None, show_world: bool | None = None,
         on_unsupported: str = "error") -> Node:
    """Read a GDML file: the placed scene (world hidden unless it is all there is), or with `solid=` one solid in its own frame.

    Lengths are in mm. `depth` keeps placed volumes at most that many levels below the world;
    `on_unsupported` is "error" (FormatError) or "skip" (warn and leave the solid out).
    """
    path = os.fspath(path)
    data, _ = read_model_bytes(path, MAX_FILE_BYTES)
    source = os.path.basename(path) or path
    return loads(data, source, base_dir=os.path.dirname(os.path.abspath(path)), solid=solid, depth=depth,
                 show_world=show_world, on_unsupported=on_unsupported)
