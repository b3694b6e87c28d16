"""Geant4's twisted solids and generic trapezoids (arb8) as polygons swept through z.

Each of these solids is, at every height z, a polygon: G4GenericTrap's quadrilateral has its
corners moving linearly from the -dz face to the +dz face; G4TwistedTrap's (and the box and
trd it generalizes) is the trapezoid of that height turned by PhiTwist z / (2 dz) about its
centre, which moves along the theta/phi line; G4TwistedTubs' is an annular sector whose
radii grow as hyperbolas and whose edges turn by atan(kappa z). Their side surfaces are ruled
(straight in each plane z = const) but twisted, so `model.mesh.ruled_mesh` meshes them from
`SLICES` + 1 such polygons, with every edge split into `PER_EDGE` pieces (arcs into `PER_ARC`):
exact where the faces are planar (an arb8 without twist), and otherwise within about
twist x edge length / (4 SLICES PER_EDGE) of the true surface (6e-5 of the solid's size for a
twist of 1 rad; half as many slices and pieces left 0.1-0.25 % of rays off by more than 1e-3
of the size against Geant4, at grazing incidence).
"""
from __future__ import annotations

import math

import numpy as np

SLICES = 128
PER_EDGE = 32
PER_ARC = 96


def _densified(corners: np.ndarray, per_edge: int) -> np.ndarray:
    """The closed polygon's corners with every edge split into `per_edge` pieces."""
    nxt = np.roll(corners, -1, axis=0)
    s = np.arange(per_edge)[:, None, None] / per_edge
    return (corners[None] * (1 - s) + nxt[None] * s).transpose(1, 0, 2).reshape(-1, 2)


def _ring(polygon: np.ndarray, z: float) -> np.ndarray:
    return np.column_stack([polygon, np.full(len(polygon), z)])


def generic_trap_rings(dz: float, vertices: np.ndarray, twisted: bool) -> np.ndarray:
    """G4GenericTrap: `vertices` (8, 2), the first four at -dz, the last four at +dz."""
    slices, per_edge = (SLICES, PER_EDGE) if twisted else (1, 1)
    bottom, top = vertices[:4], vertices[4:]
    rings = []
    for u in np.linspace(0.0, 1.0, slices + 1):
        rings.append(_ring(_densified(bottom * (1 - u) + top * u, per_edge), -dz + 2.0 * dz * u))
    return np.array(rings)


def generic_trap_twist(dz: float, vertices: np.ndarray) -> float:
    """How far the lateral faces are from planar (0 for a frustum-like arb8), in length units."""
    worst = 0.0
    for i in range(4):
        j = (i + 1) % 4
        a, b = np.append(vertices[i], -dz), np.append(vertices[j], -dz)
        c, d = np.append(vertices[j + 4], dz), np.append(vertices[i + 4], dz)
        n = np.cross(b - a, d - a)
        if np.linalg.norm(n) < 1e-300:
            n = np.cross(c - a, d - a)
        if np.linalg.norm(n) > 0:
            worst = max(worst, abs(np.dot(c - a, n)) / np.linalg.norm(n))
    return worst


def twisted_trap_rings(twist, dz, theta, phi, y1, x1, x2, y2, x3, x4, alpha) -> np.ndarray:
    """G4TwistedTrap (half lengths; angles in radians): the trapezoid at height z turned by
    twist z / (2 dz) about its centre, which lies at z tan(theta) (cos phi, sin phi)."""
    ta = math.tan(alpha)
    rings = []
    for u in np.linspace(0.0, 1.0, SLICES + 1):
        z = -dz + 2.0 * dz * u
        h, xl, xh = y1 + (y2 - y1) * u, x1 + (x3 - x1) * u, x2 + (x4 - x2) * u
        corners = np.array([[-xl - h * ta, -h], [xl - h * ta, -h], [xh + h * ta, h], [-xh + h * ta, h]])
        angle = twist * z / (2.0 * dz)
        c, s = math.cos(angle), math.sin(angle)
        polygon = _densified(corners, PER_EDGE) @ np.array([[c, s], [-s, c]])
        polygon += z * math.tan(theta) * np.array([math.cos(phi), math.sin(phi)])
        rings.append(_ring(polygon, z))
    return np.array(rings)


def twisted_tubs_rings(twist, inner, outer, z0, z1, dphi) -> np.ndarray:
    """G4TwistedTubs: radii inner, outer at z = 0, growing as sqrt(1 + kappa^2 z^2) with
    kappa = tan(twist / 2) / max(|z0|, |z1|); the sector |angle - atan(kappa z)| <= dphi / 2."""
    kappa = math.tan(0.5 * twist) / max(abs(z0), abs(z1))
    arc = np.linspace(-0.5 * dphi, 0.5 * dphi, PER_ARC + 1)
    radial = np.linspace(0.0, 1.0, PER_EDGE + 1)[1:-1]
    rings = []
    for z in np.linspace(z0, z1, SLICES + 1):
        grow = math.sqrt(1.0 + (kappa * z) ** 2)
        turn = math.atan(kappa * z)
        ri, ro = inner * grow, outer * grow
        outer_arc = ro * np.column_stack([np.cos(arc + turn), np.sin(arc + turn)])
        inner_arc = ri * np.column_stack([np.cos(arc[::-1] + turn), np.sin(arc[::-1] + turn)])
        end = np.column_stack([np.cos(0.5 * dphi + turn), np.sin(0.5 * dphi + turn)])
        start = np.column_stack([np.cos(-0.5 * dphi + turn), np.sin(-0.5 * dphi + turn)])
        down = (ro - (ro - ri) * radial)[:, None] * end           # the edge at +dphi/2, outside in
        up = (ri + (ro - ri) * radial)[:, None] * start           # the edge at -dphi/2, inside out
        rings.append(_ring(np.vstack([outer_arc, down, inner_arc, up]), z))
    return np.array(rings)
