"""Making one learned layer: the amortised generator's forward pass, per-image distillation, or both.

``make_layer(base, resolved, label, id, method=…, optimize=…)`` is the one place a learned layer's
pixels are computed, for ``lasagna edit`` and ``lasagna render`` alike (``lasagna.editing`` describes the
methods and what the stack records). The generator's input is ``conditioning_input``: the composite
of the stack up to and including the layer it is conditioned on. ``as_stored`` replaces tensors by
what their PNGs will hold, so an edit is computed from, and composited with, exactly the values its
stack folder keeps — which is what lets a re-render reproduce it bit for bit.
"""

from __future__ import annotations

import hashlib
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator
from torch import Tensor

from lasagna import catalogue as cat
from lasagna.distill import DistillSettings
from lasagna.document import LearnedLayer
from lasagna.document.preset import METHODS, ControlNetRef, DiffusersOptions, Method
from lasagna.errors import ConditionError, DocumentError, LasagnaError, describe_validation_error
from lasagna.io.stack import Stack
from lasagna.limits import MAX_DISTILL_STEPS

GENERATORS_DIR = "generators"  # <stack>/generators/<layer id>/: copies of the generators a stack uses
CONTROLS_DIR = "controls"  # <stack>/controls/<layer id>.png: the user's conditioning image of a layer

# How a learned layer is made (``lasagna.editing`` describes both; the names are the document tier's,
# ``lasagna.document.preset.Method``). ``free`` — the CLI's ``--generator free``, "a free per-pixel
# layer" — names the per-image method and is accepted wherever a method is read.
METHOD_ALIASES: dict[str, str] = {"free": "per-image"}


def check_device(text: str | torch.device) -> str:
    """``text`` if it names a device torch knows *and* this machine has (cpu, cuda, cuda:N, mps); else a
    one-line ``LasagnaError`` — not torch's "not compiled with CUDA" from deep inside a load."""
    name = str(text)
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        raise LasagnaError(f"{name!r} is not a torch device; expected cpu, cuda, cuda:N or mps", "device") from None
    if device.type == "cuda":
        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise LasagnaError(f"{name!r}: this machine has no CUDA device; expected cpu", "device")
        if device.index is not None and device.index >= count:
            raise LasagnaError(f"{name!r}: this machine has {count} CUDA device(s); expected cuda:0..", "device")
    elif device.type == "mps":
        if not torch.backends.mps.is_available():
            raise LasagnaError(f"{name!r}: MPS is not available here; expected cpu", "device")
    elif device.type != "cpu":
        raise LasagnaError(f"{name!r} is not supported; expected cpu, cuda, cuda:N or mps", "device")
    return name


def canonical_method(name: object, where: str = "generator") -> Method:
    """The method ``name`` names (``free`` is ``per-image``); a ``LasagnaError`` listing them otherwise."""
    name = METHOD_ALIASES.get(name, name) if isinstance(name, str) else name
    if name not in METHODS:
        raise LasagnaError(f"method is {name!r}; expected one of {', '.join(METHODS)} (or 'free' for per-image)", where)
    return name  # type: ignore[return-value]


