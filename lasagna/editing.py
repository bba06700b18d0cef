"""Learned layers for users: fill a learned layer of an image or stack, re-render one from its stack.

    from lasagna.editing import edit, render_learned
    result = edit("photo.png", "shading", "left")   # EditResult: stack, layer, composite, …
    result.save("out/relit")                        # stack.json, layers/, generators/, composite.png, stack.ora
    render_learned("out/relit", all=True)           # the stack document alone reproduces the layer

**What the generator sees.** A learned layer is conditioned on the layer ``conditioned_on``: its input
is the composite of the stack from the bottom up to and including that layer (for a single opaque
base layer, the base itself). ``edit`` puts the new layer on top, conditioned on the top layer
unless ``on`` names another: an image's edit is conditioned on the image, a stack's on its composite.

**How the layer is made** (``settings["method"]``, recorded in the layer with everything it used; the
settings' typed model is ``lasagna.learned.LayerSettings``):

* ``amortised`` — the preset's amortised generator (``<catalogue>/<preset>/generator/``; the LMC-SDS
  image-to-image network) in one forward pass. Fully convolutional: any image size. Its weights are
  copied into the stack (``generators/<id>/``; the layer's ``generator`` names the file and its
  SHA-256), so the stack does not depend on the catalogue keeping them. ``optimize`` N > 0 then
  refines the layer per image: a free per-pixel layer starting from the generator's output is
  distilled for N steps (``distill_image``, the preset's loss, ω, lr and seed). It starts from an
  edit, not from the identity, so the L2 pull toward the input that eases a run out of the identity
  is off (``Weights()``: score only).
* ``per-image`` — no amortised generator (or ``generator="per-image"``, also spelled ``"free"`` as on the
  command line: a free per-pixel layer): a free layer from the identity edit, distilled for the preset's
  ``distill.steps`` (or ``optimize``) with its defaults.
  Images larger than the prior use the LMC-SDS patch strategy (``lasagna.distill.per_image``); an image of
  another aspect than the prior's is letterboxed into its view (``aspect``).

**Bring your own prior.** ``prior=`` (a diffusers folder written by ``save_pretrained`` — SD 1.x/2.x or
SDXL — or any prior folder or catalogue name) scores the preset's layer instead of the preset's prior,
with ``controlnets`` (folders, or (folder, scale) pairs), ``corrective`` (its b̂: the loss then defaults to
LMC-SDS; the preset's b̂ was fitted to its own prior and is not used, so without one it is SDS) and
``diffusers`` options (dtype, variant, offload, …, over the preset's). ``prompt`` is free text (the
label then only names it: ``"prompt"`` when no ``condition`` is given), ``negative_prompt`` replaces
the unconditional branch; both are stored in the layer's ``condition``. ``control_image`` (a file or an
image) is the ControlNet's conditioning image instead of the base; it is stored in the stack
(``controls/<id>.png``). The layer's settings record the SHA-256 of every weight file used (prior,
ControlNets, corrective); ``render_learned`` warns in one line when one changed. A stack made with a
prior outside the catalogue can be re-rendered once the prior is in it (``lasagna prior add``).

The layer itself is made by ``lasagna.learned.make_layer``, for ``edit`` and ``render_learned`` alike.
Per-image runs are seeded (``settings.distill.seed``), so ``render_learned`` reproduces them from the
stored settings, the stack's pixels and the catalogue's prior (whose SHA-256 is recorded and checked).
Learned layers are distilled on stored (sRGB-encoded) values, as the composite of a
``blend_space: "srgb"`` stack blends them; a ``linear`` stack is refused rather than edited in a
space its prior never scored.
"""

from __future__ import annotations

import contextlib
import os
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from lasagna import catalogue as cat
from lasagna.document import LearnedLayer, SurfaceLayer
from lasagna.errors import (
    DocumentError,
    ImageError,
    PathError,
)
from lasagna.io.folder import SharedFiles, check_output_folder, stage_stack_folder, write_stack_folder
from lasagna.io.image import DEFAULT_EDIT_MAX_PIXELS, check_edit_memory
from lasagna.io.render import check_depth
from lasagna.io.stack import Stack, load_stack, resolve_inside
from lasagna.learned import LayerRun, as_stored, check_device, conditioning_input, make_layer
from lasagna.recipe import Recipe
from lasagna.request import EditRequest
from lasagna.version import __version__

