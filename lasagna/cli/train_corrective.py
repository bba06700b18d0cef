"""``lasagna train-corrective``: train the LMC-SDS manifold corrective b̂ of a prior (resumable), or fit
the spectral b̂ in closed form (``lasagna.training.corrective``).

    lasagna train-corrective --kind spectral --prior layers/relight-32 --task relight --out runs/b
    lasagna train-corrective --kind spectral --prior /models/sd [--controlnet CN]… --images photos/ --out runs/b

The prior is a lasagna UNetPrior folder, a diffusers folder (SD 1.x/2.x/SDXL, written by save_pretrained;
``--controlnet`` adds ControlNets) or a catalogue name. A diffusers prior's b̂ is fitted on its
unconditional branch with each image as its own conditioning image (``unconditional_source``), on the
images of ``--images`` or the world's (``--task``). ``OUT/corrective`` is what ``lasagna edit --corrective``
and ``lasagna prior add --corrective`` take.
"""

from __future__ import annotations

import argparse
import importlib
import json

from lasagna.cli.common import device_argument, progress
from lasagna.errors import LasagnaError

HELP = "train the LMC-SDS manifold corrective b̂ of a prior (resumable)"
EXAMPLE = "lasagna train-corrective --kind spectral --prior relight-32 --task relight --out runs/relight-32-spectral"


def _import_callable(spec: str):
    module, sep, attr = spec.partition(":")
    if not sep or not module or not attr:
        raise LasagnaError(
            f"got {spec!r}; expected module:callable, e.g. lasagna.world.source:sample_batch", "--source"
        )
    try:
        obj = getattr(importlib.import_module(module), attr)
    except (ImportError, AttributeError) as exc:
        raise LasagnaError(f"cannot import {spec!r} ({exc})", "--source") from None
    if not callable(obj):
        raise LasagnaError(f"{spec!r} is not callable; expected sample_batch(batch, rng)", "--source")
    return obj


