"""One open stack in the editor: the document and its tensors, undo/redo, views, versioned saves and jobs.

An ``EditSession`` holds the stack folder's ``Stack`` in memory and changes it only through the engine's
own verbs (``Document.replace_layer``, ``Stack.add_layer``, ``lasagna.editing.plan_edit``, ``make_layer``,
``render_learned``, the exporters): the server is one more caller of the code the CLI runs, never a second
implementation of it.

* **Versions.** Every change of the document makes a new integer ``version``. A change names the version it
  was made against; any other is a ``ConflictError`` (HTTP 409): two tabs never overwrite each other's
  edits, the stale one is told and reloads.
* **Undo/redo.** A change pushes a ``Snapshot`` (document, tensor map, pending generator files) — tensors
  are never modified in place, so a snapshot costs a few dicts, not pixels.
* **Saves** go through ``lasagna.io.folder.save_in_place``: stack.json is the commit point, so a kill at any
  instant leaves the previous stack or the new one; a stack.json changed on disk by anyone else since it was
  read is a ``ConflictError`` and nothing is written.
* **Views** are composites at a power-of-two reduction ``level`` (0 = the canvas), each level with its own
  prefix-cache ``Renderer`` (``lasagna.compose.renderer``): toggling or dragging layer k recomputes from k up,
  at the size on screen. Layers are reduced once per level with an area filter and cached by tensor identity.
  Level 0 is exactly ``lasagna composite``; a reduced level is the composite of reduced layers (a preview:
  blends are not linear, so it differs slightly from a reduced composite).
* **Memory.** The session holds its budget (``--memory-budget`` when it opened; server and job threads do
  not inherit the CLI's scope) and accounts everything it holds against it (``held_bytes``: the stack, the
  undo/redo history, the views' reduced layers and cached canvases). Every render (views at any level,
  thumbnails, exports, saves) and every upload is admitted by ``_admit`` first: caches and then the oldest
  undo steps are let go, and what still does not fit is a ``BudgetError`` (HTTP 413, one line) before
  anything is allocated.
* **Jobs** (per-image refinement, re-rendering) run in one worker thread with a progress report and a
  cancel flag checked between steps (``make_layer``'s callback); the result lands as a new, undoable version.
"""

from __future__ import annotations

import contextlib
import io
import math
import threading
import time
import unicodedata
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from lasagna import catalogue as cat
from lasagna.atomic import atomic_write_bytes, temp_path
from lasagna.compose.layer import LayerTensors
from lasagna.compose.plan import plan_from_document, solid_tensors
from lasagna.compose.renderer import Renderer
from lasagna.document import Document, LearnedLayer
from lasagna.document.blend import BLEND_MODES, RANGED_BLENDS
from lasagna.document.types import unique_id
from lasagna.errors import ConflictError, DocumentError, ImageError, LasagnaError
from lasagna.heap import tune_heap
from lasagna.io.folder import save_in_place, stack_sha256
from lasagna.io.image import DEFAULT_EDIT_MAX_PIXELS, probe_image_file, read_image_file
from lasagna.io.render import BAND_ROWS, composite_codes, encode_composite, render_bytes, tensor_bytes
from lasagna.io.stack import Stack, group_mask_tensors, load_stack
from lasagna.limits import FLOAT_BYTES, BudgetError, format_size, memory_budget_scope, raster_bytes
from lasagna.limits import memory_budget as budget_in_force

MAX_UNDO = 100
"""Snapshots kept for undo: each holds references to tensors, so old pixels live while they can be undone."""
THUMB_SIDE = 96
"""Long side of a layer thumbnail in the layers panel, in pixels."""
LAYER_FIELDS = ("name", "visible", "opacity", "blend", "range", "offset", "mask", "condition", "settings")
"""Document fields a layer change may set (``mask`` only to null: a mask is removed, not painted; ``condition``
and ``settings`` of a learned layer, checked as ``lasagna render`` reads them, take effect when it is
re-rendered)."""
MAX_LEVEL = 6
"""Coarsest view: the canvas reduced 64×."""


class Cancelled(Exception):
    """Raised inside a job's per-step callback when its cancel button was pressed."""


@dataclass(frozen=True)
class Snapshot:
    """Everything a change replaces: undoing puts it back."""

    document: Document
    tensors: dict[str, Any]
    bit_depths: dict[str, int]
    files: dict[str, bytes]
    what: str


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


@dataclass
class _Level:
    renderer: Renderer
    key: tuple[Any, ...]


