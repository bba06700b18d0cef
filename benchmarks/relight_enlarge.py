"""How the relight default's ratio is enlarged from its working size (issue #24, round 21). Plain script; one JSON
row per enlargement and size, then one JSON line.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/relight_enlarge.py [--seed 1] [--splits select] [--sizes 256]

The default relight (`lasagna.edit(image, "relight", label)`, the free ratio from the surface start) is made once
per scene at its working size (64); the fast guided filter that enlarges it (`enlarge: guided`,
`lasagna.compose.resample.guided_upsample`, radius ``GUIDED_RADIUS`` and ε ``GUIDED_EPS``) is intercepted, and the
same working-size ratio is enlarged by each candidate — bilinear, the guided filter at each radius and ε of the grid,
and joint bilateral upsampling at each σ of the guide (``BILATERAL_SIGMAS``) — then measured as
`benchmarks/relight_candidates.py` measures (dB over the unchanged input, all / objects; the error split) on the same
scenes, with the texture leak on the split's bare painted walls (the ratio's PSNR against its own mean: their true
ratio is one constant). The shipped row is the enlargement the preset makes; every row enlarges one and the same
working-size ratio, so the differences are the enlargement's alone.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import machine_info, print_json_line, psnr  # noqa: E402
from relight_candidates import measure  # noqa: E402
from surface import scenes  # noqa: E402

import lasagna.compose.resample as resample  # noqa: E402
from lasagna import edit  # noqa: E402
from lasagna.catalogue import load_preset  # noqa: E402
from lasagna.world.tasks import relight_sources, relighting  # noqa: E402

PRESET = "relight"
RADII = (1, 2)
EPSILONS = (1e-5, 1e-4, 3e-4, 1e-3, 1e-2)
BILATERAL_SIGMAS = (0.05, 0.1, 0.2)


def working_ratios(base: torch.Tensor, labels: list[str]) -> tuple[list[tuple[torch.Tensor, torch.Tensor]], float]:
    """Each image's default relight at its working size with the guide its enlargement was given (y (1, 1, h, w),
    guide (1, 1, H, W)), and seconds per image. The enlargement is intercepted, so the edit runs as shipped."""
    caught: list[tuple[torch.Tensor, torch.Tensor]] = []
    shipped = resample.guided_upsample

    def record(y, guide, *a, **k):
        caught.append((y.detach().clone(), guide.detach().clone()))
        return shipped(y, guide, *a, **k)

    resample.guided_upsample = record
    t0 = time.perf_counter()
    try:
        for i in range(base.shape[0]):
            edit(base[i], PRESET, labels[i])
    finally:
        resample.guided_upsample = shipped
    if len(caught) != base.shape[0]:
        raise SystemExit(f"expected one guided enlargement per image, caught {len(caught)} (is the preset guided?)")
    return caught, (time.perf_counter() - t0) / base.shape[0]


def enlargements() -> dict[str, object]:
    """name → (y, guide) → the enlarged ratio (1, 1, H, W), unclamped."""
    out: dict[str, object] = {
        "bilinear": lambda y, g: resample.upsample(y, tuple(g.shape[-2:])),
    }
    for r in RADII:
        for e in EPSILONS:
            out[f"guided r{r} eps{e:g}"] = lambda y, g, r=r, e=e: resample.guided_upsample(y, g, radius=r, eps=e)
    for s in BILATERAL_SIGMAS:  # joint bilateral upsampling: a convex mean of the ratio's own cells (round 21)
        out[f"bilateral sigma_g {s:g}"] = lambda y, g, s=s: resample.joint_bilateral_upsample(y, g, sigma_guide=s)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--splits", nargs="+", default=["select"])
    p.add_argument("--sizes", nargs="+", type=int, default=[256])
    p.add_argument("--count", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json-out", type=Path, default=None)
    args = p.parse_args(argv)
    lo, hi = load_preset(PRESET).range
    shipped_name = f"guided r{resample.GUIDED_RADIUS} eps{resample.GUIDED_EPS:g}"
    rows: list[dict] = []
    for split in args.splits:
        for size in args.sizes:
            scene, labels = scenes(split, args.count, args.seed, size)
            rel = relighting(scene, relight_sources(scene.params))
            caught, sec = working_ratios(rel.base.float(), labels)
            walls, wall_labels = scenes(split, args.count, args.seed, size, walls=True)
            wall_caught, _ = working_ratios(relighting(walls, relight_sources(walls.params)).base.float(), wall_labels)
            for name, enlarge in enlargements().items():
                ratio = torch.cat([enlarge(y, g).clamp(lo, hi) for y, g in caught])[:, :1]
                row = measure(name, scene, rel, ratio, sec, size)
                y = torch.cat([enlarge(y, g).clamp(lo, hi) for y, g in wall_caught]).double()
                row.update(
                    leak_db=round(psnr(y, y.mean(dim=(1, 2, 3), keepdim=True).expand_as(y)), 2),
                    shipped=name == shipped_name,
                    split=split,
                    size=size,
                    seed=args.seed,
                )
                print(json.dumps(row), flush=True)
                rows.append(row)
    if args.json_out is not None:
        args.json_out.write_text(json.dumps(rows, indent=1) + "\n", encoding="utf-8")
    best = max((r for r in rows if not r["shipped"]), key=lambda r: r["db_all"])
    print_json_line(
        {
            "benchmark": "relight_enlarge",
            "shipped": shipped_name,
            "best": best["method"],
            "best_db_all": best["db_all"],
            "rows": len(rows),
            **machine_info(),
        }
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
