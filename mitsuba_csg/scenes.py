"""The paper's test scenes (Bogolepov et al. 2013, Table 2): seeded generators, and the one
registry of named scenes that the command line (`mitsuba-csg render city-3385`) and the
benchmarks use.
"""
from __future__ import annotations

import functools

import numpy as np

from .errors import CSGError
from .model import Box, Cone, Cylinder, Node, Prism, Sphere, Torus, difference, union


def cheese_holes(holes: int = 500, seed: int = 0, size: float = 2.0, radius_scale: float = 1.0):
    """(centres, radii) of the Cheese's holes: centres uniform in the cube of edge `size`,
    radii uniform in [0.03, 0.12] * size * `radius_scale`."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-0.5 * size, 0.5 * size, (holes, 3))
    radii = rng.uniform(0.03, 0.12, holes) * size * radius_scale
    return centres, radii


def cheese(holes: int = 500, seed: int = 0, size: float = 2.0, radius_scale: float = 1.0) -> Node:
    """A cube of edge `size` minus `holes` overlapping spheres (the paper's Cheese).

    Hole centres are uniform in the cube; radii uniform in [0.03, 0.12] * size (times
    `radius_scale`), so holes overlap each other and cut the faces. With fixed radii the
    cheese empties as the count grows (Cheese-8000 is almost all holes); see
    `constant_porosity_cheese` for the family that keeps Cheese-500's look. Leaf 0 is the
    cube, leaf i the i-th hole.
    """
    centres, radii = cheese_holes(holes, seed, size, radius_scale)
    spheres = [Sphere(float(r)).translate(c) for c, r in zip(centres, radii)]
    return difference(Box(size), *spheres) if holes else Box(size)


# The hole count whose solid fraction the constant-porosity family keeps.
POROSITY_OF = 500


def solid_fraction(centres, radii, size: float = 2.0, resolution: int = 80) -> float:
    """The fraction of the cube of edge `size` that no sphere (centres, radii) covers,
    counted (float64) on the cell centres of a `resolution`^3 lattice."""
    step = size / resolution
    axis = (np.arange(resolution) + 0.5) * step - 0.5 * size
    covered = np.zeros((resolution,) * 3, bool)
    # Per sphere, only the lattice block of its bounding box is tested.
    first = np.clip(np.ceil((centres - radii[:, None] + 0.5 * size) / step - 0.5), 0, resolution).astype(int)
    last = np.clip(np.floor((centres + radii[:, None] + 0.5 * size) / step - 0.5) + 1, 0, resolution).astype(int)
    for c, r, (i0, j0, k0), (i1, j1, k1) in zip(centres, radii, first, last):
        dx, dy, dz = axis[i0:i1] - c[0], axis[j0:j1] - c[1], axis[k0:k1] - c[2]
        covered[i0:i1, j0:j1, k0:k1] |= (dx[:, None, None] ** 2 + dy[None, :, None] ** 2 + dz[None, None, :] ** 2) < r * r
    return float(1.0 - covered.mean())


@functools.lru_cache(maxsize=None)
def constant_porosity_scale(holes: int, seed: int = 0, size: float = 2.0) -> float:
    """The radius scale at which `holes` holes leave Cheese-500's solid fraction.

    Scaling the radii by (500 / holes)^(1/3) keeps the holes' total volume but not the solid
    fraction: small holes lose less volume outside the cube (0.35 instead of 0.385 at 8000
    holes). So the scale is found by bisection on the solid fraction, counted on the same
    lattice as Cheese-500's.
    """
    target = solid_fraction(*cheese_holes(POROSITY_OF, seed, size), size)
    centres, unit = cheese_holes(holes, seed, size)
    guess = (POROSITY_OF / max(1, holes)) ** (1.0 / 3.0)
    lo, hi = 0.5 * guess, 1.5 * guess            # solid fraction falls as the scale grows
    for _ in range(16):
        mid = 0.5 * (lo + hi)
        if solid_fraction(centres, unit * mid, size) > target:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def constant_porosity_cheese(holes: int, seed: int = 0, size: float = 2.0) -> Node:
    """Cheese with `holes` holes, radii scaled to keep Cheese-500's solid fraction."""
    return cheese(holes, seed, size, constant_porosity_scale(holes, seed, size))


def sphere_chain(count: int, seed: int = 0) -> Node:
    """A left-deep union ((s0 | s1) | s2) | ... of `count` random spheres in a 10-unit cube."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-5.0, 5.0, (count, 3))
    radii = rng.uniform(0.05, 0.3, count)
    model: Node = Sphere(float(radii[0])).translate(centres[0])
    for c, r in zip(centres[1:], radii[1:]):
        model = model | Sphere(float(r)).translate(c)
    return model


def city(buildings: int = 340, seed: int = 0, windows: int = 2) -> Node:
    """A city as one CSG tree: a union, in row-major file order, of buildings on a square grid.

    A building is a tower (box or hexagonal prism) with a roof (cone or prism), minus
    `windows` window boxes per facade side and storey band (4 sides x `windows`), so a
    building has 2 + 4 * windows primitives (10 by default; 340 buildings ~ the paper's 3385).
    """
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(buildings)))
    blocks = []
    for i in range(buildings):
        gx, gy = i % side, i // side
        x, y = 3.0 * gx, 3.0 * gy
        width = rng.uniform(1.2, 2.2)
        height = rng.uniform(2.0, 9.0)
        hexagonal = rng.random() < 0.3
        if hexagonal:
            tower = Prism(6, 0.5 * width, height)
            roof = Cone(0.5 * width, 0.0, 0.3 * width + 0.5).translate((0, 0, 0.5 * height + 0.15 * width + 0.25))
        else:
            tower = Box((width, width, height))
            roof = Prism(4, 0.35 * width, 0.6).rotate("z", 45).translate((0, 0, 0.5 * height + 0.3))
        holes = []
        half = 0.5 * width
        for k in range(windows):
            z = (k + 0.5) / windows * 0.8 * height - 0.4 * height
            for angle in (0, 90, 180, 270):
                w = Box((0.3, 0.35 * width, 0.12 * height)).translate((half, 0, z)).rotate("z", angle)
                holes.append(w)
        building = difference(tower | roof, *holes).translate((x, y, 0.5 * height))
        blocks.append(building)
    return union(*blocks)


def satellite() -> Node:
    """One satellite (14 primitives): a bus with a dish, solar wings with cut-outs, a ring."""
    bus = Cylinder(0.5, 1.4) | Prism(6, 0.55, 0.2).translate((0, 0, 0.75))
    dish = (Sphere(0.6).translate((0, 0, 1.25)) - Sphere(0.58).translate((0, 0, 1.28))) & Box(2.0).translate((0, 0, 1.85))
    wing = Box((2.2, 0.7, 0.04)) - Box((0.3, 0.5, 0.1)).translate((0.5, 0, 0)) - Box((0.3, 0.5, 0.1)).translate((-0.5, 0, 0))
    wings = wing.translate((1.7, 0, 0)) | wing.translate((-1.7, 0, 0))
    mast = Cylinder(0.05, 2.6).rotate("y", 90)
    ring = Torus(0.75, 0.06)
    antenna = Cone(0.12, 0.0, 0.5).translate((0, 0, -0.95))
    return bus | dish | wings | mast | ring | antenna


def satellites(count: int = 6250, seed: int = 0, spread: float | None = None) -> Node:
    """`count` randomly placed and oriented satellites (14 primitives each): 6250 ~ the paper's
    87.5K primitives, 80000 ~ its 1.12M. Each satellite is a separate subtree of one union."""
    rng = np.random.default_rng(seed)
    one = satellite()
    spread = spread if spread is not None else 4.0 * count ** (1.0 / 3.0)
    centres = rng.uniform(-spread, spread, (count, 3))
    axes = rng.normal(size=(count, 3))
    angles = rng.uniform(0, 360, count)
    return union(*(one.rotate(tuple(a), float(t)).translate(c) for c, a, t in zip(centres, axes, angles)))


__all__ = ["cheese", "cheese_holes", "constant_porosity_cheese", "solid_fraction", "city", "satellites", "satellite", "sphere_chain"]


# ---- Named scenes: name -> generator call ----
NAMED = {
    "cheese-500": lambda: cheese(500),
    "cheese-1000": lambda: cheese(1000),
    "cheese-8000": lambda: cheese(8000),
    "cheese-32000": lambda: cheese(32000),
    # Constant porosity: Cheese-500's solid fraction at every count.
    "cheese-cp-1000": lambda: constant_porosity_cheese(1000),
    "cheese-cp-8000": lambda: constant_porosity_cheese(8000),
    "cheese-cp-32000": lambda: constant_porosity_cheese(32000),
    "city-3385": lambda: city(340),
    "city-34k": lambda: city(3400),
    "city-343k": lambda: city(34300),
    "city-987k": lambda: city(98700),
    "satellites-87.5k": lambda: satellites(6250),
    "satellites-1.12M": lambda: satellites(80000),
}
# Table 2 of the paper, in its order.
PAPER_TABLE_2 = ("city-3385", "city-343k", "city-987k", "cheese-500", "cheese-1000", "cheese-8000",
                 "cheese-32000", "satellites-87.5k", "satellites-1.12M")


def named(name: str) -> Node:
    """The built-in scene `name` (see `NAMED`), generated with its fixed seed."""
    if name not in NAMED:
        raise CSGError(f"unknown built-in scene {name!r}; known: {', '.join(NAMED)}")
    return NAMED[name]()
