"""Write the model card of an amortised generator (``layers/{shading,light,relight}/generator/``).

    python benchmarks/generator_card.py --run runs/shading-generator --ceiling runs/shading-supervised \
        --accuracy docs/distill_accuracy.json
    python benchmarks/generator_card.py --preset light --run runs/light-generator     (no ceiling run)
    python benchmarks/generator_card.py --preset relight --run runs/relight-generator \
        --ceiling runs/relight-supervised --accuracy docs/relight.json

Reads the two ``lasagna train-layer`` run folders (the distilled generator and its supervised ceiling:
config, log, metrics on the ``val`` split) and the held-out numbers of ``benchmarks/distill_accuracy.py``;
writes ``loss.png``, ``metrics.json`` and ``MODEL.md`` beside the installed generator. Prints one JSON line.
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from lasagna.training import cumulative_seconds, read_log  # noqa: E402


def cumulative_minutes(log: list[dict]) -> list[float]:
    return [sec / 60 for sec in cumulative_seconds(log)]


def plot(distilled: list[dict], ceiling: list[dict] | None, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2 if ceiling else 1, figsize=(9 if ceiling else 5, 3.2), dpi=100, squeeze=False)
    ax = ax[0]
    minutes = cumulative_minutes(distilled)
    ax[0].plot(minutes, [r["grad_norm"] for r in distilled], lw=0.8)
    ax[0].set_yscale("log")
    ax[0].set_xlabel("minutes")
    ax[0].set_ylabel("‖g‖ of the score gradient (batch mean)")
    ax[0].set_title("distilled")
    twin = ax[0].twinx()
    twin.plot(minutes, [r["reg"] for r in distilled], color="C1", lw=0.8)
    twin.set_ylabel("mean (f(x, y) − x)²", color="C1")
    if not ceiling:
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)
        return
    ax[1].plot(cumulative_minutes(ceiling), [r["mse"] for r in ceiling], lw=0.8, color="C2")
    ax[1].set_yscale("log")
    ax[1].set_xlabel("minutes")
    ax[1].set_ylabel("MSE to the true layer")
    ax[1].set_title("supervised ceiling (same net)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def light_card(args) -> int:
    """The light generator's card: no supervised ceiling run; held-out numbers from the light table."""
    cfg = json.loads((args.run / "train_config.json").read_text())
    m = json.loads((args.run / "metrics.json").read_text())
    log = read_log(args.run)
    acc = json.loads(args.accuracy.read_text())
    rows = {(r["method"], r["omega"]): r for r in acc["light"]}
    distilled = rows.get(("amortised (distilled)", None))
    per_image = rows.get((cfg["loss"], cfg["guidance"]))
    const, none, direct = (
        rows[("best-constant", None)],
        rows[("no light (identity edit)", None)],
        rows.get(("prior-direct", 1.0)),
    )
    plot(log, None, args.out / "loss.png")
    g = cfg["generator"]
    minutes = round(cumulative_minutes(log)[-1], 1)
    metrics = {
        "val": m,
        "heldout": {
            "distilled": distilled,
            "per_image": per_image,
            "best_constant": const,
            "no_light": none,
            "prior_direct": direct,
        },
        "steps": m["step"],
        "minutes": minutes,
        "date": datetime.date.today().isoformat(),
    }
    (args.out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")

    def line(name: str, r: dict | None) -> str:
        if r is None:
            return f"| {name} | — | — | — | — |\n"
        ms = "—" if not r.get("seconds_per_image") else f"{r['seconds_per_image'] * 1e3:.1f}"
        return f"| {name} | {r['glow_psnr']:.2f} | {r['object_psnr']:.2f} | {r['colour_error_deg']:.1f} | {ms} |\n"

    card = f"""# light/generator: the amortised light generator

A conditioned convolutional UNet (`lasagna.generators.LayerGenerator`: channels {g["channels"]}, {g["blocks"]} conv blocks
per level, label by {g["condition"]} encoding) that maps an image and a light colour (warm, cool, white) to a
`plus` layer — RGB light in [0, 1], added to the image — in one forward pass, at any image size. It starts
at the identity edit (no light) and was trained *through the composite* x + y with {cfg["loss"].upper()} at
ω = {cfg["guidance"]:g} from the bundled prior `light-32` (the light preset's defaults): the score weight rises
0.1 → 1 and the L2 to the input falls 1 → {cfg["weights"]["reg"]["end"]:g} over the first {cfg["weights"]["reg"]["steps"]} steps (cosine).

## Data and training
Fresh batches of {cfg["batch_size"]} world scenes of the `{cfg["split"]}` split every step (the rendered image as the base,
a uniformly drawn light colour); nothing on disk. {m["step"]} steps in {minutes} minutes on one thread of this
2-vCPU box (Adam lr {cfg["lr"]}, EMA {cfg["ema_decay"]} with the warm-up ramp, seed {cfg["seed"]}). Reproduce:

```sh
LASAGNA_LAYERS=layers lasagna train-layer --preset light --out runs/light-generator --steps {m["step"]} --ema-warmup --install --force   # ≈ {minutes} min here
OMP_NUM_THREADS=2 python benchmarks/distill_accuracy.py --sections light && python benchmarks/generator_card.py --preset light
```

![training](loss.png)

## Quality
`val` split ({cfg["eval_count"]} scenes, `metrics.json`): glow PSNR **{m["layer_psnr"]:.2f} dB** against the world's true
light (no light: {m["identity_psnr"]:.2f} dB).

`heldout` split (shapes, textures and walls never seen; {acc["count"]} scenes; `benchmarks/distill_accuracy.py`):

| method | glow PSNR (dB) | object pixels (dB) | colour error (°) | ms per image |
|---|---|---|---|---|
{line("this generator, one forward pass", distilled)}{line(f"per-image {cfg['loss']} ω = {cfg['guidance']:g} (free layer, {acc['steps']} steps)", per_image)}{line("the prior sampled directly (DDIM-50, ω = 1)", direct)}{line("best constant glow per image (oracle)", const)}{line("no light", none)}
Measured {metrics["date"]}; full tables in [docs/BENCHMARKS.md](../../../docs/BENCHMARKS.md#learned-layers).
"""
    (args.out / "MODEL.md").write_text(card)
    print(json.dumps({"val_psnr": m["layer_psnr"], "heldout_psnr": distilled and distilled["glow_psnr"]}))
    return 0


def relight_card(args) -> int:
    """The relight generator's card: val metrics of the distilled run and its supervised ceiling; heldout and
    far rows of ``benchmarks/relight.py`` (run with ``--methods 0 20 --supervised``)."""
    cfg = json.loads((args.run / "train_config.json").read_text())
    m, mc = (json.loads((r / "metrics.json").read_text()) for r in (args.run, args.ceiling))
    log, log_c = read_log(args.run), read_log(args.ceiling)
    bench = json.loads(args.accuracy.read_text())
    plot(log, log_c, args.out / "loss.png")
    g = cfg["generator"]
    minutes, minutes_c = (round(cumulative_minutes(x)[-1], 1) for x in (log, log_c))
    names = {
        "edit --generator amortised": "this generator, one forward pass",
        "edit --generator amortised --optimize 20": "this generator, then 20 SDS steps",
        "default edit (`lasagna edit --layer relight`)": "per-image SDS ω = 1 (the preset's default)",
        "supervised ceiling": "supervised ceiling, one forward pass",
        "best constant multiplier": "best constant multiplier per image (oracle)",
        "unchanged input": "unchanged input",
    }
    keys = [k for k in ("heldout@64", "heldout@256", "far@64", "far@256") if k in bench["relight"]]
    by = {k: {r["method"]: r for r in bench["relight"][k]} for k in keys}
    metrics = {
        "val": {"distilled": m, "supervised_ceiling": mc},
        "benchmark": {k: {names[n]: by[k][n] for n in names if n in by[k]} for k in keys},
        "steps": m["step"],
        "minutes": minutes,
        "date": datetime.date.today().isoformat(),
    }
    (args.out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")

    def cell(k: str, n: str) -> str:
        r = by[k].get(n)
        return "—" if r is None else f"{r['composite_psnr']:.2f} / {r['object_psnr']:.2f}"

    def ms(n: str) -> str:
        r = by[keys[0]].get(n)
        return "—" if r is None or not r.get("seconds_per_image") else f"{r['seconds_per_image'] * 1e3:.0f}"

    head = "| method | " + " | ".join(k.replace("@", " ") + "²" for k in keys) + " | ms per image (64²) |\n"
    head += "|---|" + "---|" * len(keys) + "---|\n"
    body = "".join(
        f"| {label} | " + " | ".join(cell(k, n) for k in keys) + f" | {ms(n)} |\n" for n, label in names.items()
    )
    sha256 = hashlib.sha256((args.run / "generator" / "model.safetensors").read_bytes()).hexdigest()
    card = f"""# relight/generator: the amortised relight generator

A conditioned convolutional UNet (`lasagna.generators.LayerGenerator`: channels {g["channels"]}, {g["blocks"]} conv blocks
per level, the light as a direction by {g["condition"]} encoding) that maps an image that is already lit and a
target light (a named one or `az=…,el=…`) to the relight layer — a 1-channel ratio in [0, 4], multiplied onto
the image — in one forward pass, at any size. It starts at the identity edit (ratio 1) and was trained
*through the composite* x·y with {cfg["loss"].upper()} at ω = {cfg["guidance"]:g} from the bundled prior `relit-32` (the preset's
defaults): the score weight rises 0.1 → 1 and the L2 to the input falls 1 → {cfg["weights"]["reg"]["end"]:g} over the first
{cfg["weights"]["reg"]["steps"]} steps (cosine).

`lasagna edit PHOTO --layer relight --generator amortised` uses it. It is **not** the preset's default: per-image
SDS was better on `heldout` (below), and `heldout` chose.

## Data and training
Fresh batches of {cfg["batch_size"]} world scenes of the `{cfg["split"]}` split at {cfg["resolution"]}² every step, the
`{cfg["task"]}` task: each scene lit by its own random source light (the base) and relit to a uniformly drawn named
light; nothing on disk. {m["step"]} steps in {minutes} minutes on two threads of this 2-vCPU box (Adam lr {cfg["lr"]}, EMA
{cfg["ema_decay"]} with the warm-up ramp, seed {cfg["seed"]}). The supervised ceiling is the same generator trained for
{minutes_c} minutes on the world's true ratio (MSE), {mc["step"]} steps. Reproduce:

```sh
OMP_NUM_THREADS=2 LASAGNA_LAYERS=layers lasagna train-layer --preset relight --out runs/relight-generator --steps {m["step"]} --ema-warmup --install --force
OMP_NUM_THREADS=2 lasagna train-layer --preset relight --supervised --out runs/relight-supervised --minutes {minutes_c} --ema-warmup
OMP_NUM_THREADS=2 python benchmarks/relight.py --threads 2 --methods 0 20 --supervised runs/relight-supervised/generator
python benchmarks/generator_card.py --preset relight --run runs/relight-generator --ceiling runs/relight-supervised \\
    --accuracy docs/relight.json
```

`model.safetensors` SHA-256 `{sha256}` (the run is seeded and single-process, so the first command gives the
same bytes again on this machine).

![training](loss.png)

## Quality
`val` split ({cfg["eval_count"]} scenes at {cfg["resolution"]}², `metrics.json`): composite PSNR **{m["layer_composite_psnr"]:.2f} dB**
distilled vs {mc["layer_composite_psnr"]:.2f} dB supervised ceiling (unchanged input {m["identity_composite_psnr"]:.2f} dB).

`benchmarks/relight.py` ({bench["count"]} scenes per split; composite PSNR against the truth, all pixels / object pixels;
`far`: shape and texture families used neither in training nor in any choice):

{head}{body}
Measured {metrics["date"]}; the reading is in [docs/BENCHMARKS.md](../../../docs/BENCHMARKS.md#relighting-lit-images).
"""
    (args.out / "MODEL.md").write_text(card)
    print(json.dumps({"val_composite_psnr": m["layer_composite_psnr"], "ceiling_val": mc["layer_composite_psnr"]}))
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", choices=("shading", "light", "relight"), default="shading")
    ap.add_argument("--run", type=Path, default=ROOT / "runs" / "shading-generator")
    ap.add_argument("--ceiling", type=Path, default=ROOT / "runs" / "shading-supervised")
    ap.add_argument("--accuracy", type=Path, default=ROOT / "docs" / "distill_accuracy.json")
    ap.add_argument("--out", type=Path, default=None, help="default: layers/<preset>/generator")
    args = ap.parse_args(argv)
    args.out = args.out or ROOT / "layers" / args.preset / "generator"
    if args.preset == "light":
        if args.run == ROOT / "runs" / "shading-generator":
            args.run = ROOT / "runs" / "light-generator"
        return light_card(args)
    if args.preset == "relight":
        return relight_card(args)

    cfg = json.loads((args.run / "train_config.json").read_text())
    m, mc = (json.loads((r / "metrics.json").read_text()) for r in (args.run, args.ceiling))
    log, log_c = read_log(args.run), read_log(args.ceiling)
    acc = json.loads(args.accuracy.read_text())
    rows = {r["method"]: r for r in acc["baselines"]}
    per_image = next((r for r in acc["shading"] if r["method"] == cfg["loss"] and r["omega"] == cfg["guidance"]), None)
    distilled, ceiling = rows.get("amortised (distilled)"), rows.get("amortised (supervised ceiling)")
    refine = next((r for k, r in rows.items() if k.startswith("amortised +")), None)
    const = rows["best-constant"]
    plot(log, log_c, args.out / "loss.png")
    g = cfg["generator"]
    params_note = f"channels {g['channels']}, {g['blocks']} conv blocks per level, label by {g['condition']} encoding"
    minutes = round(cumulative_minutes(log)[-1], 1)
    metrics = {
        "val": {"distilled": m, "supervised_ceiling": mc},
        "heldout": {
            "distilled": distilled,
            "supervised_ceiling": ceiling,
            "per_image": per_image,
            "refined": refine,
            "best_constant": const,
        },
        "steps": m["step"],
        "minutes": minutes,
        "date": datetime.date.today().isoformat(),
    }
    for part in metrics["heldout"].values():
        if isinstance(part, dict):
            part.pop("spectrum", None)
            part.pop("curve", None)
    (args.out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")

    def line(name: str, r: dict | None) -> str:
        if r is None:
            return f"| {name} | — | — | — |\n"
        return f"| {name} | {r['shading_psnr']:.2f} | {r['object_psnr']:.2f} | {r.get('seconds_per_image', float('nan')) * 1e3:.1f} |\n"

    card = f"""# shading/generator: the amortised shading generator

A conditioned convolutional UNet (`lasagna.generators.LayerGenerator`: {params_note}) that maps
a base image (the albedo) and a light direction to the shading layer — a 1-channel multiplier
y = 2·sigmoid(·) in [0, 2] — in one forward pass, at any image size (fully convolutional). It is
initialised to the identity edit (y = 1) and trained *through the composite* f(x, y) = x·y with
{cfg["loss"].upper()} at ω = {cfg["guidance"]:g} from the bundled prior `relight-32` and its spectral corrective
`relight-32-spectral` — the LMC-SDS paper's image-to-image network (Sec. 5.2): the score weight rises
0.1 → 1 and the L2 to the input falls 1 → {cfg["weights"]["reg"]["end"]:g} over the first {cfg["weights"]["reg"]["steps"]} steps (cosine).

## Data and training
Fresh batches of {cfg["batch_size"]} world scenes of the `{cfg["split"]}` split every step (albedo as the base, a
uniformly drawn light direction); nothing on disk. {m["step"]} steps in {minutes} minutes on one thread of this
2-vCPU box (Adam lr {cfg["lr"]}, EMA {cfg["ema_decay"]}, seed {cfg["seed"]}). The supervised ceiling is the same generator
trained for the same {round(cumulative_minutes(log_c)[-1], 1)} minutes on the true shading (MSE), {mc["step"]} steps. Reproduce:

```sh
LASAGNA_LAYERS=layers lasagna train-layer --preset shading --out runs/shading-generator --steps {m["step"]} --install --force   # ≈ {minutes} min here; resumable
lasagna train-layer --preset shading --supervised --out runs/shading-supervised --steps {mc["step"]}
python benchmarks/distill_accuracy.py && python benchmarks/generator_card.py
```

![training](loss.png)

## Quality
`val` split (seen shape families, other seeds; {cfg["eval_count"]} scenes, `metrics.json` of the runs): shading PSNR
**{m["layer_psnr"]:.2f} dB** distilled vs {mc["layer_psnr"]:.2f} dB supervised ceiling (identity edit {m["identity_psnr"]:.2f} dB);
composite PSNR {m["layer_composite_psnr"]:.2f} vs {mc["layer_composite_psnr"]:.2f} dB.

`heldout` split (torus, capsule, cone; textures and walls never seen; {acc["count"]} scenes; `benchmarks/distill_accuracy.py`):

| method | shading PSNR (dB) | object pixels (dB) | ms per image |
|---|---|---|---|
{line("this generator, one forward pass", distilled)}{line(f"this generator, then {refine['method'].removeprefix('amortised + ')}" if refine else "this generator + refinement", refine)}{line(f"per-image {cfg['loss']} ω = {cfg['guidance']:g} (free layer, {acc['steps']} steps)", per_image)}{line("supervised ceiling, one forward pass", ceiling)}| best constant per image | {const["shading_psnr"]:.2f} | {const["object_psnr"]:.2f} | — |

Measured {metrics["date"]}; full tables in [docs/BENCHMARKS.md](../../../docs/BENCHMARKS.md#learned-layers).
"""
    (args.out / "MODEL.md").write_text(card)
    print(
        json.dumps(
            {
                "val_psnr": m["layer_psnr"],
                "heldout_psnr": distilled and distilled["shading_psnr"],
                "ceiling_heldout": ceiling and ceiling["shading_psnr"],
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
