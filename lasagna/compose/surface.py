"""Surfaces: a height field or a normal map, rendered to a shading multiplier under a directional light.

A shading layer under a directional light is the rendering of one surface (docs/ARCHITECTURE.md, "Surface
layers"). This module is that renderer, differentiable and batch-independent:

- **Shading model** — the world's contract (`lasagna.document.condition`): S = a + (1 − a)·max(0, n·l), Lambert
  with ambient a (default ``AMBIENT`` = 0.25), l the unit light (sin el·cos az, sin el·sin az, cos el); camera
  frame x right, y up, z toward the viewer; image row 0 is the top.
- **Relight** of a lit image I = A·S(l_src) to l_tgt multiplies it by the ratio S(l_tgt)/S(l_src) of one surface.
  With a > 0 the denominator is at least a, so the ratio is finite and at most 1/a.
- **Height field** h (..., 1, H, W) in canvas units where the canvas is 2 units wide (the world's convention; a
  pixel is 2/W): n ∝ (−∂h/∂x, −∂h/∂y, 1), by central differences inside and one-sided differences on the border
  (``torch.gradient``), with ∂h/∂y = −∂h/∂row because rows run down.
- **Normal map** — tangent-space RGB n ↦ (n + 1)/2 with +Y up: the "OpenGL" convention Blender, Krita's
  tangent-normal brush and Godot's ``CanvasTexture.normal_texture`` read (a "DirectX" map flips the green
  channel). Decoding renormalises, since a quantised unit vector is not exactly unit; a 16-bit map stores each
  component to 1.5e-5, so S from a stored map is within 3e-5 of S from the exact normals.
- **Point light** at (x, y, z) over a map of h × w pixels (x, y fractions of its width and height from the
  top-left, z in units of its longer side L; `lasagna.document.condition.parse_point`): pixel (row i, column j)
  at (u, v) = ((j + ½)/w, (i + ½)/h) sees the light along d = ((x − u)·w/L, (v − y)·h/L, z) (y up), l = d/|d|,
  with inverse-square falloff normalised to 1 directly beneath it: S = a + (1 − a)·(z/|d|)²·max(0, n·l)
  (`point_lambert`). Fractions keep a stack's light where it was at any size and view level. This is the point
  light of Photoshop's Lighting Effects and of 2D engines that light normal maps (Godot's ``PointLight2D``
  with its ``height``), with the falloff of a physical point source.
- **Spot light**: a point light with a cone of half-angle C aimed at (ax, ay) on the map (fractions as x, y):
  its direct term also times m = smoothstep((cos θ − cos C)/(b·(1 − cos C))), θ the angle between the ray from
  the light to the pixel and the axis from the light to the aim point, b the edge's softness (Blender's spot mask
  and ``spot_blend``; a hard edge at b = 0) — Lighting Effects' Spot (`spot_cone`).
- **Gloss** (a layer's ``gloss`` g and ``shininess`` p): each light's direct term gains a Blinn–Phong highlight,
  S = a + (1 − a)·Σ kᵢ·cᵢ·fᵢ·(max(0, n·lᵢ) + g·max(0, n·hᵢ)^p·[n·lᵢ > 0]), h = (l + v)/|l + v| the half vector
  toward the viewer v = +z (an orthographic camera), f a point light's falloff and cone (Blinn 1977; Lighting
  Effects' Gloss, Blender's specular). g = 0 is the world's contract, rendered by the Lambert-only paths bit for
  bit; a relight ratio's source light stays diffuse (a photograph's own highlights are in its pixels). The layer
  multiplies, so the highlight takes the colour below it — a metal's highlight (Lighting Effects' Metallic end); a
  plastic's white one would be added, which a multiply layer cannot.
- **Ambient occlusion** (a layer's ``occlusion`` o): the ambient term a becomes a·(1 − o·(1 − A)), A the share of
  the sky each point of those heights sees (`lasagna.compose.shadow.occlusion`): creases and the feet of walls get
  less of the ambient light. It belongs to the surface, not to a light, so a relight ratio has it above and below.
- **Shadows** (a layer's ``shadows`` s): each light's direct term (its highlight too) also times 1 − s·(1 − V), V
  that light's visibility over the heights integrated from the layer's normals, times its ``shadow_depth``
  (`lasagna.compose.shadow`): a bump darkens what lies behind it from the light. s = 0 is the world's contract,
  rendered by the paths without shadows bit for bit; a relight ratio's source light casts none (a photograph's own
  shadows are in its pixels, and dividing them out needs their exact edges: docs/BENCHMARKS.md, round 24).
"""

from __future__ import annotations

import math
import weakref

import torch
from torch import Tensor

from lasagna.compose.layer import LayerTensors
from lasagna.compose.resample import downsample, gaussian_blur, upsample
from lasagna.compose.shadow import SHADOW_MAX_SIDE, shadow_factor
from lasagna.compose.shadow import occlusion as sky_share
from lasagna.document.condition import (
    AMBIENT,
    DEFAULT_SHININESS,
    PointLight,
    check_ambient,
    parse_direction,
    parse_point,
    unit_vector,
)
from lasagna.errors import LasagnaError

# A normal decoded from a map whose three channels round to (0.5, 0.5, 0.5) — a zero vector, which no unit
# normal encodes — would divide by zero; below this length it is taken as the flat normal +z instead.
NORMAL_EPS = 1e-6


