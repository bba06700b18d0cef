"""Making one learned layer: the amortised generator's forward pass, per-image distillation, or both.

``make_layer(recipe, base, id)`` is the one place a learned layer's pixels are computed, for ``lasagna edit``,
``lasagna render`` and the editor alike; it only computes: every choice is the ``lasagna.recipe.Recipe``'s
(``lasagna.editing`` describes the methods and what the stack records). The generator's input is
``conditioning_input``: the composite of the stack up to and including the layer it is conditioned on.
``as_stored`` replaces tensors by what their PNGs will hold, so an edit is computed from, and composited
with, exactly the values its stack folder keeps — which is what lets a re-render reproduce it bit for bit.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import torch
from torch import Tensor

from lasagna.components import LoadedGenerator
from lasagna.document import LearnedLayer
from lasagna.errors import ConditionError, LasagnaError
from lasagna.io.stack import Stack
from lasagna.recipe import METHODS, LayerSettings, Recipe, choose_method, default_steps
from lasagna.request import canonical_method

STACK_GENERATORS_DIR = "generators"  # <stack>/generators/<layer id>/: copies of the generators a stack uses
CONTROLS_DIR = "controls"  # <stack>/controls/<layer id>.png: the user's conditioning image of a layer


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
    normals: Tensor | None = None  # a surface layer's unit normals (3, H, W); ``layer`` is then its multiplier
    source_light: str | None = None  # a surface relight's source light (given, or estimated)
    made_by: dict[str, Any] = field(default_factory=dict)  # a surface layer's record (``SurfaceLayer.made_by``)


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


def working_input(base: Tensor, side: int | None, device: str | torch.device = "cpu") -> Tensor:
    """(1, 3, h, w): ``base`` (3, H, W) on ``device`` at the working size for long side ``side``."""
    from lasagna.compose.resample import downsample, working_size

    return downsample(base.to(device)[None], working_size(*base.shape[-2:], side))


def layer_input(recipe: Recipe, base: Tensor, device: str | torch.device = "cpu") -> Tensor:
    """(1, 3, h, w): what ``recipe``'s layer is made from — ``base`` (3, H, W) at the working size, or, for a colour
    over luminance (``LayerSpec.luminance`` "base"), its Rec. 709 luma as a gray image (the colorize task's input:
    a colour photograph and its grayscale get the same layer)."""
    from lasagna.compose.color import luma

    x = working_input(base, recipe.working_size, device)
    if _luminance(recipe) == "base":
        x = luma(x).expand(-1, 3, -1, -1).contiguous()
    return x


def make_layer(
    recipe: Recipe,
    base: Tensor,
    layer_id: str,
    *,
    device: str | torch.device = "cpu",
    progress: bool = False,
    loaded: LoadedGenerator | None = None,
    initial: Tensor | None = None,
    callback: Callable[[int, Tensor], None] | None = None,
) -> LayerRun:
    """The learned layer (C, H, W) ``recipe`` makes for ``base`` (3, H, W) in [0, 1] (module docstring): the
    amortised generator's pass at the recipe's working size, then its per-image steps (``recipe.distill``),
    enlarged to the base's size (``lasagna.compose.resample``). Nothing is decided here.

    ``loaded`` is the recipe's generator already loaded (``LoadedGenerator.read``), and ``initial`` its output
    (1, C, h, w) for this base at the working size (``layer_input``), computed by the caller in a batch
    (``lasagna.batch``); without them the generator is loaded and run here. ``callback(step, layer)`` is
    called before every per-image step (``lasagna.distill.distill_image``): a progress report for the editor
    (``lasagna.serve``), which cancels a run by raising from it."""
    from lasagna.compose.color import luma
    from lasagna.compose.resample import guided_upsample, upsample, upsample_colour

    if recipe.kind == "surface":
        return _make_surface(recipe, base, device, callback)
    start = time.monotonic()
    x = layer_input(recipe, base, device)  # (1, 3, h, w)
    over_luminance = _luminance(recipe) == "base"
    files: dict[str, bytes] = {}
    gen_ref = dict(recipe.stored) if recipe.stored is not None else None
    layer = None
    if recipe.method == "amortised":
        loaded = loaded or LoadedGenerator.read(recipe.generator, recipe.preset, device)
        if initial is None:
            with torch.no_grad():
                initial = loaded.net(x, [recipe.label]).float()
        if recipe.stored is None:  # a copy into the stack; a re-render keeps the one it has
            rel = f"{STACK_GENERATORS_DIR}/{layer_id}"
            files = {f"{rel}/model.safetensors": loaded.weights, f"{rel}/config.json": loaded.config}
            # Weights and config under checksums both: the config's vocabulary says which label is which.
            gen_ref = {
                "checkpoint": f"{rel}/model.safetensors",
                "sha256": loaded.sha256,
                "config_sha256": loaded.config_sha256,
            }
        layer = initial
    if layer is None and recipe.distill is not None and recipe.distill.start == "surface":
        layer = _surface_start(recipe, x, device)
    settings = LayerSettings(method=recipe.method, optimize=recipe.steps, working_size=recipe.working_size)
    history: list[dict[str, Any]] = []
    stopped = None
    if recipe.distill is not None:
        start_layer = layer
        run, settings = _optimise(recipe, x, layer, layer_id, files, device, progress, callback)
        layer, history, stopped = run.layer.float(), run.history, run.stopped_reason
        lo, hi = recipe.distill.layer.range
        if recipe.distill.lock == "planar":
            start_layer = torch.ones_like(layer) if start_layer is None else start_layer.to(layer)
            layer = planar_lock(layer, start_layer).clamp(lo, hi)
        if recipe.distill.objects_only:
            layer = objects_lock(layer, start_layer.to(layer), _start_objects(recipe, x, device).to(layer))
            layer = layer.clamp(lo, hi)
    if layer is None:  # unreachable: an amortised run has its forward pass, a per-image run its optimisation
        raise LasagnaError(f"no layer was made (method {recipe.method!r}, steps {recipe.steps})", "make_layer")
    if over_luminance:  # the colour follows the base's edges and carries its luma at full size
        layer = upsample_colour(layer.detach(), luma(base.to(layer.device)[None].float()))
    elif _enlarge(recipe) == "guided" and tuple(layer.shape[-2:]) != tuple(base.shape[-2:]):
        # The layer's edges follow the image's (the fast guided filter, the base's luma as guide): an affine map of
        # the guide per window may step outside the layer's range, so it is clamped back into it.
        lo, hi = recipe.distill.layer.range if recipe.distill is not None else recipe.preset.range
        layer = guided_upsample(layer.detach(), luma(base.to(layer.device)[None].float())).clamp(lo, hi)
    else:
        layer = upsample(layer.detach(), tuple(base.shape[-2:]))  # a convex combination of in-range values: in range
    return LayerRun(
        layer=layer[0].cpu(),
        settings=settings,
        files=files,
        generator_ref=gen_ref,
        seconds=time.monotonic() - start,
        history=history,
        stopped=stopped,
    )


@torch.no_grad()
def _surface_start(recipe: Recipe, x: Tensor, device) -> Tensor:
    """The start (1, 1, h, w) of a free layer that refines a surface (``distill.start == "surface"``): the preset's
    surface estimate of ``x`` (the working input) at ``surface.working_size`` with its dome prior and symmetry
    ensemble, its walls calmed by ``surface.start_wall_relief`` and the whole deepened by ``surface.start_relief`` (an
    estimator's regression to the mean makes it shallow where it is
    unsure; the distillation's start wants the relief, a surface layer the estimate as it is), rendered under
    the condition's light — S(l) for an unlit base, S(l)/S(l_src) for a lit one (the source light as fitted:
    ``surface.light_calibration`` is the surface layer's, since a calibrated, steeper source light makes S(l_src)
    small on surfaces facing away from it and the free layer's correction paints glows there) — clamped to the
    layer's range. The free layer's per-pixel steps then correct what one surface cannot say (a free residual
    on a surface)."""
    from lasagna.compose.surface import lambert, light_vector
    from lasagna.document.condition import parse_direction
    from lasagna.generators.surface import DomePrior, SurfaceEstimator

    net = SurfaceEstimator.from_pretrained(recipe.estimator, device=device)
    sd = recipe.surface
    dome = DomePrior(weight=sd.dome_weight, height=sd.dome_height)
    normals, source = net.estimate_at(
        x.float(),
        dome,
        side=sd.working_size,
        symmetry=sd.symmetry,
        relief=sd.start_relief,
        flat_walls=sd.flat_walls,
        wall_relief=sd.start_wall_relief,
    )
    target = light_vector(*parse_direction(recipe.label), device=normals.device)[None]
    layer = lambert(normals, target) if source is None else lambert(normals, target) / lambert(normals, source)
    lo, hi = recipe.distill.layer.range
    return layer.clamp(lo, hi)


def _start_objects(recipe: Recipe, x: Tensor, device) -> Tensor:
    """The probability (1, 1, h, w) that each pixel of the working input ``x`` lies on an object: the surface
    start's estimator's silhouette head, read as the start reads ``x`` (at ``surface.working_size``, its symmetry
    ensemble), enlarged bilinearly to ``x``'s size."""
    from lasagna.compose.resample import downsample, upsample, working_size
    from lasagna.generators.surface import SurfaceEstimator

    net = SurfaceEstimator.from_pretrained(recipe.estimator, device=device)
    sd = recipe.surface
    small = downsample(x.float(), working_size(*x.shape[-2:], sd.working_size))
    return upsample(net.silhouette(small, sd.symmetry), tuple(x.shape[-2:])).clamp(0.0, 1.0)


def objects_lock(layer: Tensor, start: Tensor, objects: Tensor) -> Tensor:
    """``layer`` (N, C, h, w) with its correction to ``start`` kept on the objects only (``distill.objects_only``):
    start · exp(p · log(layer / start)) = start · (layer / start)^p, p ∈ [0, 1] the silhouette probability (N, 1,
    h, w), in float64 — a wall (p = 0) keeps the surface start (a flat painted wall stays flat), an object (p = 1)
    the distilled layer; both floored at ``LOCK_EPS`` before the logarithm, as ``planar_lock``."""
    s = start.clamp_min(LOCK_EPS).double()
    r = (layer.clamp_min(LOCK_EPS).double() / s).log()
    return (s * (objects.double() * r).exp()).to(layer.dtype)


# The floor of a layer and its start before their logarithms (``planar_lock``): a multiplier of 0 (black) is
# read as 1e-4, an 80 dB attenuation, far below an 8-bit code; such pixels keep their place in the fit without
# an infinite weight.
LOCK_EPS = 1e-4


def planar_lock(layer: Tensor, start: Tensor) -> Tensor:
    """``layer`` (N, C, h, w) with the planar trend of its correction to ``start`` removed (``distill.lock`` 'planar').

    With r = log(max(layer, ε) / max(start, ε)) and its least-squares plane a + b·u + c·v over each channel's pixels
    (u, v the column and row in [−1, 1], solved in float64), the result is start · exp(r − b·u − c·v): the level a
    and what no plane explains of the correction are kept, its tilt across the image is not — so the distillation may
    brighten, darken and reshape a surface's relight but cannot turn its light toward another side."""
    n, c, h, w = layer.shape
    r = (layer.clamp_min(LOCK_EPS).double() / start.clamp_min(LOCK_EPS).double()).log()
    v, u = torch.meshgrid(
        torch.linspace(-1.0, 1.0, h, dtype=torch.float64, device=layer.device),
        torch.linspace(-1.0, 1.0, w, dtype=torch.float64, device=layer.device),
        indexing="ij",
    )
    design = torch.stack([torch.ones_like(u), u, v], -1).reshape(h * w, 3)
    coef = torch.linalg.lstsq(design, r.reshape(n * c, h * w).T).solution  # (3, n·c)
    tilt = (design[:, 1:] @ coef[1:]).T.reshape(n, c, h, w)
    return (start.clamp_min(LOCK_EPS).double() * (r - tilt).exp()).to(layer.dtype)


def _enlarge(recipe: Recipe) -> str:
    """How the layer is enlarged from the working size (``LayerSpec.enlarge``): the distillation settings' (recorded
    with a layer, so a layer made before the guided enlargement re-renders as it was made), else the preset's."""
    if recipe.distill is not None:
        return recipe.distill.layer.enlarge
    return recipe.preset.enlarge


def _luminance(recipe: Recipe) -> str:
    """Where the layer's luminance comes from (``LayerSpec.luminance``): the distillation settings' (recorded with a
    layer, so a layer made before colour over luminance re-renders as it was made), else the preset's."""
    if recipe.distill is not None:
        return recipe.distill.layer.luminance
    return recipe.preset.luminance


def _make_surface(recipe: Recipe, base: Tensor, device, callback) -> LayerRun:
    """A surface layer (``recipe.kind == "surface"``): the estimator's surface (height or normals) at the working
    size, refined by ``recipe.steps`` multi-light score-distillation steps when asked, enlarged bicubically to the
    base's size; its normals, its source light (a lit input's: fitted, or given — the estimate then turned to its
    azimuth, ``turn_to_azimuth``) and the multiplier they render
    to under the condition's light — through the 16-bit map the stack will store, so it is what the stack
    renders."""
    from lasagna.components import load_prior
    from lasagna.compose.layer import LayerTensors
    from lasagna.compose.surface import (
        enlarge_surface,
        light_vector,
        surface_normals,
        surface_tensors,
        turn_to_azimuth,
    )
    from lasagna.distill.surface import distill_surface
    from lasagna.document.condition import AMBIENT, parse_direction
    from lasagna.generators.surface import DomePrior, SurfaceEstimator
    from lasagna.io.stack import stored_normals

    start = time.monotonic()
    reading = None
    if recipe.source_within is not None:  # a rough reading of the source light: its elevation fused with the fit's
        reading = recipe.source_light
        recipe = replace(recipe, source_light=fused_source_light(recipe, base, device))
    net = SurfaceEstimator.from_pretrained(recipe.estimator, device=device)
    x = working_input(base, recipe.working_size, device)  # (1, 3, h, w)
    sd = recipe.surface
    dome = DomePrior(weight=sd.dome_weight, height=sd.dome_height)
    given = None
    if net.config.input == "lit" and recipe.source_light is not None:
        given = light_vector(*parse_direction(recipe.source_light), device=x.device)[None]
    with torch.no_grad():
        surface, fitted = net.estimate(
            x,
            dome,
            symmetry=sd.symmetry,
            elevation=sd.light_calibration,
            source_elevation=sd.source_elevation,
            flat_walls=sd.flat_walls,
            light=given if net.config.light_input else None,  # an estimator that reads the light is told it
            wall_relief=sd.wall_relief,
        )
    source = None
    turned = None
    if net.config.input == "lit":
        source = recipe.source_light or light_condition(fitted[0])
        if given is not None:
            # A given source light is adopted, not only divided by: the estimate turned about the view axis to its
            # azimuth (turn_to_azimuth), so the relief the estimate found for the source shading moves with it.
            surface = turn_to_azimuth(surface_normals(surface), fitted, given.to(fitted))
            turned = light_condition(fitted[0])
    history: list[dict[str, Any]] = []
    made_by: dict[str, Any] = {
        "preset": recipe.preset.name,
        "estimator_sha256": recipe.estimator_sha256,
        "working_size": recipe.working_size,
        "reads": net.config.input,  # "lit": a relight's estimator, which a source light can be told (reread_surface)
    }
    if dome.weight > 0:
        made_by.update(dome_weight=dome.weight, dome_height=dome.height)
    if sd.symmetry != "none":
        made_by.update(symmetry=sd.symmetry)
    if sd.flat_walls > 0:
        made_by.update(flat_walls=sd.flat_walls)
    if recipe.source_light is not None and recipe.preset.surface.told is not None:
        made_by.update(told_estimator=sd.estimator)  # the estimator a told light reads (SurfaceDefaults.told)
    if sd.wall_relief != 1.0:
        made_by.update(wall_relief=sd.wall_relief)
    if reading is not None:  # the reader's light and its σ; the stack stores the fused light it was told
        made_by.update(source_read=reading, source_within=recipe.source_within)
    if turned is not None:
        made_by.update(turned_from=turned)  # the fitted light the estimate was turned from to the given one
    if net.config.input == "lit" and recipe.source_light is None and sd.source_elevation != "fit":
        made_by.update(source_elevation=sd.source_elevation)
    if net.config.input == "lit" and recipe.source_light is None and sd.light_calibration is not None:
        made_by.update(light_calibration=list(sd.light_calibration))
    if recipe.distill is not None:
        prior = load_prior(recipe.prior, preset=recipe.preset, device=device)
        ds, sd = recipe.distill, recipe.surface
        src = None if source is None else light_vector(*parse_direction(source), device=device)[None]
        whole = 1.0
        if sd.refine_size is not None and sd.refine_size != recipe.working_size:
            # Refined at another size: the estimate enlarged to it (heights in canvas units), scored like a free
            # layer at that size — the whole image first, then crops at native resolution.
            x = working_input(base, sd.refine_size, device)
            surface = enlarge_surface(surface, tuple(x.shape[-2:]))
            whole = ds.patches.whole_fraction
            made_by.update(refine_size=sd.refine_size)
        weight = None
        if sd.refine_objects:  # the walls keep the estimate: the correction weighted by the silhouette probability
            with torch.no_grad():
                weight = net.silhouette(working_input(base, recipe.working_size, device), sd.symmetry)
            if tuple(weight.shape[-2:]) != tuple(x.shape[-2:]):
                weight = torch.nn.functional.interpolate(weight, size=tuple(x.shape[-2:]), mode="bilinear")
            made_by.update(refine_objects=True)
        fit = distill_surface(
            x,
            prior,
            init_surface=surface,
            lights=list(recipe.preset.vocabulary),
            source=src,
            steps=recipe.steps,
            lights_per_step=sd.lights_per_step,
            lr=sd.lr,
            anchor=sd.anchor,
            guidance=ds.guidance,
            loss=ds.loss,
            t_min=ds.t_min,
            t_max=ds.t_max,
            seed=ds.seed,
            aspect=ds.aspect,
            refine_source=sd.refine_light and recipe.source_light is None,
            lock_sigma=sd.refine_lock,
            smooth_sigma=sd.refine_smooth,
            callback=callback,
            whole_fraction=whole,
            weight=weight,
        )
        surface, history = fit.surface, fit.history
        made_by.update(
            refine_steps=recipe.steps,
            lights_per_step=sd.lights_per_step,
            refine_lr=sd.lr,
            anchor=sd.anchor,
            prior=recipe.prior_ref,
            prior_sha256=recipe.prior_sha256,
        )
        if sd.refine_lock > 0:
            made_by.update(refine_lock=sd.refine_lock)
        if sd.refine_smooth > 0:
            made_by.update(refine_smooth=sd.refine_smooth)
        if sd.refine_light and recipe.source_light is None and fit.source is not None:
            source = light_condition(fit.source[0])  # the refined light, as the stack stores and renders it
            made_by.update(refine_light=True)
    if sd.closer_walls is not None:
        surface = walls_read_closer(net, base, surface, sd, given, device)
        made_by.update(closer_walls=sd.closer_walls.model_dump())
    size = tuple(base.shape[-2:])
    if recipe.surface.enlarge != "bicubic" and tuple(surface.shape[-2:]) != size:
        # The relief's edges follow the image's, not the working size's pixel grid (a 32² normal map enlarged 16×
        # bicubically shows it as a staircase, and spreads an object's rim a working pixel into a sky), the base's
        # luma as guide: 'guided', the fast guided filter; 'bilateral', joint bilateral upsampling (round 21).
        from lasagna.compose.color import luma
        from lasagna.compose.resample import guided_upsample, joint_bilateral_upsample
        from lasagna.compose.surface import facing_normals

        enlarge = guided_upsample if recipe.surface.enlarge == "guided" else joint_bilateral_upsample
        guide = luma(base.to(surface.device)[None].float())
        normals = facing_normals(enlarge(surface_normals(surface), guide))[0].cpu()
        made_by.update(enlarge=recipe.surface.enlarge)
    else:
        normals = surface_normals(enlarge_surface(surface, size))[0].cpu()
    stored = LayerTensors(stored_normals(normals))  # what the 16-bit map gives back, made a band at a time
    layer = surface_tensors(stored, recipe.label, source, AMBIENT).color
    settings = LayerSettings(method=recipe.method, optimize=recipe.steps, working_size=recipe.working_size)
    return LayerRun(
        layer=layer.float(),
        settings=settings,
        files={},
        generator_ref=None,
        seconds=time.monotonic() - start,
        history=history,
        normals=normals,
        source_light=source,
        made_by=made_by,
    )


@torch.no_grad()
def walls_read_closer(net, base: Tensor, surface: Tensor, sd, light: Tensor | None, device) -> Tensor:
    """Unit normals (1, 3, h, w) at ``sd.closer_walls.size``: ``surface`` (the working-size read, refined where
    asked: a height field or normals) on the objects, the image read again at that size on the walls, mixed by
    the working-size read's silhouette probability p (dilated by ``keep_rims`` working-size pixels, where the
    closer read sees a wall when ``rims_by_closer``) —
    normalise(p·n_working + (1 − p)·n_closer) — as
    ``SurfaceDefaults.closer_walls`` says. The closer read uses the same dome prior and symmetry ensemble, its walls
    calmed by the closer read's own ``wall_relief``; told a source light (``light`` (1, 3)), it is told it too and
    turned to its azimuth as the working-size read is (`turn_to_azimuth`). Measured in docs/BENCHMARKS.md, round
    20 (rules OW3–OW5)."""
    from lasagna.compose.surface import calm_walls, enlarge_surface, facing_normals, surface_normals, turn_to_azimuth
    from lasagna.generators.surface import DomePrior

    closer = sd.closer_walls
    if not net.config.silhouette:
        raise LasagnaError(
            "closer_walls needs an estimator with a silhouette head (train-surface --silhouette); this one has none",
            "closer_walls",
        )
    dome = DomePrior(weight=sd.dome_weight, height=sd.dome_height)
    x = working_input(base, closer.size, device)
    own = closer.gate == "own"
    near, fitted = net.estimate(
        x,
        dome,
        symmetry=sd.symmetry,
        light=light if net.config.light_input else None,
        wall_relief=closer.wall_relief if own else 1.0,
    )
    near = surface_normals(near)
    if light is not None and fitted is not None:
        near = turn_to_azimuth(near, fitted, light.to(fitted))
    size = tuple(near.shape[-2:])
    objects = net.silhouette(working_input(base, sd.working_size, device), sd.symmetry)
    p = torch.nn.functional.interpolate(objects, size=size, mode="bilinear").clamp(0.0, 1.0)
    if not own:  # the closer read's walls calmed where the working-size read sees a wall (CloserWalls.gate)
        near = calm_walls(near, 1.0 - p, closer.wall_relief)
    if closer.keep_rims > 0:  # the objects' rims keep the working-size read (CloserWalls.keep_rims)
        r = closer.keep_rims
        kept = torch.nn.functional.max_pool2d(objects, 2 * r + 1, stride=1, padding=r)
        kept = torch.nn.functional.interpolate(kept, size=size, mode="bilinear").clamp(0.0, 1.0)
        if closer.rims_by_closer:  # where the closer read sees an object, its sharper rim (CloserWalls.rims_by_closer)
            walls = net.silhouette(x, sd.symmetry) < RIM_OBJECT_PROBABILITY
            kept = p + (kept - p) * walls.to(p.dtype)
        p = kept
    working = surface_normals(enlarge_surface(surface, size))
    return facing_normals(working * p + near * (1.0 - p))


RIM_OBJECT_PROBABILITY = 0.5
"""The closer read's silhouette probability at and above which a pixel of the band round an object is the object's
(``CloserWalls.rims_by_closer``): the silhouette head's decision threshold, its logit 0."""


@torch.no_grad()
def fused_source_light(recipe: Recipe, base: Tensor, device) -> str:
    """The source light a surface layer is told when the reader gives theirs with an uncertainty
    (``recipe.source_within``, degrees): the reader's azimuth, and the elevation fused by inverse variance
    (`lasagna.compose.surface.fuse_elevation`) with the untold read's — the preset's own estimator and settings,
    its fit calibrated as an untold layer's is (``recipe.fit_estimator``, ``preset.surface``). A flat wall's ratio
    follows the told elevation directly, so a reading off by 10° costs more than the fit's error (docs/BENCHMARKS.md
    round 23, probes N and N2)."""
    from lasagna.compose.surface import fuse_elevation
    from lasagna.document.condition import format_direction, parse_direction
    from lasagna.generators.surface import DomePrior, SurfaceEstimator

    sd = recipe.preset.surface
    net = SurfaceEstimator.from_pretrained(recipe.fit_estimator, device=device)
    _, fitted = net.estimate(
        working_input(base, sd.working_size, device),
        DomePrior(weight=sd.dome_weight, height=sd.dome_height),
        symmetry=sd.symmetry,
        elevation=sd.light_calibration,
        source_elevation=sd.source_elevation,
        flat_walls=sd.flat_walls,
        wall_relief=sd.wall_relief,
    )
    az, el = parse_direction(recipe.source_light)
    fit_el = parse_direction(light_condition(fitted[0]))[1]
    return format_direction(az, round(fuse_elevation(el, recipe.source_within, fit_el), 2))


def light_condition(light: Tensor) -> str:
    """The condition text ``az=…,el=…`` of a unit light (3,), its angles rounded to 0.01° (the text is what the
    stack stores and renders, so it is exact: the vector is rounded, not the text)."""
    import math

    from lasagna.document.condition import format_direction

    x, y, z = (float(v) for v in light)
    az = round(math.degrees(math.atan2(y, x)) % 360.0, 2) % 360.0
    el = round(math.degrees(math.acos(max(-1.0, min(1.0, z)))), 2)
    return format_direction(az, el)


def _optimise(
    recipe: Recipe, x: Tensor, initial: Tensor | None, layer_id: str, files: dict, device, progress, callback
):
    """The per-image steps of ``recipe`` on ``x`` (1, 3, h, w), from ``initial`` (the amortised pass) or the
    identity: the distillation run and the layer's settings. ``files`` gets the control image's PNG."""
    from lasagna.components import load_corrective, load_prior
    from lasagna.distill import distill_image
    from lasagna.generators.free import FreeLayer

    ds, label = recipe.distill, recipe.label
    prior = load_prior(
        recipe.prior,
        preset=recipe.preset,
        device=device,
        options=recipe.options or recipe.preset.diffusers,
        prompts={label: recipe.prompt} if recipe.prompt else None,
        negative_prompt=recipe.negative_prompt,
    )
    known = tuple(getattr(prior, "vocabulary", ()) or ())
    directions = bool(getattr(getattr(prior, "config", None), "directions", False))  # any az=…,el=… (UNetPrior)
    if known and label not in known and not directions:
        raise ConditionError(
            f"label {label!r} of preset {recipe.preset.name!r} is not one prior {recipe.prior_ref!r} was trained "
            f"on; expected one of {', '.join(known)}"
            + (" (a direction az=…,el=… needs a prior trained with --directions)" if "=" in label else ""),
            "condition.label",
        )
    corrective = load_corrective(recipe.corrective, device=device) if recipe.corrective is not None else None
    control, control_ref = recipe.control, None
    if control is not None:
        from lasagna.io.png import encode_png

        control_ref = f"{CONTROLS_DIR}/{layer_id}.png"
        files[control_ref] = encode_png(control.numpy(), bit_depth=16, where="control image")
        control = working_input(control, recipe.working_size, device)
    model = "free" if initial is None else FreeLayer.from_layer(ds.layer, initial)
    run = distill_image(
        x,
        ds,
        prior,
        corrective,
        condition=label,
        generator=model,
        progress=progress,
        control=control,
        callback=callback,
    )
    settings = LayerSettings(
        method=recipe.method,
        optimize=ds.steps,
        prior=recipe.prior_ref,
        prior_sha256=recipe.prior_sha256,
        corrective=recipe.corrective_ref,
        controlnets=list(recipe.prior.controlnets) if recipe.prior.kind == "diffusers" else None,
        diffusers=recipe.options,
        control_image=control_ref,
        weights=dict(recipe.weights),
        distill=ds,
        working_size=recipe.working_size,
    )
    return run, settings


__all__ = [
    "CONTROLS_DIR",
    "METHODS",
    "STACK_GENERATORS_DIR",
    "LayerRun",
    "LayerSettings",
    "as_stored",
    "canonical_method",
    "check_device",
    "choose_method",
    "conditioning_input",
    "default_steps",
    "make_layer",
    "layer_input",
    "objects_lock",
    "planar_lock",
    "working_input",
]
