"""The colour preset on a colour photograph: colour over luminance (``LayerSpec.luminance`` "base"), made from the
image's luma at the prior's size and enlarged by the guided filter (``lasagna.compose.resample.upsample_colour``)."""

from __future__ import annotations

import numpy as np
import torch

from lasagna.compose.color import luma
from lasagna.editing import edit
from lasagna.io.stack import Stack
from lasagna.learned import layer_input
from lasagna.recipe import Recipe
from lasagna.request import EditRequest


def _photo(h: int = 64, w: int = 96) -> np.ndarray:
    """A tiny colour 'photograph': an orange disc with shading on a blue-green gradient, 8-bit codes (h, w, 3)."""
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w]).reshape(2, 1, 1)
    img = np.stack([0.2 + 0.3 * x, 0.5 + 0.2 * y, 0.7 - 0.3 * x], -1)
    disc = (x - 0.45) ** 2 + (y - 0.5) ** 2 < 0.09
    img[disc] = np.array([0.95, 0.55, 0.15]) * (0.6 + 0.4 * (1 - y[disc]))[:, None]
    return np.round(img * 255).astype(np.uint8)


def test_composite_keeps_the_photos_luminance_and_has_no_block_edges():
    codes = _photo()
    res = edit(codes, "color", optimize=4)
    base = torch.from_numpy(codes.astype(np.float64) / 255.0).permute(2, 0, 1)
    comp = res.composite.double()
    # 1. Colour over luminance: the composite's Rec. 709 luma is the input's, up to the layer's storage (16-bit
    # codes, alpha-weighted) — and the colour did change.
    dy = (luma(comp[None]) - luma(base[None])).abs().max()
    assert float(dy) < 0.5 / 255, f"luma moved by {float(dy) * 255:.3f} codes"
    assert float((comp - base).abs().max()) > 2 / 255
    # 2. No block edges: made at 32 (96 × 64 → 32 × 21, 3 pixels a working pixel), the layer's chroma has no more
    # gradient energy across working-pixel boundaries (pixels 3k − 1 | 3k) than across the others, in both
    # directions. A blocky enlargement puts all its energy there (nearest: the others hold only the guide's
    # texture); a smooth one spreads it, up to the orange disc's edges falling on one side or the other (× 2).
    colour = res.layer[:3].double()
    chroma = colour - luma(colour[None])[0]
    for dim, other in ((-1, -2), (-2, -1)):
        d = chroma.diff(dim=dim).pow(2).sum(dim=0).mean(dim=other)  # energy between pixels j and j + 1
        at_boundary = torch.tensor([j % 3 == 2 for j in range(d.numel())])
        assert float(d[at_boundary].mean()) <= 2.0 * float(d[~at_boundary].mean())
    assert res.settings["working_size"] == 32 and res.settings["distill"]["layer"]["luminance"] == "base"


def test_the_layer_is_made_from_the_luminance_alone():
    # A colour photograph and its gray (R = G = B = its luma) give the layer the same input.
    colour = torch.from_numpy(_photo().astype(np.float32) / 255.0).permute(2, 0, 1)
    recipe = Recipe.for_edit(Stack.from_image(colour), EditRequest(preset="color"))
    gray = luma(colour[None])[0].expand(3, -1, -1)
    x, g = layer_input(recipe, colour), layer_input(recipe, gray)
    assert x.shape == (1, 3, 21, 32)
    torch.testing.assert_close(x, g, atol=1e-6, rtol=0)
    torch.testing.assert_close(x[:, 0], x[:, 2], atol=0, rtol=0)  # gray
