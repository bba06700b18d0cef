"""Install a trained surface estimator into the catalogue with its model card.

    OMP_NUM_THREADS=1 python benchmarks/surface_card.py --run runs/surface-lit-32 --name surface-lit-32 \
        --measured docs/surface.json

Copies ``RUN/surface`` (config.json, model.safetensors) to ``layers/NAME/`` and writes ``layers/NAME/MODEL.md``:
what it reads, the architecture and its size, the data (the world's training split and the splits it never saw),
the training (steps, minutes, the exact command from the run's train_config.json), its loss curve (loss.png) and
the quality measured by benchmarks/surface.py (the rows of ``--measured`` for this estimator, with the oracle and
headroom rows beside them). Ends with one JSON line.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import print_json_line  # noqa: E402

from lasagna.generators.surface import SurfaceEstimator  # noqa: E402
from lasagna.training.loop import read_log  # noqa: E402
from lasagna.world.splits import SPLITS  # noqa: E402

ROWS = {
    "albedo": ("shading", "surface estimator (albedo)"),
    "lit": ("relight", "surface estimator (lit), its source light"),
}


# Where a run's last stage ran unless ``--where`` says otherwise.
WHERE = "on this 2-core CPU (one thread)"


def command(cfg: dict, run: Path) -> str:
    net = cfg["net"]
    return (
        f"lasagna train-surface --input {net['input']} --out {run} --working-size {net['working_size']} "
        f"--channels {','.join(map(str, net['channels']))} --blocks {net['blocks']} --lights {cfg['lights']} "
        f"--batch-size {cfg['batch_size']} --lr {cfg['lr']} --minutes {cfg['max_minutes']:g}"
        + (f" --output {net['output']}" if net.get("output", "height") != "height" else "")
        + (" --silhouette" if net.get("silhouette") else "")
        + (f" --split {cfg['split']}" if cfg.get("split", "train") != "train" else "")
        + (f" --world-seed {cfg['world_seed']}" if cfg.get("world_seed", 7) != 7 else "")
        + (f" --zoom {cfg['zoom']:g}" if cfg.get("zoom", 1.0) != 1.0 else "")
        + (f" --init-from {cfg['init_from']}" if cfg.get("init_from") else "")
        + "".join(
            f" {flag} {cfg[key]:g}"
            for key, flag, default in OPTIONAL_FLAGS
            if key in cfg and cfg[key] != default and (key not in LIGHT_KEYS or net.get("light_input"))
        )
        + (" --light-input" if net.get("light_input") else "")
    )


# train_config.json keys the command line names only where they differ from the CLI's default (key, flag, default).
OPTIONAL_FLAGS = (
    ("warmup_steps", "--warmup", 100),
    ("light_given", "--light-given", 0.75),
    ("light_jitter", "--light-jitter", 10.0),
    ("light_weight", "--light-weight", 0.1),
    ("walls_only", "--walls-only", 0.0),
    ("relief", "--relief", 0.0),
    ("stray", "--stray", 0.0),
    ("shadows", "--shadows", 0.0),
    ("rest", "--rest", 0.0),
    ("height_weight", "--height-weight", 0.0),
    ("scene_bank", "--scene-bank", 0),
)
LIGHT_KEYS = {"light_given", "light_jitter"}  # read only by an estimator told the light (--light-input)


def stage_line(k: int, run: Path, where: str) -> str:
    """One earlier stage of a run that started from another's weights: its steps, minutes, machine and command."""
    cfg = json.loads((run / "train_config.json").read_text(encoding="utf-8"))
    log = read_log(run)
    return (
        f"{k}. {log[-1]['step']} steps in {log[-1]['elapsed_s'] / 60:.1f} minutes ({where}, batch {cfg['batch_size']}"
        + (f", close-ups to zoom {cfg['zoom']:g}" if cfg.get("zoom", 1.0) != 1.0 else "")
        + f"): `{command(cfg, run)}`"
    )


