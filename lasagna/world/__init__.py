"""lasagna.world: procedural scenes with ground truth (albedo, normals, shading, labels, masks).

Textured analytic objects (1–5, occluding each other) before a painted wall that may carry relief,
seen by an orthographic camera and lit by one of eight named directional lights, or any direction
``az=…,el=…`` (the contract in `lasagna.world.lighting`). Paint is independent of geometry: many
texture families — solid patterns, dead leaves, cells, text, photographs — on walls, objects and
flat panels alike. Deterministic by (split, seed, index); vectorised in torch; fast enough to
generate training data on the fly.

    from lasagna.world import generate
    scene = generate("train", count=64, seed=0, resolution=32)
    scene.image, scene.albedo, scene.shading, scene.normals, scene.mask, scene.label

Modules: ``lighting`` (the vocabulary and shading formula), ``shapes``, ``textures`` (with
``paint`` for the 2D painted families and ``noise`` for the lattice hash) and ``relief`` (the
families), ``splits`` (which split uses which families — ``train``/``val``, ``heldout`` for choosing,
``far`` untouched until the final measurement; per-scene random streams), ``params``
(scene parameters and their sampling), ``scene`` (rendering), ``tasks`` (colourisation,
additive-light and relighting data), ``export`` and ``cli`` (stack folders, ``lasagna world``).
"""

from lasagna.world.lighting import (
    AMBIENT,
    GLOW_VOCABULARY,
    LIGHTS,
    VOCABULARY,
    WALL_SHADING,
    condition_direction,
    direction_vector,
    lambert,
    light_vectors,
    named_direction,
    parse_direction,
)
from lasagna.world.params import SceneParams, sample_scenes
from lasagna.world.scene import Scene, batches, generate, relight, render, with_light
from lasagna.world.splits import SPLIT_NAMES, SPLITS
from lasagna.world.tasks import AdditiveLight, Colorization, Relighting, additive_light, colorization, relighting

__all__ = [
    "AMBIENT",
    "GLOW_VOCABULARY",
    "LIGHTS",
    "VOCABULARY",
    "WALL_SHADING",
    "lambert",
    "light_vectors",
    "condition_direction",
    "direction_vector",
    "named_direction",
    "parse_direction",
    "SceneParams",
    "sample_scenes",
    "Scene",
    "batches",
    "generate",
    "relight",
    "render",
    "with_light",
    "SPLIT_NAMES",
    "SPLITS",
    "AdditiveLight",
    "Colorization",
    "additive_light",
    "colorization",
    "Relighting",
    "relighting",
]
