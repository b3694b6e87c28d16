"""Batch rendering (`mitsuba-csg batch`, `mitsuba_csg.batch`): job files, chunk seeds and
merging, resuming, failures, and a local Ray cluster of 2 workers (killed worker included).

References: Mitsuba's own `mi.render` for a one-chunk job (its film develops the image), a
many-sample render for merged chunks (within noise), the in-process batch for the Ray one
(bitwise: the same chunks with the same seeds on the same number of Dr.Jit threads).
"""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import mitsuba as mi
import numpy as np
import OpenEXR
import pytest

import mitsuba_csg as csg
from mitsuba_csg import batch
from mitsuba_csg.batch import runner
from mitsuba_csg.errors import CSGError

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "scenes" / "models" / "demo_cheese_small.json"
SCENE = ROOT / "scenes" / "cheese.xml"


def read_rgb(path) -> np.ndarray:
    with OpenEXR.File(str(path)) as f:
        return np.array(f.channels()["RGB"].pixels)


def small_jobs(folder: Path, missing=False) -> list[dict]:
    jobs = [
        {"input": str(MODEL), "output": str(folder / "model.exr"), "size": "40x30", "spp": 6, "chunk_spp": 2},
        {"input": "cheese-500", "output": str(folder / "orbit.exr"), "size": [36, 24], "spp": 4, "chunk_spp": 2,
         "orbit": 120, "seed": 7},
        {"input": str(SCENE), "output": str(folder / "scene.exr"), "size": "32x18", "spp": 4, "chunk_spp": 2},
    ]
    if missing:
        jobs.insert(1, {"input": str(folder / "missing.json"), "output": str(folder / "missing.exr")})
    return jobs


# ---- jobs, seeds, merging (in-process) ----

def test_a_one_chunk_job_is_mitsubas_own_render(tmp_path):
    """The batch's develop (raw sums / weights) equals Mitsuba's film for the same seed."""
    [job] = batch.parse_jobs([{"input": str(MODEL), "output": "one.exr", "size": "24x16", "spp": 3,
                               "chunk_spp": 3, "png": False}], tmp_path)
    summary = batch.run([job], use_ray=False, progress=False)
    assert summary.results[0].status == "done"
    from mitsuba_csg.scene_setup import load_scene
    scene, _ = load_scene(mi, csg, str(MODEL), 24, 16, 3, "csg_path")
    reference = np.array(mi.render(scene, seed=job.chunks()[0].seed, spp=3))
    # Several Dr.Jit threads splat into the film in varying order: equal to a few ulps.
    np.testing.assert_allclose(read_rgb(tmp_path / "one.exr"), reference, rtol=1e-6, atol=1e-7)
    assert not (tmp_path / "one.png").exists()


def test_merged_chunks_estimate_the_image_as_one_render_does(tmp_path):
    """8 chunks of 2 spp against one 16-spp render, both against a 256-spp reference: the
    merged image's error is that of a 16-spp render (chunks are independent, weights exact)."""
    from mitsuba_csg.scene_setup import load_scene
    scene, _ = load_scene(mi, csg, str(MODEL), 32, 24, 16, "csg_path")
    reference = np.array(mi.render(scene, seed=1000, spp=256))
    single = np.array(mi.render(scene, seed=2000, spp=16))
    batch.render(str(MODEL), output=str(tmp_path / "m.exr"), size="32x24", spp=16, chunk_spp=2, use_ray=False,
                 progress=False)
    merged = read_rgb(tmp_path / "m.exr")
    err_single = np.mean((single - reference) ** 2)
    err_merged = np.mean((merged - reference) ** 2)
    assert 0.6 < err_merged / err_single < 1.6
    assert abs(merged.mean() / reference.mean() - 1) < 0.02


def test_chunk_seeds_are_fixed_and_distinct():
    [job] = batch.parse_jobs([{"output": "x.exr", "spp": 20, "chunk_spp": 8, "seed": 3}], Path("."))
    chunks = job.chunks()
    assert [c.spp for c in chunks] == [8, 8, 4] and job.chunk_count == 3
    assert len({c.seed for c in chunks}) == 3
    assert [c.seed for c in chunks] == [c.seed for c in job.chunks()]            # not random per run
    [other] = batch.parse_jobs([{"output": "x.exr", "spp": 20, "chunk_spp": 8, "seed": 4}], Path("."))
    assert not {c.seed for c in chunks} & {c.seed for c in other.chunks()}


