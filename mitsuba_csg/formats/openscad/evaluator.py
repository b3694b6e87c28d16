"""Semantics: statements -> a model, as OpenSCAD evaluates its CSG tree (the package's
docstring lists what is supported and how)."""
from __future__ import annotations

import math
import warnings

import numpy as np

from ...errors import ModelError
from ...model import transform as tf
from ...model.nodes import DIFFERENCE, INTERSECTION, UNION, Node, Operation
from ...model.mesh import Mesh, MeshOrientationWarning
from ...model.polyhedra import CONVEX_LEAF_PLANES, convex_planes
from ...model.primitives import Box, Cone, ConvexPolyhedron, Sphere
from ..reading import FormatError
from . import shapes_2d
from .parser import Range, Statement
from .source import Source

SUPPORTED_NODES = ("group", "union", "render", "difference", "intersection", "multmatrix", "color",
                   "cube", "sphere", "cylinder", "polyhedron", "square", "circle", "polygon", "linear_extrude",
                   "rotate_extrude", "hull", "minkowski", "text", "offset", "resize", "projection")
UNSUPPORTED_NODES = {
    # 2D primitives and operations
    "import": "imported geometry",
    "roof": "a 2D-to-3D operation", "fill": "a 2D operation",
    # 3D nodes mitsuba-csg cannot represent exactly
    "surface": "a height-map mesh",
}


class Nothing:
    """NULL: no geometry at all (not an operand); EMPTY: geometry that is the empty set."""

    __slots__ = ("name",)

    def __init__(self, name):
        self.name = name

    def __repr__(self):
        return self.name


NULL, EMPTY = Nothing("NULL"), Nothing("EMPTY")

_POSITIONAL = {
    "cube": ("size", "center"), "sphere": ("r",), "cylinder": ("h", "r1", "r2", "center"),
    "polyhedron": ("points", "faces", "convexity"), "multmatrix": ("m",), "color": ("c", "alpha"),
    "render": ("convexity",), "square": ("size", "center"), "circle": ("r",), "polygon": ("points", "paths"),
    "linear_extrude": ("height",), "rotate_extrude": ("angle",),
    "text": ("text", "size", "font", "halign", "valign", "spacing", "direction", "language", "script"),
    "offset": ("r",), "resize": ("newsize",),
}
_KNOWN_ARGS = {
    "cube": {"size", "center"}, "sphere": {"r", "d"},
    "cylinder": {"h", "r", "r1", "r2", "d", "d1", "d2", "center"},
    "polyhedron": {"points", "faces", "triangles", "convexity"}, "multmatrix": {"m"},
    "color": {"c", "alpha"}, "render": {"convexity"}, "group": set(), "union": set(),
    "difference": set(), "intersection": set(),
    "square": {"size", "center"}, "circle": {"r", "d"}, "polygon": {"points", "paths", "convexity"},
    "linear_extrude": {"height", "center", "convexity", "twist", "slices", "scale", "segments", "v"},
    "rotate_extrude": {"angle", "convexity"}, "hull": set(), "minkowski": {"convexity"},
    "text": {"text", "size", "font", "halign", "valign", "spacing", "direction", "language", "script"},
    "offset": {"r", "delta", "chamfer"}, "resize": {"newsize", "auto", "convexity"},
    "projection": {"cut", "convexity"},
}
_FACETS = {"$fn": 0.0, "$fs": 2.0, "$fa": 12.0}         # OpenSCAD's defaults
# An explicit $fn up to this is a polygon the author wants (a nut trap's $fn = 6): such spheres
# and cylinders are OpenSCAD's faceted solids. Larger $fn, and OpenSCAD's $fa/$fs defaults,
# approximate a circle, which we trace exactly.
FACETED_FN = 16
FACET_MODES = ("auto", "exact", "openscad")


