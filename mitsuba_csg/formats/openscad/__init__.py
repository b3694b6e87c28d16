"""OpenSCAD `.csg` files (what `openscad -o model.csg model.scad` writes) -> a CSG model.

    group() {
        difference() {
            cube(size = [10, 10, 10], center = true);
            sphere($fn = 0, $fa = 12, $fs = 2, r = 6);
        }
        color([1, 0, 0, 1]) multmatrix([[1, 0, 0, 8], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]) {
            cylinder(h = 4, r1 = 2, r2 = 0, center = false);
        }
    }

Supported nodes: `group`, `union`, `render` (implicit unions), `difference`, `intersection`,
`multmatrix(m)` (4x4 or 3x4 affine), `color(c, alpha)` (a material named `color_R_G_B_A`,
or the colour's name for `color("red")`), `cube(size, center)`, `sphere(r | d)`,
`cylinder(h, r1, r2 | r | d | d1 | d2, center)` (cones and r = 0 ends included),
`polyhedron(points, faces)` (a convex polyhedron when it is one, otherwise a closed mesh
leaf), and 2D outlines extruded: `square`, `circle` (with OpenSCAD's `$fn`/`$fa`/`$fs`
fragments), `polygon(points, paths)`, their 2D unions, differences, intersections and
placements, under `linear_extrude(height, center, twist, slices, scale)` or
`rotate_extrude(angle)` (an outline wholly at x <= 0 sweeps as its mirror; one across the axis
is dropped with a warning, as OpenSCAD reports it and renders the rest), as mesh leaves
(`shapes_2d`); `offset(r | delta, chamfer)` (Clipper's joins, as OpenSCAD) and
`resize(newsize, auto)` (OpenSCAD's scale rule, measured on our exact solid); `projection(cut)`
(the shadow, or the section at z = 0, of the faceted children); `text()`, whose
glyphs OpenSCAD itself draws where it is installed (`tool`); `hull()` and
`minkowski()` of OpenSCAD's faceted solids: convex polyhedra from the facet points of
unions, placements and primitives, and otherwise (differences, extrusions, non-convex
operands) manifold3d's hull and Minkowski sum of the faceted subtree, a mesh leaf. Malformed
polyhedra (open, inconsistently oriented, bad indices) are dropped with a warning, as OpenSCAD
drops them. `.scad` sources are evaluated by OpenSCAD first (`load_scad`). The modifiers `#` (highlight)
and `!` (root: that subtree alone is the model, as in OpenSCAD) keep their subtree; `%`
(background) and `*` (disabled) drop it. Spheres and cylinders are the exact analytic solids,
except where `$fn` is set explicitly to at most FACETED_FN (16): a `cylinder(r = 3, h = 2,
$fn = 6)` is a nut trap, the hexagonal prism OpenSCAD builds (`facets="exact"` or
`"openscad"` makes every one round or OpenSCAD's polygon); a 2D circle is OpenSCAD's polygon,
as OpenSCAD renders its extrusions. A twisted extrusion's side quads may be split along the other diagonal than
the OpenSCAD version at hand chooses.

Semantics follow OpenSCAD: a cube has its corner at the origin unless `center = true`; a
cylinder spans z in [0, h] unless centred; degenerate solids (a size, radius or height <= 0,
a singular `multmatrix`) produce nothing, with an `OpenSCADWarning`. "Nothing" is handled as
OpenSCAD does: a difference whose first operand is empty is empty, an intersection with an
empty operand is empty, a node with no geometric children at all (`group();`) is not an
operand. A model that ends up empty is a `FormatError`.

Files are untrusted input: every problem is a `FormatError` (a `ModelError`) whose message
starts with the file, line and column, e.g. `model.csg: line 3, column 5: sphere: r must be a
finite number, got inf`. Unsupported nodes (`import`, `surface`, `roof`, `fill`) are
refused by name, or skipped with a warning when `on_unsupported="skip"`.
File size, statement count and nesting depth are bounded; parsing and evaluation use
explicit stacks, never deep recursion.
"""
from __future__ import annotations

