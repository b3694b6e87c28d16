"""The CSG model: immutable trees of primitives and Boolean operations (numpy, float64).

`nodes` holds the tree and its operators, `primitives` the analytic solids, `mesh` closed
triangle meshes as leaves, `transform`
the affine matrices, `values` the checks of user-given numbers, `polyhedra` convex solids
as planes and vertices, and `construct` the cuts that file readers build solids from.
Nothing here knows about the kernel or Mitsuba.
"""
from .nodes import DIFFERENCE, INTERSECTION, OPERATIONS, UNION, Node, Operation, Primitive, difference, intersection, union
from .mesh import Mesh, MeshOrientationWarning
from .primitives import Box, Cone, ConvexPolyhedron, Cylinder, Hyperboloid, Paraboloid, Prism, Sphere, Torus

__all__ = ["DIFFERENCE", "INTERSECTION", "OPERATIONS", "UNION", "Box", "Cone", "ConvexPolyhedron", "Cylinder", "Hyperboloid", "Mesh",
           "MeshOrientationWarning",
           "Node", "Operation", "Paraboloid", "Primitive", "Prism", "Sphere", "Torus", "difference", "intersection", "union"]