def quality(measured: dict, kind: str) -> list[str]:
    task, method = ROWS[kind]
    keep = {m for m in (r["method"] for r in measured.get(task, [])) if m.startswith(method.split(",")[0])}
    keep |= {"oracle: true outlines inflated", "oracle: true outlines inflated, true source light"}
    keep |= {m for m in (r["method"] for r in measured.get(task, [])) if m.startswith("truth at working size")}
    keep |= {m for m in (r["method"] for r in measured.get(task, [])) if m.startswith("lasagna edit")}
    out = [
        "| split | size | method | dB over "
        + ("the best constant" if task == "shading" else "the input")
        + " (all / objects) |",
        "|---|---|---|---|",
    ]
    for r in measured.get(task, []):
        if r["method"] in keep:
            out.append(
                f"| {r['split']} | {r['size']}² | {r['method']} | {r['gain_db']:+.2f} / {r['gain_obj_db']:+.2f} |"
            )
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, required=True)
    ap.add_argument("--name", required=True)
    ap.add_argument("--measured", type=Path, default=None, help="benchmarks/surface.py --json-out of this estimator")
    ap.add_argument("--dome", default=None, metavar="WEIGHT,HEIGHT", help="the dome prior the preset uses with it")
    ap.add_argument(
        "--stages",
        nargs="*",
        default=[],
        metavar="RUN=WHERE",
        help="earlier stages of a run that started from another's weights (--init-from), oldest first: each run "
        "folder and the machine it ran on, e.g. runs/surface-lit-32='this CPU, one thread'",
    )
    ap.add_argument(
        "--quality",
        type=Path,
        default=None,
        help="a Markdown file: the card's Quality section as it is (an estimator measured by another benchmark than "
        "benchmarks/surface.py, e.g. a told-light estimator by relight_candidates.py)",
    )
    ap.add_argument(
        "--where",
        default=WHERE,
        help="where the last stage ran, as the card says it, e.g. 'on a lent H200 (three processes sharing it)'",
    )
    args = ap.parse_args(argv)
    folder = ROOT / "layers" / args.name
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("config.json", "model.safetensors"):
        shutil.copyfile(args.run / "surface" / name, folder / name)
    net = SurfaceEstimator.from_pretrained(folder)
    params = sum(p.numel() for p in net.parameters())
    cfg = json.loads((args.run / "train_config.json").read_text(encoding="utf-8"))
    log = read_log(args.run)
    steps, minutes = log[-1]["step"], log[-1]["elapsed_s"] / 60
    kind = net.config.input
    train = SPLITS[cfg["split"]]
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 3))
        ax.plot([r["step"] for r in log], [r["shading_mse"] for r in log], lw=0.6, label="multi-light shading MSE")
        if kind == "lit":
            ax.plot([r["step"] for r in log], [r["light_cos_err"] for r in log], lw=0.6, label="source light 1 − cos")
        ax.set_yscale("log")
        ax.set_xlabel("step")
        ax.legend()
        fig.tight_layout()
        fig.savefig(folder / "loss.png", dpi=100)
    except ImportError:
        pass
    reads = (
        "the unlit base (albedo): geometry from outlines and paint"
        if kind == "albedo"
        else (
            "an image already lit: geometry from its shading, and the source light fitted to it"
            + (
                " — or told it: the light (its vector and a 'given' flag) is four more input channels, so a light "
                "the user knows (`--from`) is read with the image"
                if net.config.light_input
                else ""
            )
        )
    )
    measured = json.loads(args.measured.read_text(encoding="utf-8")) if args.measured else {}
    # The measurement's own command (benchmarks/surface.py records it), else the usual one.
    measured_command = f"OMP_NUM_THREADS=1 python {measured['command']}" if measured.get("command") else None
    stages = [tuple(st.split("=", 1)) if "=" in st else (st, "this CPU, one thread") for st in args.stages]
    lines = [
        f"# {args.name}: a surface estimator ({kind} input)",
        "",
        f"A `SurfaceEstimator` (`lasagna.generators.surface`, {params / 1e6:.2f} M parameters, channels "
        f"{list(net.config.channels)}, {net.config.blocks} conv blocks per level, no normalisation) that reads "
        f"{reads}, and outputs "
        + ("a height field (canvas units)" if net.config.output == "height" else "unit normals")
        + f" at working size {net.config.working_size}. Its "
        "normals, rendered by Lambert with ambient 0.25 (`lasagna.compose.surface`), are a shading layer under "
        "any light"
        + (
            ": the lit estimator also outputs the source light's shading, and the source light is the least-squares "
            "fit of the normals to it (`fit_light`)."
            if kind == "lit"
            else "."
        )
        + (
            " It also outputs each pixel's probability of lying on an object (a silhouette head, trained by "
            "cross-entropy against the objects' mask): the dome prior inflates those silhouettes into domes and mixes "
            "them into the normals"
            + (
                f" (weight {args.dome.split(',')[0]}, height {args.dome.split(',')[1]}: the preset's "
                "`surface.dome_weight` and `dome_height`, chosen on `select`)."
                if args.dome
                else "."
            )
            if net.config.silhouette
            else ""
        ),
        "",
        "## Data",
        f"Fresh batches of {cfg['batch_size']} scenes of the world's `{cfg['split']}` split (world seed "
        f"{cfg['world_seed']}) every step: shapes {', '.join(train.shapes)}; textures "
        f"{', '.join(sorted(train.textures))}; wall relief {', '.join(train.reliefs) or 'none'}. Supervised by the "
        f"world's true normals, rendered under {cfg['lights']} random lights per scene and step (azimuth uniform, "
        "elevation 0–75°): one geometry must shade right under all of them"
        + (
            f"; close-ups: each scene rendered at {cfg['zoom']:g}× the working size and a square window of 1 to "
            f"{cfg['zoom']:g} working sizes around one of its object pixels reduced to the working size, so objects "
            "fill the frame as in photographs"
            if cfg.get("zoom", 1.0) != 1.0
            else ""
        )
        + (
            "; each scene is lit by a random source light (elevation 30–75°) before the estimator reads it."
            if kind == "lit"
            else "."
        )
        + (
            f" The light was given to the estimator on {cfg['light_given']:.0%} of the scenes, jittered by "
            f"{cfg['light_jitter']:g}° per component (as a fitted light is off), and withheld (a zero row) on the rest."
            if net.config.light_input
            else ""
        )
        + (
            f" A wall the split drew flat was given relief of one of its families with probability {cfg['relief']:g}."
            if cfg.get("relief")
            else ""
        )
        + (
            f" A scene was its wall alone, objects removed, with probability {cfg['walls_only']:g}."
            if cfg.get("walls_only")
            else ""
        )
        + (
            f" A scene's input kept the world's cast shadows under its source light with probability "
            f"{cfg['shadows']:g} (the truth shadowless: shadows taught as paint)."
            if cfg.get("shadows")
            else ""
        )
        + (
            f" A scene's objects rested on the wall with probability {cfg['rest']:g} (sunk 0.25–1 bounding radii)."
            if cfg.get("rest")
            else ""
        )
        + (
            f" Its height field was fitted to the true heights above the wall (weight {cfg['height_weight']:g})."
            if cfg.get("height_weight")
            else ""
        ),
        "`select`, `heldout` and `far` (families training never uses) are never seen; every choice is made on "
        "`select`.",
        "",
        "## Training",
        *(
            [
                "In stages, each started from the previous one's final EMA weights (`--init-from`):",
                "",
                *(stage_line(k + 1, Path(run), where) for k, (run, where) in enumerate(stages)),
                f"{len(args.stages) + 1}. the last stage, below.",
                "",
            ]
            if args.stages
            else []
        ),
        f"{steps} steps in {minutes:.1f} minutes {args.where}, Adam lr {cfg['lr']} after "
        f"{cfg['warmup_steps']} warm-up steps, EMA {cfg['ema_decay']} (ramped), gradient clip {cfg['grad_clip']}. "
        "Reproduce (resumable; the same command continues a killed run bit for bit):",
        "",
        "```sh",
        command(cfg, args.run),
        *(
            []
            if args.measured is None
            else [
                measured_command
                or f"OMP_NUM_THREADS=1 python benchmarks/surface.py --splits select heldout far --sizes 64 256 "
                f"--count 16 --{'albedo' if kind == 'albedo' else 'lit'} layers/{args.name}"
                + (f" --dome {args.dome}" if args.dome else "")
                + f" --json-out {args.measured}"
            ]
        ),
        f"python benchmarks/surface_card.py --run {args.run} --name {args.name}"
        + (f" --measured {args.measured}" if args.measured else "")
        + (f" --quality {args.quality}" if args.quality else "")
        + (f" --dome {args.dome}" if args.dome else "")
        + "".join(f" --stages '{st}'" if k == 0 else f" '{st}'" for k, st in enumerate(args.stages))
        + (f" --where '{args.where}'" if args.where != WHERE else ""),
        "```",
        "",
        "![loss](loss.png)",
        "",
        *([] if args.quality is None else ["## Quality", args.quality.read_text(encoding="utf-8").strip(), ""]),
    ]
    if args.quality is None:
        lines += quality_section(measured, kind)
    (folder / "MODEL.md").write_text("\n".join(lines), encoding="utf-8")
    print_json_line({"name": args.name, "params": params, "steps": steps, "minutes": round(minutes, 1)})
    return 0


def quality_section(measured: dict, kind: str) -> list[str]:
    """The Quality section from benchmarks/surface.py's measurement of the estimator."""
    return [
        "## Quality",
        "Measured by `benchmarks/surface.py` on 16 scenes per split (world seed 0), beside the outline-inflation "
        "oracle (the true outlines inflated into domes) and the headroom of any layer made at the working size "
        "(the truth reduced and enlarged back):",
        "",
        *quality(measured, kind),
        "",
        "Texture leak on walls alone (the scenes' objects removed: the true shading is one constant; the layer's "
        "PSNR against its own mean, ∞ for a flat surface): "
        + ", ".join(
            f"{r['split']} {r['size']}² {r[f'leak_db_{kind}']:.1f} dB"
            for r in measured.get("leak", [])
            if f"leak_db_{kind}" in r
        )
        + ".",
        "",
    ]


if __name__ == "__main__":
    raise SystemExit(main())
