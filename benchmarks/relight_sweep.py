"""The sweep that chose the relight preset's per-image settings, on heldout only (issue #11; defaults are
never chosen on far). Plain script; one JSON row per setting, then one JSON line.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/relight_sweep.py            # 16 scenes at 64² (~20 min)
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/relight_sweep.py --count 2 --only default "particles 4"

Each setting runs ``lasagna.editing.edit(image, "relight", label, **overrides)`` on the scenes of
``benchmarks/relight.py`` (each lit by its own source light A, relit to a named light B) and reports the
composite PSNR against the truth over all pixels and over object pixels (``_common.row``). "N seeds" rows
average the layers of N runs with seeds 0…N−1 after the runs; "particles K" rows are one run with K
particles (``distill.particles``: K layers per image in one batch, averaged). The overrides are given
explicitly, so the rows do not depend on the preset's current defaults (the preset now says particles 4,
t_min 0.1: the row "particles 4 + t_min 0.1").
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

from _common import machine_info, print_json_line, row, scenes  # noqa: E402

from lasagna.editing import edit  # noqa: E402

# The previous default, explicitly: one run, t ~ U(0.02, 0.98), SDS at ω = 1.
BASE = {"particles": 1, "t_min": 0.02, "t_max": 0.98, "guidance": 1.0, "loss": "sds"}


def seeds(n: int, **o) -> list[dict]:
    return [{**BASE, **o, "seed": s} for s in range(n)]


SETTINGS: dict[str, list[dict]] = {
    "default (1 run, t_min 0.02)": seeds(1),
    "4 seeds averaged": seeds(4),
    "8 seeds averaged": seeds(8),
    "300 steps": seeds(1, optimize=300),
    "lr 0.015": seeds(1, lr=0.015),
    "lr 0.06": seeds(1, lr=0.06),
    "t_max 0.6": seeds(1, t_max=0.6),
    "t_min 0.1": seeds(1, t_min=0.1),
    "ω 1.5": seeds(1, guidance=1.5),
    "ω 0.5": seeds(1, guidance=0.5),
    "ω 2, 4 seeds": seeds(4, guidance=2.0),
    "ω 3, 4 seeds": seeds(4, guidance=3.0),
    "LMC-SDS ω 3, 4 seeds": seeds(4, guidance=3.0, loss="lmc-sds"),
    "particles 4": seeds(1, particles=4),
    "particles 8": seeds(1, particles=8),
    "particles 4 + t_min 0.1": seeds(1, particles=4, t_min=0.1),
    "particles 8 + t_min 0.1": seeds(1, particles=8, t_min=0.1),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--count", type=int, default=16)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0, help="world seed")
    ap.add_argument("--only", nargs="*", default=None, help="settings to run (names as in the rows)")
    args = ap.parse_args(argv)
    rel, labels = scenes("heldout", args.count, args.seed, args.size)
    images = rel.base.float()
    cache: dict[str, torch.Tensor] = {}
    rows = []
    for name, runs in SETTINGS.items():
        if args.only is not None and name not in args.only:
            continue
        t0 = time.perf_counter()
        layers = []
        for o in runs:
            key = json.dumps(o, sort_keys=True)
            if key not in cache:
                cache[key] = torch.stack(
                    [edit(images[i], "relight", labels[i], **o).layer for i in range(images.shape[0])]
                ).double()
            layers.append(cache[key])
        r = row(rel, name, torch.stack(layers).mean(0), time.perf_counter() - t0)
        r.update(split="heldout", size=args.size)
        rows.append(r)
        print(json.dumps(r), flush=True)
    print_json_line({"benchmark": "relight_sweep", "rows": rows, "count": args.count, "machine": machine_info()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
