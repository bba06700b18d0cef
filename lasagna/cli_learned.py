"""The learned-layer subcommands of the ``lasagna`` console script (wired into ``lasagna.cli.COMMANDS``).

    lasagna edit IMAGE --layer shading --condition left -o OUT [--on ID] [--optimize N] [--loss NAME]
                 [--guidance W] [--steps N] [--seed S] [--lr LR] [--generator amortised|free] [--force]
    lasagna render STACK [--all]
    lasagna train-layer --preset shading [--out DIR] [--minutes M] [--steps N] [--supervised] [--install] …
    lasagna layers                                   list the catalogue: presets, priors, correctives, generators
    lasagna demo -o DIR                              relight, colourise and light the bundled examples (lasagna.demo)

IMAGE is a PNG/JPEG or a stack folder; OUT is a new (or empty) folder. Errors are one line and exit 2
(``lasagna.cli.main``); OUT is written through a temporary sibling folder renamed at the end, so a
failure leaves nothing half-written.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from lasagna.errors import LasagnaError, PathError


def _warn(message: str) -> None:
    print(f"lasagna: warning: {message}", file=sys.stderr)


def _progress() -> bool:
    return sys.stderr.isatty()


def _distill_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--loss", choices=("sds", "lmc-sds", "dds", "nfsd", "ms-sds"), help="score-distillation loss (default: the preset's)")
    p.add_argument("--guidance", type=float, metavar="W", help="guidance weight ω in ε_u + ω(ε_c − ε_u) (default: the preset's)")
    p.add_argument("--seed", type=int, metavar="S", help="seed of the per-image run (default: the preset's)")
    p.add_argument("--lr", type=float, help="Adam learning rate of the per-image run (default: the preset's)")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")


# ---- edit -------------------------------------------------------------------------------------------


def edit_arguments(p: argparse.ArgumentParser) -> None:
    from lasagna.edit import DEFAULT_EDIT_MAX_PIXELS

    p.add_argument("image", help="a PNG/JPEG image, or a stack folder (the layer goes on top of it)")
    p.add_argument("--layer", default="shading", metavar="PRESET", help="learned-layer preset (default shading; see 'lasagna layers')")
    p.add_argument("--condition", required=True, metavar="LABEL", help="a label of the preset's vocabulary, e.g. left")
    p.add_argument("-o", "--output", required=True, metavar="OUT", help="stack folder to write (new or empty)")
    p.add_argument("--on", metavar="ID", help="condition on the composite up to this layer (default: the top layer)")
    p.add_argument("--id", help="id of the new layer (default PRESET-LABEL)")
    p.add_argument("--generator", choices=("amortised", "free"),
                   help="amortised: the preset's trained generator, one forward pass; free: a per-pixel layer "
                        "optimised for this image (default: amortised when the preset has one)")
    p.add_argument("--optimize", type=int, metavar="N", help="per-image optimisation steps (after the amortised pass; "
                   "default 0, or the preset's steps for a free layer)")
    p.add_argument("--steps", type=int, metavar="N", help="the same number as --optimize, named as in the preset")
    _distill_args(p)
    p.add_argument("--no-ora", action="store_true", help="do not write stack.ora")
    p.add_argument("--force", action="store_true", help="replace OUT if it already holds a stack")
    p.add_argument("--max-pixels", type=int, default=DEFAULT_EDIT_MAX_PIXELS, metavar="N",
                   help=f"refuse images with more than N pixels (default {DEFAULT_EDIT_MAX_PIXELS})")


def run_edit(args: argparse.Namespace) -> int:
    from lasagna.edit import check_output_folder, edit

    out = check_output_folder(args.output, force=args.force)
    if Path(args.image).resolve() == out.resolve() and not args.force:
        raise PathError("is the input stack; expected another folder (or --force to replace it)", str(out))
    result = edit(args.image, args.layer, args.condition, on=args.on, id=args.id, generator=args.generator,
                  optimize=args.optimize, steps=args.steps, loss=args.loss, guidance=args.guidance, seed=args.seed,
                  lr=args.lr, max_pixels=args.max_pixels, device=args.device, progress=_progress())
    result.save(out, force=args.force, ora=not args.no_ora, warn=_warn)
    s = result.settings
    how = "amortised generator, one forward pass" if s["method"] == "amortised" and not s["optimize"] else (
        f"amortised generator + {s['optimize']} per-image steps" if s["method"] == "amortised"
        else f"per-image optimisation, {len(result.history)} of {s['optimize']} steps "
             f"({s['distill']['loss']}, ω = {s['distill']['guidance']:g})")
    lo, hi = float(result.layer.min()), float(result.layer.max())
    print(f"wrote {out}/ (layer {result.layer_id!r}: {how}; values in [{lo:.3g}, {hi:.3g}]; {result.seconds:.1f} s)")
    print(f"  {out / 'composite.png'}, {out / 'stack.json'}, {out / 'layers'}/" + ("" if args.no_ora else f", {out / 'stack.ora'}"))
    return 0


# ---- render ------------------------------------------------------------------------------------------


def render_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("stack", help="stack folder or its stack.json")
    p.add_argument("--all", action="store_true", help="re-render every learned layer, not only those without pixels")
    p.add_argument("--device", default="cpu", help="torch device (default cpu)")


def run_render(args: argparse.Namespace) -> int:
    from lasagna.document import stack_file
    from lasagna.edit import render_learned
    from lasagna.io.stack import load_stack

    stack = load_stack(args.stack)
    folder = stack_file(args.stack).parent
    if not os.access(folder, os.W_OK | os.X_OK):
        raise PathError("is not writable; expected a stack folder render can write into", str(folder))
    stack, ids = render_learned(stack, all=args.all, device=args.device, progress=_progress(), warn=_warn)
    if not ids:
        from lasagna.io.render import write_composite

        write_composite(stack.render(), folder / "composite.png")
        print(f"no learned layer to render (use --all to re-render); wrote {folder / 'composite.png'}")
        return 0
    print(f"rendered {', '.join(ids)}; wrote their PNGs, {folder / 'stack.json'} and {folder / 'composite.png'}")
    return 0


# ---- train-layer -------------------------------------------------------------------------------------


def train_layer_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--preset", required=True, help="learned-layer preset whose generator to train (e.g. shading)")
    p.add_argument("--out", metavar="DIR", help="run folder; run again with the same folder to resume "
                   "(default runs/<preset>-generator)")
    p.add_argument("--minutes", type=float, help="time budget of this invocation")
    p.add_argument("--steps", type=int, default=3000, help="training steps (an upper bound with --minutes; default 3000)")
    p.add_argument("--supervised", action="store_true", help="train on the world's true layer (the supervised ceiling)")
    p.add_argument("--loss", choices=("sds", "lmc-sds", "dds", "nfsd", "ms-sds"), help="default: the preset's")
    p.add_argument("--guidance", type=float, metavar="W", help="default: the preset's")
    p.add_argument("--lr", type=float, default=1e-3)
    p.add_argument("--ramp", type=int, default=500, metavar="N",
                   help="steps of the LMC-SDS recipe's cosine ramps: score weight 0.1 → 1, L2-to-input weight 1 → --reg-final")
    p.add_argument("--reg-final", type=float, default=0.0, metavar="W",
                   help="L2-to-input weight after the ramp (default 0; the LMC-SDS paper's image network keeps 0.1)")
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--resolution", type=int, help="world scene size (default: the prior's resolution, else 32)")
    p.add_argument("--channels", default="16,32,64,128", help="generator widths per level (default 16,32,64,128)")
    p.add_argument("--ema", type=float, default=0.999, help="EMA decay of the weights saved (default 0.999)")
    p.add_argument("--ema-warmup", action="store_true",
                   help="ramp the EMA decay as min(ema, (1+step)/(10+step)) so a short run's average forgets its start")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--install", action="store_true",
                   help="copy the trained generator into the preset's catalogue folder (<catalogue>/<preset>/generator/)")
    p.add_argument("--device", default=None, help="torch device (default cuda if available, else cpu)")


def run_train_layer(args: argparse.Namespace) -> int:
    from lasagna import catalogue as cat
    from lasagna.distill import AmortisedConfig, train_layer_generator
    from lasagna.distill.schedules import Weights
    from lasagna.distill.tasks import TASK_FOR_BLEND
    from lasagna.generators.unet import LayerGeneratorConfig

    resolved = cat.resolve(args.preset, need_prior=not args.supervised)
    preset = resolved.preset
    try:
        widths = tuple(int(c) for c in str(args.channels).split(","))
    except ValueError:
        raise LasagnaError(f"{args.channels!r} is not a comma-separated list of integers; expected e.g. 16,32,64,128",
                           "--channels") from None
    loss = args.loss or preset.distill.loss
    prior = corrective = None
    resolution = args.resolution
    if not args.supervised:
        prior = cat.load_prior(resolved.prior, preset=preset)
        if loss == "lmc-sds":
            corrective = cat.load_corrective(cat.component_path(preset, "corrective", resolved.preset_file))
        if resolution is None:
            from lasagna.distill import prior_image_size

            resolution = prior_image_size(prior)[0]
    out = Path(args.out or f"runs/{preset.name}-generator")
    config = AmortisedConfig(
        generator=LayerGeneratorConfig.for_preset(preset, channels=widths), task=TASK_FOR_BLEND[preset.blend],
        prior=None if args.supervised else str(resolved.prior),
        corrective=str(resolved.corrective) if corrective is not None else None,
        supervised=args.supervised, loss=loss, guidance=args.guidance or preset.distill.guidance,
        t_min=preset.distill.t_min, t_max=preset.distill.t_max, lr=args.lr, batch_size=args.batch_size,
        weights=Weights.lmc_network(args.ramp, reg_end=args.reg_final),
        resolution=resolution or 32, steps=args.steps, max_minutes=args.minutes, ema_decay=args.ema, ema_warmup=args.ema_warmup, seed=args.seed,
        progress=_progress(),
    )
    result = train_layer_generator(config, out, prior=prior, corrective=corrective, device=args.device)
    line = {"out": str(out / "generator"), "preset": preset.name, "step": result.step, "stopped": result.stopped,
            **{k: v for k, v in result.metrics.items() if k.endswith("psnr")}}
    if args.install:
        line["installed"] = str(install_generator(out / "generator", resolved.preset_file.parent))
    print(json.dumps(line))
    return 0


def install_generator(source: Path, preset_dir: Path) -> Path:
    """Copy a trained generator (model.safetensors + config.json) into ``preset_dir/generator/``, atomically per file."""
    from lasagna.io.atomic import atomic_write_bytes

    target = preset_dir / "generator"
    for name in ("model.safetensors", "config.json"):  # the weights first: a config.json marks a complete folder
        atomic_write_bytes(target / name, (source / name).read_bytes())
    return target


# ---- layers ------------------------------------------------------------------------------------------


def layers_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print the listing as JSON")


def run_layers(args: argparse.Namespace) -> int:
    from lasagna import catalogue as cat

    found = cat.available()
    status = {name: cat.preset_status(name) for name in found["preset"]}
    if args.json:
        print(json.dumps({"catalogues": [str(c) for c in cat.catalogues()], **found, "status": status}))
        return 0
    print(f"catalogues: {', '.join(map(str, cat.catalogues())) or '(none)'}")
    for kind in cat.KINDS:
        print(f"{kind}s: {', '.join(found[kind]) or '(none)'}")
    for name, st in status.items():
        how = f"ready ({st['method']}: {st['why']})" if st["usable"] else f"not usable: {st['why']}"
        print(f"  {name}: {how}")
    return 0
