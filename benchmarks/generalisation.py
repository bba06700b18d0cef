"""Generalisation of the learned layers: `heldout` (chooses every default) and `far` (touched only here), 64² and 256².

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/generalisation.py              (~20 min on 2 vCPUs)
    .venv/bin/python benchmarks/generalisation.py --quick                          (~1 min smoke run)
    .venv/bin/python benchmarks/generalisation.py --catalogue runs/cand/layers     (a candidate catalogue first)

`far`'s shape, texture and relief families are used neither in training nor in choosing anything
(`lasagna.world.splits`); `heldout`'s are new to training too and choose defaults. For each split and
size, on ``--count`` scenes (base = albedo, labels cycling through the vocabulary), against the world's
truth:

* **shading** (the `shading` preset): the identity edit (y = 1), the best constant (per image, least
  squares: the bar every learned layer must clear), the prior sampled directly (DDIM-50 at its size,
  the implied shading enlarged), **the default edit** — exactly ``lasagna edit --layer shading`` (the
  API's ``edit``, one image at a time, its stored 8-bit input) — per-image SDS and LMC-SDS at each
  ``--omegas`` (batched, at the preset's working size, enlarged as the edit does), and the supervised
  ceiling (``--supervised``: the same generator trained on the true shading, run the same way).
  PSNR over all pixels and over object pixels, and the gain over the best constant;
* **texture leak**: the same splits' walls with no objects and no relief (their true shading is one
  constant): PSNR of the default edit's layer against its own mean, and its σ;
* **light** (the `light` preset): no light, the oracle constant glow (per image and channel), the
  default edit; glow PSNR, colour error (°), darkening;
* **sheets**: `far` scenes (albedo | true shading | default | supervised) and the 512² photographs
  (photo | layer and composite for two lights), in ``docs/img/``.

Writes ``--json-out`` and the sheets; ends with one JSON line: ``far_gain_db``, ``far_gain_obj_db``,
``far256_gain_db``, ``leak_db`` (the worst of far and heldout at both sizes), ``heldout_gain_db`` and
the rest of the headline (default edit of the shading preset, dB over the best constant).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import (  # noqa: E402
    add_labels,
    darkening,
    glow_colour_error,
    implied_shading,
    machine_info,
    print_json_line,
    psnr,
    save_sheet,
)

from lasagna import catalogue as cat  # noqa: E402
from lasagna.compose.resample import downsample, upsample, working_size  # noqa: E402
from lasagna.compose.surface import inflated_normals  # noqa: E402
from lasagna.distill import DistillSettings, distill_image  # noqa: E402
from lasagna.editing import edit  # noqa: E402
from lasagna.priors.base import Condition  # noqa: E402
from lasagna.priors.ddim import ddim_sample  # noqa: E402
from lasagna.world import GLOW_VOCABULARY, VOCABULARY, additive_light, generate, render, sample_scenes  # noqa: E402
from lasagna.world.lighting import lambert, light_vectors  # noqa: E402

PHOTOS = ("astronaut", "coffee", "rocket", "chelsea")
PHOTO_LIGHTS = ("left", "top-right")


def region_means(shading: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """Each visible object's and the wall's own true mean shading: what silhouettes alone could reach.

    An oracle (it reads the truth, as the best constant does): a layer that knows every object's outline
    and its average brightness, but nothing of its shape inside. Its gain over the best constant bounds
    what outlines buy; the rest of a target above it has to come from shape inferred inside objects.
    """
    out = torch.empty_like(shading)
    for b in range(shading.shape[0]):
        for k in index[b].unique():
            where = index[b] == k
            out[b][where] = shading[b][where].mean()
    return out


def inflated_silhouettes(index: torch.Tensor, labels: list[str]) -> torch.Tensor:
    """Shading of every object's *true* outline inflated into a round dome, lit by the scene's light.

    Another oracle (it reads the true outlines, not the albedo): each visible object region becomes a height
    field with a circular profile (`lasagna.compose.surface.inflate_regions`: a disc inflates to the exact
    hemisphere), the wall keeps n = +z (``inflated_normals``), Lambert with the condition's light. This is the
    classic shape-from-silhouette prior (Johnston's Lumo, Teddy-style inflation): what a model that only segments
    objects and assumes generic round shapes can reach. Faceted objects (far's octahedra and prisms) are where it
    falls short.
    """
    return lambert(inflated_normals(index), light_vectors(labels, dtype=torch.float64)).float()


# -- shading ------------------------------------------------------------------------------------
def row(method: str, y: torch.Tensor, scene, const_db: tuple[float, float], seconds: float | None, **extra) -> dict:
    """Shading metrics of y (B, 1, H, W) against the scene's truth, and the gain over the best constant."""
    all_db, obj_db = psnr(y, scene.shading), psnr(y, scene.shading, scene.mask)
    out = {
        "method": method,
        "shading_psnr": round(all_db, 2),
        "object_psnr": round(obj_db, 2),
        "gain_db": round(all_db - const_db[0], 2),
        "gain_obj_db": round(obj_db - const_db[1], 2),
    }
    if seconds is not None:
        out["seconds_per_image"] = round(seconds / y.shape[0], 4)
    return {**out, **extra}


def default_edit(images: torch.Tensor, labels: list[str], preset: str, dirs, **options) -> tuple[torch.Tensor, float]:
    """``lasagna edit``'s default (or with ``options``: ``generator``, ``optimize``) for every image (B, 3, H, W)
    → layers (B, C, H, W), seconds in all."""
    t0 = time.perf_counter()
    layers = [edit(images[i], preset, labels[i], catalogue_dirs=dirs, **options).layer for i in range(images.shape[0])]
    return torch.stack(layers), time.perf_counter() - t0


def at_working_size(fn, images: torch.Tensor, side: int | None) -> torch.Tensor:
    """fn(images reduced to the working size) enlarged back, as ``lasagna edit`` makes a layer."""
    full = tuple(images.shape[-2:])
    return upsample(fn(downsample(images, working_size(*full, side))), full)


def supervised_layers(albedo: torch.Tensor, labels, folder: Path, side: int | None) -> torch.Tensor:
    from lasagna.generators.unet import LayerGenerator

    gen = LayerGenerator.from_pretrained(folder)
    with torch.no_grad():
        return at_working_size(lambda x: gen(x, labels)[:, :1], albedo, side)


def per_image(scene, labels, preset, prior, corrective, loss: str, omega: float, steps: int) -> torch.Tensor:
    settings = DistillSettings.from_preset(preset, loss=loss, guidance=omega, steps=steps, seed=0)

    def run(x):
        return (
            distill_image(
                x, settings, prior, corrective if loss == "lmc-sds" else None, condition=labels, early_stop=False
            )
            .layer[:, :1]
            .detach()
        )

    return at_working_size(run, scene.albedo, preset.working_size)


def prior_direct(scene, labels, prior, omega: float) -> torch.Tensor:
    side = prior.sample_shape[-1]
    small = downsample(scene.albedo, (side, side))
    out = ddim_sample(
        prior, Condition(labels, image=small), steps=50, omega=omega, rng=torch.Generator().manual_seed(0)
    ).image
    return upsample(implied_shading(out, small), tuple(scene.albedo.shape[-2:]))


def shading_table(args, split: str, size: int, parts, prior, corrective) -> tuple[list[dict], dict]:
    preset = parts.preset
    labels = [VOCABULARY[i % len(VOCABULARY)] for i in range(args.count)]
    scene = generate(split, args.count, args.seed, size, labels=labels)
    const = scene.shading.mean(dim=(1, 2, 3), keepdim=True).expand_as(scene.shading)
    cdb = (psnr(const, scene.shading), psnr(const, scene.shading, scene.mask))
    rows = [
        row("identity (y = 1)", torch.ones_like(const), scene, cdb, None),
        row("best constant", const, scene, cdb, None),
        row("oracle: true mean per object and wall", region_means(scene.shading, scene.object_index), scene, cdb, None),
        row("oracle: true outlines inflated", inflated_silhouettes(scene.object_index, labels), scene, cdb, None),
    ]
    t0 = time.perf_counter()
    rows.append(
        row(
            "prior sampled directly (ω = 1)",
            prior_direct(scene, labels, prior, 1.0),
            scene,
            cdb,
            time.perf_counter() - t0,
        )
    )
    layers, seconds = default_edit(scene.albedo, labels, "shading", args.catalogue)
    rows.append(row("default edit", layers[:, :1], scene, cdb, seconds))
    for n in args.methods:  # the candidates for the preset's method / refine_steps, each through `lasagna edit`
        if n in ("surface", "free"):  # the layer kinds (issue #24): a surface, or today's per-pixel layer
            y, secs = default_edit(scene.albedo, labels, "shading", args.catalogue, layer_kind=n)
            rows.append(row(f"edit --layer-kind {n}", y[:, :1], scene, cdb, secs))
            continue
        generator, optimize = ("free", None) if n == "per-image" else ("amortised", int(n))
        y, secs = default_edit(scene.albedo, labels, "shading", args.catalogue, generator=generator, optimize=optimize)
        rows.append(
            row(
                f"edit --generator {generator}" + (f" --optimize {n}" if optimize is not None else ""),
                y[:, :1],
                scene,
                cdb,
                secs,
            )
        )
    sup = None
    if args.supervised and (args.supervised / "config.json").is_file():
        sup = supervised_layers(scene.albedo, labels, args.supervised, preset.working_size)
        rows.append(row("supervised ceiling", sup, scene, cdb, None))
    for loss in args.losses:
        if loss == "lmc-sds" and corrective is None:
            continue
        for w in args.omegas:
            t0 = time.perf_counter()
            y = per_image(scene, labels, preset, prior, corrective, loss, w, args.steps)
            rows.append(row(f"per-image {loss}", y, scene, cdb, time.perf_counter() - t0, omega=w, steps=args.steps))
    for r in rows:
        print(json.dumps({"split": split, "size": size, **r}), flush=True)
    sheet = {
        "albedo": scene.albedo[: args.sheet],
        "truth": scene.shading[: args.sheet],
        "default": layers[: args.sheet, :1],
    }
    if sup is not None:
        sheet["supervised"] = sup[: args.sheet]
    return rows, sheet


def leak(args, split: str, size: int) -> dict:
    """The default edit on textured walls alone: its deviation from its own mean (the truth is one constant)."""
    labels = [VOCABULARY[i % len(VOCABULARY)] for i in range(args.count)]
    walls = render(sample_scenes(split, args.seed, range(args.count)).walls_only().with_labels(labels), size)
    y, _ = default_edit(walls.albedo, labels, "shading", args.catalogue)
    y = y[:, :1].double()
    flat = y.mean(dim=(1, 2, 3), keepdim=True).expand_as(y)
    out = {"split": split, "size": size, "leak_db": round(psnr(y, flat), 2), "sigma": round(float((y - flat).std()), 4)}
    print(json.dumps({"leak": out}), flush=True)
    return out


# -- light --------------------------------------------------------------------------------------
def light_table(args, split: str, size: int) -> list[dict]:
    status = cat.preset_status("light", args.catalogue)
    if not status["usable"]:
        return [{"split": split, "size": size, "skipped": status["why"]}]
    labels = [GLOW_VOCABULARY[i % len(GLOW_VOCABULARY)] for i in range(args.count)]
    add = additive_light(generate(split, args.count, args.seed, size), labels)

    def lrow(method, glow, seconds=None):
        comp = (add.base + glow).clamp(0, 1)
        r = {
            "split": split,
            "size": size,
            "method": method,
            "glow_psnr": round(psnr(glow, add.glow), 2),
            "object_psnr": round(psnr(glow, add.glow, add.scene.mask), 2),
            "composite_psnr": round(psnr(comp, add.lit), 2),
            "colour_error_deg": round(glow_colour_error(glow, add.glow), 2),
            "darkening": round(darkening(comp, add.base), 5),
        }
        if seconds is not None:
            r["seconds_per_image"] = round(seconds / glow.shape[0], 4)
        return r

    rows = [
        lrow("no light", torch.zeros_like(add.glow)),
        lrow("oracle constant glow", add.glow.mean(dim=(2, 3), keepdim=True).expand_as(add.glow)),
    ]
    glow, seconds = default_edit(add.base, add_labels(add), "light", args.catalogue)
    rows.append(lrow("default edit", glow, seconds))
    for r in rows:
        print(json.dumps(r), flush=True)
    return rows


# -- sheets -------------------------------------------------------------------------------------


def photo_sheet(args, path: Path) -> list[dict]:
    cols: list[list[torch.Tensor]] = [[]] + [[] for _ in PHOTO_LIGHTS for _ in (0, 1)]
    stats = []
    for name in PHOTOS:
        file = args.photos / f"{name}.jpg"
        if not file.is_file():
            continue
        for k, light in enumerate(PHOTO_LIGHTS):
            t0 = time.perf_counter()
            res = edit(file, "shading", light, catalogue_dirs=args.catalogue)
            seconds = time.perf_counter() - t0
            if k == 0:
                with Image.open(file) as im:
                    cols[0].append(
                        torch.from_numpy(np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0).permute(2, 0, 1)
                    )
            cols[1 + 2 * k].append(res.layer[:1])
            cols[2 + 2 * k].append(res.composite)
            y = res.layer[:1].double()
            stats.append(
                {
                    "photo": name,
                    "light": light,
                    "size": list(y.shape[-2:]),
                    "seconds": round(seconds, 3),
                    "layer_sigma": round(float(y.std()), 4),
                }
            )
    if cols[0]:
        save_sheet(cols, path)
    return stats


# -- markdown -----------------------------------------------------------------------------------
def _fmt(v, spec=".2f") -> str:
    return "—" if v is None else format(v, spec)


def markdown(result: dict) -> str:
    """The tables of docs/BENCHMARKS.md#generalisation from a result dict."""
    out = []
    keys = list(result["shading"])
    methods: list[str] = []
    for k in keys:
        for r in result["shading"][k]:
            name = r["method"] + (f" ω = {r['omega']:g}" if "omega" in r else "")
            if name not in methods:
                methods.append(name)
    out.append("| shading layer | " + " | ".join(f"{k.replace('@', ' ')}²" for k in keys) + " |")
    out.append("|---|" + "---|" * len(keys))
    for m in methods:
        cells = []
        for k in keys:
            r = next(
                (
                    r
                    for r in result["shading"][k]
                    if r["method"] + (f" ω = {r['omega']:g}" if "omega" in r else "") == m
                ),
                None,
            )
            cells.append("" if r is None else f"{r['shading_psnr']:.2f} / {r['object_psnr']:.2f} ({r['gain_db']:+.2f})")
        out.append(f"| {m} | " + " | ".join(cells) + " |")
    out.append("")
    out.append(
        "| texture leak (bare walls) | " + " | ".join(f"{x['split']} {x['size']}²" for x in result["leak"]) + " |"
    )
    out.append("|---|" + "---|" * len(result["leak"]))
    out.append(
        "| default edit: PSNR of the layer against its mean (σ) | "
        + " | ".join(f"{x['leak_db']:.2f} ({x['sigma']:.3f})" for x in result["leak"])
        + " |"
    )
    light = [r for r in result.get("light", []) if "method" in r]
    if light:
        out.append("")
        out.append("| light | split | size | glow PSNR | objects | colour error (°) | darkening |")
        out.append("|---|---|---|---|---|---|---|")
        for r in light:
            out.append(
                f"| {r['method']} | {r['split']} | {r['size']}² | {r['glow_psnr']:.2f} | {r['object_psnr']:.2f} | "
                f"{_fmt(r['colour_error_deg'])} | {r['darkening']:.5f} |"
            )
    if result.get("photos"):
        out.append("")
        out.append("| photograph (512²) | light | layer σ | seconds |")
        out.append("|---|---|---|---|")
        for r in result["photos"]:
            out.append(f"| {r['photo']} | {r['light']} | {r['layer_sigma']:.3f} | {r['seconds']:.2f} |")
    return "\n".join(out)


# -- main ---------------------------------------------------------------------------------------
def headline(shading: dict, leaks: list[dict]) -> dict:
    def gain(split, size, key="gain_db"):
        rows = shading.get(f"{split}@{size}", [])
        r = next((r for r in rows if r["method"] == "default edit"), None)
        return None if r is None else r[key]

    head = {
        "far_gain_db": gain("far", 64),
        "far_gain_obj_db": gain("far", 64, "gain_obj_db"),
        "far256_gain_db": gain("far", 256),
        "far256_gain_obj_db": gain("far", 256, "gain_obj_db"),
        "heldout_gain_db": gain("heldout", 64),
        "heldout256_gain_db": gain("heldout", 256),
        "leak_db": min((x["leak_db"] for x in leaks), default=None),
    }
    for split in ("far", "heldout"):
        rows = shading.get(f"{split}@64", [])
        ceil = next((r for r in rows if r["method"] == "supervised ceiling"), None)
        dflt = next((r for r in rows if r["method"] == "default edit"), None)
        if ceil and dflt:
            head[f"{split}_below_ceiling_db"] = round(ceil["shading_psnr"] - dflt["shading_psnr"], 2)
    return head


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--splits", nargs="+", default=["heldout", "far"])
    ap.add_argument("--sizes", nargs="+", type=int, default=[64, 256])
    ap.add_argument("--count", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0, help="world seed of the scenes")
    ap.add_argument("--steps", type=int, default=150, help="per-image steps")
    ap.add_argument(
        "--methods",
        nargs="*",
        default=[],
        help="edit variants to add: 'per-image' (the preset's per-image run), N (amortised + N refine steps), "
        "'surface' or 'free' (--layer-kind)",
    )
    ap.add_argument("--losses", nargs="*", default=["sds", "lmc-sds"])
    ap.add_argument("--omegas", nargs="*", type=float, default=[1.0, 3.0])
    ap.add_argument("--supervised", type=Path, default=ROOT / "runs" / "shading-supervised" / "generator")
    ap.add_argument("--catalogue", type=Path, nargs="*", default=None, help="catalogue folders searched first")
    ap.add_argument("--photos", type=Path, default=ROOT / "examples" / "photos" / "large")
    ap.add_argument("--no-light", action="store_true")
    ap.add_argument("--sheet", type=int, default=8, help="scenes in the far sheet")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="4 scenes, 64² only, 5 per-image steps, no photos")
    ap.add_argument("--markdown", action="store_true", help="print the tables of docs/BENCHMARKS.md")
    ap.add_argument("--photos-only", action="store_true", help="add the photograph sheet to the run in --json-out")
    ap.add_argument("--replot", action="store_true", help="print the tables from --json-out without running anything")
    ap.add_argument("--json-out", type=Path, default=ROOT / "docs" / "generalisation.json")
    ap.add_argument("--img", type=Path, default=ROOT / "docs" / "img")
    args = ap.parse_args(argv)
    if args.replot:
        print(markdown(json.loads(args.json_out.read_text())))
        return 0
    if args.photos_only:  # redo the photograph sheet of a saved run
        result = json.loads(args.json_out.read_text())
        result["photos"] = photo_sheet(args, args.img / "generalisation_photos.png")
        args.json_out.write_text(json.dumps(result, indent=1) + "\n")
        print(markdown(result))
        return 0
    if args.quick:
        args.count, args.sizes, args.steps, args.omegas, args.sheet = 4, [64], 5, [1.0], 4
        args.json_out, args.img, args.photos = (
            Path("/tmp/generalisation_quick.json"),
            Path("/tmp/generalisation_quick"),
            Path("/nonexistent"),
        )
    torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    parts = cat.resolve("shading", catalogue_dirs=args.catalogue)
    prior = cat.load_prior(parts.prior)
    corrective = cat.load_corrective(parts.corrective) if parts.corrective else None
    result: dict = {
        "machine": machine_info(),
        "count": args.count,
        "seed": args.seed,
        "steps": args.steps,
        "preset": parts.preset.model_dump(mode="json"),
        "generator": str(parts.generator),
        "shading": {},
        "leak": [],
        "light": [],
    }
    sheets = {}
    for split in args.splits:
        for size in args.sizes:
            rows, sheet = shading_table(args, split, size, parts, prior, corrective)
            result["shading"][f"{split}@{size}"] = rows
            sheets[(split, size)] = sheet
            result["leak"].append(leak(args, split, size))
            if not args.no_light:
                result["light"] += light_table(args, split, size)
    for (split, size), sheet in sheets.items():
        if size == min(args.sizes):
            cols = [list(sheet[key]) for key in ("albedo", "truth", "default", "supervised") if key in sheet]
            save_sheet(cols, args.img / f"generalisation_{split}.png")
    result["photos"] = photo_sheet(args, args.img / "generalisation_photos.png")
    result["headline"] = headline(result["shading"], result["leak"])
    result["wall_seconds"] = round(time.perf_counter() - t_start, 1)
    args.json_out.parent.mkdir(parents=True, exist_ok=True)
    args.json_out.write_text(json.dumps(result, indent=1) + "\n")
    if args.markdown:
        print(markdown(result))
    print_json_line({"benchmark": "generalisation", **result["headline"], "wall_seconds": result["wall_seconds"]})
    return 0


if __name__ == "__main__":
    sys.exit(main())
