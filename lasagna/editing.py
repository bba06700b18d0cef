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

import os
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import torch
from pydantic import ValidationError
from torch import Tensor

from lasagna import catalogue as cat
from lasagna.document import DiffusersOptions, LearnedLayer
from lasagna.errors import (
    ConditionError,
    DocumentError,
    ImageError,
    LasagnaError,
    PathError,
    describe_validation_error,
)
from lasagna.io.folder import SharedFiles, check_output_folder, stage_stack_folder, write_stack_folder
from lasagna.io.image import DEFAULT_EDIT_MAX_PIXELS
from lasagna.io.stack import Stack, load_stack, resolve_inside
from lasagna.learned import (
    LayerRun,
    LayerSettings,
    OwnPrior,
    as_stored,
    canonical_method,
    changed_weights,
    check_device,
    choose_method,
    conditioning_input,
    default_steps,
    file_sha256,
    make_layer,
)
from lasagna.version import __version__

META_KEY = "lasagna.edit"  # document metadata: per learned layer, the tool version, time, timing
PROMPT_LABEL = "prompt"  # the label of a layer asked for by free text alone (it names the prompt, no more)


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

    def save(
        self,
        out: str | os.PathLike,
        *,
        force: bool = False,
        ora: bool = True,
        warn: Callable[[str], None] | None = None,
    ) -> Path:
        """Write the stack folder ``out``, all or nothing (``lasagna.io.folder.write_stack_folder``): stack.json,
        layers/, generators/, composite.png and (``ora``) stack.ora; returns it. With ``force`` a stack
        folder already there is replaced."""
        check_output_folder(out, force=force)  # before any work
        return write_stack_folder(self.stack, out, **self._contents(ora, warn), force=force)

    def stage(
        self,
        out: str | os.PathLike,
        *,
        force: bool = False,
        ora: bool = True,
        warn: Callable[[str], None] | None = None,
        shared: SharedFiles | None = None,
    ) -> Path:
        """``save`` up to the rename: the stack folder written into a temporary sibling of ``out``, returned
        (``lasagna.io.folder.stage_stack_folder``; ``swap_in`` renames it into place). ``shared``: a batch's
        store its large files (the generator's weights) are hard-linked from (``SharedFiles``)."""
        return stage_stack_folder(self.stack, out, **self._contents(ora, warn), force=force, shared=shared)

    def _contents(self, ora: bool, warn) -> dict[str, Any]:
        from lasagna.export.ora import encode_ora
        from lasagna.io.render import encode_composite

        result = self.stack.render()
        composite_png = encode_composite(result)  # composite.png, and the ORA's merged image: encoded once
        files = dict(self.files)
        if ora:
            files["stack.ora"] = encode_ora(self.stack, composite=result.image, merged_png=composite_png, warn=warn)
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
    on: str | None = None,
    id: str | None = None,
    generator: str | None = None,
    optimize: int | None = None,
    steps: int | None = None,
    loss: str | None = None,
    guidance: float | None = None,
    seed: int | None = None,
    lr: float | None = None,
    catalogue_dirs=None,
    max_pixels: int = DEFAULT_EDIT_MAX_PIXELS,
    device: str | torch.device = "cpu",
    progress: bool = False,
    prior: str | os.PathLike | None = None,
    controlnets: Sequence[str | os.PathLike | tuple[str | os.PathLike, float]] = (),
    corrective: str | os.PathLike | None = None,
    control_image=None,
    prompt: str | None = None,
    negative_prompt: str | None = None,
    diffusers: DiffusersOptions | dict | None = None,
    t_min: float | None = None,
    t_max: float | None = None,
    aspect: str | None = None,
    particles: int | None = None,
) -> EditResult:
    """Add a learned layer of ``preset`` for ``condition`` on top of ``image`` (module docstring).

    ``condition``: a label of the preset's vocabulary (default its first, or ``"prompt"`` with a ``prompt``).
    ``prior``, ``controlnets``, ``corrective``, ``control_image``, ``prompt``, ``negative_prompt``,
    ``diffusers``: a prior of one's own (module docstring, "Bring your own prior"). ``t_min``/``t_max``
    (t ~ U(t_min, t_max)), ``aspect`` (``"letterbox"`` or ``"stretch"``) and ``particles`` (per-image free
    layers averaged at the end, ``lasagna.distill.per_image``) override the preset's too.

    ``image``: an image file, a stack folder, a ``Stack``, or a tensor/array/PIL image. ``on``: the
    layer it is conditioned on (default: the top layer). ``generator``: what makes the layer —
    ``"amortised"`` (the preset's trained network) or ``"free"`` (a free per-pixel layer optimised for this
    image: the ``"per-image"`` method, accepted by that name too); default the preset's ``method``, else
    amortised if the preset has a generator (``lasagna.learned.choose_method``). ``optimize``: per-image
    steps — after the amortised pass (default the preset's ``refine_steps``), or of the free layer (default
    its ``distill.steps``); the layer's
    settings record it under the same name. ``steps`` is its old second name, deprecated (a
    ``DeprecationWarning``; give ``optimize``). ``loss``, ``guidance``, ``seed``, ``lr`` override the
    preset's ``distill`` defaults.
    """
    start = time.monotonic()
    n = check_edit_options(preset, optimize, steps)
    check_device(device)
    own = own_prior(prior, controlnets, corrective)
    plan = plan_edit(
        image,
        preset,
        condition,
        on=on,
        id=id,
        generator=generator,
        optimize=n,
        max_pixels=max_pixels,
        catalogue_dirs=catalogue_dirs,
        prompt=prompt,
        negative_prompt=negative_prompt,
        own=own,
    )
    if control_image is not None or diffusers is not None:
        own = own or OwnPrior()
        own.options = diffusers_options(plan.resolved.preset, diffusers)
    if control_image is not None:
        own.control = read_control_image(control_image, tuple(plan.base.shape[-2:]), max_pixels)
    plan.own = own
    plan.overrides = {
        k: v
        for k, v in (("t_min", t_min), ("t_max", t_max), ("aspect", aspect), ("particles", particles))
        if v is not None
    }
    if own is not None and own.prior is not None and loss is None:
        # A corrective is given for LMC-SDS; without one (the preset's belongs to its own prior) LMC-SDS
        # cannot run, and the preset's other losses still can.
        default = plan.resolved.preset.distill.loss
        loss = "lmc-sds" if own.corrective is not None else ("sds" if default == "lmc-sds" else None)
    run = plan.make(
        loss=loss, guidance=guidance, seed=seed, lr=lr, catalogue_dirs=catalogue_dirs, device=device, progress=progress
    )
    return plan.finish(run, time.monotonic() - start)