META_KEY = "lasagna.edit"  # document metadata: per learned layer, the tool version, time, timing

# ``phase(what, bar=False)``: a context manager entered around each phase of an edit or a save (decoding, making
# the layer, encoding, …), so a caller can report progress; ``bar``: the phase draws a progress bar of its own.
Phase = Callable[..., contextlib.AbstractContextManager]


def _no_phase(what: str, bar: bool = False) -> contextlib.AbstractContextManager:
    return contextlib.nullcontext()


@dataclass
class EditResult:
    """An edited stack in memory: ``stack`` (the new learned layer ``layer_id`` included, with pixels),
    the layer's values (C, H, W), the composite (3, H, W) in [0, 1], the per-image ``history`` (empty
    for one forward pass), seconds taken, and the files the stack folder needs besides its PNGs."""

    stack: Stack
    layer_id: str
    layer: Tensor
    composite: Tensor
    settings: dict[str, Any]
    seconds: float
    history: list[dict[str, Any]]
    files: dict[str, bytes]
    # The render ``composite`` came from, and what the stack was then (its document and layer tensors): ``save``
    # writes it instead of rendering again while the stack is unchanged (a 12 MP render is ~1 s and 144 MB).
    rendered: tuple[Any, Any] | None = field(default=None, repr=False, compare=False)

    def _render(self):
        if self.rendered is not None:
            (doc, tensors), (now_doc, now_tensors) = self.rendered[1], _state(self.stack)
            if doc is now_doc and tensors == now_tensors:
                return self.rendered[0]
        return self.stack.render()

    def save(
        self,
        out: str | os.PathLike,
        *,
        force: bool = False,
        ora: bool = True,
        warn: Callable[[str], None] | None = None,
        phase: Phase | None = None,
        depth: int = 8,
    ) -> Path:
        """Write the stack folder ``out``, all or nothing (``lasagna.io.folder.write_stack_folder``): stack.json,
        layers/, generators/, composite.png (``depth`` 8 or 16 bits; RGBA for a transparent document) and
        (``ora``) stack.ora; returns it. With ``force`` a stack folder already there is replaced. ``phase(what)``
        is entered around each phase (``Phase``)."""
        phase = phase or _no_phase
        check_depth(depth)
        check_output_folder(out, force=force)  # before any work
        contents = self._contents(ora, warn, phase, depth)
        with phase("writing the layers and stack.json"):
            return write_stack_folder(self.stack, out, **contents, force=force)

    def stage(
        self,
        out: str | os.PathLike,
        *,
        force: bool = False,
        ora: bool = True,
        warn: Callable[[str], None] | None = None,
        shared: SharedFiles | None = None,
        depth: int = 8,
    ) -> Path:
        """``save`` up to the rename: the stack folder written into a temporary sibling of ``out``, returned
        (``lasagna.io.folder.stage_stack_folder``; ``swap_in`` renames it into place). ``shared``: a batch's
        store its large files (the generator's weights) are hard-linked from (``SharedFiles``)."""
        contents = self._contents(ora, warn, None, depth)
        return stage_stack_folder(self.stack, out, **contents, force=force, shared=shared)

    def _contents(self, ora: bool, warn, phase: Phase | None = None, depth: int = 8) -> dict[str, Any]:
        from lasagna.export.ora import encode_ora
        from lasagna.io.render import encode_composite

        phase = phase or _no_phase
        with phase("encoding composite.png"):
            result = self._render()
            composite_png = encode_composite(result, depth=depth)  # type: ignore[arg-type]
        files = dict(self.files)
        if ora:
            # The ORA's merged image is composite.png's bytes when 8-bit (encoded once); OpenRaster readers
            # expect 8-bit layers, so a 16-bit composite.png is not reused there.
            merged = composite_png if depth == 8 else None
            with phase("encoding stack.ora"):
                files["stack.ora"] = encode_ora(self.stack, composite=result, merged_png=merged, warn=warn)
        return {"files": files, "result": result, "composite_png": composite_png}


# ---- inputs ----------------------------------------------------------------------------------------


