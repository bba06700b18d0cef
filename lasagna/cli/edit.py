"""``lasagna edit``: add a learned layer to an image or a stack; writes a stack folder.

    lasagna edit IMAGE --layer shading --condition left -o OUT [--on ID] [--optimize N] [--loss NAME]
                 [--guidance W] [--steps N] [--seed S] [--lr LR] [--generator amortised|free] [--force]
    lasagna edit IMAGE --prior SD_FOLDER [--controlnet CN [--controlnet-scale S]]… [--control-image IMG]
                 --prompt "dramatic rim light" [--negative-prompt TEXT] [--corrective B_HAT] -o OUT
                 [--dtype auto|float16|bfloat16|float32] [--variant fp16] [--cpu-offload] [--attention-slicing]
                 [--channels-last] [--t-min T] [--t-max T] [--particles K] [--aspect letterbox|stretch]
    lasagna edit IMAGE… | FOLDER | 'GLOB' --condition left -o OUTDIR [--batch-size N] [--force]
    torchrun --nproc_per_node=N -m lasagna.cli edit 'photos/**/*.png' --condition left -o OUTDIR

IMAGE is a PNG/JPEG or a stack folder; OUT is a new (or empty) folder, written through a temporary
sibling folder renamed at the end (``lasagna.io.folder``), so a failure leaves nothing half-written.

**Many inputs** — more than one, a folder that is not a stack folder, or a glob pattern (expanded here, so
quote it: ``**`` crosses folders) — and OUTDIR holds one stack folder per input, ``OUTDIR/<stem>/``
(``lasagna.batch``: names, resumption, shards). A stack folder among them is edited on top, as alone.
Each output records its source file (path under the folder given, size, hash) and what was asked; a
complete output is skipped when both match, redone when its source changed (one line says so), refused in
one line when it was made with another condition or layer (``--force`` rewrites them), so running again
after a kill finishes the rest.
Each failure is one line on stderr, ``lasagna: error: <input>: <what>``, and the others are still written;
the last line on stdout is ``edited N, skipped K (complete), failed F``; exit status 2 if any failed. Under
``torchrun`` (``WORLD_SIZE`` > 1) every process takes its shard and rank 0 reports for all.
"""

from __future__ import annotations

import argparse
import dataclasses
import glob
import json
import os
import sys
from pathlib import Path

from lasagna.cli.common import PROG, depth_argument, distill_arguments, phase, progress, warn
from lasagna.errors import LasagnaError, PathError, printable

