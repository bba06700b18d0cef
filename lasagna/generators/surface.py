"""``SurfaceEstimator``: the conditioned U-Net whose layer is a surface — a height field — not a multiplier.

A shading layer under a directional light is the rendering of one surface (`lasagna.compose.surface`): the
estimator reads an image and outputs the height field h (B, 1, H, W) in canvas units (the canvas is 2 units
wide), whose normals n ∝ (−∂h/∂x, −∂h/∂y, 1) are rendered by Lambert with ambient under *any* light. So one
estimate serves every light, a flat painted wall stays flat unless the estimator bends it, and relighting
toward left and toward right differ by construction.

Two inputs (``SurfaceConfig.input``):

* ``"albedo"`` — the unlit base layer (the ``shading`` task): geometry from outlines and paint alone;
* ``"lit"`` — an image already lit by an unknown directional light (the ``relight`` task): geometry from
  shading. A second output channel is that light's shading S_src (a + (1 − a)·sigmoid, per pixel: an
  intrinsic decomposition's shading), and the source light the relight ratio S(l_tgt)/S(l_src) needs is the
  least-squares fit of the surface's normals to it (`lasagna.compose.surface.fit_light`): one surface and one
  light that explain the image together. (A global head regressing the light from the bottleneck's average
  collapsed to the mean answer, "light from the viewer", within 1 500 steps: the fit reads the light where it
  shows, in each surface's shading.)

The body is the layer generator's (`lasagna.generators.unet`): per level ``blocks`` × (Conv3×3 → SiLU), 2×2
average pooling, nearest ×2 and skip concatenation on the way up, no normalisation layer (a pixel does not
depend on the batch or on far-away pixels' statistics); any H, W (replicate-padded to a multiple of
2^(levels − 1), cropped back). The height head is a zero-initialised 1×1 convolution: an untrained estimator
returns the flat surface h = 0 (n = +z everywhere), whose shading is the wall's, a + (1 − a)·cos el.

**The symmetry ensemble** (``estimate(..., symmetry=...)``): a mirror or a quarter turn of the image mirrors or
turns its surface and its light, but a convolutional estimator is not equivariant to them: its answer to a
transformed image is a second opinion on the same surface. ``"mirrors"`` estimates the image and its three mirror
images (left-right, top-bottom, both: a half turn); ``"dihedral"`` adds their transposes (the reflection across
the diagonal and its compositions: all eight symmetries of the square, the dihedral group D4). Each estimate is
mapped back — its pixels, and its normals' (x, y) components (negated by a mirror, swapped and negated by the
transpose, since rows run down while y runs up) — and they are averaged: normals renormalised, source shadings
averaged, the light fitted to the averages. The average is equivariant under the group (estimating a transformed
image gives the transformed estimate, up to the rounding of the sum's order). It is test-time augmentation
(Krizhevsky et al. 2012) where the symmetry is known exactly. Four or eight passes at the working size (32²:
milliseconds).
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple

import torch
from pydantic import BaseModel, ConfigDict, Field, field_validator
from torch import Tensor, nn

from lasagna.compose.resample import downsample, working_size
from lasagna.compose.surface import (
    DOME_MAX_SIDE,
    calibrate_elevation,
    calm_walls,
    deepen_normals,
    dome_normals,
    enlarge_surface,
    facing_normals,
    fit_light,
    flatten_walls,
    label_regions,
    mix_normals,
    surface_normals,
    wall_elevation,
)
from lasagna.document.condition import AMBIENT
from lasagna.document.preset import SYMMETRIES, SourceElevation, Symmetry
from lasagna.errors import LasagnaError
from lasagna.generators.unet import pad_to_levels, run_unet, unet_body
from lasagna.io.checkpoint import Pretrained
from lasagna.limits import MAX_GENERATOR_BLOCKS, MAX_GENERATOR_LEVELS, MAX_GENERATOR_WIDTH

FORMAT = "lasagna.surface_estimator"

# softplus(FLAT_Z) = 1: a zero head output is the flat normal +z (an untrained estimator's wall).
FLAT_Z = math.log(math.e - 1.0)

LIGHT_CHANNELS = 4
"""Constant input channels of an estimator with a light input: the source light's (x, y, z) and a flag, 1 where
the light is given (a zero row: not known, all four channels 0)."""


def light_channels(light: Tensor | None, like: Tensor) -> Tensor:
    """(B, 4, H, W) constant maps of ``light`` (B, 3) — unit rows, or zero rows for "not known"; None: none known —
    shaped and typed as ``like`` (B, C, H, W)."""
    b, _, h, w = like.shape
    if light is None:
        return like.new_zeros(b, LIGHT_CHANNELS, h, w)
    if light.shape != (b, 3):
        raise LasagnaError(f"light has shape {tuple(light.shape)}; expected ({b}, 3)", "light")
    light = light.to(like)
    given = (light.norm(dim=1, keepdim=True) > 0.5).to(like)
    return torch.cat([light * given, given], 1)[:, :, None, None].expand(b, LIGHT_CHANNELS, h, w)


def normals_from_head(out: Tensor) -> Tensor:
    """Unit normals (B, 3, H, W) of a normals head's output (a, b, c): (a, b, softplus(c + FLAT_Z)) normalised, so
    n_z > 0 (every normal faces the viewer, as a height field's do) and a zero output is +z."""
    z = torch.nn.functional.softplus(out[:, 2:3] + FLAT_Z)
    n = torch.cat([out[:, :2], z], 1)
    return n * torch.rsqrt((n * n).sum(1, keepdim=True))


class SurfaceConfig(BaseModel):
    """Everything that rebuilds a ``SurfaceEstimator`` (saved as config.json beside the weights)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    input: Literal["albedo", "lit"] = Field(description="What it reads: the unlit base, or an image already lit.")
    output: Literal["height", "normals"] = Field(
        "height",
        description="What its head outputs: a height field (normals by differences) or the unit normals directly.",
    )
    channels: tuple[int, ...] = Field(
        (32, 64, 128), min_length=1, max_length=MAX_GENERATOR_LEVELS, description="Feature widths per level."
    )
    blocks: int = Field(2, ge=1, le=MAX_GENERATOR_BLOCKS, description="Conv3×3+SiLU blocks per level.")
    silhouette: bool = Field(
        False,
        description="Also output each pixel's probability of lying on an object (the silhouettes the dome prior "
        "inflates: `lasagna.compose.surface.dome_normals`).",
    )
    working_size: int = Field(32, ge=8, le=1024, description="The side it was trained at (and is applied at).")
    light_input: bool = Field(
        False,
        description="A lit input's estimator also reads its source light, when one is known, as four constant "
        "channels (l and a flag that it is given): relief shading is a derivative along the light, so a bump lit "
        "from the left and a dent lit from the right look alike until the light is known (module docstring).",
    )

    @field_validator("light_input")
    @classmethod
    def _lit(cls, v: bool, info) -> bool:
        if v and info.data.get("input") != "lit":
            raise ValueError("a light input needs input 'lit' (an albedo has no source light)")
        return v

    @field_validator("channels")
    @classmethod
    def _widths(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        if any(c < 1 or c > MAX_GENERATOR_WIDTH for c in v):
            raise ValueError(f"widths must lie in [1, {MAX_GENERATOR_WIDTH}]; got {list(v)}")
        return v


class SurfaceOutputs(NamedTuple):
    """What the estimator's head gives for a batch: the surface (height (B, 1, H, W) or unit normals (B, 3, H, W)),
    a lit input's source shading (B, 1, H, W) in [a, 1] (else None), and the silhouette logits (B, 1, H, W) of an
    estimator with a silhouette head (else None)."""

    surface: Tensor
    shading: Tensor | None
    silhouette: Tensor | None


class DomePrior(BaseModel):
    """The shape prior "silhouettes bound volumes": the estimated silhouettes inflated into domes
    (`lasagna.compose.surface.dome_normals`, ``height`` their height as a fraction of the round dome's) and mixed
    into the estimated normals with ``weight`` (0: the estimate alone; 1: the domes alone)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    weight: float = Field(0.0, ge=0.0, le=1.0)
    height: float = Field(1.0, gt=0.0, le=4.0)

    def apply(self, normals: Tensor, silhouette_logit: Tensor) -> Tensor:
        """Unit normals: ``normals`` (B, 3, H, W) mixed with the domes of the pixels whose silhouette probability
        is above one half (inflated at most ``DOME_MAX_SIDE`` pixels on the long side)."""
        size = tuple(silhouette_logit.shape[-2:])
        small = working_size(*size, DOME_MAX_SIDE)
        logit = silhouette_logit if small == size else downsample(silhouette_logit, small)
        domes = dome_normals(label_regions(logit > 0), self.height).to(normals.dtype)
        return mix_normals(normals, enlarge_surface(domes, size), self.weight)


# The mirror images of the symmetry ensemble: the flipped tensor dimensions, and which normal components change sign.
# Columns (dim −1) are x; rows (dim −2) run down while y runs up, so a top-bottom mirror negates n_y.
MIRRORS: tuple[tuple[tuple[int, ...], tuple[float, float, float]], ...] = (
    ((), (1.0, 1.0, 1.0)),
    ((-1,), (-1.0, 1.0, 1.0)),
    ((-2,), (1.0, -1.0, 1.0)),
    ((-2, -1), (-1.0, -1.0, 1.0)),
)


def transpose_normals(n: Tensor) -> Tensor:
    """Normals (B, 3, H, W) of a surface transposed (rows ↔ columns): pixels transposed, (n_x, n_y) → (−n_y, −n_x)
    (x runs along columns, y against rows). An involution: it maps an estimate of the transposed image back too."""
    n = n.transpose(-1, -2)
    return torch.cat([-n[:, 1:2], -n[:, 0:1], n[:, 2:3]], 1)


def view_light(light: Tensor | None, dims: tuple[int, ...], sign: tuple[float, float, float], transpose: bool):
    """``light`` (B, 3) as seen in a view of the symmetry ensemble: transposed (when ``transpose``), then mirrored
    (``dims``, ``sign`` as in ``MIRRORS``) — the view's own map, applied to a vector; zero rows stay zero."""
    if light is None:
        return None
    if transpose:
        light = torch.stack([-light[:, 1], -light[:, 0], light[:, 2]], 1)
    return light * light.new_tensor(sign) if dims else light


class SurfaceEstimator(Pretrained, nn.Module):
    """image (B, 3, H, W) in [0, 1] → height (B, 1, H, W) and, for ``input="lit"``, the source light (B, 3)."""

    FORMAT = FORMAT
    CONFIG = SurfaceConfig

    def __init__(self, config: SurfaceConfig):
        super().__init__()
        self.config = config
        ch = config.channels
        self.enc, self.dec = unet_body(3 + LIGHT_CHANNELS * config.light_input, ch, config.blocks)
        # Height, and for a lit input its source shading's logit; zero-initialised: the flat surface, lit at the
        # midpoint a + (1 − a)/2 of the shading's range (module docstring).
        self.surface_channels = 1 if config.output == "height" else 3
        self.head = nn.Conv2d(ch[0], self.surface_channels + (config.input == "lit") + config.silhouette, 1)
        with torch.no_grad():
            self.head.weight.zero_()
            self.head.bias.zero_()

    def _features(self, image: Tensor, light: Tensor | None = None) -> Tensor:
        if not isinstance(image, Tensor) or image.dim() != 4 or image.shape[1] != 3:
            got = tuple(image.shape) if isinstance(image, Tensor) else type(image).__name__
            raise LasagnaError(f"image has shape {got}; expected (B, 3, H, W) in [0, 1]", "image")
        x = image.to(self.head.weight.dtype) * 2 - 1
        if self.config.light_input:
            x = torch.cat([x, light_channels(light, x)], 1)
        elif light is not None:
            raise LasagnaError("this estimator reads no light (trained without --light-input)", "light")
        x, h, w = pad_to_levels(x, len(self.config.channels))
        return self.head(run_unet(self.enc, self.dec, x))[:, :, :h, :w]

    def forward(self, image: Tensor) -> Tensor:
        """The surface: the height field (B, 1, H, W) in canvas units, or the unit normals (B, 3, H, W)."""
        return self.decompose(image)[0]

    def outputs(self, image: Tensor, light: Tensor | None = None) -> SurfaceOutputs:
        """Every output of the head for ``image`` (B, 3, H, W) in [0, 1] (``SurfaceOutputs``); ``light`` (B, 3) the
        source lights of an estimator with a light input (a zero row, or None: not known)."""
        out = self._features(image, light)
        k = self.surface_channels
        surface = out[:, :1] if k == 1 else normals_from_head(out[:, :k])
        shading = None
        if self.config.input == "lit":
            shading = AMBIENT + (1.0 - AMBIENT) * torch.sigmoid(out[:, k : k + 1])
            k += 1
        silhouette = out[:, k : k + 1] if self.config.silhouette else None
        return SurfaceOutputs(surface, shading, silhouette)

    def decompose(self, image: Tensor) -> tuple[Tensor, Tensor | None]:
        """(the surface — height (B, 1, H, W) or unit normals (B, 3, H, W), per ``config.output`` — and the source
        light's shading (B, 1, H, W) in [a, 1], or None for albedo input)."""
        out = self.outputs(image)
        return out.surface, out.shading

    def normals(self, surface: Tensor) -> Tensor:
        """Unit normals (B, 3, H, W) of a surface this estimator output (a height field's by differences)."""
        return surface_normals(surface)

    def estimate(
        self,
        image: Tensor,
        dome: DomePrior | None = None,
        symmetry: Symmetry = "none",
        relief: float = 1.0,
        elevation: tuple[float, float] | None = None,
        source_elevation: SourceElevation = "fit",
        flat_walls: float = 0.0,
        light: Tensor | None = None,
        readings: int = 2,
        wall_relief: float = 1.0,
    ) -> tuple[Tensor, Tensor | None]:
        """(surface — height or normals, as ``decompose``; unit normals where ``dome`` mixes in the dome prior,
        ``symmetry`` averages an ensemble, ``flat_walls`` > 0 removes the walls' large-scale tilt (`flatten_walls`,
        σ that fraction of the long side, walls weighted by 1 − the silhouette probability), ``wall_relief`` ≠ 1 scales
        the walls' slopes (`calm_walls`, the same weights) or ``relief`` ≠ 1
        deepens the estimate (`deepen_normals`: slopes times ``relief``) — and the source light (B, 3), or None for
        albedo input): the light is the fit of the final surface's normals to the estimated source shading (module
        docstring); with ``source_elevation`` "walls" its
        elevation is the one that lights a flat wall to the estimated shading's mean over the walls (weighted by
        1 − the silhouette probability, `lasagna.compose.surface.wall_elevation`); then mapped by ``elevation``
        (offset, gain) when given (`lasagna.compose.surface.calibrate_elevation`). An estimator with a light input
        reads ``light`` (B, 3), the source light when it is known; when it is not, the image is read ``readings``
        times: alone, then each time told the light fitted to the reading before."""
        if symmetry not in SYMMETRIES:
            raise LasagnaError(f"got {symmetry!r}; expected one of {', '.join(SYMMETRIES)}", "symmetry")
        if readings < 1:
            raise LasagnaError(f"got {readings}; expected at least 1", "readings")
        if self.config.light_input and light is None:
            # The image alone, the light fitted to that estimate, then the image read with that light (readings
            # in all, each told the light fitted to the reading before).
            for _ in range(readings - 1):
                first, first_shading, _ = self._views(image, dome, symmetry, light)
                light = fit_light(self.normals(first), first_shading)
        surface, shading, objects = self._views(image, dome, symmetry, light)
        if flat_walls > 0:
            if objects is None:
                raise LasagnaError(
                    "flat walls need a silhouette head (train-surface --silhouette); this estimator has none",
                    "flat_walls",
                )
            surface = flatten_walls(self.normals(surface), 1.0 - objects, flat_walls * max(surface.shape[-2:]))
        if wall_relief != 1.0:
            if objects is None:
                raise LasagnaError(
                    "a wall relief gain needs a silhouette head (train-surface --silhouette); this estimator has none",
                    "wall_relief",
                )
            surface = calm_walls(self.normals(surface), 1.0 - objects, wall_relief)
        if relief != 1.0:
            surface = deepen_normals(self.normals(surface), relief)
        if shading is None:
            return surface, None
        light = fit_light(self.normals(surface), shading)
        if source_elevation == "walls":
            if objects is None:
                raise LasagnaError(
                    "the source elevation from the walls needs a silhouette head (train-surface --silhouette)",
                    "source_elevation",
                )
            light = wall_elevation(light, shading, 1.0 - objects)
        return surface, light if elevation is None else calibrate_elevation(light, *elevation)

    @torch.no_grad()
    def height_field(self, image: Tensor, symmetry: Symmetry = "none", light: Tensor | None = None) -> Tensor:
        """The height field (B, 1, H, W, canvas units, each image's mean removed) the head outputs for ``image``,
        averaged over ``symmetry``'s ensemble — a height moves with its pixels, so each view's field is only moved
        back — ``light`` (B, 3) mapped into each view as ``estimate`` maps it. What a cast shadow is marched over
        (an estimator trained with a height loss, `lasagna.training.surface`'s ``height_weight``: the heights of
        one trained on normals alone are free across an object's outline)."""
        if self.config.output != "height":
            raise LasagnaError("this estimator outputs normals; expected a height-output estimator", "height_field")
        if symmetry not in SYMMETRIES:
            raise LasagnaError(f"got {symmetry!r}; expected one of {', '.join(SYMMETRIES)}", "symmetry")
        fields = []
        transposes = (False, True) if symmetry == "dihedral" else (False,)
        for transpose in transposes:
            seen = image.transpose(-1, -2) if transpose else image
            for dims, sign in MIRRORS if symmetry != "none" else MIRRORS[:1]:
                h = self.outputs(seen.flip(dims) if dims else seen, view_light(light, dims, sign, transpose)).surface
                h = h.flip(dims) if dims else h
                fields.append(h.transpose(-1, -2) if transpose else h)
        h = torch.stack(fields).mean(0)
        return h - h.mean(dim=(-2, -1), keepdim=True)

    @torch.no_grad()
    def silhouette(self, image: Tensor, symmetry: Symmetry = "none") -> Tensor:
        """The probability (B, 1, H, W) that each pixel of ``image`` lies on an object, by the silhouette head (its
        sigmoid), averaged over ``symmetry``'s ensemble as ``estimate`` averages the surface."""
        if not self.config.silhouette:
            raise LasagnaError(
                "this estimator has no silhouette head (train-surface --silhouette); expected one", "silhouette"
            )
        if symmetry not in SYMMETRIES:
            raise LasagnaError(f"got {symmetry!r}; expected one of {', '.join(SYMMETRIES)}", "symmetry")
        views = []
        for transpose in (False, True) if symmetry == "dihedral" else (False,):
            seen = image.transpose(-1, -2) if transpose else image
            for dims, _ in MIRRORS if symmetry != "none" else ((None, None),):
                p = torch.sigmoid(self.outputs(seen.flip(dims) if dims else seen).silhouette)
                p = p.flip(dims) if dims else p
                views.append(p.transpose(-1, -2) if transpose else p)
        return torch.stack(views).mean(0)

    def _views(
        self, image: Tensor, dome: DomePrior | None, symmetry: Symmetry, light: Tensor | None
    ) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """(surface, source shading or None, silhouette probability or None) of ``image`` averaged over
        ``symmetry``'s ensemble (module docstring); ``light`` (B, 3) is mapped into each view as its normals are."""
        if symmetry == "none":
            return self._one_estimate(image, dome, light)
        normals, shadings, probs = [], [], []
        for transpose in (False, True) if symmetry == "dihedral" else (False,):
            seen = image.transpose(-1, -2) if transpose else image
            for dims, sign in MIRRORS:
                surface, shading, p = self._one_estimate(
                    seen.flip(dims) if dims else seen, dome, view_light(light, dims, sign, transpose)
                )
                n = self.normals(surface)
                maps = [shading, p]
                if dims:
                    n = n.flip(dims) * n.new_tensor(sign).view(1, 3, 1, 1)
                    maps = [None if m is None else m.flip(dims) for m in maps]
                if transpose:
                    n = transpose_normals(n)
                    maps = [None if m is None else m.transpose(-1, -2) for m in maps]
                normals.append(n)
                shadings.append(maps[0])
                probs.append(maps[1])
        surface = facing_normals(torch.stack(normals).mean(0))
        shading = None if shadings[0] is None else torch.stack(shadings).mean(0)
        objects = None if probs[0] is None else torch.stack(probs).mean(0)
        return surface, shading, objects

    def _one_estimate(
        self, image: Tensor, dome: DomePrior | None, light: Tensor | None = None
    ) -> tuple[Tensor, Tensor | None, Tensor | None]:
        """(surface, with the dome prior mixed in where asked; the source shading or None; the silhouette
        probability or None) of one pass."""
        out = self.outputs(image, light)
        surface = out.surface
        if dome is not None and dome.weight > 0:
            if out.silhouette is None:
                raise LasagnaError(
                    "this estimator has no silhouette head; the dome prior needs one (train-surface --silhouette)",
                    "dome",
                )
            surface = dome.apply(self.normals(surface), out.silhouette)
        prob = None if out.silhouette is None else torch.sigmoid(out.silhouette)
        return surface, out.shading, prob

    @torch.no_grad()
    def estimate_at(
        self,
        image: Tensor,
        dome: DomePrior | None = None,
        side: int | None = None,
        symmetry: Symmetry = "none",
        relief: float = 1.0,
        elevation: tuple[float, float] | None = None,
        source_elevation: SourceElevation = "fit",
        flat_walls: float = 0.0,
        light: Tensor | None = None,
        wall_relief: float = 1.0,
    ) -> tuple[Tensor, Tensor | None]:
        """(unit normals (B, 3, H, W), source light (B, 3) or None) of ``image`` (B, 3, H, W) in [0, 1]: estimated
        at the working size ``side`` (None: the one it was trained at; `lasagna.compose.resample.working_size`),
        the surface enlarged back to (H, W) (`lasagna.compose.surface.enlarge_surface`)."""
        full = tuple(image.shape[-2:])
        small = downsample(image, working_size(*full, side or self.config.working_size))
        surface, fitted = self.estimate(
            small, dome, symmetry, relief, elevation, source_elevation, flat_walls, light, wall_relief=wall_relief
        )
        return self.normals(enlarge_surface(surface, full)), fitted
