"""Amortised distillation: one ``LayerGenerator`` for every base image (LMC-SDS Sec. 5.2, Lasagna's G(θ)).

    config = AmortisedConfig(generator=LayerGeneratorConfig.for_preset(preset), prior="runs/relight-32/prior",
                             corrective="runs/relight-32-bhat/corrective", steps=3000, max_minutes=30)
    result = train_layer_generator(config, "runs/shading-gen")      # resumable: run again to continue

Each step draws world scenes (``lasagna.training.tasks.task_batch``: the base layer of the preset's task and a label
from the vocabulary), runs the generator, and minimises ``objective.ScoreObjective`` — LMC-SDS by
default, with the LMC-SDS network recipe's cosine schedule: the score weight rises 0.1 → 1 and the
L2 to the input falls 1 → 0.1 over ``weights``' ramp ("let the network first focus on reconstructing
the original image and then on edits"; the paper ramps over 20 K of 200 K steps). At inference one
forward pass edits an unseen image.

``supervised=True`` trains the same generator, with the same loop and budget, on the world's true
layer (mean squared error to the true shading, colour+α or glow): the *supervised ceiling* reported
beside every distilled number. No prior is needed then.

The loop is ``lasagna.training.loop.train_loop``: progress bar, EMA, atomic checkpoints, resume after a
kill (the same folder continues bit for bit), time budget, seed; ``train_config.json`` (this config)
beside the checkpoint. The final generator (EMA weights when enabled) is saved to ``out/generator``
and its error on ``eval_count`` scenes of ``eval_split`` to ``out/metrics.json``.

**Scale-out.** Unchanged under ``torchrun --nproc_per_node=N`` (DistributedDataParallel: gloo on
CPU, nccl on GPU; ``train_loop`` wraps the model). The global batch of ``batch_size`` is cut into
chunks of ``micro_batch``; every chunk has its own random stream (its scenes, labels, t, ε), seeded
from the shared generator, and each process takes a contiguous share of the chunks. The loss is
the mean over chunks, so DDP's gradient average over processes equals the one-process gradient:
runs with the same ``micro_batch`` and seed agree across process counts (within float rounding).
``micro_batch=None`` means ``batch_size`` / processes (runs then differ across process counts in
their random draws, not in their statistics). Only rank 0 writes files.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import torch
import torch.nn.functional as F
from pydantic import ConfigDict, Field, model_validator

from lasagna.atomic import atomic_write_text
from lasagna.distill.objective import ConditionImage, ScoreObjective, build_loss
from lasagna.distill.schedules import Weights
from lasagna.distill.settings import LossName
from lasagna.errors import LasagnaError
from lasagna.generators.layer import composite
from lasagna.generators.unet import LayerGenerator, LayerGeneratorConfig
from lasagna.priors.base import Prior
from lasagna.training.loop import LoopConfig, dist_info, init_distributed, shutdown_distributed, train_loop
from lasagna.training.tasks import Task, task_batch

CHECKPOINT_FORMAT = "lasagna.layer_generator_checkpoint"
_EVAL_SEED_OFFSET = 1_000_003  # the evaluation scenes come from their own rng, never the training one


class AmortisedConfig(LoopConfig):
    """How a layer generator is trained (saved as train_config.json and inside every checkpoint); the
    loop's settings (steps, lr, EMA, grad_clip, checkpoints, time budget, seed) come from ``LoopConfig``."""

    model_config = ConfigDict(extra="forbid")

    generator: LayerGeneratorConfig
    task: Task = Field("relight", description="World data: relight (albedo → shading), colorize, light.")
    prior: str | None = Field(
        None,
        description="The prior: a catalogue name (relight-32) or a folder (a path with '/'); "
        "None = passed to train_layer_generator.",
    )
    corrective: str | None = Field(
        None, description="The LMC-SDS corrective b̂ (loss lmc-sds): a catalogue name or a folder (a path with '/')."
    )
    supervised: bool = Field(False, description="Train on the true layer (MSE) instead of the prior: the ceiling.")
    loss: LossName = "lmc-sds"
    loss_options: dict[str, Any] = Field(default_factory=dict)
    guidance: float = Field(1.0, gt=0.0)
    t_min: float = Field(0.02, ge=0.0, le=1.0)
    t_max: float = Field(0.98, ge=0.0, le=1.0)
    weights: Weights = Weights.lmc_network(500)
    condition_image: ConditionImage = "auto"
    lr: float = Field(1e-3, gt=0.0)
    batch_size: int = Field(32, ge=1, description="The global batch (over all processes).")
    micro_batch: int | None = Field(
        None, ge=1, description="Chunk size with its own random stream; None = batch/processes."
    )
    resolution: int = Field(32, ge=1, description="World scenes are rendered at this size.")
    split: str = "train"
    world_seed: int = 0
    shadows: bool = False
    eval_split: str = "val"
    eval_count: int = Field(64, ge=0, description="Scenes for metrics.json (0: none).")

    @model_validator(mode="after")
    def _check(self) -> AmortisedConfig:
        if self.t_min > self.t_max:
            raise ValueError(f"t_min {self.t_min} > t_max {self.t_max}; expected t_min <= t_max")
        if self.micro_batch is not None and self.batch_size % self.micro_batch:
            raise ValueError(f"batch_size {self.batch_size} is not a multiple of micro_batch {self.micro_batch}")
        return self


