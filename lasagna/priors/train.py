"""Training the bundled conditional priors on the procedural world, on this CPU (resumable).

Three tasks, each a ``UNetPrior`` trained with the simple diffusion objective (v-prediction by default)
and classifier-free label dropout, on fresh world batches generated on the fly (no data set on disk):

* ``relight``: x₀ = the lit image (albedo × shading), conditioned ControlNet-style on the albedo
  (3 channels) and on the lighting label (the world's eight named directions);
* ``colorize``: x₀ = the colour image, conditioned on its Rec. 709 luma (1 channel) and the single
  label ``natural``;
* ``light``: x₀ = the image with the world's coloured fill light added (``lasagna.world.tasks``),
  conditioned on the unlit image (3 channels) and the glow's label (warm, cool, white).

The conditioning image is what Lasagna's base layer will be at distillation time. Every random draw
(which scenes, t, ε, label dropout) comes from the loop's checkpointed generator, so a killed run
resumes bit for bit (``lasagna.training``). Scenes come from the ``train`` split only; ``val`` and
``heldout`` stay unseen for evaluation.

    lasagna train-prior --task relight --out runs/relight-32 --minutes 30
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Literal

import torch
from pydantic import ConfigDict, Field

from lasagna.errors import LasagnaError
from lasagna.priors import io
from lasagna.priors.unet import UNetConfig, UNetPrior
from lasagna.training import LoopConfig, train_loop

CHECKPOINT_FORMAT = "lasagna.prior_checkpoint"
Task = Literal["relight", "colorize", "light"]
# The world's scene index range the trainer draws batches from: large enough that no batch repeats
# in any run this CPU can afford (2**30 scenes), small enough for int32 seeds.
_SCENE_RANGE = 2**30


class PriorTrainConfig(LoopConfig):
    """How a bundled prior is trained (saved as train_config.json and inside every checkpoint)."""

    model_config = ConfigDict(extra="forbid")

    task: Task = "relight"
    unet: UNetConfig
    batch_size: int = Field(64, ge=1)
    p_uncond: float = Field(0.15, ge=0.0, le=1.0, description="label dropout for classifier-free guidance")
    split: str = Field("train", description="world split the training scenes come from")
    world_seed: int = Field(0, description="seed of the world split (scenes are (split, seed, index))")
    shadows: bool = Field(False, description="render cast shadows in the training scenes")
    init_from: str | None = Field(None, description="a saved prior (folder) whose weights start this run: "
                                  "a second training stage, e.g. an lr anneal after a constant-lr run")
    init_labels: Literal["keep", "fresh"] = Field(
        "keep", description="keep: init_from has this run's vocabulary; fresh: it may have another (a prior of "
        "another task with the same architecture): every tensor is copied but the label embedding, whose rows "
        "all start as init_from's null label — the new task starts from the old prior's unconditional model")


def task_vocabulary(task: Task) -> tuple[str, ...]:
    from lasagna.world import GLOW_VOCABULARY, VOCABULARY

    return {"relight": tuple(VOCABULARY), "colorize": ("natural",), "light": tuple(GLOW_VOCABULARY)}[task]


def task_cond_channels(task: Task) -> int:
    return 1 if task == "colorize" else 3


def unet_config_for(task: Task, resolution: int = 32, channels: tuple[int, ...] = (32, 64, 128), res_blocks: int = 1,
                    attention: bool = False, prediction: Literal["epsilon", "v"] = "v") -> UNetConfig:
    """The UNetConfig of a task's prior: image 3 channels, its conditioning channels and vocabulary."""
    return UNetConfig(image_channels=3, cond_channels=task_cond_channels(task), resolution=resolution, channels=channels,
                      res_blocks=res_blocks, attention=attention, vocabulary=task_vocabulary(task), prediction=prediction)