def test_turntable_frames_circle_the_vertical_axis():
    from mitsuba_csg.scene_setup import look_at, orbit
    to_world = look_at(mi, [4.0, -6.0, 3.0], [0.0, 0.0, 0.5], [0, 0, 1])
    quarter = orbit(to_world, [0.0, 0.0, 0.5], 90.0)
    np.testing.assert_allclose(quarter[:3, 3], [6.0, 4.0, 3.0], atol=1e-12)        # turned about +z
    np.testing.assert_allclose(orbit(to_world, [0, 0, 0.5], 360.0), to_world, atol=1e-12)
    y_up = look_at(mi, [0.0, 3.0, 5.0], [0.0, 0.0, 0.0], [0, 1, 0])
    np.testing.assert_allclose(orbit(y_up, [0, 0, 0], 180.0)[:3, 3], [0.0, 3.0, -5.0], atol=1e-12)   # about +y
    frames = batch.parse_jobs([{"input": "cheese-500", "output": "t.exr"}], Path("."), frames=3)
    assert [f.output.name for f in frames] == ["t_0000.exr", "t_0001.exr", "t_0002.exr"]
    assert [f.orbit for f in frames] == [0.0, 120.0, 240.0]


def test_a_turntable_renders_frames_of_one_loaded_scene(tmp_path):
    summary = batch.render("cheese-500", frames=2, output=str(tmp_path / "t.exr"), size="32x24", spp=2,
                           use_ray=False, progress=False)
    assert [r.status for r in summary.results] == ["done", "done"]
    a, b = read_rgb(tmp_path / "t_0000.exr"), read_rgb(tmp_path / "t_0001.exr")
    assert np.abs(a - b).mean() > 0.02                 # the camera moved
    # Frame 0 of a turntable is the job without an orbit.
    batch.render("cheese-500", output=str(tmp_path / "still.exr"), size="32x24", spp=2, use_ray=False,
                 progress=False)
    np.testing.assert_allclose(a, read_rgb(tmp_path / "still.exr"), rtol=1e-6, atol=1e-7)


def test_a_camera_pose_in_the_job(tmp_path):
    """A job's camera replaces the scene's, seen through csg_aov's depth: the distance from the
    camera to a unit sphere's surface at the image centre."""
    model = tmp_path / "ball.json"
    model.write_text('{"format": "mitsuba-csg", "version": 1, "root": {"type": "sphere", "radius": 1.0}}')
    batch.render(str(model), output=str(tmp_path / "d.exr"), size="9x9", spp=1, integrator="csg_aov",
                 camera={"origin": [0, -5, 0], "target": [0, 0, 0], "up": [0, 0, 1], "fov": 20}, use_ray=False,
                 progress=False)
    with OpenEXR.File(str(tmp_path / "d.exr"), separate_channels=True) as f:
        depth = np.array(f.channels()["dd.y"].pixels)
    assert depth[4, 4] == pytest.approx(4.0, rel=5e-3)     # the framing camera would see it at 4.17


@pytest.mark.parametrize("jobs, message", [
    ({"jobs": [{"output": "a.exr", "sppp": 3}]}, "unknown field(s) ['sppp']"),
    ({"jobs": [{"output": "a.png"}]}, "OpenEXR"),
    ({"jobs": [{"output": "a.exr", "size": "10by5"}]}, "jobs[0].size"),
    ({"jobs": [{"output": "a.exr", "spp": 0}]}, "jobs[0].spp: expected an integer >= 1"),
    ({"jobs": [{"output": "a.exr", "spp": 2.5}]}, "jobs[0].spp"),
    ({"jobs": [{"output": "a.exr"}, {"output": "./a.exr"}]}, "write the same output"),
    ({"jobs": [{"input": "x.xml", "output": "a.exr", "integrator": "csg_aov"}]}, "names its own integrator"),
    ({"jobs": [{"input": "cheese-500", "output": "a.exr", "cut": ["x>0"]}]}, "apply to model files"),
    ({"jobs": [{"output": "a.exr", "camera": {"origin": [0, 0, 1]}}]}, "jobs[0].camera"),
    ({"jobs": [{"output": "a.exr", "camera": {"origin": [0, 0, 1], "target": [0, 0, "x"]}}]}, "camera.target"),
    ({"jobs": []}, "non-empty list"),
    ({"job": []}, 'expected {"jobs"'),
])
def test_job_file_mistakes_name_the_place(tmp_path, jobs, message):
    path = tmp_path / "jobs.json"
    path.write_text(json.dumps(jobs))
    with pytest.raises(CSGError, match=None) as e:
        batch.load_jobs(path)
    assert message in str(e.value) and str(path) in str(e.value)


