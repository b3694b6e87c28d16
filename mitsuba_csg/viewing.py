"""What a first render of a model shows: colours per material, cut-aways, and detectors drawn
as Geant4's visualisation draws them (mothers see-through, daughters solid).

Used by the command line (`mitsuba-csg render`); the functions return models and Mitsuba
scene-dict pieces, so scripts can build the same views.
"""
from __future__ import annotations

import colorsys
import re
import zlib

import numpy as np

from .errors import CSGError
from .model.nodes import Node, intersection, union
from .model.primitives import Box

# OpenSCAD's color("name") leaves the name as the material (formats.openscad); the CSS basics.
_NAMED = {"red": (1, 0, 0), "green": (0, 0.5, 0), "blue": (0, 0, 1), "yellow": (1, 1, 0), "white": (1, 1, 1),
          "black": (0, 0, 0), "gray": (0.5, 0.5, 0.5), "grey": (0.5, 0.5, 0.5), "orange": (1, 0.65, 0),
          "purple": (0.5, 0, 0.5), "cyan": (0, 1, 1), "magenta": (1, 0, 1), "lime": (0, 1, 0),
          "silver": (0.75, 0.75, 0.75), "brown": (0.65, 0.16, 0.16), "pink": (1, 0.75, 0.8)}
MOTHER_OPACITY = 0.15
# Envelopes of air or vacuum are drawn by nobody (Geant4's examples hide them in vis.mac).
_GAS = re.compile(r"air|vacuum|galactic|gas|helium|nitrogen|argon_gas", re.IGNORECASE)


def is_gas(material: str | None) -> bool:
    return bool(material) and bool(_GAS.search(material))


# Well-separated hues for materials without a colour of their own, in order of their names.
_PALETTE = [colorsys.hsv_to_rgb(((k * 0.381966) % 1.0), 0.5, 0.85) for k in range(24)]


def material_colour(name: str | None, index: int | None = None) -> tuple[float, float, float, float]:
    """RGBA for a material: OpenSCAD's `color_R_G_B_A` and colour names as written, any other
    name the palette colour `index` (of its place among the scene's materials; without one, a
    stable colour from a hash of the name), no material a light grey."""
    if not name:
        return (0.7, 0.7, 0.72, 1.0)
    m = re.fullmatch(r"color_([0-9.]+)_([0-9.]+)_([0-9.]+)_([0-9.]+)", name)
    if m:
        return tuple(min(1.0, max(0.0, float(v))) for v in m.groups())
    if name.lower() in _NAMED:
        return (*_NAMED[name.lower()], 1.0)
    k = index if index is not None else zlib.crc32(name.encode("utf-8"))
    return (*_PALETTE[k % len(_PALETTE)], 1.0)


def bsdf(rgba) -> dict:
    """A diffuse BSDF of the colour; translucent colours (alpha < 1) through Mitsuba's mask."""
    r, g, b, a = (float(v) for v in rgba)
    diffuse = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [r, g, b]}}
    return diffuse if a >= 1.0 else {"type": "mask", "opacity": {"type": "rgb", "value": [a, a, a]},
                                     "bsdf": diffuse}


def material_bsdfs(model: Node) -> dict:
    """One BSDF per material name of the model's leaves (keys as the csg shape reads them)."""
    names = sorted({leaf.material for leaf in model.leaves() if leaf.material})
    return {name: bsdf(material_colour(name, k)) for k, name in enumerate(names)}


_CUT = re.compile(r"^\s*([xyz])\s*([<>])\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*$")


def parse_cut(text: str) -> tuple[int, int, float]:
    """`x>0`, `y<-10`, `z>2.5`: (axis, +1 keep above / -1 keep below, value)."""
    m = _CUT.match(text)
    if not m:
        raise CSGError(f"--cut {text!r}: expected AXIS>VALUE or AXIS<VALUE, such as x>0 or z<12.5")
    return "xyz".index(m.group(1)), 1 if m.group(2) == ">" else -1, float(m.group(3))


