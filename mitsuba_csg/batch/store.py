"""Finished chunks on disk, beside each job's output, so that an interrupted batch resumes.

A job's chunks live in ``.<output name>.chunks/`` in its output folder: ``job.json`` (the
job's fingerprint, whether the image was written) and one ``chunk-NNNN.npz`` per finished
chunk, holding the film's raw sums (filter-weighted values and the weight sum per pixel).
Files are written under a temporary name and renamed, so a killed run never leaves half a
chunk. Once the image is written the chunk files are removed and ``job.json`` says so, and a
rerun of the same job skips it.

Merging sums the raw chunks and divides by the summed weights once: the same as one render
with all the samples, whatever the film's reconstruction filter (docs/batch.md).
"""
from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np

from ..images import write_exr, write_png
from .jobs import Job


class ChunkStore:
    def __init__(self, job: Job):
        self.job = job
        self.folder = job.output.with_name(f".{job.output.name}.chunks")
        self.fingerprint = job.fingerprint()

    # ---- state ----
    def _meta(self) -> dict:
        try:
            return json.loads((self.folder / "job.json").read_text())
        except (OSError, ValueError):
            return {}

    def complete(self) -> bool:
        """The image was written by an earlier run of this very job, and is still there."""
        meta = self._meta()
        return (meta.get("fingerprint") == self.fingerprint and meta.get("complete") is True
                and self.job.output.is_file())

    def open(self) -> set[int]:
        """Prepare the folder; the indices of chunks an earlier run of this job finished (chunks
        of a changed job are discarded)."""
        if self._meta().get("fingerprint") != self.fingerprint and self.folder.exists():
            shutil.rmtree(self.folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        for stray in self.folder.glob(".*.partial*"):      # a run killed while writing
            stray.unlink(missing_ok=True)
        self._write_meta(complete=False)
        done = set()
        for chunk in self.job.chunks():
            path = self._path(chunk.index)
            if path.is_file():
                try:
                    with np.load(path) as f:
                        if int(f["seed"]) == chunk.seed and int(f["spp"]) == chunk.spp:
                            done.add(chunk.index)
                except (OSError, ValueError, KeyError):
                    path.unlink(missing_ok=True)      # unreadable: render it again
        return done

    def save(self, index: int, raw: np.ndarray, names: list[str], spp: int, seed: int):
        path = self._path(index)
        partial = path.with_name(f".{path.name}.partial.npz")
        np.savez(partial, raw=raw, names=np.array(names), spp=spp, seed=seed)
        os.replace(partial, path)

    def merge(self) -> tuple[np.ndarray, list[str]]:
        """The job's image (H, W, C) from its saved chunks, and its channel names (without W)."""
        total, names = None, None
        for chunk in self.job.chunks():
            with np.load(self._path(chunk.index)) as f:
                raw, chunk_names = f["raw"].astype(np.float64), [str(n) for n in f["names"]]
            if total is None:
                total, names = raw, chunk_names
            elif chunk_names != names or raw.shape != total.shape:
                raise ValueError(f"{self.folder}: chunk {chunk.index} does not match chunk 0")
            else:
                total += raw
        return develop(total, names)

    def write_outputs(self, image: np.ndarray, names: list[str]) -> list[Path]:
        self.job.output.parent.mkdir(parents=True, exist_ok=True)
        written = [write_exr(self.job.output, image, names)]
        colour = [k for k, name in enumerate(names) if name in ("R", "G", "B", "Y")]
        if self.job.png and colour:
            written.append(write_png(self.job.output.with_suffix(".png"), image[..., colour]))
        for chunk in self.job.chunks():
            self._path(chunk.index).unlink(missing_ok=True)
        self._write_meta(complete=True)
        return written

    # ---- files ----
    def _path(self, index: int) -> Path:
        return self.folder / f"chunk-{index:04d}.npz"

    def _write_meta(self, complete: bool):
        meta = {"fingerprint": self.fingerprint, "complete": complete, "chunks": self.job.chunk_count,
                "input": self.job.input, "spp": self.job.spp, "seed": self.job.seed}
        partial = self.folder / ".job.json.partial"
        partial.write_text(json.dumps(meta, indent=1))
        os.replace(partial, self.folder / "job.json")


def develop(raw: np.ndarray, names: list[str]) -> tuple[np.ndarray, list[str]]:
    """Divide a film's raw sums by its weight channel W (pixels without samples are 0), as
    Mitsuba's film develops them; the image and its channel names without W."""
    w = names.index("W")
    weight = raw[..., w:w + 1]
    keep = [k for k in range(len(names)) if k != w]
    values = raw[..., keep]
    image = np.divide(values, weight, out=np.zeros_like(values), where=weight > 0)
    return image.astype(np.float32), [names[k] for k in keep]
