"""Batch job files: what to render (a scene or model, a camera, samples, a seed, an output),
checked field by field, and each job's split into sample chunks with their seeds.

A job file is JSON: ``{"jobs": [{...}, ...], "defaults": {...}}`` (docs/batch.md lists the
fields). Relative paths are relative to the job file's folder. Chunk seeds depend only on the
job's seed and the chunk's index, so the same job renders the same image wherever and in
whatever order its chunks run.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
from pathlib import Path

import numpy as np

from ..errors import CSGError
from ..plugins.registry import integrator_names
from ..scenes import NAMED as BUILTIN_SCENES

DEFAULT_SPP = 16
DEFAULT_CHUNK_SPP = 8
DEFAULT_SIZE = (640, 360)


@dataclasses.dataclass(frozen=True)
class Chunk:
    index: int
    spp: int
    seed: int


@dataclasses.dataclass(frozen=True)
class Job:
    """One image to render. `input` is a path (resolved), a built-in scene name, or None (the
    demo Cheese); `size` None means an .xml scene's own film size."""
    name: str
    input: str | None
    output: Path
    spp: int = DEFAULT_SPP
    chunk_spp: int = DEFAULT_CHUNK_SPP
    seed: int = 0
    size: tuple[int, int] | None = None
    integrator: str = "csg_path"
    sensor: int = 0
    camera: dict | None = None         # {"origin", "target", "up", "fov"}
    orbit: float = 0.0                 # degrees about the camera's up axis through orbit_centre
    orbit_centre: tuple | None = None  # None: the centre of the scene's bounding box
    png: bool = True
    cut: tuple = ()
    hide: str | None = None
    skip_unsupported: bool = False
    depth: int | None = None
    world: bool | None = None

    @property
    def is_xml(self) -> bool:
        return self.input is not None and self.input.lower().endswith(".xml")

    @property
    def chunk_count(self) -> int:
        return -(-self.spp // self.chunk_spp)

    def chunks(self) -> list[Chunk]:
        """Full chunks of `chunk_spp` samples, then the remainder; seeds from (seed, index)."""
        counts = [self.chunk_spp] * (self.spp // self.chunk_spp)
        if self.spp % self.chunk_spp:
            counts.append(self.spp % self.chunk_spp)
        return [Chunk(k, n, chunk_seed(self.seed, k)) for k, n in enumerate(counts)]

    def scene_key(self) -> tuple:
        """What a loaded scene depends on: jobs that differ only in camera, samples or seed (a
        turntable's frames) share one loaded scene and its compiled kernels."""
        return (self.input, self.size, self.integrator, self.cut, self.hide, self.skip_unsupported, self.depth,
                self.world)

    def to_dict(self) -> dict:
        """Plain data for shipping to a worker (`from_dict` rebuilds it)."""
        d = dataclasses.asdict(self)
        d["output"] = str(self.output)
        return d

    @staticmethod
    def from_dict(d: dict) -> "Job":
        d = dict(d)
        d["output"] = Path(d["output"])
        for key in ("size", "cut", "orbit_centre"):
            if d.get(key) is not None:
                d[key] = tuple(d[key])
        return Job(**d)

    def fingerprint(self) -> str:
        """A hash of everything the image depends on (the input file's bytes included), so a
        rerun reuses saved chunks only of an unchanged job."""
        d = self.to_dict()
        d.pop("name"), d.pop("png")
        if self.input is not None and Path(self.input).is_file():
            d["input_sha1"] = _file_sha1(Path(self.input))
        return hashlib.sha1(json.dumps(d, sort_keys=True).encode()).hexdigest()


def chunk_seed(job_seed: int, index: int) -> int:
    """A 32-bit sampler seed for chunk `index` of a job: independent streams per chunk."""
    return int(np.random.SeedSequence([job_seed, index]).generate_state(1)[0])


def _file_sha1(path: Path) -> str:
    """The file's SHA-1, read once per (path, size, modification time): the frames of a
    turntable of one large file share it."""
    stat = path.stat()
    return _sha1_of(str(path.resolve()), stat.st_size, stat.st_mtime_ns)


@functools.lru_cache(maxsize=64)
def _sha1_of(path: str, size: int, mtime_ns: int) -> str:
    h = hashlib.sha1()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


# ---- Reading job files ----

_FIELDS = {f.name for f in dataclasses.fields(Job)} - {"name"}


def load_jobs(path, frames: int | None = None) -> list[Job]:
    """The jobs of a job file, checked; with `frames`, each job becomes a turntable (`turntable`)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise CSGError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise CSGError(f"{path}: cannot read it ({e})") from None
    except json.JSONDecodeError as e:
        raise CSGError(f"{path}: not valid JSON: {e.msg} at line {e.lineno}, column {e.colno}") from None
    return parse_jobs(data, path.parent, str(path), frames)


def is_job_file(path) -> bool:
    """A JSON file whose top level has "jobs" (a native model has "format" instead)."""
    path = Path(path)
    if path.suffix.lower() != ".json" or not path.is_file():
        return False
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 16).decode("utf-8", errors="replace")
    except OSError:
        return False
    return '"jobs"' in head and '"format"' not in head


def parse_jobs(data, base: Path, source: str = "<jobs>", frames: int | None = None) -> list[Job]:
    if isinstance(data, list):
        data = {"jobs": data}
    if not isinstance(data, dict) or "jobs" not in data:
        raise CSGError(f'{source}: expected {{"jobs": [...]}} (optionally with "defaults")')
    extra = set(data) - {"jobs", "defaults"}
    if extra:
        raise CSGError(f"{source}: unknown top-level key(s) {sorted(extra)}; expected jobs, defaults")
    defaults = data.get("defaults", {})
    if not isinstance(defaults, dict):
        raise CSGError(f"{source}: defaults: expected an object")
    entries = data["jobs"]
    if not isinstance(entries, list) or not entries:
        raise CSGError(f"{source}: jobs: expected a non-empty list")
    jobs = []
    for k, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise CSGError(f"{source}: jobs[{k}]: expected an object")
        jobs.append(job_from_fields({**defaults, **entry}, base, f"{source}: jobs[{k}]"))
    if frames is not None:
        jobs = [frame for job in jobs for frame in turntable(job, frames)]
    _check_distinct_outputs(jobs, source)
    return jobs


def job_from_fields(fields: dict, base: Path, where: str) -> Job:
    """A Job from a job file's object (or the command line's options), every field checked."""
    unknown = set(fields) - _FIELDS
    if unknown:
        raise CSGError(f"{where}: unknown field(s) {sorted(unknown)}; known: {', '.join(sorted(_FIELDS))}")

    def fail(key, expected):
        raise CSGError(f"{where}.{key}: expected {expected}, got {fields[key]!r}")

    def integer(key, default, low):
        v = fields.get(key, default)
        if v is None and default is None:
            return None
        if isinstance(v, bool) or not isinstance(v, int) or v < low:
            fail(key, f"an integer >= {low}")
        return v

    def boolean(key, default):
        v = fields.get(key, default)
        if v is not None and not isinstance(v, bool):
            fail(key, "true or false")
        return v

    def vector(key, value):
        if (not isinstance(value, (list, tuple)) or len(value) != 3
                or not all(isinstance(c, (int, float)) and not isinstance(c, bool) and np.isfinite(c) for c in value)):
            raise CSGError(f"{where}.{key}: expected three finite numbers, got {value!r}")
        return tuple(float(c) for c in value)

    source = fields.get("input")
    if source is not None:
        if not isinstance(source, str) or not source:
            fail("input", "a scene or model path, or a built-in scene name")
        if source not in BUILTIN_SCENES:
            source = str((base / source) if not Path(source).is_absolute() else Path(source))
    output = fields.get("output")
    if not isinstance(output, str) or not output:
        raise CSGError(f"{where}.output: expected an .exr path, got {output!r}")
    output = Path(output) if Path(output).is_absolute() else base / output
    if output.suffix.lower() != ".exr":
        raise CSGError(f"{where}.output: {output.name}: the output is an OpenEXR file (.exr)")
    size = fields.get("size")
    if size is not None:
        if isinstance(size, str):
            try:
                size = tuple(int(v) for v in size.lower().split("x"))
            except ValueError:
                fail("size", 'WIDTHxHEIGHT such as "640x360", or [width, height]')
        if (not isinstance(size, (list, tuple)) or len(size) != 2
                or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in size)
                or size[0] * size[1] > 64_000_000):
            fail("size", 'WIDTHxHEIGHT such as "640x360", or [width, height]')
        size = tuple(size)
    is_xml = source is not None and source.lower().endswith(".xml")
    if size is None and not is_xml:
        size = DEFAULT_SIZE
    integrator = fields.get("integrator", "csg_path")
    if "integrator" in fields and is_xml:
        raise CSGError(f"{where}.integrator: an .xml scene names its own integrator")
    names = integrator_names()
    if integrator not in names:
        fail("integrator", " or ".join(names))
    camera = fields.get("camera")
    if camera is not None:
        if not isinstance(camera, dict) or not {"origin", "target"} <= set(camera) \
                or set(camera) - {"origin", "target", "up", "fov"}:
            fail("camera", '{"origin": [x, y, z], "target": [x, y, z], "up": [x, y, z], "fov": degrees}')
        fov = camera.get("fov")
        if fov is not None and (isinstance(fov, bool) or not isinstance(fov, (int, float)) or not 0 < fov < 180):
            raise CSGError(f"{where}.camera.fov: expected degrees in (0, 180), got {fov!r}")
        camera = {"origin": vector("camera.origin", camera["origin"]),
                  "target": vector("camera.target", camera["target"]),
                  "up": vector("camera.up", camera.get("up", (0.0, 0.0, 1.0))),
                  "fov": None if fov is None else float(fov)}
    orbit = fields.get("orbit", 0.0)
    if isinstance(orbit, bool) or not isinstance(orbit, (int, float)) or not np.isfinite(orbit):
        fail("orbit", "degrees")
    centre = fields.get("orbit_centre")
    cut = fields.get("cut", ())
    if isinstance(cut, str):
        cut = (cut,)
    if not isinstance(cut, (list, tuple)) or not all(isinstance(c, str) for c in cut):
        fail("cut", 'a list of cuts such as ["x>0"]')
    hide = fields.get("hide")
    if isinstance(hide, list) and all(isinstance(h, str) for h in hide):
        hide = ",".join(hide)
    if hide is not None and not isinstance(hide, str):
        fail("hide", "a list of volume or material names")
    model_only = [k for k in ("cut", "hide", "skip_unsupported", "depth", "world") if k in fields]
    if model_only and (source is None or is_xml or source in BUILTIN_SCENES):
        raise CSGError(f"{where}: {', '.join(model_only)} apply to model files")
    job = Job(name=output.stem, input=source, output=output,
              spp=integer("spp", DEFAULT_SPP, 1), chunk_spp=integer("chunk_spp", DEFAULT_CHUNK_SPP, 1),
              seed=integer("seed", 0, 0), size=size, integrator=integrator, sensor=integer("sensor", 0, 0),
              camera=camera, orbit=float(orbit), orbit_centre=None if centre is None else vector("orbit_centre", centre),
              png=boolean("png", True), cut=tuple(cut), hide=hide,
              skip_unsupported=boolean("skip_unsupported", False), depth=integer("depth", None, 0),
              world=boolean("world", None))
    if job.seed >= 2**32:
        fail("seed", "an integer below 2^32")
    return job


def turntable(job: Job, frames: int) -> list[Job]:
    """`frames` copies of `job` with the camera turned by 360 k / frames degrees (outputs
    `name_0000.exr`, ...); each frame has its own seeds."""
    if frames < 1:
        raise CSGError(f"--frames: expected a positive count, got {frames}")
    digits = max(4, len(str(frames - 1)))
    out = []
    for k in range(frames):
        output = job.output.with_name(f"{job.output.stem}_{k:0{digits}d}{job.output.suffix}")
        out.append(dataclasses.replace(job, name=output.stem, output=output, orbit=job.orbit + 360.0 * k / frames,
                                       seed=(job.seed + k) % 2**32))
    return out


def _check_distinct_outputs(jobs: list[Job], source: str):
    seen = {}
    for k, job in enumerate(jobs):
        key = job.output.resolve()
        if key in seen:
            raise CSGError(f"{source}: jobs {seen[key]} and {k} write the same output {job.output}")
        seen[key] = k
