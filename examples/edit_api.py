"""Learned layers through the Python API: what ``lasagna edit`` and ``lasagna render`` do, step by step.

    python examples/edit_api.py [OUT_DIR]        (default out/edit_api; a few seconds with an amortised
                                                  generator, under a minute with per-image optimisation)

The same as, on the command line::

    lasagna layers
    lasagna edit examples/photos/coffee.png --layer shading --condition left -o OUT/coffee-left
    lasagna edit OUT/coffee-left --layer shading --condition top --on base --generator free -o OUT/coffee-top
    lasagna render OUT/coffee-top --all
    lasagna edit OUT/coffee-top --layer light --condition warm -o OUT/coffee-warm
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

import lasagna
from lasagna import catalogue
from lasagna.api import edit, render_learned
from lasagna.errors import LasagnaError

EXAMPLES = Path(__file__).resolve().parent


def main(out: Path) -> None:
    # 1. The catalogue: presets, and the priors/correctives/generators they name.
    print("catalogue:", catalogue.catalogues())
    print("available:", catalogue.available())
    parts = catalogue.resolve("shading", need_prior=False)
    print(
        f"preset shading: {parts.preset.blend}, range {parts.preset.range}, labels {parts.preset.vocabulary}; "
        f"generator {'yes' if parts.generator else 'none (per-image optimisation)'}"
    )

    # 2. Relight a photograph from the left. Amortised generator if the preset has one, else per-image.
    result = edit(EXAMPLES / "photos" / "coffee.png", "shading", "left")
    print(
        f"layer {result.layer_id!r}: {tuple(result.layer.shape)} in [{result.layer.min():.3f}, "
        f"{result.layer.max():.3f}], "
        f"{result.settings['method']}, {result.seconds:.2f} s"
    )
    first = result.save(out / "coffee-left", force=True)

    # 3. A stack folder is an input too: a second learned layer, conditioned on the base, per image.
    try:
        second = edit(first, "shading", "top", on="base", generator="free", optimize=40)
    except LasagnaError as err:  # no prior in the catalogue: per-image optimisation cannot run
        print(f"skipped the per-image edit: {err}")
        return
    print(
        f"layer {second.layer_id!r}: {len(second.history)} steps, last grad norm {second.history[-1]['grad_norm']:.3g}"
    )
    folder = second.save(out / "coffee-top", force=True)

    # 4. The document alone reproduces the edit: drop the learned pixels, render them again.
    stack = lasagna.load(folder)
    before = {i: stack.tensors[i].color.clone() for i in (result.layer_id, second.layer_id)}
    for i in before:
        del stack.tensors[i]
    stack, rendered = render_learned(stack, write=False)
    for i in rendered:
        print(f"re-rendered {i}: max difference {float((stack.tensors[i].color - before[i]).abs().max()):.2e}")
    print(f"wrote {first} and {folder} (stack.json, layers/, generators/, composite.png, stack.ora)")

    # 5. Another kind of learned layer on top: a warm fill light (a plus layer, so it can only brighten).
    lit = edit(folder, "light", "warm")
    assert bool((lit.composite >= lasagna.render(stack).image - 1e-6).all())  # plus never darkens
    print(
        f"layer {lit.layer_id!r}: mean light added {float(lit.layer.mean()):.3f}; wrote "
        f"{lit.save(out / 'coffee-warm', force=True)}"
    )


if __name__ == "__main__":
    torch.set_num_threads(1)
    try:
        main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("out/edit_api"))
    except LasagnaError as err:
        sys.exit(f"edit_api: {err}")