def read_image(path: str | os.PathLike, max_pixels: int = DEFAULT_EDIT_MAX_PIXELS) -> Stack:
    """An image file as a one-layer stack (layer ``base``), read under the input policy of
    ``lasagna.io.image`` (PNG, JPEG, WebP, BMP, TIFF 8/16-bit; nothing else is opened)."""
    from lasagna.io.image import read_image_file

    img = read_image_file(path, max_pixels=max_pixels)
    alpha = torch.from_numpy(img.alpha) if img.alpha is not None else None
    return Stack.from_image(torch.from_numpy(img.color), alpha=alpha, bit_depth=img.bit_depth, name=Path(path).stem)


def input_stack(image, max_pixels: int = DEFAULT_EDIT_MAX_PIXELS) -> Stack:
    """The stack to edit: a stack folder (or its stack.json), an image file, a ``Stack`` (copied), or an
    image given as a tensor (values), numpy array or PIL image (``Stack.from_image``)."""
    if isinstance(image, Stack):
        stack = Stack(image.document, image.folder, dict(image.tensors), dict(image.bit_depths))
    elif isinstance(image, (str, os.PathLike)):
        p = Path(image)
        if p.is_dir() or p.suffix.lower() == ".json":
            stack = load_stack(p, max_pixels=max_pixels)
        elif not p.exists():
            raise PathError("does not exist; expected an image file (PNG, JPEG) or a stack folder", str(p))
        else:
            stack = read_image(p, max_pixels)
    else:
        stack = as_stored(Stack.from_image(image))
    if isinstance(image, Stack):
        stack = as_stored(stack)
    if stack.width * stack.height > max_pixels:
        raise ImageError(
            f"canvas is {stack.width}x{stack.height} = {stack.width * stack.height} pixels, over the limit "
            f"of {max_pixels}; expected at most {max_pixels} pixels (raise --max-pixels if intended)",
            "image",
        )
    check_edit_memory(stack.width, stack.height, "image")
    if stack.document.blend_space != "srgb":
        raise DocumentError(
            f"blend_space is {stack.document.blend_space!r}; learned layers are distilled on stored "
            "(sRGB-encoded) values, expected blend_space 'srgb'",
            "blend_space",
        )
    return stack


def _default_id(preset: str, condition: str) -> str:
    """``<preset>-<condition>`` as a layer id: ``relight-left``, ``relight-az135-el40`` (characters an id may not
    hold, such as ``=`` and ``,``, are dropped or become ``-``)."""
    text = condition.replace("=", "").replace(",", "-")
    text = "".join(c if c.isalnum() or c in "_.-" else "-" for c in text)
    return f"{preset}-{text}"[:64]


def _unique_id(stack: Stack, wanted: str) -> str:
    from lasagna.document.types import check_id

    taken = {i.casefold() for i in stack.ids}
    candidate, n = wanted, 2
    while candidate.casefold() in taken:
        candidate, n = f"{wanted}-{n}", n + 1
    try:
        return check_id(candidate)
    except ValueError as exc:
        raise DocumentError(str(exc), "id") from None


