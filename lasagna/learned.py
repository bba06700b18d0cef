"""Making one learned layer: the amortised generator's forward pass, per-image distillation, or both.

``make_layer(base, resolved, label, id, method=…, optimize=…)`` is the one place a learned layer's
pixels are computed, for ``lasagna edit`` and ``lasagna render`` alike (``lasagna.edit`` describes the
methods and what the stack records). The generator's input is ``conditioning_input``: the composite
of the stack up to and including the layer it is conditioned on. ``as_stored`` replaces tensors by
what their PNGs will hold, so an edit is computed from, and composited with, exactly the values its
stack folder keeps — which is what lets a re-render reproduce it bit for bit.
"""
from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor

from lasagna import catalogue as cat
from lasagna.document import LearnedLayer
from lasagna.errors import ConditionError, LasagnaError
from lasagna.io.stack import Stack

GENERATORS_DIR = "generators"  # <stack>/generators/<layer id>/: copies of the generators a stack uses
Method = Literal["amortised", "free"]


@dataclass
class LayerRun:
    """What generating one learned layer produced: values (C, H, W) in the preset's range, the layer's
    settings (JSON), the generator files to store in the stack (relative path → bytes), timing."""

    layer: Tensor
    settings: dict[str, Any]
    files: dict[str, bytes]
    generator_ref: dict[str, str] | None
    seconds: float
    history: list[dict[str, Any]] = field(default_factory=list)
    stopped: str | None = None


def as_stored(stack: Stack, ids=None) -> Stack:
    """Replace the tensors of raster layers ``ids`` (default all) by what saving and loading them gives
    (PNG codes at their bit depth, mapped to the range as ``load_stack`` maps them), so the edit is
    computed from, and composited with, exactly the values its stack folder will hold."""
    from lasagna.io.png import decode_png
    from lasagna.io.stack import encode_layer, layer_tensors

    for layer_id in list(stack.tensors) if ids is None else ids:
        layer = stack.document.layer(layer_id)
        data, mask_data = encode_layer(stack, layer_id)
        img = decode_png(data, f"layer {layer_id!r}")
        mask_img = decode_png(mask_data, f"layer {layer_id!r} mask") if mask_data is not None else None
        stack.tensors[layer_id] = layer_tensors(img, layer.range, mask_img, f"layer {layer_id!r} mask")
        stack.bit_depths[layer_id] = img.header.bit_depth if img.header.bit_depth == 16 else 8
    return stack


def conditioning_input(stack: Stack, upto: str) -> Tensor:
    """(3, H, W) in [0, 1]: the composite of ``stack`` from the bottom up to and including layer ``upto``."""
    from lasagna.io.render import render_stack

    doc = stack.document
    k = doc.index(upto) + 1
    pending = [l.id for l in doc.layers[:k] if isinstance(l, LearnedLayer) and l.id not in stack.tensors]
    if pending:
        raise LasagnaError(f"learned layer(s) {', '.join(pending)} at or below {upto!r} have no pixels; "
                           "expected them rendered first (lasagna render STACK)", "conditioned_on")
    prefix = doc.with_layers(list(doc.layers[:k]))
    sub = Stack(prefix, stack.folder, {i: t for i, t in stack.tensors.items() if i in prefix.ids}, dict(stack.bit_depths))
    return render_stack(sub).image.detach().float().clamp(0.0, 1.0)


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def file_sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _components(resolved: cat.Resolved, label: str, loss: str, catalogue_dirs, device, refs: dict[str, Any] | None = None):
    """(prior, prior ref, its weights' sha256, corrective, corrective ref) for a per-image run: those the
    preset names, or those named in ``refs`` (a layer's stored settings: a re-render uses what the
    layer was made with, not what the preset names today)."""
    preset = resolved.preset
    refs = refs or {}
    here = resolved.preset_file.parent
    prior_ref = refs.get("prior") or preset.prior
    corrective_ref = refs.get("corrective") or preset.corrective
    prior_dir = cat.find(prior_ref, "prior", catalogue_dirs=catalogue_dirs,  # raises, listing the priors there are
                         relative_to=here if "/" in prior_ref else None)
    prior = cat.load_prior(prior_dir, preset=preset, device=device)
    known = tuple(getattr(prior, "vocabulary", ()) or ())
    if known and label not in known:
        raise ConditionError(f"label {label!r} of preset {preset.name!r} is not one prior {prior_ref!r} was trained on; "
                             f"expected one of {', '.join(known)}", "condition.label")
    weights = prior_dir / "model.safetensors"
    prior_sha = file_sha256(weights) if weights.is_file() else None
    corrective = None
    if loss == "lmc-sds":
        if corrective_ref is None:
            raise LasagnaError(f"loss 'lmc-sds' needs a corrective and preset {preset.name!r} names none; expected "
                               "another --loss or a preset with a corrective", "loss")
        corrective = cat.load_corrective(corrective_ref, catalogue_dirs=catalogue_dirs,
                                         relative_to=here if "/" in corrective_ref else None, device=device)
    return prior, prior_ref, prior_sha, corrective, corrective_ref if loss == "lmc-sds" else None


