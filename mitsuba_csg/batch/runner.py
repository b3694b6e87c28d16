"""Running a batch: chunks of every job on Ray actors (or in this process), merged per job.

The driver (this process) plans the chunks, skips those an earlier run saved, hands the rest
to workers, saves each result as it arrives, and writes a job's image once its last chunk is
in. Workers only render: what travels per task is the job's description (a small dict) and a
chunk's index, samples and seed; what comes back is the chunk's raw film (H x W x C floats).
Each worker loads a scene the first time it renders a chunk of it and keeps it.

Ray retries a chunk whose worker process died (the actor restarts and loads its scene again);
the chunk's seed is fixed, so the retried chunk renders the same samples. A job whose scene
fails to load, or whose chunk keeps failing, fails alone; the other jobs go on.
"""
from __future__ import annotations

import dataclasses
import os
import signal
import sys
import time
from collections import deque
from pathlib import Path

from ..errors import CSGError
from ..scenes import NAMED as BUILTIN_SCENES
from .jobs import Job
from .store import ChunkStore

# Tries of a chunk whose worker dies (killed, out of memory, crashed) before its job fails.
CHUNK_TRIES = 3


@dataclasses.dataclass
class JobResult:
    job: Job
    status: str = "pending"          # done, done earlier, failed
    error: str | None = None
    chunks_rendered: int = 0
    chunks_reused: int = 0
    seconds: float = 0.0             # worker time spent on its chunks
    outputs: list = dataclasses.field(default_factory=list)


@dataclasses.dataclass
class BatchSummary:
    results: list
    seconds: float
    backend: str
    workers: int
    worker_pids: set = dataclasses.field(default_factory=set)   # processes that rendered chunks

    @property
    def failed(self) -> list:
        return [r for r in self.results if r.status == "failed"]


def ray_available() -> bool:
    try:
        import ray  # noqa: F401
        return True
    except ImportError:
        return False


def run(jobs: list[Job], workers: int | None = None, threads: int | None = None, address: str | None = None,
        use_ray: bool | None = None, progress: bool | None = None, variant: str | None = None) -> BatchSummary:
    """Render `jobs`, resuming from chunks an earlier run saved. `use_ray` None: on Ray when it
    is installed (a local cluster sized to the machine, or the cluster at `address`), else in
    this process. `workers` Ray actors of `threads` Dr.Jit threads each (defaults in
    docs/batch.md). `progress` None: a bar when stderr is a terminal."""
    import mitsuba as mi
    variant = variant or mi.variant()
    if use_ray is None:
        use_ray = ray_available() or address is not None
    if use_ray and not ray_available():
        raise CSGError("Ray is not installed: pip install 'mitsuba-csg[distributed]', or run in-process (--local)")
    t0 = time.perf_counter()
    results = [JobResult(job) for job in jobs]
    queue = deque()
    stores = {}
    for k, result in enumerate(results):
        job = result.job
        store = ChunkStore(job)
        if store.complete():
            result.status, result.outputs = "done earlier", [job.output]
            continue
        problem = _input_problem(job)
        if problem is None:
            try:
                done = store.open()
            except OSError as e:
                problem = f"{job.output}: cannot write there ({e.strerror or e})"
        if problem is not None:
            result.status, result.error = "failed", problem
            continue
        stores[k] = store
        result.chunks_reused = len(done)
        pending = [c for c in job.chunks() if c.index not in done]
        queue.extend((k, c) for c in pending)
        if not pending:
            _finish(result, store)
    bar = _Progress(len(queue), progress)
    pids = set()
    try:
        with _StopRequest() as stop:
            if not queue:
                backend, count = "nothing to render", 0
            elif use_ray:
                backend, count = _run_ray(queue, results, stores, bar, pids, stop, workers, threads, address, variant)
            else:
                backend, count = _run_here(queue, results, stores, bar, pids, stop, variant, threads)
    finally:
        bar.close()
    return BatchSummary(results, time.perf_counter() - t0, backend, count, pids)


def _input_problem(job: Job) -> str | None:
    if job.input is None or job.input in BUILTIN_SCENES:
        return None
    if not Path(job.input).is_file():
        return f"{job.input}: no such file"
    return None


def _finish(result: JobResult, store: ChunkStore):
    try:
        image, names = store.merge()
        result.outputs = store.write_outputs(image, names)
        result.status = "done"
    except (OSError, ValueError) as e:
        result.status, result.error = "failed", f"writing {result.job.output}: {e}"


def _accept(reply: dict, k: int, chunk, results, stores, bar, pids):
    """A chunk's result arrived: save it; write the job's image if it was the last."""
    pids.add(reply["pid"])
    result = results[k]
    if result.status == "failed":
        return
    stores[k].save(chunk.index, reply["raw"], reply["names"], chunk.spp, chunk.seed)
    result.chunks_rendered += 1
    result.seconds += reply["seconds"]
    height, width = reply["raw"].shape[:2]
    bar.advance(width * height * chunk.spp)
    if result.chunks_rendered + result.chunks_reused == result.job.chunk_count:
        _finish(result, stores[k])


def _fail(k: int, error: str, results, queue, bar):
    """Job k fails alone: its queued chunks are dropped."""
    result = results[k]
    if result.status != "failed":
        result.status, result.error = "failed", error
    kept = [item for item in queue if item[0] != k]
    bar.skip(len(queue) - len(kept))
    queue.clear()
    queue.extend(kept)


def _one_line(error: BaseException) -> str:
    text = str(error).strip().splitlines()
    return (text[-1] if text else type(error).__name__)[:2000]