def edit(
    image,
    preset: str = "shading",
    condition: str | None = None,
    *,
    request: EditRequest | None = None,
    catalogue_dirs=None,
    max_pixels: int = DEFAULT_EDIT_MAX_PIXELS,
    device: str | torch.device = "cpu",
    progress: bool = False,
    phase: Phase | None = None,
    **options: Any,
) -> EditResult:
    """Add a learned layer of ``preset`` for ``condition`` on top of ``image`` (module docstring).

    ``image``: an image file, a stack folder, a ``Stack``, or a tensor/array/PIL image. The other keywords
    are ``lasagna.request.EditRequest``'s fields (or give ``request``): ``on`` (the layer it is conditioned on,
    default the top layer), ``id``, ``generator`` (``"amortised"``, ``"per-image"`` or ``"free"``; default the
    preset's), ``optimize`` (per-image steps; ``steps`` is its deprecated second name), ``loss``,
    ``guidance``, ``seed``, ``lr``, ``t_min``, ``t_max``, ``aspect``, ``particles`` (over the preset's
    ``distill`` defaults), and a prior of one's own: ``prior``, ``controlnets``, ``corrective``,
    ``control_image``, ``prompt``, ``negative_prompt``, ``diffusers`` (module docstring); for a relight surface
    layer ``layer_kind``, ``source_light`` (``--from``) and ``source_within`` (``--within``: the reading's uncertainty
    in degrees, its elevation then fused with the estimator's fit).
    """
    start = time.monotonic()
    if options.get("steps") is not None:
        warnings.warn(
            "edit(steps=N) is deprecated; use optimize=N (the same number, as the layer's settings record it)",
            DeprecationWarning,
            stacklevel=2,
        )
    if request is None:
        unknown = sorted(set(options) - set(EditRequest.__dataclass_fields__))
        if unknown:
            raise TypeError(f"edit() got unexpected keyword argument(s) {', '.join(unknown)}")
        request = EditRequest(preset=preset, condition=condition, **options)
    check_device(device)
    phase = phase or _no_phase
    with phase(f"reading {Path(image).name}" if isinstance(image, (str, os.PathLike)) else "reading the image"):
        plan = plan_edit(image, request, catalogue_dirs=catalogue_dirs, max_pixels=max_pixels)
    with phase(f"making the layer {plan.layer_id!r}", bar=progress and plan.recipe.distill is not None):
        run = make_layer(plan.recipe, plan.conditioning, plan.layer_id, device=device, progress=progress)
    with phase("compositing"):
        return plan.finish(run, time.monotonic() - start)


@dataclass(frozen=True)
class EditPlan:
    """One edit with everything decided but its layer: the input ``stack`` (and the ``source`` given), the
    ``recipe``, the new layer's id, the layer it is conditioned on and its ``conditioning`` input (3, H, W),
    the files the input folder carries. ``make_layer`` computes the layer, ``finish`` places it."""

    stack: Stack
    source: Any  # what was given (a path is recorded by name in the edit's metadata)
    recipe: Recipe
    on: str
    layer_id: str
    conditioning: Tensor
    carried: dict[str, bytes]

    def finish(self, run: LayerRun, seconds: float) -> EditResult:
        """Put ``run``'s layer on top of the stack, record the edit and render the composite."""
        stack = self.stack
        place_layer(stack, self.layer_id, self.recipe, self.on, run)
        _record(stack, self.layer_id, seconds, run, self.source)
        result = stack.render()
        # Clamped in place: every output clamps the composite anyway (its codes, the ORA's exact-composite layer).
        composite = result.image.detach().clamp_(0.0, 1.0)
        return EditResult(
            stack=stack,
            layer_id=self.layer_id,
            layer=run.layer,
            composite=composite,
            settings=run.settings.to_json(),
            seconds=seconds,
            history=run.history,
            files={**self.carried, **run.files},
            rendered=(result, _state(stack)),
        )


def _state(stack: Stack) -> tuple[Any, tuple[tuple[str, int], ...]]:
    """What a render of ``stack`` depends on, compared by identity: its (immutable) document and its layer tensors."""
    return stack.document, tuple((k, id(v)) for k, v in stack.tensors.items())


def plan_edit(
    image,
    request: EditRequest,
    *,
    catalogue_dirs=None,
    max_pixels: int = DEFAULT_EDIT_MAX_PIXELS,
    resolve: Callable[[Stack], cat.Resolved] | None = None,
) -> EditPlan:
    """Read ``image`` and decide its edit: the ``Recipe`` of ``request``, the layer's id and what it is
    conditioned on. ``resolve`` finds the preset for a stack (a batch passes a cached lookup)."""
    stack = input_stack(image, max_pixels)
    on = request.on if request.on is not None else stack.ids[-1]
    stack.document.index(on)  # DocumentError listing the ids
    recipe = Recipe.for_edit(stack, request, catalogue_dirs=catalogue_dirs, max_pixels=max_pixels, resolve=resolve)
    return EditPlan(
        stack=stack,
        source=image,
        recipe=recipe,
        on=on,
        layer_id=_unique_id(stack, request.id or _default_id(recipe.preset.name, recipe.label)),
        conditioning=conditioning_input(stack, on),
        carried=carried_files(stack),  # before the new layer: its generator is not in the input folder
    )


