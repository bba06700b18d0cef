"""Write the photographs the world paints on surfaces: small grayscale crops of scikit-image's bundled images.

    pip install scikit-image          # only to run this script once; not a dependency of lasagna
    python examples/make_paint.py     # writes lasagna/_data/paint/<name>.png (128x128, 8-bit gray)

The world (`lasagna.world.paint`) uses their luminance as paint, tinted by a surface's colours: the
``photo`` family (training) uses the first group, the ``naturephoto`` family (the ``far`` split, never
trained on) the second. The photographs the demo and the benchmarks edit (astronaut, chelsea, coffee,
rocket) are used by neither. All are public domain or CC0 (scikit-image's data README credits them).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from PIL import Image

SIZE = 128
# name -> (scikit-image loader, (left, top, side) of the square box in the original's pixels)
CROPS = {
    # photo (train)
    "camera": ("camera", (100, 40, 320)),
    "coins": ("coins", (0, 0, 300)),
    "moon": ("moon", (60, 60, 380)),
    "hubble": ("hubble_deep_field", (200, 150, 400)),
    "ihc": ("immunohistochemistry", (120, 120, 380)),
    "retina": ("retina", (300, 300, 700)),
    "motorcycle": ("stereo_motorcycle", (150, 100, 400)),
    "page": ("page", (0, 0, 190)),
    "cell": ("cell", (100, 100, 400)),
    # naturephoto (far)
    "grass": ("grass", (0, 0, 512)),
    "gravel": ("gravel", (0, 0, 512)),
    "brick": ("brick", (0, 0, 512)),
}


def main(out: Path) -> None:
    import skimage.data

    out.mkdir(parents=True, exist_ok=True)
    for name, (loader, (left, top, side)) in CROPS.items():
        data = getattr(skimage.data, loader)()
        if isinstance(data, tuple):  # stereo_motorcycle returns (left, right, disparity)
            data = data[0]
        image = Image.fromarray(np.asarray(data)).convert("L")
        side = min(side, image.width - left, image.height - top)
        crop = image.crop((left, top, left + side, top + side)).resize((SIZE, SIZE), Image.Resampling.LANCZOS)
        crop.save(out / f"{name}.png", optimize=True)
        print(f"wrote {out / f'{name}.png'} ({loader}, box {left, top, side})")


if __name__ == "__main__":
    main(
        Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1] / "lasagna" / "_data" / "paint"
    )
