"""Primary rays of a pinhole camera, as numpy arrays (for `trace`, demos and benchmarks), and
the pixel order that traces them fastest."""
from __future__ import annotations

import numpy as np


def look_at_rays(origin, target, up=(0.0, 0.0, 1.0), fov_degrees: float = 40.0,
                 width: int = 1280, height: int = 720) -> tuple[np.ndarray, np.ndarray]:
    """Origins and unit directions (width*height, 3), row-major from the top-left pixel centre."""
    origin, target, up = (np.asarray(v, dtype=np.float64) for v in (origin, target, up))
    forward = target - origin
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    true_up = np.cross(right, forward)
    half_w = np.tan(np.radians(fov_degrees) / 2.0)      # horizontal field of view
    half_h = half_w * height / width
    u = (np.arange(width) + 0.5) / width * 2.0 - 1.0
    v = 1.0 - (np.arange(height) + 0.5) / height * 2.0
    uu, vv = np.meshgrid(u * half_w, v * half_h)
    d = forward + uu.reshape(-1, 1) * right + vv.reshape(-1, 1) * true_up
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.broadcast_to(origin, d.shape).copy(), d


def tile_order(width: int, height: int, tile: int = 4) -> np.ndarray:
    """A permutation of the row-major pixels of a width x height image into tile x tile blocks.

    The kernel runs rays in SIMD packets of consecutive lanes (16 on AVX-512, a warp on a
    GPU), each packet as long as its slowest ray. Rays of a 4x4 block see more alike
    geometry than 16 pixels of a row, so a packet wastes fewer lanes: trace `rays[perm]`,
    then put results back with `image.reshape(-1)[perm] = results`.
    """
    if tile < 1:
        raise ValueError(f"tile: expected a positive size, got {tile}")
    y, x = np.divmod(np.arange(width * height), width)
    blocks_x = -(-width // tile)
    key = ((y // tile) * blocks_x + x // tile) * tile * tile + (y % tile) * tile + x % tile
    return np.argsort(key, kind="stable")


def framing(lower, upper, fov_degrees: float = 40.0, aspect: float = 16 / 9, direction=(1.0, -1.6, 0.9)):
    """A camera origin and target that frame the box [lower, upper] from `direction`.

    `fov_degrees` is horizontal; `aspect` = width / height decides the narrower angle.
    """
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    centre = 0.5 * (lower + upper)
    radius = 0.5 * np.linalg.norm(upper - lower)
    d = np.asarray(direction, float)
    d /= np.linalg.norm(d)
    half_w = np.radians(fov_degrees) / 2.0
    half = min(half_w, np.arctan(np.tan(half_w) / aspect))
    distance = radius / np.sin(half) * 1.02
    return centre + d * distance, centre
