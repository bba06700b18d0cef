"""The colour preset on colour photographs: a sheet (input | layer | composite | composite before) and one JSON line.

    python benchmarks/color_photos.py [--sheet docs/img/color_photos.png]

Each of ``examples/photos/large`` (512², scikit-image's photographs) is edited with ``--layer color`` as a user would
(``lasagna.edit``, defaults), and with the preset as it was before colour over luminance (``luminance`` free, made at
the image's own size: the "before" column). Per photo: the largest difference between the composite's and the
input's Rec. 709 luma, in 8-bit codes (colour over luminance keeps it); Hasler & Süsstrunk's colourfulness M of the
input and of both composites; and the mean α.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import colourfulness, luma, machine_info, print_json_line, save_sheet  # noqa: E402

import lasagna  # noqa: E402
from lasagna.document import Preset, load_preset  # noqa: E402

PHOTOS = ("astronaut", "chelsea", "coffee", "rocket")


def _before_catalogue(folder: Path) -> Path:
    """A catalogue holding the colour preset as it was: luminance free, the layer made at the image's size."""
    preset = load_preset(ROOT / "layers" / "color" / "preset.json")
    old = Preset.model_validate({**preset.model_dump(), "luminance": "free", "working_size": None})
    (folder / "color").mkdir(parents=True)
    (folder / "color" / "preset.json").write_text(old.to_json(), encoding="utf-8")
    return folder


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sheet", type=Path, default=ROOT / "docs" / "img" / "color_photos.png")
    args = ap.parse_args()
    torch.set_num_threads(1)
    inputs, layers, composites, befores, rows = [], [], [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        before_dirs = [_before_catalogue(Path(tmp)), ROOT / "layers"]
        for name in PHOTOS:
            path = ROOT / "examples" / "photos" / "large" / f"{name}.jpg"
            image = torch.from_numpy(np.asarray(Image.open(path).convert("RGB"), dtype=np.float32) / 255.0)
            image = image.permute(2, 0, 1)
            t0 = time.perf_counter()
            new = lasagna.edit(str(path), "color")
            seconds = time.perf_counter() - t0
            old = lasagna.edit(str(path), "color", catalogue_dirs=before_dirs)
            codes = [torch.from_numpy(lasagna.to_numpy(r.composite)).permute(2, 0, 1).double() for r in (new, old)]
            dy = [float((luma(c[None]) - luma(255.0 * image.double()[None])).abs().max()) for c in codes]
            inputs.append(image)
            layers.append(new.layer[:3])
            composites.append(new.composite)
            befores.append(old.composite)
            rows.append(
                {
                    "photo": name,
                    "luma_max_codes": round(dy[0], 2),
                    "luma_max_codes_before": round(dy[1], 2),
                    "colourfulness_input": round(colourfulness(image[None]), 1),
                    "colourfulness": round(colourfulness(new.composite[None]), 1),
                    "colourfulness_before": round(colourfulness(old.composite[None]), 1),
                    "alpha_mean": round(float(new.layer[3].mean()), 3),
                    "seconds": round(seconds, 2),
                }
            )
            print(json.dumps(rows[-1]), file=sys.stderr)
    save_sheet([inputs, layers, composites, befores], args.sheet)
    print_json_line({"benchmark": "color_photos", "sheet": str(args.sheet), "photos": rows, **machine_info()})


if __name__ == "__main__":
    main()