class LayerSettings(BaseModel):
    """A learned layer's ``settings`` in its stack (``LearnedLayer.settings`` holds them as JSON): how the
    layer was made, enough to make it again (``lasagna render``).

    ``method`` and ``optimize`` (the per-image steps: after the amortised pass, or of the free layer) are
    always written, ``working_size`` when the layer was made at a working size (`lasagna.compose.resample`);
    ``prior``, its weights' ``prior_sha256``, ``corrective`` and ``distill`` (the resolved
    ``DistillSettings``) only when per-image steps ran. A document may leave any of them out: ``render``
    then makes the layer as ``edit`` would and fills them in.
    """

    model_config = ConfigDict(extra="forbid")

    method: Method | None = Field(None, description="amortised (the preset's generator) or per-image.")
    optimize: int | None = Field(None, ge=0, le=MAX_DISTILL_STEPS, strict=True, description="Per-image steps.")
    prior: str | None = Field(None, description="The prior scored against, by catalogue name or path.")
    prior_sha256: str | None = Field(
        None,
        description="SHA-256 of the prior's model.safetensors (a diffusers prior: of its files' names and SHA-256s, "
        "ControlNets included, as ``weights`` lists them).",
    )
    corrective: str | None = Field(None, description="The LMC-SDS corrective, when the loss used one.")
    controlnets: list[ControlNetRef] | None = Field(None, description="A diffusers prior's ControlNets, as used.")
    diffusers: DiffusersOptions | None = Field(None, description="How a diffusers prior was loaded and run.")
    control_image: str | None = Field(
        None, description="The conditioning image used instead of the base: a PNG inside the stack folder."
    )
    weights: dict[str, str] | None = Field(
        None,
        description="SHA-256 of every file the prior, its ControlNets and the corrective were read from, by name "
        "(prior/…, controlnet<i>/…, corrective/…); `lasagna render` warns when one changed.",
    )
    distill: DistillSettings | None = Field(None, description="The per-image run's resolved settings.")
    working_size: int | None = Field(
        None, ge=8, le=4096, strict=True, description="The long side the layer was made at (absent: the base's size)."
    )

    @field_validator("method", mode="before")
    @classmethod
    def _alias(cls, value: object) -> object:
        return METHOD_ALIASES.get(value, value) if isinstance(value, str) else value

    @classmethod
    def parse(cls, data: Any, where: str) -> LayerSettings:
        """Validate stored settings; a bad field is a one-line ``DocumentError`` at ``where: settings.<field>``."""
        try:
            return cls.model_validate(data)
        except ValidationError as exc:
            raise describe_validation_error(exc, where, cls, DocumentError, prefix="settings") from None

    def to_json(self) -> dict[str, Any]:
        """The JSON the stack stores: the fields in their order, the per-image ones only with ``distill``."""
        data = self.model_dump(mode="json")
        if self.distill is None:
            data = {k: data[k] for k in ("method", "optimize", "working_size")}
        for key in ("controlnets", "diffusers", "control_image", "weights"):  # absent: as before they existed
            if data.get(key) is None:
                data.pop(key, None)
        if self.working_size is None:
            del data["working_size"]  # a layer made at the base's size: the document as before working sizes
        return data


@dataclass
class LayerRun:
    """What generating one learned layer produced: values (C, H, W) in the preset's range, the layer's
    settings, the generator files to store in the stack (relative path → bytes), timing."""

    layer: Tensor
    settings: LayerSettings
    files: dict[str, bytes]
    generator_ref: dict[str, str] | None
    seconds: float
    history: list[dict[str, Any]] = field(default_factory=list)
    stopped: str | None = None


def as_stored(stack: Stack, ids=None) -> Stack:
    """Replace the tensors of raster layers ``ids`` (default all) by what saving and loading them gives
    (PNG codes at their bit depth, mapped to the range as ``load_stack`` maps them), so the edit is
    computed from, and composited with, exactly the values its stack folder will hold.

    Tensors already known to hold stored values at the layer's range (loaded from a folder, or made here,
    and unchanged since: ``LayerTensors.noted``) are kept as they are, so an editor that adds learned
    layers to a large stack does not re-quantise every layer each time."""
    from lasagna.io.stack import stored_tensors

    for layer_id in list(stack.tensors) if ids is None else ids:
        layer = stack.document.layer(layer_id)
        if stack.tensors[layer_id].noted("stored") == tuple(layer.range):
            continue
        stack.tensors[layer_id], depth = stored_tensors(stack, layer_id)
        stack.bit_depths[layer_id] = depth
    return stack


