"""What cast shadows are worth to a relight through a surface (issue #24, round 23). Plain script; one JSON line.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_shadows.py                    # objects resting on the wall
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_shadows.py --sink none        # the world as sampled

The world's objects float in front of the wall (`lasagna.world.params.WALL_Z`), so with ``shadows=True`` their shadows
fall detached on it; a photograph's shade is mostly attached (a cup on its saucer, an eave under its roof). With
``--sink S`` every object's centre is moved to S bounding radii in front of the wall: the objects rest on it (sunk
into it for S < 1) and cast contact shadows, which a height field can hold. Each of ``--count`` scenes of ``--split``
is rendered at ``--size`` with the world's exact cast shadows, lit by its relight task's source light and relit toward
its named light; the relight preset's surface layer is made told the true source light (`lasagna edit --layer
relight --layer-kind surface --from`), and its stored normals n̂ re-rendered with visibility V from a height field h
(``cast_shadows``: a ray marched from each pixel toward the light over h, one pixel per step, bilinear; 0 where
the ray passes below h):

    ratio = (a + (1 − a)·V_t·max(0, n̂·l_t)) / (a + (1 − a)·V_s·max(0, n̂·l_s)),  clamped to [0, 4]

for h the true heights (depth − WALL_Z: the headroom of casting), the layer's own normals integrated
(``integrate_normals``, Frankot–Chellappa 1988 on a mirrored extension) times each of ``--gains``, and the height
field of each estimator in ``--heights`` (told the true source light; round 24's height-trained estimators), both
lights' shadows and the target's alone cast onto the walls (V_t = 1 − (1 − V)·(1 − p), p its silhouette probability;
the source's shadows left in the image, V_s = 1). Rows:
the layer's own ``shadows`` option (0.5 and 1: `lasagna.compose.shadow`, the target light's shadows over its
integrated heights, the product's render); dB of the composite over the unchanged input (all / objects), with and
without the world's shadows; the ray march's
agreement with the world's own shadows (share of pixels, IoU of the shadowed ones). Nothing here is a default: a probe's
reproducible form (docs/BENCHMARKS.md, round 23, S2 and S3).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import machine_info, psnr  # noqa: E402

from lasagna import edit  # noqa: E402
from lasagna.compose.resample import downsample  # noqa: E402
from lasagna.compose.surface import (  # noqa: E402
    AMBIENT,
    decode_normal_map,
    integrate_normals,
    lambert,
    layer_surface_tensors,
)
from lasagna.generators.surface import SurfaceEstimator  # noqa: E402
from lasagna.world.lighting import VOCABULARY  # noqa: E402
from lasagna.world.params import WALL_Z, sample_scenes  # noqa: E402
from lasagna.world.scene import render  # noqa: E402
from lasagna.world.tasks import relight_sources, relighting  # noqa: E402

RATIO_MAX = 4.0
"""A relight ratio's bound (1/ambient: a point at the ambient floor lit fully)."""
SHADOW_EPS = 1e-3
"""A ray passes below the height field only by more than this (canvas units): a surface never shadows itself by
bilinear rounding."""