def test_a_job_file_is_told_from_a_native_model(tmp_path):
    (tmp_path / "jobs.json").write_text('{"jobs": [{"output": "a.exr"}]}')
    assert batch.is_job_file(tmp_path / "jobs.json")
    assert not batch.is_job_file(MODEL)
    with pytest.raises(CSGError, match="not valid JSON"):
        (tmp_path / "bad.json").write_text('{"jobs": [')
        batch.load_jobs(tmp_path / "bad.json")


def test_an_unusable_camera_is_an_error_of_its_job(tmp_path):
    summary = batch.render([
        {"input": "cheese-500", "output": str(tmp_path / "bad.exr"), "size": "8x8", "spp": 1,
         "camera": {"origin": [0, 0, 5], "target": [0, 0, 0], "up": [0, 0, 1]}},
        {"input": "cheese-500", "output": str(tmp_path / "good.exr"), "size": "8x8", "spp": 1}],
        use_ray=False, progress=False)
    bad, good = summary.results
    assert bad.status == "failed" and "up is parallel" in bad.error
    assert good.status == "done"


def test_a_changed_job_does_not_reuse_old_chunks(tmp_path):
    jobs = [{"input": "cheese-500", "output": str(tmp_path / "a.exr"), "size": "16x12", "spp": 4, "chunk_spp": 2}]
    first = batch.render(jobs, use_ray=False, progress=False)
    assert first.results[0].chunks_rendered == 2
    again = batch.render(jobs, use_ray=False, progress=False)
    assert again.results[0].status == "done earlier" and again.results[0].chunks_rendered == 0
    jobs[0]["seed"] = 1
    changed = batch.render(jobs, use_ray=False, progress=False)
    assert changed.results[0].status == "done" and changed.results[0].chunks_rendered == 2


def test_without_ray_the_batch_runs_in_process(tmp_path, monkeypatch):
    monkeypatch.setattr(runner, "ray_available", lambda: False)
    summary = batch.render("cheese-500", output=str(tmp_path / "a.exr"), size="8x8", spp=1, progress=False)
    assert summary.backend == "in-process" and summary.results[0].status == "done"
    with pytest.raises(CSGError, match="Ray is not installed"):
        batch.render("cheese-500", output=str(tmp_path / "b.exr"), size="8x8", spp=1, use_ray=True)


def test_cli_batch_reports_each_job_and_fails_on_a_failed_one(tmp_path, capsys):
    from mitsuba_csg.cli import main
    jobs = tmp_path / "jobs.json"
    jobs.write_text(json.dumps({"defaults": {"size": "12x8", "spp": 2},
                                "jobs": [{"input": "cheese-500", "output": "a.exr"},
                                         {"input": "nowhere.json", "output": "b.exr"}]}))
    assert main(["batch", str(jobs), "--local"]) == 1
    out, err = capsys.readouterr()
    assert "done" in out and "nowhere.json: no such file" in out and "1 of 2 jobs failed" in err
    assert (tmp_path / "a.exr").exists() and (tmp_path / "a.png").exists()
    assert main(["batch", str(jobs), "--local", "--spp", "4"]) == 2
    assert "sets spp itself" in capsys.readouterr().err


# ---- interrupted and resumed (the driver is killed with Ctrl-C) ----

@pytest.mark.slow
def test_an_interrupted_batch_resumes_from_its_saved_chunks(tmp_path):
    """Ctrl-C after the first saved chunk, rerun: the saved chunks are reused, and the images equal
    those of an uninterrupted run (the same chunks, the same seeds)."""
    def job_file(folder):
        folder.mkdir()
        # Chunks long enough (about 0.1 s each) that the Ctrl-C lands while job a is running.
        (folder / "jobs.json").write_text(json.dumps({"defaults": {"size": "320x240", "chunk_spp": 1},
                                                      "jobs": [{"input": "cheese-500", "output": "a.exr", "spp": 48},
                                                               {"input": str(MODEL), "output": "b.exr", "spp": 4}]}))
        return folder / "jobs.json"
    command = [sys.executable, "-m", "mitsuba_csg", "batch", "--local", "--threads", "1"]
    whole = job_file(tmp_path / "whole")
    subprocess.run([*command, str(whole)], check=True, capture_output=True, cwd=ROOT)
    cut = job_file(tmp_path / "cut")
    # As from a terminal: a test run started in the background inherits SIGINT ignored, and
    # the signal mask of whichever thread of this process forks (a library's worker thread may
    # block SIGINT) goes over to the child too.
    def as_from_a_terminal():
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    process = subprocess.Popen([*command, str(cut)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               cwd=ROOT, preexec_fn=as_from_a_terminal)
    chunks = cut.parent / ".a.exr.chunks"
    deadline = time.time() + 120
    while not list(chunks.glob("chunk-*.npz")) and time.time() < deadline and process.poll() is None:
        time.sleep(0.01)
    assert process.poll() is None, "the batch ended before a chunk of job a was seen"
    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=120)
    assert process.returncode == 130, err
    assert "rerun the same command to resume" in err
    saved = len(list(chunks.glob("chunk-*.npz")))
    assert saved >= 1 and not (cut.parent / "b.exr").exists()
    rerun = subprocess.run([*command, str(cut)], capture_output=True, text=True, cwd=ROOT)
    assert rerun.returncode == 0, rerun.stderr
    assert f"{48 - saved} rendered, {saved} reused" in rerun.stdout
    for name in ("a.exr", "b.exr"):
        np.testing.assert_array_equal(read_rgb(cut.parent / name), read_rgb(whole.parent / name))
    assert not list(chunks.glob("chunk-*.npz"))         # removed once the image is written


