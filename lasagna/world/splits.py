"""The named splits of the world and the random stream of every scene.

Each split names the families its scenes draw from. ``train`` is broad on purpose — many painted
texture families laid on walls and objects independently of their geometry, flat textured panels,
relief that is not in the paint, up to five objects that occlude each other — so that a model
trained on it learns that texture is not geometry. ``val`` shares ``train``'s families (other
scenes). ``heldout`` (unchanged since the first world, bit for bit), ``far`` and ``select`` use only
families ``train`` never uses, and no two of them share one, checked at import. The rule for learned
layers: every default, hyper-parameter and stopping rule is chosen on ``select``; ``heldout`` (training's
shape of world, other families) is reported, never chosen on; ``far`` is touched only by the final
measurement.

=========  ===========================  ==================================  ===================  ==============
split      shapes (objects per scene)   object textures                     wall textures        wall relief
=========  ===========================  ==================================  ===================  ==============
train/val  ellipsoid, box, cylinder,    stripes, checker, noise, tiles,     the same 9           bumps,
           roundbox, panel (1–5)        deadleaves, cells, gradient,                             grooves
                                        glyphs, photo                                            (p = 0.25)
heldout    torus, capsule, cone (1–3)   dots, marble, rings                 bricks, dots         none
far        octahedron, hexprism,        hexagons, zigzag, naturephoto       hexagons, zigzag,    bevels
           triprism (1–5)                                                   naturephoto          (p = 0.25)
select     pyramid, bicone, lens (1–5)  plaid, scales, weave                the same 3           ripples
                                                                                                 (p = 0.25)
wide       train's 5 + gem, blob (1–5)  train's 9                           train's 9            train's
=========  ===========================  ==================================  ===================  ==============

``wide`` is for training only: ``train``'s families and two generic ones, ``gem`` (a random faceted crystal: a
cube's faces tilted and moved, four alternate corners cut) and ``blob`` (three spheres smoothly joined), whose
codes draw a new shape for every object instead of one shape at new sizes. They are cousins of no held family in
particular (the gem cuts only four corners, never an octahedron's eight; it has no apex, no prism axis), so an
estimator trained on ``wide`` meets faceted and organic shapes without meeting any held family.

In train/val, far and select half of the surfaces are painted between two free colours (``two_tone``), the
rest in one colour and its shade, as every surface of heldout.

Scene ``index`` of split ``split`` under ``seed`` is drawn from its own counter-based generator
(NumPy's Philox, whose output is specified bit for bit across platforms) keyed by a BLAKE2b hash of
``(split, seed, index)``. So any scene can be regenerated alone, a batch is the same scenes whatever
its size, and two splits (or two seeds) never share a random stream: their scenes are distinct with
probability 1 (the parameters are continuous), and ``heldout`` and ``far`` differ in families besides.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from lasagna.errors import LasagnaError
from lasagna.world.names import SPLIT_NAMES
from lasagna.world.relief import RELIEFS
from lasagna.world.shapes import SHAPES
from lasagna.world.textures import TEXTURES

MAX_OBJECTS = 5
"""Object slots per scene (the first world had 3; ``heldout`` still draws 1–3)."""
WORLD_VERSION = 4
"""The families and layout: 1 was the first world (train: 3 shapes, 3 + 2 textures); 2 broadened train/val
and added ``far``; 3 added ``select`` (new families appended to the registries, so every scene of 2 is unchanged);
4 added the training-only ``wide`` (two generic shapes appended; every earlier scene unchanged).
``heldout``'s scenes are bit-identical in all (new draws are appended to its stream)."""


@dataclass(frozen=True)
class Split:
    """The families one split draws from (each a non-empty tuple of registered names), and how.

    ``objects`` is the (min, max) object count; ``object_floor`` and ``wall_floor`` the ranges of the
    texture's contrast floor lo; ``two_tone`` the probability that a surface's paint runs between
    two free colours instead of one colour and its shade; ``relief_probability`` that the wall
    carries relief of one of ``reliefs``.
    """

    name: str
    shapes: tuple[str, ...]
    object_textures: tuple[str, ...]
    wall_textures: tuple[str, ...]
    objects: tuple[int, int] = (1, 3)
    object_floor: tuple[float, float] = (0.2, 0.55)
    wall_floor: tuple[float, float] = (0.45, 0.75)
    two_tone: float = 0.0
    reliefs: tuple[str, ...] = ()
    relief_probability: float = 0.0

    @property
    def textures(self) -> frozenset[str]:
        return frozenset(self.object_textures) | frozenset(self.wall_textures)


