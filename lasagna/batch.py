"""Edits at scale: one learned layer for many images, one stack folder per input, resumable and shardable.

    from lasagna.batch import edit_many
    report = edit_many(["photos/", "more/*.jpg"], "shading", "left", "out/", generator="amortised")
    print(report.summary())        # "edited 41, skipped 3 (complete), failed 1"
    report.failed                  # [Outcome(input='photos/bad.png', status='failed', error='…'), …]

**Inputs, names and records** (``lasagna.batch_records``, its names re-exported here): files, stack folders,
folders and glob patterns, sorted; ``out_dir/<name>/`` per input, the name matched to the source its folder
records, never to a sort position, so one input keeps its folder across runs.

**Outputs**: each stack folder is written all or nothing (``lasagna.io.folder``), so a folder that exists
with its stack.json is **complete**: it is skipped when its record matches (same source bytes, same
request); redone in place when its source changed (``Outcome.note`` says so); refused in one line when it
was asked with other settings (a different condition or layer: ``force`` redoes it, or use another
``out_dir``). ``force`` rewrites all. Finished folders are staged (written into temporary siblings without
fsync, ``lasagna.atomic.unsynced``) and committed together: one file-system sync, then each renamed into
place (``COMMIT_EVERY``). A killed run leaves only hidden temporaries, swept when the next run starts
(``lasagna.atomic.sweep_stale``): running again finishes the rest, losing nothing complete and redoing
nothing complete. Each input's failure is caught and reported (``Outcome.error``, one line) and the others
go on. A large file every folder carries byte for byte (the generator's weights, 2 MB) is written once per
run and hard-linked into each folder (``lasagna.io.folder.SharedFiles``; copies where the file system takes
no links): each folder stays whole and self-contained.

**Batches and shards.** The sorted inputs are cut into consecutive chunks of ``batch_size``; chunk k belongs
to rank ``k mod world`` (with ``batch_size`` 1: ``inputs[rank::world]``). Within a chunk the amortised
generator (loaded once per run) runs once per group of inputs of the same working-size shape. Per-image
runs go one at a time whatever ``batch_size``: ``distill_image`` draws t, ε and patches for the whole batch
from one generator and stops it as a whole, so a batched run would depend on its company.

**Determinism.** With ``batch_size`` 1 (the default) every layer is computed exactly as ``edit`` computes it,
so outputs equal ``edit``'s — and a sharded run's equal a single process's — bit for bit. A batched forward
pass is not batch-invariant on CPU (the convolutions' float order depends on the batch size): it differs
from the one-at-a-time pass by a few float32 ulps before the layer is stored as 16-bit codes (measured:
2.4e-7 for the shipped shading generator at 64², ``tests/test_batch.py``), and batches are chunks of the
whole sorted input list, so a sharded run still equals the single-process run with the same ``batch_size``
bit for bit — a re-run that skips complete inputs computes the rest in smaller batches, within that
tolerance. Batching gains nothing on a CPU (7 ms per 64² image at any batch size, one thread): it is for
accelerators.

**Processes.** ``rank``/``world`` default to the initialised process group (``torch.distributed``;
``lasagna edit`` under ``torchrun`` joins it through ``lasagna.training.loop.init_distributed``, gloo on
CPU); with a group, every rank's report holds every input's outcome (gathered at the end).
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch

from lasagna import catalogue as cat
from lasagna.atomic import sweep_stale, sync_filesystem, unsynced
from lasagna.batch_records import (
    BATCH_KEY,
    IMAGE_SUFFIXES,
    assign_names,
    collect_inputs,
    collect_with_roots,
    compare_record,
    output_names,
    read_record,
    request_record,
    source_or_none,
    source_record,
    with_record,
)
from lasagna.components import LoadedGenerator
from lasagna.document import STACK_FILE
from lasagna.editing import EditPlan, plan_edit
from lasagna.errors import LasagnaError, PathError, printable
from lasagna.io.folder import SharedFiles, check_writable, swap_in
from lasagna.io.image import DEFAULT_EDIT_MAX_PIXELS
from lasagna.learned import choose_method, layer_input, make_layer
from lasagna.recipe import amortised_generator
from lasagna.request import EditRequest

Status = Literal["done", "skipped", "failed"]

# Finished stack folders wait, written but not renamed into place, until this many are staged or this many
# seconds have passed; then one file-system sync makes them all durable and each is renamed in. The sync
# replaces seven fsyncs per stack folder (24 ms of a 64² edit's ~45 ms here); a kill loses at most the
# staged ones' work, never a complete output.
COMMIT_EVERY = 32
COMMIT_SECONDS = 2.0


@dataclass
class Outcome:
    """What became of one input: ``done`` (written to ``output``), ``skipped`` (``output`` was complete),
    ``failed`` (``error``: one line, ``where: what; expected …``); ``note``: why a complete output was redone."""

    index: int  # in the sorted input list
    input: str
    output: str
    status: Status
    error: str | None = None
    seconds: float = 0.0
    note: str | None = None


@dataclass
class BatchReport:
    """Every input's ``Outcome`` (this rank's alone when there is no process group to gather from)."""

    outcomes: list[Outcome] = field(default_factory=list)
    seconds: float = 0.0

    def _with(self, status: Status) -> list[Outcome]:
        return [o for o in self.outcomes if o.status == status]

    @property
    def done(self) -> list[Outcome]:
        return self._with("done")

    @property
    def skipped(self) -> list[Outcome]:
        return self._with("skipped")

    @property
    def failed(self) -> list[Outcome]:
        return self._with("failed")

    @property
    def ok(self) -> bool:
        """True when no input failed."""
        return not self.failed

    def summary(self) -> str:
        return f"edited {len(self.done)}, skipped {len(self.skipped)} (complete), failed {len(self.failed)}"


# ---- the run ------------------------------------------------------------------------------------------


def is_complete(folder: Path) -> bool:
    """A stack folder written by ``write_stack_folder`` (renamed into place when finished): it exists with
    its stack.json (and composite.png, written before the rename)."""
    return (folder / STACK_FILE).is_file() and (folder / "composite.png").is_file()


def shard(count: int, batch_size: int, rank: int, world: int) -> list[list[int]]:
    """The chunks of input indices rank ``rank`` of ``world`` takes: chunks of ``batch_size`` consecutive
    indices of ``range(count)``, chunk k to rank k mod world."""
    chunks = [list(range(i, min(i + batch_size, count))) for i in range(0, count, batch_size)]
    return chunks[rank::world]


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _describe(exc: BaseException, label: str) -> str:
    """An input's failure as one line (a ``LasagnaError`` as it reads, less a leading ``label: ``, which the
    report names anyway; anything else with its type)."""
    text, shown = _message(exc), printable(label)  # a LasagnaError writes its place escaped (lasagna.errors)
    return text[len(shown) + 2 :] if text.startswith(f"{shown}: ") else text


def _message(exc: BaseException) -> str:
    from pydantic import ValidationError

    from lasagna.errors import describe_validation_error

    if isinstance(exc, ValidationError):
        return _one_line(str(describe_validation_error(exc)))
    if isinstance(exc, LasagnaError):
        return _one_line(str(exc))
    if isinstance(exc, OSError):
        return _one_line(f"{exc.strerror or exc}; expected a readable input and a writable output")
    return _one_line(f"{type(exc).__name__}: {exc}")


def _process_group() -> tuple[int, int]:
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _gather(outcomes: list[Outcome]) -> list[Outcome]:
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return outcomes
    every: list[list[Outcome] | None] = [None] * dist.get_world_size()
    dist.all_gather_object(every, outcomes)
    return sorted((o for part in every for o in (part or [])), key=lambda o: o.index)


def edit_many(
    inputs: Sequence[Any] | Any,
    preset: str,
    condition: str,
    out_dir: str | os.PathLike,
    *,
    rank: int | None = None,
    world: int | None = None,
    batch_size: int = 1,
    force: bool = False,
    ora: bool = True,
    depth: int = 8,
    progress: bool | Callable[[Outcome], None] = False,
    on: str | None = None,
    id: str | None = None,
    generator: str | None = None,
    optimize: int | None = None,
    loss: str | None = None,
    guidance: float | None = None,
    seed: int | None = None,
    lr: float | None = None,
    catalogue_dirs=None,
    max_pixels: int = DEFAULT_EDIT_MAX_PIXELS,
    device: str | torch.device = "cpu",
    warn: Callable[[str], None] | None = None,
    request: EditRequest | None = None,
) -> BatchReport:
    """Edit every input (``collect_inputs``) as ``lasagna.editing.edit`` would, writing ``out_dir/<name>/`` per
    input (module docstring). ``progress``: a progress bar on rank 0 (True), or a function called with each
    outcome. The other keywords are ``edit``'s and ``EditResult.save``'s (``request``: an ``EditRequest`` in
    place of the preset, condition and ``edit``'s options). Returns the ``BatchReport``.

    Refused before any work (a ``LasagnaError``): a bad preset name, condition or ``optimize``, an
    ``out_dir`` that is not a writable folder, a folder or pattern that finds nothing.
    """
    start = time.monotonic()
    rank, world = _rank_and_world(batch_size, rank, world)
    request = request or EditRequest(
        preset=preset,
        condition=condition,
        on=on,
        id=id,
        generator=generator,
        optimize=optimize,
        loss=loss,
        guidance=guidance,
        seed=seed,
        lr=lr,
    )
    generators = _first_generator(request, catalogue_dirs, device)  # refusals before any work
    items, roots = collect_with_roots(inputs)
    out_dir = check_writable(out_dir, folder=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    sweep_stale(out_dir)  # a killed run's temporaries (their owners are gone)
    names = assign_names(items, roots, out_dir)
    mine = shard(len(items), batch_size, rank, world)
    run = _Run(request, items, roots, names, out_dir, generators, catalogue_dirs, max_pixels, device)
    run.force, run.ora, run.warn, run.depth = force, ora, warn, depth
    run.start_progress(progress, rank, sum(map(len, mine)))
    try:
        for chunk in mine:
            run.make(run.plan(chunk))
        run.commit()
    finally:
        run.close()
    return BatchReport(_gather(run.outcomes), time.monotonic() - start)


def _rank_and_world(batch_size: int, rank: int | None, world: int | None) -> tuple[int, int]:
    """``batch_size`` checked; ``rank`` and ``world`` (the process group's where not given) checked."""
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise LasagnaError(f"expected a positive integer, got {batch_size!r}", "batch_size")
    group_rank, group_world = _process_group()
    rank = group_rank if rank is None else rank
    world = group_world if world is None else world
    if not 0 <= rank < world:
        raise LasagnaError(f"rank {rank} of world {world}; expected 0 <= rank < world", "rank")
    return rank, world


def _first_generator(request: EditRequest, catalogue_dirs, device) -> dict[Path, LoadedGenerator]:
    """The preset resolved and the condition checked before any work; the catalogue's amortised generator
    loaded once for the run where the request runs it (generator folder → loaded generator)."""
    first = cat.resolve(request.preset, None, catalogue_dirs, need_prior=False)
    first.preset.prompt_for(request.condition)
    generators: dict[Path, LoadedGenerator] = {}
    if choose_method(first, request.generator) == "amortised":
        generators[first.generator] = LoadedGenerator.read(amortised_generator(first), first.preset, device)
    return generators


class _Run:
    """One ``edit_many`` run: where each input goes, what it will record, the folders staged but not yet
    renamed into place, and every outcome."""

    def __init__(self, request, items, roots, names, out_dir, generators, catalogue_dirs, max_pixels, device):
        self.request, self.items, self.roots, self.out_dir = request, items, roots, out_dir
        self.generators, self.catalogue_dirs, self.max_pixels, self.device = (
            generators,
            catalogue_dirs,
            max_pixels,
            device,
        )
        self.force, self.ora, self.warn, self.depth = False, True, None, 8
        self.asked = request_record(request)
        self.labels = [os.fspath(x) if isinstance(x, (str, os.PathLike)) else n for x, n in zip(items, names)]
        self.outputs = [out_dir / name for name in names]
        self.resolved: dict[Path | None, cat.Resolved] = {}
        self.outcomes: list[Outcome] = []
        self.records: dict[int, dict[str, Any]] = {}  # what each output will record (BATCH_KEY)
        self.notes: dict[int, str | None] = {}  # why a complete output is redone
        self.staged: list[tuple[int, Path, float, str | None]] = []  # (index, temporary, start, note): not renamed
        self.shared = SharedFiles(out_dir)  # the generator's weights: written once, hard-linked into every folder
        self.since = time.monotonic()
        self.bar = None
        self.progress: Callable[[Outcome], None] | None = None

    def start_progress(self, progress: bool | Callable[[Outcome], None], rank: int, total: int) -> None:
        if progress is True and rank == 0:
            from tqdm.auto import tqdm

            desc = f"edit {self.request.preset}-{self.request.condition}"
            self.bar = tqdm(total=total, desc=desc, unit="image", leave=False)
        elif callable(progress):
            self.progress = progress

    def resolve(self, stack) -> cat.Resolved:
        """The preset, once per stack folder that might ship its own (``plan_edit``'s ``resolve``)."""
        key = stack.folder if stack.folder is not None and (stack.folder / "layers").is_dir() else None
        if key not in self.resolved:
            self.resolved[key] = cat.resolve(self.request.preset, key, self.catalogue_dirs, need_prior=False)
        return self.resolved[key]

    def report(self, outcome: Outcome) -> None:
        self.outcomes.append(outcome)
        if self.bar is not None:
            self.bar.update(1)
        elif self.progress is not None:
            self.progress(outcome)

    def failed(self, i: int, exc: BaseException, t0: float | None) -> None:
        label, seconds = self.labels[i], 0.0 if t0 is None else time.monotonic() - t0
        self.report(Outcome(i, label, str(self.outputs[i]), "failed", _describe(exc, label), seconds))

    def plan(self, chunk: list[int]) -> list[tuple[int, EditPlan, float]]:
        """Each input of ``chunk`` skipped (complete, its record matching), failed, or planned."""
        todo: list[tuple[int, EditPlan, float]] = []
        for i in chunk:
            item, out, t0 = self.items[i], self.outputs[i], time.monotonic()
            try:
                if isinstance(item, (str, os.PathLike)) and Path(item).resolve() == out.resolve():
                    raise PathError("is the input stack; expected an OUTDIR other than its folder", str(out))
                self.records[i] = {"source": source_or_none(item, self.roots[i]), "request": self.asked}
                if is_complete(out) and not self.force:
                    self.notes[i] = compare_record(read_record(out), self.records[i], out)
                    if self.notes[i] is None:
                        self.report(Outcome(i, self.labels[i], str(out), "skipped"))
                        continue
                kw = {"max_pixels": self.max_pixels, "catalogue_dirs": self.catalogue_dirs, "resolve": self.resolve}
                todo.append((i, plan_edit(item, self.request, **kw), t0))
            except Exception as exc:  # noqa: BLE001 - every input's failure is reported, the others go on
                self.failed(i, exc, t0)
        return todo

    def make(self, todo: list[tuple[int, EditPlan, float]]) -> None:
        """The planned layers made (one generator forward per group) and staged; committed every
        ``COMMIT_EVERY`` folders or ``COMMIT_SECONDS``."""
        initial = _forward(todo, self.generators, self.device)
        for i, plan, t0 in todo:
            try:
                gen, y = initial[i]
                if isinstance(y, Exception):
                    raise y
                run = make_layer(
                    plan.recipe, plan.conditioning, plan.layer_id, device=self.device, loaded=gen, initial=y
                )
                result = with_record(plan.finish(run, time.monotonic() - t0), self.records[i])
                force = self.force or i in self.notes
                with unsynced():  # made durable together by commit()
                    tmp = result.stage(
                        self.outputs[i], force=force, ora=self.ora, warn=self.warn, shared=self.shared, depth=self.depth
                    )
                    self.staged.append((i, tmp, t0, self.notes.get(i)))
            except Exception as exc:  # noqa: BLE001
                self.failed(i, exc, t0)
            if len(self.staged) >= COMMIT_EVERY or time.monotonic() - self.since >= COMMIT_SECONDS:
                self.commit()

    def commit(self) -> None:
        """One flush for every staged folder, then each renamed into place: complete, or not there at all."""
        if self.staged:
            sync_filesystem(self.out_dir)
        while self.staged:
            i, tmp, t0, note = self.staged.pop(0)
            out = self.outputs[i]
            try:
                swap_in(tmp, out, force=self.force or note is not None)  # a note: a stale output redone
                self.report(Outcome(i, self.labels[i], str(out), "done", None, time.monotonic() - t0, note))
            except Exception as exc:  # noqa: BLE001 - e.g. another writer filled the folder meanwhile
                shutil.rmtree(tmp, ignore_errors=True)
                self.failed(i, exc, None)
        self.since = time.monotonic()

    def close(self) -> None:
        """Interrupted: finished work not yet renamed in is dropped, nothing half-written."""
        for _, tmp, _, _ in self.staged:
            shutil.rmtree(tmp, ignore_errors=True)
        self.shared.close()
        if self.bar is not None:
            self.bar.close()


def _forward(todo, generators: dict[Path, LoadedGenerator], device) -> dict[int, tuple[Any, Any]]:
    """The amortised generator's outputs at the working size for the planned inputs of one chunk, one
    forward pass per (generator, label, shape) group: index → (loaded generator, (1, C, h, w)); (None, None)
    for a per-image plan or a surface; (None, the exception) for an input whose generator could not be loaded."""
    out: dict[int, tuple[Any, Any]] = {}
    groups: dict[tuple, list[tuple[int, torch.Tensor]]] = {}
    for i, plan, _ in todo:
        recipe = plan.recipe
        if recipe.method != "amortised" or recipe.kind == "surface":  # a surface is its estimator's (make_layer)
            out[i] = (None, None)
            continue
        gen_dir = recipe.generator
        try:
            if gen_dir not in generators:
                generators[gen_dir] = LoadedGenerator.read(gen_dir, recipe.preset, device)
            x = layer_input(recipe, plan.conditioning, device)
        except Exception as exc:  # noqa: BLE001 - reported as that input's failure
            out[i] = (None, exc)
            continue
        groups.setdefault((gen_dir, recipe.label, tuple(x.shape)), []).append((i, x))
    for (gen_dir, condition, _), members in groups.items():
        gen = generators[gen_dir]
        with torch.no_grad():
            y = gen.net(torch.cat([x for _, x in members]), [condition] * len(members)).float()  # (B, C, h, w)
        for k, (i, _) in enumerate(members):
            out[i] = (gen, y[k : k + 1])
    return out


__all__ = [
    "BATCH_KEY",
    "BatchReport",
    "IMAGE_SUFFIXES",
    "Outcome",
    "assign_names",
    "collect_inputs",
    "edit_many",
    "is_complete",
    "output_names",
    "read_record",
    "source_record",
]