@dataclass
class AmortisedResult:
    generator: LayerGenerator  # final weights (EMA when enabled), eval mode
    step: int
    stopped: Literal["done", "time"]
    metrics: dict[str, Any]


def chunking(config: AmortisedConfig, world_size: int) -> tuple[int, int]:
    """(micro batch, number of chunks) of the global batch; the chunks must split evenly over processes."""
    micro = config.micro_batch if config.micro_batch is not None else config.batch_size // world_size
    if micro < 1 or config.batch_size % micro:
        raise LasagnaError(
            f"batch_size {config.batch_size} cannot be cut into chunks for {world_size} processes; "
            "expected batch_size divisible by the number of processes",
            "batch_size",
        )
    chunks = config.batch_size // micro
    if chunks % world_size:
        raise LasagnaError(
            f"{chunks} chunks of {micro} do not split over {world_size} processes; expected micro_batch "
            f"dividing batch_size / processes (e.g. {config.batch_size // world_size})",
            "micro_batch",
        )
    return micro, chunks


def train_layer_generator(
    config: AmortisedConfig,
    out_dir: str | Path,
    *,
    prior: Prior | None = None,
    corrective=None,
    device: str | torch.device | None = None,
) -> AmortisedResult:
    """Train (or resume training) the generator in ``out_dir``; see the module docstring."""
    info = init_distributed(device)
    try:
        return _train(config, Path(out_dir), prior, corrective, device)
    finally:
        shutdown_distributed(info)


