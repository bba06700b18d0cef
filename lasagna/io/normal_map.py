"""A normal map — or a height map — of one's own read from a PNG file: its codes as stored, decoded to unit normals.

A normal map — baked in Blender, painted with Krita's tangent-normal brush, made by a 2D-lighting tool — is an 8- or
16-bit RGB PNG in tangent space, +Y up (the OpenGL convention of Blender, Krita and Godot) or +Y down (DirectX:
green flipped, Unreal's and Substance's DirectX preset). It is data, not colour: its codes are read as stored, and a
colour profile it carries is not applied (``read_png``, not the image policy of ``read_image_file``); an alpha
channel is ignored. ``lasagna add-surface`` and the editor's "Add normal map" both read it here; the stack stores the
normals as its own 16-bit OpenGL map (``Stack.add_surface``).

A **height map** (a bump map, Photoshop's Lighting Effects "texture channel", a displacement map) is an 8- or 16-bit
grey PNG (an RGB one is read as the mean of its channels): black its lowest point, white ``depth`` pixels above it —
as `lasagna export --height-map` writes one and prints its depth. Its normals are the height field's
(`lasagna.compose.surface.normals_from_height`: central differences), in the layer's own pixels.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

from lasagna.errors import ImageError
from lasagna.io.png import DEFAULT_MAX_PIXELS, PNG_SIGNATURE, decode_png, read_png

if TYPE_CHECKING:
    import torch


def _read_map(path, data: bytes | None, max_pixels: int, where: str, expected: str):
    """The decoded PNG (`lasagna.io.png.PngImage`) at ``path`` or of ``data``, its codes as stored; a file that is not
    a PNG refused in one line saying what was ``expected``."""
    if data is None:
        with open(Path(path), "rb") as f:
            head = f.read(8)
    else:
        head = data[:8]
    if head != PNG_SIGNATURE:
        raise ImageError(f"not a PNG; expected {expected}", where=where)
    return read_png(path, max_pixels=max_pixels) if data is None else decode_png(data, where, max_pixels=max_pixels)


def normal_map_normals(
    path: str | os.PathLike | None = None,
    *,
    data: bytes | None = None,
    directx: bool = False,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    where: str | None = None,
) -> torch.Tensor:
    """Unit normals (3, h, w), float32, of the normal-map PNG at ``path`` (or its bytes ``data``), +Y up after
    decoding (``directx``: the file's green is flipped); `ImageError` in one line for anything else."""
    where = where or str(path)
    png = _read_map(path, data, max_pixels, where, "a normal map as an 8- or 16-bit RGB PNG")
    if png.color.shape[0] != 3:
        raise ImageError(f"has {png.color.shape[0]} colour channel(s); expected an RGB normal map", where=where)
    # torch only now: a file refused above costs no torch import (~1.5 s), as the CLI's other refusals.
    import torch

    from lasagna.compose.surface import decode_normal_map

    rgb = torch.from_numpy(png.color)[None].double()
    return decode_normal_map(rgb, convention="directx" if directx else "opengl")[0].float()


MAX_HEIGHT_DEPTH = 65535.0
"""The greatest depth a height map may give its white, in pixels: one 16-bit code a pixel."""


def height_map_normals(
    path: str | os.PathLike | None = None,
    *,
    data: bytes | None = None,
    depth: float,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    where: str | None = None,
) -> torch.Tensor:
    """Unit normals (3, h, w), float32, of the height-map PNG at ``path`` (or its bytes ``data``): its grey codes
    (the mean of an RGB map's channels) times ``depth`` pixels, white the highest (module docstring); `ImageError` in
    one line for anything else."""
    where = where or str(path)
    if not (isinstance(depth, (int, float)) and not isinstance(depth, bool) and 0.0 < depth <= MAX_HEIGHT_DEPTH):
        raise ImageError(
            f"got a depth of {depth!r}; expected the pixels white stands above black, in (0, {MAX_HEIGHT_DEPTH:g}]",
            where="height",
        )
    png = _read_map(path, data, max_pixels, where, "a height map as an 8- or 16-bit grey PNG")
    import torch

    from lasagna.compose.surface import normals_from_height

    grey = torch.from_numpy(png.color).double().mean(0)  # (h, w) in [0, 1]
    heights = grey * float(depth) * (2.0 / grey.shape[-1])  # pixels to canvas units (the layer is 2 units wide)
    return normals_from_height(heights[None, None])[0].float()


__all__ = ["height_map_normals", "normal_map_normals"]
