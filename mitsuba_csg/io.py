"""`load` and `save`: model files by extension."""
from __future__ import annotations

from pathlib import Path

from .errors import CSGError

SUPPORTED = {".json": "mitsuba-csg native JSON", ".csg": "OpenSCAD .csg", ".gdml": "Geant4 GDML"}
PLANNED: dict[str, str] = {}


def load(path, **options):
    """Load a model from `path`; the extension picks the format (`.json`, `.csg`, `.gdml`).

    Options go to the format's loader: `on_unsupported="skip"` (OpenSCAD, GDML) and, for
    GDML, `solid="name"` (one solid in its own frame), `depth=k`, `show_world=True`.
    """
    suffix = Path(path).suffix.lower()
    if suffix == ".json":
        from . import native
        return native.load(path, **options)
    if suffix == ".csg":
        from . import openscad
        return openscad.load(path, **options)
    if suffix == ".gdml":
        from . import gdml
        return gdml.load(path, **options)
    if suffix in PLANNED:
        raise CSGError(f"{path}: {PLANNED[suffix]} files are not supported yet; supported: "
                       f"{', '.join(SUPPORTED)}")
    raise CSGError(f"{path}: unknown model format {suffix or '(no extension)'!r}; supported: {', '.join(SUPPORTED)}")


def save(model, path, **options):
    """Save a model to `path` (`.json`), or a mesh of it (`.ply`, `.obj`, `.stl`)."""
    suffix = Path(path).suffix.lower()
    if suffix == ".json":
        from . import native
        return native.save(model, path, **options)
    from .mesh import MESH_FORMATS, save_mesh
    if suffix in MESH_FORMATS:
        return save_mesh(model, path, **options)
    raise CSGError(f"{path}: cannot save {suffix or '(no extension)'!r}; use .json, {', '.join(MESH_FORMATS)}")
