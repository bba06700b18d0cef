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
* **Memory.** The session holds its budget (``--memory-budget`` when it opened; server and job threads do
  not inherit the CLI's scope) and accounts everything it holds against it (``held_bytes``: the stack, the
  undo/redo history, the views' reduced layers and cached canvases). Every render (views at any level,
  thumbnails, exports, saves) and every upload is admitted by ``_admit`` first: caches and then the oldest
  undo steps are let go, and what still does not fit is a ``BudgetError`` (HTTP 413, one line) before
  anything is allocated.
* **Views** (composites at zoom levels, thumbnails, exports) are ``lasagna.serve.views``; **jobs** (per-image
  refinement, re-rendering: start, progress, cancel) are ``lasagna.serve.jobs``. Both are parts of ``EditSession``
  and work through its lock, budget and versions.
"""

from __future__ import annotations

import contextlib
import threading
import time
import unicodedata
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from lasagna import catalogue as cat
from lasagna.atomic import atomic_write_bytes, temp_path
from lasagna.compose.layer import LayerTensors
from lasagna.compose.surface import memo_tensors
from lasagna.document import Document
from lasagna.document.blend import BLEND_MODES, RANGED_BLENDS
from lasagna.document.condition import parse_direction, parse_point, point_direction
from lasagna.document.types import unique_id
from lasagna.errors import ConflictError, DocumentError, ImageError, LasagnaError
from lasagna.heap import tune_heap
from lasagna.io.folder import save_in_place, stack_sha256
from lasagna.io.image import DEFAULT_EDIT_MAX_PIXELS, probe_image_file, read_image_file
from lasagna.io.render import render_bytes, tensor_bytes
from lasagna.io.stack import Stack, load_stack
from lasagna.limits import BudgetError, format_size, memory_budget_scope, raster_bytes
from lasagna.limits import memory_budget as budget_in_force
from lasagna.serve.jobs import Cancelled, Job, SessionJobs
from lasagna.serve.views import SessionViews, _Level

MAX_UNDO = 100
"""Snapshots kept for undo: each holds references to tensors, so old pixels live while they can be undone."""
LAYER_FIELDS = ("name", "visible", "opacity", "blend", "range", "offset", "mask", "condition", "settings")
"""Document fields a layer change may set (``mask`` only to null: a mask is removed, not painted; ``condition``
and ``settings`` of a learned layer, checked as ``lasagna render`` reads them, take effect when it is
re-rendered)."""


@dataclass(frozen=True)
class Snapshot:
    """Everything a change replaces: undoing puts it back."""

    document: Document
    tensors: dict[str, Any]
    bit_depths: dict[str, int]
    files: dict[str, bytes]
    what: str


class EditSession(SessionViews, SessionJobs):
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
        self.stack = load_stack(self.folder, max_pixels=self.max_pixels)  # the CLI's --max-pixels: any PNG
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
        tensors), surface layers' rendered multipliers and normals, the views' cached canvases, and the pending
        generator files."""
        with self.lock:
            maps = [self.stack.tensors, self.unchanged, *(s.tensors for s in (*self.undo_stack, *self.redo_stack))]
            owners = [lt for m in maps for lt in m.values()] + [lt for _, lt in self.reduced.values()]
            tensors = [x for lt in owners for x in lt.tensors()]
            # Its surface layers' multipliers, re-lit normals and shadows' heights (compose.surface).
            tensors += memo_tensors(owners)
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
                "surfaces": _surfaces(doc, self.stack.tensors),
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

    def set_light(self, version: Any, id: str, light: str, **fields: Any) -> dict[str, Any]:
        """Re-light surface layer ``id`` (``Stack.set_light``): its stored normal map is drawn under ``light`` and
        ``fields`` (``source_light``, ``ambient``, ``relief``, ``light_color``, ``light_intensity``, ``extra_lights``,
        ``gloss``, ``shininess``, ``shadows``, ``occlusion``, ``shadow_depth``:
        ``Stack.set_light``'s keywords, an absent one kept); no pixels change, nothing is learned. One undo step."""

        def apply() -> None:
            self.stack.set_light(id, light, **fields)

        return self._change(version, f"light of {id}", apply)

    def reread_surface(self, version: Any, id: str, within: float | None = None) -> dict[str, Any]:
        """Read relight surface layer ``id`` again from its image, told the source light it holds now
        (``lasagna.editing.reread_surface``: the preset's told estimator, about a second for ``relight``): what a
        dragged source light becomes when the user asks. ``within`` (degrees): that light is a rough reading, its
        elevation fused with the estimator's fit, and the layer then holds the fused light (``lasagna light
        --within``). Its lights and look are kept. One undo step."""
        from lasagna.editing import reread_surface

        def apply() -> None:
            reread_surface(self.stack, id, within=within, catalogue_dirs=self.catalogue_dirs, device=self.device)

        return self._change(version, f"re-read {id}", apply)

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

    def add_normal_map(
        self, version: Any, data: bytes, name: Any = None, directx: bool = False, height: float | None = None
    ) -> dict[str, Any]:
        """A new surface layer on top from an uploaded normal-map PNG's bytes (``lasagna add-surface``'s reading,
        `lasagna.io.normal_map`: its codes as stored; ``directx``: +Y down; ``height``: a grey height map, white that
        many pixels above black), lit from the top-left; its light is then the page's to drag."""
        from lasagna.io.normal_map import height_map_normals, normal_map_normals
        from lasagna.io.png import PNG_SIGNATURE, parse_header

        name = name if isinstance(name, str) and name.strip() else "Normal map"
        stem = Path(name).stem or "normal-map"
        where = f"upload {name!r}"
        with self._guard():
            self._check_version(version)
            if data[:8] == PNG_SIGNATURE:  # its decoded codes and float normals admitted before decoding
                header = parse_header(data, where)
                self._admit(
                    raster_bytes(header.width, header.height, 4) * 3,
                    f"the {header.width}x{header.height} normal map",
                    where,
                )
            try:
                if height is not None:
                    if directx:
                        raise LasagnaError("a height map has no green to flip; expected height or directx", "directx")
                    normals = height_map_normals(data=data, depth=height, max_pixels=self.max_pixels, where=where)
                else:
                    normals = normal_map_normals(
                        data=data, directx=bool(directx), max_pixels=self.max_pixels, where=where
                    )
            except BudgetError as exc:
                raise exc.at(where) from None
            id = self._new_id(stem.lower())
            return self._change(
                version, f"add {id}", lambda: self.stack.add_surface(id, normals, "top-left", name=stem)
            )

    def add_learned(
        self,
        version: Any,
        preset: Any,
        condition: Any,
        on: Any = None,
        method: Any = "amortised",
        kind: Any = None,
    ) -> dict[str, Any]:
        """A learned layer of catalogue preset ``preset`` for ``condition`` on top, by ``lasagna edit``'s recipe
        (``lasagna.editing.plan_edit``). ``amortised``: made now (one forward pass). ``per-image``: added without
        pixels, its settings saying how to make it, for a ``rerender`` job to make with progress. ``kind``
        "surface": a surface layer (``--layer-kind surface``), made now — the preset's estimator and its refinement
        steps, if any (about a second for ``relight``) — whose light the page then drags."""
        from lasagna.editing import layer_fields, plan_edit
        from lasagna.learned import make_layer
        from lasagna.request import EditRequest

        if not isinstance(preset, str) or not isinstance(condition, str):
            raise LasagnaError("expected a preset name and a condition", "preset")
        with self._guard():
            self._check_version(version)
            self._check_idle("add learned layer")
            start = time.monotonic()
            if kind == "surface":
                request = EditRequest(preset=preset, condition=condition, on=on, layer_kind="surface")
            else:
                request = EditRequest(preset=preset, condition=condition, on=on, generator=method, layer_kind=kind)
            plan = plan_edit(self.stack, request, catalogue_dirs=self.catalogue_dirs)
            if plan.recipe.method == "per-image" and plan.recipe.kind != "surface":
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

    # ---- saving -------------------------------------------------------------------------------------

    def save(self, version: Any) -> dict[str, Any]:
        """Write the stack into its folder (``save_in_place``); ``ConflictError`` if the tab is stale or the
        folder's stack.json changed since it was read."""
        from lasagna.export.ora import keep_ora_current

        extra = keep_ora_current(self.folder)  # a `lasagna edit` folder keeps its OpenRaster current
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
                    vocabulary=list(p.vocabulary),
                    blend=p.blend,
                    description=p.description,
                    channels=p.channels,
                    surface=p.surface is not None,
                )
            except LasagnaError as exc:
                entry.update(ready=False, why=str(exc))
            out.append(entry)
        return out