def diffusers_options(preset, diffusers: DiffusersOptions | dict | None) -> DiffusersOptions:
    """The diffusers options of an edit: ``DiffusersOptions`` as given, or a dict of fields over the preset's."""
    if isinstance(diffusers, DiffusersOptions):
        return diffusers
    base = preset.diffusers or DiffusersOptions()
    try:
        return DiffusersOptions.model_validate({**base.model_dump(), **(diffusers or {})})
    except ValidationError as err:
        raise describe_validation_error(err, "diffusers", DiffusersOptions) from None


def own_prior(prior, controlnets=(), corrective=None) -> OwnPrior | None:
    """``edit``'s prior options as an ``OwnPrior`` (None when none is given). A folder that exists is taken by
    its absolute path; anything else is a catalogue name. ControlNets and a corrective need ``prior``."""
    from lasagna.document.preset import ControlNetRef

    if prior is None:
        if controlnets or corrective is not None:
            raise LasagnaError(
                "ControlNets and a corrective go with a prior of one's own; expected --prior PATH too", "prior"
            )
        return None
    nets = []
    for i, net in enumerate(controlnets):
        path, scale = net if isinstance(net, tuple) else (net, None)
        if not Path(path).is_dir():
            raise PathError("does not exist; expected a ControlNet folder written by save_pretrained", str(path))
        nets.append(ControlNetRef(path=str(Path(path).resolve()), scale=scale))

    def absolute(ref):
        if ref is None:
            return None
        return str(Path(ref).resolve()) if Path(ref).is_dir() or isinstance(ref, os.PathLike) else str(ref)

    return OwnPrior(prior=absolute(prior), controlnets=tuple(nets), corrective=absolute(corrective))


def read_control_image(source, size: tuple[int, int], max_pixels: int = DEFAULT_EDIT_MAX_PIXELS) -> Tensor:
    """A conditioning image (a file, tensor (C, H, W), array or PIL image) as (3, H, W) in [0, 1] at the base's
    ``size``: another size of the same aspect (within 1 %) is resampled; another aspect is refused."""
    from lasagna.distill.objective import resize

    if isinstance(source, (str, os.PathLike)):
        from lasagna.io.image import read_image_file

        img = torch.from_numpy(read_image_file(source, max_pixels=max_pixels).color).float()
        where = str(source)
    else:
        img = Stack.from_image(source).tensors["base"].float()
        where = "control_image"
    if img.shape[0] == 1:
        img = img.expand(3, -1, -1)
    h, w = img.shape[-2:]
    if abs(h * size[1] - w * size[0]) > 0.01 * h * size[1]:
        raise ImageError(
            f"is {w}x{h}; expected the aspect of the image it conditions, {size[1]}x{size[0]} (any size)", where
        )
    return resize(img[:3][None], size)[0].clamp(0, 1)


