"""Geant4 itself as the reference for GDML files: run as a script, one file per process.

    python tests/geant4_reference.py FILE.gdml RAYS.npz OUT.npz [SOLID]

A fatal Geant4 error ends the process, so the tests call this in a subprocess. It reads the
file with Geant4's own GDML parser and, for the union of every volume placed below the
world (what `csg.load` shows), answers per ray (RAYS.npz: origins `o`, unit directions `d`,
in mm):

- `inside`: whether the origin lies inside some placed solid (`G4VSolid::Inside`),
- `t`: for an inside origin, where the ray leaves the union: the largest
  `DistanceToOut` over the solids holding the point, repeated from just past there until
  no solid holds the ray (touching solids hand the ray on); for an outside
  origin, the smallest `DistanceToIn` (inf for a miss).

With SOLID, the answers are for that one solid in its own frame instead.
Files with replicated, divided or parameterised volumes are answered by Geant4's navigator
instead (`answer_by_navigation`), which places those copies by itself. Where RAYS.npz also
holds `points`, OUT.npz gets `level`: the placement depth of the deepest volume holding
each point, which sees daughters that the union of the placed solids hides.

Nothing here shares code with mitsuba-csg.
"""
from __future__ import annotations

import os
import sys
import tempfile

import numpy as np

MAX_HANDOVERS = 10_000
G4_INFINITY = 1e90             # Geant4 reports a miss as kInfinity (9e99; a scaled solid scales it)
STEP_AHEAD = 1e-6              # mm past a boundary: beyond Geant4's surface tolerance (1e-9 mm)


def _import_geant4():
    # Without GEANT4_DATA_DIR the import asks on stdin (or, under CI, downloads) the data sets,
    # which geometry queries do not need.
    os.environ.setdefault("GEANT4_DATA_DIR", tempfile.mkdtemp())
    import geant4_pybind
    return geant4_pybind


def _matrix(g4, pv):
    """x_mother = R x_local + t of a physical volume, as a 4x4 matrix."""
    r, t = pv.GetObjectRotationValue(), pv.GetObjectTranslation()
    m = np.eye(4)
    m[:3, :3] = [[r.xx, r.xy, r.xz], [r.yx, r.yy, r.yz], [r.zx, r.zy, r.zz]]
    m[:3, 3] = [t.x, t.y, t.z]
    return m


def placed_solids(g4, world):
    """(solid, local -> world matrix, world box lo, hi) of every volume placed below the world
    (the world itself when nothing is placed in it)."""
    out, stack = [], [(world.GetLogicalVolume(), np.eye(4))]
    lo, hi = g4.G4ThreeVector(), g4.G4ThreeVector()

    def add(solid, m):
        g4.G4VSolid.BoundingLimits(solid, lo, hi)
        corners = np.array([[x, y, z, 1.0] for x in (lo.x, hi.x) for y in (lo.y, hi.y) for z in (lo.z, hi.z)])
        world_corners = (corners @ m.T)[:, :3]
        out.append((solid, m, np.linalg.inv(m), world_corners.min(0), world_corners.max(0)))

    while stack:
        lv, to_world = stack.pop()
        for i in range(lv.GetNoDaughters()):
            pv = lv.GetDaughter(i)
            m = to_world @ _matrix(g4, pv)
            child = pv.GetLogicalVolume()
            add(child.GetSolid(), m)
            stack.append((child, m))
    if not out:
        add(world.GetLogicalVolume().GetSolid(), np.eye(4))
    return out


def answer(g4, solids, o, d):
    V = g4.G4ThreeVector
    lows = np.array([s[3] for s in solids]) - 1e-6
    highs = np.array([s[4] for s in solids]) + 1e-6

    def local(inv, p, v):
        lp = inv[:3, :3] @ p + inv[:3, 3]
        lv = inv[:3, :3] @ v
        return V(*lp), V(*(lv / np.linalg.norm(lv))), np.linalg.norm(lv)

    def boxed(p):
        return np.flatnonzero(np.all((p >= lows) & (p <= highs), axis=1))

    n = len(o)
    inside, t = np.zeros(n, bool), np.full(n, np.inf)
    for i in range(n):
        p, v = o[i], d[i]
        cand = boxed(p)
        inside[i] = any(g4.G4VSolid.Inside(solids[k][0], local(solids[k][2], p, v)[0]) == g4.EInside.kInside
                        for k in cand)
        if inside[i]:
            # From a boundary point, a solid holds the ray if a point just ahead is inside it
            # (DistanceToOut on a surface point of some solids reports the boundary after it).
            total, ahead = 0.0, 0.0
            for _ in range(MAX_HANDOVERS):
                q = p + (total + ahead) * v
                step = 0.0
                for k in boxed(q):
                    lp, lv, scale = local(solids[k][2], q, v)
                    if g4.G4VSolid.Inside(solids[k][0], lp) == g4.EInside.kInside:
                        step = max(step, ahead + g4.G4VSolid.DistanceToOut(solids[k][0], lp, lv) / scale)
                if step <= ahead:
                    break
                total += step
                ahead = STEP_AHEAD
            t[i] = total
        else:
            best = np.inf
            for k in range(len(solids)):
                lp, lv, scale = local(solids[k][2], p, v)
                dist = g4.G4VSolid.DistanceToIn(solids[k][0], lp, lv)
                if dist < G4_INFINITY:
                    best = min(best, dist / scale)
            t[i] = best
    return inside, t


