"""What reading a surface layer back from a file costs (`lasagna.export.surface_import`). Plain script; one JSON line.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_import.py
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_import.py --sizes 512 2048 --repeats 3

Per ``--sizes`` S: a stack of S² — a base and one surface layer of smooth hills (``hills``; a steep relief's cast
shadows do not survive an 8-bit map, `tests/export/test_surface_import.py`) — exported to OpenRaster (`encode_ora`)
once per case, then imported (`import_ora`, median of ``--repeats``): with ``surfaces=False`` (the file's layers as
pixels: the baseline, in the same run) and as shipped (the pair made one surface layer again). Cases: ``fitted`` (a
directional light: the light fitted to the pixels), ``named`` (a point light with gloss: the fields its map's name
carries, rendered and checked) and ``shadowed`` (a directional light casting shadows and occlusion 0.8: its named
fields, the shadows' slack). ``*_extra_ms`` is the restore's cost over the baseline; ``*_restored`` whether the layer
came back (it must).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import torch  # noqa: E402
from _common import machine_info, print_json_line  # noqa: E402

from lasagna.compose.surface import normals_from_height  # noqa: E402
from lasagna.export import encode_ora, import_ora  # noqa: E402
from lasagna.io.stack import Stack  # noqa: E402

CASES = {
    "fitted": {"light": "az=120,el=50"},
    "named": {"light": "x=0.3,y=0.2,z=0.4", "gloss": 0.4},
    "shadowed": {"light": "az=200,el=70", "shadows": 0.8, "occlusion": 0.8},
}


def hills(size: int) -> Stack:
    """A base and a surface layer of five Gaussian hills, S²."""
    rows, cols = torch.meshgrid(torch.linspace(0, 1, size), torch.linspace(0, 1, size), indexing="ij")
    h = torch.zeros(size, size)
    for x, y, r, top in (
        (0.25, 0.3, 0.1, 0.15),
        (0.7, 0.25, 0.08, 0.1),
        (0.5, 0.6, 0.15, 0.2),
        (0.2, 0.8, 0.07, 0.08),
        (0.8, 0.75, 0.1, 0.12),
    ):
        h = h + top * torch.exp(-((cols - x) ** 2 + (rows - y) ** 2) / (2 * r * r))
    y = torch.linspace(0.55, 0.8, size).view(size, 1).expand(size, size)
    stack = Stack.from_image(torch.stack([y, 0.9 * y, 0.75 * y]))
    stack.add_surface("shape", normals_from_height(h[None, None])[0], "left")
    return stack


def timings(size: int, repeats: int, folder: Path) -> dict:
    out: dict = {}
    for case, fields in CASES.items():
        stack = hills(size)
        fields = dict(fields)
        light = fields.pop("light")
        stack.set_light("shape", light, **fields)
        path = folder / f"{case}-{size}.ora"
        path.write_bytes(encode_ora(stack))

        def once(surfaces: bool, path=path) -> tuple[float, object]:
            t0 = time.perf_counter()
            back = import_ora(path, warn=lambda line: None, surfaces=surfaces)
            return time.perf_counter() - t0, back

        once(False)  # warm: the zip, PNG decoders and the compositor's first call
        plain = sorted(once(False)[0] for _ in range(repeats))[repeats // 2]
        runs = [once(True) for _ in range(repeats)]
        restored = sorted(t for t, _ in runs)[repeats // 2]
        kinds = {layer.kind for layer in runs[-1][1].document.layers}
        out[f"{case}_plain_ms"] = round(plain * 1000, 1)
        out[f"{case}_ms"] = round(restored * 1000, 1)
        out[f"{case}_extra_ms"] = round((restored - plain) * 1000, 1)
        out[f"{case}_restored"] = "surface" in kinds
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[512, 2048])
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args(argv)
    rows = {}
    with tempfile.TemporaryDirectory() as tmp:
        for size in args.sizes:
            rows[str(size)] = timings(size, args.repeats, Path(tmp))
    print_json_line({"benchmark": "surface_import", "sizes": rows, "machine": machine_info()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
