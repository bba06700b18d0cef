"""Relighting photographs toward opposite lights through the library call: does the light move? (issue #24)

    OMP_NUM_THREADS=2 python benchmarks/photo_swing.py                              # the selection set
    OMP_NUM_THREADS=2 python benchmarks/photo_swing.py --photos examples/photos/large   # the issue's four: a report

Each photograph (its long side at 512) is edited by ``lasagna.edit(image, PRESET, light)`` — the default
``lasagna edit --layer relight``, every preset field as shipped — toward ``left``, ``right``, ``top`` and
``bottom``. The swing of an edit is the mean of composite/input over the third of the image nearest the light
minus the farthest third (``_common.swing``); an axis's swing is the sum over its two edits. Issue #24's target
is ≥ 0.10 on every photograph and axis, ≥ 0.20 on average and never negative; a relight that cannot tell left
from right swings ~0.

``examples/photos/select`` (seven photographs other than the issue's, examples/photos/README.md) is where choices
for photographs are made; ``examples/photos/large`` is reported, never chosen on. A candidate (another estimator,
another preset field) is measured by a catalogue put first with ``LASAGNA_LAYERS`` (lasagna.catalogue: the first
entry of a name wins), e.g. a folder holding ``relight/preset.json`` and ``surface-lit-32`` (a link to the
candidate estimator). ``--sheet`` writes input | toward left | toward right | toward top | toward bottom per
photograph; ``--layer-sheet`` the layers toward the left: input | the surface alone (``layer_kind="surface"``) |
the edit's layer | its composite (layers shown at half their value, so 1 is mid-grey): what the distillation adds
to the surface, paint included, is seen there. ``--surface-sheet`` shows the surface layer itself (issue #24's
sheet): input | its normal map | its shading from the top-left | toward the left | toward the right. Ends with one
JSON line: per photograph and axis, the mean, the smallest and the count of wrong signs. ``--relief 1 2 3`` instead
reports the surface layer re-lit by its stored map at each relief gain (the editor's Relief slider; a user's
control, chosen by nobody here), with ``--relief-sheet``: input | left and right at each gain. ``--point`` reports
it re-lit by point lights beside each edge instead (``POINT_LIGHTS``; ``--point-sheet``: input | left and right by
directions | by point lights). ``--from PHOTO=LIGHT`` gives a photograph's source light as a person reads it: its
edits are the surface layer told that light (`lasagna edit --from`), what a user who knows the light gets.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import PHOTO_AXES, machine_info, print_json_line, read_photo, save_sheet, swing  # noqa: E402

import lasagna  # noqa: E402


def half(t: torch.Tensor) -> torch.Tensor:
    return F.interpolate(t[None], scale_factor=0.5, mode="area")[0]


def layer_tile(layer: torch.Tensor) -> torch.Tensor:
    """A multiplier layer (1, H, W) as a grey tile at half its value (1 → mid-grey), clamped."""
    return (layer[:1] / 2).clamp(0, 1).expand(3, -1, -1)


def surface_sheet(folder: Path, preset: str, path: Path) -> None:
    """Issue #24's sheet of the surface layer (``layer_kind="surface"``, as `lasagna edit --layer-kind surface`
    makes it): input | its stored normal map | its shading from the top-left | composite toward the left | toward
    the right, one row per photograph, at half size."""
    from lasagna.compose.surface import decode_normal_map, lambert, light_vector
    from lasagna.document.condition import parse_direction

    rows = []
    for file in sorted(folder.glob("*.jpg")):
        image = read_photo(file)[0]
        left = lasagna.edit(image, preset, "left", layer_kind="surface")
        right = lasagna.edit(image, preset, "right", layer_kind="surface")
        rgb = left.stack.tensors[left.layer_id].color  # the 16-bit tangent-space map, +Y up
        shading = lambert(decode_normal_map(rgb[None].float()), light_vector(*parse_direction("top-left"))[None])[0]
        shown = (image, rgb, shading.clamp(0, 1).expand(3, -1, -1), left.composite, right.composite)
        rows.append([half(t) for t in shown])
    save_sheet([list(column) for column in zip(*rows)], path)


def relief_report(folder: Path, preset: str, gains: list[float], sheet: Path | None) -> dict:
    """The surface layer (``layer_kind="surface"``) of each photograph, made once toward the left, re-lit by the
    stack itself (``Stack.set_light``: the stored map, no learning) toward each light of each axis at each relief
    gain: the swings per gain (a user's control, not a default: nothing here chooses it), and a sheet input | left
    and right at each gain."""
    per_gain: dict[float, list[float]] = {g: [] for g in gains}
    rows, tiles = [], []
    for file in sorted(folder.glob("*.jpg")):
        image = read_photo(file)[0]
        made = lasagna.edit(image, preset, "left", layer_kind="surface")
        stack, id = made.stack, made.layer_id
        row: dict = {"photo": file.stem}
        shown = [image]
        for g in gains:
            for axis, pair in PHOTO_AXES.items():
                total = 0.0
                for light in pair:
                    composite = stack.set_light(id, light, relief=g).render().image
                    total += swing(image, composite, light)
                    if axis == "left-right":
                        shown.append(composite)
                row[f"{axis} x{g:g}"] = round(total, 4)
                per_gain[g].append(total)
        rows.append(row)
        print(row, flush=True)
        tiles.append([half(t) for t in shown])
    if sheet is not None and tiles:
        save_sheet([list(column) for column in zip(*tiles)], sheet)
    return {
        "relief_rows": rows,
        "relief": {
            f"x{g:g}": {
                "swing_mean": round(sum(v) / len(v), 4),
                "below_0.10": sum(x < 0.10 for x in v),
                "wrong_signs": sum(x < 0 for x in v),
            }
            for g, v in per_gain.items()
        },
    }


POINT_LIGHTS = {
    "left": "x=-0.2,y=0.5,z=0.6",
    "right": "x=1.2,y=0.5,z=0.6",
    "top": "x=0.5,y=-0.2,z=0.6",
    "bottom": "x=0.5,y=1.2,z=0.6",
}
"""Point lights beside each edge of the photograph, 0.7 of its longer side from its centre and 0.6 above it."""


def point_report(folder: Path, preset: str, sheet: Path | None) -> dict:
    """The surface layer (``layer_kind="surface"``) of each photograph, made once toward the left, re-lit by the
    stack itself toward a point light beside each edge (``POINT_LIGHTS``: no learning): the swings, and a sheet
    input | toward the left and the right by the directions | by the point lights. A user's light, chosen by nobody
    here; the falloff brightens the near side whatever the surface says, so these swings are not the surface's."""
    rows, tiles, values = [], [], []
    for file in sorted(folder.glob("*.jpg")):
        image = read_photo(file)[0]
        made = lasagna.edit(image, preset, "left", layer_kind="surface")
        stack, id = made.stack, made.layer_id
        row: dict = {"photo": file.stem}
        for axis, pair in PHOTO_AXES.items():
            total = sum(swing(image, stack.set_light(id, POINT_LIGHTS[lt]).render().image, lt) for lt in pair)
            row[axis] = round(total, 4)
            values.append(total)
        rows.append(row)
        print(row, flush=True)
        shown = [image, *(stack.set_light(id, lt).render().image for lt in ("left", "right"))]
        shown += [stack.set_light(id, POINT_LIGHTS[lt]).render().image for lt in ("left", "right")]
        tiles.append([half(t) for t in shown])
    if sheet is not None and tiles:
        save_sheet([list(column) for column in zip(*tiles)], sheet)
    return {
        "point_rows": rows,
        "point": {
            "swing_mean": round(sum(values) / len(values), 4),
            "below_0.10": sum(v < 0.10 for v in values),
            "wrong_signs": sum(v < 0 for v in values),
        },
    }


def measure(
    folder: Path,
    preset: str,
    sheet: Path | None,
    layer_sheet: Path | None = None,
    sources: dict[str, str] | None = None,
) -> dict:
    """``sources``: per photograph (its stem), the source light a person gave (``--from``): its edits are
    ``lasagna.edit(..., source_light=L)``, the surface layer told L, as `lasagna edit --from L` makes it."""
    rows, tiles, layer_tiles, seconds = [], [], [], []
    sources = sources or {}
    for file in sorted(folder.glob("*.jpg")):
        image = read_photo(file)[0]
        row: dict = {"photo": file.stem}
        told = {"source_light": sources[file.stem]} if file.stem in sources else {}
        if told:
            row["from"] = told["source_light"]
        composites = {}
        for axis, pair in PHOTO_AXES.items():
            total = 0.0
            for light in pair:
                t0 = time.perf_counter()
                result = lasagna.edit(image, preset, light, **told)
                seconds.append(time.perf_counter() - t0)
                composites[light] = result.composite
                if light == "left" and layer_sheet is not None:
                    surface = lasagna.edit(image, preset, light, layer_kind="surface").layer
                    shown = (image, layer_tile(surface), layer_tile(result.layer), result.composite)
                    layer_tiles.append([half(t) for t in shown])
                total += swing(image, result.composite, light)
            row[axis] = round(total, 4)
        rows.append(row)
        print(row, flush=True)
        row_tiles = [image, *(composites[light] for light in ("left", "right", "top", "bottom"))]
        tiles.append([half(t) for t in row_tiles])
    if sheet is not None and tiles:
        save_sheet([list(column) for column in zip(*tiles)], sheet)
    if layer_sheet is not None and layer_tiles:
        save_sheet([list(column) for column in zip(*layer_tiles)], layer_sheet)
    values = [r[axis] for r in rows for axis in PHOTO_AXES if axis in r]
    return {
        "photos": rows,
        "swing_mean": round(sum(values) / len(values), 4),
        "swing_min": round(min(values), 4),
        "wrong_signs": sum(v < 0 for v in values),
        "below_0.10": sum(v < 0.10 for v in values),
        "seconds_per_edit_median": round(sorted(seconds)[len(seconds) // 2], 3),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--photos", type=Path, default=ROOT / "examples" / "photos" / "select")
    p.add_argument("--preset", default="relight")
    p.add_argument("--sheet", type=Path, default=None, help="input | left | right | top | bottom, one row per photo")
    p.add_argument(
        "--layer-sheet", type=Path, default=None, help="toward the left: input | surface alone | layer | composite"
    )
    p.add_argument(
        "--surface-sheet",
        type=Path,
        default=None,
        help="the surface layer: input | normal map | shading from the top-left | toward left | toward right",
    )
    p.add_argument("--label", default="", help="a name for this candidate in the JSON line")
    p.add_argument(
        "--from",
        dest="sources",
        nargs="+",
        default=[],
        metavar="PHOTO=LIGHT",
        help="a source light a person gave for a photograph (its file's stem), e.g. coffee=az=120,el=45: its edits "
        "are made told it (`lasagna edit --from`)",
    )
    p.add_argument(
        "--relief",
        nargs="+",
        type=float,
        default=None,
        metavar="G",
        help="instead: the surface layer re-lit at these relief gains (`relief` of the stack's surface layer)",
    )
    p.add_argument("--relief-sheet", type=Path, default=None, help="with --relief: input | left, right at each gain")
    p.add_argument(
        "--point",
        action="store_true",
        help="instead: the surface layer re-lit by point lights beside each edge (POINT_LIGHTS; a user's light)",
    )
    p.add_argument(
        "--point-sheet", type=Path, default=None, help="with --point: input | left, right by directions | by points"
    )
    args = p.parse_args(argv)
    torch.manual_seed(0)
    record = {
        "benchmark": "photo_swing",
        "machine": machine_info(),
        "photos_folder": str(args.photos),
        "preset": args.preset,
    }
    if args.point:
        record.update(point_report(args.photos, args.preset, args.point_sheet))
    elif args.relief:
        record.update(relief_report(args.photos, args.preset, args.relief, args.relief_sheet))
    else:
        if args.surface_sheet is not None:
            surface_sheet(args.photos, args.preset, args.surface_sheet)
        record.update(catalogue_first=os.environ.get("LASAGNA_LAYERS", ""), label=args.label)
        sources = dict(spec.split("=", 1) for spec in args.sources)
        record.update(measure(args.photos, args.preset, args.sheet, args.layer_sheet, sources))
    print_json_line(record)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
