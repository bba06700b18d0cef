"""Training the bundled conditional priors on the procedural world, on this CPU (resumable).

Four tasks, each a ``UNetPrior`` trained with the simple diffusion objective (v-prediction by default)
and classifier-free label dropout, on fresh world batches generated on the fly (no data set on disk):

* ``relight``: x₀ = the lit image (albedo × shading), conditioned ControlNet-style on the albedo
  (3 channels) and on the lighting label (the world's eight named directions);
* ``colorize``: x₀ = the colour image, conditioned on its Rec. 709 luma (1 channel) and the single
  label ``natural``;
* ``light``: x₀ = the image with the world's coloured fill light added (``lasagna.world.tasks``),
  conditioned on the unlit image (3 channels) and the glow's label (warm, cool, white);
* ``relit``: x₀ = the scene lit by the label's light B, conditioned on the same scene lit by its own
  random source light A (3 channels: an already lit image, the Lasagna paper's setting) and on B.

The conditioning image is what Lasagna's base layer will be at distillation time. Every random draw
(which scenes, t, ε, label dropout) comes from the loop's checkpointed ``rng``, so a killed run
resumes bit for bit (``lasagna.training``). Scenes come from one split, ``train`` unless the config names
another (``wide`` adds generic shapes); a held split's benchmark scenes (world seed 0) are refused
(``lasagna.world.splits.check_training_scenes``), and ``val`` stays unseen for evaluation.

The command line is ``lasagna train-prior`` (``lasagna.cli.train_prior``)::

    lasagna train-prior --task relight --out runs/relight-32 --minutes 30
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import torch
from pydantic import ConfigDict, Field

from lasagna.errors import LasagnaError
from lasagna.io.checkpoint import read_config
from lasagna.priors.unet import UNetConfig, UNetPrior
from lasagna.training.loop import LoopConfig, network_from_checkpoint, train_loop
from lasagna.training.tasks import SCENE_RANGE, Task
from lasagna.world.splits import check_training_scenes

CHECKPOINT_FORMAT = "lasagna.prior_checkpoint"


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
    render_on: Literal["device", "cpu"] = Field(
        "device",
        description="where the scenes are rendered: the training device (a GPU renders a batch faster than the "
        "CPU feeds it) or the CPU (the same bits as a CPU run's, whatever the device)",
    )
    init_from: str | None = Field(
        None,
        description="a saved prior (folder) whose weights start this run: "
        "a second training stage, e.g. an lr anneal after a constant-lr run",
    )
    init_labels: Literal["keep", "fresh"] = Field(
        "keep",
        description="keep: init_from has this run's vocabulary; fresh: it may have another (a prior of "
        "another task with the same architecture): every tensor is copied but the label embedding, whose rows "
        "all start as init_from's null label — the new task starts from the old prior's unconditional model",
    )


DIRECTION_TASKS: tuple[str, ...] = ("relight", "relit")
"""Tasks whose label is a light direction, so a prior of them may be conditioned on any direction."""
NAMED_SHARE = 0.5
"""With ``directions``, the share of training samples lit by a named light (the rest: a uniform azimuth and an
elevation in the relight range), so the named lights — what most people ask for — are as well learnt as a
label prior's, and the directions between them are learnt at all (issue #11: within 1 dB of the named)."""


def task_vocabulary(task: Task) -> tuple[str, ...]:
    from lasagna.world import GLOW_VOCABULARY, VOCABULARY

    return {
        "relight": tuple(VOCABULARY),
        "relit": tuple(VOCABULARY),
        "colorize": ("natural",),
        "light": tuple(GLOW_VOCABULARY),
    }[task]


def task_cond_channels(task: Task) -> int:
    return 1 if task == "colorize" else 3


def unet_config_for(
    task: Task,
    resolution: int = 32,
    channels: tuple[int, ...] = (32, 64, 128),
    res_blocks: int = 1,
    attention: bool = False,
    prediction: Literal["epsilon", "v"] = "v",
    directions: bool = False,
) -> UNetConfig:
    """The UNetConfig of a task's prior: image 3 channels, its conditioning channels and vocabulary (and, for
    the light tasks, ``directions``: conditioned on any light direction, not only the named labels)."""
    if directions and task not in DIRECTION_TASKS:
        raise LasagnaError(
            f"the {task} task has no light direction; expected one of {', '.join(DIRECTION_TASKS)}", "--directions"
        )
    return UNetConfig(
        image_channels=3,
        cond_channels=task_cond_channels(task),
        resolution=resolution,
        channels=channels,
        res_blocks=res_blocks,
        attention=attention,
        vocabulary=task_vocabulary(task),
        prediction=prediction,
        directions=directions,
    )


