"""Measure a bundled prior against the world's ground truth and write its model card.

    python benchmarks/prior_quality.py --run runs/relight-32 --name relight-32 [--snapshots runs/relight-32-snaps]

Reads the run folder of ``lasagna train-prior`` (its final EMA prior in ``prior/``, its log and
config), measures on the ``heldout`` split (shape and texture families the prior never saw):

* DDIM-50 samples conditioned on each scene's conditioning image and label, PSNR against the true
  image, per label, for ω ∈ {1, 3, 7.5} (the guidance sweep);
* denoising error (MSE of the conditional x̂₀) per t;
* with ``--snapshots``: the same ω = 1 PSNR for every checkpoint copied during training (run time
  against error);

copies the weights to ``layers/<name>/`` and writes ``MODEL.md``, ``loss.png`` and ``metrics.json``
there. Ends by printing one JSON line.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lasagna.priors.evaluate import denoising_error, sample_quality  # noqa: E402
from lasagna.priors.unet import UNetPrior  # noqa: E402
from lasagna.training import cumulative_seconds, read_log  # noqa: E402
from lasagna.training.prior import (  # noqa: E402
    NAMED_SHARE,
    PriorTrainConfig,
    prior_batch,
    prior_from_checkpoint,
    task_vocabulary,
)
from lasagna.world import generate  # noqa: E402

BETWEEN = 22.5
"""Degrees of azimuth from each named light to the direction between it and the next (benchmarks/relight.py's)."""


def heldout(task: str, count: int, resolution: int, seed: int, split: str = "heldout"):
    vocab = task_vocabulary(task)
    # An equal number of scenes per label, so per-label means are comparable.
    labels = [vocab[i % len(vocab)] for i in range(count)]
    scene = generate(split, count, seed, resolution, labels=labels if task in ("relight", "relit") else None)
    if task == "light":
        scene = replace(scene, params=scene.params.with_glow_labels(labels))
    x0, lab_idx, cond = prior_batch(task, scene)
    return x0, [vocab[i] for i in lab_idx.tolist()], cond


def between(task: str, count: int, resolution: int, seed: int, split: str = "heldout"):
    """``heldout``'s scenes and targets for the directions between the named ones (az + 22.5°, the same
    elevation), as ``az=…,el=…`` labels: what a prior conditioned on directions never saw named."""
    from lasagna.document.condition import format_direction, named_direction
    from lasagna.world import relighting, with_light
    from lasagna.world.tasks import relight_sources

    vocab = task_vocabulary(task)
    named = [vocab[i % len(vocab)] for i in range(count)]
    scene = generate(split, count, seed, resolution, labels=named)
    lights = [format_direction(named_direction(n)[0] + BETWEEN, named_direction(n)[1]) for n in named]
    if task == "relit":
        rel = relighting(scene, relight_sources(scene.params), lights)
        return rel.target, lights, rel.base
    return with_light(scene, lights).image, lights, scene.albedo


def train_seconds(log: list[dict], step: int) -> float:
    """Training wall time up to ``step``, summed over invocations (each resume restarts elapsed_s)."""
    secs = cumulative_seconds(log)
    return next((s for r, s in zip(log, secs) if r["step"] >= step), secs[-1] if secs else 0.0)


def loss_plot(log: list[dict], path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = [r["step"] for r in log]
    loss = [r["loss"] for r in log]
    k = 20
    smooth = [sum(loss[max(0, i - k + 1) : i + 1]) / len(loss[max(0, i - k + 1) : i + 1]) for i in range(len(loss))]
    fig, ax = plt.subplots(figsize=(6, 3.2), dpi=100)
    ax.plot(steps, loss, lw=0.5, alpha=0.4, label="per step")
    ax.plot(steps, smooth, lw=1.5, label=f"mean of {k}")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("diffusion loss (v-MSE)")
    ax.set_title(title)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", required=True, type=Path)
    ap.add_argument("--name", required=True)
    ap.add_argument("--count", type=int, default=64, help="held-out scenes (8 per label for relight)")
    ap.add_argument("--omegas", default="1,3,7.5")
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--snapshots", type=Path, default=None)
    ap.add_argument("--snapshot-count", type=int, default=32)
    ap.add_argument("--out", type=Path, default=ROOT / "layers")
    ap.add_argument(
        "--split",
        default="heldout",
        help="world split of the scenes (heldout: the card's; val: seen families — pass another --out)",
    )
    ap.add_argument(
        "--previous",
        type=Path,
        default=None,
        help="metrics.json of the run this one started from (train-prior --init-from): "
        "the card then describes both stages and their total time",
    )
    args = ap.parse_args(argv)
    torch.set_num_threads(1)

    config = PriorTrainConfig.model_validate_json((args.run / "train_config.json").read_text())
    prior = UNetPrior.from_pretrained(args.run / "prior")
    res = config.unet.resolution
    x0, labels, cond = heldout(config.task, args.count, res, args.seed, args.split)
    omegas = [float(w) for w in args.omegas.split(",")]

    t0 = time.perf_counter()
    quality = sample_quality(prior, x0, labels, cond, omegas=omegas, steps=args.steps, seed=args.seed)
    eval_s = time.perf_counter() - t0
    denoise = denoising_error(prior, x0, labels, cond, seed=args.seed)
    mid = None
    if config.unet.directions:
        xm, lm, cm = between(config.task, args.count, res, args.seed, args.split)
        q = sample_quality(prior, xm, lm, cm, omegas=omegas, steps=args.steps, seed=args.seed)
        mid = {str(w): round(v["all"], 2) for w, v in q.items()}

    log = read_log(args.run)
    growth = []
    if args.snapshots is not None:
        x_s, l_s, c_s = heldout(config.task, args.snapshot_count, res, args.seed)
        final_step = prior_from_checkpoint(args.run / "checkpoint.safetensors")[1]
        seen = set()
        for snap in sorted(args.snapshots.glob("*.safetensors")):
            p, step = prior_from_checkpoint(snap)
            if step in seen or step == final_step:  # copies taken after training stopped add nothing
                continue
            seen.add(step)
            elapsed = train_seconds(log, step)
            q = sample_quality(p, x_s, l_s, c_s, omegas=(1.0,), steps=args.steps, seed=args.seed)
            growth.append(
                {
                    "step": step,
                    "train_minutes": None if elapsed is None else round(elapsed / 60, 1),
                    "psnr_omega1": round(q[1.0]["all"], 2),
                }
            )
        final_q = sample_quality(prior, x_s, l_s, c_s, omegas=(1.0,), steps=args.steps, seed=args.seed)
        growth.append(
            {
                "step": final_step,
                "train_minutes": round(train_seconds(log, final_step) / 60, 1) if log else None,
                "psnr_omega1": round(final_q[1.0]["all"], 2),
                "final_ema": True,
            }
        )

    previous = _previous_stage(args.previous)
    if previous and previous.get("growth"):  # continue the first stage's curve with this stage's final weights
        x_s, l_s, c_s = heldout(config.task, args.snapshot_count, res, args.seed)
        final_q = sample_quality(prior, x_s, l_s, c_s, omegas=(1.0,), steps=args.steps, seed=args.seed)
        final_step = prior_from_checkpoint(args.run / "checkpoint.safetensors")[1]
        growth = (
            [g for g in previous["growth"] if not g.get("final_ema")]
            + [{**g, "final_ema": False, "stage": 1} for g in previous["growth"] if g.get("final_ema")]
            + [
                {
                    "step": previous["steps"] + final_step,
                    "stage": 2,
                    "final_ema": True,
                    "psnr_omega1": round(final_q[1.0]["all"], 2),
                    "train_minutes": round(
                        (previous.get("train_minutes") or 0) + train_seconds(log, final_step) / 60, 1
                    ),
                }
            ]
        )

    dest = args.out / args.name
    dest.mkdir(parents=True, exist_ok=True)
    for f in ("model.safetensors", "config.json"):
        shutil.copyfile(args.run / "prior" / f, dest / f)
    loss_plot(log, dest / "loss.png", f"{args.name}: training loss")
    n_params = sum(p.numel() for p in prior.parameters())
    metrics = {
        "name": args.name,
        "task": config.task,
        "params": n_params,
        "resolution": res,
        "steps": prior_from_checkpoint(args.run / "checkpoint.safetensors")[1],
        "train_minutes": round(train_seconds(log, log[-1]["step"]) / 60, 1) if log else None,
        "heldout_scenes": args.count,
        "ddim_steps": args.steps,
        "psnr": {str(w): {k: round(v, 2) for k, v in q.items()} for w, q in quality.items()},
        "denoise_mse_per_t": {str(k): round(v, 6) for k, v in denoise.items()},
        "psnr_between": mid,
        "growth": growth,
        "eval_seconds": round(eval_s, 1),
        "previous": previous and {k: v for k, v in previous.items() if k != "growth"},
        "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} thread(s), "
        f"torch {torch.__version__}",
        "date": datetime.date.today().isoformat(),
    }
    (dest / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    (dest / "MODEL.md").write_text(model_card(metrics, config, args))
    print(
        json.dumps(
            {
                "name": args.name,
                "psnr_omega1": metrics["psnr"].get("1.0", {}).get("all"),
                "psnr": {w: q["all"] for w, q in metrics["psnr"].items()},
            }
        )
    )
    return 0


def _previous_stage(path: Path | None) -> dict | None:
    """The first stage of a two-stage run: its steps, minutes, lr and ω = 1 PSNR (from its metrics.json)."""
    if path is None:
        return None
    prev = json.loads(path.read_text())
    keep = ("steps", "train_minutes", "lr", "psnr_omega1", "command", "growth")
    out = {k: prev[k] for k in keep if k in prev}
    out.setdefault("psnr_omega1", prev.get("psnr", {}).get("1.0", {}).get("all"))
    return out


def _training_section(m: dict, config: PriorTrainConfig) -> str:
    extra = "".join(
        [
            " --directions" if config.unet.directions else "",
            f" --init-from layers/{Path(config.init_from).name}" if config.init_from is not None else "",
            f" --lr {config.lr:g}" if config.lr != 2e-3 else "",
            f" --lr-schedule {config.lr_schedule}" if config.lr_schedule != "step" else "",
            f" --warmup {config.warmup_steps}" if config.init_from is not None else "",
            f" --ema {config.ema_decay:g}" if config.init_from is not None else "",
            " --ema-warmup" if config.ema_warmup else "",
            f" --seed {config.seed}" if config.seed != 0 else "",
        ]
    )
    one = (
        f"lasagna train-prior --task {config.task} --out runs/{m['name']} --steps {m['steps']}{extra}   "
        f"# ≈ {m['train_minutes']} min here; resumable"
    )
    ema = f"EMA {config.ema_decay}" + (
        " with the warm-up ramp min(decay, (1 + step)/(10 + step))" if config.ema_warmup else ""
    )
    stage = (
        f"{m['steps']} steps in {m['train_minutes']} minutes (Adam, lr {config.lr} ({config.lr_schedule}) with "
        f"{config.warmup_steps} warm-up steps, gradient clip {config.grad_clip}, {ema}, seed {config.seed})"
    )
    prev = m.get("previous")
    if config.init_from is not None and config.init_labels == "fresh":
        source = Path(config.init_from).name
        tune = (
            f"lasagna train-prior --task {config.task} --out runs/{m['name']} --init-from layers/{source} "
            "--init-labels fresh "
            f"--lr {config.lr} --lr-schedule {config.lr_schedule} --steps {m['steps']} --warmup {config.warmup_steps}"
            + (" --ema-warmup" if config.ema_warmup else "")
        )
        return (
            f"Fine-tuned from the bundled prior `{source}` (same architecture; [its card](../{source}/MODEL.md)): "
            "every "
            f"weight copied except the label embedding, whose rows all start as `{source}`'s null label, so training "
            f"begins from its unconditional model. {stage}. Reproduce:\n\n```sh\n{tune}\n"
            f"python benchmarks/prior_quality.py --run runs/{m['name']} --name {m['name']}\n```\n"
        )
    if not prev:
        start = ""
        if config.init_from is not None:
            source = Path(config.init_from).name
            start = (
                f"Started from the bundled prior `{source}`'s weights ([its card](../{source}/MODEL.md))"
                + (
                    " — its label embedding gives way to the direction encoder, trained from scratch"
                    if config.unet.directions
                    else ""
                )
                + "; "
            )
        return (
            f"{start}{stage}. Reproduce:\n\n```sh\n{one}\n"
            f"python benchmarks/prior_quality.py --run runs/{m['name']} --name {m['name']}\n```\n"
        )
    total = round((prev.get("train_minutes") or 0) + (m["train_minutes"] or 0), 1)
    first = prev.get("command") or (
        f"lasagna train-prior --task {config.task} --out runs/{m['name']} --steps {prev['steps']}"
    )
    anneal = (
        f"lasagna train-prior --task {config.task} --out runs/{m['name']}-anneal --init-from runs/{m['name']}/prior "
        f"--lr {config.lr} --lr-schedule {config.lr_schedule} --steps {m['steps']} --warmup {config.warmup_steps} "
        f"--ema {config.ema_decay} --seed {config.seed}"
    )
    return (
        f"Two stages, {prev['steps'] + m['steps']} steps and {total} minutes in all:\n\n"
        f"1. {prev['steps']} steps in {prev.get('train_minutes')} minutes at a constant lr {prev.get('lr', 2e-3)} "
        f"(ω = 1 held-out PSNR after it: {prev.get('psnr_omega1')} dB);\n"
        f"2. an anneal from those EMA weights: {stage}.\n\nReproduce:\n\n```sh\n{first}\n{anneal}\n"
        f"python benchmarks/prior_quality.py --run runs/{m['name']}-anneal --name {m['name']} --previous "
        f"runs/{m['name']}/metrics.json\n```\n"
    )


def _families(split: str) -> str:
    from lasagna.world.splits import get_split

    sp = get_split(split)
    walls = sorted(set(sp.wall_textures))
    relief = f"; wall relief {', '.join(sp.reliefs)}" if sp.reliefs else ""
    return (
        f"shapes {', '.join(sp.shapes)}, {sp.objects[0]}–{sp.objects[1]} per scene; object textures "
        f"{', '.join(sp.object_textures)}; wall textures {', '.join(walls)}{relief}"
    )


def model_card(m: dict, config: PriorTrainConfig, args) -> str:
    u = config.unet
    cond, target = {
        "relight": ("the albedo (3 channels) and the lighting label", "the lit image albedo × shading"),
        "relit": (
            "the scene already lit by a random source light A (3 channels: the Lasagna paper's setting) and the "
            "target light B",
            "the same scene lit by B (the relight ratio S_B / S_A is what a layer then carries)",
        ),
        "colorize": ("the Rec. 709 luma (1 channel) and the label `natural`", "the colour image"),
        "light": (
            "the unlit image (3 channels) and the glow's label (warm, cool, white)",
            "the image with the world's coloured fill light added (`lasagna.world.tasks`)",
        ),
    }[config.task]
    labels = [k for k in next(iter(m["psnr"].values())) if k != "all"]
    head = "| label | " + " | ".join(f"ω = {w}" for w in m["psnr"]) + " |\n|---|" + "---|" * len(m["psnr"]) + "\n"
    rows = "".join(
        f"| {lab} | " + " | ".join(f"{m['psnr'][w][lab]:.2f}" for w in m["psnr"]) + " |\n" for lab in labels + ["all"]
    )
    den = (
        "| t | "
        + " | ".join(m["denoise_mse_per_t"])
        + " |\n|---|"
        + "---|" * len(m["denoise_mse_per_t"])
        + "\n| MSE of x̂₀ | "
        + " | ".join(f"{v:.4f}" for v in m["denoise_mse_per_t"].values())
        + " |\n"
    )
    light = ""
    if u.directions:
        light = (
            "\nThe light is a direction, not a label: a named light is its unit vector (azimuth from +x toward +y, "
            "elevation from the view axis; `left` is az=180,el=60), Fourier features → MLP; training lit "
            f"{round(100 * NAMED_SHARE)} % of scenes by a named light and the rest by a uniformly random direction.\n"
        )
    mid = ""
    if m.get("psnr_between"):
        mid = (
            "\nDirections between the named ones (each named light's azimuth + 22.5°, the same elevation), the same "
            "scenes: "
            + ", ".join(f"ω = {w}: {v:.2f} dB" for w, v in m["psnr_between"].items())
            + " (named: "
            + ", ".join(f"ω = {w}: {q['all']:.2f} dB" for w, q in m["psnr"].items())
            + ").\n"
        )
    grow = ""
    if m["growth"]:
        grow = (
            "\n## Run time against error\n\nDDIM-50 PSNR at ω = 1 on the first "
            f"{args.snapshot_count} held-out scenes, for checkpoints copied during training (EMA weights):\n\n| step "
            "| minutes | PSNR (dB) |\n|---|---|---|\n"
            + "".join(f"| {g['step']} | {g['train_minutes']} | {g['psnr_omega1']:.2f} |\n" for g in m["growth"])
        )
    return f"""# {m["name"]}: a conditional pixel-space diffusion prior ({config.task})

A `UNetPrior` ({m["params"] / 1e6:.2f} M parameters, channels {list(u.channels)}, {u.res_blocks} residual block(s) per level,
{u.prediction}-prediction, linear β schedule with T = {u.schedule.num_steps}) at {m["resolution"]}² pixels, trained on
this 2-core CPU on the procedural world, conditioned ControlNet-style on {cond}; it generates {target}.
Label dropout {config.p_uncond} trains the null label for classifier-free guidance (ε̂ = ε_u + ω(ε_c − ε_u)).
{light}
## Data
Fresh batches of {config.batch_size} scenes from the world's `train` split every step (no data set on disk; {_families("train")});
`val`, `heldout` and `far` are never seen. Evaluated on {m["heldout_scenes"]} scenes of the `heldout` split: other seeds
and families the prior never saw ({_families("heldout")}).

## Training
{_training_section(m, config)}
![loss](loss.png)

## Quality (held-out split)
DDIM-{m["ddim_steps"]} samples against the true image, PSNR in dB (higher is better), per label and guidance weight:

{head}{rows}
Denoising error per t (conditional x̂₀, [0, 1] units):

{den}{mid}{grow}
Measured {m["date"]} on {m["machine"]}; evaluation took {m["eval_seconds"]} s.
"""


if __name__ == "__main__":
    sys.exit(main())
