"""A stack folder with a learned-style surface layer for the editor's tests: a base photograph-like gradient, a
surface (a dome's normal map, offset and smaller than the canvas) lit from the top left, and a translucent tint
above it, so a re-light changes the pixels under the layer above too."""

from __future__ import annotations

from pathlib import Path

import torch

from lasagna.io.stack import Stack


def dome_normals(w: int, h: int) -> torch.Tensor:
    """Unit normals (3, h, w), +Y up, of a dome filling the rectangle (flat beyond its ellipse)."""
    y, x = torch.meshgrid(
        torch.linspace(1, -1, h, dtype=torch.float64), torch.linspace(-1, 1, w, dtype=torch.float64), indexing="ij"
    )
    r2 = x * x + y * y
    inside = r2 < 0.9
    n = torch.stack([torch.where(inside, x, 0.0), torch.where(inside, y, 0.0), torch.sqrt((1 - r2).clamp_min(0.1))])
    return n / n.norm(dim=0, keepdim=True)


def surface_stack(folder: Path, width: int = 64, height: int = 48) -> Path:
    y, x = torch.meshgrid(torch.linspace(0, 1, height), torch.linspace(0, 1, width), indexing="ij")
    base = torch.stack([0.3 + 0.6 * x, 0.4 + 0.5 * y, 0.8 - 0.3 * x])
    stack = Stack.from_image(base, name="Photo")
    sw, sh = width * 5 // 8, height * 2 // 3
    stack.add_surface("shape", dome_normals(sw, sh).float(), "top-left", offset=(width // 8, height // 6), name="Shape")
    stack.add_solid("tint", (1.0, 0.8, 0.4, 0.2), name="Tint")
    stack.save(folder)
    return folder