def cut(model: Node, cuts, lower=None, upper=None, material: str | None = None) -> Node:
    """The model intersected with half-spaces (`parse_cut` triples): exact, the cut faces are
    the planes, of `material` (else the default). The half-spaces are boxes reaching well past
    the bounds [lower, upper] (the model's by default)."""
    if not cuts:
        return model
    if lower is None:
        lower, upper = model.bounds()
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    reach = 4.0 * float(np.max(upper - lower)) + 1.0
    centre = 0.5 * (lower + upper)
    keep = []
    for axis, side, value in cuts:
        size = np.full(3, 2.0 * reach)
        offset = centre.copy()
        offset[axis] = value + side * reach
        keep.append(Box(tuple(size), material=material).translate(tuple(offset)))
    return intersection(model, *keep)


class DetectorView:
    """A GDML detector as Geant4's visualisation shows it: the volumes that hold others
    (mothers) see-through, the rest solid, each in its colour (the file's `colorref`, else its
    material's); volumes of air or vacuum (envelopes; unless nothing else is there) and hidden
    ones (by logical-volume name or material) left out."""

    def __init__(self, volumes, hide=()):
        hide = set(hide)
        shown = [v for v in volumes if v.name not in hide and (v.node.material or "") not in hide]
        solid = [v for v in shown if not (is_gas(v.node.material) and v.colour is None)]
        shown = solid or shown              # a geometry made of air only (a test file) stays visible
        if not shown:
            raise CSGError("nothing left to show: every placed volume is hidden")
        self.mothers, self.solids, self.colours = [], [], {}
        for i, v in enumerate(shown):
            holds = i + 1 < len(shown) and shown[i + 1].level > v.level
            node = v.node
            if v.colour is not None:
                key = "rgba_" + "_".join(f"{c:.3f}" for c in v.colour)
                self.colours[key] = v.colour
                node = node.with_material(key)
            (self.mothers if holds else self.solids).append(node)

    def models(self, cuts=()):
        """(mothers, solids): unions (or None), cut by the half-spaces."""
        everything = self.mothers + self.solids
        lower, upper = union(*everything).bounds() if len(everything) > 1 else everything[0].bounds()
        out = []
        for nodes in (self.mothers, self.solids):
            # Each volume is cut on its own, so that its cut face has its material (a section view).
            nodes = [cut(n, cuts, lower, upper, n.material) for n in nodes]
            out.append(None if not nodes else nodes[0] if len(nodes) == 1 else union(*nodes))
        return out[0], out[1]

    def bsdfs(self, solids: Node) -> dict:
        table = material_bsdfs(solids)
        for key, rgba in self.colours.items():
            if key in table:
                table[key] = bsdf(rgba)
        return table


def mother_bsdf() -> dict:
    return bsdf((0.75, 0.8, 0.9, MOTHER_OPACITY))


def model_parts(path, cuts=(), hide=(), **load_options) -> list:
    """The csg shapes a model file is shown with: [(model, {material: bsdf dict}, default bsdf
    dict)] for `scene_setup.scene_dict`. A GDML detector gives its see-through mothers and its solid
    volumes (`DetectorView`), anything else one shape; `cuts` are `parse_cut` triples."""
    from pathlib import Path
    from .formats import load
    if Path(path).suffix.lower() == ".gdml":
        from .formats import gdml
        view = DetectorView(gdml.volumes(path, **load_options), hide=hide)
        mothers, solids = view.models(cuts)
        parts = []
        if solids is not None:
            parts.append((solids, view.bsdfs(solids), bsdf(material_colour(None))))
        if mothers is not None:
            parts.append((mothers, {}, mother_bsdf()))
        return parts
    if hide:
        raise CSGError(f"{path}: hiding volumes applies to GDML detectors")
    model = cut(load(path, **load_options), cuts)
    return [(model, material_bsdfs(model), bsdf(material_colour(None)))]
