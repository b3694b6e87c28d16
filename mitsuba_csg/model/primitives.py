"""Analytic primitives and their canonical forms.

Every primitive is described to the kernel as a *canonical* solid (unit sphere, cube
[-1,1]^3, capped cone with |z| <= 1, capped quadric of revolution rho^2 <= a z^2 + b z + c with
|z| <= 1, torus of major radius 1, convex polyhedron; meshes are their own) plus the
matrix that maps the canonical solid to the primitive's local frame. Sizes thus live in
matrices, and the kernel intersects only the canonical shapes of `engine.layout.SHAPE_CODES`. All sizes are full lengths (as in
GDML and OpenSCAD); `radius`, `apothem` and `major_radius` are radii.
"""
from __future__ import annotations

import numpy as np

from ..errors import ModelError
from . import transform as tf
from . import values
from .polyhedra import MAX_PLANES, checked_polyhedron
from .nodes import Primitive


def _positive(value, what: str) -> float:
    return values.checked(values.positive, value, what)


def _nonnegative(value, what: str) -> float:
    return values.checked(values.nonnegative, value, what)


class Sphere(Primitive):
    """Sphere of `radius` centred on the origin."""

    __slots__ = ("radius",)
    canonical_shape = "sphere"

    def __init__(self, radius: float = 1.0, *, material: str | None = None):
        super().__init__(material=material)
        self.radius = _positive(radius, "Sphere.radius")

    def canonical(self):
        return np.diag([self.radius] * 3 + [1.0]), (0.0, 0.0), None

    def __repr__(self):
        return f"Sphere(radius={self.radius:g}){self._transform_repr()}"


class Box(Primitive):
    """Axis-aligned box of full edge lengths `size` (a number or (x, y, z)), centred on the origin."""

    __slots__ = ("size",)
    canonical_shape = "box"

    def __init__(self, size=(1.0, 1.0, 1.0), *, material: str | None = None):
        super().__init__(material=material)
        if isinstance(size, (list, tuple, np.ndarray)):
            if len(size) != 3 or (isinstance(size, np.ndarray) and size.ndim != 1):
                raise ModelError(f"Box.size: expected a number or 3 numbers, got {len(size)} items")
            self.size = tuple(_positive(v, f"Box.size[{i}]") for i, v in enumerate(size))
        else:               # one number for all three edges, checked like any other size
            self.size = (_positive(size, "Box.size"),) * 3

    def canonical(self):
        return np.diag([*(0.5 * np.array(self.size)), 1.0]), (0.0, 0.0), None

    def __repr__(self):
        return f"Box(size=({', '.join(f'{v:g}' for v in self.size)})){self._transform_repr()}"


class Cone(Primitive):
    """Truncated cone along z, centred on the origin, capped at z = -height/2 and +height/2.

    `radius_bottom` is the radius at -height/2, `radius_top` at +height/2; one of them may be 0.
    """

    __slots__ = ("radius_bottom", "radius_top", "height")
    canonical_shape = "cone"

    def __init__(self, radius_bottom: float = 1.0, radius_top: float = 0.0, height: float = 1.0, *,
                 material: str | None = None):
        super().__init__(material=material)
        name = type(self).__name__
        self.radius_bottom = _nonnegative(radius_bottom, f"{name}.radius_bottom")
        self.radius_top = _nonnegative(radius_top, f"{name}.radius_top")
        if self.radius_bottom == 0 and self.radius_top == 0:
            raise ModelError(f"{name}: radius_bottom and radius_top are both 0 (no volume)")
        self.height = _positive(height, f"{name}.height")

    def canonical(self):
        r = max(self.radius_bottom, self.radius_top)
        return (np.diag([r, r, 0.5 * self.height, 1.0]),
                (self.radius_bottom / r, self.radius_top / r), None)

    def __repr__(self):
        return (f"Cone(radius_bottom={self.radius_bottom:g}, radius_top={self.radius_top:g}, "
                f"height={self.height:g}){self._transform_repr()}")


