"""What a surface layer's cast shadows cost, and what they look like (`lasagna.compose.shadow`). Plain script; one
JSON line.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/surface_cast.py
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/surface_cast.py --sizes 512 --sheet docs/img/surface_cast_shadows.png

Per ``--sizes`` S: a stack of S² — a base and one surface layer, the normals of a relief of boxes, a pyramid and
domes (`relief`) — rendered (`render_stack`, median of ``--repeats`` after a warm-up) under a new light each time, as
a light drag re-lights it: without shadows (the baseline, in the same run), with ``shadows`` 0.8 under a directional
light, and under a point light; ``*_cold_ms`` the first render with shadows of a fresh map (the heights integrated
once, then kept per map); ``occluded_ms`` with ``occlusion`` 0.8 instead (``occluded_cold_ms``: a fresh map's
first, its sky share traced). ``--sheet``: per row — the relief, a shading surface read from a photograph (`lasagna
edit --layer shading`), a relight told its source light (`--from`) — the input, the layer lit low without and with
shadows, and a point light with shadows; a fifth column lit low with shadows and occlusion 0.8.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import machine_info, print_json_line, read_photo, save_sheet  # noqa: E402

from lasagna.compose.surface import normals_from_height  # noqa: E402
from lasagna.io.render import render_stack  # noqa: E402
from lasagna.io.stack import Stack  # noqa: E402

SHADOWS = 0.8
OCCLUSION = 0.8
LOW = "az=200,el=70"  # a low light from the left and a little below
POINT = "x=0.1,y=0.15,z=0.25"


def relief(size: int) -> torch.Tensor:
    """Heights (1, 1, S, S), canvas units: two boxes, a pyramid and three domes on a flat ground."""
    rows, cols = torch.meshgrid(torch.linspace(0, 1, size), torch.linspace(0, 1, size), indexing="ij")
    h = torch.zeros(size, size)
    h = torch.maximum(h, 0.12 * ((cols - 0.2).abs() < 0.08) * ((rows - 0.25).abs() < 0.1))
    h = torch.maximum(h, 0.2 * ((cols - 0.55).abs() < 0.05) * ((rows - 0.2).abs() < 0.12))
    h = torch.maximum(h, (0.25 - 1.6 * torch.maximum((cols - 0.75).abs(), (rows - 0.7).abs())).clamp_min(0))
    for x, y, r in ((0.25, 0.7, 0.12), (0.5, 0.55, 0.07), (0.85, 0.25, 0.09)):
        d2 = ((cols - x) ** 2 + (rows - y) ** 2) / (r * r)
        h = torch.maximum(h, 2 * r * (1 - d2).clamp_min(0).sqrt())
    return h[None, None]


def relief_stack(size: int) -> Stack:
    y = torch.linspace(0.55, 0.8, size).view(size, 1).expand(size, size)
    stack = Stack.from_image(torch.stack([y, 0.9 * y, 0.75 * y]))
    stack.add_surface("shape", normals_from_height(relief(size))[0], LOW)
    return stack


def timings(size: int, repeats: int) -> dict:
    stack = relief_stack(size)
    azimuths = itertools.count(0, 7)

    def once(**fields) -> float:
        az = next(azimuths) % 360
        light = fields.pop("light", f"az={az},el=70")
        stack.set_light("shape", light, **fields)
        t0 = time.perf_counter()
        render_stack(stack)
        return time.perf_counter() - t0

    def median(**fields) -> float:
        once(**fields)
        return sorted(once(**fields) for _ in range(repeats))[repeats // 2]

    plain = median(shadows=0.0)
    fresh = relief_stack(size)  # a map never rendered with shadows: its heights integrated on the first
    fresh.set_light("shape", LOW, shadows=SHADOWS)
    t0 = time.perf_counter()
    render_stack(fresh)
    cold = time.perf_counter() - t0
    shadowed = median(shadows=SHADOWS)
    points = [f"x={0.1 + 0.05 * k},y=0.2,z=0.25" for k in range(repeats + 1)]
    point = sorted(once(light=p, shadows=SHADOWS) for p in points)[repeats // 2]
    fresh = relief_stack(size)  # ambient occlusion of a fresh map: its sky share traced on the first render
    fresh.set_light("shape", LOW, occlusion=OCCLUSION)
    t0 = time.perf_counter()
    render_stack(fresh)
    occluded_cold = time.perf_counter() - t0
    occluded = median(shadows=0.0, occlusion=OCCLUSION)
    return {
        "size": size,
        "render_ms": round(plain * 1000, 1),
        "shadowed_ms": round(shadowed * 1000, 1),
        "shadowed_point_ms": round(point * 1000, 1),
        "shadowed_cold_ms": round(cold * 1000, 1),
        "occluded_ms": round(occluded * 1000, 1),
        "occluded_cold_ms": round(occluded_cold * 1000, 1),
    }


def sheet(path: Path) -> None:
    import lasagna

    rows = []
    base = relief_stack(512)
    rows.append((base.render().image, base, "shape"))
    cat = read_photo(ROOT / "examples" / "photos" / "large" / "chelsea.jpg")[0]
    made = lasagna.edit(cat, "shading", LOW)
    rows.append((cat, made.stack, made.layer_id))
    cup = read_photo(ROOT / "examples" / "photos" / "large" / "coffee.jpg")[0]
    made = lasagna.edit(cup, "relight", LOW, layer_kind="surface", source_light="az=120,el=45")
    rows.append((cup, made.stack, made.layer_id))
    columns: list[list[torch.Tensor]] = [[], [], [], [], []]
    looks = ((LOW, 0.0, 0.0), (LOW, SHADOWS, 0.0), (POINT, SHADOWS, 0.0), (LOW, SHADOWS, OCCLUSION))
    for image, stack, id in rows:
        columns[0].append(image)
        for k, (light, shadows, occlusion) in enumerate(looks):
            stack.set_light(id, light, shadows=shadows, occlusion=occlusion)
            columns[k + 1].append(stack.render().image)
    save_sheet(columns, path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sizes", nargs="+", type=int, default=[512, 2048])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument(
        "--sheet",
        type=Path,
        default=None,
        help="input | lit low | with shadows | a point light's | with shadows and occlusion",
    )
    args = p.parse_args(argv)
    rows = [timings(size, args.repeats) for size in args.sizes]
    for r in rows:
        print(r, file=sys.stderr)
    if args.sheet is not None:
        sheet(args.sheet)
    print_json_line({"benchmark": "surface_cast", **machine_info(), "sizes": rows, "command": " ".join(sys.argv)})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