def _reduce(t: torch.Tensor | None, size: tuple[int, int]) -> torch.Tensor | None:
    if t is None:
        return None
    if tuple(t.shape[-2:]) == size:
        return t
    return F.interpolate(t.unsqueeze(0).float(), size=size, mode="area")[0].to(t.dtype)


def _reduced_side(n: int, level: int) -> int:
    return max(1, math.ceil(n / 2**level))


class EditSession:
    """The open stack (module docstring). Thread-safe: every method takes the session's lock."""

    def __init__(
        self,
        folder: str | Path,
        *,
        catalogue_dirs=None,
        device: str = "cpu",
        max_pixels: int = DEFAULT_EDIT_MAX_PIXELS,
        memory_budget: int | None = None,
    ):
        # Before any render: a long-lived server keeps glibc's adaptive maxima, not the compute profile's
        # up to 1 GiB of retained heap (lasagna/heap.py, the two profiles).
        tune_heap("server")
        self.folder = Path(folder)
        self.catalogue_dirs = catalogue_dirs
        self.device = device
        self.max_pixels = max_pixels
        self.budget = int(memory_budget) if memory_budget is not None else budget_in_force()
        self.lock = threading.RLock()
        self._load()

    # ---- state ---------------------------------------------------------------------------------------

    def _load(self) -> None:
        self.disk_sha = stack_sha256(self.folder)
        self.stack = load_stack(self.folder)
        self.files: dict[str, bytes] = {}
        self.unchanged: dict[str, object] = dict(self.stack.tensors)  # what the PNGs on disk hold
        self.version = 1
        self.saved_version = 1
        self.undo_stack: list[Snapshot] = []
        self.redo_stack: list[Snapshot] = []
        self.levels: dict[int, _Level] = {}
        self.reduced: dict[tuple[str, int], tuple[object, LayerTensors]] = {}
        self.thumbs: dict[str, tuple[object, Any, bytes]] = {}
        self.job: Job | None = None
        self.jobs: dict[str, Job] = {}

    @contextlib.contextmanager
    def _guard(self):
        """The session's lock, under the session's memory budget: the engine's own checks (decoding, rendering)
        then measure against the budget the editor was opened with, in whatever thread runs the request."""
        with self.lock, memory_budget_scope(self.budget):
            yield

    # ---- memory ----------------------------------------------------------------------------------------

    def held_bytes(self) -> int:
        """Bytes the session holds: every tensor of the stack, of the undo/redo history, of the files on disk
        (``unchanged``) and of the views' reduced layers (each storage once: snapshots share unchanged
        tensors), the views' cached canvases, and the pending generator files."""
        with self.lock:
            maps = [self.stack.tensors, self.unchanged, *(s.tensors for s in (*self.undo_stack, *self.redo_stack))]
            tensors = [x for m in maps for lt in m.values() for x in lt.tensors()]
            tensors += [x for _, lt in self.reduced.values() for x in lt.tensors()]
            held = tensor_bytes(tensors)
            for lv in self.levels.values():
                w, h = lv.key[:2]
                held += lv.renderer.cached_bytes + render_bytes(w, h)  # its snapshots and its last image
            files = {id(b): len(b) for f in (self.files, *(s.files for s in self.undo_stack)) for b in f.values()}
            return held + sum(files.values())

    def _evict(self, extra: int = 0) -> None:
        """Let go of what the session holds beyond the document until ``extra`` more bytes fit the budget:
        first the views' caches, then undo steps, oldest first, then redo steps."""
        if self.held_bytes() + extra <= self.budget:
            return
        self.levels.clear()
        self.reduced.clear()
        self.thumbs.clear()
        for history in (self.undo_stack, self.redo_stack):
            while history and self.held_bytes() + extra > self.budget:
                history.pop(0)

    def _admit(self, extra: int, what: str, where: str) -> None:
        """Refuse (``BudgetError``, one line) work that would allocate ``extra`` bytes beyond what the session
        holds when the two together exceed the budget even after ``_evict``; every render and upload asks."""
        with self.lock:
            if self.held_bytes() + extra <= self.budget:
                return
            self._evict(extra)
            held = self.held_bytes()
            if held + extra > self.budget:
                raise BudgetError(
                    f"{what} needs ~{format_size(extra)} beside the ~{format_size(held)} the editor holds (the open "
                    f"stack), over the memory budget of {format_size(self.budget)}; expected a coarser view, a "
                    "smaller image or fewer layers, or a larger --memory-budget",
                    where,
                )

    def reload(self) -> dict[str, Any]:
        """Read the folder again, dropping unsaved changes and history (after a save conflict)."""
        with self._guard():
            self._check_idle("reload")
            self._load()
            self.version = int(time.time() * 1000) % 10**9  # never a version an old tab could still hold
            self.saved_version = self.version
            return self.state()

    def _snapshot(self, what: str) -> Snapshot:
        s = self.stack
        return Snapshot(s.document, dict(s.tensors), dict(s.bit_depths), dict(self.files), what)

    def _restore(self, snap: Snapshot) -> None:
        self.stack = Stack(snap.document, self.stack.folder, dict(snap.tensors), dict(snap.bit_depths))
        self.files = dict(snap.files)

    def _check_version(self, version: Any) -> None:
        if isinstance(version, bool) or not isinstance(version, int):
            raise LasagnaError(f"expected the integer version the change was made against, got {version!r}", "version")
        if version != self.version:
            raise ConflictError(
                f"the stack is at version {self.version}, the change was made against {version} (another tab "
                "changed it); expected the current version: reload",
                "version",
            )

    def _check_idle(self, what: str) -> None:
        if self.job is not None and self.job.state == "running":
            raise ConflictError(f"a {self.job.what} job is running; expected it to finish or be cancelled", what)

    def _change(self, version: Any, what: str, apply) -> dict[str, Any]:
        """Check ``version``, apply ``apply()`` (which changes ``self.stack``), push the undo snapshot."""
        with self._guard():
            self._check_version(version)
            self._check_idle(what)
            before = self._snapshot(what)
            try:
                apply()
            except BaseException:
                self._restore(before)
                raise
            self._push(before)
            return self.state()

    def _push(self, before: Snapshot) -> None:
        """A change is made: ``before`` goes on the undo stack, the redo stack is cleared, a new version."""
        self.undo_stack.append(before)
        del self.undo_stack[:-MAX_UNDO]
        self.redo_stack.clear()
        self.version += 1
        self._evict()  # history beyond the budget goes (the change itself was admitted)

    def state(self) -> dict[str, Any]:
        """The document, version, history and job as the page needs them (JSON data)."""
        with self._guard():
            doc = self.stack.document
            return {
                "version": self.version,
                "saved_version": self.saved_version,
                "dirty": self.version != self.saved_version,
                "folder": self.folder.name,
                "document": doc.to_dict(),
                "not_rendered": self.stack.not_rendered,
                "undo": self.undo_stack[-1].what if self.undo_stack else None,
                "redo": self.redo_stack[-1].what if self.redo_stack else None,
                "job": self.job.report() if self.job is not None else None,
                "levels": self.max_level() + 1,
                "blends": list(BLEND_MODES),
                "ranged_blends": sorted(RANGED_BLENDS),
            }

    # ---- document changes ---------------------------------------------------------------------------

    def set_layer(self, version: Any, id: str, changes: dict[str, Any]) -> dict[str, Any]:
        """Change document fields of layer ``id`` (``LAYER_FIELDS``); a range change keeps the stored values."""
        if not isinstance(changes, dict) or not changes:
            raise LasagnaError("expected an object of layer fields to change", "changes")
        unknown = sorted(set(changes) - set(LAYER_FIELDS))
        if unknown:
            raise LasagnaError(
                f"cannot set {', '.join(unknown)}; expected some of {', '.join(LAYER_FIELDS)}", "changes"
            )
        if "mask" in changes and changes["mask"] is not None:
            raise LasagnaError("a mask can only be removed here (null); expected null", "changes.mask")

        def apply() -> None:
            from lasagna.learned import LayerSettings

            s = self.stack
            layer = s.document.layer(id)
            s.document = s.document.replace_layer(id, **changes)
            if "settings" in changes:
                LayerSettings.parse(s.document.layer(id).settings, f"layer {id!r}.settings")
            t = s.tensors.get(id)
            new = s.document.layer(id)
            if t is not None and tuple(new.range) != tuple(layer.range):
                (lo, hi), (nlo, nhi) = tuple(layer.range), tuple(new.range)
                # The same stored codes v = (y - lo)/(hi - lo): both ranges passed the document's range rule
                # (spans normal and finite in float32), so v and the new values are finite.
                color = nlo + (nhi - nlo) * ((t.color - lo) / (hi - lo))
                if not bool(torch.isfinite(color).all()):
                    raise DocumentError(
                        f"re-encoding [{lo:g}, {hi:g}] as [{nlo:g}, {nhi:g}] gives values that are not finite; "
                        "expected a range whose values float32 holds",
                        f"layer {id!r}.range",
                    )
                s.tensors[id] = LayerTensors(color, t.alpha, t.mask)
            if "mask" in changes and t is not None and t.mask is not None:
                s.tensors[id] = LayerTensors(s.tensors[id].color, s.tensors[id].alpha, None)

        what = ", ".join(sorted(changes))
        return self._change(version, f"{what} of {id}", apply)

    def move_layer(self, version: Any, id: str, index: Any) -> dict[str, Any]:
        """Move layer ``id`` to position ``index`` (0 = bottom) of the list it is in (top level, or its group)."""
        if isinstance(index, bool) or not isinstance(index, int):
            raise LasagnaError(f"expected an integer position, got {index!r}", "index")

        def apply() -> None:
            self.stack.document = self.stack.document.moved_layer(id, index)

        return self._change(version, f"move {id}", apply)

    def delete_layer(self, version: Any, id: str) -> dict[str, Any]:
        """Delete layer ``id`` (at any depth; a group with its layers)."""
        if [layer.id for layer in self.stack.document.layers] == [id]:
            raise DocumentError("it is the only layer; expected a stack to keep at least one", f"layer {id!r}")
        return self._change(version, f"delete {id}", lambda: self.stack.remove_layer(id))

    def group_layers(self, version: Any, ids: Any, name: Any = None) -> dict[str, Any]:
        """Wrap the layers ``ids`` (siblings, at any depth) into a new pass-through group at their place."""
        if not isinstance(ids, list) or not ids or not all(isinstance(i, str) for i in ids):
            raise LasagnaError(f"expected a list of layer ids to group, got {ids!r}", "ids")
        name = name if isinstance(name, str) and name.strip() else "Group"
        with self._guard():
            gid = self._new_id(name.lower())

            def apply() -> None:
                self.stack.document = self.stack.document.grouped(ids, {"id": gid, "name": name})

            return self._change(version, f"group {', '.join(ids)}", apply)

    def ungroup(self, version: Any, id: Any) -> dict[str, Any]:
        """Replace group ``id`` by its layers, in place (``Document.ungrouped``)."""

        def apply() -> None:
            self.stack.document = self.stack.document.ungrouped(id)

        return self._change(version, f"ungroup {id}", apply)

    def _new_id(self, wanted: str) -> str:
        """An id for a new layer from its display name (free text: ``café``, ``写真``, ``Ébauche``): accents
        folded to ASCII first (``cafe``), then ``unique_id`` (what an id cannot hold becomes ``-``)."""
        folded = unicodedata.normalize("NFKD", wanted).encode("ascii", "ignore").decode("ascii")
        return unique_id(folded, {i.casefold() for i in self.stack.document.all_ids})

    def add_solid(self, version: Any, color: Any, name: Any = None, blend: Any = "normal") -> dict[str, Any]:
        if not isinstance(color, list) or len(color) not in (3, 4):
            raise LasagnaError(f"expected RGB or RGBA in [0, 1], got {color!r}", "color")
        name = name if isinstance(name, str) and name.strip() else "Solid"
        id = self._new_id(name.lower())
        return self._change(
            version, f"add {id}", lambda: self.stack.add_solid(id, [float(c) for c in color], name=name, blend=blend)
        )

    def add_image(self, version: Any, data: bytes, name: Any = None) -> dict[str, Any]:
        """A new pixels layer on top from an uploaded image file's bytes, read under the CLI's input policy."""
        name = name if isinstance(name, str) and name.strip() else "Image"
        stem = Path(name).stem or "image"
        with self._guard():
            self._check_version(version)
            tmp = temp_path(self.folder / "upload", suffix=Path(name).suffix.lower()[:8])
            try:
                atomic_write_bytes(tmp, data)
                w, h = probe_image_file(tmp, max_pixels=self.max_pixels)
                # Its float32 RGBA tensors, kept, and half as much again for the decoder's codes while reading.
                self._admit(raster_bytes(w, h, 4) * 3 // 2, f"the {w}x{h} upload", f"upload {name!r}")
                img = read_image_file(tmp, max_pixels=self.max_pixels)
            except (ImageError, BudgetError) as exc:
                raise exc.at(f"upload {name!r}") from None
            finally:
                tmp.unlink(missing_ok=True)
            id = self._new_id(stem.lower())
            color = torch.from_numpy(img.color)
            alpha = torch.from_numpy(img.alpha) if img.alpha is not None else None
            return self._change(
                version,
                f"add {id}",
                lambda: self.stack.add_layer(id, color, alpha=alpha, bit_depth=img.bit_depth, name=stem),
            )

    def add_learned(
        self, version: Any, preset: Any, condition: Any, on: Any = None, method: Any = "amortised"
    ) -> dict[str, Any]:
        """A learned layer of catalogue preset ``preset`` for ``condition`` on top, by ``lasagna edit``'s recipe
        (``lasagna.editing.plan_edit``). ``amortised``: made now (one forward pass). ``per-image``: added without
        pixels, its settings saying how to make it, for a ``rerender`` job to make with progress."""
        from lasagna.editing import layer_fields, plan_edit
        from lasagna.learned import make_layer
        from lasagna.recipe import EditRequest

        if not isinstance(preset, str) or not isinstance(condition, str):
            raise LasagnaError("expected a preset name and a condition", "preset")
        with self._guard():
            self._check_version(version)
            self._check_idle("add learned layer")
            start = time.monotonic()
            request = EditRequest(preset=preset, condition=condition, on=on, generator=method)
            plan = plan_edit(self.stack, request, catalogue_dirs=self.catalogue_dirs)
            if plan.recipe.method == "per-image":
                fields = {
                    **layer_fields(plan.layer_id, plan.recipe, plan.on),
                    "settings": plan.recipe.pending_settings(),
                }
                return self._change(
                    version,
                    f"add {plan.layer_id}",
                    lambda: setattr(self.stack, "document", self.stack.document.with_layer(fields)),
                )
            run = make_layer(plan.recipe, plan.conditioning, plan.layer_id, device=self.device)
            result = plan.finish(run, time.monotonic() - start)

            def apply() -> None:
                # The other layers keep their tensor objects (as_stored left their values as they were), so the
                # view cache and the save's "unchanged" map still recognise them.
                tensors = {
                    id: self.stack.tensors.get(id, t) if id != result.layer_id else t
                    for id, t in result.stack.tensors.items()
                }
                self.stack = Stack(result.stack.document, self.folder, tensors, result.stack.bit_depths)
                self.files.update(run.files)

            return self._change(version, f"add {result.layer_id}", apply)

    def undo(self, version: Any) -> dict[str, Any]:
        return self._step(version, self.undo_stack, self.redo_stack, "undo")

    def redo(self, version: Any) -> dict[str, Any]:
        return self._step(version, self.redo_stack, self.undo_stack, "redo")

    def _step(self, version: Any, source: list[Snapshot], target: list[Snapshot], what: str) -> dict[str, Any]:
        with self._guard():
            self._check_version(version)
            self._check_idle(what)
            if not source:
                raise LasagnaError(f"nothing to {what}; expected a change first", what)
            snap = source.pop()
            target.append(self._snapshot(snap.what))
            self._restore(snap)
            self.version += 1
            return self.state()

    # ---- saving and exporting -----------------------------------------------------------------------

    def save(self, version: Any) -> dict[str, Any]:
        """Write the stack into its folder (``save_in_place``); ``ConflictError`` if the tab is stale or the
        folder's stack.json changed since it was read."""
        from lasagna.export.ora import encode_ora

        def extra(stack: Stack, result) -> dict[str, bytes]:
            if (self.folder / "stack.ora").is_file():  # a `lasagna edit` folder keeps its OpenRaster current
                return {"stack.ora": encode_ora(stack, composite=result.image)}
            return {}

        with self._guard():
            self._check_version(version)
            self._check_idle("save")
            self._admit(self._render_bytes(encode_layers=True), f"saving {self.folder.name}", "save")
            self.disk_sha, self.unchanged = save_in_place(
                self.stack, unchanged=self.unchanged, files=self.files, expect_sha256=self.disk_sha, extra=extra
            )
            self.files = {}
            self.saved_version = self.version
            return self.state()

    def export(self, kind: str) -> tuple[bytes, str, str]:
        """(bytes, file name, media type) of the current stack as ``ora``, ``psd`` or ``png`` (the composite)."""
        if kind not in ("ora", "psd", "png"):
            raise LasagnaError(f"unknown export {kind!r}; expected ora, psd or png", "export")
        with self._guard():
            self._admit(self._render_bytes(encode_layers=kind != "png"), f"the {kind} export", f"export {kind}")
            stack = Stack(self.stack.document, self.folder, dict(self.stack.tensors), dict(self.stack.bit_depths))
        with memory_budget_scope(self.budget):
            return self._encode_export(stack, kind)

    def _encode_export(self, stack: Stack, kind: str) -> tuple[bytes, str, str]:
        result = stack.render()
        name = self.folder.name
        if kind == "ora":
            from lasagna.export.ora import encode_ora

            return encode_ora(stack, composite=result.image), f"{name}.ora", "image/openraster"
        if kind == "psd":
            from lasagna.export.psd import encode_psd

            return encode_psd(stack, composite=result.image), f"{name}.psd", "image/vnd.adobe.photoshop"
        return encode_composite(result), f"{name}.png", "image/png"

    def _render_bytes(self, *, encode_layers: bool) -> int:
        """What a full-size render of the stack allocates (``render_stack``'s output canvas) and, with
        ``encode_layers`` (saves, ORA and PSD), a layer's stored codes while it is encoded: float64 values and
        codes of the largest layer, four times its float32 tensors."""
        need = render_bytes(self.stack.width, self.stack.height)
        if encode_layers:
            need += 4 * max((tensor_bytes(lt.tensors()) for lt in self.stack.tensors.values()), default=0)
        return need

    # ---- views ----------------------------------------------------------------------------------------

    def max_level(self) -> int:
        side = max(self.stack.width, self.stack.height)
        return max(0, min(MAX_LEVEL, int(math.floor(math.log2(side))) - 4)) if side > 16 else 0

    def _level_tensors(self, doc: Document, level: int) -> dict[str, LayerTensors]:
        """Every layer's tensors reduced by 2**level (cached by the source tensors' identity)."""
        out: dict[str, LayerTensors] = {}
        for _, layer in doc.walk():  # groups' children too
            t = self._layer_at(layer, level)
            if t is not None:
                out[layer.id] = t
        return out

    def _layer_at(self, layer, level: int) -> LayerTensors | None:
        """Layer ``layer``'s tensors reduced by 2**level (None for a layer without pixels): a solid's are
        zero-stride views of its size at that level, a group's hold its mask (``group_mask_tensors``)."""
        if layer.kind == "solid":
            lo, hi = tuple(layer.range)
            w, h = (
                (layer.size.width, layer.size.height)
                if layer.size is not None
                else (self.stack.width, self.stack.height)
            )
            key = (layer.id, level)
            stamp = (tuple(layer.color), w, h, lo, hi)
            hit = self.reduced.get(key)
            if hit is None or hit[0] != stamp:
                rw, rh = _reduced_side(w, level), _reduced_side(h, level)
                shape = type("Solid", (), {"color": layer.color, "size": None})()  # its size is the one given
                hit = (stamp, solid_tensors(shape, lo, hi, rw, rh, layer.id))
                self.reduced[key] = hit
            return hit[1]
        t = self.stack.tensors.get(layer.id)  # a group's tensors hold only its mask
        if t is None or level == 0:
            return t
        key = (layer.id, level)
        hit = self.reduced.get(key)
        if hit is None or hit[0] is not t:
            if layer.kind == "group":
                size = (_reduced_side(t.mask.shape[-2], level), _reduced_side(t.mask.shape[-1], level))
                hit = (t, group_mask_tensors(_reduce(t.mask, size)))
            else:
                size = (_reduced_side(t.color.shape[-2], level), _reduced_side(t.color.shape[-1], level))
                hit = (t, LayerTensors(_reduce(t.color, size), _reduce(t.alpha, size), _reduce(t.mask, size)))
            self.reduced[key] = hit
        return hit[1]

    def _reduction_bytes(self, layers, level: int) -> int:
        """Bytes ``_layer_at`` would allocate for ``layers`` at ``level`` (reductions not cached yet; a solid's
        and level 0's cost nothing)."""
        need = 0
        for layer in layers:
            t = self.stack.tensors.get(layer.id)
            if level == 0 or layer.kind == "solid" or t is None:
                continue
            hit = self.reduced.get((layer.id, level))
            if hit is not None and hit[0] is t:
                continue
            for x in t.tensors():
                if x is not None and x.stride(-1) != 0:  # a zero-stride view (a group's ones) is reduced to one
                    rows, cols = _reduced_side(x.shape[-2], level), _reduced_side(x.shape[-1], level)
                    need += x.shape[0] * rows * cols * FLOAT_BYTES
        return need

    def view(
        self,
        level: int = 0,
        *,
        opacity: dict[str, float] | None = None,
        solo: str | None = None,
        upto: str | None = None,
    ) -> tuple[bytes, int, int]:
        """The composite at reduction ``level`` as RGBA8 bytes (row-major), with transient overrides that are
        not changes (``opacity`` while a slider is dragged; ``solo`` one layer alone; ``upto`` a layer: the
        stack up to and including it, the "before" of a before/after split). Layers are named at any depth:
        a soloed layer inside a group shows with the groups that hold it."""
        if isinstance(level, bool) or not isinstance(level, int) or not 0 <= level <= self.max_level():
            raise LasagnaError(f"expected a level in [0, {self.max_level()}], got {level!r}", "level")
        with self._guard():
            doc = self.stack.document
            for id in [*(opacity or {}), *([solo] if solo else []), *([upto] if upto else [])]:
                doc.layer(id)  # DocumentError naming the ids
            for id, v in (opacity or {}).items():
                if not (isinstance(v, (int, float)) and 0.0 <= float(v) <= 1.0):
                    raise LasagnaError(f"expected an opacity in [0, 1], got {v!r}", f"opacity.{id}")
            layers = _overridden(doc, opacity or {}, solo, upto)
            w, h = _reduced_side(self.stack.width, level), _reduced_side(self.stack.height, level)
            # The layers reduced to this level, the canvas and the renderer's snapshot below the top layer
            # (``lasagna.compose.renderer``), and the RGBA8 bytes returned.
            need = self._reduction_bytes([layer for _, layer in doc.walk()], level) + 2 * render_bytes(w, h) + 4 * w * h
            self._admit(need, f"the {w}x{h} view (level {level})", "view")
            tensors = self._level_tensors(doc, level)
            f = 2**level
            specs = plan_from_document(_Scaled(doc, layers, w, h, f), tensors, cull=True, dtype=torch.float32).layers
            key = (w, h, tuple(doc.canvas.background), doc.blend_space, doc.clamp)
            lv = self.levels.get(level)
            if lv is None or lv.key != key:
                lv = _Level(Renderer((h, w), tuple(doc.canvas.background), doc.blend_space, doc.clamp), key)
                self.levels[level] = lv
            image = lv.renderer.render(specs).image
            rgba = np.empty((h, w, 4), np.uint8)
            rgba[..., 3] = 255
            for y in range(0, h, BAND_ROWS):  # a band at a time: no canvas-sized float64 copy
                band = image[:, y : y + BAND_ROWS]
                codes = composite_codes(band) if level == 0 else (band.clamp(0.0, 1.0) * 255.0).round().to(torch.uint8)
                rgba[y : y + BAND_ROWS, :, :3] = codes.permute(1, 2, 0).numpy()
            return rgba.tobytes(), w, h

    def thumbnail(self, id: str) -> bytes:
        """A small PNG of layer ``id``'s stored values (RGB codes v and alpha), as the layers panel shows it,
        made from the layer reduced to about twice the thumbnail's side (a reduced view level's tensors)."""
        from PIL import Image

        with self._guard():
            layer = self.stack.document.layer(id)
            side = max(self.stack.width, self.stack.height)
            level = max(0, int(math.log2(max(1, side // (2 * THUMB_SIDE)))))
            need = self._reduction_bytes([layer], level) + 8 * 4 * THUMB_SIDE * THUMB_SIDE
            self._admit(need, f"the thumbnail of {id}", f"layer {id!r}")
            t = self._layer_at(layer, level)
            rng = tuple(layer.range) if layer.kind != "group" else (0.0, 1.0)  # a group's tensors: its mask
        if t is None:  # a learned layer not rendered yet
            rgba = np.zeros((8, 8, 4), np.uint8)
        else:
            hit = self.thumbs.get(id)
            if hit is not None and hit[0] is t and hit[1] == rng:
                return hit[2]
            lo, hi = rng
            h, w = t.color.shape[-2:]
            s = min(1.0, THUMB_SIDE / max(h, w))
            size = (max(1, round(h * s)), max(1, round(w * s)))
            # Reduced first, then mapped to codes: the map is linear, so the area average commutes with it.
            color = ((_reduce(t.color, size) - lo) / (hi - lo)).clamp(0, 1).expand(3, *size)
            alpha = _reduce(t.alpha, size) if t.alpha is not None else torch.ones(1, *size)
            rgba = (torch.cat([color, alpha.clamp(0, 1)]) * 255).round().to(torch.uint8).permute(1, 2, 0).numpy()
        buf = io.BytesIO()
        Image.fromarray(np.ascontiguousarray(rgba), "RGBA").save(buf, "PNG")
        data = buf.getvalue()
        if t is not None:
            self.thumbs[id] = (t, rng, data)
        return data

    # ---- the catalogue --------------------------------------------------------------------------------

    def presets(self) -> list[dict[str, Any]]:
        """Every preset of the catalogue: ready or why not, its vocabulary, blend and description."""
        out = []
        for name in cat.available("preset", self.catalogue_dirs)["preset"]:
            status = cat.preset_status(name, self.catalogue_dirs)
            entry: dict[str, Any] = {"name": name, "ready": bool(status["usable"]), "why": status["why"]}
            entry.update(method=status.get("method"), amortised=bool(status.get("amortised")))
            try:
                p = cat.load_preset(name, self.folder, self.catalogue_dirs)
                entry.update(
                    vocabulary=list(p.vocabulary), blend=p.blend, description=p.description, channels=p.channels
                )
            except LasagnaError as exc:
                entry.update(ready=False, why=str(exc))
            out.append(entry)
        return out

    # ---- jobs -----------------------------------------------------------------------------------------

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


def _overridden(doc: Document, opacity: dict[str, float], solo: str | None, upto: str | None) -> list:
    """``doc``'s layer tree with a view's transient overrides (``EditSession.view``), layers named at any depth:
    ``opacity`` per layer; ``solo``: that layer (with what it holds) alone, the groups holding it shown;
    ``upto``: every layer after it in the tree's order (depth first, a group before its layers) hidden,
    except its own layers."""
    order = [layer.id for _, layer in doc.walk()]
    inside: dict[str, set[str]] = {}  # group id → ids of every layer it holds, at any depth
    holders: dict[str, list[str]] = {}  # layer id → ids of the groups holding it, outermost first

    def index(layers, path: list[str]) -> None:
        for layer in layers:
            holders[layer.id] = list(path)
            for g in path:
                inside.setdefault(g, set()).add(layer.id)
            if layer.kind == "group":
                inside.setdefault(layer.id, set())
                index(layer.layers, [*path, layer.id])

    index(doc.layers, [])
    shown: set[str] | None = None
    if solo is not None:
        shown = {solo, *holders[solo], *inside.get(solo, ())}
    hidden: set[str] = set()
    if upto is not None:
        after = order[order.index(upto) + 1 :]
        hidden = set(after) - inside.get(upto, set())

    def visit(layers) -> list:
        out = []
        for layer in layers:
            changes: dict[str, Any] = {}
            if layer.id in opacity:
                changes["opacity"] = float(opacity[layer.id])
            if shown is not None and layer.id == solo:
                changes["visible"] = True
            elif shown is not None and layer.id not in shown:
                changes["visible"] = False
            if layer.id in hidden:
                changes["visible"] = False
            if layer.kind == "group":
                changes["layers"] = tuple(visit(layer.layers))
            out.append(layer.model_copy(update=changes) if changes else layer)
        return out

    return visit(doc.layers)


class _Scaled:
    """A document seen at a reduced view level: the canvas, offsets and solid sizes divided by ``f``, and the
    layer list with transient overrides (read through attributes only, as ``plan_from_document`` does)."""

    def __init__(self, doc: Document, layers, w: int, h: int, f: int):
        self.canvas = type("Canvas", (), {"width": w, "height": h, "background": doc.canvas.background})()
        self.blend_space = doc.blend_space
        self.clamp = doc.clamp
        self.layers = [_ScaledLayer(layer, f) for layer in layers] if f > 1 else layers


class _ScaledLayer:
    """A layer whose offset is divided by ``f`` (its other attributes are the layer's; a group's children
    are scaled too)."""

    def __init__(self, layer, f: int):
        self._layer = layer
        self.offset = type("Offset", (), {"x": layer.offset.x // f, "y": layer.offset.y // f})()
        if layer.kind == "group":
            self.layers = [_ScaledLayer(child, f) for child in layer.layers]

    def __getattr__(self, name: str) -> Any:
        return getattr(self._layer, name)


def _unsaved_generator(stack: Stack, layer: LearnedLayer) -> bool:
    """Whether ``layer`` was made by a generator whose copy is not in the stack folder yet (added, unsaved)."""
    if layer.generator is None or stack.folder is None:
        return False
    return not (Path(stack.folder) / layer.generator.checkpoint).is_file()


__all__ = ["Cancelled", "EditSession", "Job", "Snapshot"]
