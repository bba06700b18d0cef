"""``lasagna train-surface``: train a surface estimator on the world's truth under many lights (resumable;
``lasagna.training.surface``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lasagna.cli.common import device_argument, progress

HELP = "train a surface estimator (height field from an image) on the procedural world (resumable)"
EXAMPLE = (
    "lasagna train-surface --input albedo --silhouette --out runs/surface-albedo-32 --minutes 30  # resumable",
    "lasagna train-surface --input lit --out runs/surface-lit-32 --minutes 30",
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--input", choices=("albedo", "lit"), required=True, help="what it reads: unlit base or lit image")
    p.add_argument(
        "--output",
        choices=("height", "normals"),
        default="height",
        help="what the estimator outputs: a height field, or unit normals directly",
    )
    p.add_argument(
        "--silhouette",
        action="store_true",
        help="also learn where the objects are (a silhouette head, for the dome prior)",
    )
    p.add_argument(
        "--light-input",
        action="store_true",
        help="lit input: also read the source light when it is known (given to it on --light-given of the scenes, "
        "jittered by --light-jitter degrees); at use it reads an image, fits the light, and reads it again",
    )
    p.add_argument("--light-given", type=float, default=0.75, help="probability that a scene's light is given")
    p.add_argument("--light-jitter", type=float, default=10.0, help="noise on a given light, degrees per component")
    p.add_argument(
        "--light-weight",
        type=float,
        default=0.1,
        help="lit input: weight of the fitted source light's cosine error in the loss (λ_l)",
    )
    p.add_argument("--out", required=True, help="run folder; run again with the same folder to resume")
    p.add_argument("--working-size", type=int, default=32, help="the side it trains (and later works) at")
    p.add_argument("--channels", default="32,64,128", help="feature channels per level")
    p.add_argument("--blocks", type=int, default=2)
    p.add_argument("--lights", type=int, default=3, help="random lights per scene and step")
    p.add_argument("--steps", type=int, default=100_000, help="upper bound; --minutes usually stops first")
    p.add_argument("--minutes", type=float, default=None, help="time budget of this invocation")
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--warmup", type=int, default=100)
    p.add_argument("--ema", type=float, default=0.998)
    p.add_argument("--grad-clip", type=float, default=1.0)
    p.add_argument("--world-seed", type=int, default=7, help="seed of the training split's scenes")
    p.add_argument(
        "--split",
        default="train",
        help="world split of the training scenes (wide: train's families and the generic gem and blob shapes)",
    )
    p.add_argument(
        "--zoom",
        type=float,
        default=1.0,
        help="close-ups: render at zoom × the working size and crop windows of 1 to zoom working sizes around "
        "object pixels (objects that fill the frame, as in photographs; 1: off)",
    )
    p.add_argument(
        "--stray",
        type=float,
        default=0.0,
        help="lit input: probability that a scene carries stray illumination (a sky's gradient, a vignette, a "
        "spotlight's pool) the estimator must learn as paint (0: off)",
    )
    p.add_argument(
        "--shadows",
        type=float,
        default=0.0,
        metavar="P",
        help="lit input: probability that a scene's input carries the world's cast shadows under its source light, "
        "learned as paint (the truth stays shadowless; 0: off)",
    )
    p.add_argument(
        "--rest",
        type=float,
        default=0.0,
        metavar="P",
        help="probability that a scene's objects rest on the wall (attached shadows, a height field above the wall) "
        "instead of floating in front of it (0: as sampled)",
    )
    p.add_argument(
        "--low-key",
        type=float,
        default=0.0,
        metavar="P",
        help="probability that each surface (the wall, each object) is painted dark, as photographs' backdrops are "
        "(0: as sampled)",
    )
    p.add_argument(
        "--height-weight",
        type=float,
        default=0.0,
        metavar="W",
        help="weight of the height field's error against the true heights above the wall (the heights a cast "
        "shadow needs; 0: off)",
    )
    p.add_argument(
        "--relief",
        type=float,
        default=0.0,
        help="probability that a wall the split drew flat is given relief of one of the split's families instead "
        "(more relief walls to learn from; 0: as drawn)",
    )
    p.add_argument(
        "--walls-only",
        type=float,
        nargs="?",
        const=1.0,
        default=0.0,
        metavar="P",
        help="make a scene its wall alone, objects removed, with probability P (alone: 1, every scene; with "
        "--relief 1: every scene a painted wall with relief)",
    )
    p.add_argument(
        "--scene-bank",
        type=int,
        default=0,
        metavar="N",
        help="render N scenes once and draw every step's batch from them, turned and lit anew (where rendering "
        "bounds a step, a GPU's; 0: fresh scenes every step)",
    )
    p.add_argument(
        "--init-from",
        default=None,
        help="a saved estimator folder (a run's surface/) of the same architecture (any working size) whose weights "
        "start this run",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")
    p.add_argument(
        "--render-on",
        choices=("device", "cpu"),
        default="device",
        help="where the training scenes are rendered (cpu: the same bits whatever the device)",
    )
    device_argument(p, default=None, help="torch device (default cuda if available, else cpu)")


def run(args: argparse.Namespace) -> int:
    from lasagna.errors import LasagnaError
    from lasagna.generators.surface import SurfaceConfig
    from lasagna.training.surface import SurfaceTrainConfig, train_surface

    try:
        channels = tuple(int(c) for c in str(args.channels).split(","))
    except ValueError:
        raise LasagnaError(
            f"{args.channels!r} is not a comma-separated list of integers; expected e.g. 32,64,128", "--channels"
        ) from None
    config = SurfaceTrainConfig(
        net=SurfaceConfig(
            input=args.input,
            output=args.output,
            silhouette=args.silhouette,
            channels=channels,
            blocks=args.blocks,
            working_size=args.working_size,
            light_input=args.light_input,
        ),
        light_given=args.light_given,
        light_jitter=args.light_jitter,
        light_weight=args.light_weight,
        lights=args.lights,
        steps=args.steps,
        max_minutes=args.minutes,
        batch_size=args.batch_size,
        lr=args.lr,
        warmup_steps=args.warmup,
        ema_decay=args.ema,
        ema_warmup=True,
        grad_clip=args.grad_clip,
        world_seed=args.world_seed,
        split=args.split,
        init_from=args.init_from,
        zoom=args.zoom,
        stray=args.stray,
        shadows=args.shadows,
        relief=args.relief,
        rest=args.rest,
        low_key=args.low_key,
        height_weight=args.height_weight,
        walls_only=args.walls_only,
        scene_bank=args.scene_bank,
        render_on=args.render_on,
        seed=args.seed,
        progress=progress() and not args.no_progress,  # bars only for a person watching (or --progress)
    )
    train_surface(config, args.out, device=args.device)
    print(json.dumps({"out": str(Path(args.out) / "surface"), "input": args.input}))
    return 0