def cast_shadows(height: torch.Tensor, light: torch.Tensor, eps: float = SHADOW_EPS) -> torch.Tensor:
    """Visibility (B, 1, H, W) in {0, 1} of each pixel toward ``light`` (B, 3) over ``height`` (B, 1, H, W, canvas
    units: the canvas is 2 wide, y up): the ray from the pixel's surface point toward the light, sampled once per pixel
    of its image-plane path (bilinear), is blocked where the height field rises above it by more than ``eps``. A
    light on the view axis casts nothing; the ray stops at the image's edge or where it clears the highest point.
    The march rounds 23 and 24 measured with, kept so their numbers reproduce; a surface layer's own shadows are
    `lasagna.compose.shadow`'s (the same rays, by a running maximum)."""
    b, _, h, w = height.shape
    step = 2.0 / w
    vis = torch.ones_like(height)
    rows, cols = torch.meshgrid(torch.arange(h, dtype=height.dtype), torch.arange(w, dtype=height.dtype), indexing="ij")
    for i in range(b):
        lx, ly, lz = (float(v) for v in light[i])
        across = math.hypot(lx, ly)
        if across < 1e-9:
            continue
        rise = step * lz / across  # the ray's climb per pixel of image-plane travel
        hi = height[i : i + 1]
        steps = min(int(math.ceil(float(hi.max() - hi.min()) / max(rise, 1e-9))) + 1, 2 * max(h, w))
        for k in range(1, steps + 1):
            col, row = cols + k * lx / across, rows - k * ly / across  # y up: toward the light is up the image
            grid = torch.stack([(col + 0.5) / w * 2 - 1, (row + 0.5) / h * 2 - 1], -1)[None]
            above = F.grid_sample(hi, grid, mode="bilinear", padding_mode="border", align_corners=False)
            inside = ((col >= 0) & (col <= w - 1) & (row >= 0) & (row <= h - 1))[None, None]
            vis[i : i + 1] = torch.where(inside & (above > hi + k * rise + eps), 0.0, vis[i : i + 1])
    return vis


