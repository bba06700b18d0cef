"""Cast shadows over a height field: which pixels of a surface layer see each of its lights.

A surface layer's shading S = a + (1 − a)·max(0, n·l) (`lasagna.compose.surface`) is local: a face turned away
from the light is dark, but a bump does not darken the ground behind it. With ``shadows`` s > 0 a layer's direct
term is also times 1 − s·(1 − V), V the visibility of the light over the layer's heights — the height field whose
slopes best fit its normal map (`lasagna.compose.surface.integrate_normals`, Frankot–Chellappa), the self-shadowing
of Sprite Lamp's and Laigter's depth maps and of a displacement render. Heights are in canvas units (the canvas is 2
units wide, y up; `lasagna.compose.surface`), their least value 0: the plane a point light's height is measured
from.

- **Directional light** l = (l_x, l_y, l_z): a pixel p is in shadow when the ray from its surface point toward the
  light passes below the height field somewhere ahead, h(p + t·d) > h(p) + t·r for some t > 0, with d = (l_x, l_y)/
  |(l_x, l_y)| the light's direction across the image and r = l_z/|(l_x, l_y)| the ray's climb per unit of travel.
  Along each line of direction d that is a running maximum: p is lit iff max_{t > 0} g(p + t·d) ≤ g(p), g(q) =
  h(q) − r·(q·d). The heights are resampled onto a grid turned so that d runs along its rows (bilinear), the maximum
  taken ahead of each sample by one ``cummax`` per row, and the answer sampled back at the pixels (bilinear): O(pixels)
  per light, whatever its elevation — Max's horizon mapping ("Horizon mapping: shadows for bump-mapped surfaces",
  1988) for one direction. A light on the view axis casts nothing.
- **Point or spot light** at (x, y, z) (`lasagna.document.condition.parse_point`: x, y fractions of the map, z in
  units of its longer side above the heights' zero): a point is hidden when a point nearer the light's foot on the
  same ray out of it lies less steeply below the light — a running minimum along each ray, on a polar grid about the
  foot (`point_visibility`); what lies outside the map casts nothing. A spot's cone does not change its shadows.
- **Ambient occlusion**: the share of the sky a point of the height field sees, cosine-weighted — the mean
  visibility of ``OCCLUSION_AZIMUTHS`` × ``OCCLUSION_ELEVATIONS`` directional lights spread over the hemisphere so
  that each stands for an equal share of a cosine-weighted sky (elevations from the view axis asin √u for u the
  middles of equal bands), traced at most at ``OCCLUSION_MAX_SIDE`` on a side (it varies slowly) — the
  screen-space ambient occlusion of a height map (Sprite Lamp's and Laigter's AO maps). A flat map sees all of it.

Shadows are traced on the heights reduced to at most ``SHADOW_MAX_SIDE`` pixels on a side and the visibility
enlarged bilinearly to the layer (edges soft over about a traced pixel). A height rising above the ray by less than
``SHADOW_EPS`` casts nothing, so resampling never shadows a smooth surface by itself. The visibility is a constant
of the stored map and the light: no gradient flows through it.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor

from lasagna.compose.resample import downsample, upsample
from lasagna.document.condition import parse_direction, parse_point, unit_vector

SHADOW_MAX_SIDE = 512
"""Shadows are traced at most this many pixels on a side (module docstring): a 4096² layer's shadows cost what a
512² one's do, their edges soft over 1/512 of the layer."""
SHADOW_EPS = 1e-3
"""Canvas units (a 512-pixel map's pixel is 2/512 ≈ 0.004): how far the heights must rise above a ray to block it,
so the bilinear resampling of a smooth surface never shadows itself."""
OCCLUSION_MAX_SIDE = 256
"""Ambient occlusion is traced at most this many pixels on a side: 36 directions, once per map and relief."""
OCCLUSION_AZIMUTHS = 12
OCCLUSION_ELEVATIONS = 3
"""The sky's directions for ambient occlusion: 12 azimuths 30° apart at 3 elevations, each an equal share of a
cosine-weighted hemisphere (module docstring)."""
ACROSS_MIN = 1e-9
"""A directional light whose component across the image is below this is on the view axis: it casts no shadow."""