def _run_here(queue, results, stores, bar, pids, stop, variant, threads):
    import drjit as dr
    from .worker import ChunkRenderer
    before = dr.thread_count()
    try:
        renderer = ChunkRenderer(variant, threads)
        _render_queue(renderer, queue, results, stores, bar, pids, stop)
    finally:
        dr.set_thread_count(before)
    return "in-process", 1


def _render_queue(renderer, queue, results, stores, bar, pids, stop):
    while queue:
        stop.check()
        k, chunk = queue.popleft()
        try:
            reply = renderer.render(results[k].job.to_dict(), chunk.index, chunk.spp, chunk.seed)
        except Exception as e:          # the job's scene or render failed: that job alone
            _fail(k, _one_line(e), results, queue, bar)
            continue
        _accept(reply, k, chunk, results, stores, bar, pids)


def _run_ray(queue, results, stores, bar, pids, stop, workers, threads, address, variant):
    import ray
    threads = threads or 1
    started = not ray.is_initialized()
    if started:
        # The embedded default: a local cluster sized to this machine (at least as many CPUs as
        # the workers asked for reserve), or the cluster at `address`.
        local = {"num_cpus": max(os.cpu_count() or 1, (workers or 0) * threads)} if address is None else {}
        ray.init(address=address, include_dashboard=False, logging_level="error", log_to_driver=True, **local)
    try:
        cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        workers = workers or max(1, cpus // threads)
        if workers * threads > cpus:
            # Actors that reserve more CPUs than the cluster has would wait for ever.
            raise CSGError(f"the Ray cluster has {cpus} CPUs; {workers} workers of {threads} threads need "
                           f"{workers * threads}")
        from .worker import ChunkRenderer
        actor_class = ray.remote(ChunkRenderer).options(num_cpus=threads, max_restarts=-1,
                                                        max_task_retries=CHUNK_TRIES - 1)
        actors = [actor_class.remote(variant, threads) for _ in range(workers)]
        in_flight = {}                  # object ref -> (actor, job index, chunk)
        idle = deque(actors * 2)        # two chunks queued per actor keep it busy between replies
        try:
            while queue or in_flight:
                stop.check()
                while queue and idle:
                    actor = idle.popleft()
                    k, chunk = queue.popleft()
                    ref = actor.render.remote(results[k].job.to_dict(), chunk.index, chunk.spp, chunk.seed)
                    in_flight[ref] = (actor, k, chunk)
                ready, _ = ray.wait(list(in_flight), num_returns=1, timeout=0.25)
                if not ready:
                    continue
                actor, k, chunk = in_flight.pop(ready[0])
                idle.append(actor)
                try:
                    reply = ray.get(ready[0])
                except ray.exceptions.RayTaskError as e:       # raised by our code in the worker
                    cause = getattr(e, "cause", None)
                    _fail(k, _one_line(cause if cause is not None else e), results, queue, bar)
                    continue
                except ray.exceptions.RayActorError as e:      # the worker died CHUNK_TRIES times
                    _fail(k, f"chunk {chunk.index}: its worker died {CHUNK_TRIES} times ({_one_line(e)})",
                          results, queue, bar)
                    continue
                _accept(reply, k, chunk, results, stores, bar, pids)
        finally:
            for actor in actors:           # ends their chunks in progress too
                ray.kill(actor, no_restart=True)
        return ("ray (local cluster)" if address is None else f"ray ({address})"), workers
    finally:
        if started:
            ray.shutdown()


class _StopRequest:
    """Ctrl-C while a batch runs: the first stops it between chunks (a KeyboardInterrupt raised in
    the middle of Dr.Jit's kernel tracing can leave it deadlocked), the second at once. Saved
    chunks are whole either way (written under a temporary name, then renamed)."""

    def __init__(self):
        self.requested = False
        self._previous = None

    def __enter__(self):
        import threading
        # Only from the main thread, and not where SIGINT is ignored (nohup, a background job
        # of a script): such a run is not meant to stop on Ctrl-C.
        if (threading.current_thread() is threading.main_thread()
                and signal.getsignal(signal.SIGINT) is not signal.SIG_IGN):
            self._previous = signal.signal(signal.SIGINT, self._handle)
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            signal.signal(signal.SIGINT, self._previous)
        return False

    def _handle(self, signum, frame):
        if self.requested:
            sys.stderr.write("\nmitsuba-csg: stopped at once; finished chunks are saved\n")
            os._exit(130)
        self.requested = True
        sys.stderr.write("\nmitsuba-csg: stopping; finished chunks are kept (Ctrl-C again: stop at once)\n")

    def check(self):
        if self.requested:
            raise KeyboardInterrupt


class _Progress:
    """One bar over all jobs' chunks, with camera rays per second (pixel samples) and an ETA."""

    def __init__(self, total: int, enabled: bool | None):
        from tqdm import tqdm
        self.bar = tqdm(total=total, unit="chunk", disable=(not sys.stderr.isatty()) if enabled is None else not enabled,
                        dynamic_ncols=True, smoothing=0.1)
        self.rays, self.t0 = 0, time.perf_counter()

    def advance(self, rays: int):
        self.rays += rays
        rate = self.rays / max(time.perf_counter() - self.t0, 1e-9)
        self.bar.set_postfix_str(self.bar.format_sizeof(rate, "rays/s"), refresh=False)
        self.bar.update(1)

    def skip(self, count: int):
        if count:
            self.bar.total -= count
            self.bar.refresh()

    def close(self):
        self.bar.close()
