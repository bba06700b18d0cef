"""The editor's learned-layer jobs: start, progress, cancel.

``SessionJobs`` is a part of ``EditSession`` (``lasagna.serve.session``). A job (per-image refinement,
re-rendering) runs in one worker thread with a progress report and a cancel flag checked between steps
(``make_layer``'s callback); the result lands as a new, undoable version of the session's stack.
"""

from __future__ import annotations

import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from lasagna.document import LearnedLayer
from lasagna.errors import DocumentError, LasagnaError
from lasagna.io.stack import Stack
from lasagna.limits import memory_budget_scope


class Cancelled(Exception):
    """Raised inside a job's per-step callback when its cancel button was pressed."""


@dataclass
class Job:
    """A long-running change (per-image refinement, re-rendering): progress and the cancel flag."""

    id: str
    what: str
    layer_id: str
    steps: int
    step: int = 0
    state: str = "running"  # running, done, cancelled, failed
    error: str | None = None
    version: int | None = None  # the version its result became
    cancel: threading.Event = field(default_factory=threading.Event)
    started: float = field(default_factory=time.monotonic)

    def report(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "what": self.what,
            "layer": self.layer_id,
            "steps": self.steps,
            "step": self.step,
            "state": self.state,
            "error": self.error,
            "version": self.version,
            "seconds": round(time.monotonic() - self.started, 2),
        }


class SessionJobs:
    """Learned-layer jobs of ``EditSession``'s stack (module docstring)."""

    # Provided by ``EditSession`` (lasagna.serve.session).
    folder: Path
    stack: Stack
    budget: int
    _guard: Any
    _admit: Any
    catalogue_dirs: Any
    device: str
    job: Job | None
    jobs: dict[str, Job]
    _check_version: Any
    _check_idle: Any
    _snapshot: Any
    _push: Any
    files: dict[str, bytes]
    version: int

    def start_job(self, version: Any, kind: str, id: str, steps: Any = None) -> Job:
        """Start ``refine`` (per-image optimisation of learned layer ``id`` for ``steps``; from its amortised
        pass when it has one) or ``rerender`` (from its record) in the worker thread."""
        from lasagna.limits import MAX_DISTILL_STEPS
        from lasagna.recipe import Recipe

        if kind not in ("refine", "rerender"):
            raise LasagnaError(f"unknown job {kind!r}; expected refine or rerender", "job")
        with self._guard():
            self._check_version(version)
            self._check_idle(kind)
            layer = self.stack.document.layer(id)
            if not isinstance(layer, LearnedLayer):
                raise DocumentError(f"is a {layer.kind} layer; expected a learned layer", f"layer {id!r}")
            stack = Stack(self.stack.document, self.folder, dict(self.stack.tensors), dict(self.stack.bit_depths))
            options: dict[str, Any] = {}
            if kind == "refine":
                if isinstance(steps, bool) or not isinstance(steps, int) or not 1 <= steps <= MAX_DISTILL_STEPS:
                    raise LasagnaError(
                        f"expected an integer number of steps in [1, {MAX_DISTILL_STEPS}], got {steps!r}", "steps"
                    )
                # A generator copy not saved yet is the catalogue's it was copied from.
                options = {"refine": steps, "catalogue_generator": _unsaved_generator(stack, layer)}
            recipe = Recipe.from_layer(stack, layer, catalogue_dirs=self.catalogue_dirs, **options)
            job = Job(uuid.uuid4().hex[:12], kind, id, recipe.steps)
            self.job = job
            self.jobs[job.id] = job
        threading.Thread(target=self._run_job, args=(job, stack, recipe), daemon=True, name=f"job-{job.id}").start()
        return job

    def _run_job(self, job: Job, stack: Stack, recipe) -> None:
        with memory_budget_scope(self.budget):  # a new thread: the session's budget, not the default
            self._run_job_in_budget(job, stack, recipe)

    def _run_job_in_budget(self, job: Job, stack: Stack, recipe) -> None:
        from lasagna.editing import remake_layer

        def callback(step: int, layer) -> None:
            job.step = step + 1  # steps done once this one is
            if job.cancel.is_set():
                raise Cancelled

        try:
            run = remake_layer(stack, job.layer_id, recipe, device=self.device, callback=callback)
        except Cancelled:
            job.state = "cancelled"
            return
        except LasagnaError as exc:
            job.state, job.error = "failed", str(exc)
            return
        except Exception as exc:  # noqa: BLE001 - reported to the page in one line, the server stays up
            job.state, job.error = "failed", f"internal error: {type(exc).__name__}: {exc}"
            return
        finally:
            if job.state == "running" and job.cancel.is_set():
                job.state = "cancelled"
        with self._guard():
            self._land(job, stack, run.files)

    def _land(self, job: Job, new: Stack, files: dict[str, bytes]) -> None:
        """A finished job's layer put into the current stack as a new, undoable version (its name, visibility,
        opacity and offset as they are now: the user may have changed them while it ran)."""
        cur_doc = self.stack.document
        base = new.document.layer(job.layer_id)
        if job.layer_id not in cur_doc.ids or cur_doc.layer(job.layer_id).conditioned_on != base.conditioned_on:
            job.state, job.error = "failed", "the layer was removed or re-parented while the job ran; run it again"
            return
        before = self._snapshot(f"{job.what} {job.layer_id}")
        keep = {k: getattr(cur_doc.layer(job.layer_id), k) for k in ("name", "visible", "opacity", "offset")}
        fields = {
            **base.model_dump(),
            **{k: (v.model_dump() if hasattr(v, "model_dump") else v) for k, v in keep.items()},
        }
        self.stack.document = cur_doc.with_layer(fields).replace(metadata=new.document.metadata)
        self.stack.tensors[job.layer_id] = new.tensors[job.layer_id]
        self.stack.bit_depths[job.layer_id] = new.bit_depths.get(job.layer_id, 16)
        self.files.update(files)
        self._push(before)
        job.version = self.version
        job.step = max(job.step, job.steps)
        job.state = "done"

    def cancel_job(self, job_id: str) -> dict[str, Any]:
        job = self.jobs.get(job_id)
        if job is None:
            raise LasagnaError(f"no job {job_id!r}; expected the id a job was started with", "job")
        job.cancel.set()
        return job.report()


def _unsaved_generator(stack: Stack, layer: LearnedLayer) -> bool:
    """Whether ``layer`` was made by a generator whose copy is not in the stack folder yet (added, unsaved)."""
    if layer.generator is None or stack.folder is None:
        return False
    return not (Path(stack.folder) / layer.generator.checkpoint).is_file()


__all__ = ["Cancelled", "Job", "SessionJobs"]
