"""``lasagna edit``: add a learned layer to an image or a stack; writes a stack folder.

    lasagna edit IMAGE --layer shading --condition left -o OUT [--on ID] [--optimize N] [--loss NAME]
                 [--guidance W] [--steps N] [--seed S] [--lr LR] [--generator amortised|free] [--force]

IMAGE is a PNG/JPEG or a stack folder; OUT is a new (or empty) folder, written through a temporary
sibling folder renamed at the end (``lasagna.io.folder``), so a failure leaves nothing half-written.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from lasagna.cli.common import distill_arguments, progress, warn
from lasagna.errors import LasagnaError, PathError

HELP = "add a learned layer (relight, colourise, …) to an image or stack; writes a stack folder"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lasagna.io.image import DEFAULT_EDIT_MAX_PIXELS

    p.add_argument("image", help="a PNG/JPEG image, or a stack folder (the layer goes on top of it)")
    p.add_argument(
        "--layer",
        default="shading",
        metavar="PRESET",
        help="learned-layer preset (default shading; see 'lasagna layers')",
    )
    p.add_argument("--condition", required=True, metavar="LABEL", help="a label of the preset's vocabulary, e.g. left")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="stack folder to write (new or empty)")
    p.add_argument("--on", metavar="ID", help="condition on the composite up to this layer (default: the top layer)")
    p.add_argument("--id", help="id of the new layer (default PRESET-LABEL)")
    p.add_argument(
        "--generator",
        choices=("amortised", "free"),  # the methods of lasagna.learned, "per-image" spelled as its alias "free"
        help="amortised: the preset's trained generator, one forward pass; free: a per-pixel layer "
        "optimised for this image (default: amortised when the preset has one)",
    )
    p.add_argument(
        "--optimize",
        type=int,
        metavar="N",
        help="per-image optimisation steps (after the amortised pass; default: the preset's refine_steps, "
        "or its distill.steps for a free layer)",
    )
    p.add_argument("--steps", type=int, metavar="N", help="the same number as --optimize, named as in the preset")
    distill_arguments(p)
    p.add_argument("--no-ora", action="store_true", help="do not write stack.ora")
    p.add_argument("--force", action="store_true", help="replace OUT if it already holds a stack")
    p.add_argument(
        "--max-pixels",
        type=int,
        default=DEFAULT_EDIT_MAX_PIXELS,
        metavar="N",
        help=f"refuse images with more than N pixels (default {DEFAULT_EDIT_MAX_PIXELS})",
    )


def run(args: argparse.Namespace) -> int:
    from lasagna.io.folder import check_output_folder
    from lasagna.io.image import probe_image_file
    from lasagna.io.survey import survey_stack

    out = check_output_folder(args.output, force=args.force)
    # The input's format, size and memory checked before torch and the priors are loaded.
    image = Path(args.image)
    if image.is_dir() or image.suffix.lower() == ".json":
        survey_stack(image, max_pixels=args.max_pixels)
    elif image.exists():
        probe_image_file(image, max_pixels=args.max_pixels)

    from lasagna.edit import edit

    if Path(args.image).resolve() == out.resolve() and not args.force:
        raise PathError("is the input stack; expected another folder (or --force to replace it)", str(out))
    if args.optimize is not None and args.steps is not None and args.optimize != args.steps:
        raise LasagnaError(
            f"optimize {args.optimize} and steps {args.steps} differ; expected one of them (they are the same number)",
            "steps",
        )
    optimize = args.optimize if args.optimize is not None else args.steps  # --steps: --optimize's other name
    result = edit(
        args.image,
        args.layer,
        args.condition,
        on=args.on,
        id=args.id,
        generator=args.generator,
        optimize=optimize,
        loss=args.loss,
        guidance=args.guidance,
        seed=args.seed,
        lr=args.lr,
        max_pixels=args.max_pixels,
        device=args.device,
        progress=progress(),
    )
    result.save(out, force=args.force, ora=not args.no_ora, warn=warn)
    s = result.settings
    how = (
        "amortised generator, one forward pass"
        if s["method"] == "amortised" and not s["optimize"]
        else (
            f"amortised generator + {s['optimize']} per-image steps"
            if s["method"] == "amortised"
            else f"per-image optimisation, {len(result.history)} of {s['optimize']} steps "
            f"({s['distill']['loss']}, ω = {s['distill']['guidance']:g})"
        )
    )
    lo, hi = float(result.layer.min()), float(result.layer.max())
    print(f"wrote {out}/ (layer {result.layer_id!r}: {how}; values in [{lo:.3g}, {hi:.3g}]; {result.seconds:.1f} s)")
    print(
        f"  {out / 'composite.png'}, {out / 'stack.json'}, {out / 'layers'}/"
        + ("" if args.no_ora else f", {out / 'stack.ora'}")
    )
    return 0