def conditioning_input(stack: Stack, upto: str) -> Tensor:
    """(3, H, W) in [0, 1]: the composite of ``stack`` from the bottom up to and including layer ``upto``."""
    from lasagna.io.render import render_stack

    doc = stack.document
    k = doc.index(upto) + 1
    pending = [
        layer.id for layer in doc.layers[:k] if isinstance(layer, LearnedLayer) and layer.id not in stack.tensors
    ]
    if pending:
        raise LasagnaError(
            f"learned layer(s) {', '.join(pending)} at or below {upto!r} have no pixels; "
            "expected them rendered first (lasagna render STACK)",
            "conditioned_on",
        )
    prefix = doc.with_layers(list(doc.layers[:k]))
    sub = Stack(
        prefix, stack.folder, {i: t for i, t in stack.tensors.items() if i in prefix.ids}, dict(stack.bit_depths)
    )
    return render_stack(sub).image.detach().float().clamp(0.0, 1.0)


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# (resolved path, size, mtime_ns) -> SHA-256: a multi-GB diffusers checkpoint is read once per process, not
# once per edit (a file rewritten in place changes its mtime, so a stale digest is not reused).
_SHA_CACHE: dict[tuple[str, int, int], str] = {}


def file_sha256(path: Path) -> str:
    stat = Path(path).stat()
    key = (str(Path(path).resolve()), stat.st_size, stat.st_mtime_ns)
    if key in _SHA_CACHE:
        return _SHA_CACHE[key]
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    _SHA_CACHE[key] = digest.hexdigest()
    return _SHA_CACHE[key]


def files_sha256(files: dict[str, Path]) -> dict[str, str]:
    """SHA-256 of each file by name (the files that exist; a missing one is simply not listed)."""
    return {name: file_sha256(path) for name, path in sorted(files.items()) if Path(path).is_file()}


def listing_sha256(digests: dict[str, str]) -> str:
    """One SHA-256 for several files: of their "name digest" lines, sorted by name."""
    return _sha256("".join(f"{name} {digest}\n" for name, digest in sorted(digests.items())).encode())


def changed_weights(recorded: dict[str, str], current: dict[str, str]) -> list[str]:
    """The names whose digest differs between two ``weights`` records (changed, missing or new), sorted."""
    return sorted(n for n in set(recorded) | set(current) if recorded.get(n) != current.get(n))


@dataclass
class OwnPrior:
    """A prior chosen for one edit instead of the preset's (``lasagna edit --prior``): a folder or catalogue
    name, its ControlNets (a folder's), a corrective (the preset's was fitted to its own prior, so it is not
    used), how a diffusers prior runs (``options``, over the preset's), and the conditioning image to use
    instead of the base (``control``: (C, H, W) in [0, 1] at the base's size, or None)."""

    prior: str | None = None
    controlnets: tuple[ControlNetRef, ...] = ()
    corrective: str | None = None
    options: DiffusersOptions | None = None
    control: Tensor | None = None


@dataclass
class Components:
    """What a per-image run is scored with, and the record of it: the prior and its reference, the SHA-256
    of its weights (``prior_sha``) and of every file read (``weights``), the corrective and its reference,
    a diffusers prior's ControlNets and options as used."""

    prior: Any
    prior_ref: str
    prior_sha: str | None
    corrective: Any
    corrective_ref: str | None
    weights: dict[str, str]
    controlnets: list[ControlNetRef] | None
    options: DiffusersOptions | None


