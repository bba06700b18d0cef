"""Edits at scale: one learned layer for many images, one stack folder per input, resumable and shardable.

    from lasagna.batch import edit_many
    report = edit_many(["photos/", "more/*.jpg"], "shading", "left", "out/", generator="amortised")
    print(report.summary())        # "edited 41, skipped 3 (complete), failed 1"
    report.failed                  # [Outcome(input='photos/bad.png', status='failed', error='…'), …]

**Inputs** (``collect_inputs``): a file, a stack folder (a folder holding stack.json, or its stack.json:
the layer goes on top of it, as ``edit`` does), a folder that is not a stack folder (its image files and
the stack folders directly inside it), or a glob pattern (``glob.glob(recursive=True)``: ``**`` crosses
folders; its matches filtered to image files and stack folders). A folder or pattern that finds nothing
is refused before any work. Path inputs are sorted and de-duplicated; in-memory images (tensors, arrays,
PIL images, ``Stack``) keep their order and come after them.

**Outputs**: ``out_dir/<name>/`` per input. Each stack folder records, in its stack.json's metadata
(``lasagna.batch``), the source it was made from — its path relative to its **batch root** (the folder
given, a pattern's fixed leading folder, a file's own folder), size and SHA-256 — and what was asked
(preset, condition and the settings that change the layer). Names are matched to sources, never to sort
positions (``assign_names``): an existing folder is claimed by the input whose path it records, so one
input keeps its folder across runs whatever is added beside it; the other inputs take their stem (a stack
folder's name), made unique in input order without regard to case (``a.png``, ``a.jpg`` → ``a``, ``a-2``)
and skipping every name already in ``out_dir`` (a folder of another source, or one without a record, is
never touched). In-memory images are ``image-1``, ``image-2``, … Each stack folder is written all or
nothing (``lasagna.io.folder``), so a folder that exists with its stack.json is **complete**: it is
skipped when its record matches (same source bytes, same request); redone in place when its source
changed (``Outcome.note`` says so); refused in one line when it was asked with other settings (a
different condition or layer: ``force`` redoes it, or use another ``out_dir``). ``force`` rewrites all. Finished
folders are staged (written into temporary siblings without fsync, ``lasagna.atomic.unsynced``) and
committed together: one file-system sync, then each renamed into place (``COMMIT_EVERY``). A killed run
leaves only hidden temporaries, swept when the next run starts (``lasagna.atomic.sweep_stale``): running
again finishes the rest, losing nothing complete and redoing nothing complete. Each input's failure is
caught and reported (``Outcome.error``, one line) and the others go on. A large file every folder carries
byte for byte (the generator's weights, 2 MB) is written once per run and hard-linked into each folder
(``lasagna.io.folder.SharedFiles``; copies where the file system takes no links): each folder stays whole
and self-contained.

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

import glob
import hashlib
import json
import os
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch

from lasagna import catalogue as cat
from lasagna.atomic import open_regular, sweep_stale, sync_filesystem, unsynced
from lasagna.components import LoadedGenerator
from lasagna.document import STACK_FILE
from lasagna.editing import EditPlan, plan_edit
from lasagna.errors import LasagnaError, PathError, printable
from lasagna.io.folder import SharedFiles, check_writable, swap_in
from lasagna.io.image import DEFAULT_EDIT_MAX_PIXELS
from lasagna.learned import choose_method, make_layer, working_input
from lasagna.recipe import EditRequest, amortised_generator

# The image files a folder or a glob contributes (``lasagna.io.image`` reads these; nothing else is opened).
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp", ".bmp", ".tif", ".tiff")

Status = Literal["done", "skipped", "failed"]

# Finished stack folders wait, written but not renamed into place, until this many are staged or this many
# seconds have passed; then one file-system sync makes them all durable and each is renamed in. The sync
# replaces seven fsyncs per stack folder (24 ms of a 64² edit's ~45 ms here); a kill loses at most the
# staged ones' work, never a complete output.
COMMIT_EVERY = 32
COMMIT_SECONDS = 2.0

# The stack.json metadata key of a batch output's record: its source and what was asked (module docstring).
BATCH_KEY = "lasagna.batch"


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


# ---- inputs and names -------------------------------------------------------------------------------


def _is_image(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES


def _is_stack(path: Path) -> bool:
    return path.is_dir() and (path / STACK_FILE).is_file()


def _found(paths, where: str, what: str) -> list[Path]:
    found = [p for p in paths if _is_image(p) or _is_stack(p)]
    if not found:
        raise PathError(f"{what} no image file or stack folder; expected at least one", where)
    return found


def collect_inputs(items: Sequence[Any] | Any) -> list[Any]:
    """The inputs ``items`` name (module docstring): paths sorted and de-duplicated, then in-memory images."""
    return _collect(items)[0]


def _pattern_root(pattern: str) -> Path:
    """A glob pattern's fixed leading folder: ``photos/**/*.png`` → ``photos``."""
    parts = Path(pattern).parts
    fixed = parts[: next(i for i, part in enumerate(parts) if glob.has_magic(part))]
    return Path(*fixed) if fixed else Path(".")


