"""Seeded generators of the paper's test models (Bogolepov et al. 2013, Table 2)."""
from __future__ import annotations

import numpy as np

from .model import Node, difference, union
from .primitives import Box, Sphere


def cheese(holes: int = 500, seed: int = 0, size: float = 2.0) -> Node:
    """A cube of edge `size` minus `holes` overlapping spheres (the paper's Cheese).

    Hole centres are uniform in the cube; radii uniform in [0.03, 0.12] * size, so holes
    overlap each other and cut the faces. Leaf 0 is the cube, leaf i the i-th hole.
    """
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-0.5 * size, 0.5 * size, (holes, 3))
    radii = rng.uniform(0.03, 0.12, holes) * size
    spheres = [Sphere(float(r)).translate(c) for c, r in zip(centres, radii)]
    return difference(Box(size), *spheres) if holes else Box(size)


def sphere_chain(count: int, seed: int = 0) -> Node:
    """A left-deep union ((s0 | s1) | s2) | ... of `count` random spheres in a 10-unit cube."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-5.0, 5.0, (count, 3))
    radii = rng.uniform(0.05, 0.3, count)
    model: Node = Sphere(float(radii[0])).translate(centres[0])
    for c, r in zip(centres[1:], radii[1:]):
        model = model | Sphere(float(r)).translate(c)
    return model


__all__ = ["cheese", "sphere_chain", "union"]