def _train(cfg: AmortisedConfig, out: Path, prior: Prior | None, corrective, device) -> AmortisedResult:
    info = dist_info()
    if device is None:
        device = f"cuda:{info.local_rank}" if torch.cuda.is_available() else "cpu"
    device = torch.device(device)
    objective = None
    if not cfg.supervised:
        prior = prior if prior is not None else _load_prior(cfg.prior, device)
        if cfg.loss == "lmc-sds" and corrective is None:
            corrective = _load_corrective(cfg.corrective, device)
        loss = build_loss(cfg.loss, corrective, cfg.loss_options, cfg.t_min, cfg.t_max)
        objective = ScoreObjective(cfg.generator.layer, prior, loss, cfg.guidance, cfg.weights, cfg.condition_image)
    micro, chunks = chunking(cfg, info.world_size)
    mine = range(info.rank * chunks // info.world_size, (info.rank + 1) * chunks // info.world_size)
    vocab = cfg.generator.vocabulary

    with torch.random.fork_rng(devices=[]):  # a seeded initialisation without touching the global RNG
        torch.manual_seed(cfg.seed)
        model = LayerGenerator(cfg.generator)

    def step_fn(net: torch.nn.Module, rng: torch.Generator, step: int) -> tuple[torch.Tensor, dict[str, float]]:
        seeds = torch.randint(0, 2**62, (chunks,), generator=rng)  # every process draws all: streams stay in step
        rngs = [torch.Generator().manual_seed(int(seeds[k])) for k in mine]
        data = [
            task_batch(
                cfg.task,
                vocab,
                micro,
                r,
                split=cfg.split,
                seed=cfg.world_seed,
                resolution=cfg.resolution,
                shadows=cfg.shadows,
            )
            for r in rngs
        ]
        base = torch.cat([d.base for d in data]).to(device)
        labels = [lab for d in data for lab in d.labels]
        layer = net(base, labels)  # one forward through the (DDP) wrapper
        losses, parts = [], []
        for j, (r, d) in enumerate(zip(rngs, data)):
            sl = slice(j * micro, (j + 1) * micro)
            if objective is None:
                losses.append(F.mse_loss(layer[sl], d.target.to(device)))
                parts.append({"mse": float(losses[-1].detach())})
            else:
                o = objective(base[sl], layer[sl], d.labels, rng=r, step=step)
                losses.append(o.total)
                parts.append({k: v for k, v in o.summary().items() if k != "total"})
        metrics = {k: sum(p[k] for p in parts) / len(parts) for k in parts[0]}
        return torch.stack(losses).mean(), metrics

    done = train_loop(
        model,
        step_fn,
        cfg,
        cfg,
        out,
        checkpoint_format=CHECKPOINT_FORMAT,
        desc="generator:supervised" if cfg.supervised else f"generator:{cfg.loss}",
        device=device,
    )
    final: LayerGenerator = done.model  # type: ignore[assignment]
    metrics: dict[str, Any] = {
        "step": done.step,
        "stopped": done.stopped,
        "supervised": cfg.supervised,
        "processes": info.world_size,
    }
    if info.is_main:
        final.save_pretrained(out / "generator")
        if cfg.eval_count:
            metrics.update(evaluate(final, cfg, device))
        atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    if info.world_size > 1:
        torch.distributed.barrier()
    return AmortisedResult(generator=final, step=done.step, stopped=done.stopped, metrics=metrics)


@torch.no_grad()
def evaluate(generator: LayerGenerator, cfg: AmortisedConfig, device: torch.device) -> dict[str, float]:
    """Layer and composite error of one forward pass on ``eval_count`` scenes of ``eval_split``, beside
    the identity edit's (PSNR with peak 1, over all pixels)."""
    rng = torch.Generator().manual_seed(cfg.seed + _EVAL_SEED_OFFSET)
    d = task_batch(
        cfg.task,
        cfg.generator.vocabulary,
        cfg.eval_count,
        rng,
        split=cfg.eval_split,
        seed=cfg.world_seed,
        resolution=cfg.resolution,
        shadows=cfg.shadows,
    )
    base, target = d.base.to(device), d.target.to(device)
    spec = generator.spec
    layer = generator.to(device)(base, d.labels)
    identity = spec.identity_layer(*base.shape[:1], *base.shape[2:], dtype=base.dtype, device=device)
    truth = composite(base, target, spec)
    out = {}
    for name, y in (("layer", layer), ("identity", identity)):
        mse = float((y - target).pow(2).mean())
        cmse = float((composite(base, y, spec).clamp(0, 1) - truth.clamp(0, 1)).pow(2).mean())
        out[f"{name}_mse"] = mse
        out[f"{name}_psnr"] = _psnr(mse)
        out[f"{name}_composite_psnr"] = _psnr(cmse)
    return out


def _psnr(mse: float) -> float | None:
    from lasagna.priors.evaluate import psnr_db

    return None if mse <= 0 else float(psnr_db(mse, floor=0.0))  # strict JSON has no infinity


def _load_prior(path: str | None, device: torch.device) -> Prior:
    if path is None:
        raise LasagnaError(
            "no prior: pass prior= or set config.prior to a catalogue name or a folder (or set supervised=true)",
            "prior",
        )
    from lasagna.catalogue import load_prior  # a name as `lasagna train-layer` takes it, or a folder

    return load_prior(path, device=device)


def _load_corrective(path: str | None, device: torch.device):
    if path is None:
        raise LasagnaError(
            "loss 'lmc-sds' needs the corrective b̂: pass corrective= or set config.corrective to its name or folder",
            "corrective",
        )
    from lasagna.catalogue import load_corrective  # a network or a spectral b̂, by its config's format

    return load_corrective(path, device=device)