def _collect(items: Sequence[Any] | Any) -> tuple[list[Any], list[Path | None]]:
    """``collect_inputs``'s list, and each path input's batch root (module docstring; None for an image)."""
    if isinstance(items, (str, os.PathLike)) or not isinstance(items, Sequence):
        items = [items]
    paths: dict[str, tuple[Path, Path]] = {}
    images: list[Any] = []
    for item in items:
        if not isinstance(item, (str, os.PathLike)):
            images.append(item)
            continue
        text = os.fspath(item)
        p = Path(text)
        if p.exists() or os.path.lexists(p):
            listed = p.is_dir() and not _is_stack(p)
            found = _found(sorted(p.iterdir()), text, "holds") if listed else [p]
            root = p if listed else _folder_of(p).parent
        elif glob.has_magic(text):
            found = _found((Path(m) for m in sorted(glob.glob(text, recursive=True))), text, "matches")
            root = _pattern_root(text)
        else:
            found, root = [p], p.parent  # reported as missing, with the others written
        for f in found:
            paths.setdefault(os.path.normpath(os.path.abspath(f)), (f, root))
    keys = sorted(paths)
    return [paths[k][0] for k in keys] + images, [paths[k][1] for k in keys] + [None] * len(images)


def _folder_of(p: Path) -> Path:
    """A stack input's folder (``p`` itself for a folder or an image file's path)."""
    return p.parent if p.name == STACK_FILE else p


def _relative(item: Path, root: Path) -> str:
    """``item``'s path relative to its batch root, with '/' (what a record keeps)."""
    return Path(os.path.relpath(os.path.abspath(_folder_of(item)), os.path.abspath(root))).as_posix()


def source_record(item: Path, root: Path) -> dict[str, Any]:
    """What a batch output records of its source: path relative to the batch root, size and SHA-256 of the
    image file (of a stack folder's stack.json). Read through ``open_regular``: a FIFO is one line."""
    p = Path(item)
    file = p / STACK_FILE if p.is_dir() else p
    digest, size = hashlib.sha256(), 0
    with open_regular(file, str(p), expected="an image file or a stack folder") as fh:
        while chunk := fh.read(1 << 20):
            digest.update(chunk)
            size += len(chunk)
    return {"path": _relative(p, root), "size": size, "sha256": digest.hexdigest()}


def read_record(folder: Path) -> dict[str, Any] | None:
    """The batch record in ``folder``'s stack.json (``BATCH_KEY``), or None (none, or not readable)."""
    from lasagna.document.validation import parse_json, read_json_text

    try:
        doc = parse_json(read_json_text(folder / STACK_FILE, "stack.json"), str(folder / STACK_FILE))
    except (LasagnaError, OSError, RecursionError):
        return None
    meta = doc.get("metadata") if isinstance(doc, dict) else None
    record = meta.get(BATCH_KEY) if isinstance(meta, dict) else None
    return record if isinstance(record, dict) else None


def _recorded_path(record: dict[str, Any] | None) -> str | None:
    source = record.get("source") if record else None
    path = source.get("path") if isinstance(source, dict) else None
    return path if isinstance(path, str) else None