def task_batch(task: Task, scene) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(x₀ in [0, 1], label index, conditioning image in [0, 1]) of a world ``Scene`` batch for ``task``."""
    from lasagna.world import additive_light, colorization

    if task == "relight":
        return scene.image, scene.label_index.long(), scene.albedo
    if task == "light":
        add = additive_light(scene)
        return add.lit, scene.params.glow_label.long(), add.base
    col = colorization(scene)
    return col.target, torch.zeros(scene.image.shape[0], dtype=torch.long), col.base[:, :1]


def world_source(task: Task, resolution: int, split: str = "train", seed: int = 0, shadows: bool = False):
    """``sample_batch(batch, generator) -> (images, label_idx, cond_image)`` drawing world scenes.

    The data-source signature shared with the corrective's trainer; the scenes drawn depend only on
    ``generator``'s stream.
    """
    from lasagna.world import generate

    def sample_batch(batch: int, generator: torch.Generator):
        start = int(torch.randint(0, _SCENE_RANGE, (1,), generator=generator))
        scene = generate(split, batch, seed, resolution, start=start, shadows=shadows)
        return task_batch(task, scene)

    return sample_batch


def train_prior(config: PriorTrainConfig, out_dir: str | Path, device: str | torch.device = "cpu") -> UNetPrior:
    """Train (or resume) the prior in ``out_dir``; the final EMA weights go to ``out_dir/prior``."""
    source = world_source(config.task, config.unet.resolution, config.split, config.world_seed, config.shadows)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        prior = UNetPrior(config.unet)
    if config.init_from is not None:
        start = UNetPrior.from_pretrained(config.init_from)
        theirs = start.config
        if config.init_labels == "fresh":
            theirs = theirs.model_copy(update={"vocabulary": config.unet.vocabulary})
        if theirs != config.unet:
            raise LasagnaError(f"its UNet config differs from this run's ({start.config} vs {config.unet})",
                               config.init_from)
        state = start.state_dict()
        if config.init_labels == "fresh":
            key = "net.label_emb.weight"
            state[key] = state[key][-1].expand(len(config.unet.vocabulary) + 1, -1).clone()
        prior.load_state_dict(state)

    def step_fn(net: UNetPrior, gen: torch.Generator, step: int):
        images, labels, cond = source(config.batch_size, gen)
        loss = net.training_loss(net.encode(images.to(device)), labels.to(device), cond.to(device), gen, config.p_uncond)
        return loss, {}

    done = train_loop(prior, step_fn, config, config, out_dir, checkpoint_format=CHECKPOINT_FORMAT,
                      desc=f"prior:{config.task}", device=device)
    final: UNetPrior = done.model  # type: ignore[assignment]
    final.save_pretrained(Path(out_dir) / "prior")
    return final


def prior_from_checkpoint(path: str | Path, ema: bool = True) -> tuple[UNetPrior, int]:
    """(prior, step) from a training checkpoint: its EMA weights (or the raw ones), in eval mode.

    Lets a run be measured while it trains, and snapshots of a run be measured afterwards.
    """
    tensors, meta = io.load_tensors(path)
    if meta.get("format") != CHECKPOINT_FORMAT:
        raise LasagnaError(f"format is {meta.get('format')!r}; expected {CHECKPOINT_FORMAT!r}", str(path))
    config = PriorTrainConfig.model_validate_json(meta["config"])
    prefix = "ema." if ema and any(k.startswith("ema.") for k in tensors) else "model."
    prior = UNetPrior(config.unet)
    io.load_state_strict(prior, {k[len(prefix):]: v for k, v in tensors.items() if k.startswith(prefix)}, str(path))
    return prior.eval(), int(meta["step"])


def build_parser(p: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    p = p or argparse.ArgumentParser(prog="lasagna train-prior", description=__doc__.splitlines()[0])
    p.add_argument("--task", choices=("relight", "colorize", "light"), default="relight")
    p.add_argument("--out", required=True, help="run folder; run again with the same folder to resume")
    p.add_argument("--resolution", type=int, default=32)
    p.add_argument("--channels", default="32,64,128", help="feature channels per level")
    p.add_argument("--res-blocks", type=int, default=1)
    p.add_argument("--attention", action="store_true")
    p.add_argument("--prediction", choices=("v", "epsilon"), default="v")
    p.add_argument("--steps", type=int, default=100_000, help="upper bound; --minutes usually stops first")
    p.add_argument("--minutes", type=float, default=None, help="time budget of this invocation")
    p.add_argument("--batch-size", type=int, default=64)
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--lr-schedule", choices=("step", "cosine"), default="step",
                   help="step: constant lr (after warm-up); cosine: anneal to 0 over --steps")
    p.add_argument("--init-from", default=None,
                   help="start from this saved prior's weights (its architecture replaces --channels etc.)")
    p.add_argument("--init-labels", choices=("keep", "fresh"), default="keep",
                   help="fresh: --init-from may be a prior of another task with the same conditioning channels; "
                        "its label embedding is replaced (every label starts as its null label)")
    p.add_argument("--warmup", type=int, default=200)
    p.add_argument("--ema", type=float, default=0.999)
    p.add_argument("--ema-warmup", action="store_true",
                   help="ramp the EMA decay as min(ema, (1+step)/(10+step)): for short runs and fine-tunes, whose "
                        "average would otherwise keep 0.999^steps of the starting weights")
    p.add_argument("--grad-clip", type=float, default=1.0)
    p.add_argument("--checkpoint-every", type=int, default=200)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-progress", action="store_true")
    return p


def run(args: argparse.Namespace) -> int:
    channels = tuple(int(c) for c in str(args.channels).split(","))
    unet = unet_config_for(args.task, args.resolution, channels, args.res_blocks, args.attention, args.prediction)
    if args.init_from is not None:
        unet = io.read_config(args.init_from, UNetPrior.FORMAT, UNetConfig)
        want = unet_config_for(args.task)
        if args.init_labels == "fresh":
            if unet.cond_channels != want.cond_channels:
                raise LasagnaError(f"it is a prior with {unet.cond_channels} conditioning channel(s); a {args.task} prior "
                                   f"needs {want.cond_channels}, so its weights cannot start one", "--init-from")
            unet = unet.model_copy(update={"vocabulary": want.vocabulary})
        elif (unet.cond_channels, tuple(unet.vocabulary)) != (want.cond_channels, tuple(want.vocabulary)):
            raise LasagnaError(f"it is a prior with {unet.cond_channels} conditioning channel(s) and labels "
                               f"{', '.join(unet.vocabulary) or '(none)'}; expected a {args.task} prior "
                               f"({want.cond_channels} channel(s), labels {', '.join(want.vocabulary)}; "
                               "--init-labels fresh starts a new vocabulary from it)", "--init-from")
    config = PriorTrainConfig(
        task=args.task, unet=unet, init_from=args.init_from, init_labels=args.init_labels, lr_schedule=args.lr_schedule,
        steps=args.steps, max_minutes=args.minutes, batch_size=args.batch_size, lr=args.lr, warmup_steps=args.warmup,
        ema_decay=args.ema, ema_warmup=args.ema_warmup, grad_clip=args.grad_clip, checkpoint_every=args.checkpoint_every, seed=args.seed,
        progress=not args.no_progress,
    )
    train_prior(config, args.out)
    print(json.dumps({"out": str(Path(args.out) / "prior"), "task": args.task}))
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m lasagna.priors.train …`` is ``lasagna train-prior …``."""
    from lasagna.cli import main as cli_main

    return cli_main(["train-prior", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":
    sys.exit(main())
