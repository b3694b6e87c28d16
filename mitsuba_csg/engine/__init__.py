"""The engine: a model becomes flat arrays on the device, traced by the Dr.Jit automaton.

`layout` (codes and bit layouts), `lowering` (model -> flat binary tree, bounds),
`optimize` and `sah` (paper §4), `shapes` (the canonical primitives: intersection, surface
function, bounds), `device` (upload), `automaton` (the kernel), `hit_geometry` (normals and
the differentiable hit), `backend` (LLVM or CUDA types).
"""
