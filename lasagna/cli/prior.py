"""``lasagna prior add``: register a diffusers folder (your own Stable Diffusion, with ControlNets) as a
catalogue entry, so that ``lasagna edit IMAGE --layer NAME`` uses it (``lasagna.catalogue.add_prior``).

    lasagna prior add /models/sd15 --name relight-sd [--controlnet /models/cn [--controlnet-scale 0.8]]…
                      [--like shading] [--corrective runs/b/corrective] [--vocabulary left,right]
                      [--prompt-template "A photo of an object with {label} lighting"]
                      [--dtype float16] [--variant fp16] [--cpu-offload] [--attention-slicing] [--channels-last]
                      [--catalogue DIR] [--force]

The entry goes to the first folder of ``$LASAGNA_LAYERS``, else to ``$XDG_DATA_HOME/lasagna/layers``
(``~/.local/share/lasagna/layers``), which ``lasagna layers`` and ``lasagna edit`` search; the weights
stay where they are (the entry links to them by absolute path).
"""

from __future__ import annotations

import argparse

from lasagna.cli.common import example_epilog
from lasagna.errors import LasagnaError

HELP = "register your own prior (a diffusers folder) in the catalogue: lasagna prior add PATH --name N"
EXAMPLE = (
    "lasagna prior add /models/sd15 --name my-sd --controlnet /models/cn-depth",
    "lasagna edit photo.png --layer my-sd --condition left -o out/left",
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from lasagna.document.preset import TORCH_DTYPES

    sub = p.add_subparsers(dest="action", metavar="ACTION", parser_class=type(p))
    sub.required = True
    a = sub.add_parser(
        "add",
        help="write a catalogue entry and a preset for a diffusers folder",
        description=HELP,
        epilog=example_epilog(EXAMPLE),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    a.add_argument("path", help="the diffusers folder (written by save_pretrained: unet/ scheduler/ text_encoder/ …)")
    a.add_argument("--name", required=True, help="the entry's name: then lasagna edit --layer NAME")
    a.add_argument("--like", default="shading", metavar="PRESET", help="the preset whose layer it makes (shading)")
    a.add_argument("--controlnet", action="append", default=[], metavar="PATH", help="a ControlNet folder (repeat)")
    a.add_argument(
        "--controlnet-scale", action="append", type=float, default=[], metavar="S", help="each net's scale, in order"
    )
    a.add_argument("--corrective", metavar="PATH", help="its b̂ (train-corrective's OUT/corrective): LMC-SDS")
    a.add_argument("--vocabulary", metavar="A,B,…", help="the labels (default the --like preset's)")
    a.add_argument("--prompt-template", metavar="TEXT", help="the prompt, with one {label} (default the preset's)")
    a.add_argument("--dtype", choices=TORCH_DTYPES, help="networks' float type (default auto: fp16 on CUDA)")
    a.add_argument("--variant", metavar="NAME", help="weight files' variant, e.g. fp16")
    a.add_argument("--cpu-offload", action="store_true", help="model CPU offload (CUDA)")
    a.add_argument("--attention-slicing", action="store_true", help="attention in slices")
    a.add_argument("--channels-last", action="store_true", help="NHWC activations")
    a.add_argument(
        "--catalogue",
        metavar="DIR",
        help="the catalogue folder (default $LASAGNA_LAYERS's first, or ~/.local/share/lasagna/layers)",
    )
    a.add_argument("--force", action="store_true", help="replace an entry of that name")


def run(args: argparse.Namespace) -> int:
    from lasagna import catalogue as cat
    from lasagna.document.preset import ControlNetRef, DiffusersOptions

    nets, scales = args.controlnet, args.controlnet_scale
    if scales and len(scales) not in (1, len(nets)):
        raise LasagnaError(
            f"got {len(scales)} --controlnet-scale for {len(nets)} --controlnet; expected one, or one per net",
            "--controlnet-scale",
        )
    refs = [
        ControlNetRef(path=net, scale=(scales[0] if len(scales) == 1 else scales[i]) if scales else None)
        for i, net in enumerate(nets)
    ]
    options = DiffusersOptions(
        torch_dtype=args.dtype or "auto",
        variant=args.variant,
        cpu_offload=args.cpu_offload,
        attention_slicing=args.attention_slicing,
        channels_last=args.channels_last,
    )
    vocabulary = [v.strip() for v in args.vocabulary.split(",")] if args.vocabulary else None
    written = cat.add_prior(
        args.path,
        args.name,
        like=args.like,
        controlnets=refs,
        corrective=args.corrective,
        vocabulary=vocabulary,
        prompt=args.prompt_template,
        options=options,
        catalogue=args.catalogue,
        force=args.force,
    )
    print(f"wrote {written.parent}/ (preset and prior {args.name!r}); next: lasagna edit IMAGE --layer {args.name}")
    return 0
