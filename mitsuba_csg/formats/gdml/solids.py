"""GDML solids as CSG of our primitives: one builder per solid element, `_solid_<tag>`.

Phi segments are intersections with (or, above 180 degrees, subtractions of) convex
wedges; rmin holes are subtracted cones, spheres or tori extended past the caps so no faces
coincide; theta cuts are cones with their apex at the centre (`model.construct`).
"""
from __future__ import annotations

import math
import warnings
import xml.etree.ElementTree as ET

import numpy as np

from ...errors import ModelError
from ...model import values
from ...model.construct import frustum_chunk, inner_cone, phi_cut, rz_sections, theta_cut
from ...model.mesh import Mesh, orient_consistently, ruled_mesh, signed_volume, weld
from ...model.nodes import Node, Operation
from ...model.polyhedra import hull_planes
from ...model.primitives import Box, Cone, ConvexPolyhedron, Cylinder, Hyperboloid, Paraboloid, Sphere, Torus
from ..reading import FormatError
from .defines import affine, placement, rotation_matrix, vector
from .expressions import TWO_PI
from .twisted import generic_trap_rings, generic_trap_twist, twisted_trap_rings, twisted_tubs_rings

# Solids we know Geant4 has but cannot represent exactly with our primitives.
UNSUPPORTED_SOLIDS = ("gencone",)
_BOOLEANS = {"union": "union", "subtraction": "difference", "intersection": "intersection"}


