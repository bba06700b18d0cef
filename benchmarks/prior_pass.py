"""The relight edit's prior passes, before and after two savings that change no value beyond float rounding.

    OMP_NUM_THREADS=2 python benchmarks/prior_pass.py            # passes, then the four 512² photographs
    OMP_NUM_THREADS=2 python benchmarks/prior_pass.py --quick    # passes only

The default relight edit (SDS at ω = 1, 4 particles, `relit-32`) spends most of its time in the UNet prior. Two
savings, each measured against its baseline in the same run:

* **ω = 1 needs no unconditional branch** (`lasagna.losses.sds`): ω(ε_c − ε_u) + (ε_u − ε) = ε_c − ε, so a pass
  is of 4 samples, not 8;
* **NHWC weights and activations** for a frozen prior on the CPU (`UNetPrior.channels_last`, set by
  `lasagna.components.load_prior`).

Part 1 times one prior pass at the edit's shapes (batch 8 or 4, 32², the lit image as conditioning), NCHW and
NHWC, interleaved, the median of ``--repeats``. Part 2 times ``lasagna.edit(photo, "relight", light)`` on
``examples/photos/large`` toward left and right, in fresh processes alternating the baseline (both savings
undone: the two-branch SDS and NCHW) with the shipped code; it reports the median seconds per edit of each and the
largest difference between their layers (the same edit up to rounding). Ends with one JSON line.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import machine_info, print_json_line  # noqa: E402

LIGHTS = ("left", "right")


def pass_times(repeats: int) -> dict[str, float]:
    """Milliseconds per prior pass, median of ``repeats``, for batch 8 / 4 and NCHW / NHWC."""
    from lasagna.priors.unet import UNetPrior

    nchw = UNetPrior.from_pretrained(ROOT / "layers" / "relit-32").eval()
    nhwc = UNetPrior.from_pretrained(ROOT / "layers" / "relit-32").eval().channels_last()
    g = torch.Generator().manual_seed(0)
    times: dict[str, list[float]] = {}
    with torch.inference_mode():
        for _ in range(repeats):
            for b in (8, 4):
                z = torch.randn(b, 3, 32, 32, generator=g)
                image = torch.rand(b, 3, 32, 32, generator=g)
                t = torch.randint(0, 1000, (b,), generator=g)
                label = nchw.null_tensor(b)
                for name, prior in (("nchw", nchw), ("nhwc", nhwc)):
                    t0 = time.perf_counter()
                    prior.raw(z, t, label, image)
                    times.setdefault(f"batch{b}_{name}_ms", []).append((time.perf_counter() - t0) * 1000)
    return {k: round(statistics.median(v), 2) for k, v in times.items()}


def edit_child(mode: str, photos: list[Path], out: Path) -> None:
    """In a fresh process: the edits of every photo toward LIGHTS, with both savings undone for ``baseline``;
    seconds per edit (after one warm-up edit) and the layers, saved to ``out``."""
    import lasagna
    from lasagna.losses.base import Terms
    from lasagna.losses.sds import SDS
    from lasagna.priors.nn import randn
    from lasagna.priors.unet import UNetPrior

    if mode == "baseline":

        def two_branch(self, z, t, prior, cond, omega, rng):  # the SDS terms before the ω = 1 saving
            eps = randn(tuple(z.shape), rng, z.device, z.dtype)
            z_t = prior.schedule.add_noise(z, eps, t)
            e_c, e_u = (e.to(z.dtype) for e in prior.predict_many([(z_t, "cond"), (z_t, "uncond")], t, cond))
            return Terms(components={"cond": omega * (e_c - e_u), "proj": e_u - eps}, noise={"eps": eps})

        SDS.terms = two_branch
        UNetPrior.channels_last = lambda self: self  # NCHW, as before
    from PIL import Image

    images = [Image.open(p).convert("RGB") for p in photos]
    lasagna.edit(images[0], "relight", "top")  # loads the prior and the estimator
    seconds, layers = [], []
    for image in images:
        for light in LIGHTS:
            t0 = time.perf_counter()
            result = lasagna.edit(image, "relight", light)
            seconds.append(time.perf_counter() - t0)
            layers.append(result.layer)
    torch.save({"seconds": seconds, "layers": layers}, out)


def edit_times(photos: list[Path], rounds: int, tmp: Path) -> dict:
    runs: dict[str, list[dict]] = {"baseline": [], "shipped": []}
    for r in range(rounds):
        for mode in ("baseline", "shipped") if r % 2 == 0 else ("shipped", "baseline"):
            out = tmp / f"{mode}-{r}.pt"
            cmd = [sys.executable, __file__, "--child", mode, "--out", str(out), *map(str, photos)]
            subprocess.run(cmd, check=True)
            runs[mode].append(torch.load(out))
    med = {m: statistics.median(s for run in v for s in run["seconds"]) for m, v in runs.items()}
    diff = max(float((a - b).abs().max()) for a, b in zip(runs["baseline"][0]["layers"], runs["shipped"][0]["layers"]))
    return {
        "edit_seconds_baseline": round(med["baseline"], 3),
        "edit_seconds": round(med["shipped"], 3),
        "edit_speedup": round(med["baseline"] / med["shipped"], 2),
        "layer_max_abs_diff": diff,
        "edits_per_mode": sum(len(run["seconds"]) for run in runs["shipped"]),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=60)
    p.add_argument("--rounds", type=int, default=2, help="fresh-process rounds per mode (alternating)")
    p.add_argument("--quick", action="store_true", help="the passes only")
    p.add_argument("--child", choices=("baseline", "shipped"), help=argparse.SUPPRESS)
    p.add_argument("--out", type=Path, help=argparse.SUPPRESS)
    p.add_argument("photos", nargs="*", type=Path)
    args = p.parse_args(argv)
    if args.child:
        edit_child(args.child, args.photos, args.out)
        return 0
    result = {"benchmark": "prior_pass", "machine": machine_info(), "command": " ".join(sys.argv)}
    result.update(pass_times(args.repeats))
    print(json.dumps(result), flush=True)
    if not args.quick:
        import tempfile

        photos = sorted((ROOT / "examples" / "photos" / "large").glob("*.jpg"))
        with tempfile.TemporaryDirectory() as tmp:
            result.update(edit_times(photos, args.rounds, Path(tmp)))
    print_json_line(result)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
