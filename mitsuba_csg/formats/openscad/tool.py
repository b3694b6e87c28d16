"""OpenSCAD itself, where it is installed: `.scad` sources and the glyphs of `text()`.

mitsuba-csg reads OpenSCAD's `.csg` export (its evaluated CSG tree). For a `.scad` file we
run `openscad -o model.csg model.scad` first, and for `text()`, whose glyph outlines no
library of ours provides, OpenSCAD meshes `linear_extrude(1) text(...)` and the outline is
that mesh's section at half height, so the text is the polygon OpenSCAD itself makes (its
fonts, its `$fn`). Without OpenSCAD both say how to install it. The executable is found on
PATH (or named by the environment variable `MITSUBA_CSG_OPENSCAD`); each run is bounded in time.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from ...errors import CSGError

TIMEOUT_S = 300
INSTALL_HINT = "install OpenSCAD (Debian: apt-get install openscad)"


class OpenSCADMissing(CSGError):
    """OpenSCAD is needed and not installed."""


def executable() -> str | None:
    """The OpenSCAD executable, or None."""
    named = os.environ.get("MITSUBA_CSG_OPENSCAD")
    if named:
        return named if Path(named).is_file() else shutil.which(named)
    return shutil.which("openscad")


def run(source_path: Path, out_path: Path, what: str) -> None:
    """`openscad -o out source`; a CSGError with OpenSCAD's own message when it fails."""
    exe = executable()
    if exe is None:
        raise OpenSCADMissing(f"{what}: needs OpenSCAD, which is not installed; {INSTALL_HINT}")
    try:
        done = subprocess.run([exe, "-o", str(out_path), str(source_path)], capture_output=True, text=True,
                              timeout=TIMEOUT_S, stdin=subprocess.DEVNULL)
    except subprocess.TimeoutExpired:
        raise CSGError(f"{what}: OpenSCAD took longer than {TIMEOUT_S} s") from None
    except OSError as e:
        raise CSGError(f"{what}: could not run OpenSCAD ({exe}): {e}") from None
    if done.returncode != 0 or not out_path.exists():
        errors = [line for line in (done.stderr or "").splitlines() if "ERROR" in line or "error" in line]
        raise CSGError(f"{what}: OpenSCAD failed (exit {done.returncode})"
                       + (f": {errors[0].strip()}" if errors else ""))


def export_csg(scad_path) -> str:
    """The `.csg` text OpenSCAD evaluates `scad_path` to."""
    scad_path = Path(os.fspath(scad_path))
    if not scad_path.exists():
        raise CSGError(f"{scad_path}: no such file")
    with tempfile.TemporaryDirectory(prefix="mitsuba-csg-") as tmp:
        out = Path(tmp) / (scad_path.stem + ".csg")
        what = (f"{scad_path.name}: an OpenSCAD source (.scad) is evaluated by OpenSCAD; without it, export "
                f"the CSG tree elsewhere with `openscad -o {scad_path.stem}.csg {scad_path.name}` and load that")
        if executable() is None:
            raise OpenSCADMissing(f"{what}; {INSTALL_HINT}")
        run(scad_path.resolve(), out, scad_path.name)
        return out.read_text(encoding="utf-8")


_TEXT_CACHE: dict[str, object] = {}


def text_outline(call: str, what: str):
    """The manifold3d CrossSection of an OpenSCAD `text(...)` call (its source text)."""
    if call in _TEXT_CACHE:
        return _TEXT_CACHE[call]
    import manifold3d as m3
    from ...model.mesh import weld
    from ..mesh_import import _read_stl
    if executable() is None:
        raise OpenSCADMissing(f"{what}: text() needs OpenSCAD to draw its glyphs, and it is not installed; "
                              f"{INSTALL_HINT}, or load with on_unsupported='skip'")
    with tempfile.TemporaryDirectory(prefix="mitsuba-csg-") as tmp:
        src, out = Path(tmp) / "text.scad", Path(tmp) / "text.stl"
        src.write_text(f"linear_extrude(height = 1) {call};\n", encoding="utf-8")
        try:
            run(src, out, what)
        except CSGError as e:
            if "Current top level object is empty" in str(e) or not out.exists():
                section = m3.CrossSection()          # a text of spaces (or no glyphs): nothing
                _TEXT_CACHE[call] = section
                return section
            raise
        corners, faces = _read_stl(out.read_bytes(), str(out))
        vertices, faces = weld(corners, faces)
        solid = m3.Manifold(m3.Mesh(vert_properties=vertices.astype("float32"), tri_verts=faces.astype("uint32")))
        section = solid.slice(0.5)
    _TEXT_CACHE[call] = section
    return section