def check_edit_options(preset, optimize: int | None, steps: int | None = None) -> int | None:
    """``edit``'s checks of its options that need no image: the preset is a name, ``optimize`` (or its
    deprecated second name ``steps``) a non-negative integer; returns the steps asked for (None: default)."""
    if preset is not None and not isinstance(preset, (str, os.PathLike)):
        # A Preset object has no folder: the layer's record could not name it for a later render.
        raise LasagnaError(
            f"got a {type(preset).__name__}; expected a catalogue name (write the preset with preset.to_json() "
            "into <folder>/<name>/preset.json and add <folder> with catalogue_dirs= or LASAGNA_LAYERS)",
            "preset",
        )
    if preset is None or "/" in str(preset) or isinstance(preset, os.PathLike):
        raise LasagnaError(
            f"preset {str(preset)!r} is not a name; expected a catalogue name (add a catalogue folder "
            "with LASAGNA_LAYERS)",
            "preset",
        )
    if steps is not None:
        warnings.warn(
            "edit(steps=N) is deprecated; use optimize=N (the same number, as the layer's settings record it)",
            DeprecationWarning,
            stacklevel=3,
        )
        if optimize is not None and optimize != steps:
            raise LasagnaError(
                f"optimize {optimize} and steps {steps} differ; expected one of them (they are the same number)",
                "steps",
            )
    n = optimize if optimize is not None else steps
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 0):
        raise LasagnaError(f"expected a non-negative integer, got {n!r}", "optimize")
    return n


@dataclass
class EditPlan:
    """One edit with everything decided but its layer: the input ``stack``, the resolved preset, the method
    and per-image steps, the new layer's id, what it is conditioned on and the conditioning input ``base``
    (3, H, W). ``make`` computes the layer (``lasagna.learned.make_layer``), ``finish`` places it."""

    stack: Stack
    source: Any  # what was given (a path is recorded by name in the edit's metadata)
    resolved: cat.Resolved
    condition: str
    on: str
    layer_id: str
    method: str
    optimize: int
    base: Tensor
    carried: dict[str, bytes]
    prompt: str | None = None
    negative_prompt: str | None = None
    own: OwnPrior | None = None
    overrides: dict[str, Any] = field(default_factory=dict)

    def make(self, **options) -> LayerRun:
        """The layer: ``make_layer`` with this plan's choices and ``options`` (loss, guidance, seed, lr,
        catalogue_dirs, device, progress, and ``loaded``/``initial`` for a generator run in a batch)."""
        return make_layer(
            self.base,
            self.resolved,
            self.condition,
            self.layer_id,
            method=self.method,
            optimize=self.optimize,
            generator_dir=self.resolved.generator,
            own=self.own,
            prompt=self.prompt,
            negative_prompt=self.negative_prompt,
            overrides=self.overrides,
            **options,
        )

    def finish(self, run: LayerRun, seconds: float) -> EditResult:
        """Put ``run``'s layer on top of the stack, record the edit and render the composite."""
        stack = self.stack
        place_layer(
            stack,
            self.layer_id,
            self.resolved.preset,
            self.condition,
            self.on,
            run,
            prompt=self.prompt,
            negative_prompt=self.negative_prompt,
        )
        _record(stack, self.layer_id, seconds, run, self.source)
        composite = stack.render().image.detach().clamp(0.0, 1.0)
        return EditResult(
            stack=stack,
            layer_id=self.layer_id,
            layer=run.layer,
            composite=composite,
            settings=run.settings.to_json(),
            seconds=seconds,
            history=run.history,
            files={**self.carried, **run.files},
        )


