"""Analytic primitives and their canonical forms.

Every primitive is described to the kernel as a *canonical* solid (unit sphere, cube
[-1,1]^3, capped cone with |z| <= 1, capped quadric of revolution rho^2 <= a z^2 + b z + c with
|z| <= 1, torus of major radius 1, convex polyhedron; meshes are their own) plus the
matrix that maps the canonical solid to the primitive's local frame. Sizes thus live in
matrices, and the kernel intersects only the canonical shapes of `engine.shapes`. All sizes
are full lengths (as in GDML and OpenSCAD); `radius`, `apothem` and `major_radius` are radii.

Each class also carries its name and parameters in native files and its reference mesh
(`nodes.Primitive`): a primitive that a canonical shape covers is this module's class alone.
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
    type_name = "sphere"
    file_parameters = {"radius": "positive"}

    def __init__(self, radius: float = 1.0, *, material: str | None = None):
        super().__init__(material=material)
        self.radius = _positive(radius, "Sphere.radius")

    def canonical(self):
        return np.diag([self.radius] * 3 + [1.0]), (0.0, 0.0), None

    def tessellate(self, segments: int):
        import manifold3d as m3
        return m3.Manifold.sphere(self.radius, segments)

    def __repr__(self):
        return f"Sphere(radius={self.radius:g}){self._transform_repr()}"


class Box(Primitive):
    """Axis-aligned box of full edge lengths `size` (a number or (x, y, z)), centred on the origin."""

    __slots__ = ("size",)
    canonical_shape = "box"
    type_name = "box"
    file_parameters = {"size": "size"}

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

    def parameters(self) -> dict:
        return {"size": list(self.size)}

    def tessellate(self, segments: int):
        import manifold3d as m3
        return m3.Manifold.cube(tuple(self.size), center=True)

    def __repr__(self):
        return f"Box(size=({', '.join(f'{v:g}' for v in self.size)})){self._transform_repr()}"


class Cone(Primitive):
    """Truncated cone along z, centred on the origin, capped at z = -height/2 and +height/2.

    `radius_bottom` is the radius at -height/2, `radius_top` at +height/2; one of them may be 0.
    """

    __slots__ = ("radius_bottom", "radius_top", "height")
    canonical_shape = "cone"
    type_name = "cone"
    file_parameters = {"radius_bottom": "nonnegative", "radius_top": "nonnegative", "height": "positive"}

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

    def mesh_key(self) -> tuple:
        return ("cone", self.radius_bottom, self.radius_top, self.height)     # cylinders too

    def tessellate(self, segments: int):
        import manifold3d as m3
        return m3.Manifold.cylinder(self.height, self.radius_bottom, self.radius_top, segments, center=True)

    def __repr__(self):
        return (f"Cone(radius_bottom={self.radius_bottom:g}, radius_top={self.radius_top:g}, "
                f"height={self.height:g}){self._transform_repr()}")


class Cylinder(Cone):
    """Capped cylinder of `radius` along z with full `height`, centred on the origin."""

    __slots__ = ()
    type_name = "cylinder"
    file_parameters = {"radius": "positive", "height": "positive"}

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
    type_name = "paraboloid"
    file_parameters = {"radius_bottom": "nonnegative", "radius_top": "nonnegative", "height": "positive"}

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

    def tessellate(self, segments: int):
        return _revolved_quadric(self, segments)

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
    type_name = "hyperboloid"
    file_parameters = {"radius": "nonnegative", "radius_end": "positive", "height": "positive"}

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

    def tessellate(self, segments: int):
        return _revolved_quadric(self, segments)

    def __repr__(self):
        return (f"Hyperboloid(radius={self.radius:g}, radius_end={self.radius_end:g}, "
                f"height={self.height:g}){self._transform_repr()}")


class Torus(Primitive):
    """Ring torus around the z axis: tube of `minor_radius` swept along a circle of `major_radius`."""

    __slots__ = ("major_radius", "minor_radius")
    canonical_shape = "torus"
    type_name = "torus"
    file_parameters = {"major_radius": "positive", "minor_radius": "positive"}

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

    def tessellate(self, segments: int):
        import manifold3d as m3
        tube = m3.CrossSection.circle(self.minor_radius, segments).translate((self.major_radius, 0.0))
        return m3.Manifold.revolve(tube, segments)

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
    type_name = "convex_polyhedron"
    file_parameters = {"planes": "planes"}
    MAX_PLANES = MAX_PLANES

    def __init__(self, planes, *, material: str | None = None):
        super().__init__(material=material)
        self.planes, self.vertices = checked_polyhedron(planes, type(self).__name__)

    def canonical(self):
        return tf.IDENTITY, (0.0, 0.0), self.planes

    def parameters(self) -> dict:
        return {"planes": self.planes.tolist()}

    def mesh_key(self) -> tuple:
        return ("convex", id(self.vertices))     # the vertices the model derived from the planes

    def tessellate(self, segments: int):
        import manifold3d as m3
        return m3.Manifold.hull_points(np.asarray(self.vertices, dtype=np.float64))

    def __repr__(self):
        return f"ConvexPolyhedron(<{len(self.planes)} planes>){self._transform_repr()}"


class Prism(ConvexPolyhedron):
    """Right prism along z over a regular polygon with `sides` sides and inner radius `apothem`.

    Full `height`, centred on the origin; one vertex-free edge faces +x (a side's normal is +x).
    `Prism(6, a, h)` is the hexagonal prism of the paper and GDML polyhedra.
    """

    __slots__ = ("sides", "apothem", "height")
    type_name = "prism"
    file_parameters = {"sides": "sides", "apothem": "positive", "height": "positive"}
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

    def parameters(self) -> dict:
        return {"sides": self.sides, "apothem": self.apothem, "height": self.height}

    def mesh_key(self) -> tuple:
        return ("prism", self.sides, self.apothem, self.height)

    def tessellate(self, segments: int):
        import manifold3d as m3
        # A regular polygon with apothem a has its vertices at a / cos(pi / sides); a side faces +x.
        k = np.arange(self.sides)
        angles = (k + 0.5) * 2.0 * np.pi / self.sides
        r = self.apothem / np.cos(np.pi / self.sides)
        ring = np.stack([r * np.cos(angles), r * np.sin(angles)], 1)
        z = np.full((self.sides, 1), 0.5 * self.height)
        return m3.Manifold.hull_points(np.vstack([np.hstack([ring, -z]), np.hstack([ring, z])]))

    def __repr__(self):
        return (f"Prism(sides={self.sides}, apothem={self.apothem:g}, height={self.height:g})"
                f"{self._transform_repr()}")


def _revolved_quadric(prim, n: int):
    """The reference mesh of a paraboloid or hyperboloid: its profile rho(z) revolved, sampled
    at n / 2 even steps in z and at the z of n / 2 even steps in rho on each side (a tip's rho
    grows as a square root), so that the profile's chords stray about as far as the circles'
    sagitta."""
    import manifold3d as m3
    canonical, (a, b), _ = prim.canonical()
    r, half = canonical[0, 0], canonical[2, 2]
    c = 1.0 - a - abs(b)
    k = max(n // 2, 2)
    levels = np.linspace(0.0, 1.0, k + 1) ** 2 - c         # a z^2 + b z = rho^2 - c
    with np.errstate(divide="ignore", invalid="ignore"):
        if a > 0:
            disc = np.sqrt(np.maximum(b * b + 4.0 * a * levels, 0.0))
            steps = np.concatenate([(-b - disc) / (2.0 * a), (-b + disc) / (2.0 * a)])
        else:
            steps = levels / b
    steps = steps[np.isfinite(steps) & (np.abs(steps) < 1.0)]
    s = np.unique(np.concatenate([np.linspace(-1.0, 1.0, k + 1), steps]))
    s = s[np.concatenate([[True], np.diff(s) > 1e-9])]
    rho = r * np.sqrt(np.maximum(a * s * s + b * s + c, 0.0))
    # The outline runs up the axis' far side: from (0, -half) along the profile to (0, half).
    # Profile points on the axis (a tip, a double cone's apex) are the axis points themselves.
    on_axis = rho <= 1e-9 * r
    points = [[0.0, -half]]
    for k in range(len(s)):
        if not on_axis[k]:
            points.append([rho[k], half * s[k]])
        elif 0 < k < len(s) - 1:
            points.append([0.0, half * s[k]])
    points.append([0.0, half])
    polygon = np.array(points)
    return m3.Manifold.revolve(m3.CrossSection([polygon]), n)