def has_copies(world) -> bool:
    """Whether some volume is replicated, divided or parameterised (one physical volume, many copies)."""
    stack = [world.GetLogicalVolume()]
    while stack:
        lv = stack.pop()
        for i in range(lv.GetNoDaughters()):
            pv = lv.GetDaughter(i)
            if pv.IsReplicated():
                return True
            stack.append(pv.GetLogicalVolume())
    return False


def answer_by_navigation(g4, world, o, d):
    """The same answers from Geant4's navigator, which places every copy of replicated,
    divided and parameterised volumes itself: a point is inside when it is located in a
    volume below the world; a ray is followed from boundary to boundary until it leaves
    (or, from outside, first enters) that union."""
    V = g4.G4ThreeVector
    g4.G4GeometryManager.GetInstance().CloseGeometry(False, False, world)
    nav = g4.G4Navigator()
    nav.SetWorldVolume(world)
    world_lv = world.GetLogicalVolume().GetName()

    def below_world(pv):
        return pv is not None and pv.GetLogicalVolume().GetName() != world_lv

    n = len(o)
    inside, t = np.zeros(n, bool), np.full(n, np.inf)
    for i in range(n):
        dv = V(*d[i])
        pv = nav.LocateGlobalPointAndSetup(V(*o[i]), dv, False, False)
        inside[i] = below_world(pv)
        total = 0.0
        for _ in range(MAX_HANDOVERS):
            step = nav.ComputeStep(V(*(o[i] + total * d[i])), dv, 1e99, 0.0)
            if step >= G4_INFINITY:
                total = np.inf
                break
            total += step
            nav.SetGeometricallyLimitedStep()
            pv = nav.LocateGlobalPointAndSetup(V(*(o[i] + total * d[i])), dv, True, False)
            if pv is None:                       # left the world
                total = np.inf if not inside[i] else total
                break
            if below_world(pv) != inside[i]:
                break
        t[i] = total
    return inside, t


def levels(g4, world, points):
    """How many placement levels below the world the deepest volume holding each point lies
    (0: the world or outside it), as Geant4's navigator locates it."""
    V = g4.G4ThreeVector
    g4.G4GeometryManager.GetInstance().CloseGeometry(False, False, world)
    nav = g4.G4Navigator()
    nav.SetWorldVolume(world)
    out = np.zeros(len(points), dtype=np.int64)
    for i, p in enumerate(points):
        if nav.LocateGlobalPointAndSetup(V(*p), None, False, True) is not None:
            out[i] = nav.CreateTouchableHistory().GetHistoryDepth()
    return out


def _geometry_only(path, tmp):
    """The file without optical property tables and surfaces, which Geant4 without its data
    sets fails to read ("basic_string: construction from null"); the geometry is unchanged."""
    import xml.etree.ElementTree as ET
    text = open(path, encoding="utf-8").read()
    if "<matrix" not in text and "surface" not in text:
        return path
    root = ET.fromstring(text)
    # Matrices that only property tables use go too; others may hold geometry (m[i,j]).
    tables = {el.get("ref") for el in root.iter("property")}
    for parent in root.iter():
        for child in list(parent):
            if child.tag in ("property", "opticalsurface", "skinsurface", "bordersurface") or (
                    child.tag == "matrix" and child.get("name") in tables):
                parent.remove(child)
    stripped = os.path.join(tmp, os.path.basename(path))
    ET.ElementTree(root).write(stripped, encoding="utf-8", xml_declaration=True)
    return stripped


def main(argv):
    path, rays, out = argv[1:4]
    solid_name = argv[4] if len(argv) > 4 else None
    g4 = _import_geant4()
    parser = g4.G4GDMLParser()
    parser.SetOverlapCheck(False)
    parser.Read(_geometry_only(path, os.path.dirname(os.path.abspath(out))), False)   # False: no schema fetch
    world = parser.GetWorldVolume()
    data = np.load(rays)
    o, d = data["o"].astype(float), data["d"].astype(float)
    if solid_name is not None:          # one solid in its own frame
        solid = g4.G4SolidStore.GetInstance().GetSolid(solid_name, True, False)
        lo, hi = g4.G4ThreeVector(), g4.G4ThreeVector()
        g4.G4VSolid.BoundingLimits(solid, lo, hi)
        box = (np.array([lo.x, lo.y, lo.z]), np.array([hi.x, hi.y, hi.z]))
        inside, t = answer(g4, [(solid, np.eye(4), np.eye(4), *box)], o, d)
    elif has_copies(world):
        inside, t = answer_by_navigation(g4, world, o, d)
    else:
        inside, t = answer(g4, placed_solids(g4, world), o, d)
    np.savez(out, inside=inside, t=t, level=levels(g4, world, data["points"]) if "points" in data else [])


if __name__ == "__main__":
    main(sys.argv)
