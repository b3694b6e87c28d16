"""Mitsuba scenes for what a user names on the command line or in a batch job: a scene file
(.xml), a model file, a built-in scene, or nothing (the demo Cheese). Models get a camera that
frames them, a floor, a sky and a sun; cameras can be re-posed after loading (`pose_sensor`).

Used by `mitsuba-csg render` and by the batch renderer's workers, so that both load a job the
same way.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import CSGError
from .formats import MODEL_SUFFIXES
from .scenes import NAMED as BUILTIN_SCENES


def demo_scene_dict(mi, csg, width, height, spp, integrator):
    """The built-in demo: the paper's Cheese (a cube minus 500 spheres) on a floor."""
    from .scenes import cheese
    return model_scene_dict(mi, csg, cheese(500, seed=0), width, height, spp, integrator,
                            colour=[0.85, 0.65, 0.25])


def model_scene_dict(mi, csg, model, width, height, spp, integrator, colour=None):
    """A model on a floor, framed by a camera, lit by a sky and a sun; each material in its colour
    (`viewing.material_colour`), or all in `colour`."""
    from . import viewing
    default = viewing.bsdf((*colour, 1.0) if colour is not None else viewing.material_colour(None))
    return scene_dict(mi, csg, [(model, {} if colour is not None else viewing.material_bsdfs(model), default)],
                      width, height, spp, integrator)


def scene_dict(mi, csg, parts, width, height, spp, integrator):
    """Mitsuba's dict for csg shapes `parts` [(model, {material: bsdf}, default bsdf)] on a floor,
    framed by a camera whose clip planes follow the scene's size (a 40 m detector in mm too)."""
    from .camera import framing
    boxes = np.array([part[0].bounds() for part in parts])
    lower, upper = boxes[:, 0].min(axis=0), boxes[:, 1].max(axis=0)
    origin, target = framing(lower, upper, 40.0, width / height)
    size = float((upper - lower).max())
    distance = float(np.linalg.norm(origin - target))
    shapes = {}
    for k, (model, bsdfs, default) in enumerate(parts):
        shape = {"type": "csg", "model": csg.model_ref(model), "bsdf": default}
        shape.update({name: value for name, value in bsdfs.items()})
        shapes[f"model{k}" if k else "model"] = shape
    return {
        "type": "scene",
        "integrator": {"type": integrator, "max_depth": 6} if integrator != "csg_aov" else {"type": "csg_aov"},
        "sensor": {"type": "perspective", "fov": 40.0, "fov_axis": "x",
                   "near_clip": 1e-4 * distance, "far_clip": distance + 10.0 * size,
                   "to_world": mi.ScalarTransform4f().look_at(origin.tolist(), target.tolist(), [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": width, "height": height},
                   "sampler": {"type": "independent", "sample_count": spp}},
        **shapes,
        "floor": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([float(target[0]), float(target[1]), float(lower[2])])
                  .scale(4.0 * size),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.55]}}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.35, 0.4, 0.5]}},
        "sun": {"type": "directional", "direction": [-1.0, 1.2, -2.0], "irradiance": {"type": "rgb", "value": [3.0, 2.8, 2.5]}},
    }


def load_options(path: str, skip_unsupported=False, depth=None, world=None, hide=None) -> dict:
    """Reader options for a model file: skip_unsupported (GDML, OpenSCAD), depth and world (GDML);
    `hide` is checked here and applied by `viewing.model_parts`."""
    suffix = Path(path).suffix.lower()
    options = {}
    if skip_unsupported:
        if suffix not in (".gdml", ".csg", ".scad"):
            raise CSGError(f"{path}: --skip-unsupported applies to GDML and OpenSCAD files")
        options["on_unsupported"] = "skip"
    gdml_only = {"depth": depth, "show_world": world or None, "hide": hide}
    if suffix != ".gdml" and any(v is not None for v in gdml_only.values()):
        raise CSGError(f"{path}: --depth, --world and --hide apply to GDML detectors")
    if suffix == ".gdml":
        options.update({k: v for k, v in gdml_only.items() if k != "hide" and v is not None})
    return options


def mitsuba_reason(message: str) -> str:
    """Mitsuba's error without the Python traceback it embeds for a failing Python plugin: its
    place (file, line, plugin) and the exception's own last line, which says why."""
    lines = [line for line in message.splitlines() if line.strip()]
    if len(lines) > 1 and "Traceback (most recent call last)" in lines[0]:
        head = lines[0].split("Traceback (most recent call last)")[0].rstrip(": ")
        return f"{head}: {lines[-1].strip()}"
    return lines[0] if lines else message


def names(text) -> list[str]:
    """`a, b,c` -> ['a', 'b', 'c']."""
    return [n.strip() for n in (text or "").split(",") if n.strip()]


