"""Does a lit surface estimator read the relief of walls? (issue #24, round 16). Plain script; one JSON line.

    OMP_NUM_THREADS=2 python benchmarks/relief_walls.py                                   # the relight preset's
    OMP_NUM_THREADS=2 python benchmarks/relief_walls.py --estimator runs/lit-relief/surface --splits val

Each scene of ``--splits`` (world seed ``--seed``, ``--count`` scenes at ``--size``²) is lit by its relight task's
source light and relit toward its named light. The ratio S(l_tgt)/S(l_src) of the estimator's surface (the relight
preset's dome prior and symmetry ensemble, at its working size, enlarged bicubically) is taken under the **true**
source light, so the light's error is out of the measurement (an estimator that reads its source light,
``SurfaceConfig.light_input``, is told that true light too), and its composite's squared error is summed where it
falls: objects, flat walls, relief walls (a wall whose true ratio varies). In the same run, as baselines:

* **walls flat** — the same estimate with its wall pixels (by the true mask) replaced by +z: no relief at all;
* **true at the working size** — the true normals reduced to the working size and enlarged: its headroom.

An estimator whose relief walls are no better than "walls flat" reads no relief. Units: a ``--size``² image's pixels
(summed squared error of the clamped composite, RGB mean per pixel).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import machine_info  # noqa: E402
from surface import lights_of, scenes  # noqa: E402

from lasagna.catalogue import load_preset  # noqa: E402
from lasagna.compose.resample import downsample  # noqa: E402
from lasagna.compose.surface import enlarge_surface, lambert, light_vector, surface_normals  # noqa: E402
from lasagna.document.condition import parse_direction  # noqa: E402
from lasagna.generators.surface import DomePrior, SurfaceEstimator  # noqa: E402
from lasagna.world.tasks import relight_sources, relighting  # noqa: E402

RELIEF_STD = 1e-3
"""A wall is a relief wall when its true ratio's relative standard deviation exceeds this (a flat wall's is 0)."""


def split_errors(scene, rel, normals: torch.Tensor, src: torch.Tensor, tgt: torch.Tensor) -> dict[str, float]:
    """Summed squared error of the composite of S(tgt)/S(src) of ``normals``, by objects / flat / relief walls."""
    return ratio_errors(scene, rel, lambert(normals, tgt) / lambert(normals, src))


def ratio_errors(scene, rel, ratio: torch.Tensor) -> dict[str, float]:
    """Summed squared error of the composite ``rel.base × ratio`` (clamped to [0, 1]) against the relit truth, by
    where it falls: objects, flat walls, relief walls."""
    y = (rel.base * ratio).clamp(0, 1)
    target = rel.target.clamp(0, 1)
    out = {"objects": 0.0, "flat_walls": 0.0, "relief_walls": 0.0}
    for i in range(len(y)):
        wall = scene.mask[i, 0] < 0.5
        se = ((y[i] - target[i]) ** 2).mean(0)
        truth = rel.layer[i, 0][wall]
        kind = "relief_walls" if float(truth.std() / truth.mean()) > RELIEF_STD else "flat_walls"
        out[kind] += float(se[wall].sum())
        out["objects"] += float(se[~wall].sum())
    return {k: round(v, 1) for k, v in out.items()}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--estimator", default=None, help="a lit estimator folder (default: the relight preset's)")
    p.add_argument("--splits", nargs="+", default=["select", "val"])
    p.add_argument("--count", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--size", type=int, default=64)
    args = p.parse_args(argv)
    preset = load_preset("relight")
    sd = preset.surface
    folder = args.estimator or str(ROOT / "layers" / sd.estimator)
    net = SurfaceEstimator.from_pretrained(folder)
    dome = DomePrior(weight=sd.dome_weight, height=sd.dome_height)
    result: dict = {"estimator": folder, "size": args.size, "told_light": net.config.light_input}
    result["machine"] = machine_info()
    for split in args.splits:
        scene, labels = scenes(split, args.count, args.seed, args.size)
        sources = relight_sources(scene.params)
        rel = relighting(scene, sources)
        src = torch.cat([light_vector(*parse_direction(s))[None] for s in sources]).float()
        tgt = lights_of(labels).float()
        full = (args.size, args.size)
        with torch.no_grad():
            small = downsample(rel.base.float(), (sd.working_size,) * 2)
            # An estimator that reads its source light is told the true one, as the ratio below divides by it.
            told = src if net.config.light_input else None
            est, _ = net.estimate(small, dome, symmetry=sd.symmetry, light=told)
        normals = surface_normals(enlarge_surface(est, full))
        wall = (scene.mask < 0.5).expand_as(normals)
        flat = torch.zeros_like(normals)
        flat[:, 2] = 1.0
        truth = surface_normals(enlarge_surface(downsample(scene.normals.float(), (sd.working_size,) * 2), full))
        rows = {
            "estimate": split_errors(scene, rel, normals, src, tgt),
            "estimate, walls flat": split_errors(scene, rel, torch.where(wall, flat, normals), src, tgt),
            "true at the working size": split_errors(scene, rel, truth, src, tgt),
        }
        for name, row in rows.items():
            print(json.dumps({"split": split, "surface": name, **row}), flush=True)
        result[split] = rows
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
