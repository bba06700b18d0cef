"""Random stack folders for tests, written without ``lasagna``: JSON by ``json``, PNGs by Pillow
(8-bit) and pypng (16-bit), as an artist's tools or a judge's script would write them."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import png as pypng
from PIL import Image


def write_png8(path: Path, codes: np.ndarray) -> None:
    """(h, w) or (h, w, C) uint8 → PNG via Pillow (L, LA, RGB, RGBA by channel count)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if codes.ndim == 3 and codes.shape[2] == 1:
        codes = codes[:, :, 0]
    Image.fromarray(codes.astype(np.uint8)).save(path)


def write_png16(path: Path, codes: np.ndarray) -> None:
    """(h, w) or (h, w, C) uint16 → 16-bit PNG via pypng."""
    path.parent.mkdir(parents=True, exist_ok=True)
    c = codes if codes.ndim == 3 else codes[:, :, None]
    h, w, n = c.shape
    with open(path, "wb") as fh:
        pypng.Writer(w, h, greyscale=n in (1, 2), alpha=n in (2, 4), bitdepth=16).write(
            fh, c.reshape(h, w * n).tolist()
        )


def write_stack(folder: Path, doc: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "stack.json").write_text(json.dumps(doc, indent=1))
    return folder


def random_stack(
    folder: Path,
    seed: int,
    *,
    blend_space: str = "srgb",
    clamp: str = "layer",
    n_layers: int = 5,
    unit_only: bool = False,
) -> Path:
    """A random stack: 8-bit and 16-bit PNGs, gray/GA/RGB/RGBA, [0, 2] multipliers, offsets partly
    outside the canvas, masks, opacities, solid, hidden and learned layers. ``unit_only``: every
    range is [0, 1] (no 16-bit ranged layers)."""
    rng = np.random.default_rng(seed)
    W, H = int(rng.integers(8, 33)), int(rng.integers(8, 33))
    layers = []
    base = rng.integers(0, 256, (H, W, 3))
    write_png8(folder / "layers/base.png", base)
    layers.append({"id": "base", "kind": "pixels", "source": "layers/base.png"})
    for i in range(n_layers):
        lid = f"l{i}"
        h, w = int(rng.integers(3, H + 6)), int(rng.integers(3, W + 6))
        layer: dict = {
            "id": lid,
            "opacity": float(rng.choice([1.0, rng.random()])),
            "offset": {"x": int(rng.integers(-w // 2, W)), "y": int(rng.integers(-h // 2, H))},
        }
        kinds = ["normal", "multiply16", "multiply8", "plus", "screen", "solid", "learned", "plusneg"]
        kind = rng.choice(kinds[:1] + kinds[2:6] if unit_only else kinds)
        src = f"layers/{lid}.png"
        if kind == "normal":
            write_png8(folder / src, rng.integers(0, 256, (h, w, int(rng.choice([1, 2, 3, 4])))))
            layer.update(kind="pixels", source=src, blend=str(rng.choice(["normal", "alpha-linear"])))
        elif kind == "multiply16":
            channels = int(rng.choice([1, 2, 3, 4]))
            write_png16(folder / src, rng.integers(0, 65536, (h, w, channels)))
            layer.update(kind="pixels", source=src, blend="multiply", range=[0.0, 2.0])
        elif kind == "multiply8":
            write_png8(folder / src, rng.integers(0, 256, (h, w, int(rng.choice([1, 3])))))
            layer.update(kind="pixels", source=src, blend="multiply-luminosity")
        elif kind in ("plus", "screen"):
            write_png8(folder / src, rng.integers(0, 160, (h, w, 3)))
            layer.update(kind="pixels", source=src, blend="additive" if kind == "plus" else "screen")
        elif kind == "plusneg":
            write_png16(folder / src, rng.integers(0, 65536, (h, w, 3)))
            layer.update(kind="pixels", source=src, blend="plus", range=[-0.5, 0.5])
        elif kind == "solid":
            color = [float(v) for v in rng.random(int(rng.choice([3, 4])))]
            blend = str(rng.choice(["normal", "multiply", "plus", "screen"]))
            layer.update(kind="solid", color=color, blend=blend, size={"width": w, "height": h})
            if blend == "multiply" and not unit_only:
                layer["range"] = [0.0, 2.0]
        else:  # learned, rendered: stored exactly as a 16-bit pixels layer
            write_png16(folder / src, rng.integers(0, 65536, (h, w)))
            layer.update(
                kind="learned",
                preset="shading",
                condition={"label": "left"},
                conditioned_on="base",
                source=src,
                blend="multiply",
                range=[0.0, 2.0],
            )
        if layer["kind"] != "solid" and rng.random() < 0.35:
            write_png8(folder / f"masks/{lid}.png", rng.integers(0, 256, (h, w)))
            layer["mask"] = f"masks/{lid}.png"
        if rng.random() < 0.12:
            layer["visible"] = False
        layers.append(layer)
    doc = {
        "format": "lasagna.stack",
        "version": 1,
        "canvas": {"width": W, "height": H, "background": [float(v) for v in rng.random(3)]},
        "blend_space": blend_space,
        "clamp": clamp,
        "layers": layers,
    }
    return write_stack(folder, doc)


BLEND_NAMES = (
    "normal multiply plus screen overlay darken lighten color-dodge color-burn hard-light soft-light "
    "difference exclusion hue saturation color luminosity"
).split()


def random_group_stack(folder: Path, seed: int, *, depth: int = 3, clamp: str = "layer", modes=None) -> Path:
    """A random stack with nested groups: isolated ones with every blend mode, pass-through ones, group
    opacity, masks (any size, at the group's offset) and offsets, and pixel layers of every mode inside."""
    rng = np.random.default_rng(seed)
    W, H = int(rng.integers(8, 25)), int(rng.integers(8, 25))
    count = iter(range(10_000))
    modes = BLEND_NAMES if modes is None else modes

    def pixels() -> dict:
        lid = f"l{next(count)}"
        h, w = int(rng.integers(3, H + 4)), int(rng.integers(3, W + 4))
        src = f"layers/{lid}.png"
        write_png8(folder / src, rng.integers(0, 256, (h, w, int(rng.choice([1, 2, 3, 4])))))
        layer = {
            "id": lid,
            "kind": "pixels",
            "source": src,
            "blend": str(rng.choice(modes)),
            "opacity": float(rng.choice([1.0, rng.random()])),
            "offset": {"x": int(rng.integers(-w // 2, W)), "y": int(rng.integers(-h // 2, H))},
        }
        if rng.random() < 0.25:
            write_png8(folder / f"masks/{lid}.png", rng.integers(0, 256, (h, w)))
            layer["mask"] = f"masks/{lid}.png"
        return layer

    def group(d: int) -> dict:
        gid = f"g{next(count)}"
        isolated = bool(rng.random() < 0.5)
        kids = [group(d - 1) if d > 0 and rng.random() < 0.4 else pixels() for _ in range(int(rng.integers(1, 4)))]
        layer = {
            "id": gid,
            "kind": "group",
            "isolated": isolated,
            "blend": str(rng.choice(modes)) if isolated else "normal",
            "opacity": float(rng.choice([1.0, rng.random()])),
            "offset": {"x": int(rng.integers(-3, 4)), "y": int(rng.integers(-3, 4))},
            "layers": kids,
        }
        if rng.random() < 0.3:
            write_png8(
                folder / f"masks/{gid}.png", rng.integers(0, 256, (int(rng.integers(3, H)), int(rng.integers(3, W))))
            )
            layer["mask"] = f"masks/{gid}.png"
        if rng.random() < 0.1:
            layer["visible"] = False
        return layer

    write_png8(folder / "layers/base.png", rng.integers(0, 256, (H, W, 3)))
    layers = [{"id": "base", "kind": "pixels", "source": "layers/base.png"}]
    layers += [group(depth) if rng.random() < 0.7 else pixels() for _ in range(int(rng.integers(2, 5)))]
    doc = {
        "format": "lasagna.stack",
        "version": 1,
        "canvas": {"width": W, "height": H, "background": [float(v) for v in rng.random(3)]},
        "clamp": clamp,
        "layers": layers,
    }
    return write_stack(folder, doc)