def plan_edit(
    image,
    preset: str,
    condition: str,
    *,
    on: str | None = None,
    id: str | None = None,
    generator: str | None = None,
    optimize: int | None = None,
    max_pixels: int = DEFAULT_EDIT_MAX_PIXELS,
    catalogue_dirs=None,
    resolve: Callable[[Stack], cat.Resolved] | None = None,
    prompt: str | None = None,
    negative_prompt: str | None = None,
    own: OwnPrior | None = None,
) -> EditPlan:
    """Read ``image`` and decide its edit (``edit``'s arguments; ``optimize`` checked by
    ``check_edit_options``). ``resolve`` finds the preset for a stack (default ``lasagna.catalogue.resolve``;
    a batch passes a cached one). Free text (``prompt``) or one's own prior (``own``) is scored per image:
    the preset's amortised generator knows neither."""
    stack = input_stack(image, max_pixels)
    if resolve is None:
        resolved = cat.resolve(preset, stack.folder, catalogue_dirs, need_prior=False)
    else:
        resolved = resolve(stack)
    p = resolved.preset
    for text, name in ((prompt, "prompt"), (negative_prompt, "negative_prompt")):
        if text is not None and not (isinstance(text, str) and text.strip()):
            raise ConditionError(f"got {text!r}; expected non-empty text", name)
    if condition is None:
        condition = PROMPT_LABEL if prompt is not None else p.vocabulary[0]
    if prompt is None:
        p.prompt_for(condition)  # ConditionError listing the vocabulary
    on = on if on is not None else stack.ids[-1]
    stack.document.index(on)  # DocumentError listing the ids
    own_scored = prompt is not None or (own is not None and own.prior is not None)
    if own_scored and generator is not None and canonical_method(generator) == "amortised":
        raise LasagnaError(
            "the amortised generator was trained with the preset's prior and labels; expected --generator free "
            "with --prior or --prompt",
            "generator",
        )
    method = choose_method(resolved, "per-image" if own_scored else generator)
    if method == "per-image" and optimize == 0:
        raise LasagnaError(
            "per-image optimisation with 0 steps would leave the identity edit; expected --optimize N > 0", "optimize"
        )
    return EditPlan(
        stack=stack,
        source=image,
        resolved=resolved,
        condition=condition,
        on=on,
        layer_id=_unique_id(stack, id or _default_id(p.name, condition)),
        method=method,
        optimize=default_steps(resolved, method) if optimize is None else optimize,
        base=conditioning_input(stack, on),
        carried=carried_files(stack),  # before the new layer: its generator is not in the input folder
        prompt=prompt,
        negative_prompt=negative_prompt,
    )


def place_layer(
    stack: Stack,
    layer_id: str,
    preset,
    label: str,
    on: str,
    run: LayerRun,
    *,
    prompt: str | None = None,
    negative_prompt: str | None = None,
) -> None:
    """Add (or update) the learned layer ``layer_id`` with ``run``'s pixels, settings and generator."""
    settings = run.settings.to_json()
    condition = {"label": label}
    condition.update({k: v for k, v in (("prompt", prompt), ("negative_prompt", negative_prompt)) if v is not None})
    fields = {
        "id": layer_id,
        "name": f"{preset.name.capitalize()} ({label})",
        "kind": "learned",
        "blend": preset.blend,
        "range": list(preset.range),
        "preset": preset.name,
        "condition": condition,
        "conditioned_on": on,
        "generator": run.generator_ref,
        "settings": settings,
    }
    if layer_id in stack.ids:
        old = stack.document.layer(layer_id).model_dump(mode="json")
        stack.document = stack.document.with_layer({**old, "generator": run.generator_ref, "settings": settings})
    else:
        stack.document = stack.document.with_layer(fields)
    stack.set_pixels(layer_id, run.layer, bit_depth=16)
    as_stored(stack, [layer_id])


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
        start = time.monotonic()
        run = _rerun(stack, layer, catalogue_dirs, device, progress, callback)
        place_layer(
            stack,
            layer.id,
            cat.load_preset(layer.preset, stack.folder, catalogue_dirs),
            layer.condition.label,
            layer.conditioned_on,
            run,
            prompt=layer.condition.prompt,
            negative_prompt=layer.condition.negative_prompt,
        )
        files.update(run.files)
        _record(stack, layer.id, time.monotonic() - start, run, rendered=True)
        rendered.append(layer.id)
    if write and stack.folder is not None and rendered:
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
            writes.append((folder / "stack.ora", encode_ora(stack, composite=result.image, warn=warn)))
        with folder_lock(folder):
            atomic_write_all(writes)
    return stack, rendered


def _confined_ref(stack: Stack, ref: str | None, where: str) -> str | None:
    """A stored prior/corrective reference as ``render`` may follow it: a catalogue name, or a relative
    path inside the stack folder. Anything else is refused before the filesystem is asked about it, so
    the message says nothing about what exists outside the folder."""
    if ref is None or ("/" not in ref and "\\" not in ref):
        return ref
    parts = ref.replace("\\", "/").split("/")
    if ref.startswith(("/", "\\")) or ":" in parts[0] or ".." in parts or stack.folder is None:
        raise PathError(
            f"{ref!r} is not a catalogue name or a relative path inside the stack folder; expected one of those",
            where,
        )
    try:
        return str(resolve_inside(stack.folder, ref, where))
    except PathError:
        raise PathError(f"{ref!r} leaves the stack folder (through a link); expected a path inside it", where) from None


