"""The Cheese statistics of the benchmarks against analytic answers, and the constant-porosity
family against Cheese-500's solid fraction."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from mitsuba_csg import scenes

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import cheese_statistics as stats  # noqa: E402


def test_one_central_hole():
    r = 0.6
    centres, radii = np.zeros((1, 3)), np.array([r])
    expected = 1.0 - 4.0 / 3.0 * np.pi * r**3 / stats.SIZE**3
    assert abs(scenes.solid_fraction(centres, radii) - expected) < 0.005
    # Rays along z: through the hole (x < r), past it (x > r), and one that misses the cube.
    o = np.array([[0.0, 0.0, -5.0], [0.3, 0.0, -5.0], [0.8, 0.0, -5.0], [3.0, 0.0, -5.0]])
    d = np.tile([0.0, 0.0, 2.0], (4, 1))                     # not unit: t is in units of d
    t_hit = np.array([np.inf, np.inf, 2.0, np.inf])           # entry face at z = -1 is t = 2
    assert stats.holes_crossed(centres, radii, o, d, t_hit) == 2 / 3
    # A hit in front of the hole: nothing crossed before it.
    assert stats.holes_crossed(centres, radii, o[:1], d[:1], np.array([2.0])) == 0.0


def test_constant_porosity_keeps_cheese_500s_solid_fraction():
    """Checked on points the calibration never saw (brute force, another seed)."""
    def solid(centres, radii, n=10_000):
        p = np.random.default_rng(99).uniform(-1, 1, (n, 3))
        inside = np.zeros(n, bool)
        for k in range(0, len(centres), 256):
            d2 = ((p[:, None, :] - centres[None, k:k + 256]) ** 2).sum(-1)
            inside |= (d2 < radii[None, k:k + 256] ** 2).any(1)
        return 1.0 - inside.mean()
    base = solid(*scenes.cheese_holes(500))
    assert 0.3 < base < 0.45
    fixed = solid(*scenes.cheese_holes(8000))
    kept = solid(*scenes.cheese_holes(8000, radius_scale=scenes.constant_porosity_scale(8000)))
    assert abs(kept - base) < 0.015 and fixed < base - 0.2
    assert stats.holes_of("cheese-cp-8000")[1].max() < stats.holes_of("cheese-8000")[1].max()
