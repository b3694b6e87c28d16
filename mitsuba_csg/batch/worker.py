"""Rendering one chunk of a job: the worker side of a batch, the same in-process and on Ray.

A `ChunkRenderer` keeps the scenes it loaded (a few, most recently used first), so the chunks
of one job, and the frames of a turntable, reuse one loaded scene and its compiled kernels.
"""
from __future__ import annotations

import os
import time
from collections import OrderedDict

import numpy as np

from ..errors import CSGError

KEEP_SCENES = 2


class ChunkRenderer:
    def __init__(self, variant: str, threads: int | None = None):
        import drjit as dr
        import mitsuba as mi
        mi.set_variant(variant)
        import mitsuba_csg as csg
        csg.register_plugins()
        if threads:
            dr.set_thread_count(int(threads))
        self.mi, self.dr, self.csg = mi, dr, csg
        self._scenes: OrderedDict = OrderedDict()

    def pid(self) -> int:
        return os.getpid()

    def render(self, job: dict, index: int, spp: int, seed: int) -> dict:
        """Chunk `index` of `job` (`Job.to_dict()`): the film's raw sums (H, W, C) as float32,
        their channel names (W is the weight sum), and the seconds it took."""
        from .jobs import Job
        mi, dr = self.mi, self.dr
        job = Job.from_dict(job)
        t0 = time.perf_counter()
        scene, poses = self._scene(job)
        sensors = scene.sensors()
        if job.sensor >= len(sensors):
            raise CSGError(f"{job.input}: sensor {job.sensor} asked for, the scene has {len(sensors)}")
        sensor = sensors[job.sensor]
        self._pose(job, scene, sensor, poses)
        mi.render(scene, sensor=sensor, seed=seed, spp=spp)
        if scene.integrator().should_stop():
            # Mitsuba's render loop takes Ctrl-C itself ("winding down"): the chunk may lack
            # samples, so it is dropped, and the interrupt goes on to the batch.
            raise KeyboardInterrupt
        bitmap = sensor.film().bitmap(raw=True)
        raw = np.array(bitmap, dtype=np.float32)
        dr.sync_thread()
        names = [field.name for field in bitmap.struct_()]
        if raw.ndim == 2:
            raw = raw[..., None]
        return {"raw": raw, "names": names, "seconds": time.perf_counter() - t0, "spp": spp, "seed": seed,
                "index": index, "pid": os.getpid()}

    def _scene(self, job):
        key = job.scene_key()
        if key in self._scenes:
            self._scenes.move_to_end(key)
            return self._scenes[key]
        from ..scene_setup import load_scene
        width, height = job.size if job.size is not None else (0, 0)
        scene, _ = load_scene(self.mi, self.csg, job.input, width, height, job.spp, job.integrator, cuts=job.cut,
                              hide=job.hide, skip_unsupported=job.skip_unsupported, depth=job.depth,
                              world=job.world, size_given=job.size is not None)
        # Each sensor's pose and field of view as loaded: orbits turn the pose, and a camera that
        # one job sets does not stick to the next job's frames.
        poses = [self._sensor_pose(s) for s in scene.sensors()]
        while len(self._scenes) >= KEEP_SCENES:
            self._scenes.popitem(last=False)
        self._scenes[key] = (scene, poses)
        return scene, poses

    def _sensor_pose(self, sensor):
        params = self.mi.traverse(sensor)
        to_world = np.array(params["to_world"].matrix, np.float64)[..., 0] if "to_world" in params else None
        fov = float(params["x_fov"][0]) if "x_fov" in params else None
        return to_world, fov

    def _pose(self, job, scene, sensor, poses):
        from ..scene_setup import look_at, orbit, pose_sensor
        base, fov = poses[job.sensor]
        axis = None
        if job.camera is not None:
            axis = job.camera["up"]
            base = look_at(self.mi, job.camera["origin"], job.camera["target"], job.camera["up"])
            if job.camera["fov"] is not None:
                fov = job.camera["fov"]
        if base is None:
            if job.orbit or job.camera is not None:
                raise CSGError(f"{job.input}: the scene's sensor cannot be moved (it has no to_world)")
            return
        to_world = base
        if job.orbit:
            if job.orbit_centre is not None:
                centre = np.array(job.orbit_centre)
            else:
                box = scene.bbox()
                centre = 0.5 * (np.array(box.min, np.float64) + np.array(box.max, np.float64)).ravel()
            to_world = orbit(base, centre, job.orbit, axis)
        pose_sensor(self.mi, scene, sensor, to_world, fov)
