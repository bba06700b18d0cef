"""Rendering scenes to ground-truth tensors, and the `generate` entry point.

The camera is orthographic, looking down −z at the square x, y ∈ [−1, 1]; pixel (i, j) of an R×R
image looks along the ray through x = −1 + (j + ½)·2/R, y = 1 − (i + ½)·2/R (row 0 is the top). Each
pixel takes the nearest surface its ray meets: an object or the wall at z = ``WALL_Z`` (normal +z, or
its relief's normal). Albedo is
colour × (lo + (1 − lo)·pattern) of that surface's texture, shading follows `lasagna.world.lighting`,
and image = albedo × shading exactly (the same float operation on the returned tensors).

Work is proportional to covered pixels: each object is intersected only with the rays inside its
projected bounding circle (and, for shadows, the light rays that pass within its bounding sphere),
all as flat tensors. Every pixel is computed independently with elementwise operations, so a scene
renders to the same bits alone or in any batch (on the same device and dtype).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace

import torch

from lasagna.errors import LasagnaError
from lasagna.world.lighting import AMBIENT, VOCABULARY, check_ambient, lambert, light_vectors, resolve_lights
from lasagna.world.params import WALL_Z, SceneParams, sample_scenes
from lasagna.world.relief import relief_normals
from lasagna.world.shapes import SHAPE_NAMES, SHAPES, Vec
from lasagna.world.splits import MAX_OBJECTS
from lasagna.world.textures import evaluate

Tensor = torch.Tensor

# Rays start at z = 2, above every object (centre z ≤ 0.2, bounding radius ≤ 0.6).
_RAY_Z = 2.0
# Shadow rays leave the surface this far along its normal and ignore hits closer than _SHADOW_T_MIN,
# so a surface never shadows itself through rounding (float32 depth error at z ~ 1 is ~1e-7), while
# a real occluder (objects are ≥ 0.06 thick) is never skipped.
_SHADOW_OFFSET = 1e-3
_SHADOW_T_MIN = 1e-4
# Scenes are rendered in chunks of at most this many pixels to bound peak memory (~0.5 GB).
_CHUNK_PIXELS = 1 << 20
MAX_RESOLUTION = 4096


@dataclass(frozen=True)
class Scene:
    """A rendered batch: ground-truth tensors (B, C, H, W) in ``dtype``, plus what made them.

    albedo (3), normals (3, unit, camera frame; the wall is +z), shading (1, in [ambient, 1]),
    image (3) = albedo × shading, mask (1, 1.0 on object pixels, 0.0 on the wall), depth (1, camera z
    of the visible surface; the wall is ``WALL_Z``), object_index (1, int64 slot of the visible object, −1 for
    the wall); light (B, 3) unit vectors, label (the light's names, or the ``az=…,el=…`` condition of
    a light between them), label_index (B,) into VOCABULARY (−1 for a light between the named ones).
    """

    albedo: Tensor
    normals: Tensor
    shading: Tensor
    image: Tensor
    mask: Tensor
    depth: Tensor
    object_index: Tensor
    light: Tensor
    label: list[str]
    label_index: Tensor
    params: SceneParams
    ambient: float
    shadows: bool

    def __len__(self) -> int:
        return int(self.image.shape[0])

    def select(self, idx: int | slice | Sequence[int]) -> Scene:
        """The scenes at ``idx`` (an index, a slice or an index list) as a new batch."""
        if isinstance(idx, int):
            idx = [idx]
        rows = list(range(len(self)))[idx] if isinstance(idx, slice) else [int(i) for i in idx]
        sel = torch.tensor(rows, dtype=torch.int64)
        dev = sel.to(self.image.device)
        pick = {
            name: getattr(self, name)[dev]
            for name in (
                "albedo",
                "normals",
                "shading",
                "image",
                "mask",
                "depth",
                "object_index",
                "light",
                "label_index",
            )
        }
        return replace(self, **pick, label=[self.label[i] for i in rows], params=self.params.select(sel))


def pixel_grid(h: int, w: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    xs = -1.0 + (torch.arange(w, dtype=torch.float64) + 0.5) * (2.0 / w)
    ys = 1.0 - (torch.arange(h, dtype=torch.float64) + 0.5) * (2.0 / h)
    return xs.to(dtype=dtype, device=device), ys.to(dtype=dtype, device=device)


def _cast(obj: dict[str, Tensor], slot: Tensor, o: Vec, d: Vec, t_min: float) -> tuple[Tensor, Vec, Vec]:
    """Intersect ray m (camera-frame origin o[m], direction d[m]) with object slot[m] (flat b·K index).

    Returns t (M,), the camera-frame unit normal and the object-local hit point.
    """
    c = obj["center"][slot]  # (M, 3)
    r = obj["rotation"][slot]  # (M, 3, 3)
    s = obj["size"][slot]
    fam = obj["shape"][slot]
    w = (o[0] - c[:, 0], o[1] - c[:, 1], o[2] - c[:, 2])
    # Local = Rᵀ·camera, written per component (see the module docstring on batch independence).
    ol = tuple(r[:, 0, j] * w[0] + r[:, 1, j] * w[1] + r[:, 2, j] * w[2] for j in range(3))
    dl = tuple(r[:, 0, j] * d[0] + r[:, 1, j] * d[1] + r[:, 2, j] * d[2] for j in range(3))
    m = slot.shape[0]
    t = torch.full((m,), float("inf"), dtype=c.dtype, device=c.device)
    nl = [torch.zeros_like(t), torch.zeros_like(t), torch.ones_like(t)]
    for f, name in enumerate(SHAPE_NAMES):
        sel = (fam == f).nonzero().squeeze(1)
        if sel.numel() == 0:
            continue
        tf, nf = SHAPES[name].intersect(
            tuple(v[sel] for v in ol), tuple(v[sel] for v in dl), tuple(s[sel, j] for j in range(3)), t_min
        )
        t[sel] = tf
        for j in range(3):
            nl[j][sel] = nf[j]
    n = tuple(r[:, j, 0] * nl[0] + r[:, j, 1] * nl[1] + r[:, j, 2] * nl[2] for j in range(3))
    tt = torch.where(torch.isfinite(t), t, torch.zeros_like(t))
    p_local = tuple(ol[j] + tt * dl[j] for j in range(3))
    return t, n, p_local


def _render_chunk(
    p: SceneParams,
    h: int,
    w: int,
    ambient: float,
    shadows: bool,
    dtype: torch.dtype,
    device: torch.device,
    light: Tensor | None = None,
) -> dict[str, Tensor]:
    b, k = len(p), MAX_OBJECTS
    to = dict(dtype=dtype, device=device)
    obj = {
        "center": p.center.reshape(b * k, 3).to(**to),
        "rotation": p.rotation.reshape(b * k, 3, 3).to(**to),
        "size": p.size.reshape(b * k, 3).to(**to),
        "shape": p.shape.reshape(b * k).to(device),
    }
    xs, ys = pixel_grid(h, w, dtype, device)
    radius = p.radius.to(**to)
    present = p.present.to(device)
    cx, cy = obj["center"][:, 0].reshape(b, k), obj["center"][:, 1].reshape(b, k)

    # 1. Primary rays, culled to each object's projected bounding circle.
    inside = (
        (xs.view(1, 1, 1, w) - cx[..., None, None]) ** 2 + (ys.view(1, 1, h, 1) - cy[..., None, None]) ** 2
        <= (radius * (1 + 1e-6))[..., None, None] ** 2
    ) & present[..., None, None]
    bi, ki, ii, jj = inside.nonzero(as_tuple=True)
    slot = bi * k + ki
    ox, oy = xs[jj], ys[ii]
    m = slot.shape[0]
    t, n, pl = _cast(
        obj,
        slot,
        (ox, oy, torch.full((m,), _RAY_Z, **to)),
        (torch.zeros((m,), **to), torch.zeros((m,), **to), torch.full((m,), -1.0, **to)),
        0.0,
    )

    # 2. Depth test: the nearest object per pixel; the wall where no object is hit.
    tbuf = torch.full((b, k, h, w), float("inf"), **to)
    tbuf[bi, ki, ii, jj] = t
    tmin, kmin = tbuf.min(dim=1)  # (B, H, W)
    # An object sunk into the wall (`SceneParams.resting`) is hidden where its surface lies behind the wall's plane;
    # objects as sampled never reach it, so this changes no sampled scene.
    tmin = torch.where(_RAY_Z - tmin > WALL_Z, tmin, torch.full_like(tmin, float("inf")))
    hit = torch.isfinite(tmin)
    vis_slot = torch.where(hit, kmin, torch.full_like(kmin, -1))
    won = torch.isfinite(t) & (vis_slot[bi, ii, jj] == ki)
    vb, vi, vj = bi[won], ii[won], jj[won]

    normals = _wall_normals(p, xs, ys)
    local = [
        xs.view(1, 1, w).expand(b, h, w).clone(),
        ys.view(1, h, 1).expand(b, h, w).clone(),
        torch.zeros((b, h, w), **to),
    ]
    for j in range(3):
        normals[vb, j, vi, vj] = n[j][won]
        local[j][vb, vi, vj] = pl[j][won]
    depth = torch.where(hit, _RAY_Z - tmin, torch.full_like(tmin, WALL_Z))

    # 3. Albedo: each pixel's surface (object slot, or slot K = the wall) picks colour and texture.
    surf = torch.where(hit, vis_slot, torch.full_like(vis_slot, k)) + torch.arange(b, device=device).view(b, 1, 1) * (
        k + 1
    )
    surf = surf.reshape(-1)
    tex = torch.cat([p.texture, p.wall_texture[:, None]], 1).reshape(-1).to(device)
    prm = torch.cat([p.texture_params, p.wall_texture_params[:, None]], 1).reshape(b * (k + 1), -1).to(**to)
    seed = torch.cat([p.texture_seed, p.wall_texture_seed[:, None]], 1).reshape(-1).to(device)
    color = torch.cat([p.color, p.wall_color[:, None]], 1).reshape(b * (k + 1), 3).to(**to)
    pattern = evaluate(surf, tex, tuple(v.reshape(-1) for v in local), prm, seed)
    lo = prm[:, 8][surf]
    albedo = color[surf] * (lo + (1.0 - lo) * pattern)[:, None]  # (B·H·W, 3)
    delta = torch.cat([p.color_delta, p.wall_color_delta[:, None]], 1).reshape(b * (k + 1), 3)
    if delta.any():  # two-colour paint: c₁·(lo + (1 − lo)·pattern) + Δ·(1 − pattern) = lerp(c₂, c₁, pattern)
        albedo = albedo + delta.to(**to)[surf] * (1.0 - pattern)[:, None]
    albedo = albedo.reshape(b, h, w, 3).permute(0, 3, 1, 2).contiguous()

    # 4. Shading, then cast shadows: a lit point is shadowed when its ray toward l meets any object.
    if light is None:
        light = light_vectors([VOCABULARY[i] for i in p.label.tolist()], dtype=dtype, device=device)
    else:  # float64 (b, 3) → dtype: the same rounding as light_vectors' of the same values
        light = light.to(dtype=dtype, device=device)
    shading = lambert(normals, light, ambient)
    if shadows:
        shading = torch.where(
            _shadowed(obj, present, radius, normals, depth, xs, ys, light), torch.full_like(shading, ambient), shading
        )
    return {
        "albedo": albedo,
        "normals": normals,
        "shading": shading,
        "light": light,
        "depth": depth[:, None],
        "object_index": vis_slot[:, None],
    }


def _wall_normals(p: SceneParams, xs: Tensor, ys: Tensor) -> Tensor:
    """(B, 3, H, W): +z, or the relief's normal (`lasagna.world.relief`) on walls that carry relief."""
    b, h, w = len(p), ys.shape[0], xs.shape[0]
    normals = torch.zeros((b, 3, h, w), dtype=xs.dtype, device=xs.device)
    normals[:, 2] = 1.0
    rough = (p.relief >= 0).nonzero().squeeze(1)
    if rough.numel():
        n = rough.numel()
        x = xs.view(1, 1, w).expand(n, h, w).reshape(-1)
        y = ys.view(1, h, 1).expand(n, h, w).reshape(-1)
        kind = p.relief[rough].to(xs.device).repeat_interleave(h * w)
        prm = p.relief_params[rough].to(dtype=xs.dtype, device=xs.device).repeat_interleave(h * w, dim=0)
        nx, ny, nz = relief_normals(kind, prm, x, y)
        normals[rough.to(xs.device)] = torch.stack([nx, ny, nz]).reshape(3, n, h, w).transpose(0, 1)
    return normals