def prior_batch(task: Task, scene) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(x₀ in [0, 1], label index, conditioning image in [0, 1]) of a world ``Scene`` batch for ``task``."""
    from lasagna.world import additive_light, colorization

    if task == "relight":
        return scene.image, scene.label_index.long(), scene.albedo
    if task == "relit":
        from lasagna.training.tasks import relit

        rel = relit(scene)
        return rel.target, scene.label_index.long(), rel.base
    if task == "light":
        add = additive_light(scene)
        return add.lit, scene.params.glow_label.long(), add.base
    col = colorization(scene)
    return col.target, torch.zeros(scene.image.shape[0], dtype=torch.long), col.base[:, :1]


def direction_batch(task: Task, scene, rng: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``prior_batch`` for a prior conditioned on directions: each scene is lit by a named light (its own,
    with probability ``NAMED_SHARE``) or by a random direction, drawn from ``rng``; the labels are (B, 4)
    direction rows (``lasagna.priors.unet.direction_rows``)."""
    from lasagna.document.condition import format_direction
    from lasagna.priors.unet import direction_rows
    from lasagna.world.scene import with_light
    from lasagna.world.tasks import RELIGHT_ELEVATION, relight_sources, relighting

    b = scene.image.shape[0]
    u = torch.rand((b, 3), generator=rng, dtype=torch.float64)
    lo, hi = RELIGHT_ELEVATION
    lights = [
        scene.label[i]
        if float(u[i, 0]) < NAMED_SHARE
        else format_direction(round(360.0 * float(u[i, 1]), 2) % 360.0, round(lo + (hi - lo) * float(u[i, 2]), 2))
        for i in range(b)
    ]
    rows = direction_rows(lights)
    if task == "relit":
        rel = relighting(scene, relight_sources(scene.params), lights)
        return rel.target, rows, rel.base
    lit = with_light(scene, lights)
    return lit.image, rows, scene.albedo


def world_source(
    task: Task,
    resolution: int,
    split: str = "train",
    seed: int = 0,
    shadows: bool = False,
    directions: bool = False,
    device: str | torch.device = "cpu",
):
    """``sample_batch(batch, rng) -> (images, label_idx, cond_image)`` drawing world scenes, rendered on ``device``.

    The data-source signature shared with the corrective's trainer; the scenes drawn depend only on
    ``rng``'s stream.
    """
    from lasagna.world import generate

    def sample_batch(batch: int, rng: torch.Generator):
        start = int(torch.randint(0, SCENE_RANGE, (1,), generator=rng))
        scene = generate(split, batch, seed, resolution, start=start, shadows=shadows, device=device)
        if directions:
            return direction_batch(task, scene, rng)
        return prior_batch(task, scene)

    return sample_batch


