"""Where a surface layer's gap to a told source light lies (issue #24, round 18). Plain script; one JSON row per
(estimator, light), then one JSON line.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/source_light.py               # the relight preset's estimator
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/source_light.py --estimator runs/lit-m/surface --count 32

Each scene of ``--split`` (world seed ``--seed``) is lit by its relight task's source light (``relight_sources``) and
relit toward its named light; the estimator reads it as the relight preset's surface layer does (its dome prior,
symmetry ensemble and elevation calibration, at ``surface.working_size``) and fits the source light. Two things are
measured:

* **the fitted light's error**: the angle to the true light (median, RMS), the azimuth's (median of its absolute
  value) and the count of azimuths off by more than 90° (a convex surface read as concave: a "flip"), the elevation's
  RMS and bias (degrees from the view axis, fitted minus true);
* **what each part of the light is worth**: the estimate re-read told each of ``LIGHTS`` — the fitted light, the
  true one, the true azimuth with the fitted elevation, the fitted azimuth with the true elevation, the fitted light
  with its flips set to the true azimuth — rendered S(target)/S(light) (no refinement) and composited; dB over the
  unchanged input, all pixels and objects. An estimator that reads no light gives one surface for every light, so
  its rows price the light alone.

A flat wall's ratio S(target)/S(source) is a constant only the source elevation sets, and walls are most pixels, so
the elevation row moves the all-pixel figure; the objects' figure moves with the azimuth.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import machine_info, psnr  # noqa: E402
from surface import lights_of, scenes  # noqa: E402

from lasagna.catalogue import load_preset, resolve  # noqa: E402
from lasagna.compose.surface import lambert  # noqa: E402
from lasagna.generators.surface import DomePrior, SurfaceEstimator  # noqa: E402
from lasagna.world.tasks import relight_sources, relighting  # noqa: E402

PRESET = "relight"
LIGHTS = ("fitted", "true", "true azimuth, fitted elevation", "fitted azimuth, true elevation", "flips set right")
FLIP_DEG = 90.0
"""An azimuth off by more than this is a flip: the convex–concave ambiguity's other reading."""
RATIO_RANGE = (0.0, 4.0)
"""The relight preset's layer range, which the ratio is clamped to as the edit clamps it."""


def azimuth_elevation(light: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(azimuth, elevation from the view axis) in radians of unit lights (B, 3), float64."""
    light = light.double()
    return torch.atan2(light[:, 1], light[:, 0]), torch.acos(light[:, 2].clamp(-1.0, 1.0))


def from_angles(azimuth: torch.Tensor, elevation: torch.Tensor) -> torch.Tensor:
    """Unit lights (B, 3) of ``azimuth`` and ``elevation`` (radians): (sin e cos a, sin e sin a, cos e)."""
    s = torch.sin(elevation)
    return torch.stack([s * torch.cos(azimuth), s * torch.sin(azimuth), torch.cos(elevation)], 1)


def wrapped_deg(turn: torch.Tensor) -> torch.Tensor:
    """An angle difference (radians) in degrees, wrapped to (−180, 180]."""
    return torch.rad2deg(torch.atan2(torch.sin(turn), torch.cos(turn)))


def light_errors(fitted: torch.Tensor, true: torch.Tensor) -> dict:
    """The fitted lights' errors against the true ones (module docstring), degrees."""
    (fa, fe), (ta, te) = azimuth_elevation(fitted), azimuth_elevation(true)
    angle = torch.rad2deg(torch.acos((fitted.double() * true.double()).sum(1).clamp(-1.0, 1.0)))
    az, el = wrapped_deg(fa - ta), torch.rad2deg(fe - te)
    return {
        "median_deg": round(float(angle.median()), 2),
        "rms_deg": round(float(angle.pow(2).mean().sqrt()), 2),
        "azimuth_median_deg": round(float(az.abs().median()), 2),
        "flips": int((az.abs() > FLIP_DEG).sum()),
        "elevation_rms_deg": round(float(el.pow(2).mean().sqrt()), 2),
        "elevation_bias_deg": round(float(el.mean()), 2),
    }


def mixed_lights(fitted: torch.Tensor, true: torch.Tensor) -> dict[str, torch.Tensor]:
    """Every light of ``LIGHTS`` (B, 3 each, float64)."""
    (fa, fe), (ta, te) = azimuth_elevation(fitted), azimuth_elevation(true)
    flip = wrapped_deg(fa - ta).abs() > FLIP_DEG
    return {
        "fitted": from_angles(fa, fe),
        "true": true.double(),
        "true azimuth, fitted elevation": from_angles(ta, fe),
        "fitted azimuth, true elevation": from_angles(fa, te),
        "flips set right": from_angles(torch.where(flip, ta, fa), fe),
    }


def measure(folder: str | None, split: str, count: int, seed: int, size: int) -> list[dict]:
    sd = load_preset(PRESET).surface
    net = SurfaceEstimator.from_pretrained(folder or resolve(PRESET, None, None, need_prior=False).estimator)
    dome = DomePrior(weight=sd.dome_weight, height=sd.dome_height)
    scene, labels = scenes(split, count, seed, size)
    sources = relight_sources(scene.params)
    rel = relighting(scene, sources)
    base, target, mask = rel.base.float().clamp(0, 1), rel.target.float().clamp(0, 1), scene.mask
    true, toward = lights_of(sources).double(), lights_of(labels).float()
    kw = dict(side=sd.working_size, symmetry=sd.symmetry)
    with torch.no_grad():
        _, fitted = net.estimate_at(base, dome, elevation=sd.light_calibration, **kw)
        rows = [{"estimator": folder or sd.estimator, "light": "fitted, as read", **light_errors(fitted, true)}]
        for name, light in mixed_lights(fitted, true).items():
            told = light.float() if net.config.light_input else None  # one surface for every light otherwise
            normals, _ = net.estimate_at(base, dome, light=told, **kw)
            ratio = (lambert(normals, toward) / lambert(normals, light.float())).clamp(*RATIO_RANGE)
            comp = (base * ratio).clamp(0, 1)
            rows.append(
                {
                    "estimator": folder or sd.estimator,
                    "light": name,
                    "db_all": round(psnr(comp, target) - psnr(base, target), 3),
                    "db_objects": round(psnr(comp, target, mask) - psnr(base, target, mask), 3),
                }
            )
    for r in rows:
        r.update(split=split, size=size, count=count)
    return rows


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--estimator", nargs="*", default=[], help="lit estimator folders (none: the preset's)")
    p.add_argument("--split", default="select")
    p.add_argument("--count", type=int, default=32)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--size", type=int, default=64)
    args = p.parse_args(argv)
    rows = []
    for folder in args.estimator or [None]:
        for row in measure(folder, args.split, args.count, args.seed, args.size):
            print(json.dumps(row), flush=True)
            rows.append(row)
    print(json.dumps({"machine": machine_info(), "command": " ".join(sys.argv), "flip_deg": FLIP_DEG, "rows": rows}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
