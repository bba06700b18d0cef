"""``lasagna export``: a stack as OpenRaster, layered PSD and/or one raw-value PNG per layer."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from lasagna.cli.common import depth_argument, max_pixels_argument, warn
from lasagna.errors import LasagnaError

HELP = "export a stack as OpenRaster, PSD and/or per-layer PNGs"
EXAMPLE = (
    "lasagna export examples/stacks/basic --ora out.ora --psd out.psd --layers out/layers",
    "lasagna export out/photo --normal-map photo-normals.png   # a surface layer's normal map",
    "lasagna export out/photo --normal-map photo-normals-dx.png --directx   # the same, +Y down (Unreal)",
    "lasagna export out/photo --height-map photo-heights.png   # and its heights (a displacement map)",
    "lasagna export out/photo --occlusion-map photo-ao.png     # and its ambient occlusion (an AO map)",
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("stack", help="stack folder or its stack.json")
    p.add_argument("--ora", help="OpenRaster file to write")
    p.add_argument("--psd", help="layered PSD file to write (needs the psd extra)")
    p.add_argument("--layers", metavar="DIR", help="folder for one raw-value PNG per layer")
    p.add_argument(
        "--normal-map",
        metavar="PNG",
        help="write a surface layer's normal map (16-bit RGB, tangent space, +Y up: the OpenGL convention of "
        "Blender, Krita and Godot), on the canvas, for a game or 2D-lighting engine",
    )
    p.add_argument(
        "--directx",
        action="store_true",
        help="write --normal-map +Y down instead (DirectX: green flipped, as Unreal and Substance's DirectX preset "
        "read it; `lasagna add-surface --directx` reads it back)",
    )
    p.add_argument(
        "--height-map",
        metavar="PNG",
        help="write a surface layer's height map (16-bit grey, the heights whose slopes best fit its normals; white "
        "is the peak, printed in pixels), on the canvas, for displacement or parallax",
    )
    p.add_argument(
        "--occlusion-map",
        metavar="PNG",
        help="write a surface layer's ambient-occlusion map (16-bit grey: the share of the sky each point of its "
        "heights sees, white open), on the canvas, for a game or 2D-lighting engine",
    )
    p.add_argument(
        "--surface",
        metavar="ID",
        help="which surface layer --normal-map, --height-map and --occlusion-map write (default: the topmost)",
    )
    depth_argument(p, "the PSD")
    max_pixels_argument(p)


def run(args: argparse.Namespace) -> int:
    from lasagna.atomic import atomic_write_all
    from lasagna.io.folder import check_not_input, check_writable
    from lasagna.io.survey import survey_stack

    maps = (args.normal_map, args.height_map, args.occlusion_map)
    if not (args.ora or args.psd or args.layers or any(maps)):
        raise LasagnaError(
            "nothing to export; expected at least one of --ora, --psd, --layers, --normal-map, --height-map, "
            "--occlusion-map",
            where="export",
        )
    if args.surface and not any(maps):
        raise LasagnaError(
            "--surface names the layer --normal-map, --height-map or --occlusion-map writes; expected one of them too",
            "--surface",
        )
    if args.directx and not args.normal_map:
        raise LasagnaError("--directx is the convention --normal-map writes in; expected --normal-map too", "--directx")
    for path in (args.ora, args.psd, *maps):
        if path:
            check_writable(path)
    if args.layers:
        check_writable(args.layers, folder=True)
    if args.psd:
        from lasagna.export.psd_tools_api import require_psd_tools

        require_psd_tools()  # fail before any work if psd-tools is missing
    # Decoded layers, the canvas, and the encoders' copies of the layers (about one more set): refused
    # here, before torch is loaded, when that is over the memory budget.
    survey = survey_stack(args.stack, max_pixels=args.max_pixels, composite=True, copies=1)

    from lasagna.export.png import layer_pngs
    from lasagna.io.render import render_stack
    from lasagna.io.stack import load_surveyed

    stack = load_surveyed(survey)
    composite = render_stack(stack)
    # Encode everything in memory first, then write all outputs or none (lasagna.atomic.atomic_write_all).
    outputs: list[tuple[Path, bytes]] = []
    if args.ora:
        from lasagna.export.ora import encode_ora

        outputs.append((Path(args.ora), encode_ora(stack, composite=composite, warn=warn)))
    if args.psd:
        from lasagna.export.psd import encode_psd

        outputs.append((Path(args.psd), encode_psd(stack, composite=composite, warn=warn, depth=args.depth)))
    if args.layers:
        folder = Path(args.layers)
        layer_files, meta = layer_pngs(stack)
        outputs += [(folder / name, data) for name, data in layer_files.items()]
        outputs.append((folder / "layers.json", (json.dumps(meta, indent=2) + "\n").encode("utf-8")))
    if args.normal_map:
        from lasagna.export.png import normal_map_png

        outputs.append((Path(args.normal_map), normal_map_png(stack, args.surface, directx=args.directx)))
    peak = None
    if args.height_map:
        from lasagna.export.png import height_map_png

        data, peak = height_map_png(stack, args.surface)
        outputs.append((Path(args.height_map), data))
    if args.occlusion_map:
        from lasagna.export.png import occlusion_map_png

        outputs.append((Path(args.occlusion_map), occlusion_map_png(stack, args.surface)))
    check_not_input([path for path, _ in outputs], stack)
    atomic_write_all(outputs)
    for path in (args.ora, args.psd, args.normal_map, args.occlusion_map):
        if path:
            print(f"wrote {path}")
    if args.height_map:
        print(f"wrote {args.height_map} (black 0, white {peak:.6g} pixels above it)")
    if args.layers:
        print(f"wrote {len(layer_files)} layer PNGs and layers.json to {folder}")
    return 0