def place_layer(stack: Stack, layer_id: str, recipe: Recipe, on: str, run: LayerRun) -> None:
    """Add (or update) the learned layer ``layer_id`` with ``run``'s pixels, settings and generator (a surface
    run: the surface layer of its normals, lit by the recipe's condition). In a transparent document a new layer
    is clipped to the one below (Photoshop's clipping mask): over transparency a multiply or normal layer would
    paint where the image has no pixels (W3C section 10: Cr = Cs where αb = 0); clipped, the edit keeps the
    image's alpha."""
    new = layer_id not in stack.ids
    if run.normals is not None:
        name = layer_fields(layer_id, recipe, on)["name"]
        stack.add_surface(layer_id, run.normals, recipe.label, source_light=run.source_light, name=name)
        stack.document = stack.document.replace_layer(layer_id, made_by={**run.made_by, "conditioned_on": on})
        _clip_if_transparent(stack, layer_id, new)
        return
    settings = run.settings.to_json()
    if layer_id in stack.ids:
        old = stack.document.layer(layer_id).model_dump(mode="json")
        stack.document = stack.document.with_layer({**old, "generator": run.generator_ref, "settings": settings})
    else:
        stack.document = stack.document.with_layer(
            {**layer_fields(layer_id, recipe, on), "generator": run.generator_ref, "settings": settings}
        )
    stack.set_pixels(layer_id, run.layer, bit_depth=16)
    as_stored(stack, [layer_id])
    _clip_if_transparent(stack, layer_id, new)


def _clip_if_transparent(stack: Stack, layer_id: str, new: bool) -> None:
    if new and stack.document.canvas.background is None and stack.document.layers[0].id != layer_id:
        stack.document = stack.document.replace_layer(layer_id, clip=True)


def layer_fields(layer_id: str, recipe: Recipe, on: str) -> dict[str, Any]:
    """The document fields of a new learned layer made by ``recipe`` (its generator and settings aside)."""
    condition = {"label": recipe.label}
    pairs = (("prompt", recipe.prompt), ("negative_prompt", recipe.negative_prompt))
    condition.update({k: v for k, v in pairs if v is not None})
    preset = recipe.preset
    return {
        "id": layer_id,
        "name": f"{preset.name.capitalize()} ({recipe.label})",
        "kind": "learned",
        "blend": preset.blend,
        "range": list(preset.range),
        "preset": preset.name,
        "condition": condition,
        "conditioned_on": on,
    }


def _record(stack: Stack, layer_id: str, seconds: float, run: LayerRun, source=None, *, rendered: bool = False) -> None:
    """metadata["lasagna.edit"][layer_id]: tool version, when, seconds, steps run and why they stopped
    (a re-render keeps the edit's record and adds when and how long it took)."""
    meta = dict(stack.document.metadata)
    entries = dict(meta.get(META_KEY) or {}) if isinstance(meta.get(META_KEY), dict) else {}
    now = datetime.now(timezone.utc).isoformat(timespec="seconds")
    old = entries.get(layer_id) if isinstance(entries.get(layer_id), dict) else {}
    if rendered:
        entry = {**old, "tool": f"lasagna {__version__}", "rendered": now, "render_seconds": round(seconds, 3)}
    else:
        entry = {
            "tool": f"lasagna {__version__}",
            "created": now,
            "seconds": round(seconds, 3),
            "generate_seconds": round(run.seconds, 3),
            "steps_run": len(run.history),
            "stopped": run.stopped,
        }
        if isinstance(source, (str, os.PathLike)):
            entry["input"] = Path(source).name
    entries[layer_id] = entry
    meta[META_KEY] = entries
    stack.document = stack.document.replace(metadata=meta)


