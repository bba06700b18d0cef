"""``lasagna add-surface``: a normal map of one's own — baked in Blender, painted with Krita's tangent-normal brush,
made by a 2D-lighting tool — or, with ``--height PX``, a height (bump) map — added to a stack as a surface layer and
lit, with no learning.

The map is a PNG, 8- or 16-bit RGB (an alpha channel is ignored), in tangent space, +Y up (the OpenGL convention of
Blender, Krita and Godot) or, with ``--directx``, +Y down (green flipped: Unreal's and Substance's DirectX preset).
Its codes are read as they are stored — a normal map is data, not colour, so a colour profile it carries is not
applied. They are decoded to unit normals (`compose.surface.decode_normal_map`: renormalised, a zero vector read
as the flat normal; a height map's by its slopes, `lasagna.io.normal_map.height_map_normals`: white ``PX`` pixels above
black) and stored as the stack's 16-bit OpenGL map, so the layer renders and exports as every surface
layer does; ``lasagna light`` re-lights it afterwards.

The stack is written in place as ``lasagna light`` writes it (``save_in_place``): the new layer's PNG, stack.json
(the commit point), composite.png and a stack.ora the folder holds; no other layer PNG is written, and a stack.json
changed on disk since it was read is refused.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lasagna.errors import LasagnaError

HELP = (
    "add a normal map (or a height map) of your own to a stack as a surface layer, lit by a light you choose; "
    "no learning"
)
EXAMPLE = (
    "lasagna add-surface out/chelsea-left bumps.png --light top-left         # an OpenGL (+Y up) map",
    "lasagna add-surface out/chelsea-left unreal_n.png --directx --offset 32,16 --light x=0.2,y=0.3,z=0.5",
    "lasagna add-surface out/chelsea-left bump.png --height 12 --light az=250,el=60  # a grey height map, white 12 px",
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("stack", help="stack folder or its stack.json")
    p.add_argument(
        "map", help="the normal map: an 8- or 16-bit RGB PNG, tangent space (with --height: a grey height map)"
    )
    p.add_argument("--id", help="the new layer's id (default: made from the map's file name)")
    p.add_argument("--name", help="the new layer's name (default: its id)")
    p.add_argument(
        "--light", default="top-left", help="its light: a named light, az=A,el=E or x=X,y=Y,z=Z (default top-left)"
    )
    p.add_argument("--from", dest="source", help="a relight's source light: the layer becomes S(light)/S(source)")
    p.add_argument("--ambient", type=float, help="the ambient term a (default 0.25)")
    p.add_argument("--offset", metavar="X,Y", help="its top-left corner on the canvas, integer pixels (default 0,0)")
    p.add_argument("--directx", action="store_true", help="the map is +Y down (DirectX): its green is flipped")
    p.add_argument(
        "--height",
        type=float,
        metavar="PX",
        help="the map is a height (bump) map, grey: white PX pixels above black (as `lasagna export --height-map` "
        "writes one and prints its PX)",
    )


def parse_offset(text: str | None) -> tuple[int, int]:
    """``--offset X,Y``: two integers (the document model bounds them)."""
    if text is None:
        return 0, 0
    try:
        x, y = (int(v) for v in text.split(","))
    except ValueError:
        raise LasagnaError(f"got {text!r}; expected X,Y in integer pixels", where="--offset") from None
    return x, y


def run(args: argparse.Namespace) -> int:
    from lasagna.document import stack_file
    from lasagna.io.survey import survey_stack

    offset = parse_offset(args.offset)
    map_path = Path(args.map)
    survey = survey_stack(args.stack, composite=True)  # a refusal needs no torch

    from lasagna.io.normal_map import height_map_normals, normal_map_normals

    if args.height is not None and args.directx:
        raise LasagnaError("a height map has no green to flip; expected --height or --directx, not both", "--directx")
    # Refused before the stack is read.
    if args.height is not None:
        normals = height_map_normals(map_path, depth=args.height)
    else:
        normals = normal_map_normals(map_path, directx=args.directx)

    from lasagna.document.condition import AMBIENT
    from lasagna.document.types import unique_id
    from lasagna.export.ora import keep_ora_current
    from lasagna.io.folder import check_writable, save_in_place, stack_sha256
    from lasagna.io.stack import load_surveyed

    folder = stack_file(args.stack).parent
    check_writable(folder / "stack.json")
    check_writable(folder / "composite.png")
    sha = stack_sha256(folder)
    stack = load_surveyed(survey)
    taken = {i.casefold() for i in stack.document.all_ids}
    id = args.id if args.id is not None else unique_id(map_path.stem, set(taken))
    if id.casefold() in taken:
        raise LasagnaError(f"the stack already has a layer {id!r}; expected a new id", where="--id")
    unchanged = dict(stack.tensors)  # the PNGs on disk hold exactly these: only the new layer's is written
    stack.add_surface(
        id,
        normals,
        args.light,
        source_light=args.source,
        ambient=AMBIENT if args.ambient is None else args.ambient,
        name=args.name,
        offset=offset,
    )
    save_in_place(stack, unchanged=unchanged, expect_sha256=sha, extra=keep_ora_current(folder))
    h, w = normals.shape[-2:]
    print(f"added surface layer {id} ({w}x{h}, light {args.light}) to {folder}")
    return 0