# ---- a local Ray cluster of 2 workers ----

def _worker_pids() -> list[int]:
    """Processes of the batch's Ray actors (Ray names them after the actor class)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                cmdline = (entry / "cmdline").read_bytes().decode(errors="replace")
            except OSError:
                continue
            if "ray::ChunkRenderer" in cmdline:
                pids.append(int(entry.name))
    return pids


@pytest.fixture(scope="module")
def in_process_reference(tmp_path_factory):
    """The small jobs rendered in this process on one Dr.Jit thread, as each Ray worker renders."""
    folder = tmp_path_factory.mktemp("reference")
    summary = batch.render(small_jobs(folder), use_ray=False, threads=1, progress=False)
    assert all(r.status == "done" for r in summary.results)
    return folder


@pytest.mark.slow
@pytest.mark.skipif(not runner.ray_available(), reason="Ray is not installed (pip install 'mitsuba-csg[distributed]')")
def test_ray_workers_render_what_one_process_renders(tmp_path, in_process_reference):
    """3 jobs (a model, a built-in scene turned by an orbit, an .xml scene) and one whose file is
    missing, on 2 Ray workers: the missing one fails alone, the others equal the in-process images
    bit for bit."""
    summary = batch.render(small_jobs(tmp_path, missing=True), workers=2, threads=1, progress=False)
    assert summary.backend.startswith("ray") and summary.workers == 2
    status = {r.job.name: (r.status, r.error) for r in summary.results}
    assert status["missing"][0] == "failed" and "missing.json: no such file" in status["missing"][1]
    assert all(status[name][0] == "done" for name in ("model", "orbit", "scene"))
    assert len(summary.worker_pids) == 2 and os.getpid() not in summary.worker_pids
    for name in ("model", "orbit", "scene"):
        np.testing.assert_array_equal(read_rgb(tmp_path / f"{name}.exr"), read_rgb(in_process_reference / f"{name}.exr"))


@pytest.mark.slow
@pytest.mark.skipif(not runner.ray_available(), reason="Ray is not installed (pip install 'mitsuba-csg[distributed]')")
def test_a_killed_worker_is_replaced_and_its_chunk_rendered_again(tmp_path, in_process_reference):
    """SIGKILL one of the 2 worker processes once the first chunk is saved: Ray restarts it and
    retries its chunks; every job completes, with the same images."""
    jobs = small_jobs(tmp_path)
    killed = []

    def kill_one():
        deadline = time.time() + 180
        while time.time() < deadline and not killed:
            if list(tmp_path.glob(".*.chunks/chunk-*.npz")):
                pids = _worker_pids()
                if pids:
                    os.kill(pids[0], signal.SIGKILL)
                    killed.append(pids[0])
            time.sleep(0.02)

    watcher = threading.Thread(target=kill_one, daemon=True)
    watcher.start()
    summary = batch.render(jobs, workers=2, threads=1, progress=False)
    watcher.join(timeout=5)
    assert killed, "no worker was found to kill"
    assert [r.status for r in summary.results] == ["done"] * 3, [r.error for r in summary.results]
    # The replacement is a new process; the killed one rendered no chunk after its death.
    assert len(summary.worker_pids) >= 2
    for name in ("model", "orbit", "scene"):
        np.testing.assert_array_equal(read_rgb(tmp_path / f"{name}.exr"), read_rgb(in_process_reference / f"{name}.exr"))