def load_scene(mi, csg, source: str | None, width: int, height: int, spp: int, integrator: str,
               cuts=(), hide=None, skip_unsupported=False, depth=None, world=None, size_given=True):
    """(scene, description) for `source`: None (the demo Cheese), a Mitsuba scene (.xml), a model
    file, or a built-in scene name. An .xml scene gets only the parameters it names ($spp,
    $width, $height); with `size_given` a scene whose film size is fixed is refused rather than
    rendered at another size than asked. `cuts` are `viewing.parse_cut` strings."""
    from . import viewing
    if source is None:
        return mi.load_dict(demo_scene_dict(mi, csg, width, height, spp, integrator)), "the built-in Cheese (500 holes)"
    if source.lower().endswith(".xml"):
        if not Path(source).exists():
            raise CSGError(f"{source}: no such file")
        text = Path(source).read_text(errors="replace")
        params = {k: v for k, v in (("spp", spp), ("width", width), ("height", height)) if f"${k}" in text}
        if size_given and not {"width", "height"} <= set(params):
            raise CSGError(f"{source}: the scene's film has a fixed size (no $width and $height to set); "
                           "leave the size out to render at the scene's own")
        try:
            scene = mi.load_file(source, **params)
        except Exception as e:                               # Mitsuba's parser errors
            raise CSGError(f"{source}: {mitsuba_reason(str(e))}") from e
        return scene, source
    if source.lower().endswith(MODEL_SUFFIXES):
        if not Path(source).exists():
            raise CSGError(f"{source}: no such file")
        parts = viewing.model_parts(source, [viewing.parse_cut(c) for c in (cuts or [])], names(hide),
                                    **load_options(source, skip_unsupported, depth, world, hide))
        return mi.load_dict(scene_dict(mi, csg, parts, width, height, spp, integrator)), source
    if source in BUILTIN_SCENES:
        model = BUILTIN_SCENES[source]()
        return mi.load_dict(model_scene_dict(mi, csg, model, width, height, spp, integrator)), f"the built-in {source}"
    raise CSGError(f"{source}: expected a Mitsuba scene (.xml), a model ({', '.join(MODEL_SUFFIXES)}) "
                   f"or a built-in scene ({', '.join(BUILTIN_SCENES)})")


def vertical_axis(to_world: np.ndarray) -> np.ndarray:
    """The coordinate axis (signed) nearest a camera's up direction: a scene's vertical, +z or
    +y in most scenes, even when the camera looks down on it."""
    up = np.asarray(to_world, float)[:3, 1]
    axis = np.zeros(3)
    k = int(np.argmax(np.abs(up)))
    axis[k] = np.sign(up[k]) or 1.0
    return axis


def orbit(to_world: np.ndarray, centre, degrees: float, axis=None) -> np.ndarray:
    """A camera's 4x4 `to_world` turned by `degrees` about `axis` (default: `vertical_axis`)
    through `centre`: a turntable, the scene stays put and the camera circles it."""
    to_world = np.asarray(to_world, float)
    axis = vertical_axis(to_world) if axis is None else np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.radians(degrees)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + np.sin(a) * k + (1 - np.cos(a)) * (k @ k)
    turn = np.eye(4)
    turn[:3, :3] = rotation
    turn[:3, 3] = np.asarray(centre, float) - rotation @ np.asarray(centre, float)
    return turn @ to_world


def look_at(mi, origin, target, up) -> np.ndarray:
    """Mitsuba's look-at camera-to-world matrix as a 4x4 array, with the degenerate poses refused."""
    origin, target, up = (np.asarray(v, float) for v in (origin, target, up))
    forward = target - origin
    if not np.all(np.isfinite([origin, target, up])):
        raise CSGError("camera: origin, target and up must be finite")
    if np.linalg.norm(forward) == 0:
        raise CSGError("camera: origin and target are the same point")
    if np.linalg.norm(np.cross(up, forward)) <= 1e-9 * np.linalg.norm(up) * np.linalg.norm(forward):
        raise CSGError("camera: up is parallel to the viewing direction (or zero)")
    return np.array(mi.ScalarTransform4f().look_at(origin.tolist(), target.tolist(), up.tolist()).matrix, float)


def pose_sensor(mi, scene, sensor, to_world: np.ndarray | None, fov: float | None = None):
    """Move `sensor` to the 4x4 `to_world` (and set its horizontal field of view), through
    `mi.traverse` as a user's script would. None keeps the pose."""
    params = mi.traverse(sensor)
    if to_world is not None:
        params["to_world"] = mi.Transform4f(np.asarray(to_world, np.float64).tolist())
    if fov is not None:
        if "x_fov" not in params:
            raise CSGError(f"camera: the scene's {type(sensor).__name__} has no field of view to set")
        params["x_fov"] = float(fov)
    params.update()
