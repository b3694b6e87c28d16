"""Cuts and holes that turn Geant4-style solids (phi segments, theta ranges, rmin holes,
polyhedra sections) into CSG of our primitives; shared by the file readers.
"""
from __future__ import annotations

import math

from .nodes import Node
from .primitives import Box, Cone, ConvexPolyhedron, Cylinder

TWO_PI = 2.0 * math.pi


def inner_cone(r_bottom: float, r_top: float, height: float) -> Node | None:
    """The hole r < r(z) of a frustum section |z| <= height/2, extended past both caps along its slope
    (as far as the radius stays >= 0) so that subtracting it leaves no coincident faces."""
    if r_bottom <= 0 and r_top <= 0:
        return None
    s = (r_top - r_bottom) / height
    eb = 0.5 * height if s <= 0 else min(0.5 * height, r_bottom / s)
    et = 0.5 * height if s >= 0 else min(0.5 * height, r_top / -s)
    rb, rt = max(0.0, r_bottom - s * eb), max(0.0, r_top + s * et)
    if rb == rt:
        return Cylinder(rb, height + eb + et).translate((0.0, 0.0, 0.5 * (et - eb)))
    return Cone(rb, rt, height + eb + et).translate((0.0, 0.0, 0.5 * (et - eb)))


def wedge(phi0: float, dphi: float, radius: float, half_z: float) -> ConvexPolyhedron:
    """The convex wedge phi0 <= phi <= phi0 + dphi (dphi <= pi), |x|,|y| <= radius, |z| <= half_z."""
    phi1 = phi0 + dphi
    return ConvexPolyhedron([
        [math.sin(phi0), -math.cos(phi0), 0.0, 0.0], [-math.sin(phi1), math.cos(phi1), 0.0, 0.0],
        [1, 0, 0, radius], [-1, 0, 0, radius], [0, 1, 0, radius], [0, -1, 0, radius],
        [0, 0, 1, half_z], [0, 0, -1, half_z]])


def phi_cut(solid: Node, phi0: float, dphi: float, radius: float, half_z: float) -> Node:
    """`solid` restricted to phi0 <= phi <= phi0 + dphi; the wedge overreaches the solid's extent."""
    if dphi >= TWO_PI - 1e-12:
        return solid
    r, h = 2.0 * radius + 1e-6, 2.0 * half_z + 1e-6
    if dphi <= math.pi:
        return solid & wedge(phi0, dphi, r, h)
    return solid - wedge(phi0 + dphi, TWO_PI - dphi, r, h)


def theta_cut(solid: Node, theta0: float, theta1: float, reach: float) -> Node:
    """`solid` (centred on the origin, inside a ball of radius reach/2) limited to theta0 <= theta <= theta1."""
    half = 0.5 * math.pi

    def up(t):      # theta < t, z in [0, reach], apex at the origin
        return Cone(0.0, reach * math.tan(t), reach).translate((0.0, 0.0, 0.5 * reach))

    def down(t):    # theta > pi - t, z in [-reach, 0]
        return Cone(reach * math.tan(t), 0.0, reach).translate((0.0, 0.0, -0.5 * reach))

    def half_space(sign):
        return Box((2 * reach, 2 * reach, reach)).translate((0.0, 0.0, 0.5 * sign * reach))

    if theta0 > 1e-12:
        if abs(theta0 - half) < 1e-9:
            solid = solid & half_space(-1)
        elif theta0 < half:
            solid = solid - up(theta0)
        else:
            solid = solid & down(math.pi - theta0)
    if theta1 < math.pi - 1e-12:
        if abs(theta1 - half) < 1e-9:
            solid = solid & half_space(+1)
        elif theta1 > half:
            solid = solid - down(math.pi - theta1)
        else:
            solid = solid & up(theta1)
    return solid


def frustum_chunk(phi0, step, chunk, full, z0, z1, r0, r1, extend_bottom, extend_top, phi_margin):
    """Sides `chunk` of a polyhedra section between z0 (apothem r0) and z1 (apothem r1), as one convex
    polyhedron; a partial chunk is closed by radial planes (pushed out by phi_margin), the caps are pushed
    out by extend_bottom/extend_top."""
    s = (r1 - r0) / (z1 - z0)
    planes = []
    for k in chunk:
        a = phi0 + (k + 0.5) * step
        planes.append([math.cos(a), math.sin(a), -s, r0 - s * z0])
    if not full:
        b0, b1 = phi0 + chunk[0] * step, phi0 + (chunk[-1] + 1) * step
        planes.append([math.sin(b0), -math.cos(b0), 0.0, phi_margin])
        planes.append([-math.sin(b1), math.cos(b1), 0.0, phi_margin])
    planes.append([0.0, 0.0, 1.0, z1 + extend_top])
    planes.append([0.0, 0.0, -1.0, -(z0 - extend_bottom)])
    return ConvexPolyhedron(planes)


def rz_sections(points) -> list[tuple[tuple[float, float, float], tuple[float, float, float]]]:
    """An (r, z) polygon (Geant4's generic polycone/polyhedra: any simple polygon with r >= 0)
    as polycone sections: ((z0, rmin0, rmax0), (z1, rmin1, rmax1)) pairs, one per pair of
    edges that bound the polygon's inside in each slab between two vertex heights (even-odd
    from the axis), so that the revolved polygon is the union of the sections' frustum shells."""
    pts = [(float(r), float(z)) for r, z in points]
    edges = [(pts[i], pts[(i + 1) % len(pts)]) for i in range(len(pts))]
    heights = sorted({z for _, z in pts})
    sections = []
    for z0, z1 in zip(heights, heights[1:]):
        zm = 0.5 * (z0 + z1)
        crossing = []
        for (ra, za), (rb, zb) in edges:
            if min(za, zb) <= z0 and max(za, zb) >= z1 and za != zb:
                at = lambda z: ra + (rb - ra) * (z - za) / (zb - za)     # noqa: E731
                crossing.append((at(zm), at(z0), at(z1)))
        crossing.sort()
        for inner, outer in zip(crossing[0::2], crossing[1::2]):
            sections.append(((z0, inner[1], outer[1]), (z1, inner[2], outer[2])))
    return sections