class Solids:
    """The solids of a document, built on first use (with their operands) and kept by name."""

    def __init__(self, doc):
        self.doc = doc
        self.solids: dict[str, Node | None] = {}  # built; None = unsupported and skipped

    def _solid_refs(self, el) -> list[tuple[ET.Element, str]]:
        tag = el.tag
        refs = []
        if tag in _BOOLEANS:
            for part in ("first", "second"):
                child = el.find(part)
                if child is None or not child.get("ref"):
                    self.doc.fail(el, f"needs <{part} ref=\"...\"/>")
                refs.append((child, child.get("ref")))
        elif tag == "multiUnion":
            for node in el.findall("multiUnionNode"):
                child = node.find("solid")
                if child is None or not child.get("ref"):
                    self.doc.fail(node, "needs <solid ref=\"...\"/>")
                refs.append((child, child.get("ref")))
        elif tag == "reflectedSolid":
            if not el.get("solid"):
                self.doc.fail(el, "needs a solid attribute")
            refs.append((el, el.get("solid")))
        elif tag == "scaledSolid":
            child = el.find("solidref")
            if child is None or not child.get("ref"):
                self.doc.fail(el, "needs <solidref ref=\"...\"/>")
            refs.append((child, child.get("ref")))
        return refs

    def solid(self, name: str, referrer) -> Node | None:
        """The solid `name`, built with its operands (explicit stack: deep boolean chains are fine)."""
        if name in self.solids:
            return self.solids[name]
        if name not in self.doc.solid_elements:
            self.doc.fail(referrer, f"refers to undefined solid {name!r}")
        stack, visiting = [name], {name}
        while stack:
            current = stack[-1]
            el = self.doc.solid_elements[current]
            pending = []
            for ref_el, ref in self._solid_refs(el):
                if ref in self.solids:
                    continue
                if ref not in self.doc.solid_elements:
                    self.doc.fail(ref_el, f"solid {current!r} refers to undefined solid {ref!r}")
                if ref in visiting:
                    self.doc.fail(el, f"solid reference cycle: {' -> '.join(stack[stack.index(ref):] + [ref])}")
                pending.append(ref)
            if pending:
                for ref in dict.fromkeys(pending):
                    stack.append(ref)
                    visiting.add(ref)
                continue
            stack.pop()
            visiting.discard(current)
            self.solids[current] = self._build(el)
        return self.solids[name]

    def build(self, el) -> Node | None:
        """A solid element that refers to no other solid (a parameterised copy's dimensions)."""
        return self._build(el)

    def _build(self, el) -> Node | None:
        tag = el.tag
        builder = getattr(self, "_solid_" + tag, None)
        if builder is None:
            if tag in UNSUPPORTED_SOLIDS or tag.startswith("twisted"):
                self.doc.unsupported(el, f"the GDML solid <{tag}> cannot be represented exactly with analytic "
                                     f"primitives")
                return None
            if tag in ("opticalsurface",):
                return None
            self.doc.unsupported(el, f"unknown solid <{tag}>")
            return None
        try:
            return builder(el)
        except ModelError as e:
            if isinstance(e, FormatError):
                raise
            self.doc.fail(el, str(e))

    def _units(self, el):
        return self.doc.unit(el, "lunit", "mm"), self.doc.unit(el, "aunit", "rad")

    def _positive(self, el, attr, unit, default=None) -> float:
        return self._checked(values.positive, el, attr, unit, default)

    def _nonnegative(self, el, attr, unit, default=None) -> float:
        return self._checked(values.nonnegative, el, attr, unit, default)

    def _checked(self, check, el, attr, unit, default):
        try:
            return check(self.doc.number(el, attr, default, unit))
        except values.ValueProblem as e:
            self.doc.fail(el, f"{attr}: {e}")

    def _phi(self, el, aunit, start="startphi", delta="deltaphi"):
        phi0 = self.doc.number(el, start, 0.0, aunit)
        dphi = self.doc.number(el, delta, None, aunit) if el.get(delta) is not None else TWO_PI
        if dphi <= 0:
            self.doc.fail(el, f"{delta}: must be > 0, got {dphi:g}")
        return phi0, min(dphi, TWO_PI)

    def _solid_box(self, el):
        lunit, _ = self._units(el)
        return Box([self._positive(el, a, lunit) for a in "xyz"])

    def _solid_orb(self, el):
        lunit, _ = self._units(el)
        return Sphere(self._positive(el, "r", lunit))

    def _solid_tube(self, el):
        lunit, aunit = self._units(el)
        rmin = self._nonnegative(el, "rmin", lunit, 0.0)
        rmax = self._positive(el, "rmax", lunit)
        z = self._positive(el, "z", lunit)
        if rmin >= rmax:
            self.doc.fail(el, f"rmin ({rmin:g}) must be < rmax ({rmax:g})")
        solid = Cylinder(rmax, z)
        if rmin > 0:
            solid = solid - inner_cone(rmin, rmin, z)
        return phi_cut(solid, *self._phi(el, aunit), rmax, 0.5 * z)

    def _solid_cutTube(self, el):
        lunit, aunit = self._units(el)
        rmin = self._nonnegative(el, "rmin", lunit, 0.0)
        rmax = self._positive(el, "rmax", lunit)
        dz = 0.5 * self._positive(el, "z", lunit)
        if rmin >= rmax:
            self.doc.fail(el, f"rmin ({rmin:g}) must be < rmax ({rmax:g})")
        low = np.array([self.doc.number(el, a, 0.0) for a in ("lowX", "lowY", "lowZ")])
        high = np.array([self.doc.number(el, a, 0.0) for a in ("highX", "highY", "highZ")])
        if not (np.linalg.norm(low) > 0 and low[2] < 0 and np.linalg.norm(high) > 0 and high[2] > 0):
            self.doc.fail(el, "the low cut normal needs a negative z component and the high one a positive one")
        low, high = low / np.linalg.norm(low), high / np.linalg.norm(high)
        reach = dz + rmax * max(np.hypot(*low[:2]) / -low[2], np.hypot(*high[:2]) / high[2])
        height = 2.0 * reach + 2.0 * rmax
        solid = Cylinder(rmax, height)
        if rmin > 0:
            solid = solid - Cylinder(rmin, 1.5 * height)
        r, h = 2.0 * rmax, height
        cut = ConvexPolyhedron([[*low, -low[2] * dz], [*high, high[2] * dz], [1, 0, 0, r], [-1, 0, 0, r],
                                [0, 1, 0, r], [0, -1, 0, r], [0, 0, 1, h], [0, 0, -1, h]])
        return phi_cut(solid & cut, *self._phi(el, aunit), rmax, reach)

    def _solid_cone(self, el):
        lunit, aunit = self._units(el)
        rmin1, rmin2 = (self._nonnegative(el, a, lunit, 0.0) for a in ("rmin1", "rmin2"))
        rmax1, rmax2 = (self._nonnegative(el, a, lunit, 0.0) for a in ("rmax1", "rmax2"))
        z = self._positive(el, "z", lunit)
        if rmin1 > rmax1 or rmin2 > rmax2 or (rmin1 == rmax1 and rmin2 == rmax2):
            self.doc.fail(el, "needs rmin1 <= rmax1 and rmin2 <= rmax2, not both equal")
        solid = Cone(rmax1, rmax2, z)
        inner = inner_cone(rmin1, rmin2, z)
        if inner is not None:
            solid = solid - inner
        return phi_cut(solid, *self._phi(el, aunit), max(rmax1, rmax2), 0.5 * z)

    def _solid_sphere(self, el):
        lunit, aunit = self._units(el)
        rmin = self._nonnegative(el, "rmin", lunit, 0.0)
        rmax = self._positive(el, "rmax", lunit)
        if rmin >= rmax:
            self.doc.fail(el, f"rmin ({rmin:g}) must be < rmax ({rmax:g})")
        solid = Sphere(rmax)
        if rmin > 0:
            solid = solid - Sphere(rmin)
        theta0 = self.doc.number(el, "starttheta", 0.0, aunit)
        dtheta = self.doc.number(el, "deltatheta", None, aunit) if el.get("deltatheta") is not None else math.pi
        if not (0 <= theta0 < math.pi) or dtheta <= 0:
            self.doc.fail(el, f"needs 0 <= starttheta < 180 deg and deltatheta > 0, got {theta0:g} rad, {dtheta:g} rad")
        solid = theta_cut(solid, theta0, min(theta0 + dtheta, math.pi), 2.0 * rmax)
        return phi_cut(solid, *self._phi(el, aunit), rmax, rmax)

    def _solid_torus(self, el):
        lunit, aunit = self._units(el)
        rmin = self._nonnegative(el, "rmin", lunit, 0.0)
        rmax = self._positive(el, "rmax", lunit)
        rtor = self._positive(el, "rtor", lunit)
        if rmin >= rmax or rmax >= rtor:
            self.doc.fail(el, f"needs rmin < rmax < rtor, got {rmin:g}, {rmax:g}, {rtor:g}")
        solid = Torus(rtor, rmax)
        if rmin > 0:
            solid = solid - Torus(rtor, rmin)
        return phi_cut(solid, *self._phi(el, aunit), rtor + rmax, rmax)

    def _zplanes(self, el, lunit):
        planes = []
        for zp in el.findall("zplane"):
            z = self.doc.number(zp, "z", None, lunit)
            rmin = self.doc.number(zp, "rmin", 0.0, lunit)
            rmax = self.doc.number(zp, "rmax", None, lunit)
            if rmin < 0 or rmax < rmin:
                self.doc.fail(zp, f"needs 0 <= rmin <= rmax, got rmin {rmin:g}, rmax {rmax:g}")
            planes.append((z, rmin, rmax))
        if len(planes) < 2:
            self.doc.fail(el, f"needs at least 2 <zplane> elements, got {len(planes)}")
        zs = [p[0] for p in planes]
        if not (all(a <= b for a, b in zip(zs, zs[1:])) or all(a >= b for a, b in zip(zs, zs[1:]))):
            self.doc.fail(el, "zplane z values must be monotonic")
        if zs[0] > zs[-1]:
            planes.reverse()
        sections = [(a, b) for a, b in zip(planes, planes[1:]) if b[0] > a[0] and max(a[2], b[2]) > 0]
        if not sections:
            self.doc.fail(el, "the z planes enclose no volume")
        return planes, sections

    def _solid_polycone(self, el):
        lunit, aunit = self._units(el)
        _, sections = self._zplanes(el, lunit)
        return self._polycone(el, sections, *self._phi(el, aunit))

    def _rz_points(self, el, lunit):
        """The (r, z) polygon of a generic polycone or polyhedra (Geant4 takes either winding)."""
        points = [(self.doc.number(p, "r", None, lunit), self.doc.number(p, "z", None, lunit))
                  for p in el.findall("rzpoint")]
        if len(points) < 3:
            self.doc.fail(el, f"needs at least 3 <rzpoint> elements, got {len(points)}")
        if min(r for r, _ in points) < 0:
            self.doc.fail(el, "rzpoint r values must be >= 0")
        r, z = np.array(points).T
        if abs(np.dot(r, np.roll(z, -1)) - np.dot(np.roll(r, -1), z)) <= 1e-12 * (np.ptp(r) + np.ptp(z)) ** 2:
            self.doc.fail(el, "the (r, z) polygon encloses no area")
        sections = rz_sections(points)
        if not sections:
            self.doc.fail(el, "the (r, z) polygon encloses no volume")
        return sections

    def _solid_genericPolycone(self, el):
        lunit, aunit = self._units(el)
        return self._polycone(el, self._rz_points(el, lunit), *self._phi(el, aunit))

    def _polycone(self, el, sections, phi0, dphi):
        """The union of the frustum shells of polycone sections, cut to the phi range."""
        pieces = []
        for (z0, rmin0, rmax0), (z1, rmin1, rmax1) in sections:
            h = z1 - z0
            piece = Cone(rmax0, rmax1, h)
            inner = inner_cone(rmin0, rmin1, h)
            if inner is not None:
                piece = piece - inner
            pieces.append(piece.translate((0.0, 0.0, 0.5 * (z0 + z1))))
        solid = pieces[0] if len(pieces) == 1 else Operation("union", pieces)
        rmax = max(max(a[2], b[2]) for a, b in sections)
        zreach = max(max(abs(a[0]), abs(b[0])) for a, b in sections)
        return phi_cut(solid, phi0, dphi, rmax, zreach)

    def _sides(self, el):
        sides = self.doc.number(el, "numsides")
        if sides != int(sides) or not 1 <= sides <= 10_000:
            self.doc.fail(el, f"numsides: expected a whole number in 1..10000, got {sides:g}")
        return int(sides)

    def _solid_polyhedra(self, el):
        lunit, aunit = self._units(el)
        _, sections = self._zplanes(el, lunit)
        return self._polyhedra(el, self._sides(el), *self._phi(el, aunit), sections)

    def _solid_genericPolyhedra(self, el):
        """G4Polyhedra from (r, z) corners: r is the corner radius there (the z-plane form's
        rmax is the apothem), so each r becomes r cos(half a side's angle)."""
        lunit, aunit = self._units(el)
        sides = self._sides(el)
        phi0, dphi = self._phi(el, aunit)
        k = math.cos(0.5 * dphi / sides)
        sections = [tuple((z, k * rmin, k * rmax) for z, rmin, rmax in section)
                    for section in self._rz_points(el, lunit)]
        return self._polyhedra(el, sides, phi0, dphi, sections)

    def _polyhedra(self, el, sides, phi0, dphi, sections):
        full = dphi >= TWO_PI - 1e-12
        step = dphi / sides
        if step >= math.pi - 1e-9:
            self.doc.fail(el, f"each side spans {math.degrees(step):g} deg; a polyhedra side must span less than 180")
        scale = max(max(max(a[2], b[2], abs(a[0]), abs(b[0])) for a, b in sections), 1e-9)
        per_chunk = sides if full else max(1, int(math.floor((math.pi - 1e-9) / step)))
        chunks = [range(k, min(k + per_chunk, sides)) for k in range(0, sides, per_chunk)]
        pieces = []
        for (z0, rmin0, rmax0), (z1, rmin1, rmax1) in sections:
            for chunk in chunks:
                outer = frustum_chunk(phi0, step, chunk, full, z0, z1, rmax0, rmax1, 0.0, 0.0, 0.0)
                piece = outer
                if rmin0 > 0 or rmin1 > 0:
                    h = z1 - z0
                    s = (rmin1 - rmin0) / h
                    eb = 0.5 * h if s <= 0 else min(0.5 * h, rmin0 / s)
                    et = 0.5 * h if s >= 0 else min(0.5 * h, rmin1 / -s)
                    inner = frustum_chunk(phi0, step, chunk, full, z0, z1, rmin0, rmin1, eb, et,
                                          1e-3 * scale)
                    piece = outer - inner
                pieces.append(piece)
        return pieces[0] if len(pieces) == 1 else Operation("union", pieces)

    def _solid_trd(self, el):
        lunit, _ = self._units(el)
        x1, x2, y1, y2 = (0.5 * self._nonnegative(el, a, lunit) for a in ("x1", "x2", "y1", "y2"))
        dz = 0.5 * self._positive(el, "z", lunit)
        verts = [(sx * x, sy * y, z) for z, x, y in ((-dz, x1, y1), (dz, x2, y2)) for sx in (-1, 1) for sy in (-1, 1)]
        return self._hull(el, verts)

    def _trap_vertices(self, dz, theta, phi, y1, x1, x2, alpha1, y2, x3, x4, alpha2):
        # G4Trap's vertex order and parameters (all half lengths).
        tx, ty = math.tan(theta) * math.cos(phi), math.tan(theta) * math.sin(phi)
        ta1, ta2 = math.tan(alpha1), math.tan(alpha2)
        return [(-dz * tx - y1 * ta1 - x1, -dz * ty - y1, -dz), (-dz * tx - y1 * ta1 + x1, -dz * ty - y1, -dz),
                (-dz * tx + y1 * ta1 - x2, -dz * ty + y1, -dz), (-dz * tx + y1 * ta1 + x2, -dz * ty + y1, -dz),
                (dz * tx - y2 * ta2 - x3, dz * ty - y2, dz), (dz * tx - y2 * ta2 + x3, dz * ty - y2, dz),
                (dz * tx + y2 * ta2 - x4, dz * ty + y2, dz), (dz * tx + y2 * ta2 + x4, dz * ty + y2, dz)]

    def _solid_trap(self, el):
        lunit, aunit = self._units(el)
        h = {a: 0.5 * self._nonnegative(el, a, lunit) for a in ("z", "y1", "x1", "x2", "y2", "x3", "x4")}
        ang = {a: self.doc.number(el, a, 0.0, aunit) for a in ("theta", "phi", "alpha1", "alpha2")}
        return self._hull(el, self._trap_vertices(h["z"], ang["theta"], ang["phi"], h["y1"], h["x1"], h["x2"],
                                                  ang["alpha1"], h["y2"], h["x3"], h["x4"], ang["alpha2"]))

    def _solid_para(self, el):
        lunit, aunit = self._units(el)
        x, y, z = (0.5 * self._positive(el, a, lunit) for a in "xyz")
        alpha, theta, phi = (self.doc.number(el, a, 0.0, aunit) for a in ("alpha", "theta", "phi"))
        return self._hull(el, self._trap_vertices(z, theta, phi, y, x, x, alpha, y, x, x, alpha))

    def _hull(self, el, vertices):
        try:
            return ConvexPolyhedron(hull_planes(vertices, max_faces=6))
        except ModelError as e:
            self.doc.fail(el, str(e))

    # ---- Planar-faced solids as triangle meshes (exact) ----

    def _vertex(self, el, attr, lunit) -> np.ndarray:
        """A facet vertex: a named <position> of <define>, times the solid's lunit (as Geant4)."""
        name = el.get(attr)
        if not name:
            self.doc.fail(el, f"needs a {attr} attribute (the name of a <position>)")
        target = self.doc.vectors["position"].get(name)
        if target is None:
            self.doc.fail(el, f"{attr}: refers to undefined position {name!r}")
        return vector(self.doc, target, "position") * lunit

    def _solid_tet(self, el):
        lunit, _ = self._units(el)
        return self._hull(el, [self._vertex(el, f"vertex{k}", lunit) for k in range(1, 5)])

    def _solid_tessellated(self, el):
        """Triangular and quadrangular facets, counter-clockwise seen from outside (G4TessellatedSolid);
        RELATIVE facets give their later vertices as offsets from the first."""
        lunit, _ = self._units(el)
        corners = []
        for facet in el:
            count = {"triangular": 3, "quadrangular": 4}.get(facet.tag)
            if count is None:
                self.doc.fail(facet, f"unknown facet <{facet.tag}> in <tessellated>")
            points = [self._vertex(facet, f"vertex{k}", lunit) for k in range(1, count + 1)]
            kind = (facet.get("type") or "ABSOLUTE").upper()
            if kind == "RELATIVE":
                points = [points[0]] + [points[0] + p for p in points[1:]]
            elif kind != "ABSOLUTE":
                self.doc.fail(facet, f"type: expected ABSOLUTE or RELATIVE, got {facet.get('type')!r}")
            corners.append(points[:3])
            if count == 4:
                corners.append([points[0], points[2], points[3]])
        if not corners:
            self.doc.fail(el, "a <tessellated> solid needs facets")
        vertices, faces = weld(np.array(corners).reshape(-1, 3), np.arange(3 * len(corners)).reshape(-1, 3))
        # Geant4 takes facets in either order (G4TessellatedSolid finds its outside by itself).
        faces, turned = orient_consistently(faces)
        if turned:
            warnings.warn(f"{self.doc.where(el)}: facets are not all counter-clockwise seen from outside; "
                          f"turned them to agree with their neighbours", UserWarning, stacklevel=2)
            if signed_volume(vertices, faces) < 0:
                faces = faces[:, ::-1]
        return self._mesh(el, vertices, faces)

    def _solid_xtru(self, el):
        """A polygon swept through z sections, each scaled and offset (G4ExtrudedSolid)."""
        lunit, _ = self._units(el)
        polygon = np.array([[self.doc.number(v, a, None, lunit) for a in "xy"] for v in el.findall("twoDimVertex")])
        sections = sorted(((self.doc.number(sec, "zOrder", None), self.doc.number(sec, "zPosition", None, lunit),
                            self.doc.number(sec, "xOffset", 0.0, lunit), self.doc.number(sec, "yOffset", 0.0, lunit),
                            self.doc.number(sec, "scalingFactor", 1.0)) for sec in el.findall("section")))
        if len(polygon) < 3 or len(sections) < 2:
            self.doc.fail(el, f"an <xtru> needs at least 3 <twoDimVertex> and 2 <section>, got {len(polygon)} "
                          f"and {len(sections)}")
        rings = [np.column_stack([scale * polygon + (dx, dy), np.full(len(polygon), z)])
                 for _, z, dx, dy, scale in sections]
        return self._mesh(el, *ruled_mesh(np.array(rings)))

    def _mesh(self, el, vertices, faces):
        vertices, faces = weld(vertices, faces)
        try:
            return Mesh(vertices, faces)
        except ModelError as e:
            self.doc.fail(el, str(e))

    # ---- Twisted solids and generic trapezoids as swept-polygon meshes (`twisted`) ----

    def _solid_arb8(self, el):
        lunit, _ = self._units(el)
        dz = self._positive(el, "dz", lunit)
        vertices = np.array([[self.doc.number(el, f"v{k}{a}", None, lunit) for a in "xy"] for k in range(1, 9)])
        size = max(float(np.ptp(vertices, axis=0).max()), 2.0 * dz)
        twisted = generic_trap_twist(dz, vertices) > 1e-9 * size
        if not twisted:
            corners = [(x, y, z) for (x, y), z in zip(vertices, [-dz] * 4 + [dz] * 4)]
            try:
                hull = ConvexPolyhedron(hull_planes(corners, max_faces=6))
            except ModelError:
                hull = None
        solid = self._mesh(el, *ruled_mesh(generic_trap_rings(dz, vertices, twisted)))
        if not twisted and hull is not None and math.isclose(
                signed_volume(solid.vertices, solid.faces), _hull_volume(corners), rel_tol=1e-9):
            return hull                        # a convex arb8: the exact (and cheaper) polyhedron
        return solid

    def _twisted_trap(self, el, twist, dz, theta, phi, y1, x1, x2, y2, x3, x4, alpha):
        return self._mesh(el, *ruled_mesh(twisted_trap_rings(twist, dz, theta, phi, y1, x1, x2, y2, x3, x4, alpha)))

    def _solid_twistedbox(self, el):
        lunit, aunit = self._units(el)
        x, y, z = (0.5 * self._positive(el, a, lunit) for a in "xyz")
        return self._twisted_trap(el, self.doc.number(el, "PhiTwist", None, aunit), z, 0.0, 0.0, y, x, x, y, x, x, 0.0)

    def _solid_twistedtrd(self, el):
        lunit, aunit = self._units(el)
        x1, x2, y1, y2 = (0.5 * self._positive(el, a, lunit) for a in ("x1", "x2", "y1", "y2"))
        z = 0.5 * self._positive(el, "z", lunit)
        return self._twisted_trap(el, self.doc.number(el, "PhiTwist", None, aunit), z, 0.0, 0.0, y1, x1, x1, y2, x2, x2,
                                  0.0)

    def _solid_twistedtrap(self, el):
        lunit, aunit = self._units(el)
        h = {a: 0.5 * self._positive(el, a, lunit) for a in ("z", "y1", "x1", "x2", "y2", "x3", "x4")}
        ang = {a: self.doc.number(el, a, 0.0, aunit) for a in ("PhiTwist", "Theta", "Phi", "Alph")}
        return self._twisted_trap(el, ang["PhiTwist"], h["z"], ang["Theta"], ang["Phi"], h["y1"], h["x1"], h["x2"],
                                  h["y2"], h["x3"], h["x4"], ang["Alph"])

    def _solid_twistedtubs(self, el):
        """G4TwistedTubs from its end radii and length (or its radii at z = 0 and the two end z),
        the sector angle `phi` (or `totphi` / `nseg`)."""
        lunit, aunit = self._units(el)
        twist = self.doc.number(el, "twistedangle", None, aunit)
        if not 0 < abs(twist) < math.pi:
            self.doc.fail(el, f"twistedangle must lie strictly between 0 and 180 degrees, got {twist:g} rad")
        if el.get("phi") is not None:
            dphi = self._positive(el, "phi", aunit)
        else:
            dphi = self._positive(el, "totphi", aunit) / self._positive(el, "nseg", 1.0)
        if el.get("endinnerrad") is not None:
            half = 0.5 * self._positive(el, "zlen", lunit)
            shrink = math.cos(0.5 * twist)                 # end radius -> radius at z = 0
            inner = self._positive(el, "endinnerrad", lunit) * shrink
            outer = self._positive(el, "endouterrad", lunit) * shrink
            z0, z1 = -half, half
        else:
            inner = self._positive(el, "midinnerrad", lunit)
            outer = self._positive(el, "midouterrad", lunit)
            z0, z1 = self.doc.number(el, "negativeEndz", None, lunit), self.doc.number(el, "positiveEndz", None, lunit)
            if not z0 < z1:
                self.doc.fail(el, f"needs negativeEndz < positiveEndz, got {z0:g} and {z1:g}")
        if not inner < outer or dphi >= TWO_PI:
            self.doc.fail(el, "needs an inner radius below the outer one and phi below 360 degrees")
        return self._mesh(el, *ruled_mesh(twisted_tubs_rings(twist, inner, outer, z0, z1, dphi)))

    def _solid_ellipsoid(self, el):
        lunit, _ = self._units(el)
        ax, by, cz = (self._positive(el, a, lunit) for a in ("ax", "by", "cz"))
        zcut1, zcut2 = self.doc.number(el, "zcut1", 0.0, lunit), self.doc.number(el, "zcut2", 0.0, lunit)
        # G4Ellipsoid (Geant4 11): only both cuts 0 mean "no cut" (one cut alone keeps the other
        # at z = 0); cuts beyond the surface are clamped.
        if zcut1 == 0 and zcut2 == 0:
            lo, hi = -cz, cz
        else:
            lo, hi = max(-cz, zcut1), min(cz, zcut2)
        if lo >= hi:
            self.doc.fail(el, f"zcut1 ({zcut1:g}) must be below zcut2 ({zcut2:g}) inside the ellipsoid")
        solid = Sphere(1.0).scale((ax, by, cz))
        if lo > -cz or hi < cz:
            solid = solid & Box((2.5 * ax, 2.5 * by, hi - lo)).translate((0.0, 0.0, 0.5 * (lo + hi)))
        return solid

    def _solid_eltube(self, el):
        lunit, _ = self._units(el)
        dx, dy, dz = (self._positive(el, a, lunit) for a in ("dx", "dy", "dz"))
        return Cylinder(1.0, 2.0 * dz).scale((dx, dy, 1.0))

    def _solid_elcone(self, el):
        lunit, _ = self._units(el)
        dx, dy = self._positive(el, "dx", 1.0), self._positive(el, "dy", 1.0)   # dimensionless slopes
        zmax = self._positive(el, "zmax", lunit)
        zcut = min(self._positive(el, "zcut", lunit), zmax)
        return Cone(zmax + zcut, zmax - zcut, 2.0 * zcut).scale((dx, dy, 1.0))

    def _solid_paraboloid(self, el):
        """G4Paraboloid: rho^2 = k1 z + k2 through rlo at -dz and rhi at +dz (dz a half length)."""
        lunit, _ = self._units(el)
        rlo = self._nonnegative(el, "rlo", lunit)
        rhi = self._positive(el, "rhi", lunit)
        dz = self._positive(el, "dz", lunit)
        if rlo >= rhi:
            self.doc.fail(el, f"needs rlo < rhi (Geant4's G4Paraboloid), got {rlo:g} and {rhi:g}")
        return Paraboloid(rlo, rhi, 2.0 * dz)

    def _solid_hype(self, el):
        """G4Hype: between the hyperboloids rho^2 = r^2 + tan^2(stereo) z^2 of the inner and outer
        radius and stereo angle, |z| <= z / 2. The inner one is cut out, extended past the caps."""
        lunit, aunit = self._units(el)
        rmin = self._nonnegative(el, "rmin", lunit, 0.0)
        rmax = self._positive(el, "rmax", lunit)
        inst = self._nonnegative(el, "inst", aunit, 0.0)
        outst = self._nonnegative(el, "outst", aunit, 0.0)
        z = self._positive(el, "z", lunit)
        # G4Hype uses tan^2 of the stereo angles only (a file may give 20 rad).
        t_in, t_out = abs(math.tan(inst)), abs(math.tan(outst))
        solid = Hyperboloid(rmax, math.hypot(rmax, t_out * 0.5 * z), z)
        if math.hypot(rmin, t_in * 0.5 * z) >= solid.radius_end or rmin >= rmax:
            self.doc.fail(el, f"the inner surface (rmin {rmin:g}, inst {inst:g} rad) must lie inside the outer one "
                              f"(rmax {rmax:g}, outst {outst:g} rad)")
        if rmin > 0 or t_in > 0:
            solid = solid - Hyperboloid(rmin, math.hypot(rmin, t_in * 0.75 * z), 1.5 * z)
        return solid

    def _operand(self, ref_el) -> Node | None:
        return self.solids[ref_el.get("ref")]

    def _boolean(self, el):
        first = self._operand(el.find("first"))
        second = self._operand(el.find("second"))
        if first is None or second is None:
            self.doc.unsupported(el, "built from a skipped solid")
            return None
        t, r, _ = placement(self.doc, el)
        second = second.transform(affine(rotation_matrix(r), t))
        t1, r1, _ = placement(self.doc, el, "first")
        if np.any(t1) or np.any(r1):
            first = first.transform(affine(rotation_matrix(r1), t1))
        return Operation(_BOOLEANS[el.tag], (first, second))

    _solid_union = _solid_subtraction = _solid_intersection = _boolean

    def _solid_multiUnion(self, el):
        parts = []
        for node in el.findall("multiUnionNode"):
            solid = self._operand(node.find("solid"))
            if solid is None:
                self.doc.unsupported(el, "built from a skipped solid")
                return None
            t, r, _ = placement(self.doc, node)
            parts.append(solid.transform(affine(rotation_matrix(r), t)))
        if not parts:
            self.doc.fail(el, "needs at least one <multiUnionNode>")
        return Operation("union", parts)

    def _solid_reflectedSolid(self, el):
        """G4ReflectedSolid: the solid under G4Transform3D(R, d) * G4Scale3D(s), x' = R (s x) + d."""
        solid = self.solids[el.get("solid")]
        if solid is None:
            self.doc.unsupported(el, "built from a skipped solid")
            return None
        lunit, aunit = self._units(el)
        scale = np.array([self.doc.number(el, a, 1.0) for a in ("sx", "sy", "sz")])
        if np.any(scale == 0):
            self.doc.fail(el, f"scale factors must be non-zero, got {scale.tolist()}")
        angles = [self.doc.number(el, a, 0.0, aunit) for a in ("rx", "ry", "rz")]
        offset = [self.doc.number(el, a, 0.0, lunit) for a in ("dx", "dy", "dz")]
        return solid.transform(affine(rotation_matrix(angles) @ np.diag(scale), offset))

    def _solid_scaledSolid(self, el):
        solid = self._operand(el.find("solidref"))
        if solid is None:
            self.doc.unsupported(el, "built from a skipped solid")
            return None
        _, _, s = placement(self.doc, el)
        if np.any(s == 0):
            self.doc.fail(el, f"scale factors must be non-zero, got {s.tolist()}")
        return solid.scale(s)


def _hull_volume(points) -> float:
    import manifold3d as m3
    return m3.Manifold.hull_points(np.asarray(points, dtype=np.float64)).volume()