def light_vector(az: float, el: float, *, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """The unit light (3,) of (az, el) in degrees, by the one closed form (`lasagna.document.condition`)."""
    return torch.tensor(unit_vector(az, el), dtype=torch.float64).to(dtype=dtype, device=device)


def lambert(normals: Tensor, light: Tensor, ambient: float = AMBIENT) -> Tensor:
    """Shading a + (1 − a)·max(0, n·l) of unit ``normals`` (B, 3, H, W) under ``light`` (B, 3): (B, 1, H, W).

    The dot product is written out per component (no matmul), so every pixel's value is independent of the
    batch it was computed in: a scene renders bit-identically alone or in any batch.
    """
    check_ambient(ambient)
    if light.ndim == 1:
        light = light[None].expand(normals.shape[0], 3)
    lx, ly, lz = (light[:, i, None, None, None] for i in range(3))
    ndotl = normals[:, 0:1] * lx + normals[:, 1:2] * ly + normals[:, 2:3] * lz
    return ambient + (1.0 - ambient) * ndotl.clamp_min(0.0)


def point_offsets(
    point: tuple[float, ...], h: int, w: int, *, dtype: torch.dtype = torch.float32, device=None
) -> tuple[Tensor, Tensor]:
    """The vector from each pixel of an h × w map to the point light ``point`` (a
    `lasagna.document.condition.PointLight`, or (x, y, z)), in units of the map's longer side, y up, by its
    separable parts: dx (1, 1, 1, w) per column and dy (1, 1, h, 1) per row (d_z is the light's z everywhere) —
    the module docstring's closed form, the offsets computed in float64 and rounded once to ``dtype``."""
    x, y = float(point[0]), float(point[1])
    long_side = float(max(h, w))
    u = (torch.arange(w, dtype=torch.float64, device=device) + 0.5) / w
    v = (torch.arange(h, dtype=torch.float64, device=device) + 0.5) / h
    dx = ((x - u) * (w / long_side)).view(1, 1, 1, w)
    dy = ((v - y) * (h / long_side)).view(1, 1, h, 1)
    return dx.to(dtype), dy.to(dtype)


def spot_cone(cos_angle: Tensor, cone: float, blend: float) -> Tensor:
    """A spot light's mask of the cosine of each ray's angle to its axis: 1 inside the cone, 0 outside, its edge
    a smoothstep over the fraction ``blend`` of the cone measured in cos θ — Blender's spot mask,
    smoothstep((cos θ − cos C)/(blend·(1 − cos C))); a hard step at blend 0."""
    edge = math.cos(math.radians(cone))
    if blend <= 0.0:
        return (cos_angle > edge).to(cos_angle.dtype)
    t = ((cos_angle - edge) / (blend * (1.0 - edge))).clamp(0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def point_lambert(normals: Tensor, point: tuple[float, ...], ambient: float = AMBIENT) -> Tensor:
    """Shading a + (1 − a)·(z/|d|)²·m·max(0, n·l) of unit ``normals`` (B, 3, H, W) under the point light ``point``
    (the module docstring; l = d/|d|, m a spot light's cone, else 1): (B, 1, H, W), in the normals' dtype. Per
    pixel and per component, like `lambert`, so batch-independent; the light's field is never built as an image
    (its offsets are separable: a row and a column), which keeps a point light's drag in the editor as cheap as a
    direction's."""
    check_ambient(ambient)
    h, w = normals.shape[-2:]
    dx, dy = point_offsets(point, h, w, dtype=normals.dtype, device=normals.device)
    z = float(point[2])
    d2 = dx * dx + dy * dy + z * z  # (1, 1, h, w)
    inv = d2.rsqrt()
    cos = (normals[:, 0:1] * dx + normals[:, 1:2] * dy + normals[:, 2:3] * z) * inv
    gain = (z * z) / d2
    spot = PointLight(*point) if len(point) > 3 else None
    if spot is not None and spot.cone is not None:
        # The axis from the light toward its aim point (ax, ay, 0), as the pixels' d is: from the plane up to it.
        long_side = float(max(h, w))
        axis = ((float(point[0]) - spot.ax) * w / long_side, (spot.ay - float(point[1])) * h / long_side, z)
        norm = math.sqrt(sum(c * c for c in axis))
        ax, ay, az = (c / norm for c in axis)
        gain = gain * spot_cone((dx * ax + dy * ay + z * az) * inv, spot.cone, spot.blend)
    return ambient + (1.0 - ambient) * gain * cos.clamp_min(0.0)


def relight_ratio(normals: Tensor, target: Tensor, source: Tensor, ambient: float = AMBIENT) -> Tensor:
    """S(target)/S(source) of one surface (B, 1, H, W): the multiplier that relights A·S(source) to A·S(target).

    Needs a > 0 (the denominator is then ≥ a; at a = 0 an unlit pixel would be 0/0, and nothing is known of
    its albedo): raises otherwise.
    """
    return lambert(normals, target, ambient) / lambert(normals, source, check_ratio_ambient(ambient))


def check_ratio_ambient(ambient: float) -> float:
    """A relight ratio's ambient: in (0, 1) — with a > 0 its denominator S(source) is at least a; at a = 0 an
    unlit pixel would be 0/0, and nothing is known of its albedo."""
    if check_ambient(ambient) <= 0.0:
        raise LasagnaError("a relight ratio needs an ambient term a > 0 (S(source) ≥ a); got 0", where="ambient")
    return float(ambient)


# Lit pixels in a light fit: a shading at least this far above the ambient floor (in units of 1 − a) is taken
# as n·l > 0 — below it the clamp max(0, n·l) may hide the dot product, which then says nothing of l.
LIT_MARGIN = 0.05
# Tikhonov term of the light fit's 3×3 normal equations (in units of the lit pixels' count): keeps the solve
# finite for a flat surface (all n = +z, where only l_z is determined), pulling the unseen components to 0.
FIT_RIDGE = 1e-3
MAX_FIT_ELEVATION = 85.0
"""A fitted light's elevation (degrees from the view axis) stays below this: l_z ≥ cos 85° = 0.087."""


def fit_light(normals: Tensor, shading: Tensor, ambient: float = AMBIENT) -> Tensor:
    """The unit light (B, 3) under which ``normals`` (B, 3, H, W) best give ``shading`` (B, 1, H, W): the least-
    squares solution of (1 − a)·n·l = S − a over the lit pixels (S − a > ``LIT_MARGIN``·(1 − a)), with a ridge
    ``FIT_RIDGE``, normalised, its elevation kept below ``MAX_FIT_ELEVATION``. Exact for exact data; differentiable
    (a trainer can learn through it).
    """
    check_ambient(ambient)
    b = (shading - ambient) / (1.0 - ambient)  # = n·l where lit
    w = (b > LIT_MARGIN).to(normals.dtype)
    n = normals.flatten(2)  # (B, 3, P)
    wf, bf = w.flatten(2), b.flatten(2)
    count = wf.sum(-1, keepdim=True).clamp_min(1.0)  # (B, 1, 1)
    gram = torch.einsum("bip,bjp->bij", n * wf, n) / count
    rhs = torch.einsum("bip,bp->bi", n * wf, bf[:, 0]) / count[..., 0]
    eye = torch.eye(3, dtype=normals.dtype, device=normals.device)
    light = torch.linalg.solve(gram + FIT_RIDGE * eye, rhs.unsqueeze(-1)).squeeze(-1)
    light = light / light.norm(dim=1, keepdim=True).clamp_min(1e-12)
    z_min = math.cos(math.radians(MAX_FIT_ELEVATION))
    low = light[:, 2:3] < z_min
    planar = light[:, :2] / light[:, :2].norm(dim=1, keepdim=True).clamp_min(1e-12)
    grazing = torch.cat([planar * math.sqrt(1.0 - z_min * z_min), torch.full_like(light[:, 2:3], z_min)], 1)
    return torch.where(low, grazing, light)


def calibrate_elevation(light: Tensor, offset: float, gain: float) -> Tensor:
    """Unit lights (B, 3) with their elevation θ (degrees from the view axis) mapped to offset + gain·θ, clamped to
    [0, ``MAX_FIT_ELEVATION``]; the azimuth kept (a light on the view axis keeps azimuth 0). A fitted light's
    calibration: the fit through an estimated surface is drawn toward the view axis where the estimate is shallow,
    and a line fitted on training scenes (el_true on el_fit, least squares) undoes the drift on average."""
    el = torch.rad2deg(torch.acos(light[:, 2].clamp(-1.0, 1.0)))
    return _with_elevation(light, (offset + gain * el).clamp(0.0, MAX_FIT_ELEVATION))


FIT_ELEVATION_SIGMA = 9.3
"""The RMS error (degrees) of the relight preset's untold, calibrated source-light fit's elevation on `select` (16
scenes at 64², docs/BENCHMARKS.md round 23, probe N2; round 18 measured 9.2° on 64 scenes): the weight its fit gets
against a person's reading in ``fuse_elevation``."""


def fuse_elevation(read: float, read_sigma: float, fitted: float, fitted_sigma: float = FIT_ELEVATION_SIGMA) -> float:
    """The inverse-variance mean (degrees) of two readings of a light's elevation — a person's, ``read`` ±
    ``read_sigma``, and an estimator's fit, ``fitted`` ± ``fitted_sigma``: (r/σ_r² + f/σ_f²)/(1/σ_r² + 1/σ_f²), the
    most likely elevation if both errors are Gaussian and independent. A flat wall's relight ratio follows the
    elevation its source is given directly (docs/BENCHMARKS.md round 23, probes N and N2)."""
    wr, wf = 1.0 / read_sigma**2, 1.0 / fitted_sigma**2
    return (read * wr + fitted * wf) / (wr + wf)


WALL_WEIGHT_EPS = 1e-6
"""Floor of the summed wall weight in ``wall_elevation`` (an image the silhouette calls all object)."""


def wall_elevation(light: Tensor, shading: Tensor, walls: Tensor, ambient: float = AMBIENT) -> Tensor:
    """Unit lights (B, 3) with the azimuth of ``light`` and the elevation at which a flat wall (n = +z) is lit to
    L, the mean of the estimated source shading ``shading`` (B, 1, H, W) over the walls, each pixel weighted by
    ``walls`` (B, 1, H, W) in [0, 1]: a + (1 − a)·cos el = L, clamped to [0, ``MAX_FIT_ELEVATION``]. The level of
    the walls is what sets a relight's brightness there (S(l)/S(l_src) on n = +z), and the estimator's shading head
    reads it more surely than the fit through its own surface does (docs/BENCHMARKS.md, round 8's H)."""
    level = (shading * walls).sum((1, 2, 3)) / walls.sum((1, 2, 3)).clamp_min(WALL_WEIGHT_EPS)
    cos_el = ((level - ambient) / (1.0 - ambient)).clamp(math.cos(math.radians(MAX_FIT_ELEVATION)), 1.0)
    return _with_elevation(light, torch.rad2deg(torch.acos(cos_el)))


def _with_elevation(light: Tensor, el: Tensor) -> Tensor:
    """Unit lights (B, 3): the azimuth of ``light`` (azimuth 0 for a light on the view axis), elevation ``el`` (B,)
    in degrees."""
    xy = light[:, :2]
    norm = xy.norm(dim=1, keepdim=True)
    along = torch.where(
        norm > 1e-9, xy / norm.clamp_min(1e-12), torch.tensor([1.0, 0.0], dtype=light.dtype, device=light.device)
    )
    r = torch.deg2rad(el)[:, None]
    return torch.cat([along * torch.sin(r), torch.cos(r)], 1)


# Below this length of a light's (x, y) part (sin el: 0.06° from the view axis) the light has no azimuth to turn
# from or to: ``turn_to_azimuth`` leaves the normals as they are.
AZIMUTH_EPS = 1e-3


def turn_to_azimuth(normals: Tensor, fitted: Tensor, given: Tensor) -> Tensor:
    """Unit ``normals`` (B, 3, H, W) estimated together with the light ``fitted`` (B, 3), turned about the view axis
    by the azimuth from ``fitted`` to ``given`` (B, 3): how a source light the user gives is adopted by a surface
    estimated from the lit image.

    An estimate and the light fitted to it share their errors of azimuth (what lights a bump from one side is,
    to a single image, much like what lights a turned bump from another), so dividing the estimate by the given
    light puts the source shading where the estimate has no relief for it. Turning the normals instead keeps
    n·l_fit = (R n)·(R l_fit) — the source shading the estimate explains — and moves the relief into the
    given light's frame; a flat wall (n = +z) stays flat. The elevation is not adopted this way: relief scaled
    to a new elevation (the bas-relief ambiguity's other freedom) measured worse on ``select``
    (docs/BENCHMARKS.md, round 15). Computed in float64, returned in the normals' dtype; a light on the view axis
    (|l_xy| < ``AZIMUTH_EPS``) turns nothing."""
    n, f, g = normals.double(), fitted.double(), given.double().to(normals.device)
    turn = torch.atan2(g[:, 1], g[:, 0]) - torch.atan2(f[:, 1], f[:, 0])
    axial = (f[:, :2].norm(dim=1) < AZIMUTH_EPS) | (g[:, :2].norm(dim=1) < AZIMUTH_EPS)
    turn = torch.where(axial, torch.zeros_like(turn), turn)
    c, s = turn.cos().view(-1, 1, 1), turn.sin().view(-1, 1, 1)
    x, y = n[:, 0], n[:, 1]
    return torch.stack([c * x - s * y, s * x + c * y, n[:, 2]], 1).to(normals.dtype)


def normals_from_height(height: Tensor) -> Tensor:
    """Unit normals (B, 3, H, W) of a height field (B, 1, H, W) in canvas units (the canvas is 2 units wide).

    Central differences inside, one-sided on the border (``torch.gradient``); a 1-pixel-wide axis has no
    slope along it.
    """
    if height.ndim != 4 or height.shape[1] != 1:
        raise LasagnaError(f"got shape {tuple(height.shape)}; expected (B, 1, H, W)", where="height")
    h = height[:, 0]
    pixel = 2.0 / h.shape[-1]
    zero = torch.zeros_like(h)
    d_row = torch.gradient(h, spacing=pixel, dim=-2)[0] if h.shape[-2] > 1 else zero
    d_col = torch.gradient(h, spacing=pixel, dim=-1)[0] if h.shape[-1] > 1 else zero
    # y up: ∂h/∂y = −∂h/∂row, so n ∝ (−∂h/∂x, +∂h/∂row, 1).
    n = torch.stack([-d_col, d_row, torch.ones_like(h)], 1)
    return n * torch.rsqrt((n * n).sum(1, keepdim=True))


INTEGRATE_NZ_MIN = 0.05
"""Normals' z is clamped to this before `integrate_normals` takes their slopes: a silhouette's rim (n_z → 0) would
give unbounded slopes; 0.05 bounds a slope at about 20 (87°)."""


def integrate_normals(normals: torch.Tensor) -> torch.Tensor:
    """A height field (B, 1, H, W, canvas units, its least value 0) whose gradient fits the slopes of unit
    ``normals`` in the least-squares sense: Frankot & Chellappa (1988), the slopes mirrored to a periodic image of
    twice the size so the borders do not wrap. Inverse of `lasagna.compose.surface.normals_from_height` up to a
    constant, for a smooth field."""
    nz = normals[:, 2:3].clamp_min(INTEGRATE_NZ_MIN)
    p, q = -normals[:, 0:1] / nz, normals[:, 1:2] / nz  # ∂h/∂x (x right) and ∂h/∂row (rows go down, y up)
    h, w = normals.shape[-2:]
    p2 = torch.cat([torch.cat([p, -p.flip(-1)], -1), torch.cat([p.flip(-2), -p.flip(-2).flip(-1)], -1)], -2)
    q2 = torch.cat([torch.cat([q, q.flip(-1)], -1), torch.cat([-q.flip(-2), -q.flip(-2).flip(-1)], -1)], -2)
    fy = torch.fft.fftfreq(2 * h, dtype=normals.dtype).view(-1, 1) * 2 * math.pi
    fx = torch.fft.fftfreq(2 * w, dtype=normals.dtype).view(1, -1) * 2 * math.pi
    denom = fx**2 + fy**2
    denom[0, 0] = 1.0
    z = (-1j * fx * torch.fft.fft2(p2) - 1j * fy * torch.fft.fft2(q2)) / denom
    z[..., 0, 0] = 0.0
    out = torch.fft.ifft2(z).real[..., :h, :w] * (2.0 / w)  # slopes per canvas unit × pixel size
    return out - out.amin(dim=(-2, -1), keepdim=True)


def shadow_heights(normals: Tensor, reduced_by: int = 1) -> Tensor:
    """The heights (B, 1, h, w, canvas units, least value 0) a layer's shadows are traced over: its unit ``normals``
    (B, 3, H, W) reduced to at most ``SHADOW_MAX_SIDE`` on a side (antialiased, renormalised), integrated
    (`integrate_normals`). Canvas units do not depend on the size, so a shadow is as long at any size. Normals that
    are themselves the layer's reduced by ``reduced_by`` (a zoom level's) are traced at most ``SHADOW_MAX_SIDE`` /
    ``reduced_by`` on a side — at the reduction of the full size's trace, so a zoomed-out view and the editor's drag
    proxy trace what the full render traces, reduced, and no more (a light drag repaints the trace every frame)."""
    h, w = normals.shape[-2:]
    scale = min(1.0, SHADOW_MAX_SIDE / max(1, int(reduced_by)) / max(h, w))
    small = normals.detach()
    if scale < 1.0:
        small = downsample(small, (max(1, round(h * scale)), max(1, round(w * scale))))
        small = small * torch.rsqrt((small * small).sum(1, keepdim=True).clamp_min(NORMAL_EPS))
    return integrate_normals(small)


def layer_occlusion(stored: LayerTensors, layer) -> Tensor:
    """The share of the sky (1, 1, h, w) in [0, 1] each pixel of a surface layer's stored map sees — what its
    ``occlusion`` darkens the ambient by (`lasagna.compose.shadow.occlusion` over its heights, its relief and shadow
    depth applied), at the map's size, kept with the map as its render keeps it (the editor's "Show occlusion")."""
    color = stored.color
    same_map = (id(color), color._version)
    lit = deepen_normals(decode_normal_map(color.reshape(-1, *color.shape[-3:])), float(layer.relief))
    fields = _surface_fields(stored, same_map, float(layer.relief), float(layer.shadow_depth), lit, True)
    return upsample(fields["occlusion"], tuple(lit.shape[-2:])).clamp(0.0, 1.0)[:1]


def _surface_fields(
    stored: LayerTensors, same_map: tuple, relief: float, depth: float, normals: Tensor, with_occlusion: bool
) -> dict[str, Tensor]:
    """``heights`` (`shadow_heights` of a stored map's ``normals``, its relief applied, times ``depth``) and, when
    asked, its ``occlusion`` (`lasagna.compose.shadow.occlusion` at the heights' size), kept per map, relief and depth
    (`_HEIGHTS`)."""
    key = (*same_map, relief, depth)
    hit = _HEIGHTS.get(stored)
    if hit is not None and hit[0] == key:
        fields = dict(hit[1])
    else:
        fields = {"heights": shadow_heights(normals, stored.reduced_by) * depth}
    if with_occlusion and "occlusion" not in fields:
        fields["occlusion"] = sky_share(fields["heights"], tuple(fields["heights"].shape[-2:]))
    _HEIGHTS[stored] = (key, fields)
    return fields


# Bicubic overshoot (or a refining step) can push a normal's z below 0 beside a silhouette; it is kept facing the
# viewer.
NORMAL_Z_MIN = 1e-3


def enlarge_surface(surface: Tensor, size: tuple[int, int]) -> Tensor:
    """A height field (B, 1, h, w) or unit normals (B, 3, h, w) enlarged to ``size`` bicubically (normals
    renormalised, kept facing the viewer). Bicubic, not bilinear: normals are a height's slopes, and a bilinear
    height has piecewise-constant slopes (shading in blocks of the working size's pixels), a bicubic one
    continuous slopes. Heights are in canvas units, so normals do not depend on the size they are sampled at."""
    size = (int(size[0]), int(size[1]))
    if tuple(surface.shape[-2:]) == size:
        return surface
    out = torch.nn.functional.interpolate(surface, size=size, mode="bicubic", align_corners=False)
    return out if surface.shape[1] == 1 else facing_normals(out)


def facing_normals(vectors: Tensor) -> Tensor:
    """Unit normals (B, 3, H, W) of vectors that nearly are: z kept at least ``NORMAL_Z_MIN`` (facing the viewer,
    as every height field's normal does), then normalised."""
    out = torch.cat([vectors[:, :2], vectors[:, 2:3].clamp_min(NORMAL_Z_MIN)], 1)
    return out * torch.rsqrt((out * out).sum(1, keepdim=True))


def surface_normals(surface: Tensor) -> Tensor:
    """Unit normals (B, 3, H, W) of a surface: a height field (B, 1, H, W) by ``normals_from_height``, or normal
    vectors (B, 3, H, W) by ``facing_normals``."""
    return normals_from_height(surface) if surface.shape[1] == 1 else facing_normals(surface)


def encode_normal_map(normals: Tensor) -> Tensor:
    """Tangent-space RGB in [0, 1] of unit normals (B, 3, H, W): (n + 1)/2, +Y up (OpenGL convention)."""
    return ((normals + 1.0) * 0.5).clamp(0.0, 1.0)


def decode_normal_map(rgb: Tensor, *, convention: str = "opengl") -> Tensor:
    """Unit normals (B, 3, H, W) of a tangent-space normal map in [0, 1]; ``convention="directx"`` flips Y.

    Renormalised (quantised maps are not exactly unit); a zero vector (below ``NORMAL_EPS``) becomes +z.
    """
    if convention not in ("opengl", "directx"):
        raise LasagnaError(f"unknown normal-map convention {convention!r}; expected opengl or directx", "convention")
    n = rgb * 2.0 - 1.0
    if convention == "directx":
        n = torch.cat([n[:, 0:1], -n[:, 1:2], n[:, 2:3]], 1)
    # The squares summed as written, not ``.sum(1)``: the same bits (x² + y², then + z²) without a strided
    # reduction over channels, which took half the decode's time (a light drag in the editor re-renders this).
    x, y, z = n[:, 0:1], n[:, 1:2], n[:, 2:3]
    length = (x * x + y * y + z * z).sqrt()
    flat = n.new_tensor([0.0, 0.0, 1.0]).view(1, 3, 1, 1)
    return torch.where(length > NORMAL_EPS, n / length.clamp_min(NORMAL_EPS), flat)


INFLATE_CHUNK = 4096
"""Inside pixels per distance block of ``inflate_regions``: a block holds this many × a region's outline pixels."""
DOME_MAX_SIDE = 128
"""The longest side the dome prior inflates silhouettes at (`lasagna.generators.surface.DomePrior`): a larger
estimate's silhouettes are reduced to it and the domes' normals enlarged back (inflation costs inside × outline
pixels per region)."""


def inflate_regions(index: Tensor) -> Tensor:
    """A height field (B, 1, H, W) in canvas units that inflates every labelled region into a round dome.

    ``index`` (B, 1, H, W) integer: ≥ 0 labels a region (an object's silhouette), < 0 is flat background (the
    wall). Each region becomes h = √(R² − (R − d)²), d the distance (pixels) to the nearest pixel outside it
    and R its largest d (+½): a disc inflates to the exact hemisphere. This is the classic shape-from-
    silhouette prior (Johnston's Lumo; Igarashi's Teddy): the surface a model that only knows outlines and
    assumes generic round shapes can reach — the benchmarks' oracle when given the true outlines.
    """
    b_, _, h_, w_ = index.shape
    rows, cols = torch.meshgrid(
        torch.arange(h_, dtype=torch.float64), torch.arange(w_, dtype=torch.float64), indexing="ij"
    )
    pts = torch.stack([rows, cols], -1).reshape(-1, 2)
    height = torch.zeros(b_, 1, h_, w_, dtype=torch.float64)
    for b in range(b_):
        idx = index[b, 0]
        for k in idx.unique().tolist():
            if k < 0:
                continue
            region = (idx == k).to(torch.float64)[None, None]
            # The nearest outside pixel always touches the region: search those only.
            edge = (torch.nn.functional.max_pool2d(region, 3, 1, 1) - region).reshape(-1) > 0
            inside = region.reshape(-1) > 0
            if edge.any():
                # In chunks of rows: the distance matrix of a large region (inside × edge pixels) would not fit.
                inner, rim = pts[inside], pts[edge]
                d = torch.cat([torch.cdist(c, rim).min(dim=1).values for c in inner.split(INFLATE_CHUNK)])
            else:  # the region fills the image
                d = torch.zeros(int(inside.sum()), dtype=torch.float64)
            r = d.max() + 0.5
            height[b, 0].view(-1)[inside] = (r**2 - (r - d) ** 2).clamp_min(0).sqrt()
    return height * (2.0 / w_)  # pixels → canvas units (the canvas is 2 units wide)


# ---- a surface layer of a document ------------------------------------------------------------------------

# The rendered multiplier of each stored normal map, kept while the map's tensors live and unchanged: a render
# plan asks for it on every render, and its statistics (culling) are then computed once per light, not per call.
# A map rendered under a second light is being re-lit (the editor's light drag): its decoded unit normals, which
# do not depend on the light, are kept with it from then on, so each further light costs Lambert alone. A map
# rendered under one light (a render, an export) keeps only its multiplier.
_RENDERED: weakref.WeakKeyDictionary[LayerTensors, tuple[tuple, LayerTensors, Tensor | None]] = (
    weakref.WeakKeyDictionary()
)
SKY_FLOOR = 0.05
"""The least share of the ambient a point keeps under ambient occlusion: a relight ratio divides by a·A + (1 − a)·
max(0, n·l_src), and a point that sees neither the sky nor the source light was black in the photograph (nothing is
known of it), so the ratio there stays at most (a·F + 1 − a)/(a·F) rather than unbounded."""

# The heights a stored map's shadows are traced over (`shadow_heights`) and its ambient occlusion at the traced size,
# kept while the map lives and is unchanged, per relief: a light dragged over a shadow-casting layer integrates its
# heights once, and the occlusion (no light's) is traced once.
_HEIGHTS: weakref.WeakKeyDictionary[LayerTensors, tuple[tuple, dict[str, Tensor]]] = weakref.WeakKeyDictionary()


def memo_tensors(owners=None) -> list[Tensor]:
    """Every tensor ``surface_tensors`` keeps (multipliers, re-lit maps' normals, shadows' heights) for the stored
    maps ``owners`` (LayerTensors; None: every map), for a caller that accounts the memory it holds (the editor's
    session counts its own maps', not another stack's in the same process)."""
    mine = None if owners is None else {id(lt) for lt in owners}
    out: list[Tensor] = []
    for stored, (_, rendered, normals) in list(_RENDERED.items()):
        if mine is None or id(stored) in mine:
            out.append(rendered.color)
            if normals is not None:
                out.append(normals)
    for stored, (_, fields) in list(_HEIGHTS.items()):
        if mine is None or id(stored) in mine:
            out += list(fields.values())
    return out


def surface_range(source_light: str | None, ambient: float, peak: float = 1.0) -> tuple[float, float]:
    """The interval a surface layer's multiplier lies in: [a, 1] (shading) or [a, 1/a] (relight ratio), or with a
    direct term's largest gain ``peak`` > 1 (a light's intensity times its colour's largest channel) [a, a + (1 − a)·
    peak] and that over a."""
    hi = ambient + (1.0 - ambient) * max(1.0, float(peak))
    return (ambient, hi) if source_light is None else (ambient, hi / ambient)


def layer_surface_tensors(stored: LayerTensors, layer) -> tuple[LayerTensors, tuple[float, float]]:
    """A surface layer's multiplier and its range, from the layer's light fields (a `SurfaceLayer`: light, source
    light, ambient, relief, colour, intensity, extra lights, gloss, shininess and shadows) — the one place the
    compositor and the exports read them; a highlight raises the range's top by (1 + gloss) (a shadow only lowers)."""
    ambient, intensity, gloss = float(layer.ambient), float(layer.light_intensity), float(layer.gloss)
    extras = tuple((e.light, tuple(e.color), float(e.intensity)) for e in layer.extra_lights)
    tensors = surface_tensors(
        stored,
        layer.light,
        layer.source_light,
        ambient,
        float(layer.relief),
        layer.light_color,
        intensity,
        extras,
        gloss,
        float(layer.shininess),
        float(layer.shadows),
        float(layer.occlusion),
        float(layer.shadow_depth),
    )
    peak = (intensity * max(layer.light_color) + sum(k * max(c) for _, c, k in extras)) * (1.0 + gloss)
    return tensors, surface_range(layer.source_light, ambient, peak)


def surface_tensors(
    stored: LayerTensors,
    light: str,
    source_light: str | None,
    ambient: float,
    relief: float = 1.0,
    light_color: tuple[float, float, float] = (1.0, 1.0, 1.0),
    light_intensity: float = 1.0,
    extra_lights: tuple[tuple[str, tuple[float, float, float], float], ...] = (),
    gloss: float = 0.0,
    shininess: float = DEFAULT_SHININESS,
    shadows: float = 0.0,
    occlusion: float = 0.0,
    shadow_depth: float = 1.0,
) -> LayerTensors:
    """A surface layer's tensors as the compositor blends them: its normal map ``stored.color`` (..., 3, h, w)
    of values in [0, 1] (the PNG's codes), its relief times ``relief`` (`deepen_normals`), rendered to the
    multiplier (..., 1, h, w) — S(light), or S(light)/S(source_light) — with the map's alpha and mask. ``light``
    and ``source_light`` are condition texts (a named light or ``az=…,el=…``; ``light`` may be a point light
    ``x=…,y=…,z=…``, `point_lambert`, placed in fractions of this map's size). A ``light_color`` c other than
    white makes it (..., 3, h, w): each channel's direct term times c, a + (1 − a)·c·max(0, n·l) (`coloured`), the
    source light staying white; ``light_intensity`` k multiplies the direct term too (its gain is k·c: one channel
    while that is grey). ``extra_lights`` — (light text, colour, intensity) each — add their direct terms,
    a + Σᵢ (Sᵢ − a)·kᵢ·cᵢ (`lit_by`). ``gloss`` > 0 adds each light's highlight of exponent ``shininess`` (the module
    docstring's Gloss; the source light stays diffuse); ``shadows`` > 0 darkens each light's direct term where the
    map's own heights hide the light (the module docstring's Shadows; the source light casts none); ``occlusion`` > 0
    darkens the ambient term where those heights hide the sky (Ambient occlusion); both trace the heights times
    ``shadow_depth``. The same stored map and light fields always give the same bits.
    """
    color = stored.color
    if color.shape[-3] != 3:
        raise LasagnaError(
            f"the normal map has {color.shape[-3]} channel(s); expected an RGB normal map", where="surface layer"
        )
    same_map = (id(color), color._version)
    colour = tuple(float(c) * float(light_intensity) for c in light_color)  # the direct term's gain per channel
    extras = tuple((text, tuple(float(c) * float(k) for c in col)) for text, col, k in extra_lights)
    shine = (float(gloss), float(shininess)) if gloss > 0 else (0.0,)
    key = (*same_map, light, source_light, float(ambient), float(relief), colour, extras, shine, float(shadows))
    key += (float(occlusion), float(shadow_depth))
    hit = _RENDERED.get(stored)
    if hit is not None and hit[0] == key:
        return hit[1]
    relit = hit is not None and hit[0][:2] == same_map and not color.requires_grad
    normals = hit[2] if relit else None
    if normals is None:
        normals = decode_normal_map(color.reshape(-1, *color.shape[-3:]))
    lit = deepen_normals(normals, float(relief))
    point = parse_point(light)
    white = colour == (1.0, 1.0, 1.0)
    if extras or gloss > 0 or shadows > 0 or occlusion > 0:  # direct terms summed, over S(source) for a ratio
        fields = (
            _surface_fields(stored, same_map, float(relief), float(shadow_depth), lit, float(occlusion) > 0)
            if shadows or occlusion
            else {}
        )
        sky = None
        if occlusion > 0:  # the ambient's share: 1 − o·(1 − A), enlarged from the traced size
            sky = 1.0 - float(occlusion) * (1.0 - upsample(fields["occlusion"], tuple(lit.shape[-2:])).to(lit))
            sky = sky.clamp_min(SKY_FLOOR)
        y = lit_by(
            lit,
            ((light, colour), *extras),
            ambient,
            float(gloss),
            float(shininess),
            float(shadows),
            fields.get("heights"),
            sky,
        )
        if source_light is not None:
            source = light_vector(*parse_direction(source_light), dtype=normals.dtype, device=normals.device)
            below = lambert(lit, source, check_ratio_ambient(ambient))
            y = y / (below if sky is None else below + ambient * (sky - 1.0))
    elif point is not None:  # a point light: S(point), coloured, over S(source) for a relight ratio
        y = point_lambert(lit, point, ambient)
        if not white:
            y = tinted(y, colour, ambient)
        if source_light is not None:
            source = light_vector(*parse_direction(source_light), dtype=normals.dtype, device=normals.device)
            y = y / lambert(lit, source, check_ratio_ambient(ambient))
    elif source_light is None and white:
        target = light_vector(*parse_direction(light), dtype=normals.dtype, device=normals.device)
        y = lambert(lit, target, ambient)
    elif white:
        target = light_vector(*parse_direction(light), dtype=normals.dtype, device=normals.device)
        source = light_vector(*parse_direction(source_light), dtype=normals.dtype, device=normals.device)
        y = relight_ratio(lit, target, source, ambient)
    else:
        target = light_vector(*parse_direction(light), dtype=normals.dtype, device=normals.device)
        y = tinted(lambert(lit, target, ambient), colour, ambient)
        if source_light is not None:
            source = light_vector(*parse_direction(source_light), dtype=normals.dtype, device=normals.device)
            y = y / lambert(lit, source, check_ratio_ambient(ambient))
    out = LayerTensors(y.reshape(*color.shape[:-3], y.shape[1], *color.shape[-2:]), stored.alpha, stored.mask)
    _RENDERED[stored] = (key, out, normals if relit else None)
    return out


def inflated_normals(index: Tensor) -> Tensor:
    """Unit normals (B, 3, H, W) of ``inflate_regions(index)``, flat (+z) outside every region: the normals of
    the outline-inflation oracle, which knows where the outlines are, so no slope bleeds onto the background
    beside them (central differences of the height would tilt the first background pixel)."""
    return dome_normals(index, 1.0)


def dome_normals(index: Tensor, height: float = 1.0) -> Tensor:
    """Unit normals (B, 3, H, W) of every labelled region of ``index`` inflated into a dome (``inflate_regions``)
    whose height is ``height`` times the round dome's, flat (+z) outside every region."""
    n = normals_from_height(inflate_regions(index) * height)
    flat = torch.zeros_like(n)
    flat[:, 2] = 1.0
    return torch.where(index >= 0, n, flat)


def label_regions(mask: Tensor) -> Tensor:
    """The connected regions (8-neighbours) of a boolean ``mask`` (B, 1, H, W), labelled 0, 1, … per image
    (int64), −1 outside: each pixel takes the largest pixel number of its region, spread by 3×3 maxima until
    nothing changes (at most the region's pixel count of rounds; a blob's diameter in practice)."""
    if mask.ndim != 4 or mask.shape[1] != 1:
        raise LasagnaError(f"got shape {tuple(mask.shape)}; expected (B, 1, H, W)", where="mask")
    mask = mask.bool().cpu()
    b, _, h, w = mask.shape
    ids = torch.arange(1, h * w + 1, dtype=torch.float64).view(1, 1, h, w).expand(b, 1, h, w)
    zero = torch.zeros((), dtype=torch.float64)
    label = torch.where(mask, ids, zero)
    for _ in range(h * w):
        spread = torch.where(mask, torch.nn.functional.max_pool2d(label, 3, 1, 1), zero)
        if torch.equal(spread, label):
            break
        label = spread
    out = torch.full((b, 1, h, w), -1, dtype=torch.int64)
    for i in range(b):
        values, inverse = torch.unique(label[i], return_inverse=True)
        # values[0] is 0 (the outside) wherever some pixel is outside; the regions are numbered after it.
        first = 1 if float(values[0]) == 0.0 else 0
        out[i] = torch.where(mask[i], inverse - first, out[i])
    return out


def deepen_normals(normals: Tensor, gain: float | Tensor) -> Tensor:
    """Unit normals (B, 3, H, W) of the same surface with its relief times ``gain``: (g·n_x, g·n_y, n_z)
    renormalised. For a height field's normals n ∝ (−∂h/∂x, −∂h/∂y, 1) this is exactly the normals of g·h (the same
    outlines, slopes times g); gain 1 returns ``normals`` unchanged. ``gain`` may be a map (B, 1, H, W): each pixel's
    slopes times its own gain (`calm_walls`)."""
    if isinstance(gain, (int, float)) and gain == 1.0:
        return normals
    return facing_normals(torch.cat([normals[:, :2] * gain, normals[:, 2:3]], 1))


WALL_MARGIN = 1
"""Pixels by which `calm_walls` erodes the walls: a soft silhouette calls an object's rim half wall, and the rim's
slopes are the object's (docs/BENCHMARKS.md, round 18: without a margin the gate cost the objects 0.04–0.11 dB)."""


def calm_walls(normals: Tensor, walls: Tensor, gain: float, margin: int = WALL_MARGIN) -> Tensor:
    """Unit normals (B, 3, H, W) with the walls' slopes times ``gain``: each pixel's slopes times
    1 − w + ``gain``·w, w = ``walls`` (B, 1, H, W) in [0, 1] (1 − the silhouette probability) eroded by ``margin``
    pixels (the least w in each (2·margin + 1)² window), so an object's rim keeps its slopes. The shape prior "a
    painted wall is flat" as a lit estimator told a light needs it: told a light, it reads some of a bare wall's paint
    as relief (docs/BENCHMARKS.md, round 17), and a ratio S(target)/S(source) of relief a times the wall's is a
    times as far from one, so the leak (the layer's PSNR against its mean) rises by about −20·log₁₀ ``gain`` dB
    while the objects (w = 0) keep every slope. ``gain`` 1 returns ``normals`` unchanged."""
    if gain == 1.0:
        return normals
    w = walls.to(normals.dtype)
    if margin > 0:
        w = -torch.nn.functional.max_pool2d(-w, 2 * margin + 1, stride=1, padding=margin)
    return deepen_normals(normals, 1.0 - w + gain * w)


def mix_normals(normals: Tensor, other: Tensor, weight: float) -> Tensor:
    """Unit normals (1 − weight)·``normals`` + weight·``other``, renormalised and kept facing the viewer."""
    return facing_normals((1.0 - weight) * normals + weight * other)


WALL_WEIGHT_FLOOR = 1e-3
"""Floor of the blurred wall weight in ``flatten_walls`` (a neighbourhood the silhouette calls all object: its
slopes are left as they are, since the weight there is ~0 anyway)."""


def flatten_walls(normals: Tensor, walls: Tensor, sigma: float) -> Tensor:
    """Unit normals (B, 3, H, W) with the walls' large-scale tilt removed: the slopes p = (n_x, n_y)/n_z less
    w·(G∗(w·p))/(G∗w), their wall-weighted Gaussian mean (σ = ``sigma`` pixels, `compose.resample.gaussian_blur`),
    w = ``walls`` (B, 1, H, W) in [0, 1] (1 − the silhouette probability). The shape prior "a wall is a plane facing
    the camera": a painted gradient read as relief (a night sky's glow, a vignette) tilts a whole region, while a
    wall's relief (bumps, grooves, ripples shorter than σ) averages to no tilt and is kept (a cosine of wavelength λ
    keeps 1 − exp(−2π²σ²/λ²) of its amplitude). ``sigma`` 0 returns ``normals`` unchanged."""
    if sigma <= 0:
        return normals
    slopes = normals[:, :2] / normals[:, 2:3].clamp_min(NORMAL_Z_MIN)
    w = walls.to(normals.dtype)
    tilt = gaussian_blur(w * slopes, sigma) / gaussian_blur(w, sigma).clamp_min(WALL_WEIGHT_FLOOR)
    flat = slopes - w * tilt
    return facing_normals(torch.cat([flat, torch.ones_like(normals[:, 2:3])], 1))


def coloured(shading: Tensor, colour: tuple[float, float, float], ambient: float = AMBIENT) -> Tensor:
    """A white light's shading a + (1 − a)·max(0, n·l) (B, 1, H, W) under a light of colour c instead: (B, 3, H, W),
    a + (S − a)·c per channel — the direct term coloured, the ambient white (Photoshop's Lighting Effects colours
    its light the same way, its ambience apart)."""
    c = torch.tensor(colour, dtype=shading.dtype, device=shading.device).view(1, 3, 1, 1)
    return ambient + (shading - ambient) * c


def lit_by(
    normals: Tensor,
    lights,
    ambient: float = AMBIENT,
    gloss: float = 0.0,
    shininess: float = DEFAULT_SHININESS,
    shadows: float = 0.0,
    heights: Tensor | None = None,
    sky: Tensor | None = None,
) -> Tensor:
    """a + Σᵢ (Sᵢ − a)·gᵢ of unit ``normals`` (B, 3, H, W) under ``lights`` — (light text, gain (3,)) each, a
    direction or a point light (`point_lambert`), its gain its colour times its intensity: one channel while every
    gain is grey, else three; with ``gloss`` > 0 each light's direct term also carries its highlight (`highlight`,
    the module docstring's Gloss); with ``shadows`` s > 0 each direct term is times 1 − s·(1 − Vᵢ), Vᵢ the light's
    visibility over ``heights`` (B, 1, h, w, canvas units: `shadow_heights`; `lasagna.compose.shadow.shadow_factor`);
    ``sky`` (B, 1, H, W) scales the ambient term a (ambient occlusion: a·sky + Σᵢ …)."""
    if shadows > 0.0 and heights is None:
        raise LasagnaError("shadows need the surface's heights; expected heights (shadow_heights)", "lit_by")
    check_ambient(ambient)
    grey = all(g[0] == g[1] == g[2] for _, g in lights)
    total = None
    for text, gain in lights:
        point = parse_point(text)
        if point is None:
            vector = light_vector(*parse_direction(text), dtype=normals.dtype, device=normals.device)
            s = lambert(normals, vector, ambient)
        else:
            s = point_lambert(normals, point, ambient)
        if gloss > 0.0:
            s = s + (1.0 - ambient) * gloss * highlight(normals, text, shininess)
        g = gain[0] if grey else torch.tensor(gain, dtype=normals.dtype, device=normals.device).view(1, 3, 1, 1)
        if shadows > 0.0:  # the grey gain rides on the shadow's factor, formed at the traced size
            factor = shadow_factor(heights, text, tuple(normals.shape[-2:]), shadows, g if grey else 1.0)
            term = (s - ambient) * factor.to(normals)
            term = term if grey else term * g
        else:
            term = (s - ambient) * g
        total = term if total is None else total + term
    return (ambient if sky is None else ambient * sky) + total


def highlight(normals: Tensor, light: str, shininess: float = DEFAULT_SHININESS) -> Tensor:
    """The Blinn–Phong highlight max(0, n·h)^p·[n·l > 0] (B, 1, H, W) of unit ``normals`` under ``light`` (a direction,
    or a point light with its falloff and cone, as `point_lambert` weighs its direct term): h = (l + v)/|l + v|, v =
    +z, per pixel for a point light. Zero where the light is behind the surface (n·l ≤ 0), as Lambert's term is."""
    point = parse_point(light)
    if point is None:
        lx, ly, lz = unit_vector(*parse_direction(light))
        norm = math.sqrt(lx * lx + ly * ly + (lz + 1.0) ** 2)  # |l + v| ≥ 1 for a light in front (lz ≥ 0)
        hx, hy, hz = lx / norm, ly / norm, (lz + 1.0) / norm
        ndoth = normals[:, 0:1] * hx + normals[:, 1:2] * hy + normals[:, 2:3] * hz
        ndotl = normals[:, 0:1] * lx + normals[:, 1:2] * ly + normals[:, 2:3] * lz
        return ndoth.clamp_min(0.0).pow(float(shininess)) * (ndotl > 0).to(normals.dtype)
    # A point light: l per pixel, its falloff and cone read off point_lambert's direct term at a = 0 over n·l.
    h, w = normals.shape[-2:]
    dx, dy = point_offsets(point, h, w, dtype=normals.dtype, device=normals.device)
    z = float(point[2])
    inv = (dx * dx + dy * dy + z * z).rsqrt()
    lx, ly, lz = dx * inv, dy * inv, z * inv
    hz = lz + 1.0
    hinv = (lx * lx + ly * ly + hz * hz).rsqrt()
    ndoth = (normals[:, 0:1] * lx + normals[:, 1:2] * ly + normals[:, 2:3] * hz) * hinv
    ndotl = normals[:, 0:1] * lx + normals[:, 1:2] * ly + normals[:, 2:3] * lz
    flat = torch.zeros_like(normals)
    flat[:, 2] = 1.0  # the falloff and cone alone: a surface facing +z sees f·l_z, divided back by l_z
    weight = point_lambert(flat, point, 0.0) / lz
    return ndoth.clamp_min(0.0).pow(float(shininess)) * (ndotl > 0).to(normals.dtype) * weight


def tinted(shading: Tensor, gain: tuple[float, float, float], ambient: float = AMBIENT) -> Tensor:
    """A white light's shading (B, 1, H, W) with its direct term times ``gain`` (a light's colour times its
    intensity): one channel a + (S − a)·g while the three gains are equal, else `coloured` (three channels)."""
    if gain[0] == gain[1] == gain[2]:
        return ambient + (shading - ambient) * gain[0]
    return coloured(shading, gain, ambient)


def relieved_map(color: Tensor, relief: float) -> Tensor:
    """A stored normal map's codes (..., 3, h, w) in [0, 1] with its relief times ``relief`` (`deepen_normals`),
    encoded again: the map a reader must light to see what the layer renders (a hidden normal layer, `lasagna
    export --normal-map`). Relief 1 returns ``color`` itself, bit for bit."""
    if float(relief) == 1.0:
        return color
    normals = decode_normal_map(color.reshape(-1, *color.shape[-3:]))
    return encode_normal_map(deepen_normals(normals, float(relief))).reshape(color.shape)