def visibility(height: Tensor, light: str, size: tuple[int, int]) -> Tensor:
    """The visibility (B, 1, *size) in [0, 1] of ``light`` (a condition text: a direction or a point or spot light)
    from each pixel over ``height`` (B, 1, h, w, canvas units, least value 0), traced at ``height``'s size and
    enlarged bilinearly to ``size`` (the module docstring). 1 lit, 0 in shadow."""
    with torch.no_grad():
        return upsample(_traced(height, light), tuple(size)).clamp(0.0, 1.0)


def _traced(height: Tensor, light: str) -> Tensor:
    """``light``'s visibility over ``height`` at its own size (a direction or a point or spot light)."""
    point = parse_point(light)
    if point is None:
        return directional_visibility(height, unit_vector(*parse_direction(light)))
    return point_visibility(height, (float(point[0]), float(point[1]), float(point[2])))


def shadow_factor(height: Tensor, light: str, size: tuple[int, int], strength: float, gain: float = 1.0) -> Tensor:
    """What a light's direct term is multiplied by for a layer's ``shadows`` s = ``strength``: g·(1 − s·(1 − V))
    (B, 1, *size), V ``light``'s visibility over ``height`` (`visibility`), g a grey ``gain`` (the light's). Formed
    at the traced size and then enlarged: bilinear enlargement commutes with an affine map of its values, so this is
    g times `visibility`'s factor up to float rounding, at one full-size operation instead of five (a light drag
    repaints it every frame)."""
    with torch.no_grad():
        seen = _traced(height, light).clamp(0.0, 1.0)
        return upsample(gain * (1.0 - strength * (1.0 - seen)), tuple(size))


def occlusion(height: Tensor, size: tuple[int, int]) -> Tensor:
    """The ambient visibility (B, 1, *size) in [0, 1] of ``height`` (B, 1, h, w, canvas units): the share of a
    cosine-weighted sky each point sees (module docstring), traced at most at ``OCCLUSION_MAX_SIDE`` and enlarged
    bilinearly. 1 where nothing rises around a point."""
    with torch.no_grad():
        h, w = height.shape[-2:]
        scale = min(1.0, OCCLUSION_MAX_SIDE / max(h, w))
        small = height if scale >= 1.0 else downsample(height, (max(1, round(h * scale)), max(1, round(w * scale))))
        seen = torch.zeros_like(small)
        for k in range(OCCLUSION_ELEVATIONS):
            el = math.degrees(math.asin(math.sqrt((k + 0.5) / OCCLUSION_ELEVATIONS)))
            for j in range(OCCLUSION_AZIMUTHS):
                seen += directional_visibility(small, unit_vector(360.0 * (j + 0.5) / OCCLUSION_AZIMUTHS, el))
        seen /= OCCLUSION_ELEVATIONS * OCCLUSION_AZIMUTHS
        return upsample(seen, tuple(size)).clamp(0.0, 1.0)


