"""Shared helpers for the benchmark scripts: timing (median of repeats), a description of the machine, the
metrics several benchmarks report (PSNR, luma, the implied shading, a light edit's darkening and colour), contact
sheets, and the relight task's scenes and row. Benchmarks import these from here, never from each other.

Benchmarks are plain scripts (``python benchmarks/NAME.py``), kept out of the test suite; each ends by
printing one JSON line. Times are medians of ``repeats`` runs after one warm-up run, in seconds.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image

from lasagna.compose.color import REC709
from lasagna.document.condition import format_direction, named_direction
from lasagna.priors.evaluate import psnr_db
from lasagna.world import GLOW_VOCABULARY, VOCABULARY, render, sample_scenes
from lasagna.world.tasks import relight_sources, relighting


def median_time(fn: Callable[[], Any], repeats: int, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` in seconds over ``repeats`` calls, after ``warmup`` untimed calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict[str, Any]:
    """CPU model, logical cores, torch version and threads, date (UTC), Python and OS."""
    import torch

    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "python": platform.python_version(),
        "os": f"{platform.system()} {platform.release()}",
        "date": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
    }


def print_json_line(record: dict[str, Any]) -> None:
    """The one machine-readable line a benchmark ends with."""
    print(json.dumps(record, sort_keys=True, default=str))


# ---- metrics: PSNR, luma and the implied shading, what a light edit took away or added ----


def psnr(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """PSNR (``psnr_db``) of the mean squared error over all images, or over ``mask`` pixels."""
    d = (a.double() - b.double()) ** 2
    mse = d.mean() if mask is None else (d * mask).sum() / (mask.sum() * a.shape[1]).clamp_min(1)
    return float(psnr_db(mse, floor=1e-12))


def luma(x: torch.Tensor) -> torch.Tensor:
    r, g, b = REC709
    return r * x[:, 0:1] + g * x[:, 1:2] + b * x[:, 2:3]


def colourfulness(x: torch.Tensor) -> float:
    """Hasler & Süsstrunk's colourfulness M (2003) on 0–255 values, mean over images: 0 for a gray image,
    ~15 "slightly", ~33 "moderately", ~45 "averagely colourful". PSNR cannot tell a colourisation from
    leaving the image gray; this can."""
    x = 255.0 * x.double()
    rg, yb = x[:, 0] - x[:, 1], 0.5 * (x[:, 0] + x[:, 1]) - x[:, 2]
    std = (rg.flatten(1).var(1, unbiased=False) + yb.flatten(1).var(1, unbiased=False)).sqrt()
    mean = (rg.flatten(1).mean(1) ** 2 + yb.flatten(1).mean(1) ** 2).sqrt()
    return float((std + 0.3 * mean).mean())


def implied_shading(out: torch.Tensor, base: torch.Tensor) -> torch.Tensor:
    """The luminosity multiplier that best explains ``out`` as ``base`` × y: luma ratio, in [0, 2]."""
    return (luma(out) / luma(base).clamp_min(1e-3)).clamp(0.0, 2.0)


def darkening(out: torch.Tensor, base: torch.Tensor) -> float:
    """Mean over pixels and channels of max(0, base − out): what an edit took away from the input.

    Adding light never darkens, so for the light task this is pure content drift.
    """
    return float((base.double() - out.double()).clamp_min(0.0).mean())


def glow_colour_error(glow: torch.Tensor, true: torch.Tensor) -> float:
    """Mean over images of the angle (degrees) between the summed RGB of a glow and of the true glow.

    Brightness-free: it asks only whether the light added has the label's colour. A glow with no
    light at all has no colour; it counts as 90° (orthogonal).
    """
    a, b = glow.double().sum(dim=(2, 3)), true.double().sum(dim=(2, 3))
    cos = (a * b).sum(1) / (a.norm(dim=1) * b.norm(dim=1)).clamp_min(1e-12)
    return float(torch.rad2deg(torch.arccos(cos.clamp(-1.0, 1.0))).mean())


def add_labels(add) -> list[str]:
    return [GLOW_VOCABULARY[int(k)] for k in add.scene.params.glow_label]


# ---- contact sheets ------------------------------------------------------------------------


def _tile(x: torch.Tensor) -> np.ndarray:
    """(C, H, W) in [0, 1] (a shading in [0, 2] is shown halved) → (H, W, 3) uint8."""
    x = x.detach().double()
    if x.shape[0] == 1:
        x = (x / 2.0).expand(3, -1, -1)
    return (x.clamp(0, 1).permute(1, 2, 0).numpy() * 255 + 0.5).astype(np.uint8)


def save_sheet(columns: list[list[torch.Tensor]], path: Path, pad: int = 2) -> None:
    """A grid: one row per list in ``columns``' transpose (each column a list of (C, H, W) images)."""
    rows = []
    for i in range(len(columns[0])):
        tiles = [_tile(col[i]) for col in columns]
        h = max(t.shape[0] for t in tiles)
        line = []
        for t in tiles:
            line += [t, np.full((h, pad, 3), 255, np.uint8)]
        rows += [
            np.concatenate(line[:-1], 1),
            np.full((pad, sum(t.shape[1] for t in tiles) + pad * (len(tiles) - 1), 3), 255, np.uint8),
        ]
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(rows[:-1], 0)).save(path)


