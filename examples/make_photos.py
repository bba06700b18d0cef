"""Write the small real photographs the demo edits: square crops of scikit-image's sample images.

    pip install scikit-image          # only to run this script once; not a dependency of lasagna
    python examples/make_photos.py    # writes examples/photos/<name>.png (96x96 RGB, 8-bit)

Each crop is a square box of the original image, resized with Pillow's Lanczos filter. The images
are in the public domain or CC0 (see examples/photos/README.md, which credits each one).
"""

from __future__ import annotations

import sys
from pathlib import Path

from PIL import Image

SIZE = 96
# name -> (scikit-image loader, (left, top, side) of the square box in the original's pixels)
CROPS = {
    "coffee": ("coffee", (80, 0, 400)),  # the cup on its saucer, from above
    "chelsea": ("chelsea", (70, 0, 300)),  # the cat's face
    "astronaut": ("astronaut", (140, 10, 240)),  # Eileen Collins' head and collar
    "helmet": ("astronaut", (318, 318, 194)),  # the black helmet in the corner: a shiny sphere
}


def main(out: Path) -> None:
    import skimage.data

    out.mkdir(parents=True, exist_ok=True)
    for name, (loader, (left, top, side)) in CROPS.items():
        image = Image.fromarray(getattr(skimage.data, loader)()).convert("RGB")
        box = (left, top, left + side, top + side)
        if box[2] > image.width or box[3] > image.height:
            raise SystemExit(f"{name}: box {box} leaves the {image.width}x{image.height} image")
        crop = image.crop(box).resize((SIZE, SIZE), Image.Resampling.LANCZOS)
        crop.save(out / f"{name}.png", optimize=True)
        print(f"wrote {out / f'{name}.png'} ({loader}, box {box})")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent / "photos")