def _distill_settings(preset, *, refine: bool, steps: int | None, loss, guidance, seed, lr):
    from lasagna.distill import DistillSettings
    from lasagna.distill.schedules import Weights

    settings = DistillSettings.from_preset(preset, loss=loss, guidance=guidance, steps=steps, seed=seed, lr=lr)
    return settings.model_copy(update={"weights": Weights()}) if refine else settings


def make_layer(
    base: Tensor, resolved: cat.Resolved, label: str, layer_id: str, *,
    method: Literal["amortised", "per-image"], optimize: int, generator_dir: Path | None,
    loss: str | None = None, guidance: float | None = None, seed: int | None = None, lr: float | None = None,
    distill: dict[str, Any] | None = None, refs: dict[str, Any] | None = None, catalogue_dirs=None,
    device: str | torch.device = "cpu", progress: bool = False, working: int | Literal["preset", "full"] = "preset",
) -> LayerRun:
    """One learned layer (C, H, W) for ``base`` (3, H, W) in [0, 1] and ``label`` (module docstring).

    ``distill`` (stored settings) replaces the preset defaults and the loss/guidance/seed/lr overrides,
    and ``refs`` (``prior``, ``corrective``) the preset's prior and corrective: how ``render_learned``
    reruns a layer exactly as it was made. The layer is made at the preset's ``working_size`` (``working``:
    a stored side, or ``"full"`` for a layer made at the base's size) and enlarged to the base's size
    (`lasagna.compose.resample`).
    """
    from lasagna.compose.resample import downsample, upsample, working_size
    from lasagna.distill import DistillSettings, distill_image
    from lasagna.generators.free import FreeLayer
    from lasagna.generators.unet import LayerGenerator

    preset = resolved.preset
    start = time.monotonic()
    full = tuple(base.shape[-2:])
    side = {"preset": preset.working_size, "full": None}.get(working, working)
    size = working_size(*full, side) if side else full
    x = downsample(base.to(device)[None], size)  # (1, 3, h, w)
    files: dict[str, bytes] = {}
    gen_ref = None
    initial = None
    if method == "amortised":
        if generator_dir is None:
            raise LasagnaError(f"preset {preset.name!r} has no amortised generator yet (train one: lasagna train-layer "
                               f"--preset {preset.name}); expected --generator free", "generator")
        weights = (generator_dir / "model.safetensors").read_bytes()
        config = (generator_dir / "config.json").read_bytes()
        net = LayerGenerator.from_pretrained(generator_dir, device=device)
        cat.check_generator(net, preset, str(generator_dir))
        with torch.no_grad():
            initial = net(x, [label]).float()
        rel = f"{GENERATORS_DIR}/{layer_id}"
        files = {f"{rel}/model.safetensors": weights, f"{rel}/config.json": config}
        gen_ref = {"checkpoint": f"{rel}/model.safetensors", "sha256": _sha256(weights)}
    settings: dict[str, Any] = {"method": method, "optimize": optimize}
    if side:
        settings["working_size"] = side
    history: list[dict[str, Any]] = []
    stopped = None
    layer = initial
    if optimize > 0 or method == "per-image":
        if distill is not None:
            ds = DistillSettings.parse(distill, "settings.distill")
        else:
            ds = _distill_settings(preset, refine=initial is not None, steps=optimize, loss=loss, guidance=guidance,
                                   seed=seed, lr=lr)
        prior, prior_ref, prior_sha, corrective, corrective_ref = _components(resolved, label, ds.loss, catalogue_dirs,
                                                                             device, refs)
        model = "free" if initial is None else FreeLayer.from_layer(ds.layer, initial)
        run = distill_image(x, ds, prior, corrective, condition=label, generator=model, progress=progress)
        layer, history, stopped = run.layer.float(), run.history, run.stopped_reason
        settings.update(optimize=ds.steps, prior=prior_ref, prior_sha256=prior_sha, corrective=corrective_ref,
                        distill=ds.model_dump(mode="json"))
    if layer is None:  # unreachable: an amortised run has its forward pass, a per-image run its optimisation
        raise LasagnaError(f"no layer was made (method {method!r}, optimize {optimize})", "make_layer")
    layer = upsample(layer.detach(), full)  # a convex combination of in-range values: still in range
    return LayerRun(layer=layer[0].cpu(), settings=settings, files=files, generator_ref=gen_ref,
                    seconds=time.monotonic() - start, history=history, stopped=stopped)


def choose_method(resolved: cat.Resolved, generator: Method | None) -> Literal["amortised", "per-image"]:
    """``amortised`` when asked for or when the preset has a generator (and ``free`` was not asked)."""
    if generator not in (None, "amortised", "free"):
        raise LasagnaError(f"generator is {generator!r}; expected 'amortised' or 'free'", "generator")
    if generator == "free":
        return "per-image"
    if generator == "amortised" or resolved.generator is not None:
        return "amortised"
    return "per-image"