class Cylinder(Cone):
    """Capped cylinder of `radius` along z with full `height`, centred on the origin."""

    __slots__ = ()

    def __init__(self, radius: float = 1.0, height: float = 1.0, *, material: str | None = None):
        radius = _positive(radius, "Cylinder.radius")
        super().__init__(radius, radius, height, material=material)

    @property
    def radius(self) -> float:
        return self.radius_bottom

    def __repr__(self):
        return f"Cylinder(radius={self.radius:g}, height={self.height:g}){self._transform_repr()}"


class Paraboloid(Primitive):
    """Paraboloid of revolution along z (Geant4's G4Paraboloid), capped at z = -height/2 and +height/2.

    The side is rho^2 = k1 z + k2 through `radius_bottom` at -height/2 and `radius_top` at
    +height/2 (one of them may be 0: the tip).
    """

    __slots__ = ("radius_bottom", "radius_top", "height")
    canonical_shape = "quadric"

    def __init__(self, radius_bottom: float = 0.0, radius_top: float = 1.0, height: float = 1.0, *,
                 material: str | None = None):
        super().__init__(material=material)
        name = type(self).__name__
        self.radius_bottom = _nonnegative(radius_bottom, f"{name}.radius_bottom")
        self.radius_top = _nonnegative(radius_top, f"{name}.radius_top")
        if self.radius_bottom == self.radius_top:
            raise ModelError(f"{name}: radius_bottom and radius_top are both {self.radius_top:g}; equal radii "
                             f"make no paraboloid (use a Cylinder)")
        self.height = _positive(height, f"{name}.height")

    def canonical(self):
        r = max(self.radius_bottom, self.radius_top)
        lo, hi = (self.radius_bottom / r) ** 2, (self.radius_top / r) ** 2
        return np.diag([r, r, 0.5 * self.height, 1.0]), (0.0, 0.5 * (hi - lo)), None

    def __repr__(self):
        return (f"Paraboloid(radius_bottom={self.radius_bottom:g}, radius_top={self.radius_top:g}, "
                f"height={self.height:g}){self._transform_repr()}")


class Hyperboloid(Primitive):
    """Hyperboloid of one sheet along z, capped at z = -height/2 and +height/2 (Geant4's G4Hype
    without its inner surface): rho^2 = radius^2 + (radius_end^2 - radius^2) (2 z / height)^2,
    `radius` at the waist z = 0 and `radius_end` at the caps. `radius` 0 gives a double cone;
    equal radii a cylinder.
    """

    __slots__ = ("radius", "radius_end", "height")
    canonical_shape = "quadric"

    def __init__(self, radius: float = 0.5, radius_end: float = 1.0, height: float = 1.0, *,
                 material: str | None = None):
        super().__init__(material=material)
        name = type(self).__name__
        self.radius = _nonnegative(radius, f"{name}.radius")
        self.radius_end = _positive(radius_end, f"{name}.radius_end")
        if self.radius > self.radius_end:
            raise ModelError(f"{name}: radius ({self.radius:g}) must not exceed radius_end ({self.radius_end:g}): "
                             f"the waist is the narrowest place")
        self.height = _positive(height, f"{name}.height")

    @classmethod
    def from_stereo(cls, radius: float, stereo: float, height: float, *, material: str | None = None):
        """Geant4's form: the waist `radius` and the stereo angle (radians) between the side's
        lines and the z axis, tan(stereo) = d rho / d z far from the waist."""
        slope = np.tan(values.checked(values.nonnegative, stereo, "Hyperboloid.stereo"))
        if not stereo < 0.5 * np.pi:
            raise ModelError(f"Hyperboloid.stereo: must be below 90 degrees, got {stereo:g} rad")
        return cls(radius, float(np.hypot(radius, slope * 0.5 * height)), height, material=material)

    def canonical(self):
        r = self.radius_end
        return np.diag([r, r, 0.5 * self.height, 1.0]), (1.0 - (self.radius / r) ** 2, 0.0), None

    def __repr__(self):
        return (f"Hyperboloid(radius={self.radius:g}, radius_end={self.radius_end:g}, "
                f"height={self.height:g}){self._transform_repr()}")


