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

Relighting a lit image (the relight setting of issue #11: blend ``multiply``, 1 channel). The base is
the scene lit by a light A, the target the same scene lit by B, and the ground-truth layer is the
luminosity ratio S_B / S_A of their shadings (S = a + (1 − a)·max(0, n·l), a > 0 so S_A ≥ a > 0):
base × ratio = albedo·S_A·S_B/S_A = target, exactly in real arithmetic and to a few float roundings
in the engine. The ratio lies in [a, 1/a] — [0.25, 4] with the default a = 0.25, hence the stacks'
range [0, 4] (``RELIGHT_RANGE``). With shadows off the ratio is a pointwise function of the normal;
with shadows on each of S_A, S_B is a where its light is blocked, so the identity base × ratio =
target still holds pixel by pixel and the range is the same, but the ratio is no longer a function of
the normal alone: it also removes A's cast shadows (ratio up to 1/a) and casts B's (ratio down to
a), which a per-pixel layer can still represent but only knowledge of the geometry can predict.

How the world draws A and B for a scene (``relight_sources``; ``lasagna world --task relight``): B is
the scene's own named light (its ``label``, uniform over the eight), so the target is the scene as
every other task renders it; A is continuous, azimuth uniform in [0, 360) and elevation uniform in
``RELIGHT_ELEVATION`` = [30°, 75°], both rounded to 0.01° so that the recorded condition text
``az=…,el=…`` is exactly the direction rendered. A comes from the scene's own further random stream
``"relight"`` (`lasagna.world.splits.scene_rng`), so every split's scenes and their other tasks stay
bit-identical.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import torch

from lasagna.compose.color import luma
from lasagna.errors import LasagnaError
from lasagna.world.lighting import format_direction
from lasagna.world.params import SceneParams
from lasagna.world.scene import Scene, pixel_grid, with_light
from lasagna.world.splits import scene_rng

Tensor = torch.Tensor

GLOW_FALLOFF = 1.0
"""d₀ of the point light's 1/(1 + (d/d₀)²) fall-off, in world units (the canvas is 2 units wide)."""


RELIGHT_RANGE = (0.0, 4.0)
"""The relight layer's value range: the ratio S_B / S_A lies in [a, 1/a] = [0.25, 4] for a = 0.25."""
RELIGHT_ELEVATION = (30.0, 75.0)
"""Elevations (degrees from the view axis) of the relight task's source light A; the named lights have 60."""
_RELIGHT_DECIMALS = 2  # A's angles are rounded to 0.01° so its condition text is exactly what is rendered


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


@dataclass(frozen=True)
class Relighting:
    """base (B, 3, H, W) lit by A, target (B, 3, H, W) lit by B, layer (B, 1, H, W) = S_B / S_A (multiply).

    ``source`` is the scenes lit by A, ``scene`` the scenes lit by B (their ``light`` and ``label``
    say which direction each is).
    """

    base: Tensor
    target: Tensor
    layer: Tensor
    scene: Scene
    source: Scene


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


def relighting(
    scene: Scene, light_a: str | Sequence[str] | Tensor, light_b: str | Sequence[str] | Tensor | None = None
) -> Relighting:
    """The scenes lit by ``light_a`` (the base), by ``light_b`` (the target; default: the scenes' own
    light) and the ratio S_B / S_A that maps one onto the other (see the module docstring).

    Each light is one condition, one per scene (a named label or ``az=…,el=…``) or unit vectors.
    """
    if scene.ambient <= 0.0:
        raise LasagnaError(
            f"the relight ratio S_B / S_A needs ambient > 0 (S_A is 0 where A does not reach), got {scene.ambient}",
            where="ambient",
        )
    source = with_light(scene, light_a)
    lit = scene if light_b is None else with_light(scene, light_b)
    return Relighting(base=source.image, target=lit.image, layer=lit.shading / source.shading, scene=lit, source=source)


def relight_sources(params: SceneParams) -> list[str]:
    """The relight task's source light A of each scene, as ``az=…,el=…`` text (see the module docstring)."""
    lo, hi = RELIGHT_ELEVATION
    out = []
    for index in params.index.tolist():
        u = scene_rng(params.split, params.seed, index, stream="relight").random(2)
        az = round(360.0 * float(u[0]), _RELIGHT_DECIMALS)  # 360.0 wraps to 0
        el = round(lo + (hi - lo) * float(u[1]), _RELIGHT_DECIMALS)
        out.append(format_direction(az, el))
    return out