HELP = "add a learned layer (relight, colourise, …) to an image or stack; writes a stack folder"
EXAMPLE = (
    "lasagna edit examples/photos/chelsea.png --layer shading --condition left -o out/chelsea-left",
    "lasagna edit 'shots/**/*.jpg' --condition top -o out/top   # many: out/top/<stem>/ each",
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lasagna.io.image import DEFAULT_EDIT_MAX_PIXELS

    p.add_argument(
        "image",
        nargs="+",
        help="a PNG/JPEG image, or a stack folder (the layer goes on top of it); several, a folder of images "
        "or a quoted glob: one stack folder each under OUT",
    )
    p.add_argument(
        "--layer",
        default="shading",
        metavar="PRESET",
        help="learned-layer preset (default shading; see 'lasagna layers')",
    )
    p.add_argument(
        "--condition",
        metavar="LABEL",
        help="a label of the preset's vocabulary, e.g. left (default: the preset's first label, shading's 'left'; "
        "with --prompt, the prompt's own label); required with many inputs",
    )
    p.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="OUT",
        help="stack folder to write (new or empty); with many inputs, the folder to hold one per input",
    )
    p.add_argument("--on", metavar="ID", help="condition on the composite up to this layer (default: the top layer)")
    p.add_argument("--id", help="id of the new layer (default PRESET-LABEL)")
    p.add_argument(
        "--generator",
        choices=("amortised", "free"),  # the methods of lasagna.learned, "per-image" spelled as its alias "free"
        help="amortised: the preset's trained generator, one forward pass; free: a per-pixel layer "
        "optimised for this image (default: the preset's method; shading: free)",
    )
    p.add_argument(
        "--optimize",
        type=int,
        metavar="N",
        help="per-image optimisation steps (after the amortised pass; default: the preset's refine_steps, "
        "or its distill.steps for a free layer)",
    )
    p.add_argument("--steps", type=int, metavar="N", help="the same number as --optimize, named as in the preset")
    p.add_argument(
        "--layer-kind",
        choices=("free", "surface"),
        help="free: a per-pixel multiplier; surface: a surface lit by the condition's light (any az=…,el=…), "
        "re-lit by editing its light (default: the preset's)",
    )
    p.add_argument(
        "--from",
        dest="source_light",
        metavar="LIGHT",
        help="a relight's source light (named or az=…,el=…), when you know it: the layer is then the surface read "
        "told it (a surface layer; default: the light estimated)",
    )
    p.add_argument(
        "--within",
        dest="source_within",
        type=float,
        metavar="DEG",
        help="with --from: how far your reading of the source light may be off (degrees); its elevation is then "
        "fused with the estimator's own fit, its azimuth kept — give it unless you know the light to a few degrees",
    )
    distill_arguments(p)
    own_prior_arguments(p)
    p.add_argument("--no-ora", action="store_true", help="do not write stack.ora")
    depth_argument(p, "composite.png (RGBA where the input has alpha)")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace OUT if it already holds a stack (many inputs: redo the complete ones too)",
    )
    p.add_argument(
        "--json",
        action="store_true",
        help="many inputs: one JSON object per input (input, output, status, seconds, note, error) and a summary "
        "object last, on stdout — for machines",
    )
    p.add_argument(
        "--batch-size",
        type=int,
        default=1,
        metavar="N",
        help="many inputs: run the amortised generator on N images at once (default 1: each exactly as alone; "
        "raise it on a GPU)",
    )
    p.add_argument(
        "--max-pixels",
        type=int,
        default=DEFAULT_EDIT_MAX_PIXELS,
        metavar="N",
        help=f"refuse images with more than N pixels (default {DEFAULT_EDIT_MAX_PIXELS}: what refuses a photo is "
        "the memory budget, ~24 MP at the default 8G)",
    )


def own_prior_arguments(p: argparse.ArgumentParser) -> None:
    """A prior of one's own (``lasagna.editing``'s "Bring your own prior"), its prompts and how it runs."""
    from lasagna.document.preset import ASPECTS, TORCH_DTYPES

    g = p.add_argument_group("a prior of your own (a diffusers folder written by save_pretrained)")
    g.add_argument("--prior", metavar="PATH", help="the prior folder (SD 1.x/2.x/SDXL diffusers folder) or name")
    g.add_argument(
        "--controlnet", action="append", default=[], metavar="PATH", help="a ControlNet folder (repeat for several)"
    )
    g.add_argument(
        "--controlnet-scale",
        action="append",
        type=float,
        default=[],
        metavar="S",
        help="residual scale of each --controlnet, in order (one for all, or one per net; default 1)",
    )
    g.add_argument(
        "--control-image", metavar="IMG", help="the ControlNet's conditioning image (default: the base), same aspect"
    )
    g.add_argument("--prompt", metavar="TEXT", help="free text instead of the preset's template")
    g.add_argument("--negative-prompt", metavar="TEXT", help="text replacing the unconditional branch")
    g.add_argument("--corrective", metavar="PATH", help="the prior's b̂ for LMC-SDS (lasagna train-corrective)")
    g.add_argument("--dtype", choices=TORCH_DTYPES, help="networks' float type (default auto)")
    g.add_argument("--variant", metavar="NAME", help="weight files' variant, e.g. fp16")
    g.add_argument("--cpu-offload", action="store_true", default=None, help="model CPU offload (CUDA)")
    g.add_argument("--attention-slicing", action="store_true", default=None, help="attention in slices")
    g.add_argument("--channels-last", action="store_true", default=None, help="NHWC activations")
    g.add_argument("--conditioning-scale", type=float, metavar="S", help="scale of nets without their own")
    g.add_argument("--t-min", type=float, metavar="T", help="t ~ U(t_min, t_max): lower end (default the preset's)")
    g.add_argument("--t-max", type=float, metavar="T", help="upper end (default the preset's)")
    g.add_argument(
        "--particles",
        type=int,
        metavar="K",
        help="per-image: K layers with their own noise draws, averaged (K× the passes; default the preset's)",
    )
    g.add_argument(
        "--aspect",
        choices=ASPECTS,
        help="another aspect than the prior's: letterbox (kept) or stretch (default the preset's, letterbox)",
    )


