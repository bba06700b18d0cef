"""``lasagna train-prior``: train a bundled conditional prior on the procedural world (resumable;
``lasagna.training.prior``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lasagna.cli.common import device_argument, progress

HELP = "train a bundled conditional prior on the procedural world (resumable)"
EXAMPLE = "lasagna train-prior --task relight --out runs/relight-32 --minutes 40   # run again to resume"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lasagna.document.preset import WORLD_TASKS as TASKS  # torch-free: a typing mistake is refused at once

    p.add_argument("--task", choices=TASKS, default="relight")
    p.add_argument("--out", required=True, help="run folder; run again with the same folder to resume")
    p.add_argument("--resolution", type=int, default=32)
    p.add_argument("--channels", default="32,64,128", help="feature channels per level")
    p.add_argument("--res-blocks", type=int, default=1)
    p.add_argument("--attention", action="store_true")
    p.add_argument("--prediction", choices=("v", "epsilon"), default="v")
    p.add_argument(
        "--directions",
        action="store_true",
        help="relight/relit: condition on any light direction (named or az=…,el=…), trained on named and random "
        "ones; with --init-from a label prior, its weights start it",
    )
    p.add_argument("--steps", type=int, default=100_000, help="upper bound; --minutes usually stops first")
    p.add_argument("--minutes", type=float, default=None, help="time budget of this invocation")
    p.add_argument("--batch-size", type=int, default=64)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument(
        "--lr-schedule",
        choices=("step", "cosine"),
        default="step",
        help="step: constant lr (after warm-up); cosine: anneal to 0 over --steps",
    )
    p.add_argument(
        "--init-from",
        default=None,
        help="start from this saved prior's weights (its architecture replaces --channels etc.): a prior folder or "
        "a catalogue name (e.g. relight-32)",
    )
    p.add_argument(
        "--grow-res-blocks",
        type=int,
        default=None,
        metavar="N",
        help="with --init-from: N residual blocks per level (at least its own); the added blocks start as the "
        "identity, so the grown prior starts where --init-from is",
    )
    p.add_argument(
        "--init-labels",
        choices=("keep", "fresh"),
        default="keep",
        help="fresh: --init-from may be a prior of another task with the same conditioning channels; "
        "its label embedding is replaced (every label starts as its null label)",
    )
    p.add_argument("--warmup", type=int, default=200)
    p.add_argument("--ema", type=float, default=0.999)
    p.add_argument(
        "--ema-warmup",
        action="store_true",
        help="ramp the EMA decay as min(ema, (1+step)/(10+step)): for short runs and fine-tunes, whose "
        "average would otherwise keep 0.999^steps of the starting weights",
    )
    p.add_argument("--grad-clip", type=float, default=1.0)
    p.add_argument("--checkpoint-every", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--split",
        default="train",
        help="world split of the training scenes (wide: train's families and the generic gem and blob shapes)",
    )
    p.add_argument("--world-seed", type=int, default=0, help="seed of the training split's scenes")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument(
        "--render-on",
        choices=("device", "cpu"),
        default="device",
        help="where the training scenes are rendered (cpu: the same bits whatever the device)",
    )
    device_argument(p, default=None, help="torch device (default cuda if available, else cpu)")


def run(args: argparse.Namespace) -> int:
    from lasagna.training.prior import PriorTrainConfig, run_unet_config, train_prior, unet_config_for

    channels = tuple(int(c) for c in str(args.channels).split(","))
    unet = unet_config_for(
        args.task, args.resolution, channels, args.res_blocks, args.attention, args.prediction, args.directions
    )
    if args.init_from is not None and "/" not in args.init_from and not Path(args.init_from).is_dir():
        from lasagna.catalogue import find

        args.init_from = str(find(args.init_from, "prior"))  # a catalogue name: its folder (outside a checkout too)
    unet = run_unet_config(args.task, unet, args.init_from, args.init_labels, args.grow_res_blocks)
    config = PriorTrainConfig(
        task=args.task,
        unet=unet,
        init_from=args.init_from,
        init_labels=args.init_labels,
        lr_schedule=args.lr_schedule,
        steps=args.steps,
        max_minutes=args.minutes,
        batch_size=args.batch_size,
        lr=args.lr,
        warmup_steps=args.warmup,
        ema_decay=args.ema,
        ema_warmup=args.ema_warmup,
        grad_clip=args.grad_clip,
        checkpoint_every=args.checkpoint_every,
        seed=args.seed,
        split=args.split,
        world_seed=args.world_seed,
        render_on=args.render_on,
        progress=progress() and not args.no_progress,  # bars only for a person watching (or --progress)
    )
    train_prior(config, args.out, device=args.device)
    print(json.dumps({"out": str(Path(args.out) / "prior"), "task": args.task}))
    return 0