def carried_files(stack: Stack) -> dict[str, bytes]:
    """Files of the input stack folder its document needs besides layer PNGs: the generators of its
    learned layers and presets shipped in it (``layers/<preset>/preset.json``)."""
    if stack.folder is None:
        return {}
    out: dict[str, bytes] = {}
    for i, layer in enumerate(stack.document.layers):
        if not isinstance(layer, LearnedLayer):
            continue
        if layer.generator is not None:
            ckpt = resolve_inside(stack.folder, layer.generator.checkpoint, f"layers[{i}].generator.checkpoint")
            rel = Path(layer.generator.checkpoint)
            for name in (rel, rel.parent / "config.json"):
                src = stack.folder / name
                if src.is_file():
                    out[name.as_posix()] = src.read_bytes()
            if not ckpt.is_file():
                raise PathError(
                    f"{layer.generator.checkpoint!r} does not exist; expected the generator's weights",
                    f"layers[{i}].generator.checkpoint",
                )
        control = layer.settings.get("control_image") if isinstance(layer.settings, dict) else None
        if isinstance(control, str):  # the layer's conditioning image (``lasagna.learned.CONTROLS_DIR``)
            src = resolve_inside(stack.folder, control, f"layers[{i}].settings.control_image")
            if src.is_file():
                out[control] = src.read_bytes()
        shipped = stack.folder / "layers" / layer.preset / "preset.json"
        if "/" not in layer.preset and shipped.is_file():
            out[f"layers/{layer.preset}/preset.json"] = shipped.read_bytes()
    return out


# ---- re-rendering -------------------------------------------------------------------------------------


def render_learned(
    stack,
    *,
    all: bool = False,
    catalogue_dirs=None,
    device: str | torch.device = "cpu",
    progress: bool = False,
    write: bool = True,
    warn: Callable[[str], None] | None = None,
    ids: Sequence[str] | None = None,
    callback: Callable[[int, Tensor], None] | None = None,
) -> tuple[Stack, list[str]]:
    """Render the learned layers of ``stack`` (a folder or a ``Stack``) that have no pixels (every one
    with ``all``), bottom to top, from their stored generator and settings; returns (stack, ids rendered).

    A layer whose settings are empty is made as ``edit`` would make it and its settings are filled
    in. With ``write`` (and a folder), the layer PNGs, generator copies, stack.json, composite.png —
    and stack.ora if the folder has one — are written back, each atomically, stack.json after the
    layers it names. ``ids`` renders exactly those learned layers (whether they have pixels or not);
    ``callback`` is ``make_layer``'s per-step report.
    """

    if not isinstance(stack, Stack):
        stack = load_stack(stack)
    if stack.document.blend_space != "srgb":
        raise DocumentError(
            f"blend_space is {stack.document.blend_space!r}; expected 'srgb' for learned layers", "blend_space"
        )
    if ids is not None:
        for id in ids:
            if not isinstance(stack.document.layer(id), LearnedLayer):  # DocumentError for an unknown id
                raise DocumentError(
                    f"layer {id!r} is a {stack.document.layer(id).kind} layer; expected a learned layer", "ids"
                )
    rendered: list[str] = []
    files: dict[str, bytes] = {}
    for layer in list(stack.document.layers):
        if not isinstance(layer, LearnedLayer):
            continue
        if (ids is not None and layer.id not in ids) or (ids is None and layer.id in stack.tensors and not all):
            continue
        recipe = Recipe.from_layer(stack, layer, catalogue_dirs=catalogue_dirs)
        run = remake_layer(stack, layer.id, recipe, device=device, progress=progress, callback=callback)
        files.update(run.files)
        rendered.append(layer.id)
    if write and stack.folder is not None and rendered:
        _write_back(stack, files, warn)
    return stack, rendered


def _write_back(stack: Stack, files: dict[str, bytes], warn) -> None:
    """Re-rendered layers written into the stack's folder with ``files`` (generator copies, controls)."""
    from lasagna.atomic import atomic_write_all, folder_lock
    from lasagna.export.ora import encode_ora
    from lasagna.io.render import encode_composite
    from lasagna.io.stack import stack_files

    folder = stack.folder
    # Everything encoded first, then written all or nothing under the folder's lock: a kill, a full disk
    # or a second `lasagna render` of the same stack never leaves stack.json, the PNGs and the
    # composite out of step.
    writes = [(resolve_inside(folder, rel, rel), data) for rel, data in files.items()]
    writes += stack_files(stack, folder)
    result = stack.render()
    writes.append((folder / "composite.png", encode_composite(result, str(folder / "composite.png"))))
    if (folder / "stack.ora").is_file():
        writes.append((folder / "stack.ora", encode_ora(stack, composite=result, warn=warn)))
    with folder_lock(folder):
        atomic_write_all(writes)