def estimator_heights(path: str, image: torch.Tensor, light: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(the height field (B, 1, H, W, canvas units), the walls' weight (B, 1, H, W): 1 − the silhouette probability)
    the surface estimator at ``path`` reads from ``image`` (B, 3, H, W) told ``light`` (B, 3): its eight-view ensemble
    at its working size, enlarged bilinearly to the image."""
    net = SurfaceEstimator.from_pretrained(path)
    small = downsample(image, (net.config.working_size,) * 2)
    height, objects = net.height_field(small, "dihedral", light), net.silhouette(small, "dihedral")
    size = image.shape[-2:]
    up = [F.interpolate(x, size=size, mode="bilinear", align_corners=False) for x in (height, objects)]
    return up[0], 1.0 - up[1]


def own_shadows(made, strength: float, depth: float = 1.0) -> torch.Tensor:
    """The relight layer of an edit (``lasagna.edit(...)``'s result) rendered with its ``shadows`` option set to
    ``strength`` and its ``shadow_depth`` to ``depth`` (`lasagna.compose.shadow`: the target light's shadows over the
    layer's integrated heights times ``depth``, the source light casting none): (1, H, W)."""
    update = {"shadows": strength, "shadow_depth": depth}
    layer = made.stack.document.layer(made.layer_id).model_copy(update=update)
    return (
        layer_surface_tensors(made.stack.tensors[made.layer_id], layer)[0]
        .color.float()
        .reshape(1, *made.layer.shape[-2:])
    )


def shaded(normals: torch.Tensor, light: torch.Tensor, vis: torch.Tensor, ambient: float = AMBIENT) -> torch.Tensor:
    """Lambert with ambient and visibility: a + (1 − a)·V·max(0, n·l)."""
    return ambient + (1.0 - ambient) * vis * (normals * light[:, :, None, None]).sum(1, keepdim=True).clamp_min(0.0)


def gains(rel, scene, ratio: torch.Tensor) -> tuple[float, float]:
    y = (rel.base.float() * ratio).clamp(0, 1).double()
    t, x = rel.target.clamp(0, 1).double(), rel.base.clamp(0, 1).double()
    m = (scene.mask > 0.5).expand_as(y)
    return round(psnr(y, t) - psnr(x, t), 3), round(psnr(y[m], t[m]) - psnr(x[m], t[m]), 3)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--split", default="select")
    p.add_argument("--count", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--size", type=int, default=64)
    p.add_argument(
        "--sink", default="0.5", help="objects' centres this many radii in front of the wall ('none': as sampled)"
    )
    p.add_argument("--gains", nargs="+", type=float, default=[1.0, 2.0, 3.0])
    p.add_argument(
        "--heights",
        nargs="*",
        default=[],
        metavar="ESTIMATOR",
        help="surface estimators (folders) whose own height fields, told the true source light, cast the shadows",
    )
    args = p.parse_args(argv)
    labels = [VOCABULARY[i % len(VOCABULARY)] for i in range(args.count)]
    params = sample_scenes(args.split, args.seed, range(args.count)).with_labels(labels)
    if args.sink != "none":
        params = params.resting(float(args.sink))
    out: dict = {"benchmark": "surface_shadows", "split": args.split, "size": args.size, "sink": args.sink}
    for shadows in (False, True):
        scene = render(params, args.size, shadows=shadows)
        sources = relight_sources(scene.params)
        rel = relighting(scene, sources)
        ls, lt = rel.source.light.float(), rel.scene.light.float()
        made = [
            edit(rel.base[i].float(), "relight", labels[i], layer_kind="surface", source_light=sources[i])
            for i in range(args.count)
        ]
        n = torch.cat([decode_normal_map(m.stack.tensors[m.layer_id].color[None].float()) for m in made])
        one = torch.ones_like(n[:, :1])
        key = "shadows" if shadows else "no shadows"
        rows = {"told layer": gains(rel, scene, (shaded(n, lt, one) / shaded(n, ls, one)).clamp(0, RATIO_MAX))}
        truth = scene.depth.float() - WALL_Z
        vt, vs = cast_shadows(truth, lt), cast_shadows(truth, ls)
        rows["its normals, shadows cast from the true heights"] = gains(
            rel, scene, (shaded(n, lt, vt) / shaded(n, ls, vs)).clamp(0, RATIO_MAX)
        )
        for strength, depth in ((0.5, 1.0), (1.0, 1.0), (1.0, 2.0), (1.0, 3.0)):  # the product's options, rendered
            name = f"the layer's own shadows {strength:g}, shadow depth {depth:g} (the target's light only)"
            rows[name] = gains(
                rel, scene, torch.stack([own_shadows(m, strength, depth) for m in made]).clamp(0, RATIO_MAX)
            )
        own = integrate_normals(n)
        for g in args.gains:
            vt, vs = cast_shadows(own * g, lt), cast_shadows(own * g, ls)
            rows[f"its normals, shadows cast from their integrated heights x{g:g}"] = gains(
                rel, scene, (shaded(n, lt, vt) / shaded(n, ls, vs)).clamp(0, RATIO_MAX)
            )
        for path in args.heights:
            own, walls = estimator_heights(path, rel.base.float(), ls)
            vt, vs = cast_shadows(own, lt), cast_shadows(own, ls)
            rows[f"its normals, shadows cast from {path}'s heights"] = gains(
                rel, scene, (shaded(n, lt, vt) / shaded(n, ls, vs)).clamp(0, RATIO_MAX)
            )
            rows[f"its normals, the target's shadows cast onto the walls from {path}'s heights"] = gains(
                rel, scene, (shaded(n, lt, 1 - (1 - vt) * walls) / shaded(n, ls, one)).clamp(0, RATIO_MAX)
            )
        if shadows:
            world = rel.source.shading.float() < lambert(scene.normals.float(), ls) - 1e-4
            marched = cast_shadows(truth, ls) < 0.5
            rows["ray march of the true heights against the world's source shadows"] = {
                "agree": round(float((world == marched).float().mean()), 4),
                "iou": round(float((world & marched).sum() / (world | marched).sum().clamp_min(1)), 3),
                "shadowed_share": round(float(world.float().mean()), 3),
            }
        rows["heights' mean peak (true / integrated)"] = (
            round(float(truth.amax(dim=(1, 2, 3)).mean()), 3),
            round(float(own.amax(dim=(1, 2, 3)).mean()), 3),
        )
        out[key] = rows
        print(json.dumps({key: rows}), flush=True)
    out["machine"] = machine_info()
    out["command"] = " ".join(sys.argv)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