def _filters(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers such as 32,64,128; got {text!r}") from None


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lasagna.document.preset import TORCH_DTYPES
    from lasagna.document.preset import WORLD_TASKS as TASKS  # torch-free: a typing mistake is refused at once

    p.add_argument(
        "--prior",
        required=True,
        help="the prior: a UNetPrior folder, a diffusers folder (written by save_pretrained) or a catalogue name",
    )
    p.add_argument(
        "--controlnet", action="append", default=[], metavar="PATH", help="a diffusers prior's ControlNet (repeat)"
    )
    p.add_argument("--images", metavar="FOLDER", help="draw clean images from this folder of images; instead of --task")
    p.add_argument(
        "--dtype", choices=TORCH_DTYPES, default="auto", help="a diffusers prior's float type (auto: fp16 on CUDA)"
    )
    p.add_argument(
        "--kind",
        choices=("network", "spectral"),
        default="network",
        help="network: the paper's UNet b̂ trained with L_k; spectral: a per-t linear frequency response "
        "fitted in closed form (lasagna.losses.spectral)",
    )
    p.add_argument("--batches", type=int, default=8, help="spectral: batches of clean images per timestep bucket")
    p.add_argument("--buckets", type=int, default=50, help="spectral: timestep buckets")
    p.add_argument(
        "--task",
        choices=TASKS,
        default=None,
        help="draw clean images from the procedural world's train split for this prior task",
    )
    p.add_argument(
        "--source",
        default=None,
        help="module:callable, sample_batch(batch, generator) -> (images, label_idx, cond_image); instead of --task",
    )
    p.add_argument("--out", required=True, help="output folder; run again with the same folder to resume")
    p.add_argument("--steps", type=int, default=20_000)
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--lr", type=float, default=1e-4)
    p.add_argument("--filters", type=_filters, default=(32, 64, 128), help="filters per level, e.g. 32,64,128")
    p.add_argument("--sees-condition", action="store_true", help="b̂ also sees the conditioning image and the label")
    p.add_argument("--branch", choices=("uncond", "cond"), default="uncond")
    p.add_argument("--t-min", type=float, default=0.02)
    p.add_argument("--t-max", type=float, default=0.98)
    p.add_argument("--ema", type=float, default=None, help="EMA decay, e.g. 0.999 (off by default)")
    p.add_argument("--checkpoint-every", type=int, default=500)
    p.add_argument("--log-every", type=int, default=10)
    p.add_argument("--eval-batches", type=int, default=8)
    p.add_argument("--max-minutes", type=float, default=None)
    p.add_argument("--seed", type=int, default=0)
    device_argument(p)
    p.add_argument("--no-progress", action="store_true")


def _load_prior(args: argparse.Namespace):
    """(prior, its image side, whether it is a diffusers prior) for ``--prior`` and ``--controlnet``."""
    from pathlib import Path

    from lasagna import catalogue as cat
    from lasagna.distill.objective import prior_image_size
    from lasagna.document.preset import ControlNetRef

    nets = [ControlNetRef(path=str(Path(p).resolve())) for p in args.controlnet]
    ref = str(Path(args.prior).resolve()) if Path(args.prior).is_dir() else args.prior
    source = cat.prior_source(ref, controlnets=nets)
    if source.kind == "unet":
        from lasagna.priors.unet import UNetPrior

        prior = UNetPrior.from_pretrained(source.folder, device=args.device)
        return prior, prior.config.resolution, False
    from lasagna.priors.diffusers import DiffusersPrior

    prior = DiffusersPrior.from_local(
        source.folder,
        controlnets=[n.path for n in source.controlnets],
        conditioning_scale=[1.0 if n.scale is None else n.scale for n in source.controlnets],
        vocabulary=("image",),  # one placeholder label: the fit uses the unconditional branch
        device=args.device,
        dtype=args.dtype,
    )
    return prior, prior_image_size(prior)[0], True


def run(args: argparse.Namespace) -> int:
    from lasagna.training.corrective import (
        CorrectiveTrainConfig,
        corrective_config_for,
        fit_spectral,
        image_folder_source,
        train_corrective,
        unconditional_source,
    )

    if sum(x is not None for x in (args.task, args.source, args.images)) != 1:
        raise LasagnaError("give exactly one of --task, --images and --source", "train-corrective")
    prior, size, diffusers = _load_prior(args)
    if args.task is not None:
        from lasagna.training.prior import world_source

        source = world_source(args.task, size)
    elif args.images is not None:
        source = image_folder_source(args.images, size)
    else:
        source = _import_callable(args.source)
    if diffusers:
        source = unconditional_source(source, null=len(prior.vocabulary), control=len(prior.controlnets) > 0)
    if args.kind == "spectral":
        result = fit_spectral(
            prior,
            source,
            args.out,
            batch_size=args.batch_size,
            batches=args.batches,
            buckets=args.buckets,
            branch=args.branch,
            eval_batches=args.eval_batches,
            t_min=args.t_min,
            t_max=args.t_max,
            seed=args.seed,
            device=args.device,
        )
        print(
            json.dumps(
                {
                    "kind": "spectral",
                    "lk_trained": result.lk_trained,
                    "lk_trivial": result.lk_trivial,
                    "ratio": result.ratio,
                }
            )
        )
        return 0
    cond_channels = sum(prior.control_channels) if diffusers else prior.config.cond_channels
    config = CorrectiveTrainConfig(
        corrective=corrective_config_for(prior, args.filters, args.sees_condition, cond_channels),
        steps=args.steps,
        batch_size=args.batch_size,
        lr=args.lr,
        t_min=args.t_min,
        t_max=args.t_max,
        branch=args.branch,
        ema_decay=args.ema,
        checkpoint_every=args.checkpoint_every,
        log_every=args.log_every,
        eval_batches=args.eval_batches,
        max_minutes=args.max_minutes,
        seed=args.seed,
        progress=progress() and not args.no_progress,  # bars only for a person watching (or --progress)
    )
    result = train_corrective(prior, source, config, args.out, device=args.device)
    print(
        json.dumps(
            {
                "step": result.step,
                "stopped": result.stopped,
                "lk_trained": result.lk_trained,
                "lk_trivial": result.lk_trivial,
                "ratio": result.ratio,
            }
        )
    )
    return 0