# ---- the relight task's scenes and metrics row (relight.py, relight_sweep.py) ---------------


RANGE_HI = 4.0  # the preset's range [0, 4]: ratios are compared in units of it


BETWEEN = 22.5
"""Degrees of azimuth from each named light to the direction between it and the next (same elevation)."""


def scenes(split: str, count: int, seed: int, size: int, walls: bool = False, between: bool = False):
    """The relight task of ``count`` scenes: B cycles through the named lights or, with ``between``, through
    the directions halfway between them (``az`` + 22.5°, the same elevation)."""
    labels = [VOCABULARY[i % len(VOCABULARY)] for i in range(count)]
    params = sample_scenes(split, seed, range(count))
    if walls:
        params = params.walls_only()
    scene = render(params.with_labels(labels), size)
    if between:
        labels = [format_direction(named_direction(n)[0] + BETWEEN, named_direction(n)[1]) for n in labels]
        return relighting(scene, relight_sources(scene.params), labels), labels
    return relighting(scene, relight_sources(scene.params)), labels


def row(rel, method: str, ratio: torch.Tensor, seconds: float | None = None) -> dict:
    comp = (rel.base * ratio).clamp(0, 1)
    target = rel.target.clamp(0, 1)
    mask = rel.scene.mask
    r = {
        "method": method,
        "composite_psnr": round(psnr(comp, target), 2),
        "object_psnr": round(psnr(comp, target, mask), 2),
        "ratio_psnr": round(psnr(ratio.expand_as(rel.layer) / RANGE_HI, rel.layer / RANGE_HI), 2),
    }
    if seconds is not None:
        r["seconds_per_image"] = round(seconds / rel.base.shape[0], 3)
    return r


# ---- photographs: the relight swing toward opposite lights (issue #24) ----

# The two axes of opposite lights a photograph is relit along.
PHOTO_AXES = {"left-right": ("left", "right"), "top-bottom": ("top", "bottom")}


def thirds(ratio: torch.Tensor, light: str) -> float:
    """Mean of ``ratio`` (1, H, W) over the third of the image nearest ``light`` minus over the farthest third."""
    h, w = ratio.shape[-2:]
    cols, rows = w // 3, h // 3
    near, far = {
        "left": (ratio[..., :cols], ratio[..., w - cols :]),
        "right": (ratio[..., w - cols :], ratio[..., :cols]),
        "top": (ratio[..., :rows, :], ratio[..., h - rows :, :]),
        "bottom": (ratio[..., h - rows :, :], ratio[..., :rows, :]),
    }[light]
    return float(near.double().mean() - far.double().mean())


def read_photo(path: Path, side: int = 512) -> torch.Tensor:
    """A photograph (1, 3, H, W) in [0, 1], its long side resized to ``side`` (Lanczos)."""
    with Image.open(path) as im:
        im = im.convert("RGB")
        scale = side / max(im.size)
        im = im.resize((round(im.width * scale), round(im.height * scale)), Image.LANCZOS)
        return torch.from_numpy(np.asarray(im, dtype="float32") / 255.0).permute(2, 0, 1)[None]


def swing(image: torch.Tensor, composite: torch.Tensor, light: str) -> float:
    """How much an edit toward ``light`` brightens the side the light comes from: ``thirds`` of composite/input
    (the mean over the colour channels; input floored at 1e-3). Summed over the two opposite edits of an axis it
    is issue #24's photograph swing (≥ 0.10 per photograph and axis, never negative)."""
    return thirds((composite / image.clamp_min(1e-3)).mean(-3, keepdim=True).reshape(1, *image.shape[-2:]), light)
