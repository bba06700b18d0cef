"""Regenerate the example stack folders in examples/stacks/ (deterministic: fixed seeds, no clock).

    OMP_NUM_THREADS=1 .venv/bin/python examples/make_example_stacks.py [OUT_DIR]

Each stack is small (64x48) and shows part of the format (docs/ARCHITECTURE.md):
  basic/    albedo base, a 16-bit multiply shading layer in [0, 2], an RGBA sticker hanging off the
            top-right corner, an additive warm glow, and a hidden solid layer
  linear/   blend_space "linear" and clamp "output": an 8-bit multiply shading (a factor, never
            sRGB-decoded), a translucent solid tint and an additive light
  masked/   a screen layer with a gray mask and opacity 0.6
  learned/  a learned shading layer (preset "shading", label "left") with its rendered pixels
The PNGs are smooth gradients with a little seeded texture, so renders are easy to judge by eye.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from PIL import Image

from lasagna.atomic import atomic_path
from lasagna.document import Document, save_document

W, H = 64, 48
HERE = Path(__file__).resolve().parent


def grid(w: int = W, h: int = H) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates in [0, 1], each (h, w)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return (x + 0.5) / w, (y + 0.5) / h


def save_png(path: Path, values: np.ndarray, bits: int = 8) -> None:
    """Write float values in [0, 1]: (h, w) gray, (h, w, 3) RGB or (h, w, 4) RGBA; bits 8 or 16 (gray)."""
    v = np.clip(values, 0.0, 1.0)
    if bits == 16:
        assert v.ndim == 2, "16-bit examples are gray (Pillow mode I;16)"
        image = Image.fromarray(np.round(v * 65535).astype(np.uint16))
    else:
        image = Image.fromarray(np.round(v * 255).astype(np.uint8))
    with atomic_path(path) as tmp:
        image.save(tmp, format="PNG")


def albedo(seed: int) -> np.ndarray:
    """A warm-to-cool gradient wall with a rounded object in front, plus fine seeded texture."""
    rng = np.random.default_rng(seed)
    x, y = grid()
    wall = np.stack([0.75 - 0.35 * x, 0.55 + 0.1 * y, 0.35 + 0.4 * x], axis=-1)
    inside = ((x - 0.5) / 0.28) ** 2 + ((y - 0.55) / 0.36) ** 2 < 1.0
    wall[inside] = [0.85, 0.45, 0.25]
    texture = 0.04 * rng.standard_normal((H, W, 1)) + 0.03 * np.sin(40 * x + 25 * y)[..., None]
    return wall + texture


def lambert(direction: tuple[float, float, float], lo: float = 0.3, hi: float = 1.6) -> np.ndarray:
    """Shading of a sphere bulging out of a flat wall, lit from ``direction``, mapped to [lo, hi]."""
    x, y = grid()
    u, v = (x - 0.5) / 0.28, (y - 0.55) / 0.36
    r2 = u**2 + v**2
    n = np.stack([u, v, np.sqrt(np.clip(1 - r2, 0, 1))], axis=-1)
    n[r2 >= 1] = [0.0, 0.0, 1.0]
    d = np.asarray(direction, dtype=np.float64)
    cos = np.clip(n @ (d / np.linalg.norm(d)), 0.0, 1.0)
    return lo + (hi - lo) * cos


def radial(cx: float, cy: float, radius: float, w: int = W, h: int = H) -> np.ndarray:
    """A smooth bump, 1 at (cx, cy) falling to 0 at ``radius`` (all in [0, 1] units)."""
    x, y = grid(w, h)
    return np.clip(1 - ((x - cx) ** 2 + (y - cy) ** 2) / radius**2, 0, 1) ** 2


def stack(layers: list[dict], **extra: object) -> Document:
    return Document.from_dict(
        {
            "format": "lasagna.stack",
            "version": 1,
            "canvas": {"width": W, "height": H},
            "layers": layers,
            **extra,
        }
    )


def basic(out: Path) -> None:
    save_png(out / "layers/base.png", albedo(seed=1))
    save_png(out / "layers/shade.png", lambert((-1.0, -0.3, 0.8)) / 2.0, bits=16)  # v = (y - 0) / (2 - 0)
    sticker = np.zeros((24, 32, 4))
    sticker[..., :3] = [0.2, 0.5, 0.9]
    sticker[..., 3] = np.clip(2.0 * radial(0.5, 0.5, 0.6, 32, 24), 0, 1)
    save_png(out / "layers/sticker.png", sticker)
    glow = radial(0.2, 0.2, 0.5)[..., None] * np.array([0.35, 0.22, 0.05])
    save_png(out / "layers/glow.png", glow)
    save_document(
        stack(
            [
                {"id": "base", "name": "Albedo", "kind": "pixels", "source": "layers/base.png"},
                {
                    "id": "shade",
                    "name": "Shading",
                    "kind": "pixels",
                    "source": "layers/shade.png",
                    "blend": "multiply",
                    "range": [0.0, 2.0],
                },
                {
                    "id": "sticker",
                    "name": "Sticker",
                    "kind": "pixels",
                    "source": "layers/sticker.png",
                    "offset": {"x": 44, "y": -6},
                },
                {"id": "glow", "name": "Warm glow", "kind": "pixels", "source": "layers/glow.png", "blend": "plus"},
                {
                    "id": "hidden",
                    "name": "Hidden red box",
                    "kind": "solid",
                    "color": [1.0, 0.0, 0.0],
                    "size": {"width": 16, "height": 16},
                    "offset": {"x": 4, "y": 4},
                    "visible": False,
                },
            ],
            metadata={"example": "basic"},
        ),
        out,
    )


def linear(out: Path) -> None:
    save_png(out / "layers/base.png", albedo(seed=2))
    save_png(out / "layers/shade.png", lambert((1.0, -1.0, 1.0), lo=0.25, hi=1.0))
    light = radial(0.8, 0.3, 0.6)[..., None] * np.array([0.1, 0.2, 0.35])
    save_png(out / "layers/light.png", light)
    save_document(
        stack(
            [
                {"id": "base", "kind": "pixels", "source": "layers/base.png"},
                {"id": "shade", "kind": "pixels", "source": "layers/shade.png", "blend": "multiply"},
                {
                    "id": "tint",
                    "kind": "solid",
                    "color": [0.2, 0.4, 1.0, 0.5],
                    "size": {"width": 32, "height": 24},
                    "offset": {"x": 16, "y": 12},
                },
                {"id": "light", "kind": "pixels", "source": "layers/light.png", "blend": "plus"},
            ],
            blend_space="linear",
            clamp="output",
            metadata={"example": "linear"},
        ),
        out,
    )


def masked(out: Path) -> None:
    save_png(out / "layers/base.png", albedo(seed=3))
    x, y = grid(40, 28)
    paint = np.stack([0.9 - 0.5 * y, 0.3 + 0.6 * x, 0.8 * np.ones_like(x)], axis=-1)
    save_png(out / "layers/paint.png", paint)
    save_png(out / "masks/paint.png", np.clip(1.5 * radial(0.5, 0.5, 0.7, 40, 28), 0, 1))
    save_document(
        stack(
            [
                {"id": "base", "kind": "pixels", "source": "layers/base.png"},
                {
                    "id": "paint",
                    "kind": "pixels",
                    "source": "layers/paint.png",
                    "blend": "screen",
                    "offset": {"x": 12, "y": 10},
                    "mask": "masks/paint.png",
                    "opacity": 0.6,
                },
            ],
            metadata={"example": "masked"},
        ),
        out,
    )


def learned(out: Path) -> None:
    save_png(out / "layers/base.png", albedo(seed=4))
    save_png(out / "layers/relit.png", lambert((-1.0, 0.0, 0.6)) / 2.0, bits=16)
    save_document(
        stack(
            [
                {"id": "base", "name": "Albedo", "kind": "pixels", "source": "layers/base.png"},
                {
                    "id": "relit",
                    "name": "Relit from the left",
                    "kind": "learned",
                    "preset": "shading",
                    "condition": {"label": "left"},
                    "conditioned_on": "base",
                    "blend": "multiply",
                    "range": [0.0, 2.0],
                    "source": "layers/relit.png",
                },
            ],
            metadata={"example": "learned"},
        ),
        out,
    )


def main(root: Path) -> None:
    for make in (basic, linear, masked, learned):
        make(root / make.__name__)
        print(root / make.__name__)


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE / "stacks")
