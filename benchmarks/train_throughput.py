"""Where a surface-estimator training step spends its time: scenes per second of drawing and rendering a step's
scenes, and of the estimator's loss and backward pass, per batch size and zoom (issue #24, round 17). Plain script;
one JSON row per setting, then one JSON line.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/train_throughput.py --batches 8 32 --zooms 1 3 --repeats 2
    python3 benchmarks/train_throughput.py --device cuda --batches 256 1024 4096 --zooms 1 3     # a lent GPU

Round 17's one GPU call drew 260 scenes a second at batch 512 with close-ups (zoom 3) and 1 370 at batch 1024
without, three processes sharing an H200, against 51 and 114 on this project's CPU: a GPU's scale is set by what a
step costs, so the next call sizes its batches by this table. Each setting times ``lasagna.training.surface``'s own
``step_scenes`` (the split's scenes drawn, rendered on the device — or on the CPU, ``--render-on cpu``, the baseline
in the same run — and cut to close-ups; with ``--bank N`` also drawn from a scene bank of N scenes rendered first,
``train-surface --scene-bank``) and ``step_loss`` with its backward pass, after one untimed warm-up; CUDA is
synchronised around each timed part.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import machine_info  # noqa: E402

from lasagna.generators.surface import SurfaceConfig, SurfaceEstimator  # noqa: E402
from lasagna.training.surface import SceneBank, SurfaceTrainConfig, step_loss, step_scenes  # noqa: E402


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def timed(fn, device: str):
    _sync(device)
    t0 = time.perf_counter()
    out = fn()
    _sync(device)
    return out, time.perf_counter() - t0


def measure(
    device: str, batch: int, zoom: float, render_on: str, repeats: int, channels: tuple[int, ...], bank: int = 0
) -> dict:
    """One setting's row; ``render_on`` "bank" draws the steps from a `SceneBank` of ``bank`` scenes rendered on the
    device first (its build time reported apart)."""
    config = SurfaceTrainConfig(
        net=SurfaceConfig(input="lit", silhouette=True, channels=channels, blocks=2, working_size=32),
        batch_size=batch,
        zoom=zoom,
        render_on="device" if render_on == "bank" else render_on,
        scene_bank=bank if render_on == "bank" else 0,
        world_seed=11,
        progress=False,
    )
    net = SurfaceEstimator(config.net).to(device)
    rng = torch.Generator().manual_seed(0)
    scenes, built = (None, None) if not config.scene_bank else timed(lambda: SceneBank(config, device), device)
    render_s = net_s = 0.0
    for i in range(repeats + 1):  # the first is a warm-up
        scene, t_render = timed(lambda: step_scenes(config, rng, device, scenes), device)
        (loss, _), t_loss = timed(lambda: step_loss(net, config, scene, rng, device), device)
        _, t_back = timed(loss.backward, device)
        if i:
            render_s, net_s = render_s + t_render, net_s + t_loss + t_back
    render_s, net_s = render_s / repeats, net_s / repeats
    return {
        "batch": batch,
        "zoom": zoom,
        "render_on": render_on,
        "render_s": round(render_s, 4),
        "net_s": round(net_s, 4),
        "scenes_per_s": round(batch / (render_s + net_s), 1),
        **({"bank": bank, "bank_build_s": round(built, 2)} if built is not None else {}),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--batches", nargs="+", type=int, default=[32, 256])
    p.add_argument("--zooms", nargs="+", type=float, default=[1.0, 3.0])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--channels", default="32,64,128")
    p.add_argument("--cpu-baseline-max", type=int, default=1024, help="largest batch also rendered on the CPU")
    p.add_argument("--bank", type=int, default=0, help="also a row per setting drawn from a scene bank of this size")
    args = p.parse_args(argv)
    channels = tuple(int(c) for c in args.channels.split(","))
    rows = []
    for zoom in args.zooms:
        for batch in args.batches:
            # The CPU-rendered baseline beside a GPU's rows, up to a batch the CPU renders in seconds.
            places = ["device", "cpu"] if args.device != "cpu" and batch <= args.cpu_baseline_max else ["device"]
            for where in places + ["bank"] * (args.bank > 0):
                row = measure(args.device, batch, zoom, where, args.repeats, channels, args.bank)
                print(json.dumps(row), flush=True)
                rows.append(row)
    name = torch.cuda.get_device_name() if args.device.startswith("cuda") else "cpu"
    print(json.dumps({"machine": machine_info(), "device": name, "command": " ".join(sys.argv), "rows": rows}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
