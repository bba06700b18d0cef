"""Write the small real photographs the demo edits: square crops of scikit-image's sample images.

    pip install scikit-image          # only to run this script once; not a dependency of lasagna
    python examples/make_photos.py    # writes examples/photos/<name>.png (96x96 RGB, 8-bit),
                                      # examples/photos/large/<name>.jpg (512x512, the benchmarks' sheet)
                                      # and examples/photos/select/<name>.jpg (512x512, the photo selection set)

The demo's photographs (``lasagna.demo.PHOTOS``) are also copied into the package
(``lasagna/_data/photos``), so that ``lasagna demo`` runs from an installed wheel.

Each crop is a square box of the original image, resized with Pillow's Lanczos filter. The images
are in the public domain or CC0 (see examples/photos/README.md, which credits each one).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

from PIL import Image

from lasagna.demo import PACKAGED_PHOTOS, PHOTOS

SIZE = 96
# name -> (scikit-image loader, (left, top, side) of the square box in the original's pixels)
CROPS = {
    "coffee": ("coffee", (80, 0, 400)),  # the cup on its saucer, from above
    "chelsea": ("chelsea", (70, 0, 300)),  # the cat's face
    "astronaut": ("astronaut", (140, 10, 240)),  # Eileen Collins' head and collar
    "helmet": ("astronaut", (318, 318, 194)),  # the black helmet in the corner: a shiny sphere
}


LARGE = 512
# name -> (scikit-image loader, (left, top, side)): the largest square of each photograph, at LARGE².
LARGE_CROPS = {
    "astronaut": ("astronaut", (0, 0, 512)),  # native 512²
    "coffee": ("coffee", (100, 0, 400)),  # enlarged 1.28× by Lanczos
    "rocket": ("rocket", (110, 0, 427)),  # enlarged 1.2×
    "chelsea": ("chelsea", (80, 0, 300)),  # enlarged 1.7×: the softest of the four
}


# name -> (loader, (left, top, side)): the photograph selection set (issue #24) — other photographs than the four
# above, on which choices for photographs are made (``benchmarks/photo_swing.py``), so that ``large`` stays a report.
# Loaders are scikit-image's, except ``grace_hopper`` (matplotlib's sample data, a US Navy photograph) and the two
# ``sklearn:`` ones (scikit-learn's bundled sample images, read as files: scikit-learn is not imported). The last
# three were added on 2026-11-26, before anything was measured on them: four photographs were too few to agree.
SELECT_CROPS = {
    "grace_hopper": ("grace_hopper", (0, 44, 512)),  # a portrait in uniform; native 512 wide
    "camera": ("camera", (0, 0, 512)),  # the cameraman and his tripod, grey; native 512²
    "coins": ("coins", (40, 0, 303)),  # Greek coins in rows, grey; enlarged 1.69×
    "retina": ("retina", (0, 0, 1411)),  # a fundus photograph: the eye's back, a lit disc; reduced 2.76×
    "flower": ("sklearn:flower.jpg", (95, 0, 427)),  # a dahlia in sunlight, the leaves dark; enlarged 1.2×
    "china": ("sklearn:china.jpg", (0, 0, 427)),  # a pagoda on a hill above a lake; enlarged 1.2×
    "clock": ("clock", (61, 0, 300)),  # a wall clock, the camera moving (motion blur), grey; enlarged 1.71×
}


def _select_image(loader: str) -> Image.Image:
    if loader.startswith("sklearn:"):
        import importlib.util

        package = Path(importlib.util.find_spec("sklearn").origin).parent  # found, not imported
        return Image.open(package / "datasets" / "images" / loader.removeprefix("sklearn:")).convert("RGB")
    if loader == "grace_hopper":
        from matplotlib import cbook

        with cbook.get_sample_data("grace_hopper.jpg") as f:
            return Image.open(f).convert("RGB")
    import skimage.data

    return Image.fromarray(getattr(skimage.data, loader)()).convert("RGB")


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
    for name in PHOTOS:  # the demo's, shipped in the wheel
        shutil.copyfile(out / f"{name}.png", PACKAGED_PHOTOS / f"{name}.png")
        print(f"copied {name}.png to {PACKAGED_PHOTOS}")
    (out / "large").mkdir(exist_ok=True)
    for name, (loader, (left, top, side)) in LARGE_CROPS.items():
        image = Image.fromarray(getattr(skimage.data, loader)()).convert("RGB")
        crop = image.crop((left, top, left + side, top + side)).resize((LARGE, LARGE), Image.Resampling.LANCZOS)
        crop.save(out / "large" / f"{name}.jpg", quality=92)
        print(f"wrote {out / 'large' / f'{name}.jpg'} ({loader}, box {(left, top, side)})")
    (out / "select").mkdir(exist_ok=True)
    for name, (loader, (left, top, side)) in SELECT_CROPS.items():
        image = _select_image(loader)
        crop = image.crop((left, top, left + side, top + side)).resize((LARGE, LARGE), Image.Resampling.LANCZOS)
        crop.save(out / "select" / f"{name}.jpg", quality=92)
        print(f"wrote {out / 'select' / f'{name}.jpg'} ({loader}, box {(left, top, side)})")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent / "photos")
