"""The world's split and task names, declared once and torch-free.

A command's arguments (``lasagna world --split``, ``--task``; ``train-layer --split``) offer these as choices
before anything is rendered, so a mistyped name is refused without loading torch. `lasagna.world.splits`
defines each split's families under exactly these names (checked at its import); `lasagna.world.export`
writes exactly these tasks.
"""

from __future__ import annotations

SPLIT_NAMES: tuple[str, ...] = ("train", "val", "heldout", "far", "select", "wide")
"""The named splits, in the order `lasagna.world.splits.SPLITS` defines them."""

TASKS: tuple[str, ...] = ("shading", "color", "light", "relight")
"""What a world stack folder teaches: albedo + shading, grey + colour, image + glow, lit image + ratio."""