def remake_layer(
    stack: Stack,
    layer_id: str,
    recipe: Recipe,
    *,
    device: str | torch.device = "cpu",
    progress: bool = False,
    callback: Callable[[int, Tensor], None] | None = None,
) -> LayerRun:
    """Learned layer ``layer_id`` of ``stack`` made by ``recipe``, put in place and recorded as rendered
    (``render_learned``, the editor's jobs)."""
    start = time.monotonic()
    layer = stack.document.layer(layer_id)
    base = conditioning_input(stack, layer.conditioned_on)
    run = make_layer(recipe, base, layer_id, device=device, progress=progress, callback=callback)
    place_layer(stack, layer_id, recipe, layer.conditioned_on, run)
    _record(stack, layer_id, time.monotonic() - start, run, rendered=True)
    return run


def reread_surface(
    stack: Stack,
    layer_id: str,
    *,
    within: float | None = None,
    catalogue_dirs=None,
    device: str | torch.device = "cpu",
) -> LayerRun:
    """The relight surface layer ``layer_id`` of ``stack`` read again from its image, told the source light it holds
    now — fitted when it was made, or moved since (the editor's source-light drag, ``lasagna light --from``): the
    recipe of ``lasagna edit --layer-kind surface --from`` that light, so the preset's ``surface.told`` estimator
    when it names one. A moved source light alone only divides the old estimate by another light, which leaves its
    relief where the fitted light put it (docs/BENCHMARKS.md, round 15); read again, the relief is found for the
    light the user gave. Only the normal map and ``made_by`` change: the layer's lights, ambient, relief gain,
    colour, name, opacity and mask are kept. Recorded as rendered (``metadata["lasagna.edit"]``).

    ``within`` (degrees, ``lasagna light --within``) says the source light it holds is a rough reading: its
    elevation is fused with the estimator's fit as ``lasagna edit --within`` does, and the layer then holds the fused
    light.

    One-line refusals: not a surface layer; plain shading (no source light to be told); a layer that records no
    preset or conditioning layer (a normal map of one's own)."""
    start = time.monotonic()
    layer = stack.document.layer(layer_id)
    where = f"layer {layer_id!r}"
    if not isinstance(layer, SurfaceLayer):
        raise DocumentError(f"is a {layer.kind} layer; expected a surface layer made by lasagna edit", where=where)
    if layer.source_light is None:
        raise DocumentError(
            "is plain shading (no source light to be told); expected a relight surface layer", where=where
        )
    made = layer.made_by or {}
    preset, on = made.get("preset"), made.get("conditioned_on")
    if not isinstance(preset, str) or not isinstance(on, str):
        raise DocumentError(
            "records no preset and layer it was read from (a normal map of one's own?); expected a layer made by "
            "lasagna edit --layer-kind surface",
            where=where,
        )
    if on not in stack.ids:
        raise DocumentError(
            f"was read from layer {on!r}, which the stack no longer has; expected that layer back (undo its deletion) "
            "or a new edit",
            where=where,
        )
    request = EditRequest(
        preset=preset,
        condition=layer.source_light,
        on=on,
        layer_kind="surface",
        source_light=layer.source_light,
        source_within=within,
    )  # the condition only names the recipe's light: a surface is lit by every light alike
    recipe = Recipe.for_edit(stack, request, catalogue_dirs=catalogue_dirs)
    run = make_layer(recipe, conditioning_input(stack, on), layer_id, device=device)
    kept = layer.model_dump(mode="json")
    mask = stack.tensors[layer_id].mask
    source = run.source_light  # the light it was told: the one it holds, or that reading fused with the fit (within)
    stack.add_surface(layer_id, run.normals, layer.light, source_light=source, ambient=layer.ambient, mask=mask)
    kept["source_light"] = source
    stack.document = stack.document.with_layer({**kept, "made_by": {**run.made_by, "conditioned_on": on}})
    _record(stack, layer_id, time.monotonic() - start, run, rendered=True)
    return run


__all__ = [
    "DEFAULT_EDIT_MAX_PIXELS",
    "EditPlan",
    "EditRequest",
    "EditResult",
    "edit",
    "input_stack",
    "plan_edit",
    "read_image",
    "remake_layer",
    "render_learned",
    "reread_surface",
]