def _components(
    resolved: cat.Resolved,
    label: str,
    loss: str,
    catalogue_dirs,
    device,
    refs: dict[str, Any] | None = None,
    *,
    own: OwnPrior | None = None,
    prompt: str | None = None,
    negative_prompt: str | None = None,
    options: DiffusersOptions | None = None,
) -> Components:
    """The prior and corrective of a per-image run: those the preset names, those named in ``refs`` (a
    layer's stored settings: a re-render uses what the layer was made with, not what the preset names
    today), or the user's ``own`` (then the preset's corrective is not used). ``prompt`` (free text for
    ``label``) and ``negative_prompt`` go to a text-conditioned prior; ``options`` (stored settings) or
    ``own.options`` replace the preset's diffusers options."""
    preset = resolved.preset
    refs = dict(refs or {})
    here = resolved.preset_file.parent
    if own is not None and own.prior is not None:
        refs = {"prior": own.prior, "corrective": own.corrective}
    prior_ref = refs.get("prior") or preset.prior
    corrective_ref = refs["corrective"] if "corrective" in refs else preset.corrective
    user = own is not None and own.prior is not None  # paths are the user's own (absolute), not the preset's
    if loss == "lmc-sds" and corrective_ref is None:  # before the prior is loaded: a refusal costs nothing
        hint = (
            "--corrective PATH (fit one: lasagna train-corrective --kind spectral --prior PATH)"
            if user
            else "another --loss or a preset with a corrective"
        )
        raise LasagnaError(
            f"loss 'lmc-sds' needs a corrective (b-hat of LMC-SDS eq. 10) and none is given; expected {hint}",
            "loss",
        )
    source = cat.prior_source(
        prior_ref,
        controlnets=own.controlnets if own is not None else (),
        catalogue_dirs=catalogue_dirs,  # raises, listing the priors there are
        relative_to=here if "/" in prior_ref and not user else None,
    )
    opts = options or (own.options if own is not None else None) or preset.diffusers or DiffusersOptions()
    prior = cat.load_prior(
        source,
        preset=preset,
        device=device,
        options=opts,
        prompts={label: prompt} if prompt else None,
        negative_prompt=negative_prompt,
    )
    known = tuple(getattr(prior, "vocabulary", ()) or ())
    directions = bool(getattr(getattr(prior, "config", None), "directions", False))  # any az=…,el=… (UNetPrior)
    if known and label not in known and not directions:
        raise ConditionError(
            f"label {label!r} of preset {preset.name!r} is not one prior {prior_ref!r} was trained on; "
            f"expected one of {', '.join(known)}"
            + (" (a direction az=…,el=… needs a prior trained with --directions)" if "=" in label else ""),
            "condition.label",
        )
    diffusers = source.kind == "diffusers"
    weights = files_sha256(source.files(opts.variant if diffusers else None))
    prior_sha = listing_sha256(weights) if diffusers else weights.get("prior/model.safetensors")
    corrective = None
    if loss == "lmc-sds":
        corrective_dir = cat.find(
            corrective_ref,
            "corrective",
            catalogue_dirs=catalogue_dirs,
            relative_to=here if "/" in corrective_ref and not user else None,
        )
        corrective = cat.load_corrective(corrective_dir, device=device)
        weights.update(
            files_sha256({f"corrective/{n}": corrective_dir / n for n in ("model.safetensors", "config.json")})
        )
    return Components(
        prior=prior,
        prior_ref=str(prior_ref),
        prior_sha=prior_sha,
        corrective=corrective,
        corrective_ref=corrective_ref if loss == "lmc-sds" else None,
        weights=weights,
        controlnets=list(source.controlnets) if diffusers else None,
        options=opts if diffusers else None,
    )


def _distill_settings(preset, *, refine: bool, steps: int | None, loss, guidance, seed, lr, **more):
    from lasagna.distill.schedules import Weights

    settings = DistillSettings.from_preset(preset, loss=loss, guidance=guidance, steps=steps, seed=seed, lr=lr, **more)
    return settings.model_copy(update={"weights": Weights()}) if refine else settings


@dataclass
class LoadedGenerator:
    """A preset's amortised generator, loaded and checked once: the network, its files' bytes (copied into
    every stack made with it) and their SHA-256."""

    net: Any  # lasagna.generators.unet.LayerGenerator, in eval mode on its device
    weights: bytes
    config: bytes
    sha256: str
    config_sha256: str