class Evaluator:
    def __init__(self, src: Source, on_unsupported: str, facets: str = "auto"):
        self.src = src
        self.on_unsupported = on_unsupported
        self.facet_mode = facets

    def arguments(self, st: Statement) -> dict:
        names = _POSITIONAL.get(st.name, ())
        known = _KNOWN_ARGS[st.name]
        out = {}
        for i, (key, value, pos) in enumerate(st.args):
            if key is None:
                if i >= len(names):
                    self.src.warn(pos, f"{st.name}: ignoring extra positional argument {i + 1}")
                    continue
                key = names[i]
            elif key.startswith("$"):
                continue               # $fn, $fa, $fs: facet settings; our solids are exact
            elif key not in known:
                self.src.warn(pos, f"{st.name}: ignoring unknown argument {key!r}")
                continue
            if key in out:
                self.src.warn(pos, f"{st.name}: argument {key!r} given more than once; using the last")
            out[key] = (value, pos)
        return out

    # -- value checks --
    def number(self, st, args, key, default):
        if key not in args or args[key][0] is None:
            return default
        value, pos = args[key]
        if isinstance(value, bool) or not isinstance(value, float):
            self.src.fail(pos, f"{st.name}: {key} must be a number, got {_show(value)}")
        if not math.isfinite(value):
            self.src.fail(pos, f"{st.name}: {key} must be a finite number, got {_show(value)}")
        return value

    def flag(self, st, args, key) -> bool:
        if key not in args or args[key][0] is None:
            return False
        value, pos = args[key]
        if not isinstance(value, bool):
            self.src.fail(pos, f"{st.name}: {key} must be true or false, got {_show(value)}")
        return value

    def matrix(self, st, args):
        if "m" not in args or args["m"][0] is None:
            return tf.IDENTITY
        value, pos = args["m"]
        if not (isinstance(value, list) and len(value) in (3, 4) and
                all(isinstance(r, list) and len(r) == 4 for r in value) and
                all(isinstance(x, float) and not isinstance(x, bool) for r in value for x in r)):
            self.src.fail(pos, f"multmatrix: m must be a 4x4 (or 3x4) matrix of numbers, got {_show(value)}")
        if not all(math.isfinite(x) for r in value for x in r):
            self.src.fail(pos, "multmatrix: m has inf or nan entries")
        if len(value) == 4 and max(abs(a - b) for a, b in zip(value[3], (0.0, 0.0, 0.0, 1.0))) > 1e-6:
            self.src.fail(pos, f"multmatrix: the last row must be [0, 0, 0, 1] (projective matrices "
                               f"are not supported), got {_show(value[3])}")
        return np.array(value[:3] + [[0.0, 0.0, 0.0, 1.0]], dtype=np.float64)

    # -- nodes --
    def evaluate(self, root: Statement):
        """Post-order over the statement tree with an explicit stack; returns Node or NULL/EMPTY."""
        target = self.find_root(root)
        if self.on_unsupported == "error":
            self.refuse_unsupported(target)
        return self.subtree_node(target)

    def find_root(self, root: Statement) -> Statement:
        """The first `!` statement in document order outside disabled subtrees, else the file."""
        found = []
        stack = [root]
        while stack:
            st = stack.pop()
            if _suppressed(st):
                continue
            if "!" in st.modifiers:
                found.append(st)
                if len(found) > 1:
                    break
                continue
            stack.extend(reversed(st.children))
        if len(found) > 1:
            self.src.warn(found[1].pos, "more than one root modifier (!); using the first")
        return found[0] if found else root

    def refuse_unsupported(self, root):
        """One FormatError listing every unsupported node kind under `root` with its count:
        the first one's place leads the message, each other kind names its first line."""
        found: dict[str, list] = {}
        stack = [root]
        while stack:
            st = stack.pop()
            if _suppressed(st):
                continue
            if self.is_unsupported(st):
                found.setdefault(st.name, []).append(st.pos)
                continue
            stack.extend(reversed(st.children))
        if not found:
            return
        kinds = sorted(found.items(), key=lambda kv: kv[1][0])
        name, places = kinds[0]
        what = UNSUPPORTED_NODES.get(name)
        text = f"{name} ({what}) is not supported by mitsuba-csg" if what else f"unknown node {name!r}"
        if len(kinds) > 1 or len(places) > 1:
            text += "; in all: " + ", ".join(
                f"{n} x{len(p)}" + (f" (first at line {self.src.line(p[0])})" if i else "")
                for i, (n, p) in enumerate(kinds))
        self.src.fail(places[0], f"{text}; supported nodes: {', '.join(SUPPORTED_NODES)} "
                                 f"(or load with on_unsupported='skip')")

    def is_unsupported(self, st) -> bool:
        return st.name is not None and st.name not in _KNOWN_ARGS

    def node(self, st: Statement, kids: list):
        name = st.name
        if name is None or name in ("group", "union", "render"):
            if name == "render":
                self.arguments(st)
                if not st.children:
                    return EMPTY        # OpenSCAD: intersecting with an empty render() is empty (its issue 996)
            return self.combine(st, UNION, kids)
        if self.is_unsupported(st):
            what = UNSUPPORTED_NODES.get(name)
            text = (f"{name} ({what}) is not supported by mitsuba-csg" if what else
                    f"unknown node {name!r}")
            if self.on_unsupported == "skip":
                self.src.warn(st.pos, f"{text}; skipped (on_unsupported='skip'), its subtree is treated as empty")
                return EMPTY
            self.src.fail(st.pos, f"{text}; supported nodes: {', '.join(SUPPORTED_NODES)} "
                                  f"(or load with on_unsupported='skip')")
        args = self.arguments(st)
        if name in ("difference", "intersection"):
            return self.combine(st, DIFFERENCE if name == "difference" else INTERSECTION, kids)
        try:
            if name == "hull":
                return self.hull(st, kids)
            if name == "minkowski":
                return self.minkowski(st, kids)
            if name in ("linear_extrude", "rotate_extrude"):
                return self.extrude(st, args, self.combine(st, UNION, kids, flat_context=True))
            if name == "offset":
                return self.offset(st, args, self.combine(st, UNION, kids, flat_context=True))
            if name == "resize":
                return self.resize(st, args, self.combine(st, UNION, kids))
            if name == "projection":
                return self.projection(st, args, kids)
        except FormatError:
            raise
        except ModelError as e:
            self.src.fail(st.pos, f"{name}: {e}")
        if name == "multmatrix":
            m = self.matrix(st, args)
            body = self.combine(st, UNION, kids)
            if isinstance(body, Nothing):
                return body
            if m is tf.IDENTITY or np.array_equal(m, tf.IDENTITY):
                return body
            if isinstance(body, shapes_2d.Shape2D):
                return shapes_2d.transform(body, m)
            try:
                return body.transform(m)
            except ModelError:         # singular: the children collapse to nothing 3D
                self.src.warn(st.pos, "multmatrix: singular matrix flattens its children; they are dropped")
                return EMPTY
        if name == "color":
            body = self.combine(st, UNION, kids)
            if isinstance(body, shapes_2d.Shape2D):
                return body           # a 2D colour applies to no leaf of ours
            material = self.color(st, args)
            return body if isinstance(body, Nothing) or material is None else body.with_material(material)
        if st.children:
            self.src.warn(st.pos, f"{name}: ignoring its {len(st.children)} child statement(s); a primitive has none")
        try:
            return getattr(self, "make_" + name)(st, args)
        except FormatError:
            raise
        except ModelError as e:
            self.src.fail(st.pos, f"{name}: {e}")

    def combine(self, st, kind: str, kids: list, flat_context: bool = False):
        """`_combine`, and 2D operands combined in 2D. Operands of the other dimension are
        dropped with a warning, as OpenSCAD does: 2D ones among 3D ones, and 3D ones under
        an extrusion (`flat_context`)."""
        outlines = [k for k in kids if isinstance(k, shapes_2d.Shape2D)]
        solids = [k for k in kids if not isinstance(k, (shapes_2d.Shape2D, Nothing))]
        if flat_context and solids:
            self.src.warn(st.pos, f"{st.name}: ignoring its 3D children (it extrudes 2D ones)")
            kids = [k for k in kids if not isinstance(k, Node)]
            solids = []
            if not outlines:
                return NULL
        if not outlines:
            return _combine(kind, kids)
        if solids:
            self.src.warn(st.pos, f"{st.name or 'group'}: mixing 2D and 3D operands; the 2D ones are ignored")
            return _combine(kind, [k for k in kids if not isinstance(k, shapes_2d.Shape2D)])
        kids = [k for k in kids if k is not NULL]
        if kind == INTERSECTION and any(k is EMPTY for k in kids):
            return EMPTY
        if kind == DIFFERENCE and kids[0] is EMPTY:
            return EMPTY
        return shapes_2d.combine(kind, [k for k in kids if k is not EMPTY])

    def offset(self, st, args, body):
        if isinstance(body, Nothing):
            return body
        r = self.number(st, args, "r", None)
        delta = self.number(st, args, "delta", None)
        if r is None and delta is None:
            r = 1.0                                      # OpenSCAD's default: offset(r = 1)
        fn, fs, fa = self.facets(st)
        shape = shapes_2d.offset(body, r, delta if r is None else None, self.flag(st, args, "chamfer"), fn, fs, fa)
        return EMPTY if shapes_2d.is_empty(shape) else shape

    def projection(self, st, args, kids):
        """OpenSCAD's projection(): the outline of the children's shadow on z = 0, or with
        `cut = true` their section there; of OpenSCAD's faceted solids (manifold3d)."""
        if not any(isinstance(k, Node) for k in kids):
            return EMPTY if any(k is EMPTY for k in kids) else NULL
        pieces = [self.facet_manifold(c) for c in st.children if not _suppressed(c)]
        pieces = [p for p in pieces if not p.is_empty()]
        if not pieces:
            return EMPTY
        import manifold3d as m3
        solid = pieces[0] if len(pieces) == 1 else m3.Manifold.batch_boolean(pieces, m3.OpType.Add)
        shape = shapes_2d.Shape2D(solid.slice(0.0) if self.flag(st, args, "cut") else solid.project())
        return EMPTY if shapes_2d.is_empty(shape) else shape

    def resize(self, st, args, body):
        """OpenSCAD's resize: each axis with a new size > 0 scaled to it; with `auto`, the others
        by the scale of the largest new size; the rest kept. The sizes are of our exact solid
        (OpenSCAD measures its facets: round children differ by their sagitta)."""
        if isinstance(body, Nothing):
            return body
        flat_body = isinstance(body, shapes_2d.Shape2D)
        dims = 2 if flat_body else 3
        newsize = self.sizes(st, args, "newsize", dims)
        auto = self.auto(st, args, dims)
        if flat_body:
            x0, y0, x1, y1 = body.section.bounds()
            size = np.array([x1 - x0, y1 - y0])
        else:
            lo, hi = body.bounds()
            size = hi - lo
        big = int(np.argmax(newsize))
        scale = np.where(newsize > 0, newsize / np.where(size > 0, size, 1.0), 1.0)
        scale = np.where(~auto | (newsize > 0), scale, scale[big])
        if np.any(scale <= 0) or not np.all(np.isfinite(scale)):
            self.src.warn(st.pos, "resize: a zero size cannot be resized; OpenSCAD makes nothing of it")
            return EMPTY
        if flat_body:
            return shapes_2d.scaled(body, float(scale[0]), float(scale[1]))
        return body.scale(tuple(float(v) for v in scale))

    def sizes(self, st, args, key, dims) -> np.ndarray:
        value, pos = args.get(key, (None, st.pos))
        if isinstance(value, float) and not isinstance(value, bool):
            value = [value] * dims
        if not (isinstance(value, list) and 2 <= len(value) <= 3 and
                all(isinstance(x, float) and not isinstance(x, bool) and math.isfinite(x) for x in value)):
            self.src.fail(pos, f"{st.name}: {key} must be a number or a vector of {dims}, got {_show(value)}")
        return np.array((list(value) + [0.0])[:dims])

    def auto(self, st, args, dims) -> np.ndarray:
        value, pos = args.get("auto", (False, st.pos))
        if isinstance(value, bool):
            return np.full(dims, value)
        if isinstance(value, float):
            return np.full(dims, value != 0)
        if isinstance(value, list) and all(isinstance(x, (bool, float)) for x in value):
            return np.array([bool(x) for x in (list(value) + [False] * 3)[:dims]])
        self.src.fail(pos, f"resize: auto must be true, false or a vector of them, got {_show(value)}")

    def make_text(self, st, args):
        """text(): the glyph outline OpenSCAD itself draws (`formats.openscad.tool`)."""
        from . import tool as openscad_tool
        call = "text(" + ", ".join(f"{key} = {_scad(value)}" for key, value, _ in st.args
                                   if key is not None and (key in _KNOWN_ARGS["text"] or key in _FACETS)) + ")"
        try:
            section = openscad_tool.text_outline(call, f"{self.src.name}: {self.src.where(st.pos)}")
        except openscad_tool.OpenSCADMissing as e:
            if self.on_unsupported == "skip":
                self.src.warn(st.pos, f"text: skipped (OpenSCAD, which draws its glyphs, is not installed)")
                return EMPTY
            raise FormatError(str(e)) from None
        shape = shapes_2d.Shape2D(section)
        return EMPTY if shapes_2d.is_empty(shape) else shape

    # -- hull and minkowski: of OpenSCAD's faceted solids, as OpenSCAD computes them --
    def hull(self, st, kids):
        operands = [k for k in kids if not isinstance(k, Nothing)]
        if not operands:
            return EMPTY            # as OpenSCAD: a hull of nothing is empty geometry, not no operand
        if all(isinstance(k, shapes_2d.Shape2D) for k in operands):
            return shapes_2d.hull_2d(operands)
        try:
            points = self.subtree_points(st, "hull")
        except _NeedsMesh:
            points = _vertices(self.facet_manifold(st))
        return self.convex(st, points)

    def minkowski(self, st, kids):
        operands = [k for k in kids if not isinstance(k, Nothing)]
        if not operands:
            return EMPTY
        if all(isinstance(k, shapes_2d.Shape2D) for k in operands):
            sets = []
            for k in operands:
                polygons = k.section.to_polygons()
                hull = shapes_2d.hull_2d([k])
                if len(polygons) != 1 or abs(hull.section.area() - k.section.area()) > 1e-9 * hull.section.area():
                    self.src.fail(st.pos, "minkowski: of 2D operands that are not convex is not supported")
                sets.append(np.asarray(polygons[0], dtype=np.float64))
            return shapes_2d.minkowski_2d_convex(sets)
        live = [c for c in st.children if not _suppressed(c) and c.name not in ("echo", "assert")]
        try:
            sets = [self.subtree_points(c, "minkowski", convex=True) for c in live]
        except _NeedsMesh:
            # A non-convex operand: manifold3d's Minkowski sum of OpenSCAD's facets, a mesh leaf.
            total = None
            for c in live:
                piece = self.facet_manifold(c)
                if piece.is_empty():
                    continue
                total = piece if total is None else total.minkowski_sum(piece)
            if total is None or total.is_empty():
                return EMPTY
            return Mesh.from_manifold(total)
        sets = [p for p in sets if len(p)]
        total = sets[0]
        for pts in sets[1:]:
            total = (total[:, None, :] + pts[None, :, :]).reshape(-1, 3)
            total = np.unique(np.round(total, 12), axis=0)
        return self.convex(st, total)

    def convex(self, st, points):
        solid = shapes_2d.convex_solid(points) if len(points) >= 4 else None
        if solid is None:
            self.src.warn(st.pos, f"{st.name}: no volume; OpenSCAD makes nothing of it")
            return EMPTY
        return solid

    def subtree_points(self, st, what: str, convex: bool = False) -> np.ndarray:
        """World points of the OpenSCAD facets of a 3D subtree (its unions, placements, hulls
        and primitives). With `convex`, the subtree must be one convex solid (a Minkowski
        operand): a primitive or a hull under placements."""
        out = []
        # Each entry says whether its subtree must still be one convex solid: below a hull,
        # everything is inside the hull's convex points.
        stack = [(c, tf.IDENTITY, False) for c in st.children] if not convex else [(st, tf.IDENTITY, True)]
        while stack:
            node, m, convex = stack.pop()
            if _suppressed(node) or node.name in ("echo", "assert"):
                continue
            name = node.name
            live = [c for c in node.children if not _suppressed(c)]
            if name in (None, "group", "union", "render", "color", "multmatrix", "hull"):
                if convex and name != "hull" and len(live) > 1:
                    raise _NeedsMesh(node)
                if name == "multmatrix":
                    m = m @ self.matrix(node, self.arguments(node))
                stack.extend((c, m, convex and name != "hull") for c in live)
            elif name in ("sphere", "cylinder", "cube", "polyhedron"):
                pts = self.primitive_points(node, convex)
                if len(pts):
                    out.append(pts @ m[:3, :3].T + m[:3, 3])
            else:
                raise _NeedsMesh(node)
        return np.vstack(out) if out else np.zeros((0, 3))

    def facet_manifold(self, root):
        """OpenSCAD's faceted solid of a 3D statement subtree as a manifold3d Manifold: its
        primitives with OpenSCAD's facets, booleans, placements, hulls and Minkowski sums as
        manifold3d computes them; other nodes (extrusions, resize, ...) evaluated as usual and
        meshed (their mesh leaves exactly; analytic solids at 64 segments)."""
        import manifold3d as m3
        results: dict[int, object] = {}
        stack = [(root, False)]
        while stack:
            st, done = stack.pop()
            name = st.name
            if _suppressed(st) or name in ("echo", "assert"):
                results[id(st)] = None
                continue
            structural = name in (None, "group", "union", "render", "color", "multmatrix", "difference",
                                  "intersection", "hull", "minkowski")
            if structural and not done:
                stack.append((st, True))
                stack.extend((c, False) for c in reversed(st.children))
                continue
            kids = [results.pop(id(c)) for c in st.children] if structural else []
            kids = [k for k in kids if k is not None]
            if name in ("sphere", "cylinder", "cube"):
                pts = self.primitive_points(st, False)
                results[id(st)] = m3.Manifold.hull_points(pts) if len(pts) >= 4 else None
            elif name == "polyhedron" or not structural:
                node = self.subtree_node(st)
                results[id(st)] = None if isinstance(node, (Nothing, shapes_2d.Shape2D)) else _manifold(node)
            elif not kids:
                results[id(st)] = None
            elif name == "difference":
                out = kids[0]
                for k in kids[1:]:
                    out = out - k
                results[id(st)] = out
            elif name == "intersection":
                out = kids[0]
                for k in kids[1:]:
                    out = out ^ k
                results[id(st)] = out
            elif name == "hull":
                results[id(st)] = m3.Manifold.hull_points(np.vstack([_vertices(k) for k in kids]))
            elif name == "minkowski":
                out = kids[0]
                for k in kids[1:]:
                    out = out.minkowski_sum(k)
                results[id(st)] = out
            else:
                out = m3.Manifold.batch_boolean(kids, m3.OpType.Add) if len(kids) > 1 else kids[0]
                if name == "multmatrix":
                    m = self.matrix(st, self.arguments(st))
                    out = out.transform(np.asarray(m[:3, :4], dtype=np.float64))
                results[id(st)] = out
        out = results[id(root)]
        return out if out is not None else m3.Manifold()

    def subtree_node(self, st):
        """The evaluation of one statement and its subtree: post-order with an explicit stack."""
        results: dict[int, object] = {}
        stack = [(st, False)]
        while stack:
            node, done = stack.pop()
            if _suppressed(node):
                results[id(node)] = NULL
                continue
            if not done and node.children and not self.is_unsupported(node):
                stack.append((node, True))
                stack.extend((c, False) for c in reversed(node.children))
                continue
            kids = [results.pop(id(c)) for c in node.children] if done else []
            results[id(node)] = self.node(node, kids)
        return results[id(st)]

    def primitive_points(self, st, convex: bool) -> np.ndarray:
        args = self.arguments(st)
        fn, fs, fa = self.facets(st)
        if st.name == "sphere":
            r = self.radius(st, args, "r", "d", 1.0)
            return shapes_2d.sphere_points(r, fn, fs, fa) if r > 0 else np.zeros((0, 3))
        if st.name == "cylinder":
            h = self.number(st, args, "h", 1.0)
            r = self.radius(st, args, "r", "d", 1.0)
            r1, r2 = self.radius(st, args, "r1", "d1", r), self.radius(st, args, "r2", "d2", r)
            if h <= 0 or r1 < 0 or r2 < 0 or (r1 == 0 and r2 == 0):
                return np.zeros((0, 3))
            return shapes_2d.cylinder_points(h, r1, r2, self.flag(st, args, "center"), fn, fs, fa)
        if st.name == "cube":
            solid = self.make_cube(st, args)
            if isinstance(solid, Nothing):
                return np.zeros((0, 3))
            return shapes_2d.cube_points(solid.size, self.flag(st, args, "center"))
        solid = self.make_polyhedron(st, args)
        if isinstance(solid, Nothing):
            return np.zeros((0, 3))
        if convex and not isinstance(solid, ConvexPolyhedron):
            self.src.fail(st.pos, "minkowski: of a non-convex polyhedron is not supported")
        return np.array(args["points"][0], dtype=np.float64)

    def facets(self, st) -> tuple[float, float, float]:
        """($fn, $fs, $fa) of a statement (the .csg export writes them on every round node)."""
        found = dict(_FACETS)
        for key, value, pos in st.args:
            if key in found and value is not None:
                if isinstance(value, bool) or not isinstance(value, float) or not math.isfinite(value):
                    self.src.fail(pos, f"{st.name}: {key} must be a finite number, got {_show(value)}")
                found[key] = value
        if found["$fs"] <= 0 or found["$fa"] <= 0:
            self.src.fail(st.pos, f"{st.name}: $fs and $fa must be > 0, got {found['$fs']:g} and {found['$fa']:g}")
        return found["$fn"], found["$fs"], found["$fa"]

    def extrude(self, st, args, body):
        if isinstance(body, Nothing):
            return EMPTY            # an extrusion of nothing is empty geometry (OpenSCAD's issue 996)
        if not isinstance(body, shapes_2d.Shape2D):
            self.src.fail(st.pos, f"{st.name}: its children must be 2D (square, circle, polygon, ...)")
        if shapes_2d.is_empty(body):
            self.src.warn(st.pos, f"{st.name}: the 2D outline is empty; OpenSCAD makes nothing of it")
            return EMPTY
        fn, fs, fa = self.facets(st)
        if st.name == "rotate_extrude":
            angle = self.number(st, args, "angle", 360.0)
            (x0, _, x1, _) = body.section.bounds()
            tol = 1e-9 * max(1.0, abs(x0), abs(x1))
            if x0 < -tol and x1 > tol:
                # OpenSCAD reports an error for this node and renders the rest.
                self.src.warn(st.pos, f"rotate_extrude: the outline spans x = {x0:g} .. {x1:g}, both sides of the "
                                      f"axis; OpenSCAD makes nothing of it")
                return EMPTY
            if x1 <= tol and x0 < -tol:
                body = shapes_2d.scaled(body, -1.0, 1.0)         # all at x <= 0: the mirror image sweeps the same
            if angle == 0:
                self.src.warn(st.pos, "rotate_extrude: angle 0 sweeps nothing")
                return EMPTY
            return shapes_2d.rotate_extrude(body, max(-360.0, min(360.0, angle)), fn, fs, fa)
        height = self.number(st, args, "height", 100.0)
        if height <= 0:
            self.src.warn(st.pos, f"linear_extrude: height {height:g} has no volume; OpenSCAD makes nothing of it")
            return EMPTY
        twist = self.number(st, args, "twist", 0.0)
        slices = self.number(st, args, "slices", None)
        scale = self.pair(st, args, "scale", "[sx, sy]")
        if not all(math.isfinite(x) and x >= 0 for x in scale):
            self.src.fail(args["scale"][1], f"linear_extrude: scale must be finite and >= 0, got {_show(scale)}")
        return shapes_2d.linear_extrude(body, height, self.flag(st, args, "center"), twist,
                                   None if slices is None else max(1, int(slices)), scale, fn, fs, fa)

    def pair(self, st, args, key: str, shape: str) -> list[float]:
        """A 2D argument given as one number or as two: [1, 1] when absent."""
        if key not in args or args[key][0] is None:
            return [1.0, 1.0]
        value, pos = args[key]
        if isinstance(value, float) and not isinstance(value, bool):
            return [value, value]
        if isinstance(value, list) and len(value) == 2 and \
                all(isinstance(x, float) and not isinstance(x, bool) for x in value):
            return list(value)
        self.src.fail(pos, f"{st.name}: {key} must be a number or {shape}, got {_show(value)}")

    def make_square(self, st, args):
        size = self.pair(st, args, "size", "[x, y]")
        if not all(math.isfinite(x) for x in size) or min(size) <= 0:
            self.src.warn(st.pos, f"square: size {_show(size)} has no area; OpenSCAD makes nothing of it")
            return EMPTY
        return shapes_2d.square(size, self.flag(st, args, "center"))

    def make_circle(self, st, args):
        r = self.radius(st, args, "r", "d", 1.0)
        if r <= 0:
            self.src.warn(st.pos, f"circle: radius {r:g} has no area; OpenSCAD makes nothing of it")
            return EMPTY
        return shapes_2d.circle(r, *self.facets(st))

    def make_polygon(self, st, args):
        points = args.get("points", (None, st.pos))
        pts = points[0]
        if pts is None or pts == []:
            self.src.warn(st.pos, "polygon: no points; OpenSCAD makes nothing of it")
            return EMPTY
        if not (isinstance(pts, list) and len(pts) >= 3 and all(
                isinstance(p, list) and len(p) == 2 and
                all(isinstance(x, float) and not isinstance(x, bool) and math.isfinite(x) for x in p) for p in pts)):
            self.src.fail(points[1], "polygon: points must be a list of at least 3 [x, y] with finite numbers")
        paths = args.get("paths", (None, st.pos))[0]
        if paths is not None:
            if not (isinstance(paths, list) and all(isinstance(p, list) and all(
                    isinstance(x, float) and x == int(x) and 0 <= x < len(pts) for x in p) for p in paths)):
                self.src.fail(args["paths"][1], f"polygon: paths must be lists of indices 0..{len(pts) - 1}")
            paths = [[int(x) for x in p] for p in paths]
        shape = shapes_2d.polygon(np.array(pts, dtype=np.float64), paths)
        if shapes_2d.is_empty(shape):
            self.src.warn(st.pos, "polygon: no area; OpenSCAD makes nothing of it")
            return EMPTY
        return shape

    def color(self, st, args):
        if "c" not in args or args["c"][0] is None:
            return None
        value, pos = args["c"]
        alpha = self.number(st, args, "alpha", None)
        if isinstance(value, str):
            name = value.strip()
            if not name:
                self.src.warn(pos, "color: empty colour name; no material")
                return None
            return name if alpha is None or alpha == 1.0 else f"{name}_{alpha:g}"
        if (isinstance(value, list) and len(value) in (3, 4) and
                all(isinstance(x, float) and not isinstance(x, bool) and math.isfinite(x) for x in value)):
            rgba = list(value) + [1.0] * (4 - len(value))
            if alpha is not None:
                rgba[3] = alpha
            return "color_" + "_".join(f"{x:g}" for x in rgba)
        self.src.fail(pos, f"color: c must be [r, g, b], [r, g, b, a] or a colour name, got {_show(value)}")

    def make_cube(self, st, args):
        size = [1.0, 1.0, 1.0]
        if "size" in args and args["size"][0] is not None:
            value, pos = args["size"]
            if isinstance(value, float) and not isinstance(value, bool):
                size = [value] * 3
            elif isinstance(value, list) and len(value) == 3 and \
                    all(isinstance(x, float) and not isinstance(x, bool) for x in value):
                size = list(value)
            else:
                self.src.fail(pos, f"cube: size must be a number or [x, y, z], got {_show(value)}")
            if not all(math.isfinite(x) for x in size):
                self.src.fail(pos, f"cube: size must be finite, got {_show(value)}")
        if min(size) <= 0:
            self.src.warn(st.pos, f"cube: size {_show(size)} has no volume; OpenSCAD makes nothing of it")
            return EMPTY
        box = Box(size)
        return box if self.flag(st, args, "center") else box.translate(np.array(size) / 2)

    def radius(self, st, args, r_key, d_key, default):
        if d_key in args and args[d_key][0] is not None:
            if r_key in args and args[r_key][0] is not None:
                self.src.warn(args[r_key][1], f"{st.name}: ignoring {r_key} as {d_key} is given too")
            return self.number(st, args, d_key, None) / 2
        return self.number(st, args, r_key, default)

    def faceted(self, st) -> bool:
        """Whether a round primitive is OpenSCAD's polygon solid rather than the exact one
        (`facets`: 'auto' for an explicit $fn of at most FACETED_FN, 'openscad' always, 'exact' never)."""
        if self.facet_mode == "exact":
            return False
        if self.facet_mode == "openscad":
            return True
        fn = self.facets(st)[0]
        return 3 <= fn <= FACETED_FN

    def make_sphere(self, st, args):
        r = self.radius(st, args, "r", "d", 1.0)
        if r <= 0:
            self.src.warn(st.pos, f"sphere: radius {r:g} has no volume; OpenSCAD makes nothing of it")
            return EMPTY
        if self.faceted(st):
            return shapes_2d.convex_solid(shapes_2d.sphere_points(r, *self.facets(st)))
        return Sphere(r)

    def make_cylinder(self, st, args):
        h = self.number(st, args, "h", 1.0)
        r = self.radius(st, args, "r", "d", 1.0)
        r1 = self.radius(st, args, "r1", "d1", r)
        r2 = self.radius(st, args, "r2", "d2", r)
        if h <= 0 or r1 < 0 or r2 < 0 or (r1 == 0 and r2 == 0):
            self.src.warn(st.pos, f"cylinder: h={h:g}, r1={r1:g}, r2={r2:g} has no volume; "
                                  "OpenSCAD makes nothing of it")
            return EMPTY
        if self.faceted(st):
            points = shapes_2d.cylinder_points(h, r1, r2, self.flag(st, args, "center"), *self.facets(st))
            return shapes_2d.convex_solid(points)
        cone = Cone(r1, r2, h)
        return cone if self.flag(st, args, "center") else cone.translate((0.0, 0.0, h / 2))

    def malformed(self, pos, problem: str):
        """A polyhedron OpenSCAD reports and leaves out (it renders the rest of the file)."""
        self.src.warn(pos, f"polyhedron: {problem}; OpenSCAD makes nothing of it")
        return EMPTY

    def make_polyhedron(self, st, args):
        points = args.get("points", (None, st.pos))
        faces = args.get("faces") or args.get("triangles") or (None, st.pos)
        if points[0] is None or faces[0] is None or points[0] == [] or faces[0] == []:
            self.src.warn(st.pos, "polyhedron: no points or no faces; OpenSCAD makes nothing of it")
            return EMPTY
        pts = points[0]
        if not (isinstance(pts, list) and all(
                isinstance(p, list) and len(p) == 3 and
                all(isinstance(x, float) and not isinstance(x, bool) and math.isfinite(x) for x in p)
                for p in pts)):
            return self.malformed(points[1], "points must be a list of [x, y, z] with finite numbers")
        fl = faces[0]
        if not (isinstance(fl, list) and all(isinstance(f, list) for f in fl)):
            return self.malformed(faces[1], "faces must be a list of lists of point indices")
        index_faces = []
        for k, f in enumerate(fl):
            if not all(isinstance(x, float) and math.isfinite(x) and x == int(x) for x in f):
                return self.malformed(faces[1], f"face {k} must hold integer point indices, got {_show(f)}")
            idx = [int(x) for x in f]
            bad = [x for x in idx if not 0 <= x < len(pts)]
            if bad:
                return self.malformed(faces[1], f"face {k} refers to point {bad[0]}, but there are "
                                                f"{len(pts)} points (0..{len(pts) - 1})")
            # drop consecutive repeats (including the closing one)
            idx = [x for j, x in enumerate(idx) if x != idx[j - 1]] if len(idx) > 1 else idx
            if len(idx) < 3:
                return self.malformed(faces[1], f"face {k} has fewer than 3 distinct points")
            index_faces.append(idx)
        planes, problem = convex_planes(np.array(pts, dtype=np.float64), index_faces)
        if not problem and len(planes) <= CONVEX_LEAF_PLANES:
            return ConvexPolyhedron(planes)
        # Any other closed polyhedron is a mesh leaf. OpenSCAD lists a face's points clockwise
        # seen from outside: reversed, they are the counter-clockwise triangles a Mesh takes.
        triangles = [(f[0], f[k + 1], f[k]) for f in index_faces for k in range(1, len(f) - 1)]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", MeshOrientationWarning)     # either winding is accepted
            try:
                return Mesh(np.array(pts, dtype=np.float64), np.array(triangles))
            except ModelError as e:
                # OpenSCAD drops it too ("The given mesh is not closed!") and renders the rest.
                self.src.warn(st.pos, f"polyhedron: neither a closed convex solid nor a closed, consistently "
                                      f"oriented mesh ({e}); OpenSCAD makes nothing of it")
                return EMPTY


