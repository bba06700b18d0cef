"""World data for learned layers: base layers, conditions and the true layer, per preset task.

=========  ============================  ======================  ===================================
task       base layer                    condition               true layer (supervised ceiling)
=========  ============================  ======================  ===================================
relight    albedo                        a light direction       shading (1 channel; multiply)
colorize   gray image (Rec. 709 luma)    the preset's label      the colour image with α = 1 (normal)
light      the unlit image               the preset's label      the clipped glow (plus)
=========  ============================  ======================  ===================================

Scenes come from ``lasagna.world`` (deterministic by split, seed and index); which scenes, and which
label each gets (uniform over the preset's vocabulary), is drawn from the caller's ``rng`` only,
so a batch is a function of its state. Relighting renders each scene under its drawn
label (the world's eight light names must contain the preset's labels); the light task gives each
scene's glow the drawn label's colour (`lasagna.world.lighting.GLOW_VOCABULARY`: warm, cool, white).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, get_args

import torch
from torch import Tensor

from lasagna.errors import LasagnaError

Task = Literal["relight", "colorize", "light"]  # the world tasks priors and generators are trained on
TASKS: tuple[str, ...] = get_args(Task)
TASK_FOR_BLEND = {"multiply": "relight", "normal": "colorize", "plus": "light"}
# The world's scene-index range batches are drawn from (the prior trainer's too): large enough that no batch
# repeats in any run this CPU can afford (2**30 scenes), small enough for int32 seeds.
SCENE_RANGE = 2**30


@dataclass
class TaskBatch:
    """base (B, 3, H, W) in [0, 1], one label per sample, target (B, C, H, W): the true layer."""

    base: Tensor
    labels: list[str]
    target: Tensor


def task_batch(
    task: Task,
    vocabulary: Sequence[str],
    count: int,
    rng: torch.Generator,
    *,
    split: str = "train",
    seed: int = 0,
    resolution: int = 32,
    shadows: bool = False,
) -> TaskBatch:
    """``count`` scenes of ``split`` as a (base, labels, true layer) batch for ``task`` (module docstring)."""
    from lasagna.world import GLOW_VOCABULARY, VOCABULARY, additive_light, colorization, generate

    start = int(torch.randint(0, SCENE_RANGE, (1,), generator=rng))
    idx = torch.randint(0, len(vocabulary), (count,), generator=rng).tolist()
    labels = [vocabulary[i] for i in idx]
    if task == "relight":
        unknown = sorted(set(labels) - set(VOCABULARY))
        if unknown:
            raise LasagnaError(
                f"labels {unknown} are not light directions of the world; expected labels from {', '.join(VOCABULARY)}",
                "vocabulary",
            )
        scene = generate(split, count, seed, resolution, start=start, labels=labels, shadows=shadows)
        return TaskBatch(base=scene.albedo, labels=labels, target=scene.shading)
    scene = generate(split, count, seed, resolution, start=start, shadows=shadows)
    if task == "colorize":
        col = colorization(scene)
        return TaskBatch(base=col.base, labels=labels, target=col.layer)
    if task == "light":
        unknown = sorted(set(labels) - set(GLOW_VOCABULARY))
        if unknown:
            raise LasagnaError(
                f"labels {unknown} are not glow colours of the world; expected labels from "
                f"{', '.join(GLOW_VOCABULARY)}",
                "vocabulary",
            )
        add = additive_light(scene, labels)
        return TaskBatch(base=add.base, labels=labels, target=add.glow)
    raise LasagnaError(f"unknown task {task!r}; expected relight, colorize or light", "task")
