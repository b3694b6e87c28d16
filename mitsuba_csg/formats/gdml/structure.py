"""GDML's structure: the world volume, its placed daughters and assemblies, as one union.

Placements follow `G4GDMLReadStructure::PhysvolRead`: G4Transform3D(R.inverse(), t) *
G4Scale3D(s), so a daughter moves by x' = R^-1 (s x) + t.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from typing import NamedTuple

import numpy as np

from ...errors import ModelError
from ...model import transform as tf
from ...model.nodes import MAX_LEAVES, Node, Operation
from ..reading import FormatError
from .defines import affine, placement, rotation_matrix
from .replicas import division_copies, parameterised_copies, replica_copies

MAX_PLACEMENTS = 2_000_000         # placed volumes in the scene
MAX_VOLUME_DEPTH = 10_000          # placement levels
_PLACING = ("physvol", "replicavol", "paramvol", "divisionvol")


def world_name(doc) -> tuple[str, ET.Element]:
    setups = [s for s in doc.root if s.tag == "setup"]
    if not setups:
        doc.fail(doc.root, "no <setup> with a <world ref=...>: the world volume is unknown")
    setup = next((s for s in setups if s.get("name") == "Default"), setups[0])
    world = setup.find("world")
    if world is None or not world.get("ref"):
        doc.fail(setup, "needs <world ref=\"...\"/>")
    return world.get("ref"), world


def _ref(doc, el, tag) -> tuple[ET.Element, str]:
    child = el.find(tag)
    if child is None or not child.get("ref"):
        doc.fail(el, f"needs <{tag} ref=\"...\"/>")
    return child, child.get("ref")


class PlacedVolume(NamedTuple):
    """One placed copy of a logical volume: its solid in world coordinates (named with its
    material), its placement level (the world is 0), the logical volume's name, and its colour
    (R, G, B, A from a `colorref` of Geant4's simple extension) or None."""
    node: Node
    level: int
    name: str
    colour: tuple[float, float, float, float] | None


def scene(doc, solids, depth: int | None, show_world: bool | None) -> Node:
    """The union of the placed volumes."""
    placed = [v.node for v in placed_volumes(doc, solids, depth, show_world)]
    return placed[0] if len(placed) == 1 else Operation("union", placed)


def placed_volumes(doc, solids, depth: int | None, show_world: bool | None) -> list[PlacedVolume]:
    """Every placed volume in a depth-first pre-order walk."""
    world, world_el = world_name(doc)
    if world not in doc.volumes:
        doc.fail(world_el, f"refers to undefined volume {world!r}" +
                 (" (an assembly cannot be the world)" if world in doc.assemblies else ""))
    if show_world is None:
        # A file of one volume (a phantom's organ, a test box) is that volume.
        show_world = not any(child.tag in _PLACING for child in doc.volumes[world])
    _check_expanded_size(doc, solids, world, world_el, depth, show_world)
    placed: list[PlacedVolume] = []
    count = 0
    # A volume placed many times is read once: its solid, and the copies each of its
    # placements makes (keyed by element).
    solid_of: dict[int, Node | None] = {}
    copies_of: dict[int, list] = {}
    # (element, world matrix, depth, ancestors, the copy's own solid or None); assemblies are
    # expanded at the placing level
    stack = [(doc.volumes[world], tf.IDENTITY, 0, (world,), None, world_el)]
    while stack:
        vol, matrix, level, ancestors, own_solid, placer = stack.pop()
        is_assembly = vol.tag == "assembly"
        if not is_assembly and (level > 0 or show_world):
            if own_solid is None:
                if id(vol) not in solid_of:
                    solid_of[id(vol)] = _volume_solid(doc, solids, vol)
                node = solid_of[id(vol)]
            else:
                node = _volume_solid(doc, solids, vol, own_solid)
            if node is not None:
                try:
                    node = node if matrix is tf.IDENTITY else node.transform(matrix)
                except ModelError as e:        # the placements down to here compose to no usable map
                    doc.fail(placer, f"{e} (the placement of {_strip_pointer(vol.get('name', ''))!r} in the world)")
                placed.append(PlacedVolume(node, level,
                                           _strip_pointer(vol.get("name", "")), _colour(doc, vol)))
        child_level = level if is_assembly else level + 1
        if depth is not None and child_level > depth:
            continue
        children = []
        for pv in vol:
            if pv.tag not in _PLACING:
                continue
            if pv.find("file") is not None:
                doc.unsupported(pv, "<physvol> with <file> (an external GDML file) is not supported")
                continue
            ref_el, ref = _ref(doc, pv, "volumeref")
            target = doc.volumes.get(ref)
            if target is None and pv.tag == "physvol":
                target = doc.assemblies.get(ref)
            if target is None:
                doc.fail(ref_el, f"refers to undefined volume {ref!r}")
            if ref in ancestors:
                doc.fail(pv, f"volume placement cycle: {' -> '.join(ancestors[ancestors.index(ref):] + (ref,))}")
            if len(ancestors) > MAX_VOLUME_DEPTH:
                doc.fail(pv, f"placements nested more than {MAX_VOLUME_DEPTH} deep")
            copies = copies_of.get(id(pv))
            if copies is None:
                copies = copies_of[id(pv)] = _copies(doc, solids, vol, pv)
            count += len(copies)
            if count > MAX_PLACEMENTS:
                doc.fail(pv, f"more than {MAX_PLACEMENTS} placed volumes")
            children.extend((target, tf.compose(matrix, _frozen(local)), child_level, ancestors + (ref,), solid, pv)
                            for local, solid in copies)
        stack.extend(reversed(children))   # popped in document order: a depth-first pre-order walk
    if not placed:
        raise FormatError(f"{doc.source}: nothing to show: no placed volume "
                          f"{'at all' if show_world else 'below the world (show_world=True shows the world)'}")
    return placed


def _check_expanded_size(doc, solids, world, world_el, depth, show_world) -> None:
    """Refuse, before expanding anything, a hierarchy whose placed volumes or primitives would
    exceed the limits: a volume placed twice per level doubles them at every level, so a file
    of a few kilobytes can describe 2^40 copies. Counts are kept per (volume, level), so the
    cost is that of the distinct volumes, not of their copies."""
    counts: dict[tuple[str, int], tuple[int, int]] = {}   # (placements, primitives) below a placed volume
    open_keys: set[tuple[str, int]] = set()                # on the current path: seen again, a cycle
    stack = [(world, 0, False)]
    while stack:
        name, level, children_done = stack.pop()
        # Without a depth limit only the world's own level differs from the others.
        key = (name, level if depth is not None else min(level, 1))
        if key in counts:
            continue
        vol = doc.volumes.get(name, doc.assemblies.get(name))
        is_assembly = vol.tag == "assembly"
        child_level = level if is_assembly else level + 1
        placements = []
        if depth is None or child_level <= depth:
            for pv in vol:
                if pv.tag in _PLACING and pv.find("file") is None:
                    ref = pv.find("volumeref")
                    ref = ref.get("ref") if ref is not None else None
                    if ref in doc.volumes or (pv.tag == "physvol" and ref in doc.assemblies):
                        placements.append((pv, ref))
        if not children_done:
            if key in open_keys:
                return                               # a placement cycle: the walk names it
            open_keys.add(key)
            stack.append((name, level, True))
            stack.extend((ref, child_level, False) for _, ref in placements)
            continue
        open_keys.discard(key)
        own = 0
        if not is_assembly and (level > 0 or show_world):
            node = _volume_solid(doc, solids, vol)
            own = node.leaf_count if node is not None else 0
        n_placed, n_leaves = 0, own
        for pv, ref in placements:
            copies = len(_copies(doc, solids, vol, pv))
            below = counts[(ref, child_level if depth is not None else 1)]
            n_placed += copies * (1 + below[0])
            n_leaves += copies * below[1]
            if n_placed > MAX_PLACEMENTS:
                doc.fail(pv, f"the hierarchy places {n_placed:.3g} volumes or more (copies of copies), more "
                             f"than the limit of {MAX_PLACEMENTS}")
            if n_leaves > MAX_LEAVES:
                doc.fail(pv, f"the placed volumes hold {n_leaves:.3g} primitives or more (copies of copies), "
                             f"more than the limit of {MAX_LEAVES:.0e}")
        counts[key] = (n_placed, n_leaves)


def _copies(doc, solids, vol, pv) -> list[tuple[np.ndarray, Node | None]]:
    """(placement in the mother, the copy's own solid or None) of each copy `pv` places."""
    try:
        return _placed_copies(doc, solids, vol, pv)
    except ModelError as e:
        if isinstance(e, FormatError):
            raise
        doc.fail(pv, str(e))


def _placed_copies(doc, solids, vol, pv) -> list[tuple[np.ndarray, Node | None]]:
    if pv.tag == "replicavol":
        return replica_copies(doc, pv)
    if pv.tag == "divisionvol":
        return division_copies(doc, pv, doc.solid_elements.get(_ref(doc, vol, "solidref")[1], vol))
    if pv.tag == "paramvol":
        return parameterised_copies(doc, solids, pv)
    t, r, s = placement(doc, pv)
    if np.any(s == 0):
        doc.fail(pv, f"scale factors must be non-zero, got {s.tolist()}")
    # G4GDMLReadStructure::PhysvolRead: G4Transform3D(R.inverse(), t) * G4Scale3D(s).
    return [(affine(rotation_matrix(r).T @ np.diag(s), t), None)]


def _volume_solid(doc, solids, vol, own_solid=None) -> Node | None:
    solid_el, solid_name = _ref(doc, vol, "solidref")
    node = own_solid if own_solid is not None else solids.solid(solid_name, solid_el)
    if node is None:
        return None
    mat = vol.find("materialref")
    if mat is not None and mat.get("ref"):
        name = _strip_pointer(mat.get("ref"))
        node = node.with_material(name)
    return node


def _colour(doc, vol):
    ref = vol.find("colorref")
    if ref is None or not ref.get("ref"):
        return None
    if ref.get("ref") not in doc.colours:
        doc.fail(ref, f"refers to undefined color {ref.get('ref')!r}")
    return doc.colours[ref.get("ref")]


def _frozen(m):
    m.setflags(write=False)
    return m


def _strip_pointer(name: str) -> str:
    """Geant4's writer appends '0x<address>' to names; its reader strips it, and so do we."""
    head = name.split("0x", 1)[0]
    return head if head else name