def _surfaces(doc: Document, tensors: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Each surface layer's light as the page draws its control: the texts, the light's (az, el) in degrees
    (``parse_direction``: a named light resolved; for a point light, the direction it has from the layer's
    centre) and ``point`` (x, y, z, or None for a directional light) with ``spot`` (a spot light's cone, aim
    [ax, ay] and blend, or None), a relight's source light's as ``source``, the
    ambient term, the relief gain, the light's colour and intensity, its extra lights, its gloss, shininess, shadows,
    shadow depth and occlusion, and
    ``rect``, the layer's
    [x, y, width, height] on the canvas (where a point light's fractions are placed), and ``rereadable`` (a relight
    made by a preset, which ``reread_surface`` can read again told its source light)."""
    out = {}
    for _, layer in doc.walk():
        if layer.kind == "surface":
            point = parse_point(layer.light)
            lt = tensors.get(layer.id)
            w, h = (int(lt.color.shape[-1]), int(lt.color.shape[-2])) if lt is not None else (0, 0)
            az, el = parse_direction(layer.light) if point is None else point_direction(point, w, h)
            out[layer.id] = {
                "light": layer.light,
                "az": az,
                "el": el,
                "point": None if point is None else list(point[:3]),
                "spot": None
                if point is None or point.cone is None
                else {"cone": point.cone, "aim": [point.ax, point.ay], "blend": point.blend},
                "rect": [layer.offset.x, layer.offset.y, w, h],
                "source_light": layer.source_light,
                "source": None if layer.source_light is None else list(parse_direction(layer.source_light)),
                # A relight made by a preset can be read again told its source light (EditSession.reread_surface).
                "rereadable": layer.source_light is not None
                and isinstance(layer.made_by.get("preset"), str)
                and layer.made_by.get("reads", "lit") == "lit",  # a shading layer made a relight later reads no light
                "ambient": float(layer.ambient),
                "relief": float(layer.relief),
                "light_color": [float(c) for c in layer.light_color],
                "light_intensity": float(layer.light_intensity),
                "extra_lights": [e.model_dump(mode="json") for e in layer.extra_lights],
                "gloss": float(layer.gloss),
                "shininess": float(layer.shininess),
                "shadows": float(layer.shadows),
                "occlusion": float(layer.occlusion),
                "shadow_depth": float(layer.shadow_depth),
            }
    return out


__all__ = ["Cancelled", "EditSession", "Job", "Snapshot"]