_PAINT = ("stripes", "checker", "noise", "tiles", "deadleaves", "cells", "gradient", "glyphs", "photo")
_BROAD = dict(objects=(1, 5), object_floor=(0.0, 0.7), wall_floor=(0.1, 0.85), two_tone=0.5, relief_probability=0.25)
_TRAIN_FAMILIES = dict(
    shapes=("ellipsoid", "box", "cylinder", "roundbox", "panel"),
    object_textures=_PAINT,
    wall_textures=_PAINT,
    reliefs=("bumps", "grooves"),
    **_BROAD,
)

SPLITS: dict[str, Split] = {
    "train": Split("train", **_TRAIN_FAMILIES),
    "val": Split("val", **_TRAIN_FAMILIES),
    "heldout": Split(
        "heldout",
        shapes=("torus", "capsule", "cone"),
        object_textures=("dots", "marble", "rings"),
        wall_textures=("bricks", "dots"),
    ),
    "far": Split(
        "far",
        shapes=("octahedron", "hexprism", "triprism"),
        object_textures=("hexagons", "zigzag", "naturephoto"),
        wall_textures=("hexagons", "zigzag", "naturephoto"),
        reliefs=("bevels",),
        **_BROAD,
    ),
    # Where every choice of a learned layer is made: families that neither train nor far (nor heldout) use,
    # drawn as broadly as train and far, so a choice made here is a choice made off-family.
    "select": Split(
        "select",
        shapes=("pyramid", "bicone", "lens"),
        object_textures=("plaid", "scales", "weave"),
        wall_textures=("plaid", "scales", "weave"),
        reliefs=("ripples",),
        **_BROAD,
    ),
    "wide": Split("wide", **{**_TRAIN_FAMILIES, "shapes": (*_TRAIN_FAMILIES["shapes"], "gem", "blob")}),
}
HELD_SPLITS: tuple[str, ...] = ("heldout", "far", "select")
"""The splits of families training never sees; their scenes at world seed 0 are the benchmarks' own."""

assert tuple(SPLITS) == SPLIT_NAMES, tuple(SPLITS)  # the names are declared once, in lasagna.world.names
for _s in SPLITS.values():
    assert set(_s.shapes) <= set(SHAPES) and _s.textures <= set(TEXTURES) and set(_s.reliefs) <= set(RELIEFS), _s
    assert 1 <= _s.objects[0] <= _s.objects[1] <= MAX_OBJECTS, _s
for _a, _b in (
    ("heldout", "train"),
    ("far", "train"),
    ("far", "heldout"),
    ("select", "train"),
    ("select", "heldout"),
    ("select", "far"),
    ("heldout", "wide"),
    ("far", "wide"),
    ("select", "wide"),
):
    assert not set(SPLITS[_a].shapes) & set(SPLITS[_b].shapes)
    assert not SPLITS[_a].textures & SPLITS[_b].textures
    assert not set(SPLITS[_a].reliefs) & set(SPLITS[_b].reliefs)

# Bump when the mapping from a scene's random stream to its parameters changes for every split, so
# old and new scenes of the "same" (split, seed, index) never pass for each other (WORLD_VERSION says
# which families a split had).
STREAM_VERSION = 1


def get_split(name: str) -> Split:
    """The split called ``name``; raises naming the valid splits otherwise."""
    try:
        return SPLITS[name]
    except KeyError:
        raise LasagnaError(f"unknown split {name!r}; expected one of {', '.join(SPLIT_NAMES)}", where="split") from None


def check_seed(seed: int, where: str = "seed") -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= int(seed) < 2**63:
        raise LasagnaError(f"expected an integer in [0, 2**63), got {seed!r}", where=where)
    return int(seed)


def check_training_scenes(split: str, world_seed: int, where: str = "split") -> None:
    """Refuse training scenes a benchmark measures: an unknown split, or a held split (``HELD_SPLITS``) at world
    seed 0, whose scenes are the benchmarks' own. The one statement of that rule for every trainer."""
    get_split(split)
    check_seed(world_seed, where=where)
    if split in HELD_SPLITS and world_seed == 0:
        raise LasagnaError(
            f"training on {split} scenes of world seed 0 would train on the benchmarks' own scenes; "
            "expected another world seed",
            where,
        )


def scene_rng(split: str, seed: int, index: int, stream: str = "") -> np.random.Generator:
    """The random stream of scene ``index`` of ``split`` under ``seed``.

    ``stream`` names a further stream of the same scene for draws added after its parameters were
    fixed (e.g. ``"relight"``, the relight task's source light), so that they leave every draw of
    the scene's own stream — and so every existing scene — bit-identical.
    """
    get_split(split)
    check_seed(seed)
    check_seed(index, where="index")
    tag = f"lasagna.world/v{STREAM_VERSION}/{split}/{int(seed)}/{int(index)}"
    tag = (tag + f"/{stream}" if stream else tag).encode()
    key = int.from_bytes(hashlib.blake2b(tag, digest_size=16).digest(), "little")
    return np.random.Generator(np.random.Philox(key=key))
