"""Training and evaluation data for the other layer kinds, from the same scenes.

Colourisation (the `color` preset: blend ``normal``, i.e. alpha-linear, RGBA). The base is the
grayscale of the image — Rec. 709 luma of the stored values, Y = 0.2126 R + 0.7152 G + 0.0722 B,
replicated to RGB — and the target is the colour image. The ground-truth layer is the image itself
with α = 1: a ``normal`` layer composes as Cb + α(Cs − Cb), which with α = 1 is Cs (exactly in real
arithmetic; within one float rounding, 1e-16 in float64, in the engine), so the gray base is fully
replaced and base + layer reproduces the target.

Additive light (the `light` preset: blend ``plus``, RGB). A coloured point light at ``glow_position``
(a fill light in front of the scene near the view axis; it casts no shadows) whose colour comes from
its label (warm, cool, white: `lasagna.world.lighting.GLOW_VOCABULARY`) adds, at a surface point P with
normal n and albedo ρ,

    reflected = ρ ⊙ c · I · max(0, n·ω) / (1 + (d / d₀)²),   ω = (q − P)/d,  d = |q − P|,  d₀ = 1,

plus a halo of the light itself seen through the lens, c · I_h · exp(−r²/(2σ²)) with r the in-plane
distance from the light. The glow is clipped to the head-room, glow = min(reflected + halo,
1 − image), so that lit = image + glow ≤ 1 holds exactly: the ``plus`` layer's ground truth is
``glow`` (≥ 0) and composing it onto the image gives ``lit`` with no clamp involved.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from lasagna.world.scene import Scene, pixel_grid

Tensor = torch.Tensor

REC709 = (0.2126, 0.7152, 0.0722)
"""Rec. ITU-R BT.709 luma weights, applied to stored (sRGB-encoded) values as image editors do."""
GLOW_FALLOFF = 1.0
"""d₀ of the point light's 1/(1 + (d/d₀)²) fall-off, in world units (the canvas is 2 units wide)."""


@dataclass(frozen=True)
class Colorization:
    """base (B, 3, H, W) gray, target (B, 3, H, W) colour, layer (B, 4, H, W) RGBA with α = 1."""

    base: Tensor
    target: Tensor
    layer: Tensor
    scene: Scene


@dataclass(frozen=True)
class AdditiveLight:
    """base (B, 3, H, W) the unlit image, glow (B, 3, H, W) ≥ 0 the plus layer, lit = base + glow."""

    base: Tensor
    glow: Tensor
    lit: Tensor
    scene: Scene


def luma(image: Tensor) -> Tensor:
    """Rec. 709 luma (B, 1, H, W) of stored RGB values (B, 3, H, W)."""
    r, g, b = REC709
    return r * image[:, 0:1] + g * image[:, 1:2] + b * image[:, 2:3]


def colorization(scene: Scene) -> Colorization:
    """Gray base, colour target and the α = 1 ``normal`` layer that maps one onto the other."""
    gray = luma(scene.image).expand(-1, 3, -1, -1).contiguous()
    layer = torch.cat([scene.image, torch.ones_like(scene.image[:, :1])], dim=1)
    return Colorization(base=gray, target=scene.image, layer=layer, scene=scene)


def glow(scene: Scene) -> Tensor:
    """The point light's contribution before clipping: (B, 3, H, W), ≥ 0 (see the module docstring)."""
    p = scene.params
    dtype, device = scene.image.dtype, scene.image.device
    b, _, h, w = scene.image.shape
    xs, ys = pixel_grid(h, w, dtype, device)
    q = p.glow_position.to(dtype=dtype, device=device)
    color = p.glow_color.to(dtype=dtype, device=device)[:, :, None, None]
    inten = p.glow_intensity.to(dtype=dtype, device=device).view(b, 1, 1, 1)
    vx = q[:, 0].view(b, 1, 1, 1) - xs.view(1, 1, 1, w)
    vy = q[:, 1].view(b, 1, 1, 1) - ys.view(1, 1, h, 1)
    vz = q[:, 2].view(b, 1, 1, 1) - scene.depth
    d2 = vx * vx + vy * vy + vz * vz
    n = scene.normals
    cos = ((n[:, 0:1] * vx + n[:, 1:2] * vy + n[:, 2:3] * vz) * torch.rsqrt(d2)).clamp_min(0.0)
    reflected = scene.albedo * color * inten * cos / (1.0 + d2 / GLOW_FALLOFF**2)
    sigma = p.halo_radius.to(dtype=dtype, device=device).view(b, 1, 1, 1)
    halo_i = p.halo_intensity.to(dtype=dtype, device=device).view(b, 1, 1, 1)
    halo = color * halo_i * torch.exp(-(vx * vx + vy * vy) / (2.0 * sigma * sigma))
    return reflected + halo


def additive_light(scene: Scene, labels: str | Sequence[str] | None = None) -> AdditiveLight:
    """The unlit image, the clipped glow (the ``plus`` layer) and the lit image.

    ``labels`` (glow labels, one for all or one per scene) replaces the scenes' own glow labels.
    """
    if labels is not None:
        scene = replace(scene, params=scene.params.with_glow_labels(labels))
    g = torch.minimum(glow(scene), 1.0 - scene.image)
    return AdditiveLight(base=scene.image, glow=g, lit=scene.image + g, scene=scene)