class _NeedsMesh(Exception):
    """A hull or Minkowski operand that is not unions, placements and primitives (or not convex)."""


def _vertices(manifold) -> np.ndarray:
    return np.asarray(manifold.to_mesh64().vert_properties, dtype=np.float64)[:, :3]


def _manifold(node: Node):
    """A model node as a manifold3d Manifold (`to_mesh`: mesh leaves exactly, round solids at 64 segments)."""
    from ..mesh_export import to_mesh
    return to_mesh(node, 64)


def _suppressed(st: Statement) -> bool:
    return "*" in st.modifiers or "%" in st.modifiers


def _combine(kind: str, kids: list):
    """OpenSCAD's rules for operands that are nothing: NULL is no operand; EMPTY is the empty set."""
    kids = [k for k in kids if k is not NULL]
    if not kids:
        return NULL
    if kind == UNION:
        nodes = [k for k in kids if k is not EMPTY]
        if not nodes:
            return EMPTY
    elif kind == INTERSECTION:
        if any(k is EMPTY for k in kids):
            return EMPTY
        nodes = kids
    else:
        if kids[0] is EMPTY:
            return EMPTY
        nodes = [k for k in kids if k is not EMPTY]
    return nodes[0] if len(nodes) == 1 else Operation(kind, nodes)


def _scad(value) -> str:
    """A parsed argument value written back as OpenSCAD source."""
    if value is None:
        return "undef"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"')
        return '"' + escaped.replace("\n", "\\n").replace("\t", "\\t").replace("\r", "\\r") + '"'
    if isinstance(value, list):
        return "[" + ", ".join(_scad(v) for v in value) + "]"
    if isinstance(value, Range):
        return "[" + " : ".join(_scad(v) for v in value.values) + "]"
    raise FormatError(f"cannot write {value!r} as OpenSCAD source")


def _show(value, limit: int = 60) -> str:
    def text(v):
        if v is None:
            return "undef"
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, float):
            return f"{v:g}"
        if isinstance(v, str):
            return '"' + v + '"'
        if isinstance(v, list):
            return "[" + ", ".join(text(x) for x in v[:8]) + (", ..." if len(v) > 8 else "") + "]"
        if isinstance(v, Range):
            return "[" + " : ".join(text(x) for x in v.values) + "]"
        return repr(v)
    s = text(value)
    return s if len(s) <= limit else s[:limit - 3] + "..."