def load_generator(resolved: cat.Resolved, generator_dir: Path | None, device: str | torch.device = "cpu"):
    """The amortised generator in ``generator_dir`` (the preset's), checked against the preset's layer."""
    from lasagna.generators.unet import LayerGenerator

    preset = resolved.preset
    if generator_dir is None:
        raise LasagnaError(
            f"preset {preset.name!r} has no amortised generator yet (train one: lasagna train-layer "
            f"--preset {preset.name}); expected --generator free",
            "generator",
        )
    weights = (generator_dir / "model.safetensors").read_bytes()
    config = (generator_dir / "config.json").read_bytes()
    net = LayerGenerator.from_pretrained(generator_dir, device=device)
    cat.check_generator(net, preset, str(generator_dir))
    return LoadedGenerator(net, weights, config, _sha256(weights), _sha256(config))


def working_side(preset, working: int | Literal["preset", "full"] = "preset") -> int | None:
    """The long side a layer is made at: the preset's ``working_size``, a stored side, or None (full size)."""
    return {"preset": preset.working_size, "full": None}.get(working, working)  # type: ignore[arg-type]


def working_input(base: Tensor, side: int | None, device: str | torch.device = "cpu") -> Tensor:
    """(1, 3, h, w): ``base`` (3, H, W) on ``device`` at the working size for long side ``side``."""
    from lasagna.compose.resample import downsample, working_size

    return downsample(base.to(device)[None], working_size(*base.shape[-2:], side))


