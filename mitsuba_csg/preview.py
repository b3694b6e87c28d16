"""A quick shaded image of a model from `trace` alone (no Mitsuba scene): the demo's renderer."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .camera import framing, look_at_rays
from .tracing import Hits, trace


def shade(model, width: int = 640, height: int = 360, fov_degrees: float = 40.0) -> tuple[np.ndarray, Hits]:
    """Linear RGB image (height, width, 3): two lights on a grey-blue solid over a dark gradient."""
    lower, upper = model.bounds()
    origin, target = framing(lower, upper, fov_degrees, width / height)
    o, d = look_at_rays(origin, target, fov_degrees=fov_degrees, width=width, height=height)
    hits = trace(model, o, d)
    n = hits.normal.astype(np.float64)
    key = np.array([0.4, -0.5, 0.8]) / np.linalg.norm([0.4, -0.5, 0.8])
    fill = np.array([-0.7, -0.3, 0.2]) / np.linalg.norm([-0.7, -0.3, 0.2])
    albedo = np.array([0.80, 0.62, 0.25])
    light = 0.9 * np.clip(n @ key, 0, None)[:, None] + 0.25 * np.clip(n @ fill, 0, None)[:, None] + 0.05
    rgb = albedo * light
    sky = np.linspace(0.02, 0.10, height)[::-1].repeat(width)[:, None] * np.array([0.6, 0.7, 1.0])
    hit = np.isfinite(hits.t) & (hits.prim >= 0)
    image = np.where(hit[:, None], rgb, sky).reshape(height, width, 3).astype(np.float32)
    return image, hits


def save(image: np.ndarray, path) -> list[Path]:
    """Write the image as OpenEXR (through mi.Bitmap) and an sRGB PNG beside it."""
    import mitsuba as mi
    path = Path(path)
    if path.suffix.lower() != ".exr":
        path = path.with_suffix(".exr")
    path.parent.mkdir(parents=True, exist_ok=True)
    bitmap = mi.Bitmap(image)
    bitmap.write(str(path))
    png = path.with_suffix(".png")
    bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.UInt8, srgb_gamma=True).write(str(png))
    return [path, png]