def assign_names(inputs: Sequence[Any], roots: Sequence[Path | None], out_dir: Path) -> list[str]:
    """One folder name per input, stable across runs (module docstring): each existing folder of ``out_dir``
    is claimed by the input whose path (relative to its root) it records — among several inputs of that
    path, the one whose bytes it records, else the first — then the others get ``output_names``' names,
    skipping every name already in ``out_dir`` (but empty folders)."""
    rels = {i: _relative(Path(x), r) for i, (x, r) in enumerate(zip(inputs, roots)) if r is not None}
    by_rel: dict[str, list[int]] = {}
    for i, rel in rels.items():
        by_rel.setdefault(rel, []).append(i)
    claimed: dict[int, str] = {}
    taken: set[str] = set()
    unsourced: dict[str, str] = {}  # casefolded name → folder made from an in-memory image (its record says so)
    entries = sorted(os.scandir(out_dir), key=lambda e: e.name) if out_dir.is_dir() else []
    for entry in entries:
        if entry.name.startswith("."):
            continue  # temporaries (swept) and hidden files are no one's output
        folder = Path(entry.path)
        if not (entry.is_dir(follow_symlinks=False) and not any(folder.iterdir())):
            taken.add(entry.name.casefold())  # a name in use: never given to another source
        record = read_record(folder) if entry.is_dir(follow_symlinks=False) else None
        if record is not None and record.get("source") is None:
            unsourced[entry.name.casefold()] = entry.name
        candidates = [i for i in by_rel.get(_recorded_path(record) or "", []) if i not in claimed]
        if len(candidates) > 1:  # one relative path under several roots: the bytes decide
            want = record["source"] if record else None
            same = [i for i in candidates if _same_source(inputs[i], roots[i], want)]
            candidates = same or candidates
        if candidates:
            claimed[candidates[0]] = entry.name
    positional = output_names(inputs)  # an in-memory image has only its position: image-<k>
    for i, root in enumerate(roots):
        if root is None and positional[i].casefold() in unsourced:
            claimed[i] = unsourced[positional[i].casefold()]
    return output_names(inputs, claimed=claimed, taken=taken)


def _same_source(item: Any, root: Path | None, want: Any) -> bool:
    try:
        return root is not None and source_record(Path(item), root) == want
    except (LasagnaError, OSError):
        return False


def output_names(
    inputs: Sequence[Any], *, claimed: dict[int, str] | None = None, taken: set[str] | None = None
) -> list[str]:
    """One folder name per input: a file's stem, a stack folder's name (a stack.json's folder's), else
    ``image-<k>``; made unique in order, case-insensitively, by ``-2``, ``-3``, … ``claimed``: inputs whose
    name is already decided (index → name); ``taken``: casefolded names no other input may get."""
    claimed = claimed or {}
    names: list[str] = []
    taken = set(taken or ()) | {name.casefold() for name in claimed.values()}
    width = len(str(len(inputs)))
    for k, item in enumerate(inputs):
        if k in claimed:
            names.append(claimed[k])
            continue
        if isinstance(item, (str, os.PathLike)):
            p = Path(item)
            stem = p.parent.resolve().name if p.name == STACK_FILE else (p.resolve().name if p.is_dir() else p.stem)
        else:
            stem = f"image-{k + 1:0{width}d}"
        stem = stem or "image"
        name, n = stem, 2
        while name.casefold() in taken:
            name, n = f"{stem}-{n}", n + 1
        taken.add(name.casefold())
        names.append(name)
    return names


def is_complete(folder: Path) -> bool:
    """A stack folder written by ``write_stack_folder`` (renamed into place when finished): it exists with
    its stack.json (and composite.png, written before the rename)."""
    return (folder / STACK_FILE).is_file() and (folder / "composite.png").is_file()


def shard(count: int, batch_size: int, rank: int, world: int) -> list[list[int]]:
    """The chunks of input indices rank ``rank`` of ``world`` takes: chunks of ``batch_size`` consecutive
    indices of ``range(count)``, chunk k to rank k mod world."""
    chunks = [list(range(i, min(i + batch_size, count))) for i in range(0, count, batch_size)]
    return chunks[rank::world]


