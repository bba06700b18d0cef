"""``lasagna train-layer``: train a preset's amortised layer generator on the world (resumable;
``lasagna.training.generator``), with ``--install`` into the user's catalogue (``lasagna.catalogue.install_generator``:
never inside the package; an existing generator is replaced only with ``--force``)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lasagna.cli.common import device_argument, loss_argument, progress
from lasagna.errors import LasagnaError

HELP = "train a preset's amortised layer generator on the world (resumable)"
EXAMPLE = "lasagna train-layer --preset shading --minutes 15 --install --force   # into your catalogue"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", required=True, help="learned-layer preset whose generator to train (e.g. shading)")
    p.add_argument(
        "--out",
        metavar="DIR",
        help="run folder; run again with the same folder to resume (default runs/<preset>-generator)",
    )
    p.add_argument("--minutes", type=float, help="time budget of this invocation")
    p.add_argument(
        "--steps", type=int, default=3000, help="training steps (an upper bound with --minutes; default 3000)"
    )
    p.add_argument("--supervised", action="store_true", help="train on the world's true layer (the supervised ceiling)")
    loss_argument(p, "default: the preset's")
    p.add_argument("--guidance", type=float, metavar="W", help="default: the preset's")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument(
        "--ramp",
        type=int,
        default=500,
        metavar="N",
        help="steps of the LMC-SDS recipe's cosine ramps: score weight 0.1 → 1, L2-to-input weight 1 → --reg-final",
    )
    p.add_argument(
        "--reg-final",
        type=float,
        default=0.0,
        metavar="W",
        help="L2-to-input weight after the ramp (default 0; the LMC-SDS paper's image network keeps 0.1)",
    )
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--resolution", type=int, help="world scene size (default: the prior's resolution, else 32)")
    p.add_argument("--channels", default="16,32,64,128", help="generator widths per level (default 16,32,64,128)")
    p.add_argument("--ema", type=float, default=0.999, help="EMA decay of the weights saved (default 0.999)")
    p.add_argument(
        "--ema-warmup",
        action="store_true",
        help="ramp the EMA decay as min(ema, (1+step)/(10+step)) so a short run's average forgets its start",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--split",
        default="train",
        metavar="NAME",
        help="world split of the training scenes (default train). Another split makes an in-family oracle, "
        "never a shipped default: heldout chooses defaults and far only measures (lasagna.world.splits)",
    )
    p.add_argument(
        "--world-seed",
        type=int,
        default=0,
        metavar="N",
        help="world seed of the training scenes (default 0); with --split heldout or far it must not be 0, "
        "the seed the benchmarks' scenes come from",
    )
    p.add_argument("--eval-split", default="val", metavar="NAME", help="split of metrics.json's scenes (default val)")
    p.add_argument(
        "--install",
        action="store_true",
        help="install the trained generator as the preset's in your catalogue ($LASAGNA_LAYERS's first folder, "
        "else ~/.local/share/lasagna/layers), never inside the package",
    )
    p.add_argument("--force", action="store_true", help="with --install: replace the generator the preset has")
    device_argument(p, default=None, help="torch device (default cuda if available, else cpu)")


def run(args: argparse.Namespace) -> int:
    from lasagna import catalogue as cat
    from lasagna.distill import Weights, prior_image_size
    from lasagna.generators.unet import LayerGeneratorConfig
    from lasagna.training import AmortisedConfig, train_layer_generator
    from lasagna.world.splits import SPLIT_NAMES, check_seed, check_training_scenes

    resolved = cat.resolve(args.preset, need_prior=not args.supervised)
    preset = resolved.preset
    if args.install and resolved.generator is not None and not args.force:  # before training, not after
        raise LasagnaError(
            f"preset {preset.name!r} already has a generator at {resolved.generator}; expected --force to replace it",
            "--install",
        )
    try:
        widths = tuple(int(c) for c in str(args.channels).split(","))
    except ValueError:
        raise LasagnaError(
            f"{args.channels!r} is not a comma-separated list of integers; expected e.g. 16,32,64,128", "--channels"
        ) from None
    check_seed(args.world_seed, where="--world-seed")
    for flag, name in (("--split", args.split), ("--eval-split", args.eval_split)):
        if name not in SPLIT_NAMES:
            raise LasagnaError(f"unknown split {name!r}; expected one of {', '.join(SPLIT_NAMES)}", flag)
    check_training_scenes(args.split, args.world_seed, "--world-seed")
    loss = args.loss or preset.distill.loss
    prior = corrective = None
    resolution = args.resolution
    if not args.supervised:
        prior = cat.load_prior(resolved.prior, preset=preset)
        if loss == "lmc-sds":
            corrective = cat.load_corrective(cat.component_path(preset, "corrective", resolved.preset_file))
        if resolution is None:
            resolution = prior_image_size(prior)[0]
    out = Path(args.out or f"runs/{preset.name}-generator")
    # An explicit --guidance (0 included) is the run's ω: the config refuses one that is not positive.
    guidance = args.guidance if args.guidance is not None else preset.distill.guidance
    config = AmortisedConfig(
        generator=LayerGeneratorConfig.for_preset(preset, channels=widths),
        task=preset.world_task,
        prior=None if args.supervised else str(resolved.prior),
        corrective=str(resolved.corrective) if corrective is not None else None,
        supervised=args.supervised,
        loss=loss,
        guidance=guidance,
        t_min=preset.distill.t_min,
        t_max=preset.distill.t_max,
        lr=args.lr,
        batch_size=args.batch_size,
        weights=Weights.lmc_network(args.ramp, reg_end=args.reg_final),
        resolution=resolution or 32,
        split=args.split,
        world_seed=args.world_seed,
        eval_split=args.eval_split,
        steps=args.steps,
        max_minutes=args.minutes,
        ema_decay=args.ema,
        ema_warmup=args.ema_warmup,
        seed=args.seed,
        progress=progress(),
    )
    result = train_layer_generator(config, out, prior=prior, corrective=corrective, device=args.device)
    line = {
        "out": str(out / "generator"),
        "preset": preset.name,
        "step": result.step,
        "stopped": result.stopped,
        **{k: v for k, v in result.metrics.items() if k.endswith("psnr")},
    }
    if args.install:
        line["installed"] = str(cat.install_generator(out / "generator", args.preset, force=args.force))
    print(json.dumps(line))
    return 0
