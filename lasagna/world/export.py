"""Writing world scenes as ground-truth layer-stack folders (the world dogfoods the document model).

``write_world_stacks`` renders scenes ``start … start + count − 1`` of a split and writes one stack
folder per scene, ``<out>/<split>-s<seed>-<index:06d>/``, plus ``<out>/world.json`` listing them.
Every stack uses ``blend_space: "srgb"`` (the world is defined on stored values, see
`lasagna.world.lighting`) and ``clamp: "layer"``; its layers, by task:

=========  ===========================================  =====================================
task       layers (bottom first)                         composite.png
=========  ===========================================  =====================================
shading    ``albedo`` pixels; ``shading`` multiply,      image = albedo × shading
           1 channel, range [0, 2]
color      ``gray`` pixels (Rec. 709 luma, 1 channel);   the colour image
           ``color`` normal (alpha-linear), RGBA, α = 1
light      ``image`` pixels (the unlit image);           lit = image + glow
           ``light`` plus, RGB (the glow)
relight    ``image`` pixels (the scene lit by A);        the scene lit by B (= the shading
           ``relight`` multiply, 1 channel, range        task's composite)
           [0, 4] (the ratio S_B / S_A)
=========  ===========================================  =====================================

The relight task (`lasagna.world.tasks`, "Relighting"): B is the scene's own named light and A a
continuous direction from the scene's ``"relight"`` stream; its condition is B, and the metadata
adds ``source_condition`` (A as ``az=…,el=…``) and ``source_light`` (A's vector). It needs
ambient ≥ 0.25 so that the ratio's range [a, 1/a] fits [0, 4].

Every layer PNG is 16-bit, so the engine's re-composite equals ``composite.png`` (8-bit, the
rendered float image rounded once) to within one 8-bit step. Beside the stack, not in its layer
list: ``normals.png`` (16-bit RGB, n = 2v − 1, camera frame) and ``mask.png`` (8-bit gray, 255 on
object pixels). ``metadata["lasagna.world"]`` holds the label, the light vector, the task, the
``condition`` its learned layer answers to (the light direction for shading, ``natural`` for colour,
the glow's label — warm, cool, white — for light, B's light for relight), the files, and the scene's full parameters
(``SceneParams.describe``), enough to re-render it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Literal

import torch

from lasagna.atomic import atomic_write_text
from lasagna.errors import LasagnaError, PathError
from lasagna.world.lighting import AMBIENT, GLOW_VOCABULARY, LIGHTS, VOCABULARY
from lasagna.world.names import TASKS
from lasagna.world.scene import Scene, generate
from lasagna.world.splits import STREAM_VERSION
from lasagna.world.tasks import RELIGHT_RANGE, additive_light, colorization, luma, relight_sources, relighting

Task = Literal["shading", "color", "light", "relight"]
MANIFEST = "world.json"
# Scenes rendered per batch while writing: large enough to amortise the renderer's per-call cost,
# small enough to keep memory flat at 256² and above.
_RENDER_BATCH = 16


def scene_folder_name(split: str, seed: int, index: int) -> str:
    return f"{split}-s{seed}-{index:06d}"


def _layers(task: str, scene: Scene, i: int) -> tuple[list[dict[str, Any]], torch.Tensor]:
    """The stack's layer specs (for ``stack_from_tensors``) and its composite, for scene ``i``."""
    if task == "shading":
        return [
            dict(id="albedo", name="Albedo", image=scene.albedo[i], bit_depth=16),
            dict(
                id="shading", name="Shading", image=scene.shading[i], blend="multiply", range=(0.0, 2.0), bit_depth=16
            ),
        ], scene.image[i]
    if task == "color":
        data = colorization(scene.select(i))
        return [
            dict(id="gray", name="Grayscale", image=luma(scene.image[i : i + 1])[0], bit_depth=16),
            dict(id="color", name="Colour", image=data.layer[0], blend="normal", bit_depth=16),
        ], data.target[0]
    if task == "relight":
        one = scene.select(i)
        data = relighting(one, relight_sources(one.params))
        # S_B ≤ 1 in real arithmetic, so the ratio ≤ 1/a ≤ 4; float32 rounding of n·l can lift it by ~1e-7,
        # which the clamp removes (the 16-bit code step is 6e-5).
        ratio = data.layer[0].clamp(*RELIGHT_RANGE)
        return [
            dict(id="image", name="Image (light A)", image=data.base[0], bit_depth=16),
            dict(id="relight", name="Relight", image=ratio, blend="multiply", range=RELIGHT_RANGE, bit_depth=16),
        ], data.target[0]
    data = additive_light(scene.select(i))
    return [
        dict(id="image", name="Image", image=data.base[0], bit_depth=16),
        dict(id="light", name="Light", image=data.glow[0], blend="plus", bit_depth=16),
    ], data.lit[0]


