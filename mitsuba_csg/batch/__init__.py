"""Batch rendering: many images (views, turntable frames, sample counts, seeds) split into
sample chunks, rendered on Ray workers or in this process, merged per image, resumable.

    from mitsuba_csg import batch
    summary = batch.render("jobs.json")                    # or a list of Job / dicts
    summary = batch.render("cheese-500", frames=36, output="turntable/frame.exr", spp=64)

`docs/batch.md` describes job files, chunks and seeds, merging, resuming and faults.
"""
from __future__ import annotations

from pathlib import Path

from .jobs import Chunk, Job, is_job_file, job_from_fields, load_jobs, parse_jobs, turntable
from .runner import BatchSummary, JobResult, ray_available, run


def render(what, frames: int | None = None, workers: int | None = None, threads: int | None = None,
           address: str | None = None, use_ray: bool | None = None, progress: bool | None = None,
           **job_fields) -> BatchSummary:
    """Render a job file (a path to JSON with "jobs"), a list of jobs (Job objects or job-file
    dicts), or one scene / model / built-in scene name with `job_fields` (output=..., spp=...).
    `frames` turns every job into a turntable of that many frames."""
    if isinstance(what, (list, tuple)):
        jobs = [j for j in what if isinstance(j, Job)]
        dicts = [j for j in what if not isinstance(j, Job)]
        if dicts:
            jobs += parse_jobs({"jobs": dicts}, Path.cwd(), "jobs")
        if frames is not None:
            jobs = [f for j in jobs for f in turntable(j, frames)]
    elif what is not None and is_job_file(what):
        if job_fields:
            raise TypeError(f"job fields {sorted(job_fields)} go into the job file, not the call")
        jobs = load_jobs(what, frames)
    else:
        fields = {"input": None if what is None else str(what), **job_fields}
        jobs = parse_jobs({"jobs": [fields]}, Path.cwd(), "batch", frames)
    return run(jobs, workers=workers, threads=threads, address=address, use_ray=use_ray, progress=progress)


__all__ = ["BatchSummary", "Chunk", "Job", "JobResult", "is_job_file", "job_from_fields", "load_jobs", "parse_jobs",
           "ray_available", "render", "run", "turntable"]