def _own_prior_options(args: argparse.Namespace) -> dict:
    """``edit``'s own-prior keywords from the arguments (only those given)."""
    nets, scales = args.controlnet, args.controlnet_scale
    if scales and len(scales) not in (1, len(nets)):
        raise LasagnaError(
            f"got {len(scales)} --controlnet-scale for {len(nets)} --controlnet; expected one, or one per net",
            "--controlnet-scale",
        )
    pairs = [(net, scales[0] if len(scales) == 1 else scales[i]) if scales else net for i, net in enumerate(nets)]
    names = {
        "dtype": "torch_dtype",
        "variant": "variant",
        "cpu_offload": "cpu_offload",
        "attention_slicing": "attention_slicing",
        "channels_last": "channels_last",
        "conditioning_scale": "conditioning_scale",
    }
    diffusers = {field: getattr(args, arg) for arg, field in names.items() if getattr(args, arg) is not None}
    options = dict(
        prior=args.prior,
        controlnets=pairs,
        corrective=args.corrective,
        control_image=args.control_image,
        prompt=args.prompt,
        negative_prompt=args.negative_prompt,
        diffusers=diffusers or None,
        t_min=args.t_min,
        t_max=args.t_max,
        aspect=args.aspect,
        particles=args.particles,
    )
    return {k: v for k, v in options.items() if v not in (None, [])}


def many_inputs(images: list[str]) -> bool:
    """Whether ``images`` asks for a batch: several, a folder without stack.json, or a glob matching no file."""
    if len(images) != 1:
        return True
    p = Path(images[0])
    if p.is_dir():
        return not (p / "stack.json").is_file()
    return not os.path.lexists(p) and glob.has_magic(images[0])


def _request(args: argparse.Namespace):
    """The ``EditRequest`` of the arguments (``lasagna.request``: checked there, as for every caller)."""
    from lasagna.request import EditRequest

    return EditRequest(
        preset=args.layer,
        condition=args.condition,
        on=args.on,
        id=args.id,
        generator=args.generator,
        optimize=args.optimize,
        steps=args.steps,  # --optimize's other name
        loss=args.loss,
        guidance=args.guidance,
        seed=args.seed,
        lr=args.lr,
        layer_kind=args.layer_kind,
        source_light=args.source_light,
        source_within=args.source_within,
        **_own_prior_options(args),
    )


def run(args: argparse.Namespace) -> int:
    if many_inputs(args.image):
        return run_many(args)
    args.image = args.image[0]
    return run_one(args)


def run_many(args: argparse.Namespace) -> int:
    """Many inputs, one stack folder each under OUTDIR (``lasagna.batch.edit_many``), sharded under torchrun."""
    from lasagna.batch import edit_many
    from lasagna.training.loop import init_distributed, shutdown_distributed

    request = _request(args)  # refused before the process group is joined
    if _own_prior_options(args):
        raise LasagnaError(
            "--prior, --prompt and their options take one input; expected one image or stack (a loop in the shell "
            "for many)",
            "edit",
        )
    if args.condition is None:
        raise LasagnaError("the following argument is required with many inputs: --condition", "edit")
    info = init_distributed(args.device)  # nothing without torchrun's WORLD_SIZE > 1; gloo on CPU
    try:
        report = edit_many(
            args.image,
            args.layer,
            args.condition,
            args.output,
            request=request,
            batch_size=args.batch_size,
            force=args.force,
            ora=not args.no_ora,
            depth=args.depth,
            progress=progress(),
            warn=warn,
            max_pixels=args.max_pixels,
            device=args.device,
        )
    finally:
        shutdown_distributed(info)
    if info.is_main and args.json:
        for o in report.outcomes:
            print(json.dumps(dataclasses.asdict(o), ensure_ascii=False))
        counts = {"done": len(report.done), "skipped": len(report.skipped), "failed": len(report.failed)}
        print(json.dumps({"summary": report.summary(), **counts, "seconds": round(report.seconds, 3)}))
    elif info.is_main:
        for o in report.outcomes:  # what was done to a file beyond editing it: a stale output redone
            if o.note:
                print(f"{printable(o.input)}: {o.note} ({o.output})")
        for o in report.failed:
            print(f"{PROG}: error: {printable(o.input)}: {o.error}", file=sys.stderr)
        where = f"{Path(args.output)}/" + (f" ({info.world_size} processes)" if info.world_size > 1 else "")
        print(f"{where}: {report.summary()} ({report.seconds:.1f} s)")
    return 0 if report.ok else 2


