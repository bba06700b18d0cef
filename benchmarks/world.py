"""Generation speed of the procedural world: scenes per second by resolution and batch size.

    OMP_NUM_THREADS=1 python benchmarks/world.py [--seconds S] [--splits train heldout] [--shadows]
                                                [--device cpu|cuda]
    python benchmarks/world.py --sheet docs/img/world_splits.png      (a picture of every split; no timing)

Each cell renders fresh scenes (a new index range every call, so nothing is cached) for at least
``--seconds`` after one warm-up call, and reports the median over repeats of scenes/s. Prints one
JSON line: {"benchmark": "world", "device": ..., "threads": ..., "results": [{split, resolution,
batch, shadows, scenes_per_s, ms_per_batch}, ...]}.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import torch

from lasagna.world.scene import generate

RESOLUTIONS = (32, 64, 256)
BATCHES = (1, 64)


def measure(split: str, resolution: int, batch: int, seconds: float, shadows: bool, device: str) -> dict:
    start = 0

    def once() -> float:
        nonlocal start
        t = time.perf_counter()
        s = generate(split, batch, seed=0, resolution=resolution, start=start, shadows=shadows, device=device)
        if device != "cpu":
            torch.cuda.synchronize()
        start += batch
        assert s.image.shape[0] == batch
        return time.perf_counter() - t

    once()  # warm-up: imports, allocator, first-call overheads
    times: list[float] = []
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < seconds or len(times) < 3:
        times.append(once())
    per_batch = statistics.median(times)
    return {
        "split": split,
        "resolution": resolution,
        "batch": batch,
        "shadows": shadows,
        "scenes_per_s": round(batch / per_batch, 1),
        "ms_per_batch": round(per_batch * 1e3, 2),
        "repeats": len(times),
    }


def sheet(path: str, count: int = 6, resolution: int = 96) -> None:
    """Albedo, true shading and image of ``count`` scenes of every split, one band of three rows per split."""
    import numpy as np
    from PIL import Image

    from lasagna.world.splits import SPLIT_NAMES

    rows = []
    for split in SPLIT_NAMES:
        s = generate(split, count, seed=0, resolution=resolution)
        for x in (s.albedo, s.shading.expand(-1, 3, -1, -1), s.image):
            rows.append(torch.cat(list(x), 2))
        rows.append(torch.ones(3, 4, count * resolution))
    img = torch.cat(rows[:-1], 1).clamp(0, 1).permute(1, 2, 0).numpy()
    Image.fromarray((img * 255 + 0.5).astype(np.uint8)).save(path)
    print(json.dumps({"sheet": path, "splits": list(SPLIT_NAMES), "rows": ["albedo", "shading", "image"]}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=2.0, help="minimum time per cell (default 2)")
    ap.add_argument("--splits", nargs="+", default=["train"], help="splits to measure (default train)")
    ap.add_argument("--shadows", action="store_true", help="also measure with cast shadows")
    ap.add_argument("--device", default="cpu", help="torch device (default cpu)")
    ap.add_argument("--sheet", metavar="PNG", help="write a sheet of every split's scenes instead of timing")
    args = ap.parse_args()
    if args.sheet:
        sheet(args.sheet)
        return
    results = []
    for split in args.splits:
        for shadows in (False, True) if args.shadows else (False,):
            for res in RESOLUTIONS:
                for batch in BATCHES:
                    results.append(measure(split, res, batch, args.seconds, shadows, args.device))
    device = torch.cuda.get_device_name() if args.device.startswith("cuda") else platform.processor() or "cpu"
    print(
        json.dumps(
            {
                "benchmark": "world",
                "device": device,
                "threads": torch.get_num_threads(),
                "torch": torch.__version__,
                "results": results,
            }
        )
    )


if __name__ == "__main__":
    main()
