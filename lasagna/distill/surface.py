"""Multi-light score distillation of a surface: one height field (or normal field), scored under several lights per
step.

A free per-pixel multiplier must rediscover the geometry for every light from the prior's score. A surface
(`lasagna.compose.surface`) is lit by every light for free, so one geometry must look right under all of them:
multi-light distillation is to a surface what multi-view SDS (DreamFusion) is to a NeRF. Each step:

1. draw ``lights_per_step`` conditions per image from ``lights`` (named lights or ``az=…,el=…``);
2. render the surface h (a height field at the working size, in canvas units, or a field of normal vectors as a
   normals estimator outputs) under each: the shading S(n(h), l_k) — or, for a relight of a lit image, the
   ratio S(l_k)/S(l_src) with the source light given;
3. compose base × layer for the B·K views and score them with the prior in one batched pass (SDS or LMC-SDS
   through `lasagna.distill.objective.ScoreObjective`, conditioned on each view's light);
4. an anchor λ‖h − h₀‖² keeps the surface near its start (the estimator's, `lasagna.training.surface`), so the
   prior refines a shape rather than inventing one, and Adam steps h — and, for a relight whose source light was
   fitted rather than given (``refine_source``), that light too: the fit is made to the estimator's own surface and
   is typically 15° off (docs/BENCHMARKS.md, "Relight through a surface"), which sets the level of every flat
   region's ratio, S(l)/S(l_src) at n = +z; the prior, which sees the composite under every light, can say so.

Every random draw (lights, t, ε) comes from one generator seeded with ``seed``: the same inputs give the same
surface.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import torch
from torch import Tensor

from lasagna.compose.resample import gaussian_blur
from lasagna.compose.surface import (
    MAX_FIT_ELEVATION,
    lambert,
    light_vector,
    relight_ratio,
    surface_normals,
    surface_range,
)
from lasagna.distill.adam import Adam
from lasagna.distill.objective import ScoreObjective, build_loss, draw_patches, prior_image_size
from lasagna.distill.schedules import Weights, cosine_lr
from lasagna.document.condition import AMBIENT, parse_direction
from lasagna.errors import LasagnaError
from lasagna.generators.layer import LayerSpec
from lasagna.priors.base import Prior


@dataclass
class SurfaceFit:
    """The distilled surface (height (B, 1, h, w) or normals (B, 3, h, w), as its start), its unit normals, the source
    lights (B, 3) of a relight (refined or as given; None for an unlit base), and one record per step."""

    surface: Tensor
    normals: Tensor
    source: Tensor | None = None
    history: list[dict[str, float]] = field(default_factory=list)


def distill_surface(
    base: Tensor,
    prior: Prior,
    *,
    init_surface: Tensor,
    lights: Sequence[str],
    source: Tensor | None = None,
    steps: int = 60,
    lights_per_step: int = 4,
    lr: float = 0.01,
    anchor: float = 1.0,
    guidance: float = 1.0,
    loss: str = "sds",
    corrective=None,
    t_min: float = 0.02,
    t_max: float = 0.98,
    seed: int = 0,
    ambient: float = AMBIENT,
    aspect: str = "letterbox",
    refine_source: bool = False,
    lock_sigma: float = 0.0,
    callback: Callable[[int, Tensor], None] | None = None,
    whole_fraction: float = 1.0,
    weight: Tensor | None = None,
    smooth_sigma: float = 0.0,
) -> SurfaceFit:
    """Refine ``init_surface`` — a height field (B, 1, h, w) or unit normals (B, 3, h, w) — of the bases ``base``
    (B, 3, h, w) by multi-light score distillation (module docstring). ``source`` (B, 3): the lit bases' source
    lights (a relight: the layer is a ratio); None: the bases are unlit (albedo) and the layer is the shading.
    ``refine_source``: the source lights are stepped with the surface (unit vectors, the elevation kept below
    `lasagna.compose.surface.MAX_FIT_ELEVATION`) and returned in ``SurfaceFit.source``. ``lock_sigma`` > 0: the
    correction h − h₀ is kept without its low frequencies (a Gaussian of that width, a fraction of the long side,
    removed from it): the start's large shape — what gives a photograph's relight its direction — stays the
    estimator's, and the prior refines the rest. ``callback(step, layer)``, if given, sees each step's first view
    (detached, before the update): the editor's progress, which cancels a run by raising from it.
    ``whole_fraction`` < 1 on a base larger than the prior: the rest of the steps score random crops of the prior's
    size at native resolution (one per view), as the free layer's per-image distillation does (LMC-SDS Sec. 5), so
    the prior sees the surface's detail at the working size. ``smooth_sigma`` > 0: the correction is also blurred
    by a Gaussian of that width in pixels (kept as a band, G_f∗δ − G_σ∗δ), so no relief finer than the working
    size's pixels is made: a 32² height field enlarged to a photograph's size shows such relief as blocks."""
    if base.dim() != 4 or base.shape[1] != 3:
        raise LasagnaError(f"base has shape {tuple(base.shape)}; expected (B, 3, H, W)", "base")
    if (
        init_surface.dim() != 4
        or (init_surface.shape[0], *init_surface.shape[2:])
        != (
            base.shape[0],
            *base.shape[-2:],
        )
        or init_surface.shape[1] not in (1, 3)
    ):
        raise LasagnaError(
            f"init_surface has shape {tuple(init_surface.shape)}; expected ({base.shape[0]}, 1 or 3, "
            f"{base.shape[-2]}, {base.shape[-1]})",
            "init_surface",
        )
    if not lights or lights_per_step < 1:
        raise LasagnaError("expected at least one light and lights_per_step ≥ 1", "lights")
    vectors = torch.stack([light_vector(*parse_direction(c), dtype=base.dtype) for c in lights])  # (L, 3)
    lo, hi = surface_range(None if source is None else "source", ambient)
    spec = LayerSpec(blend="multiply", channels=1, range=(0.0, max(hi, 1.0)))
    objective = ScoreObjective(
        spec,
        prior,
        build_loss(loss, corrective, None, t_min, t_max),
        guidance,
        Weights(),
        aspect=aspect,
    )
    b, k = base.shape[0], lights_per_step
    h0 = init_surface.detach()
    height = h0.clone().requires_grad_()
    params = [height]
    light = None if source is None else source.detach().to(base.dtype).clone()
    if refine_source and light is not None:
        light.requires_grad_()
        params.append(light)
    opt = Adam(params, lr=lr)
    rng = torch.Generator().manual_seed(seed)
    views = base.repeat_interleave(k, dim=0)
    history: list[dict[str, float]] = []
    size = prior_image_size(prior)
    h, w = base.shape[-2:]
    patchable = h >= size[0] and w >= size[1] and (h, w) != tuple(size)
    whole_steps = round(whole_fraction * steps) if patchable else steps
    for step in range(steps):
        for group in opt.param_groups:
            group["lr"] = cosine_lr(lr, step, steps, 0.1)
        pick = torch.randint(0, len(lights), (b * k,), generator=rng)
        normals = surface_normals(_locked(height, h0, lock_sigma, weight, smooth_sigma)).repeat_interleave(k, dim=0)
        if light is None:
            layer = lambert(normals, vectors[pick], ambient)
        else:
            src = _unit_light(light).repeat_interleave(k, dim=0)
            layer = relight_ratio(normals, vectors[pick], src, ambient)
        if callback is not None:
            callback(step, layer[:1].detach())
        rows = None if step < whole_steps else draw_patches(b * k, (h, w), size, 1, rng)
        out = objective(views, layer, [lights[int(i)] for i in pick], rng=rng, step=step, patches=rows)
        pull = anchor * (height - h0).pow(2).mean()
        total = out.total + pull
        opt.zero_grad(set_to_none=True)
        total.backward()
        opt.step()
        history.append({"step": step, "score": out.score, "anchor": float(pull.detach()), **out.summary()})
    final = _locked(height, h0, lock_sigma, weight, smooth_sigma).detach()
    lit = None if light is None else _unit_light(light.detach())
    return SurfaceFit(surface=final, normals=surface_normals(final), source=lit, history=history)


def _locked(height: Tensor, h0: Tensor, sigma: float, weight: Tensor | None = None, smooth: float = 0.0) -> Tensor:
    """h₀ + w·(G_f ∗ δ − G_σ ∗ δ) with δ = h − h₀: the refinement's correction without its low frequencies (σ a
    fraction of the long side; 0: none removed), so the start's large shape is kept, and without its finest (G_f a
    Gaussian of ``smooth`` pixels; 0: none removed); ``weight`` w (B, 1, h, w) in [0, 1] (None: 1) says where it may
    act at all."""
    if sigma <= 0 and smooth <= 0 and weight is None:
        return height
    delta = height - h0
    kept = gaussian_blur(delta, smooth) if smooth > 0 else delta
    if sigma > 0:
        kept = kept - gaussian_blur(delta, sigma * max(height.shape[-2:]))
    return h0 + (kept if weight is None else weight * kept)


def _unit_light(v: Tensor) -> Tensor:
    """Unit lights (B, 3) from free vectors, the elevation kept below ``MAX_FIT_ELEVATION`` (as a fitted light's:
    l_z ≥ cos 85°, so S(l_src) never rests on the ambient floor over a flat region)."""
    u = v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    z_min = math.cos(math.radians(MAX_FIT_ELEVATION))
    z = u[:, 2:].clamp_min(z_min)
    xy = u[:, :2] * ((1.0 - z.pow(2)).clamp_min(0.0).sqrt() / u[:, :2].norm(dim=-1, keepdim=True).clamp_min(1e-12))
    return torch.cat([xy, z], -1)
