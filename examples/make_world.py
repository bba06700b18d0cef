"""Write the world scenes the demo edits: a few held-out scenes as ground-truth stack folders.

    python examples/make_world.py            # writes examples/world/heldout-s0-00000N/ and world.json

The ``heldout`` split uses shape and texture families the bundled priors never saw in training
(``lasagna.world.splits``). Each folder is a ``lasagna world`` stack: the albedo as base, the true
shading as a multiply layer in [0, 2], ``composite.png`` = albedo × shading, plus normals.png and
mask.png. The same as ``lasagna world -o examples/world --split heldout --count 4 --resolution 64``.

The settings are ``lasagna.demo``'s (``WORLD_*``, ``write_world``): outside a checkout the demo renders these
scenes itself, the same bits (tests/test_edit.py checks the committed files against it).
"""

from __future__ import annotations

import sys
from pathlib import Path

from lasagna.demo import write_world

if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent / "world"
    for folder in write_world(out):
        print(f"wrote {folder}")
