"""Model files: one registry from file suffix to reader and writer.

    load(path, **options) -> Node          save(model, path, **options)

Each format declares the options its reader takes, so a misspelt or foreign option is
refused with the format's own list (`csg.load("m.json", on_unsupported="skip")` names
the options JSON takes). Readers share `reading.FormatError` and `reading.read_model_bytes`.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..errors import CSGError
from . import gdml, native_json, openscad
from .reading import FormatError


@dataclass(frozen=True)
class Format:
    name: str
    load: Callable | None
    load_options: tuple[str, ...] = ()
    save: Callable | None = None
    save_options: tuple[str, ...] = ()


def _load_mesh(path, **options):
    from .mesh_import import load as load_mesh
    return load_mesh(path, **options)


def _save_mesh(model, path, **options):
    from .mesh_export import save_mesh       # manifold3d is only needed for meshes
    return save_mesh(model, path, **options)


FORMATS = {
    ".json": Format("mitsuba-csg native JSON", native_json.load, (), native_json.save, ("materials",)),
    ".csg": Format("OpenSCAD .csg", openscad.load, ("on_unsupported", "facets")),
    ".scad": Format("OpenSCAD source (evaluated by OpenSCAD)", openscad.load_scad, ("on_unsupported", "facets")),
    ".gdml": Format("Geant4 GDML", gdml.load, ("solid", "depth", "show_world", "on_unsupported")),
    ".ply": Format("PLY mesh", _load_mesh, (), _save_mesh, ("segments",)),
    ".obj": Format("Wavefront OBJ mesh", _load_mesh, (), _save_mesh, ("segments",)),
    ".stl": Format("STL mesh", _load_mesh, (), _save_mesh, ("segments",)),
}
MODEL_SUFFIXES = tuple(s for s, f in FORMATS.items() if f.load is not None)
SAVE_SUFFIXES = tuple(s for s, f in FORMATS.items() if f.save is not None)


def _check_options(path, fmt: Format, given: dict, accepted: tuple[str, ...], verb: str) -> None:
    unknown = sorted(set(given) - set(accepted))
    if unknown:
        takes = f"takes {', '.join(accepted)}" if accepted else "takes no options"
        raise CSGError(f"{path}: {verb} {fmt.name} {takes}; unknown option(s): {', '.join(unknown)}")


def load(path, **options):
    """Load a model from `path`; the suffix picks the format (`.json`, `.csg`, `.gdml`, and
    the closed triangle meshes `.stl`, `.ply`, `.obj` as one `csg.Mesh` leaf).

    Options go to the format's reader: `on_unsupported="skip"` (OpenSCAD, GDML) and, for
    GDML, `solid="name"` (one solid in its own frame), `depth=k`, `show_world=True`.
    """
    suffix = Path(path).suffix.lower()
    fmt = FORMATS.get(suffix)
    if fmt is None or fmt.load is None:
        kind = f"{fmt.name} files cannot be loaded as models" if fmt else \
            f"unknown model format {suffix or '(no extension)'!r}"
        raise CSGError(f"{path}: {kind}; supported: {', '.join(MODEL_SUFFIXES)}")
    _check_options(path, fmt, options, fmt.load_options, "loading")
    return fmt.load(path, **options)


def save(model, path, **options):
    """Save a model to `path` (`.json`), or a mesh of it (`.ply`, `.obj`, `.stl`)."""
    suffix = Path(path).suffix.lower()
    fmt = FORMATS.get(suffix)
    if fmt is None or fmt.save is None:
        raise CSGError(f"{path}: cannot save {suffix or '(no extension)'!r}; use {', '.join(SAVE_SUFFIXES)}")
    _check_options(path, fmt, options, fmt.save_options, "saving")
    return fmt.save(model, path, **options)


__all__ = ["FORMATS", "Format", "FormatError", "MODEL_SUFFIXES", "SAVE_SUFFIXES", "load", "save"]