def directional_visibility(height: Tensor, light: tuple[float, float, float], eps: float = SHADOW_EPS) -> Tensor:
    """Visibility (B, 1, H, W) of the unit ``light`` (x right, y up, z toward the viewer) over ``height`` (B, 1, H,
    W, canvas units): the running maximum of g = h − r·(q·d) ahead of each pixel along the light's direction d across
    the image (module docstring), on a grid turned to d."""
    lx, ly, lz = (float(c) for c in light)
    across = math.hypot(lx, ly)
    b, _, h, w = height.shape
    if across < ACROSS_MIN:
        return torch.ones_like(height)
    dc, dr = lx / across, -ly / across  # d in pixel axes: columns right, rows down (y up)
    rise = (2.0 / w) * lz / across  # canvas units the ray climbs per pixel travelled toward the light
    cc, rc = (w - 1) / 2, (h - 1) / 2
    # The turned grid covers the map's corners, one pixel beyond: u along d (toward the light), v across it.
    corners = [(x - cc, y - rc) for x in (-0.5, w - 0.5) for y in (-0.5, h - 0.5)]
    reach_u = math.ceil(max(abs(x * dc + y * dr) for x, y in corners)) + 1
    reach_v = math.ceil(max(abs(-x * dr + y * dc) for x, y in corners)) + 1
    n_u, n_v = 2 * reach_u + 1, 2 * reach_v + 1
    # The turned grid in grid_sample's normalised coordinates, each an outer sum of a column's and a row's part (an
    # affine map, written into one tensor without per-sample Python arithmetic): column j of a row is u = reach_u − j,
    # running from the light's side back, so a running maximum along each row is the maximum ahead; row i is
    # v = i − reach_v across it.
    kw = dict(dtype=height.dtype, device=height.device)
    xo = (2 * torch.arange(n_u, **kw) + 1) / n_u - 1  # the turned grid's own normalised coordinates
    yo = (2 * torch.arange(n_v, **kw) + 1) / n_v - 1
    grid = _affine_grid(xo, yo, (-n_u * dc / w, -n_v * dr / w), (-n_u * dr / h, n_v * dc / h))
    turned = F.grid_sample(
        height, grid.expand(b, n_v, n_u, 2), mode="bilinear", padding_mode="border", align_corners=False
    )
    u = torch.arange(reach_u, -reach_u - 1, -1, **kw).view(1, n_u)
    g = turned - rise * u
    # Only the map occludes: beyond its edge (normalised coordinates past ±1) the heights are unknown and cast nothing.
    x, y = grid[..., 0], grid[..., 1]
    outside = ((x > 1.0) | (x < -1.0) | (y > 1.0) | (y < -1.0))[:, None]
    upto = g.masked_fill(outside, -math.inf).cummax(-1).values  # max over u' ≥ u (u descends along the row)
    shade = torch.zeros_like(g)
    torch.gt(upto[..., :-1], g[..., 1:] + eps, out=shade[..., 1:])  # the maximum over u' > u above the ray
    # Each pixel in the turned grid (the rotation's inverse), again an outer sum.
    xp = (2 * torch.arange(w, **kw) + 1) / w - 1
    yp = (2 * torch.arange(h, **kw) + 1) / h - 1
    back = _affine_grid(xp, yp, (-w * dc / n_u, -h * dr / n_u), (-w * dr / n_v, h * dc / n_v))
    # 1 − the shade sampled back (not the lit share): bilinear weights of zeros sum to exactly 0, so a pixel no shadow
    # comes near is exactly 1 and a layer without shadows renders as its shading alone.
    shade = F.grid_sample(shade, back.expand(b, h, w, 2), mode="bilinear", padding_mode="border", align_corners=False)
    return 1.0 - shade


def _affine_grid(xs: Tensor, ys: Tensor, x_of: tuple[float, float], y_of: tuple[float, float]) -> Tensor:
    """A sampling grid (1, len(ys), len(xs), 2) of grid_sample's normalised coordinates: at (xs[j], ys[i]) the point
    (x_of[0]·xs[j] + x_of[1]·ys[i], y_of[0]·xs[j] + y_of[1]·ys[i]) — a linear map, each coordinate an outer sum."""
    grid = torch.empty(1, ys.numel(), xs.numel(), 2, dtype=xs.dtype, device=xs.device)
    torch.add((x_of[0] * xs).view(1, -1), (x_of[1] * ys).view(-1, 1), out=grid[0, ..., 0])
    torch.add((y_of[0] * xs).view(1, -1), (y_of[1] * ys).view(-1, 1), out=grid[0, ..., 1])
    return grid