def _shadowed(
    obj: dict[str, Tensor],
    present: Tensor,
    radius: Tensor,
    normals: Tensor,
    depth: Tensor,
    xs: Tensor,
    ys: Tensor,
    light: Tensor,
) -> Tensor:
    """(B, 1, H, W) bool: the ray from the visible point toward the light meets an object."""
    b, k = present.shape
    _, _, h, w = normals.shape
    lx, ly, lz = (light[:, i].view(b, 1, 1) for i in range(3))
    nx, ny, nz = normals[:, 0], normals[:, 1], normals[:, 2]
    lit = nx * lx + ny * ly + nz * lz > 0  # unlit points are at ambient already
    px = xs.view(1, 1, w) + _SHADOW_OFFSET * nx
    py = ys.view(1, h, 1) + _SHADOW_OFFSET * ny
    pz = depth + _SHADOW_OFFSET * nz
    c = obj["center"].view(b, k, 3)
    wx, wy, wz = (c[:, :, i, None, None] - q[:, None] for i, q in enumerate((px, py, pz)))
    along = wx * lx[:, None] + wy * ly[:, None] + wz * lz[:, None]
    dist2 = wx * wx + wy * wy + wz * wz - along * along
    r = radius[..., None, None]
    cand = present[..., None, None] & lit[:, None] & (along > -r) & (dist2 <= (r * (1 + 1e-6)) ** 2)
    bi, ki, ii, jj = cand.nonzero(as_tuple=True)
    shadow = torch.zeros((b, 1, h, w), dtype=torch.bool, device=normals.device)
    if bi.numel() == 0:
        return shadow
    t, _, _ = _cast(
        obj,
        bi * k + ki,
        (px.expand(b, h, w)[bi, ii, jj], py.expand(b, h, w)[bi, ii, jj], pz[bi, ii, jj]),
        (light[bi, 0], light[bi, 1], light[bi, 2]),
        _SHADOW_T_MIN,
    )
    blocked = torch.isfinite(t)
    shadow[bi[blocked], 0, ii[blocked], jj[blocked]] = True
    return shadow


