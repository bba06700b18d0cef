"""World data for learned layers: base layers, conditions and the true layer, per preset task.

=========  ============================  ======================  ===================================
task       base layer                    condition               true layer (supervised ceiling)
=========  ============================  ======================  ===================================
relight    albedo                        a light direction       shading (1 channel; multiply)
relit      the scene lit by light A      the new light B         the ratio S_B / S_A (1 channel; multiply)
colorize   gray image (Rec. 709 luma)    the preset's label      the colour image with α = 1 (normal)
light      the unlit image               the preset's label      the clipped glow (plus)
=========  ============================  ======================  ===================================

``relit`` is the Lasagna paper's own setting (relighting what is already lit): A is each scene's own
random source light (``lasagna.world.tasks.relight_sources``: any azimuth, elevation in the relight range,
drawn from a stream of its own), B the drawn label.

Scenes come from ``lasagna.world`` (deterministic by split, seed and index); which scenes, and which
label each gets (uniform over the preset's vocabulary), is drawn from the caller's ``rng`` only,
so a batch is a function of its state. Relighting renders each scene under its drawn
label (the world's eight light names must contain the preset's labels); the light task gives each
scene's glow the drawn label's colour (`lasagna.world.lighting.GLOW_VOCABULARY`: warm, cool, white).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from lasagna.document.preset import WORLD_TASKS, WorldTask
from lasagna.errors import LasagnaError

Task = WorldTask  # the world tasks priors and generators are trained on (a preset names its own: Preset.task)
TASKS: tuple[str, ...] = WORLD_TASKS
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
    if task in ("relight", "relit"):
        unknown = sorted(set(labels) - set(VOCABULARY))
        if unknown:
            raise LasagnaError(
                f"labels {unknown} are not light directions of the world; expected labels from {', '.join(VOCABULARY)}",
                "vocabulary",
            )
        scene = generate(split, count, seed, resolution, start=start, labels=labels, shadows=shadows)
        if task == "relit":
            rel = relit(scene)
            return TaskBatch(base=rel.base, labels=labels, target=rel.layer)
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
    raise LasagnaError(f"unknown task {task!r}; expected relight, colorize, light or relit", "task")


def relit(scene):
    """The relit task of world scenes lit by their own labels (B): each lit first by its own source light A
    (``relight_sources``); ``base`` is that, ``target`` the scene under B, ``layer`` the ratio S_B / S_A."""
    from lasagna.world.tasks import relight_sources, relighting

    return relighting(scene, relight_sources(scene.params))