def point_visibility(height: Tensor, point: tuple[float, float, float], eps: float = SHADOW_EPS) -> Tensor:
    """Visibility (B, 1, H, W) of a point light at (x, y, z) (fractions of the map from its top-left; z in units of
    its longer side above the heights' zero) over ``height`` (B, 1, H, W, canvas units). Seen from the light, a point
    q at distance ρ_q across the image from the light's foot lies σ(q) = (z_L − h(q))/ρ_q below it per unit of
    travel; p is hidden when a point nearer the foot on the same ray is less steep below the light, min_{ρ_q < ρ_p}
    σ(q) < σ(p): a running minimum along each ray out of the foot, taken on a polar grid (about a ray per pixel of the
    map's border, samples one pixel apart along each) and sampled back at the pixels (bilinear), as the direction's
    running maximum is on its turned grid."""
    b, _, h, w = height.shape
    x, y, z = point
    per_pixel = w / 2.0  # pixels per canvas unit
    foot_c, foot_r, light_z = x * w - 0.5, y * h - 0.5, z * max(h, w)
    ground = height * per_pixel  # heights in pixels
    corners = [(-0.5, -0.5), (w - 0.5, -0.5), (-0.5, h - 0.5), (w - 0.5, h - 0.5)]
    reach = max(math.hypot(c - foot_c, r - foot_r) for c, r in corners) + 1.0
    near = math.hypot(max(-0.5 - foot_c, 0.0, foot_c - (w - 0.5)), max(-0.5 - foot_r, 0.0, foot_r - (h - 0.5)))
    near = max(near - 1.0, 0.0)
    if near == 0.0:  # the foot over the map (or beside it): every direction
        first, last = -math.pi, math.pi
    else:  # outside the map: the angles it subtends, less than a half-turn, measured from its centre's
        mid = math.atan2((h - 1) / 2 - foot_r, (w - 1) / 2 - foot_c)
        turns = [math.remainder(math.atan2(r - foot_r, c - foot_c) - mid, 2 * math.pi) for c, r in corners]
        first, last = mid + min(turns) - 1.0 / reach, mid + max(turns) + 1.0 / reach
    n_rho = math.ceil(reach - near) + 2
    # Rays one pixel apart where they leave the map: about its perimeter's pixels, fewer than 2π·reach from a corner.
    n_ang = min(math.ceil((last - first) * reach), 2 * (h + w)) + 2
    kw = dict(dtype=height.dtype, device=height.device)
    rho = near + torch.arange(n_rho, **kw)
    ang = first + (last - first) * torch.arange(n_ang, **kw) / (n_ang - 1)  # both ends: a full turn's are one ray
    # The polar grid in grid_sample's normalised coordinates: the foot's plus ρ·(cos θ, sin θ), an outer product.
    grid = torch.empty(1, n_ang, n_rho, 2, **kw)
    torch.outer(torch.cos(ang) * (2.0 / w), rho, out=grid[0, ..., 0]).add_((foot_c + 0.5) * 2.0 / w - 1.0)
    torch.outer(torch.sin(ang) * (2.0 / h), rho, out=grid[0, ..., 1]).add_((foot_r + 0.5) * 2.0 / h - 1.0)
    under = F.grid_sample(
        ground, grid.expand(b, n_ang, n_rho, 2), mode="bilinear", padding_mode="border", align_corners=False
    )
    gx, gy = grid[..., 0], grid[..., 1]
    outside = ((gx > 1.0) | (gx < -1.0) | (gy > 1.0) | (gy < -1.0))[:, None]
    safe = rho.clamp_min(1e-6)
    steep = (light_z - under) / safe
    occluder = steep.masked_fill(outside, math.inf)
    if near == 0.0:
        occluder[..., 0] = math.inf  # the foot itself (ρ = 0) hides nothing
    nearer = torch.full_like(steep, math.inf)
    torch.cummin(occluder[..., :-1], -1, out=(nearer[..., 1:], torch.empty(nearer[..., 1:].shape, dtype=torch.long)))
    # Rising more than ``eps`` above the ray at ρ_q is a slope short of σ(p) by eps/ρ_q ≥ eps/ρ_p: the bound that needs
    # no ρ_q (a height within eps of the ray may block a little early, never a smooth surface itself).
    shade = (nearer < steep - eps * per_pixel / safe).to(height.dtype)
    cols = torch.arange(w, **kw).view(1, w) - foot_c
    rows = torch.arange(h, **kw).view(h, 1) - foot_r
    back = torch.empty(1, h, w, 2, **kw)
    p_ang = torch.atan2(rows, cols)
    if near > 0.0:
        p_ang = mid + torch.remainder(p_ang - mid + math.pi, 2 * math.pi) - math.pi
    # The fractional sample along the ray (ρ − near) and the fractional ray, as grid_sample's coordinates.
    torch.hypot(cols, rows, out=back[0, ..., 0]).add_(0.5 - near).mul_(2.0 / n_rho).sub_(1.0)
    scale = (n_ang - 1) / (last - first)
    p_ang.sub_(first).mul_(scale).add_(0.5).mul_(2.0 / n_ang).sub_(1.0)
    back[0, ..., 1] = p_ang
    return 1.0 - F.grid_sample(
        shade, back.expand(b, h, w, 2), mode="bilinear", padding_mode="border", align_corners=False
    )