# Names that say "a file" where OUT must be a stack folder: images and the interchange formats.
FILE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp", ".tif", ".tiff", ".bmp", ".ora", ".psd", ".json")


def _stack_folder(image: Path) -> Path | None:
    """The stack folder an input names (its own ``layers/`` may hold the preset), None for an image."""
    if image.is_dir():
        return image
    return image.parent if image.suffix.lower() == ".json" else None


def run_one(args: argparse.Namespace) -> int:
    from lasagna.io.folder import check_output_folder

    if args.json:
        raise LasagnaError("--json reports a batch; expected several inputs, a folder or a glob", "--json")

    if Path(args.output).suffix.lower() in FILE_SUFFIXES:
        raise PathError(
            f"OUT is a stack folder; expected a folder name, e.g. -o {Path(args.output).with_suffix('')}", args.output
        )
    from lasagna.io.image import check_edit_memory, probe_image_file
    from lasagna.io.survey import survey_stack

    out = check_output_folder(args.output, force=args.force)
    # The input's format, size and memory checked before torch and the priors are loaded.
    image = Path(args.image)
    if image.is_dir() or image.suffix.lower() == ".json":
        survey_stack(image, max_pixels=args.max_pixels)
    elif image.exists():
        check_edit_memory(*probe_image_file(image, max_pixels=args.max_pixels), str(image))
    request = _request(args)
    if "/" not in args.layer:
        # The preset and what the request asks of it, checked before torch (a path: the request's own refusal).
        from lasagna.catalogue import load_preset
        from lasagna.request import check_request

        check_request(request, load_preset(args.layer, _stack_folder(image)))

    from lasagna.editing import edit

    if Path(args.image).resolve() == out.resolve() and not args.force:
        raise PathError("is the input stack; expected another folder (or --force to replace it)", str(out))
    result = edit(
        args.image,
        request=request,
        max_pixels=args.max_pixels,
        device=args.device,
        progress=progress(),
        phase=phase,
    )
    result.save(out, force=args.force, ora=not args.no_ora, warn=warn, phase=phase, depth=args.depth)
    s = result.settings
    layer = result.stack.document.layer(result.layer_id)
    how = (
        f"a surface lit from {layer.light}"
        + (f", source light {layer.source_light}" if layer.source_light else "")
        + (
            f" (your {layer.made_by['source_read']} ± {layer.made_by['source_within']:g}°, its elevation fused with "
            "the estimator's fit)"
            if layer.made_by and "source_read" in layer.made_by
            else ""
        )
        + f" (estimated at {s['working_size']}²"
        + (f", {s['optimize']} multi-light steps" if s["optimize"] else "")
        + ")"
        if layer.kind == "surface"
        else "amortised generator, one forward pass"
        if s["method"] == "amortised" and not s["optimize"]
        else (
            f"amortised generator + {s['optimize']} per-image steps"
            if s["method"] == "amortised"
            else f"per-image optimisation, {len(result.history)} of {s['optimize']} steps "
            f"({s['distill']['loss']}, ω = {s['distill']['guidance']:g}"
            + (f", {s['distill']['particles']} particles averaged" if s["distill"].get("particles", 1) > 1 else "")
            + ")"
        )
    )
    lo, hi = float(result.layer.min()), float(result.layer.max())
    print(f"wrote {out}/ (layer {result.layer_id!r}: {how}; values in [{lo:.3g}, {hi:.3g}]; {result.seconds:.1f} s)")
    print(
        f"  {out / 'composite.png'}, {out / 'stack.json'}, {out / 'layers'}/"
        + ("" if args.no_ora else f", {out / 'stack.ora'}")
    )
    return 0
