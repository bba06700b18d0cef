"""Painted texture families: 2D patterns laid on a surface like a decal, independent of its geometry.

Each family has the signature of `lasagna.world.textures` (``pattern(p, prm, seed) -> (N,)`` in
[0, 1]) but reads only a 2D paint coordinate: the point's first two coordinates (object-local x, y
for objects, i.e. a projection along the object's local z; the wall's own x, y), rotated by the
azimuth φ = atan2(u_y, u_x) of the parameter direction u, offset by o and scaled by the frequency f:

    a = f·( cos φ·(x + o_x) + sin φ·(y + o_y)),   b = f·(−sin φ·(x + o_x) + cos φ·(y + o_y)).

On the wall (the plane the camera faces) this is a similarity transform, so any angle and scale is
drawn; on an object it is a planar projection, so paint wraps over the surface as printed decals do.
None of these patterns says anything about the shape it lies on: that is the point of them (the world
teaches that texture is not geometry).

Families: ``deadleaves`` (occluding discs of many sizes: the scale-invariant statistics of natural
images, Lee, Mumford & Huang 2001), ``cells`` (Voronoi cells with a tone each and dark borders),
``gradient`` (smooth linear or radial ramps), ``glyphs`` (text: letters and digits rendered with
Pillow's bundled font), ``photo`` (crops of public-domain photographs as paint); and for the ``far``
split only, ``hexagons`` (a hexagonal tiling with borders), ``zigzag`` (chevron stripes) and
``naturephoto`` (photographs of grass, gravel and brick); for the ``select`` split only, ``plaid``
(tartan bands), ``scales`` (overlapping fish scales) and ``weave`` (basket weave).
"""

from __future__ import annotations

import functools
import math
import string
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from lasagna.world.noise import hash01

Tensor = torch.Tensor
Vec = tuple[Tensor, Tensor, Tensor]

PAINT_DIR = Path(__file__).resolve().parents[1] / "_data" / "paint"
"""The photographs used as paint (written by ``examples/make_paint.py``; credits there)."""
PHOTOS: dict[str, tuple[str, ...]] = {
    "photo": ("camera", "coins", "moon", "hubble", "ihc", "retina", "motorcycle", "page", "cell"),
    "naturephoto": ("grass", "gravel", "brick"),
}
GLYPHS = string.ascii_letters + string.digits
_GLYPH_CELL = 32  # pixels per glyph cell in the atlas

# Dead leaves: the relative disc-cell sizes of the layers, topmost first. Mixed sizes in a fixed,
# non-monotone order, so small leaves lie on large ones and large on small, as in the model.
_LEAF_LAYERS = (1.0, 0.42, 0.74, 0.28, 0.58, 0.2, 0.5, 0.34)


def _coords(p: Vec, prm: Tensor) -> tuple[Tensor, Tensor]:
    """The paint coordinate (a, b) of the module docstring."""
    phi = torch.atan2(prm[:, 2], prm[:, 1])
    c, s = torch.cos(phi), torch.sin(phi)
    x, y = p[0] + prm[:, 4], p[1] + prm[:, 5]
    f = prm[:, 0]
    return f * (c * x + s * y), f * (-s * x + c * y)


def _cell_hash(ix: Tensor, iy: Tensor, k: int | Tensor, seed: Tensor, dtype: torch.dtype) -> Tensor:
    kk = k if isinstance(k, Tensor) else torch.full_like(ix, k)
    return hash01(ix, iy, kk, seed, dtype)