def check_resolution(resolution: int | tuple[int, int]) -> tuple[int, int]:
    """(H, W) from an int R (square) or an (H, W) pair, each in [1, MAX_RESOLUTION]."""
    if isinstance(resolution, int):
        hw: tuple = (resolution, resolution)
    elif isinstance(resolution, (tuple, list, torch.Size)):
        hw = tuple(resolution)
    else:
        hw = ()
    if len(hw) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= MAX_RESOLUTION for v in hw):
        raise LasagnaError(
            f"expected an integer or (height, width) in [1, {MAX_RESOLUTION}], got {resolution!r}", where="resolution"
        )
    return hw[0], hw[1]


def render(
    params: SceneParams,
    resolution: int | tuple[int, int] = 32,
    *,
    labels: str | Sequence[str] | None = None,
    light: str | Sequence[str] | Tensor | None = None,
    ambient: float = AMBIENT,
    shadows: bool = False,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Scene:
    """Render ``params`` (optionally under other light ``labels``) at ``resolution``.

    ``light`` lights the scenes from any direction instead (not with ``labels``): one condition or one
    per scene (a named label or ``az=…,el=…``, `lasagna.world.lighting`), or unit vectors (3,) or
    (B, 3). The scenes' ``label`` is then each light's canonical condition and ``label_index`` its
    index in VOCABULARY, −1 for a direction between the named ones; ``params`` (and its ``label``)
    still describe the scenes as sampled. A named label as ``light`` renders the same bits as ``labels``.
    """
    h, w = check_resolution(resolution)
    check_ambient(ambient)
    if dtype not in (torch.float32, torch.float64):
        raise LasagnaError(f"expected torch.float32 or torch.float64, got {dtype}", where="dtype")
    if light is not None and labels is not None:
        raise LasagnaError("expected labels or light, got both", where="light")
    params = params.with_labels(labels)
    vectors, conditions = (None, None) if light is None else resolve_lights(light, len(params))
    device = torch.device(device) if device is not None else torch.device("cpu")
    step = max(1, _CHUNK_PIXELS // (h * w))
    parts = [
        _render_chunk(
            params.select(slice(i, i + step)),
            h,
            w,
            ambient,
            bool(shadows),
            dtype,
            device,
            None if vectors is None else vectors[i : i + step],
        )
        for i in range(0, len(params), step)
    ]
    out = {key: torch.cat([q[key] for q in parts]) for key in parts[0]}
    albedo, shading = out["albedo"], out["shading"]
    return Scene(
        albedo=albedo,
        normals=out["normals"],
        shading=shading,
        image=albedo * shading,
        mask=(out["object_index"] >= 0).to(dtype),
        depth=out["depth"],
        object_index=out["object_index"],
        light=out["light"],
        label=[VOCABULARY[i] for i in params.label.tolist()] if conditions is None else conditions,
        label_index=params.label.to(device) if conditions is None else _label_index(conditions, device),
        params=params,
        ambient=float(ambient),
        shadows=bool(shadows),
    )


def _label_index(conditions: list[str], device: torch.device | str) -> Tensor:
    """(B,) int64: each condition's index in VOCABULARY, −1 for a direction between the named ones."""
    rows = [VOCABULARY.index(c) if c in VOCABULARY else -1 for c in conditions]
    return torch.tensor(rows, dtype=torch.int64, device=device)


def with_light(scene: Scene, light: str | Sequence[str] | Tensor) -> Scene:
    """The same scenes lit from any direction: conditions (named or ``az=…,el=…``) or unit vectors.

    As `relight`: without shadows only the shading and the image are recomputed (the shading is a
    pointwise function of the normals); with shadows the scenes are rendered again. ``label`` and
    ``label_index`` follow `render`'s ``light``; ``params`` is unchanged.
    """
    if scene.shadows:
        return render(
            scene.params,
            tuple(scene.image.shape[-2:]),
            light=light,
            ambient=scene.ambient,
            shadows=True,
            dtype=scene.image.dtype,
            device=scene.image.device,
        )
    vectors, conditions = resolve_lights(light, len(scene))
    vectors = vectors.to(dtype=scene.image.dtype, device=scene.image.device)
    shading = lambert(scene.normals, vectors, scene.ambient)
    return replace(
        scene,
        shading=shading,
        image=scene.albedo * shading,
        light=vectors,
        label=conditions,
        label_index=_label_index(conditions, scene.image.device),
    )


def relight(scene: Scene, labels: str | Sequence[str]) -> Scene:
    """The same scenes under other light labels.

    Without shadows the shading is a pointwise function of the normals, so only it and the image are
    recomputed; with shadows the scenes are rendered again (shadows depend on the geometry).
    """
    if scene.shadows:
        return render(
            scene.params,
            tuple(scene.image.shape[-2:]),
            labels=labels,
            ambient=scene.ambient,
            shadows=True,
            dtype=scene.image.dtype,
            device=scene.image.device,
        )
    params = scene.params.with_labels(labels)
    light = light_vectors(
        [VOCABULARY[i] for i in params.label.tolist()], dtype=scene.image.dtype, device=scene.image.device
    )
    shading = lambert(scene.normals, light, scene.ambient)
    return replace(
        scene,
        shading=shading,
        image=scene.albedo * shading,
        light=light,
        label=[VOCABULARY[i] for i in params.label.tolist()],
        label_index=params.label.to(scene.image.device),
        params=params,
    )


def generate(
    split: str,
    count: int,
    seed: int = 0,
    resolution: int | tuple[int, int] = 32,
    *,
    start: int = 0,
    labels: str | Sequence[str] | None = None,
    ambient: float = AMBIENT,
    shadows: bool = False,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
) -> Scene:
    """Scenes ``start … start + count − 1`` of ``split`` under ``seed``, rendered at ``resolution``.

    Deterministic: the same arguments give bit-identical tensors, and scene i is the same whether
    generated alone or in a batch. ``labels`` overrides the sampled light labels.
    """
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise LasagnaError(f"expected a positive integer, got {count!r}", where="count")
    params = sample_scenes(split, seed, range(start, start + count))
    return render(params, resolution, labels=labels, ambient=ambient, shadows=shadows, dtype=dtype, device=device)


def batches(
    split: str,
    batch_size: int,
    seed: int = 0,
    resolution: int | tuple[int, int] = 32,
    *,
    start: int = 0,
    **kwargs,
) -> Iterator[Scene]:
    """An endless stream of fresh batches for on-the-fly training: scenes start, start + 1, …"""
    i = start
    while True:
        yield generate(split, batch_size, seed, resolution, start=i, **kwargs)
        i += batch_size
