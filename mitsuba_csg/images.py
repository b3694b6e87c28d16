"""Writing rendered images: multi-layer OpenEXR (colour and geometric buffers), PNG previews.

Channel names follow the EXR layer convention: colour is R, G, B (and A), a buffer with
several components is `layer.x`, `layer.y`, `layer.z` (`normal.x` ...), a scalar buffer is
its name (`depth`, `prim`). Viewers such as `exrheader` or Blender list the layers by name.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenEXR

# The command line's `--aov NAME,...` choices: name -> csg_aov type.
AOVS = {"depth": "depth", "normal": "sh_normal", "position": "position", "prim": "prim_index",
        "shape": "shape_index"}
DEFAULT_AOVS = ("depth", "normal", "prim")


def channel_names(image_channels: int, aov_names: list[str]) -> list[str]:
    """R, G, B[, A] for the colour channels, then the integrator's AOV names (`nn.x` style)."""
    colour = image_channels - len(aov_names)
    if not 0 < colour <= 4:
        raise ValueError(f"an image of {image_channels} channels cannot hold {len(aov_names)} AOVs and colour")
    base = ["R", "G", "B", "A"][:colour] if colour >= 3 else ["Y", "A"][:colour]
    return base + list(aov_names)


def write_exr(path, image: np.ndarray, names: list[str]) -> Path:
    """Write an (H, W, C) float image with one named channel per C (ZIP compressed, float32)."""
    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = image[..., None]
    if image.shape[-1] != len(names):
        raise ValueError(f"{image.shape[-1]} channels but {len(names)} names")
    channels = {name: np.ascontiguousarray(image[..., k]) for k, name in enumerate(names)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    path = Path(path)

    def write(partial: Path):
        with OpenEXR.File(header, channels) as f:
            f.write(str(partial))
        # A full disk can leave a short file without an error: read it back before trusting it.
        try:
            with OpenEXR.File(str(partial)) as back:     # the reader groups R, G, B as "RGB"
                count = sum(c.pixels.shape[2] if c.pixels.ndim == 3 else 1 for c in back.channels().values())
                complete = count == len(names)
        except Exception:
            complete = False
        if not complete:
            raise OSError(f"{path}: the image was not written completely (is the disk full?)")
    return _written_whole(path, write)


def _written_whole(path: Path, write) -> Path:
    """Write through a partial file beside `path`, renamed over it only once complete, so a
    failed write never leaves a truncated image under the real name."""
    partial = path.with_name(f".{path.name}.partial{path.suffix}")
    try:
        write(partial)
        if not partial.is_file() or partial.stat().st_size == 0:
            raise OSError(f"{path}: nothing was written (is the disk full?)")
        partial.replace(path)
    finally:
        partial.unlink(missing_ok=True)
    return path


def write_png(path, rgb: np.ndarray) -> Path:
    """A tonemapped sRGB preview of linear RGB (Mitsuba's own conversion)."""
    import mitsuba as mi
    pixels = np.ascontiguousarray(np.asarray(rgb, dtype=np.float32))
    return _written_whole(Path(path), lambda partial: mi.util.write_bitmap(str(partial), pixels, write_async=False))