# ---- the run ------------------------------------------------------------------------------------------


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
    if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
        raise LasagnaError(f"expected a positive integer, got {batch_size!r}", "batch_size")
    group_rank, group_world = _process_group()
    rank = group_rank if rank is None else rank
    world = group_world if world is None else world
    if not 0 <= rank < world:
        raise LasagnaError(f"rank {rank} of world {world}; expected 0 <= rank < world", "rank")
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
    preset, condition = request.preset, request.condition
    first = cat.resolve(preset, None, catalogue_dirs, need_prior=False)  # refusals before any work
    first.preset.prompt_for(condition)
    generators: dict[Path, LoadedGenerator] = {}
    if choose_method(first, request.generator) == "amortised":
        generators[first.generator] = LoadedGenerator.read(amortised_generator(first), first.preset, device)
    items, roots = _collect(inputs)
    out_dir = check_writable(out_dir, folder=True)
    out_dir.mkdir(parents=True, exist_ok=True)
    sweep_stale(out_dir)  # a killed run's temporaries (their owners are gone)
    names = assign_names(items, roots, out_dir)
    asked = _request(request)

    resolved: dict[Path | None, cat.Resolved] = {}

    def resolve(stack) -> cat.Resolved:  # once per stack folder that might ship its own preset
        key = stack.folder if stack.folder is not None and (stack.folder / "layers").is_dir() else None
        if key not in resolved:
            resolved[key] = cat.resolve(preset, key, catalogue_dirs, need_prior=False)
        return resolved[key]

    labels = [os.fspath(x) if isinstance(x, (str, os.PathLike)) else name for x, name in zip(items, names)]
    outputs = [out_dir / name for name in names]
    mine = shard(len(items), batch_size, rank, world)
    bar = None
    if progress is True and rank == 0:
        from tqdm.auto import tqdm

        bar = tqdm(total=sum(map(len, mine)), desc=f"edit {preset}-{condition}", unit="image", leave=False)
    outcomes: list[Outcome] = []
    records: dict[int, dict[str, Any]] = {}  # what each output will record (BATCH_KEY)
    notes: dict[int, str | None] = {}  # why a complete output is redone
    staged: list[tuple[int, Path, float, str | None]] = []  # (index, temporary folder, start, note): not renamed
    shared = SharedFiles(out_dir)  # the generator's weights: written once, hard-linked into every stack folder
    since = [time.monotonic()]

    def report(outcome: Outcome) -> None:
        outcomes.append(outcome)
        if bar is not None:
            bar.update(1)
        elif callable(progress):
            progress(outcome)

    def commit() -> None:
        """One flush for every staged folder, then each renamed into place: complete, or not there at all."""
        if staged:
            sync_filesystem(out_dir)
        while staged:
            i, tmp, t0, note = staged.pop(0)
            try:
                swap_in(tmp, outputs[i], force=force or note is not None)  # a note: a stale output redone
                report(Outcome(i, labels[i], str(outputs[i]), "done", None, time.monotonic() - t0, note))
            except Exception as exc:  # noqa: BLE001 - e.g. another writer filled the folder meanwhile
                shutil.rmtree(tmp, ignore_errors=True)
                report(Outcome(i, labels[i], str(outputs[i]), "failed", _describe(exc, labels[i]), 0.0))
        since[0] = time.monotonic()

    try:
        for chunk in mine:
            todo: list[tuple[int, EditPlan, float]] = []
            for i in chunk:
                item, label, out = items[i], labels[i], outputs[i]
                t0 = time.monotonic()
                try:
                    if isinstance(item, (str, os.PathLike)) and Path(item).resolve() == out.resolve():
                        raise PathError("is the input stack; expected an OUTDIR other than its folder", str(out))
                    records[i] = {"source": _source_or_none(item, roots[i]), "request": asked}
                    if is_complete(out) and not force:
                        notes[i] = _compare(read_record(out), records[i], out)
                        if notes[i] is None:
                            report(Outcome(i, label, str(out), "skipped"))
                            continue
                    plan = plan_edit(
                        item, request, max_pixels=max_pixels, catalogue_dirs=catalogue_dirs, resolve=resolve
                    )
                    todo.append((i, plan, t0))
                except Exception as exc:  # noqa: BLE001 - every input's failure is reported, the others go on
                    report(Outcome(i, label, str(out), "failed", _describe(exc, label), time.monotonic() - t0))
            initial = _forward(todo, generators, device)
            for i, plan, t0 in todo:
                label, out = labels[i], outputs[i]
                try:
                    gen, y = initial[i]
                    if isinstance(y, Exception):
                        raise y
                    run = make_layer(
                        plan.recipe, plan.conditioning, plan.layer_id, device=device, loaded=gen, initial=y
                    )
                    result = _recorded(plan.finish(run, time.monotonic() - t0), records[i])
                    with unsynced():  # made durable together by commit()
                        tmp = result.stage(out, force=force or i in notes, ora=ora, warn=warn, shared=shared)
                        staged.append((i, tmp, t0, notes.get(i)))
                except Exception as exc:  # noqa: BLE001
                    report(Outcome(i, label, str(out), "failed", _describe(exc, label), time.monotonic() - t0))
                if len(staged) >= COMMIT_EVERY or time.monotonic() - since[0] >= COMMIT_SECONDS:
                    commit()
        commit()
    finally:
        for _, tmp, _, _ in staged:  # interrupted: finished work not yet renamed in is dropped, nothing half-written
            shutil.rmtree(tmp, ignore_errors=True)
        shared.close()
        if bar is not None:
            bar.close()
    return BatchReport(_gather(outcomes), time.monotonic() - start)


