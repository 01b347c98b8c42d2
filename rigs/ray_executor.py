"""`omnigen render --executor ray`: the frames of a run (or of one shard) fan out over a Ray cluster.

One actor per worker holds a `omnigen.rigs.render.Renderer` (the city and the backend built once) and
renders frames by index; every frame is written by the actor straight into `--out` (a shared file
system on a multi-node cluster) with the same per-frame atomic writes as the local executor, so
records and images do not depend on the executor. The driver:

- keeps one frame in flight per actor (Cycles and pyrender are one job per process);
- restarts an actor after `frames_per_worker` frames, so a renderer's memory growth stays bounded;
- on a failed frame (an exception, or the actor's process dying mid-frame) replaces the actor
  and retries the frame, up to `retries` more times, then reports it in `summary.failed`;
  a frame is done only when the actor returns, i.e. after its record was renamed into place, so a
  crash never loses a finished frame and a half-finished one is rendered again from scratch;
- finalizes (index and manifest) when every frame of the run has its record (`finalize_run`).

Ray is an optional dependency: this module imports it only inside `run_ray`.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import fields as dataclass_fields
from typing import Any

from omnigen.rigs.render import RenderJob, RenderSummary, finalize_run, frame_id_for, load_rig

# Test hook: "FRAME:MARKER" makes the actor that renders frame FRAME exit the process (os._exit)
# after the frame's images are written and before its record is, once (the MARKER file records
# that it happened). Read by the driver and passed to the actors.
CRASH_ENV = "OMNIGEN_RAY_CRASH_ONCE"


class FrameWorker:
    """The body of the Ray actor: a Renderer built once, frames rendered by index."""

    def __init__(self, job_fields: dict[str, Any], crash: str | None = None) -> None:
        from omnigen.rigs.render import Renderer

        self.renderer = Renderer(RenderJob(**job_fields))
        self.crash = None
        if crash:
            frame, marker = crash.split(":", 1)
            self.crash = (int(frame), marker)
            write = self.renderer.writer.write

            def write_or_crash(record):
                f, m = self.crash
                if record.frame_id == self.renderer.frame_id(f) and not os.path.exists(m):
                    open(m, "w").close()
                    os._exit(17)  # the process dies in the middle of the frame: images written, no record
                return write(record)

            self.renderer.writer.write = write_or_crash

    def render(self, index: int) -> dict[str, Any]:
        s = self.renderer.summary
        before = (s.objects, s.redraws, dict(s.timings))
        self.renderer.render_frame(index)
        return {"index": index, "objects": s.objects - before[0], "redraws": s.redraws - before[1],
                "timings": {k: v - before[2].get(k, 0.0) for k, v in s.timings.items()}}

    def close(self) -> None:
        self.renderer.close()


def run_ray(job: RenderJob, address: str | None = None, workers: int | None = None, cpus_per_worker: float = 1.0,
            frames_per_worker: int = 100, retries: int = 2, show_progress: bool = True,
            init_kwargs: dict[str, Any] | None = None) -> RenderSummary:
    """Render `job` (its shard's frames) on Ray; see the module docstring.

    `address`: an existing cluster ("auto", "ray://host:10001", "host:6379"); None starts a local
    Ray for the run (the machine's CPUs) unless Ray is already initialised in this process.
    `workers`: concurrent actors (default: the cluster's CPUs / cpus_per_worker).
    """
    try:
        import ray
    except ImportError:
        raise RuntimeError("--executor ray needs Ray: pip install 'ray[default]'") from None
    from ray.exceptions import GetTimeoutError

    if frames_per_worker < 1 or retries < 0:
        raise ValueError("frames_per_worker must be >= 1 and retries >= 0")
    start = time.perf_counter()
    rig = load_rig(job.rig)  # fail early, in the driver, on a bad rig
    summary = RenderSummary()
    indices = job.shard_indices()
    records = os.path.join(job.out, "records")
    todo = [i for i in indices if not os.path.exists(os.path.join(records, frame_id_for(rig.name, job.seed, i) + ".json"))]
    summary.skipped = len(indices) - len(todo)
    os.makedirs(records, exist_ok=True)

    started = False
    if not ray.is_initialized():
        kw = {"include_dashboard": False, "log_to_driver": False}
        kw.update(init_kwargs or {})
        ray.init(address=address, **kw)
        started = True
    try:
        if todo:
            cpus = ray.cluster_resources().get("CPU", 1.0)
            n_workers = max(1, min(len(todo), workers or int(cpus // cpus_per_worker) or 1))
            _drive(ray, GetTimeoutError, job, todo, n_workers, cpus_per_worker, frames_per_worker, retries,
                   summary, show_progress)
    finally:
        if started:
            ray.shutdown()
    summary.finalized = not summary.failed and finalize_run(job, show_progress)
    summary.seconds = time.perf_counter() - start
    return summary


def _drive(ray, GetTimeoutError, job, todo, n_workers, cpus_per_worker, frames_per_worker, retries, summary,
           show_progress) -> None:
    from tqdm import tqdm

    Actor = ray.remote(num_cpus=cpus_per_worker, max_restarts=0, max_task_retries=0)(FrameWorker)
    fields = {f.name: getattr(job, f.name) for f in dataclass_fields(job)}  # shallow: overrides stay objects
    fields["out"] = str(job.out)
    crash = os.environ.get(CRASH_ENV) or None
    pending = list(reversed(todo))  # pop() takes the lowest index first
    attempts: dict[int, int] = {}
    in_flight: dict[Any, tuple[Any, int]] = {}  # ObjectRef -> (actor, frame)
    served: dict[Any, int] = {}  # actor -> frames rendered

    def new_actor():
        a = Actor.remote(fields, crash)
        served[a] = 0
        return a

    def retire(actor, graceful: bool) -> None:
        served.pop(actor, None)
        if graceful:
            try:
                ray.get(actor.close.remote(), timeout=30)
            except Exception:
                pass
        ray.kill(actor, no_restart=True)

    def submit(actor) -> None:
        i = pending.pop()
        attempts[i] = attempts.get(i, 0) + 1
        in_flight[actor.render.remote(i)] = (actor, i)

    bar = tqdm(total=len(todo), desc=f"render {job.rig} (ray)", unit="frame", dynamic_ncols=True, leave=False,
               disable=not show_progress or not sys.stderr.isatty(), mininterval=0.5)
    t0 = time.perf_counter()
    try:
        for _ in range(min(n_workers, len(pending))):
            submit(new_actor())
        while in_flight:
            ready, _ = ray.wait(list(in_flight), num_returns=1)
            ref = ready[0]
            actor, i = in_flight.pop(ref)
            try:
                res = ray.get(ref)
            except Exception as exc:  # the frame raised, or the actor's process died
                retire(actor, graceful=False)
                actor = None
                if attempts[i] <= retries:
                    pending.append(i)  # next to go
                else:
                    summary.failed.append(i)
                    print(f"omnigen render: frame {i} failed after {attempts[i]} attempts: "
                          f"{type(exc).__name__}: {str(exc).strip().splitlines()[-1] if str(exc).strip() else ''}",
                          file=sys.stderr)
            else:
                summary.rendered += 1
                summary.objects += res["objects"]
                summary.redraws += res["redraws"]
                for k, v in res["timings"].items():
                    summary.timings[k] = summary.timings.get(k, 0.0) + v
                served[actor] += 1
                if served[actor] >= frames_per_worker:
                    retire(actor, graceful=True)  # a fresh process keeps memory flat
                    actor = None
            bar.update(summary.rendered + len(summary.failed) - bar.n)
            bar.set_postfix(done=summary.rendered, failed=len(summary.failed),
                            rate=f"{summary.rendered / max(time.perf_counter() - t0, 1e-9):.2f}/s", refresh=False)
            if pending:
                submit(actor if actor is not None else new_actor())
            elif actor is not None:
                retire(actor, graceful=True)
    finally:
        bar.close()
        for actor in list(served):
            try:
                ray.kill(actor, no_restart=True)
            except Exception:
                pass
    summary.failed.sort()
