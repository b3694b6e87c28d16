"""Every generator and benchmark script runs at a tiny size, so none of them can rot."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

import mitsuba_csg as csg
from mitsuba_csg import scenes as generators

pytestmark = pytest.mark.slow     # mesh references / whole benchmark scripts: the full tier only

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("make, prims", [
    (lambda: generators.cheese(10), 11),
    (lambda: generators.city(3), 30),
    (lambda: generators.satellites(3), 42),
    (lambda: generators.sphere_chain(5), 5),
])
def test_generators(make, prims):
    model = make()
    assert len(model.leaves()) == prims
    lo, hi = model.bounds()
    hits = csg.trace(model, [0.5 * (lo + hi) - [0, 0, 100]], [[0, 0, 1.0]])
    assert hits.unfinished == 0


@pytest.mark.parametrize("script, args", [
    ("trace_throughput.py", ["--scenes", "cheese-500", "--size", "32x18", "--repeats", "1", "--no-compile"]),
    ("optimizer_scaling.py", ["--sizes", "100", "--size", "32x18"]),
    ("mesh_route.py", ["--scenes", "cheese-500", "--size", "32x18", "--repeats", "1", "--segments", "8"]),
    ("accuracy.py", ["--models", "2", "--rays", "16"]),
    ("scaling.py", ["--quick"]),
    ("traversal_mechanisms.py", ["--scenes", "cheese-500", "--size", "32x18", "--repeats", "1"]),
    ("commit_ab.py", ["--base", "HEAD", "--scenes", "cheese-500", "--size", "32x18", "--repeats", "1", "--rounds", "1"]),
    ("mesh_leaves.py", ["--triangles", "2000", "--holes", "20", "--size", "32x18", "--repeats", "1"]),
    ("gradient_cost.py", ["--size", "16x12", "--spp", "2", "--repeats", "1"]),
    ("several_shapes.py", ["--counts", "2,3", "--holes", "5", "--size", "32x18", "--repeats", "1"]),
    ("incoherent_rays.py", ["--scenes", "cheese-500", "--rays", "500", "--repeats", "1", "--segments", "8"]),
    ("path_depths.py", ["--scenes", "cheese-500", "--depths", "1,2", "--size", "32x18", "--repeats", "1",
                        "--segments", "8"]),
    ("batch_scaling.py", ["--jobs", "2", "--size", "16x9", "--spp", "2", "--chunk-spp", "1", "--overhead-spp", "2"]),
])
def test_benchmark_scripts(script, args, tmp_path):
    env = {**__import__("os").environ, "MITSUBA_CSG_BENCH_RESULTS": str(tmp_path)}
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *args], capture_output=True, text=True,
                         cwd=ROOT / "benchmarks", env=env, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    written = list(tmp_path.glob("*.json"))
    assert len(written) == 1
    payload = json.loads(written[0].read_text())
    assert payload["rows"] and "machine" in payload