import os

from ...errors import ModelError
from ...model.nodes import Node
from ..reading import FormatError, read_model_bytes
from . import limits, shapes_2d
from .evaluator import FACET_MODES, FACETED_FN, NULL, SUPPORTED_NODES, UNSUPPORTED_NODES, Evaluator, Nothing
from .parser import Parser
from .source import OpenSCADWarning, Source

__all__ = ["FormatError", "OpenSCADWarning", "load", "loads", "load_scad", "SUPPORTED_NODES", "UNSUPPORTED_NODES",
           "FACETED_FN", "FACET_MODES"]


def loads(text: str | bytes, source: str = "<string>", *, on_unsupported: str = "error",
          facets: str = "auto") -> Node:
    """The model of OpenSCAD `.csg` text; `source` names it in messages. `facets`: 'auto' (an
    explicit `$fn` <= FACETED_FN makes spheres and cylinders OpenSCAD's polygon solids, others
    exact), 'exact' (always round) or 'openscad' (always OpenSCAD's facets)."""
    if on_unsupported not in ("error", "skip"):
        raise ModelError(f"on_unsupported: expected 'error' or 'skip', got {on_unsupported!r}")
    if facets not in FACET_MODES:
        raise ModelError(f"facets: expected one of {', '.join(FACET_MODES)}, got {facets!r}")
    if isinstance(text, (bytes, bytearray)):
        if len(text) > limits.MAX_FILE_BYTES:
            raise FormatError(f"{source}: {len(text)} bytes is larger than the limit of {limits.MAX_FILE_BYTES}")
        try:
            text = bytes(text).decode("utf-8")
        except UnicodeDecodeError as e:
            line = bytes(text).count(b"\n", 0, e.start) + 1
            raise FormatError(f"{source}: not UTF-8 text (invalid byte at offset {e.start}, line {line})") from None
    if not isinstance(text, str):
        raise FormatError(f"{source}: expected .csg text, got {type(text).__name__}")
    if len(text) > limits.MAX_FILE_BYTES:
        raise FormatError(f"{source}: {len(text)} characters is larger than the limit of {limits.MAX_FILE_BYTES}")
    src = Source(source, text.removeprefix("\ufeff"))
    statements = Parser(src).parse()
    result = Evaluator(src, on_unsupported, facets).evaluate(statements)
    if isinstance(result, shapes_2d.Shape2D):
        raise FormatError(f"{source}: the model is 2D (extrude it with linear_extrude or rotate_extrude)")
    if isinstance(result, Nothing):
        raise FormatError(f"{source}: the model is empty (no solid geometry"
                          f"{'' if result is NULL else ': every solid is degenerate or removed'})")
    return result


def load_scad(path, *, on_unsupported: str = "error", facets: str = "auto") -> Node:
    """Read an OpenSCAD source (`.scad`): OpenSCAD evaluates it to its CSG tree (`openscad -o
    model.csg model.scad`, `formats.openscad.tool`), which `loads` reads. Without OpenSCAD
    installed, a CSGError says how to install it or export the tree elsewhere."""
    from . import tool as openscad_tool
    read_model_bytes(path, limits.MAX_FILE_BYTES)      # exists, is a plain file, not too large: what OpenSCAD reads
    text = openscad_tool.export_csg(path)
    name = os.path.basename(os.fspath(path))
    return loads(text, f"{name} (as OpenSCAD's .csg export)", on_unsupported=on_unsupported, facets=facets)


def load(path, *, on_unsupported: str = "error", facets: str = "auto") -> Node:
    """Read an OpenSCAD `.csg` file (`openscad -o model.csg model.scad`).

    `on_unsupported="error"` (default) refuses 2D, extrusion and other unsupported nodes with
    a FormatError naming the node and line; `"skip"` drops them with an OpenSCADWarning.
    """
    raw, source = read_model_bytes(path, limits.MAX_FILE_BYTES)
    return loads(raw, source, on_unsupported=on_unsupported, facets=facets)
