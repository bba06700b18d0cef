"""``lasagna light``: re-light a stack's surface layer in place — its light, source light, ambient, relief, colour,
intensity, gloss, shadows, occlusion or extra lights — from its stored normal map, with no learning (what dragging the
editor's light sphere or its sliders does).

Only stack.json (the commit point), composite.png and a stack.ora the folder holds change: no layer PNG is
written (``save_in_place`` with every layer unchanged), and a stack.json changed on disk since it was read is
refused. ``--read-again`` is the one exception: a relight's surface is estimated again told its source light
(``lasagna.editing.reread_surface``, the editor's "Read again from this source light"), so that layer's normal map
is written too."""

from __future__ import annotations

import argparse
from pathlib import Path

from lasagna.errors import LasagnaError

HELP = (
    "re-light a stack's surface layer in place (light, source light, ambient, relief, colour, intensity, gloss, "
    "shadows, occlusion, more lights); no learning"
)
EXAMPLE = (
    "lasagna light out/chelsea-surface --light az=30,el=45                  # the topmost surface layer",
    "lasagna light out/coffee-sl --layer relight-left --from top --relief 2  # a relight's source light, deeper",
    "lasagna light out/coffee-sl --from top --read-again                    # and its surface read again told it",
    "lasagna light out/chelsea-surface --light x=0.1,y=0.3,z=0.4            # a point light near the left edge",
    "lasagna light out/chelsea-surface --light x=0.2,y=0.1,z=0.3,cone=25,ax=0.5,ay=0.6  # a spot aimed at the eyes",
    "lasagna light out/chelsea-surface --add-light 'right;#a0c0ff;0.5'      # and a blue fill light from the right",
    "lasagna light out/chelsea-surface --gloss 0.4 --shininess 24           # a highlight where the light falls",
    "lasagna light out/chelsea-surface --light az=250,el=70 --shadows 0.8   # a low light, its bumps casting shadows",
    "lasagna light out/chelsea-surface --occlusion 0.7                      # less ambient light in its creases",
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("stack", help="stack folder or its stack.json")
    p.add_argument("--layer", metavar="ID", help="the surface layer (default: the topmost)")
    p.add_argument(
        "--light",
        help="the light it is lit by: a named light, az=A,el=E, or a point light x=X,y=Y,z=Z (x, y: fractions of the "
        "layer from its top-left; z: height in units of its longer side), a spot light with ',cone=C' (half-angle, "
        "degrees) and optionally ',ax=X,ay=Y' (its aim; default the point beneath it) and ',blend=B' (edge softness "
        "0–1, default 0.15) (default: kept)",
    )
    p.add_argument(
        "--from",
        dest="source",
        metavar="LIGHT",
        help="a relight's source light (the ratio divides by it), or 'none' for plain shading (default: kept)",
    )
    p.add_argument("--ambient", type=float, help="the ambient term a of a + (1 − a)·max(0, n·l) (default: kept)")
    p.add_argument("--relief", type=float, help="the relief gain: the map's slopes times this (default: kept)")
    p.add_argument(
        "--color",
        metavar="R,G,B",
        help="the light's colour, three numbers in [0, 1] or #rrggbb (its direct term; default: kept)",
    )
    p.add_argument(
        "--add-light",
        action="append",
        metavar="LIGHT[;COLOUR[;K]]",
        help="one more light, added to the layer's (repeatable): a light as --light, then optionally its colour "
        "(#rrggbb or R,G,B) and intensity, ';'-separated, e.g. 'x=0.9,y=0.2,z=0.5;#a0c0ff;0.6'",
    )
    p.add_argument("--clear-lights", action="store_true", help="remove the layer's extra lights (before --add-light)")
    p.add_argument(
        "--read-again",
        action="store_true",
        help="a relight made by lasagna edit: estimate its surface again told its source light (--from, or the one it "
        "has), as `lasagna edit --from` does — the preset's told estimator, about a second; its normal map is "
        "rewritten (the other changes need no learning)",
    )
    p.add_argument(
        "--within",
        type=float,
        metavar="DEG",
        help="with --read-again: the source light is a rough reading, off by up to about DEG degrees; its elevation is "
        "fused with the estimator's own fit (as lasagna edit --within)",
    )
    p.add_argument(
        "--intensity",
        type=float,
        help="the light's intensity k: its direct term times k; above 1 a shading layer brightens (default: kept)",
    )
    p.add_argument(
        "--gloss",
        type=float,
        metavar="G",
        help="a highlight's strength in [0, 1] (Blinn-Phong, as Lighting Effects' Gloss; 0: none; default: kept)",
    )
    p.add_argument(
        "--shininess",
        type=float,
        metavar="P",
        help="the highlight's exponent in [1, 1024]: larger is smaller and sharper (32 by default; default: kept)",
    )
    p.add_argument(
        "--shadows",
        type=float,
        metavar="S",
        help="cast shadows' strength in [0, 1]: each light's direct term where the surface's own heights hide it "
        "times 1 - S (0: none; default: kept)",
    )
    p.add_argument(
        "--shadow-depth",
        type=float,
        metavar="D",
        help="the heights shadows and occlusion are traced over, times D in (0, 16]: longer shadows, deeper creases; "
        "the shading unchanged (1 by default; default: kept)",
    )
    p.add_argument(
        "--occlusion",
        type=float,
        metavar="O",
        help="ambient occlusion's strength in [0, 1]: the ambient term times 1 - O*(1 - the share of the sky each "
        "point of the surface's heights sees) (0: none; default: kept)",
    )


def run(args: argparse.Namespace) -> int:
    from lasagna.document import stack_file
    from lasagna.io.survey import survey_stack

    fields = (args.light, args.source, args.ambient, args.relief, args.color, args.intensity, args.add_light)
    fields += (args.gloss, args.shininess, args.shadows, args.occlusion, args.shadow_depth)
    if all(v is None for v in fields) and not (args.clear_lights or args.read_again):
        raise LasagnaError(
            "nothing to change; expected at least one of --light, --from, --ambient, --relief, --color, --intensity, "
            "--gloss, --shininess, --shadows, --shadow-depth, --occlusion, --add-light, --clear-lights, --read-again",
            where="light",
        )
    if args.within is not None and not args.read_again:
        raise LasagnaError(
            "says how rough the source light is for reading the surface again; expected --read-again too", "--within"
        )
    added = [parse_extra_light(spec) for spec in args.add_light or ()]
    colour = None if args.color is None else parse_colour(args.color)
    survey = survey_stack(args.stack, composite=True)  # a refusal needs no torch

    from lasagna.document import SurfaceLayer

    folder = stack_file(args.stack).parent
    surfaces = [layer for _, layer in survey.document.walk() if isinstance(layer, SurfaceLayer)]
    if not surfaces:
        raise LasagnaError("the stack has no surface layer; expected one to re-light", where=str(folder))
    if args.layer is None:
        layer = surfaces[-1]
    else:
        named = [layer for layer in surfaces if layer.id == args.layer]
        if not named:
            ids = ", ".join(layer.id for layer in surfaces)
            raise LasagnaError(f"no surface layer {args.layer!r}; expected one of {ids}", where="--layer")
        layer = named[0]
    source = ... if args.source is None else (None if args.source.lower() == "none" else args.source)
    change = dict(
        source_light=source,
        ambient=args.ambient,
        relief=args.relief,
        light_color=colour,
        light_intensity=args.intensity,
        gloss=args.gloss,
        shininess=args.shininess,
        shadows=args.shadows,
        occlusion=args.occlusion,
        shadow_depth=args.shadow_depth,
        extra_lights=None
        if not (added or args.clear_lights)
        else [*(() if args.clear_lights else layer.extra_lights), *added],
    )
    # The re-lit layer checked by the document's model now, so a bad light is refused before any tensor is read.
    survey.document.relit(layer.id, args.light or layer.light, **change)

    from lasagna.export.ora import keep_ora_current
    from lasagna.io.folder import check_writable, save_in_place, stack_sha256
    from lasagna.io.stack import load_surveyed

    check_writable(folder / "stack.json")
    check_writable(folder / "composite.png")
    sha = stack_sha256(folder)
    stack = load_surveyed(survey)
    unchanged = dict(stack.tensors)  # the PNGs on disk hold exactly these: none is written again
    stack.set_light(layer.id, args.light or layer.light, **change)
    said = []
    if args.read_again:
        from lasagna.editing import reread_surface

        reread_surface(stack, layer.id, within=args.within)  # one-line refusals: plain shading, a map of one's own
        unchanged.pop(layer.id)
        said.append(f"read again by {stack.document.layer(layer.id).made_by.get('told_estimator', 'its estimator')}")
    save_in_place(stack, unchanged=unchanged, expect_sha256=sha, extra=keep_ora_current(folder))
    lit = stack.document.layer(layer.id)
    said.append(f"light {lit.light}")
    if lit.source_light is not None:
        said.append(f"from {lit.source_light}")
    said += [f"ambient {lit.ambient:g}", f"relief {lit.relief:g}"]
    if tuple(lit.light_color) != (1.0, 1.0, 1.0):
        said.append("colour " + ",".join(f"{c:.4g}" for c in lit.light_color))
    if lit.light_intensity != 1.0:
        said.append(f"intensity {lit.light_intensity:g}")
    if lit.gloss > 0:
        said.append(f"gloss {lit.gloss:g} (shininess {lit.shininess:g})")
    if lit.shadows > 0:
        said.append(f"shadows {lit.shadows:g}")
    if lit.occlusion > 0:
        said.append(f"occlusion {lit.occlusion:g}")
    if (lit.shadows > 0 or lit.occlusion > 0) and lit.shadow_depth != 1.0:
        said.append(f"shadow depth {lit.shadow_depth:g}")
    if lit.extra_lights:
        said.append(f"{len(lit.extra_lights)} more light" + ("s" if len(lit.extra_lights) > 1 else ""))
    wrote = "stack.json, composite.png" + (f", {lit.source}" if args.read_again else "")
    wrote += " and stack.ora" if (folder / "stack.ora").is_file() else ""
    print(f"re-lit {layer.id}: {', '.join(said)}; wrote {wrote} in {Path(folder)}")
    return 0


def parse_extra_light(spec: str) -> dict:
    """``--add-light LIGHT[;COLOUR[;K]]``: the extra light's fields (each checked by the document model)."""
    parts = spec.split(";")
    if len(parts) > 3 or not parts[0].strip():
        raise LasagnaError(f"got {spec!r}; expected LIGHT[;COLOUR[;INTENSITY]]", where="--add-light")
    out: dict = {"light": parts[0].strip()}
    if len(parts) > 1 and parts[1].strip():
        out["color"] = parse_colour(parts[1], where="--add-light")
    if len(parts) > 2:
        try:
            out["intensity"] = float(parts[2])
        except ValueError:
            raise LasagnaError(f"got {spec!r}; its intensity is not a number", where="--add-light") from None
    return out


def parse_colour(text: str, where: str = "--color") -> tuple[float, float, float]:
    """``--color``: ``#rrggbb`` or three comma-separated numbers (range-checked by the document model)."""
    t = text.strip()
    parts: list[float] = []
    try:
        if t.startswith("#") and len(t) == 7:
            parts = [int(t[k : k + 2], 16) / 255.0 for k in (1, 3, 5)]
        else:
            parts = [float(v) for v in t.split(",")]
    except ValueError:
        parts = []
    if len(parts) != 3:
        raise LasagnaError(f"got {text!r}; expected #rrggbb or R,G,B (three numbers in [0, 1])", where=where)
    return parts[0], parts[1], parts[2]
