"""The named splits of the world and the random stream of every scene.

Each split names the shape and texture families its scenes draw from. ``val`` shares ``train``'s
families (other scenes); ``heldout`` uses only families ``train`` never uses, checked at import:

=========  ==========================  =========================  ====================
split      shapes                      object textures            wall textures
=========  ==========================  =========================  ====================
train      ellipsoid, box, cylinder    stripes, checker, noise    tiles, noise
val        ellipsoid, box, cylinder    stripes, checker, noise    tiles, noise
heldout    torus, capsule, cone        dots, marble, rings        bricks, dots
=========  ==========================  =========================  ====================

Scene ``index`` of split ``split`` under ``seed`` is drawn from its own counter-based generator
(NumPy's Philox, whose output is specified bit for bit across platforms) keyed by a BLAKE2b hash of
``(split, seed, index)``. So any scene can be regenerated alone, a batch is the same scenes whatever
its size, and two splits (or two seeds) never share a random stream: their scenes are distinct with
probability 1 (the parameters are continuous), and ``heldout`` differs in families besides.
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

from lasagna.errors import LasagnaError
from lasagna.world.shapes import SHAPES
from lasagna.world.textures import TEXTURES


@dataclass(frozen=True)
class Split:
    """The families one split draws from (each a non-empty tuple of registered names)."""

    name: str
    shapes: tuple[str, ...]
    object_textures: tuple[str, ...]
    wall_textures: tuple[str, ...]

    @property
    def textures(self) -> frozenset[str]:
        return frozenset(self.object_textures) | frozenset(self.wall_textures)


_TRAIN_FAMILIES = dict(
    shapes=("ellipsoid", "box", "cylinder"),
    object_textures=("stripes", "checker", "noise"),
    wall_textures=("tiles", "noise"),
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
}
SPLIT_NAMES: tuple[str, ...] = tuple(SPLITS)

for _s in SPLITS.values():
    assert set(_s.shapes) <= set(SHAPES) and _s.textures <= set(TEXTURES), _s
assert not set(SPLITS["heldout"].shapes) & set(SPLITS["train"].shapes)
assert not SPLITS["heldout"].textures & SPLITS["train"].textures

# Bump when the mapping from a scene's random stream to its parameters changes, so old and new
# scenes of the "same" (split, seed, index) never pass for each other.
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


def scene_rng(split: str, seed: int, index: int) -> np.random.Generator:
    """The random stream of scene ``index`` of ``split`` under ``seed``."""
    get_split(split)
    check_seed(seed)
    check_seed(index, where="index")
    tag = f"lasagna.world/v{STREAM_VERSION}/{split}/{int(seed)}/{int(index)}".encode()
    key = int.from_bytes(hashlib.blake2b(tag, digest_size=16).digest(), "little")
    return np.random.Generator(np.random.Philox(key=key))