def deadleaves(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Dead leaves: the tone of the topmost disc covering the point (or a background tone).

    Layer l holds one disc per cell of a grid of spacing ``_LEAF_LAYERS[l]`` (in 1/f units), centred
    at a hashed point of its cell with radius 0.35–0.95 cells, so only the 3×3 neighbouring cells can
    cover a point. Within a layer the disc with the highest hashed depth wins.
    """
    a, b = _coords(p, prm)
    dt = a.dtype
    out = torch.full_like(a, -1.0)
    for layer, size in enumerate(_LEAF_LAYERS):
        qa, qb = a / size, b / size
        ca, cb = torch.floor(qa).to(torch.int64), torch.floor(qb).to(torch.int64)
        best_depth = torch.full_like(a, -1.0)
        tone = torch.zeros_like(a)
        for da in (-1, 0, 1):
            for db in (-1, 0, 1):
                ia, ib = ca + da, cb + db
                k = 8 * layer
                cx = ia.to(dt) + _cell_hash(ia, ib, k, seed, dt)
                cy = ib.to(dt) + _cell_hash(ia, ib, k + 1, seed, dt)
                r = 0.35 + 0.6 * _cell_hash(ia, ib, k + 2, seed, dt)
                depth = _cell_hash(ia, ib, k + 3, seed, dt)
                inside = ((qa - cx) ** 2 + (qb - cy) ** 2 <= r * r) & (depth > best_depth)
                best_depth = torch.where(inside, depth, best_depth)
                tone = torch.where(inside, _cell_hash(ia, ib, k + 4, seed, dt), tone)
        out = torch.where((out < 0) & (best_depth >= 0), tone, out)
    background = hash01(torch.zeros_like(seed), torch.zeros_like(seed), torch.full_like(seed, 99), seed, dt)
    return torch.where(out < 0, background, out)


def cells(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Voronoi cells (one jittered site per grid cell) with a hashed tone each and dark borders.

    A point is on a border where the distances to its nearest two sites differ by less than
    0.4·duty (F2 − F1, Worley 1996); the border is 0, a cell's tone lies in [0.25, 1].
    """
    a, b = _coords(p, prm)
    dt = a.dtype
    ca, cb = torch.floor(a).to(torch.int64), torch.floor(b).to(torch.int64)
    f1 = torch.full_like(a, math.inf)
    f2 = torch.full_like(a, math.inf)
    tone = torch.zeros_like(a)
    for da in (-1, 0, 1):
        for db in (-1, 0, 1):
            ia, ib = ca + da, cb + db
            sx = ia.to(dt) + 0.1 + 0.8 * _cell_hash(ia, ib, 0, seed, dt)
            sy = ib.to(dt) + 0.1 + 0.8 * _cell_hash(ia, ib, 1, seed, dt)
            d = torch.sqrt((a - sx) ** 2 + (b - sy) ** 2)
            nearer = d < f1
            f2 = torch.where(nearer, f1, torch.minimum(f2, d))
            tone = torch.where(nearer, 0.25 + 0.75 * _cell_hash(ia, ib, 2, seed, dt), tone)
            f1 = torch.where(nearer, d, f1)
    return torch.where(f2 - f1 < 0.4 * prm[:, 7], torch.zeros_like(tone), tone)


def gradient(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """A smooth ramp: linear along the paint axis a (extra < ½) or radial about a point (extra ≥ ½).

    Uses the unscaled rotated coordinate, so the ramp spans 1/f … 4/f world units whatever the offset.
    """
    phi = torch.atan2(prm[:, 2], prm[:, 1])
    x, y = p[0], p[1]
    f = prm[:, 0]
    linear = 0.5 + 0.5 * f * (torch.cos(phi) * x + torch.sin(phi) * y)
    cx = torch.remainder(prm[:, 4], 2.0) - 1.0
    cy = torch.remainder(prm[:, 5], 2.0) - 1.0
    radial = 1.0 - 0.5 * f * torch.sqrt((x - cx) ** 2 + (y - cy) ** 2)
    return torch.where(prm[:, 9] < 0.5, linear, radial).clamp(0.0, 1.0)


@functools.lru_cache(maxsize=1)
def glyph_atlas() -> Tensor:
    """(G, 32, 32) float64 ink coverage in [0, 1] of the letters and digits `GLYPHS`.

    Rendered once with Pillow's bundled scalable font (``ImageFont.load_default(size=26)``), each
    centred in its cell. The exact pixels depend on Pillow's FreeType build, like any text rendering.
    """
    font = ImageFont.load_default(size=26)
    atlas = np.zeros((len(GLYPHS), _GLYPH_CELL, _GLYPH_CELL))
    for i, ch in enumerate(GLYPHS):
        img = Image.new("L", (_GLYPH_CELL, _GLYPH_CELL), 0)
        draw = ImageDraw.Draw(img)
        left, top, right, bottom = draw.textbbox((0, 0), ch, font=font)
        draw.text(
            ((_GLYPH_CELL - (right - left)) / 2 - left, (_GLYPH_CELL - (bottom - top)) / 2 - top),
            ch,
            fill=255,
            font=font,
        )
        atlas[i] = np.asarray(img, dtype=np.float64) / 255.0
    return torch.from_numpy(atlas)


def glyphs(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Text: one hashed glyph per unit cell of the paint coordinate (a fraction ``duty`` of cells
    blank); dark ink on a light ground, or light on dark where extra ≥ ½."""
    a, b = _coords(p, prm)
    dt = a.dtype
    ca, cb = torch.floor(a).to(torch.int64), torch.floor(b).to(torch.int64)
    atlas = glyph_atlas().to(dtype=dt, device=a.device)
    g = (_cell_hash(ca, cb, 0, seed, dt) * len(GLYPHS)).to(torch.int64).clamp_max(len(GLYPHS) - 1)
    col = ((a - ca.to(dt)) * _GLYPH_CELL).to(torch.int64).clamp(0, _GLYPH_CELL - 1)
    row = ((1.0 - (b - cb.to(dt))) * _GLYPH_CELL).to(torch.int64).clamp(0, _GLYPH_CELL - 1)  # b points up
    ink = atlas[g, row, col]
    ink = torch.where(_cell_hash(ca, cb, 1, seed, dt) < prm[:, 7], torch.zeros_like(ink), ink)
    return torch.where(prm[:, 9] < 0.5, 1.0 - ink, ink)


@functools.cache
def photo_stack(family: str) -> Tensor:
    """(P, S, S) float64 luminance of the family's photographs, each stretched to [0, 1]."""
    rows = []
    for name in PHOTOS[family]:
        with Image.open(PAINT_DIR / f"{name}.png") as im:
            v = np.asarray(im.convert("L"), dtype=np.float64)
        lo, hi = np.percentile(v, 1), np.percentile(v, 99)
        rows.append(np.clip((v - lo) / max(hi - lo, 1.0), 0.0, 1.0))
    return torch.from_numpy(np.stack(rows))


def _mirror(x: Tensor) -> Tensor:
    """A triangle wave of period 2 in [0, 1]: mirrored repeats, so tiled photographs have no seams."""
    t = torch.remainder(x, 2.0)
    return 1.0 - (t - 1.0).abs()


def _photo(family: str, p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """One photograph (picked by the surface's seed) sampled bilinearly, mirrored beyond its edges."""
    a, b = _coords(p, prm)
    dt = a.dtype
    images = photo_stack(family).to(dtype=dt, device=a.device)
    n, size = images.shape[0], images.shape[-1]
    which = (hash01(seed, seed, torch.full_like(seed, 7), seed, dt) * n).to(torch.int64).clamp_max(n - 1)
    u = _mirror(a) * (size - 1)
    v = (1.0 - _mirror(b)) * (size - 1)
    u0, v0 = torch.floor(u).clamp(0, size - 2), torch.floor(v).clamp(0, size - 2)
    fu, fv = u - u0, v - v0
    i0, j0 = v0.to(torch.int64), u0.to(torch.int64)
    top = torch.lerp(images[which, i0, j0], images[which, i0, j0 + 1], fu)
    bottom = torch.lerp(images[which, i0 + 1, j0], images[which, i0 + 1, j0 + 1], fu)
    return torch.lerp(top, bottom, fv).clamp(0.0, 1.0)


def photo(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    return _photo("photo", p, prm, seed)


def naturephoto(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    return _photo("naturephoto", p, prm, seed)


# A hexagonal tiling: axial coordinates (Amit Patel, "Hexagonal Grids") of pointy-top hexagons of
# circumradius 1/√3, so neighbouring centres are 1 apart.
_SQRT3 = math.sqrt(3.0)


def hexagons(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Hexagonal cells with a hashed tone each and dark borders (width = duty of the apothem)."""
    a, b = _coords(p, prm)
    dt = a.dtype
    size = 1.0 / _SQRT3
    q = (_SQRT3 / 3.0 * a - b / 3.0) / size
    r = (2.0 / 3.0 * b) / size
    # Cube rounding: round all three cube coordinates, then fix the one with the largest error.
    x, z = q, r
    y = -x - z
    rx, ry, rz = torch.round(x), torch.round(y), torch.round(z)
    dx, dy, dz = (rx - x).abs(), (ry - y).abs(), (rz - z).abs()
    fix_x = (dx > dy) & (dx > dz)
    fix_y = ~fix_x & (dy > dz)
    rx = torch.where(fix_x, -ry - rz, rx)
    ry = torch.where(fix_y, -rx - rz, ry)
    rz = torch.where(~fix_x & ~fix_y, -rx - ry, rz)
    # The cell centre, and the distance to it measured by the hexagon's own (infinity-like) norm.
    cxa = size * (_SQRT3 * rx + _SQRT3 / 2.0 * rz)
    cxb = size * (1.5 * rz)
    px, py = (a - cxa).abs(), (b - cxb).abs()
    apothem = 0.5
    dist = torch.maximum(px, 0.5 * px + (_SQRT3 / 2.0) * py)  # = apothem on the hexagon's edge
    tone = 0.25 + 0.75 * hash01(rx.to(torch.int64), rz.to(torch.int64), torch.zeros_like(seed), seed, dt)
    return torch.where(dist > apothem * (1.0 - prm[:, 7]), torch.zeros_like(tone), tone)


def zigzag(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Chevron stripes: stripes across b displaced by a triangle wave of a (amplitude ½ + extra)."""
    a, b = _coords(p, prm)
    s = b + (0.5 + prm[:, 9]) * (1.0 - 2.0 * (torch.remainder(a, 2.0) - 1.0).abs())
    return (torch.remainder(s, 1.0) < prm[:, 7]).to(a.dtype)


# ---- the select split's families (lasagna.world.splits): neither train's nor far's -------------------


def plaid(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Tartan: two sets of bands (one along a, one along b, widths duty and duty/2) whose tones add."""
    a, b = _coords(p, prm)
    band_a = (torch.remainder(a, 1.0) < prm[:, 7]).to(a.dtype)
    band_b = (torch.remainder(b + prm[:, 9], 1.0) < 0.5 * prm[:, 7]).to(a.dtype)
    return 0.15 + 0.45 * band_a + 0.4 * band_b


def scales(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Fish scales: rows of overlapping discs, each row shifted half a disc, the lower row on top;
    a hashed tone per scale and a dark rim (width duty of the radius)."""
    a, b = _coords(p, prm)
    dt = a.dtype
    best, tone = torch.full_like(a, -1.0), torch.zeros_like(a)
    base_row = torch.floor(b * 2.0)
    for dr in (1, 0, -1):  # higher rows first, so the lower row (drawn last) overlaps them
        row = base_row + dr
        shift = 0.5 * torch.remainder(row, 2.0)
        col = torch.floor(a - shift + 0.5)
        for dc in (-1.0, 0.0, 1.0):
            cc = col + dc
            ca, cb = cc + shift, row * 0.5
            r = torch.sqrt((a - ca) ** 2 + (b - cb) ** 2)
            inside = (r < 0.5) & (b <= cb + 1e-9)  # the upper half of each disc is hidden by the row above
            h = hash01(cc.to(torch.int64), row.to(torch.int64), torch.full_like(seed, 3), seed, dt)
            value = torch.where(r > 0.5 * (1.0 - prm[:, 7]), torch.zeros_like(h), 0.3 + 0.7 * h)
            take = inside & (best < 0)
            tone = torch.where(take, value, tone)
            best = torch.where(take, torch.ones_like(best), best)
    return tone


def weave(p: Vec, prm: Tensor, seed: Tensor) -> Tensor:
    """Basket weave: unit squares alternately filled with bands along a and along b (duty = gap)."""
    a, b = _coords(p, prm)
    ia, ib = torch.floor(a), torch.floor(b)
    along_a = torch.remainder(ia + ib, 2.0) < 0.5
    across = torch.where(along_a, torch.remainder(b * 3.0, 1.0), torch.remainder(a * 3.0, 1.0))
    band = across > prm[:, 7]
    return torch.where(band, torch.where(along_a, 0.9, 0.6).to(a.dtype), torch.zeros_like(a))