def make_layer(
    base: Tensor,
    resolved: cat.Resolved,
    label: str,
    layer_id: str,
    *,
    method: Method,
    optimize: int,
    generator_dir: Path | None,
    loss: str | None = None,
    guidance: float | None = None,
    seed: int | None = None,
    lr: float | None = None,
    distill: DistillSettings | None = None,
    refs: dict[str, Any] | None = None,
    catalogue_dirs=None,
    device: str | torch.device = "cpu",
    progress: bool = False,
    working: int | Literal["preset", "full"] = "preset",
    loaded: LoadedGenerator | None = None,
    initial: Tensor | None = None,
    own: OwnPrior | None = None,
    prompt: str | None = None,
    negative_prompt: str | None = None,
    options: DiffusersOptions | None = None,
    control: Tensor | None = None,
    overrides: dict[str, Any] | None = None,
    callback: Callable[[int, Tensor], None] | None = None,
) -> LayerRun:
    """One learned layer (C, H, W) for ``base`` (3, H, W) in [0, 1] and ``label`` (module docstring).

    ``own``: the user's prior instead of the preset's (``OwnPrior``; its ``control`` image, too);
    ``prompt``/``negative_prompt``: the layer's free text (a text-conditioned prior); ``options`` and
    ``control`` (C, H, W): a diffusers prior's stored options and conditioning image, for a re-render;
    ``overrides``: more ``DistillSettings`` fields over the preset's (``t_min``, ``t_max``, ``aspect``).

    ``distill`` (stored settings) replaces the preset defaults and the loss/guidance/seed/lr overrides,
    and ``refs`` (``prior``, ``corrective``) the preset's prior and corrective: how ``render_learned``
    reruns a layer exactly as it was made. The layer is made at the preset's ``working_size`` (``working``:
    a stored side, or ``"full"`` for a layer made at the base's size) and enlarged to the base's size
    (`lasagna.compose.resample`).

    ``loaded`` is the generator already loaded from ``generator_dir`` (``load_generator``), and ``initial``
    its output (1, C, h, w) for this base at the working size (``working_input``), computed by the caller
    in a batch (``lasagna.batch``); without them the generator is loaded and run here. ``callback(step,
    layer)`` is called before every per-image step (``lasagna.distill.distill_image``): a progress report
    for the editor (``lasagna.serve``), which cancels a run by raising from it.
    """
    from lasagna.compose.resample import upsample
    from lasagna.distill import distill_image
    from lasagna.generators.free import FreeLayer

    preset = resolved.preset
    start = time.monotonic()
    full = tuple(base.shape[-2:])
    side = working_side(preset, working)
    x = working_input(base, side, device)  # (1, 3, h, w)
    files: dict[str, bytes] = {}
    gen_ref = None
    if method != "amortised":
        initial = None
    else:
        if loaded is None:
            loaded = load_generator(resolved, generator_dir, device)
        if initial is None:
            with torch.no_grad():
                initial = loaded.net(x, [label]).float()
        rel = f"{GENERATORS_DIR}/{layer_id}"
        files = {f"{rel}/model.safetensors": loaded.weights, f"{rel}/config.json": loaded.config}
        # Weights and config under checksums both: the config's vocabulary says which label is which.
        gen_ref = {
            "checkpoint": f"{rel}/model.safetensors",
            "sha256": loaded.sha256,
            "config_sha256": loaded.config_sha256,
        }
    settings = LayerSettings(method=method, optimize=optimize, working_size=side)
    history: list[dict[str, Any]] = []
    stopped = None
    layer = initial
    if optimize > 0 or method == "per-image":
        if distill is not None:
            ds = distill
        else:
            ds = _distill_settings(
                preset,
                refine=initial is not None,
                steps=optimize,
                loss=loss,
                guidance=guidance,
                seed=seed,
                lr=lr,
                **(overrides or {}),
            )
        parts = _components(
            resolved,
            label,
            ds.loss,
            catalogue_dirs,
            device,
            refs,
            own=own,
            prompt=prompt,
            negative_prompt=negative_prompt,
            options=options,
        )
        control = control if control is not None else (own.control if own is not None else None)
        control_ref = None
        if control is not None:
            from lasagna.io.png import encode_png

            # Stored as a 16-bit PNG in the stack, and used as stored, so a re-render sees the same values.
            control = control.float().clamp(0, 1).mul(65535).round().div(65535)
            control_ref = f"{CONTROLS_DIR}/{layer_id}.png"
            files[control_ref] = encode_png(control.numpy(), bit_depth=16, where="control image")
            control = working_input(control, side, device)
        model = "free" if initial is None else FreeLayer.from_layer(ds.layer, initial)
        run = distill_image(
            x,
            ds,
            parts.prior,
            parts.corrective,
            condition=label,
            generator=model,
            progress=progress,
            control=control,
            callback=callback,
        )
        layer, history, stopped = run.layer.float(), run.history, run.stopped_reason
        settings = LayerSettings(
            method=method,
            optimize=ds.steps,
            prior=parts.prior_ref,
            prior_sha256=parts.prior_sha,
            corrective=parts.corrective_ref,
            controlnets=parts.controlnets,
            diffusers=parts.options,
            control_image=control_ref,
            weights=parts.weights,
            distill=ds,
            working_size=side,
        )
    if layer is None:  # unreachable: an amortised run has its forward pass, a per-image run its optimisation
        raise LasagnaError(f"no layer was made (method {method!r}, optimize {optimize})", "make_layer")
    layer = upsample(layer.detach(), full)  # a convex combination of in-range values: still in range
    return LayerRun(
        layer=layer[0].cpu(),
        settings=settings,
        files=files,
        generator_ref=gen_ref,
        seconds=time.monotonic() - start,
        history=history,
        stopped=stopped,
    )


def choose_method(resolved: cat.Resolved, method: str | None) -> Method:
    """``method`` (``free`` is ``per-image``) when given; else the preset's ``method``; else ``amortised`` when
    the preset has a generator. A preset asking for ``amortised`` without a generator falls back to per-image."""
    if method is not None:
        return canonical_method(method)
    if resolved.preset.method == "per-image" or resolved.generator is None:
        return "per-image"
    return "amortised"


def default_steps(resolved: cat.Resolved, method: Method) -> int:
    """Per-image steps when none are given: the preset's ``refine_steps`` after an amortised pass, its
    ``distill.steps`` for a per-image layer."""
    preset = resolved.preset
    return preset.refine_steps if method == "amortised" else preset.distill.steps