def _request(request: EditRequest) -> dict[str, Any]:
    """What was asked, as an output records it: the preset, the condition and the settings that change the
    layer (those given), as JSON values."""
    r = request
    asked = {"preset": r.preset, "condition": r.condition, "on": r.on, "id": r.id, "generator": r.generator}
    asked.update(optimize=r.asked_steps, loss=r.loss, guidance=r.guidance, seed=r.seed, lr=r.lr)
    return json.loads(json.dumps({k: v for k, v in asked.items() if v is not None}))


def _source_or_none(item: Any, root: Path | None) -> dict[str, Any] | None:
    """``source_record`` of a path input; None for an in-memory image, or a path that cannot be read as a file
    (missing, a folder without stack.json: ``plan_edit`` says why, in its words). A FIFO, a device: refused."""
    if root is None:
        return None
    try:
        return source_record(Path(item), root)
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
        return None


def _compare(old: dict[str, Any] | None, new: dict[str, Any], out: Path) -> str | None:
    """Whether a complete output may be skipped (None), is to be redone (the reason, for ``Outcome.note``: its
    source changed), or is refused (a ``LasagnaError``: made with other settings, or not by a batch)."""
    if old is None:
        raise PathError(
            "holds a stack folder without a batch record (written by hand or by an older lasagna); expected a "
            "folder this batch wrote (--force to replace it, or another OUTDIR)",
            str(out),
        )
    before = old.get("request") if isinstance(old.get("request"), dict) else {}
    differ = [k for k in sorted(set(before) | set(new["request"])) if before.get(k) != new["request"].get(k)]
    if differ:

        def shown(value: Any) -> str:
            return "(default)" if value is None else repr(value)

        now = new["request"]
        was = ", ".join(f"{k} {shown(before.get(k))} (asked now: {shown(now.get(k))})" for k in differ)
        raise PathError(
            f"was made with {was}; expected the same request to resume (--force redoes it, or another OUTDIR)",
            str(out),
        )
    if old.get("source") != new["source"] and new["source"] is not None:
        return "redone: its source changed since this output was made"
    return None


def _recorded(result, record: dict[str, Any]):
    """``result`` with ``record`` in its stack.json's metadata (``BATCH_KEY``)."""
    doc = result.stack.document
    result.stack.document = doc.replace(metadata={**dict(doc.metadata), BATCH_KEY: record})
    return result


def _forward(todo, generators: dict[Path, LoadedGenerator], device) -> dict[int, tuple[Any, Any]]:
    """The amortised generator's outputs at the working size for the planned inputs of one chunk, one
    forward pass per (generator, label, shape) group: index → (loaded generator, (1, C, h, w)); (None, None)
    for a per-image plan; (None, the exception) for an input whose generator could not be loaded."""
    out: dict[int, tuple[Any, Any]] = {}
    groups: dict[tuple, list[tuple[int, torch.Tensor]]] = {}
    for i, plan, _ in todo:
        recipe = plan.recipe
        if recipe.method != "amortised":
            out[i] = (None, None)
            continue
        gen_dir = recipe.generator
        try:
            if gen_dir not in generators:
                generators[gen_dir] = LoadedGenerator.read(gen_dir, recipe.preset, device)
            x = working_input(plan.conditioning, recipe.working_size, device)
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
