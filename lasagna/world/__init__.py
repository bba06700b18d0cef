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
additive-light and relighting data), ``export`` and ``cli`` (stack folders, ``lasagna world``), ``names``
(the split and task names, torch-free: a command's arguments need them before anything renders).
"""

import importlib

# Where each public name lives. The package is lazy (PEP 562's module ``__getattr__``): importing
# ``lasagna.world.names`` — what a command's arguments need — must not load torch, which the renderer's
# modules import, so a mistyped ``lasagna world`` is answered in a fraction of a second.
_HOMES = {
    "lasagna.world.lighting": (
        "AMBIENT",
        "GLOW_VOCABULARY",
        "LIGHTS",
        "VOCABULARY",
        "WALL_SHADING",
        "condition_direction",
        "direction_vector",
        "lambert",
        "light_vectors",
        "named_direction",
        "parse_direction",
    ),
    "lasagna.world.params": ("SceneParams", "sample_scenes"),
    "lasagna.world.scene": ("Scene", "batches", "generate", "relight", "render", "with_light"),
    "lasagna.world.names": ("SPLIT_NAMES",),
    "lasagna.world.splits": ("SPLITS",),
    "lasagna.world.tasks": (
        "AdditiveLight",
        "Colorization",
        "Relighting",
        "additive_light",
        "colorization",
        "relighting",
    ),
}
_HOME_OF = {name: module for module, names in _HOMES.items() for name in names}


def __getattr__(name: str):
    """Import a public name's module on first use (PEP 562)."""
    try:
        module = _HOME_OF[name]
    except KeyError:
        raise AttributeError(f"module 'lasagna.world' has no attribute {name!r}") from None
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_HOME_OF])


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