def train_prior(config: PriorTrainConfig, out_dir: str | Path, device: str | torch.device | None = "cpu") -> UNetPrior:
    """Train (or resume) the prior in ``out_dir`` on ``device`` (None: CUDA where there is one); the final EMA
    weights go to ``out_dir/prior``."""
    check_training_scenes(config.split, config.world_seed, "world_seed")
    if device is None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    source = world_source(
        config.task,
        config.unet.resolution,
        config.split,
        config.world_seed,
        config.shadows,
        config.unet.directions,
        device=device if config.render_on == "device" else "cpu",
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        prior = UNetPrior(config.unet)
    if config.init_from is not None:
        start = UNetPrior.from_pretrained(config.init_from)
        theirs = start.config
        if config.init_labels == "fresh":
            theirs = theirs.model_copy(update={"vocabulary": config.unet.vocabulary})
        to_directions = config.unet.directions and not theirs.directions
        grown = config.unet.res_blocks > theirs.res_blocks
        theirs = theirs.model_copy(update={"directions": config.unet.directions, "res_blocks": config.unet.res_blocks})
        if theirs != config.unet:
            raise LasagnaError(
                f"its UNet config differs from this run's ({start.config} vs {config.unet})", config.init_from
            )
        state = start.state_dict()
        if grown:  # the blocks init_from lacks keep this run's own initialisation: the identity (see grow_res_blocks)
            state.update({k: v for k, v in prior.state_dict().items() if _added_block(k, start.config.res_blocks)})
        if config.init_labels == "fresh" and not to_directions:
            key = "net.label_emb.weight"
            state[key] = state[key][-1].expand(len(config.unet.vocabulary) + 1, -1).clone()
        if to_directions:  # a label prior starts a direction prior: its null label is the null, the MLP is new
            state["net.null_emb"] = state.pop("net.label_emb.weight")[-1].clone()
            state.update({k: v for k, v in prior.state_dict().items() if k.startswith("net.dir_mlp.")})
        prior.load_state_dict(state)

    def step_fn(net: UNetPrior, rng: torch.Generator, step: int):
        images, labels, cond = source(config.batch_size, rng)
        loss = net.training_loss(
            net.encode(images.to(device)), labels.to(device), cond.to(device), rng, config.p_uncond
        )
        return loss, {}

    done = train_loop(
        prior,
        step_fn,
        config,
        config,
        out_dir,
        checkpoint_format=CHECKPOINT_FORMAT,
        desc=f"prior:{config.task}",
        device=device,
    )
    final: UNetPrior = done.model  # type: ignore[assignment]
    final.save_pretrained(Path(out_dir) / "prior")
    return final


def _added_block(key: str, res_blocks: int) -> bool:
    """Whether a state-dict key belongs to a residual block at index ≥ ``res_blocks`` of a level (a grown one)."""
    parts = key.split(".")
    return len(parts) > 4 and parts[1] in ("down", "up") and parts[3] == "blocks" and int(parts[4]) >= res_blocks


def prior_from_checkpoint(path: str | Path, ema: bool = True) -> tuple[UNetPrior, int]:
    """(prior, step) from a training checkpoint: its EMA weights (or the raw ones), in eval mode.

    Lets a run be measured while it trains, and snapshots of a run be measured afterwards.
    """
    prior, step, _ = network_from_checkpoint(
        path, CHECKPOINT_FORMAT, PriorTrainConfig, lambda c: UNetPrior(c.unet), ema
    )
    return prior, step


def run_unet_config(
    task: Task,
    unet: UNetConfig,
    init_from: str | None,
    init_labels: Literal["keep", "fresh"],
    grow_res_blocks: int | None = None,
) -> UNetConfig:
    """The UNet config of a run: ``unet``, or with ``init_from`` that prior's own architecture — checked to
    be a ``task`` prior (or, with ``init_labels="fresh"``, one with the same conditioning channels, given
    ``task``'s vocabulary).

    ``grow_res_blocks`` (with ``init_from``): the run's prior has that many residual blocks per level, at least
    init_from's. The added blocks are ``ResBlock``s whose last convolution starts at zero, i.e. the identity,
    and the skips are taken after a level's last block, so the grown prior starts computing exactly what
    init_from computes — function-preserving growth (Net2Net's deeper network, Chen, Goodfellow & Shlens 2016)
    — and training then has the added capacity to use.
    """
    if init_from is None:
        if grow_res_blocks is not None:
            raise LasagnaError("it grows a saved prior; give --init-from too", "--grow-res-blocks")
        return unet
    directions = unet.directions
    unet = read_config(init_from, UNetPrior.FORMAT, UNetConfig).model_copy(update={"directions": directions})
    if grow_res_blocks is not None:
        if grow_res_blocks < unet.res_blocks:
            raise LasagnaError(
                f"{grow_res_blocks} residual blocks per level is fewer than the {unet.res_blocks} of {init_from}; "
                "expected at least as many (a prior is grown, never cut)",
                "--grow-res-blocks",
            )
        unet = UNetConfig.model_validate({**unet.model_dump(), "res_blocks": grow_res_blocks})
    want = unet_config_for(task)
    if init_labels == "fresh":
        if unet.cond_channels != want.cond_channels:
            raise LasagnaError(
                f"it is a prior with {unet.cond_channels} conditioning channel(s); a {task} prior "
                f"needs {want.cond_channels}, so its weights cannot start one",
                "--init-from",
            )
        return unet.model_copy(update={"vocabulary": want.vocabulary})
    if (unet.cond_channels, tuple(unet.vocabulary)) != (want.cond_channels, tuple(want.vocabulary)):
        raise LasagnaError(
            f"it is a prior with {unet.cond_channels} conditioning channel(s) and labels "
            f"{', '.join(unet.vocabulary) or '(none)'}; expected a {task} prior "
            f"({want.cond_channels} channel(s), labels {', '.join(want.vocabulary)}; "
            "--init-labels fresh starts a new vocabulary from it)",
            "--init-from",
        )
    return unet