class Torus(Primitive):
    """Ring torus around the z axis: tube of `minor_radius` swept along a circle of `major_radius`."""

    __slots__ = ("major_radius", "minor_radius")
    canonical_shape = "torus"

    def __init__(self, major_radius: float = 1.0, minor_radius: float = 0.25, *, material: str | None = None):
        super().__init__(material=material)
        self.major_radius = _positive(major_radius, "Torus.major_radius")
        self.minor_radius = _positive(minor_radius, "Torus.minor_radius")
        if self.minor_radius >= self.major_radius:
            raise ModelError(f"Torus: minor_radius ({self.minor_radius:g}) must be < major_radius "
                             f"({self.major_radius:g}); horn and spindle tori are not supported")

    def canonical(self):
        R = self.major_radius
        return np.diag([R, R, R, 1.0]), (self.minor_radius / R, 0.0), None

    def __repr__(self):
        return (f"Torus(major_radius={self.major_radius:g}, minor_radius={self.minor_radius:g})"
                f"{self._transform_repr()}")


class ConvexPolyhedron(Primitive):
    """Bounded convex solid {x : n_i . x <= d_i}, given as rows (nx, ny, nz, d) of `planes`.

    Normals point outwards and need not be unit length. The half-spaces must bound a solid
    with volume; redundant planes are allowed.
    """

    __slots__ = ("planes", "vertices")
    canonical_shape = "convex"
    MAX_PLANES = MAX_PLANES

    def __init__(self, planes, *, material: str | None = None):
        super().__init__(material=material)
        self.planes, self.vertices = checked_polyhedron(planes, type(self).__name__)

    def canonical(self):
        return tf.IDENTITY, (0.0, 0.0), self.planes

    def __repr__(self):
        return f"ConvexPolyhedron(<{len(self.planes)} planes>){self._transform_repr()}"


class Prism(ConvexPolyhedron):
    """Right prism along z over a regular polygon with `sides` sides and inner radius `apothem`.

    Full `height`, centred on the origin; one vertex-free edge faces +x (a side's normal is +x).
    `Prism(6, a, h)` is the hexagonal prism of the paper and GDML polyhedra.
    """

    __slots__ = ("sides", "apothem", "height")
    _unit_cache: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def __init__(self, sides: int = 6, apothem: float = 1.0, height: float = 1.0, *, material: str | None = None):
        Primitive.__init__(self, material=material)
        self.sides = values.checked(values.integer, sides, "Prism.sides", 3, 1000)
        self.apothem = _positive(apothem, "Prism.apothem")
        self.height = _positive(height, "Prism.height")
        # All prisms with the same number of sides share one set of canonical planes.
        if self.sides not in self._unit_cache:
            angles = 2.0 * np.pi * np.arange(self.sides) / self.sides
            sides_planes = np.stack([np.cos(angles), np.sin(angles), np.zeros_like(angles), np.ones_like(angles)], 1)
            caps = np.array([[0.0, 0.0, 1.0, 1.0], [0.0, 0.0, -1.0, 1.0]])
            self._unit_cache[self.sides] = checked_polyhedron(np.vstack([sides_planes, caps]), "Prism")
        self.planes, self.vertices = self._unit_cache[self.sides]

    def canonical(self):
        a = self.apothem
        return np.diag([a, a, 0.5 * self.height, 1.0]), (0.0, 0.0), self.planes

    def __repr__(self):
        return (f"Prism(sides={self.sides}, apothem={self.apothem:g}, height={self.height:g})"
                f"{self._transform_repr()}")
