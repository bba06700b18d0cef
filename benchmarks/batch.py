"""Edits at scale (issue #11 item 4): images per second of ``lasagna.batch.edit_many`` for 1, 16 and 256
inputs, amortised and per-image, on 1 and 2 processes (2 under torchrun, gloo). Plain script; ends with
one JSON line.

    python benchmarks/batch.py                       # the issue's table (~5 min on a quiet 2-core CPU)
    python benchmarks/batch.py --counts 8 --optimize 2   # a smoke run

Inputs: 64² albedo images of the procedural world (``lasagna.world``, held-out split), written as PNGs;
the shading preset, label ``left``. Each configuration runs as its own process group (``torchrun
--nproc_per_node=P --standalone``, or one plain process) on a fresh OUTDIR, writing what ``lasagna edit``
writes by default (stack folder and stack.ora; ``--no-ora`` leaves the ORA out). The time is ``edit_many``
alone — from a barrier after a one-image warm-up (torch imported, the generator loaded and run once) to a
barrier after the last stack folder is renamed into place — so interpreter start-up is not counted.

* ``amortised``: the preset's generator, one forward pass per image (``--batch-size``, default 1).
* ``per-image``: a free layer distilled for ``--optimize`` steps (default 10, not the preset's 150: the
  throughput of the machinery and the scaling over processes is the point, not the layer's quality).

Targets (docs/BENCHMARKS.md): per-image, 256 inputs: 2 processes ≥ 0.9 × twice 1 process's images/s;
amortised at 64² ≥ 100 images/s. Measure on a quiet machine: anything else running on the cores is
measured too.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
from _common import machine_info, print_json_line  # noqa: E402


def write_inputs(folder: Path, count: int, size: int, seed: int) -> list[Path]:
    """``count`` world albedo images ``000000.png`` … in ``folder`` (8-bit sRGB PNGs)."""
    import numpy as np
    from PIL import Image

    from lasagna.world.scene import generate

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for start in range(0, count, 64):  # in slices: the renderer's memory grows with the batch
        scene = generate("heldout", min(64, count - start), seed, size, start=start)
        for k, albedo in enumerate(scene.albedo):
            rgb = (albedo.clamp(0, 1).permute(1, 2, 0).numpy() * 255.0).round().astype(np.uint8)
            path = folder / f"{start + k:06d}.png"
            Image.fromarray(rgb).save(path)
            paths.append(path)
    return paths


def worker(args: argparse.Namespace) -> None:
    """One process of a configuration (run by ``main`` under torchrun or alone): prints rank 0's JSON."""
    import torch
    import torch.distributed as dist

    from lasagna.batch import edit_many
    from lasagna.training.loop import init_distributed, shutdown_distributed

    torch.set_num_threads(1)
    info = init_distributed("cpu")
    options = dict(generator="amortised" if args.method == "amortised" else "free", ora=not args.no_ora)
    if args.method == "per-image":
        options["optimize"] = args.optimize
    inputs = sorted(Path(args.inputs).glob("*.png"))[: args.count]
    warm = Path(args.out).with_name(Path(args.out).name + f"-warm{info.rank}")
    edit_many(inputs[:1], "shading", "left", warm, rank=0, world=1, **options)  # imports, generator, caches
    if info.world_size > 1:
        dist.barrier()
    t0 = time.perf_counter()
    report = edit_many(inputs, "shading", "left", args.out, batch_size=args.batch_size, **options)
    if info.world_size > 1:
        dist.barrier()
    seconds = time.perf_counter() - t0
    shutdown_distributed(info)
    if info.is_main:
        print(json.dumps({"seconds": seconds, "done": len(report.done), "failed": [o.error for o in report.failed]}))


def run_config(method: str, count: int, processes: int, args, inputs: Path, scratch: Path) -> dict:
    out = scratch / f"{method}-{count}-{processes}"
    shutil.rmtree(out, ignore_errors=True)
    worker_args = [
        str(Path(__file__).resolve()),
        "--worker",
        "--method",
        method,
        "--count",
        str(count),
        "--inputs",
        str(inputs),
        "--out",
        str(out),
        "--optimize",
        str(args.optimize),
        "--batch-size",
        str(args.batch_size),
        *(["--no-ora"] if args.no_ora else []),
    ]
    if processes == 1:
        cmd = [sys.executable, *worker_args]
    else:
        cmd = [sys.executable, "-m", "torch.distributed.run", f"--nproc_per_node={processes}", "--standalone"]
        cmd += worker_args
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=3600)
    if done.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{done.stderr[-3000:]}")
    result = json.loads(done.stdout.strip().splitlines()[-1])
    if result["done"] != count or result["failed"]:
        raise SystemExit(f"{method} {count} × {processes}: {result}")
    record = {
        "method": method,
        "inputs": count,
        "processes": processes,
        "seconds": round(result["seconds"], 4),
        "images_per_s": round(count / result["seconds"], 2),
    }
    print(json.dumps(record), file=sys.stderr)
    shutil.rmtree(out, ignore_errors=True)
    return record


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--counts", default="1,16,256", help="numbers of inputs (default 1,16,256)")
    p.add_argument("--processes", default="1,2", help="process counts (default 1,2)")
    p.add_argument("--methods", default="amortised,per-image")
    p.add_argument("--optimize", type=int, default=10, help="per-image steps (default 10; the preset's is 150)")
    p.add_argument("--batch-size", type=int, default=1, help="amortised images per forward pass (default 1)")
    p.add_argument("--size", type=int, default=64, help="image side (default 64)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-ora", action="store_true", help="do not write stack.ora")
    # the worker's own arguments (one process of a configuration)
    p.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--method", help=argparse.SUPPRESS)
    p.add_argument("--count", type=int, help=argparse.SUPPRESS)
    p.add_argument("--inputs", help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.worker:
        worker(args)
        return
    counts = [int(c) for c in args.counts.split(",")]
    processes = [int(c) for c in args.processes.split(",")]
    methods = args.methods.split(",")
    with tempfile.TemporaryDirectory(prefix="lasagna-batch-") as tmp:
        scratch = Path(tmp)
        write_inputs(scratch / "inputs", max(counts), args.size, args.seed)
        results = [
            run_config(m, c, n, args, scratch / "inputs", scratch) for m in methods for c in counts for n in processes
        ]
    rate = {(r["method"], r["inputs"], r["processes"]): r["images_per_s"] for r in results}
    summary = {}
    for m in methods:
        big = max(counts)
        if (m, big, 1) in rate and (m, big, 2) in rate:
            summary[f"{m}_speedup_2_over_1_at_{big}"] = round(rate[(m, big, 2)] / rate[(m, big, 1)], 3)
            summary[f"{m}_linear_fraction_at_{big}"] = round(rate[(m, big, 2)] / (2 * rate[(m, big, 1)]), 3)
        summary[f"{m}_best_images_per_s"] = max(v for k, v in rate.items() if k[0] == m)
    print_json_line(
        {
            "benchmark": "batch",
            "size": args.size,
            "optimize": args.optimize,
            "batch_size": args.batch_size,
            "ora": not args.no_ora,
            "results": results,
            **summary,
            "targets": {"per-image_linear_fraction_at_256": 0.9, "amortised_images_per_s_at_64": 100},
            "machine": machine_info(),
        }
    )


if __name__ == "__main__":
    main()