def _rerun(stack: Stack, layer: LearnedLayer, catalogue_dirs, device, progress, callback=None) -> LayerRun:
    """A learned layer made again from what the stack stores (see ``render_learned``)."""
    where = f"layer {layer.id!r}"
    resolved = cat.resolve(layer.preset, stack.folder, catalogue_dirs, need_prior=False)
    preset = resolved.preset
    if layer.condition.prompt is None:
        preset.prompt_for(layer.condition.label)
    s = LayerSettings.parse(layer.settings, where)
    method = s.method if s.method is not None else choose_method(resolved, None)
    optimize = s.optimize if s.optimize is not None else default_steps(resolved, method)
    generator_dir = resolved.generator
    if method == "amortised" and layer.generator is not None:
        if stack.folder is None:
            raise PathError(
                "the stack has no folder to find its generator in; expected a stack loaded from a folder", where
            )
        ckpt = resolve_inside(stack.folder, layer.generator.checkpoint, f"{where}.generator.checkpoint")
        if not ckpt.is_file():
            raise PathError(
                f"{layer.generator.checkpoint!r} does not exist; expected the generator's weights",
                f"{where}.generator.checkpoint",
            )
        if layer.generator.sha256 is not None and file_sha256(ckpt) != layer.generator.sha256:
            raise LasagnaError(
                "the generator's weights do not match the recorded sha256; expected the file the layer was made with",
                f"{where}.generator.checkpoint",
            )
        config = ckpt.parent / "config.json"
        if layer.generator.config_sha256 is not None:
            if not config.is_file() or file_sha256(config) != layer.generator.config_sha256:
                raise LasagnaError(
                    "the generator's config.json does not match the recorded config_sha256; expected the config "
                    "the layer was made with",
                    f"{where}.generator.config_sha256",
                )
        elif layer.generator.sha256 is not None:
            warnings.warn(
                f"{where}: the generator's config.json is under no checksum (a stack written before config_sha256); "
                "its vocabulary is trusted as found",
                stacklevel=2,
            )
        generator_dir = ckpt.parent
    base = conditioning_input(stack, layer.conditioned_on)
    refs = {k: _confined_ref(stack, getattr(s, k), f"{where}.settings.{k}") for k in ("prior", "corrective")}
    refs = {k: v for k, v in refs.items() if v is not None}
    control = None
    if s.control_image is not None:
        from lasagna.io.image import read_image_file

        path = (
            resolve_inside(stack.folder, s.control_image, f"{where}.settings.control_image") if stack.folder else None
        )
        if path is None or not path.is_file():
            raise PathError(
                f"{s.control_image!r} does not exist; expected the layer's conditioning image in the stack folder",
                f"{where}.settings.control_image",
            )
        control = torch.from_numpy(read_image_file(path, max_pixels=stack.width * stack.height).color).float()
    run = make_layer(
        base,
        resolved,
        layer.condition.label,
        layer.id,
        method=method,
        optimize=optimize,
        generator_dir=generator_dir,
        distill=s.distill,
        refs=refs,
        catalogue_dirs=catalogue_dirs,
        device=device,
        progress=progress,
        working=s.working_size if s.working_size is not None else "full",  # recorded without one: the base's size
        prompt=layer.condition.prompt,
        negative_prompt=layer.condition.negative_prompt,
        options=s.diffusers,
        control=control,
        callback=callback,
    )
    changed = changed_weights(s.weights, run.settings.weights or {}) if s.weights is not None else []
    recorded = s.prior_sha256
    if changed:
        more = f" (+{len(changed) - 1} more)" if len(changed) > 1 else ""
        warnings.warn(
            f"{where}: {changed[0]}{more} differs from the file the layer was made with (sha256); the layer is "
            "re-rendered with the current weights",
            stacklevel=2,
        )
    elif s.weights is None and recorded is not None and run.settings.prior_sha256 not in (None, recorded):
        warnings.warn(
            f"{where}: the catalogue's prior {run.settings.prior!r} differs from the one the layer was "
            "made with (sha256); the layer is re-rendered with the current one",
            stacklevel=2,
        )
    if layer.generator is not None and method == "amortised":
        run.generator_ref = layer.generator.model_dump(mode="json")
        run.files = {}  # already in the stack folder
    return run


__all__ = [
    "DEFAULT_EDIT_MAX_PIXELS",
    "EditPlan",
    "EditResult",
    "check_edit_options",
    "edit",
    "input_stack",
    "plan_edit",
    "read_image",
    "render_learned",
]
