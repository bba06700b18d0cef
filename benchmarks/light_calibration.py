"""The relight preset's ``surface.light_calibration``: a line that maps a lit estimator's fitted source-light elevation
to the true one, fitted on training scenes (issue #24, round 7). Plain script; one JSON line.

    OMP_NUM_THREADS=2 python benchmarks/light_calibration.py                      # the shipped preset's estimator
    OMP_NUM_THREADS=2 python benchmarks/light_calibration.py --split select --count 64   # a report, never fitted on
    OMP_NUM_THREADS=2 python benchmarks/light_calibration.py --source-elevation walls     # round 8's H

Each scene of ``--split`` (world seed ``--seed``) is lit by its relight task's source light (elevation uniform in
30–75°); the estimator (with the relight preset's dome prior and symmetry ensemble) fits a light through its
surface. The fit is drawn toward the view axis where the estimate is shallow. Least squares of θ_true on θ_fit
(degrees) gives (offset, gain), and the script also reports the mean offset and the RMS error of each. The fit is
made on ``train`` only: the line is a property of the estimator on its own training distribution.
``--source-elevation walls`` measures the elevation read from the estimated source shading's level on the walls
instead of the fit (`SurfaceEstimator.estimate(..., source_elevation="walls")`, round 8).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import machine_info, print_json_line  # noqa: E402

from lasagna.catalogue import load_preset  # noqa: E402
from lasagna.compose.surface import light_vector  # noqa: E402
from lasagna.document.condition import parse_direction  # noqa: E402
from lasagna.generators.surface import DomePrior, SurfaceEstimator  # noqa: E402
from lasagna.world import VOCABULARY, render, sample_scenes  # noqa: E402
from lasagna.world.tasks import relight_sources, relighting  # noqa: E402


def elevations(
    net, split: str, count: int, seed: int, size: int, dome, symmetry: str, source: str = "fit", chunk: int = 64
):
    """(true, estimated) elevations in degrees, float64, of ``count`` scenes (``source``: where the estimate's
    elevation comes from, `SurfaceEstimator.estimate`'s ``source_elevation``), and the estimated azimuth's signed
    error in degrees, wrapped to (−180, 180]."""
    true, fitted, azimuth = [], [], []
    for start in range(0, count, chunk):
        idx = range(start, min(count, start + chunk))
        scene = render(sample_scenes(split, seed, idx).with_labels([VOCABULARY[i % 8] for i in idx]), size)
        sources = relight_sources(scene.params)
        with torch.no_grad():
            _, fit = net.estimate_at(
                relighting(scene, sources).base.float(), dome, symmetry=symmetry, source_elevation=source
            )
        truth = torch.stack([light_vector(*parse_direction(t)) for t in sources]).double()
        true.append(torch.rad2deg(torch.acos(truth[:, 2])))
        fitted.append(torch.rad2deg(torch.acos(fit[:, 2].double().clamp(-1.0, 1.0))))
        fit = fit.double()
        turn = torch.atan2(fit[:, 1], fit[:, 0]) - torch.atan2(truth[:, 1], truth[:, 0])
        azimuth.append(torch.rad2deg(torch.atan2(torch.sin(turn), torch.cos(turn))))
    return torch.cat(true), torch.cat(fitted), torch.cat(azimuth)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--preset", default="relight", help="whose surface fields (estimator, domes, symmetry) are used")
    ap.add_argument("--split", default="train")
    ap.add_argument("--count", type=int, default=512)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--source-elevation", choices=("fit", "walls"), default="fit")
    args = ap.parse_args(argv)
    from lasagna import catalogue as cat

    preset = load_preset(args.preset)
    sd = preset.surface
    resolved = cat.resolve(args.preset, None, None, need_prior=False)
    net = SurfaceEstimator.from_pretrained(resolved.estimator)
    dome = DomePrior(weight=sd.dome_weight, height=sd.dome_height)
    true, fitted, azimuth = elevations(
        net, args.split, args.count, args.seed, args.size, dome, sd.symmetry, args.source_elevation
    )
    design = torch.stack([torch.ones_like(fitted), fitted], 1)
    offset, gain = torch.linalg.lstsq(design, true[:, None]).solution.flatten().tolist()
    shift = float((true - fitted).mean())

    def rms(x: torch.Tensor) -> float:
        return round(float(x.pow(2).mean().sqrt()), 2)

    print_json_line(
        {
            "benchmark": "light_calibration",
            "estimator": resolved.estimator.name,
            "split": args.split,
            "count": args.count,
            "source_elevation": args.source_elevation,
            "offset": round(offset, 2),
            "gain": round(gain, 3),
            "mean_shift_deg": round(shift, 2),
            "correlation": round(float(torch.corrcoef(torch.stack([true, fitted]))[0, 1]), 3),
            "rms_deg": {
                "as_fitted": rms(true - fitted),
                "shifted": rms(true - fitted - shift),
                "line": rms(true - design @ torch.tensor([offset, gain], dtype=torch.float64)),
            },
            "azimuth_error_deg": {  # the fit's direction: reported, never fitted (the calibration is the elevation's)
                "rms": rms(azimuth),
                "median_abs": round(float(azimuth.abs().median()), 2),
                "over_45": int((azimuth.abs() > 45).sum()),
                "over_90": int((azimuth.abs() > 90).sum()),
            },
            "machine": machine_info(),
        }
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
