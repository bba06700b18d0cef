"""Generation speed of the procedural world: scenes per second by resolution and batch size.

    OMP_NUM_THREADS=1 python benchmarks/world.py [--seconds S] [--splits train heldout] [--shadows]
                                                [--device cpu|cuda]

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=2.0, help="minimum time per cell (default 2)")
    ap.add_argument("--splits", nargs="+", default=["train"], help="splits to measure (default train)")
    ap.add_argument("--shadows", action="store_true", help="also measure with cast shadows")
    ap.add_argument("--device", default="cpu", help="torch device (default cpu)")
    args = ap.parse_args()
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