def task_condition(task: str, scene: Scene, i: int) -> str:
    """The label scene ``i``'s learned layer of ``task`` is conditioned on (its preset's vocabulary)."""
    if task in ("shading", "relight"):
        return scene.label[i]
    if task == "color":
        return "natural"
    return GLOW_VOCABULARY[int(scene.params.glow_label[i])]


def _check_task(task: str, ambient: float) -> None:
    if task not in TASKS:
        raise LasagnaError(f"unknown task {task!r}; expected one of {', '.join(TASKS)}", where="task")
    if task == "relight" and not ambient >= 1.0 / RELIGHT_RANGE[1]:
        raise LasagnaError(
            f"the relight ratio lies in [a, 1/a], which fits its range [0, {RELIGHT_RANGE[1]:g}] only for "
            f"ambient ≥ {1.0 / RELIGHT_RANGE[1]:g}; got {ambient}",
            where="ambient",
        )


def write_scene_stack(folder: str | os.PathLike, scene: Scene, i: int, task: Task = "shading") -> Path:
    """Write scene ``i`` of a rendered batch as a stack folder; returns the folder."""
    from lasagna.io.png import write_png
    from lasagna.io.render import write_composite
    from lasagna.io.stack import save_stack, stack_from_tensors

    _check_task(task, scene.ambient)
    folder = Path(folder)
    layers, composite = _layers(task, scene, i)
    p = scene.params
    meta = {
        "lasagna.world": {
            "stream_version": STREAM_VERSION,
            "task": task,
            "split": p.split,
            "seed": p.seed,
            "index": int(p.index[i]),
            "label": scene.label[i],
            "condition": task_condition(task, scene, i),
            "light": list(LIGHTS[scene.label[i]]),  # the contract's exact vector, not its float32 copy
            "ambient": scene.ambient,
            "shadows": scene.shadows,
            "blend_space_note": "image = albedo × shading on stored (sRGB-encoded) values",
            "files": {
                "normals": "normals.png",
                "normals_encoding": "n = 2*v - 1, 16-bit RGB, camera frame (x right, y up, z toward the viewer)",
                "mask": "mask.png",
            },
            "scene": p.describe(i),
        }
    }
    if task == "relight":
        from lasagna.world.lighting import condition_direction

        (source,) = relight_sources(p.select([i]))
        meta["lasagna.world"]["source_condition"] = source
        meta["lasagna.world"]["source_light"] = list(condition_direction(source))
    stack = stack_from_tensors(layers, blend_space="srgb", clamp="layer", metadata=meta)
    save_stack(stack, folder)
    # Normals are unit vectors, so (n + 1)/2 is in [0, 1] up to float rounding of the last bit.
    write_png(folder / "normals.png", ((scene.normals[i] + 1.0) * 0.5).clamp(0.0, 1.0), bit_depth=16)
    write_png(folder / "mask.png", scene.mask[i], bit_depth=8)
    write_composite(composite, folder / "composite.png")
    return folder


def write_world_stacks(
    out_dir: str | os.PathLike,
    split: str,
    count: int,
    seed: int = 0,
    resolution: int = 64,
    task: Task = "shading",
    *,
    start: int = 0,
    shadows: bool = False,
    ambient: float = AMBIENT,
    progress: bool = False,
) -> list[Path]:
    """Write ``count`` scenes of ``split`` as stack folders under ``out_dir``, and ``world.json``."""
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise LasagnaError(f"expected a positive integer, got {count!r}", where="count")
    _check_task(task, ambient)
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise PathError("exists and is not a folder; expected a folder to write into", where=str(out))
    folders: list[Path] = []
    labels: list[str] = []
    conditions: list[str] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=count, unit="scene", desc=f"world {split}")
    for first in range(start, start + count, _RENDER_BATCH):
        n = min(_RENDER_BATCH, start + count - first)
        # Rendered in float64: float32's relief gradients differ between CPUs' vector maths by up to ~2e-4
        # (tests/world/test_scene.py), a few 16-bit codes; float64's by ~1e-15, so the files are the same bits on
        # every machine (the demo renders examples/world itself outside a checkout and must match it).
        scene = generate(split, n, seed, resolution, start=first, shadows=shadows, ambient=ambient, dtype=torch.float64)
        for i in range(n):
            name = scene_folder_name(split, seed, first + i)
            folders.append(write_scene_stack(out / name, scene, i, task))
            labels.append(scene.label[i])
            conditions.append(task_condition(task, scene, i))
            if bar is not None:
                bar.update(1)
    if bar is not None:
        bar.close()
    manifest = {
        "format": "lasagna.world",
        "stream_version": STREAM_VERSION,
        "split": split,
        "seed": seed,
        "start": start,
        "count": count,
        "resolution": resolution,
        "task": task,
        "shadows": bool(shadows),
        "ambient": float(ambient),
        "vocabulary": list(VOCABULARY),
        "scenes": [{"folder": f.name, "label": lab, "condition": c} for f, lab, c in zip(folders, labels, conditions)],
    }
    atomic_write_text(out / MANIFEST, json.dumps(manifest, indent=2) + "\n")
    return folders
