"""Surface layers on held-back scenes: shading and relight through one estimated surface, with their oracles.

    OMP_NUM_THREADS=1 python benchmarks/surface.py --splits select heldout --sizes 64 256 \
        --albedo layers/surface-albedo-32 --lit layers/surface-lit-32 --json-out docs/surface.json

Rows per split and size (``--count`` scenes of world seed 0, the light cycling through the eight named lights):

* **shading** (the base is the albedo; the layer multiplies it; dB over the best constant, all / object pixels):
  the best constant; *oracle: true outlines inflated* (each object's true silhouette inflated into a dome,
  `lasagna.compose.surface.inflate_regions`, Lambert-shaded under the scene's light — what a model that knows
  the outlines and assumes round shapes reaches), and the same with the dome's height chosen per scene by the
  truth from ``ORACLE_HEIGHTS`` (issue #24's own oracle); *truth at working size 32* (the true shading reduced to the
  working size and enlarged back: the headroom of any layer made at that size); *truth on the objects, the wall
  flat* (the headroom of any layer made from the albedo: the wall's relief is not in the paint); the albedo
  estimator's surface.
* **relight** (the base is the scene lit by its own random source light; the layer is S(target)/S(source);
  dB of the clamped composite over the unchanged input): the oracle with the true source light; truth at
  working size; the lit estimator with its own source-light estimate, and with the true one (a diagnostic of
  the light head alone).
* **leak** on walls alone (every scene's objects removed: the true shading is one constant): the layer's PSNR
  against its own mean; ∞ for a flat surface.

``--stray SEED`` multiplies every relight scene's input and truth by stray illumination (`lasagna.world.stray`:
light that does not move with the key light; the true ratio is unchanged), a diagnostic of an estimator's reading
of it. ``far`` is the final measurement: pass it only then (``--splits far``). Ends with one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import PHOTO_AXES, machine_info, print_json_line, psnr, read_photo  # noqa: E402
from _common import swing as photo_swing  # noqa: E402

from lasagna.compose.resample import downsample, upsample  # noqa: E402
from lasagna.compose.surface import (  # noqa: E402
    dome_normals,
    inflated_normals,
    lambert,
    light_vector,
)
from lasagna.document.condition import parse_direction  # noqa: E402
from lasagna.document.preset import SYMMETRIES  # noqa: E402
from lasagna.generators.surface import DomePrior, SurfaceEstimator  # noqa: E402
from lasagna.training.surface import estimator_from_checkpoint  # noqa: E402
from lasagna.world import VOCABULARY, render, sample_scenes  # noqa: E402
from lasagna.world.stray import stray_gain  # noqa: E402
from lasagna.world.tasks import relight_sources, relighting  # noqa: E402

WORKING = 32
# The size the estimators read their input at (``--estimate-at``; None: the size each was trained at).
ESTIMATE_AT: int | None = None
# The estimators' symmetry ensemble (``--symmetry``: `SurfaceEstimator.estimate`'s ``symmetry``).
SYMMETRY = "none"


def dome_label(dome) -> str:
    return "" if dome is None or dome.weight == 0 else f" + domes (weight {dome.weight:g}, height {dome.height:g})"


def lights_of(conditions: list[str]) -> torch.Tensor:
    return torch.stack([light_vector(*parse_direction(c)) for c in conditions])


def scenes(split: str, count: int, seed: int, size: int, walls: bool = False, shadows: bool = False):
    """The split's first ``count`` scenes at ``size``, each under a named light cycling through VOCABULARY (walls
    alone with ``walls``; with ``shadows`` the world's exact cast shadows, `lasagna.world.scene.render`)."""
    labels = [VOCABULARY[i % len(VOCABULARY)] for i in range(count)]
    params = sample_scenes(split, seed, range(count))
    if walls:
        params = params.walls_only()
    return render(params.with_labels(labels), size, shadows=shadows), labels


def oracle_normals(scene) -> torch.Tensor:
    """The oracle's normals: the true outlines inflated into domes, the wall flat (``inflated_normals``)."""
    return inflated_normals(scene.object_index)


ORACLE_HEIGHTS = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
"""The dome heights (× the round dome's) issue #24's oracle picks from, per scene, by the truth."""


def best_per_scene(candidates: list[torch.Tensor], truth: torch.Tensor) -> torch.Tensor:
    """For every scene, the candidate (each (B, C, H, W)) with the least squared error to ``truth`` over all its
    pixels: an oracle that chooses by the truth, as issue #24's "best dome height per scene" does."""
    err = torch.stack([(c.double() - truth.double()).pow(2).flatten(1).mean(1) for c in candidates])  # (K, B)
    pick = err.argmin(0)
    return torch.stack([candidates[int(k)][i] for i, k in enumerate(pick)])


def objects_only(scene) -> torch.Tensor:
    """The true normals on the objects and a flat wall: the headroom of any layer made from the albedo, where the
    wall's relief is not in the paint (no method reading the albedo can see it)."""
    flat = torch.zeros_like(scene.normals)
    flat[:, 2] = 1.0
    return torch.where(scene.mask.bool().expand_as(flat), scene.normals, flat)


def gain_row(method: str, y: torch.Tensor, truth: torch.Tensor, mask: torch.Tensor, base_db, seconds=None) -> dict:
    a, o = psnr(y, truth), psnr(y, truth, mask)
    row = {"method": method, "gain_db": round(a - base_db[0], 2), "gain_obj_db": round(o - base_db[1], 2)}
    if seconds is not None:
        row["seconds_per_image"] = round(seconds, 4)
    return row


def edit_layers(
    images: torch.Tensor, preset: str, labels: list[str], sources: list[str] | None = None, **options
) -> tuple[torch.Tensor, float]:
    """``lasagna edit``'s layer for every image (B, 3, H, W) with ``options`` (e.g. layer_kind), each with its
    source light given (``--from``) where ``sources`` is, and seconds per image: what a user gets, through the
    whole edit path."""
    from lasagna import edit

    t0 = time.perf_counter()
    given = [{} if sources is None else {"source_light": sources[i]} for i in range(images.shape[0])]
    layers = [edit(images[i], preset, labels[i], **options, **given[i]).layer[:1] for i in range(images.shape[0])]
    return torch.stack(layers), (time.perf_counter() - t0) / images.shape[0]


def shading_rows(scene, labels, albedo_net, edits: list[str], dome=None) -> list[dict]:
    truth, mask = scene.shading, scene.mask
    const = truth.mean(dim=(1, 2, 3), keepdim=True).expand_as(truth)
    cdb = (psnr(const, truth), psnr(const, truth, mask))
    light = lights_of(labels)
    size = tuple(truth.shape[-2:])
    rows = [
        gain_row("best constant", const, truth, mask, cdb),
        gain_row(
            "oracle: true outlines inflated",
            lambert(oracle_normals(scene), light),
            truth,
            mask,
            cdb,
        ),
        gain_row(
            "oracle: true outlines inflated, best height per scene (the issue's)",
            best_per_scene([lambert(dome_normals(scene.object_index, h), light) for h in ORACLE_HEIGHTS], truth),
            truth,
            mask,
            cdb,
        ),
        gain_row(
            f"truth at working size {WORKING}", upsample(downsample(truth, (WORKING, WORKING)), size), truth, mask, cdb
        ),
        gain_row("truth on the objects, the wall flat", lambert(objects_only(scene), light), truth, mask, cdb),
    ]
    if albedo_net is not None:
        t0 = time.perf_counter()
        n, _ = albedo_net.estimate_at(scene.albedo, dome, side=ESTIMATE_AT, symmetry=SYMMETRY)
        y = lambert(n, light)
        secs = (time.perf_counter() - t0) / len(labels)
        rows.append(gain_row(f"surface estimator (albedo){dome_label(dome)}", y, truth, mask, cdb, secs))
    for kind in edits:
        y, secs = edit_layers(scene.albedo, "shading", labels, layer_kind=kind)
        rows.append(gain_row(f"lasagna edit --layer shading --layer-kind {kind}", y, truth, mask, cdb, secs))
    return rows


def relight_rows(
    scene, labels, lit_net, edits: list[str], dome=None, stray: int | None = None, given_source: bool = False
) -> list[dict]:
    sources = relight_sources(scene.params)
    rel = relighting(scene, sources)
    base, target, mask = rel.base, rel.target.clamp(0, 1), scene.mask
    if stray is not None:  # light that is not relief, on input and truth alike: the true ratio is unchanged
        gain = stray_gain(scene.mask, torch.Generator().manual_seed(stray)).to(base.dtype)
        base, target = (base * gain).clamp(0, 1), (rel.target * gain).clamp(0, 1)
    bdb = (psnr(base.clamp(0, 1), target), psnr(base.clamp(0, 1), target, mask))
    size = tuple(base.shape[-2:])
    src, tgt = lights_of(sources), lights_of(labels)

    def comp(ratio):
        return (base * ratio).clamp(0, 1)

    n_oracle = oracle_normals(scene)
    rows = [
        gain_row("unchanged input", base.clamp(0, 1), target, mask, bdb),
        gain_row(
            "oracle: true outlines inflated, true source light",
            comp(lambert(n_oracle, tgt) / lambert(n_oracle, src)),
            target,
            mask,
            bdb,
        ),
        gain_row(
            "oracle: true outlines inflated, true source light, best height per scene (the issue's)",
            best_per_scene(
                [
                    comp(lambert(n, tgt) / lambert(n, src))
                    for n in (dome_normals(scene.object_index, h) for h in ORACLE_HEIGHTS)
                ],
                target,
            ),
            target,
            mask,
            bdb,
        ),
        gain_row(
            f"truth at working size {WORKING}",
            comp(upsample(downsample(rel.layer, (WORKING, WORKING)), size)),
            target,
            mask,
            bdb,
        ),
    ]
    if lit_net is not None:
        t0 = time.perf_counter()
        n, light = lit_net.estimate_at(base, dome, side=ESTIMATE_AT, symmetry=SYMMETRY)
        ratio = lambert(n, tgt) / lambert(n, light)
        secs = (time.perf_counter() - t0) / len(labels)
        method = f"surface estimator (lit){dome_label(dome)}, its source light"
        rows.append(gain_row(method, comp(ratio), target, mask, bdb, secs))
        rows.append(
            gain_row(
                "surface estimator (lit), true source light", comp(lambert(n, tgt) / lambert(n, src)), target, mask, bdb
            )
        )
        err = torch.rad2deg(torch.acos((light * src).sum(1).clamp(-1, 1)))
        rows[-2]["source_light_error_deg_median"] = round(float(err.median()), 1)
    for kind in edits:
        ratio, secs = edit_layers(base.float(), "relight", labels, layer_kind=kind)
        rows.append(gain_row(f"lasagna edit --layer relight --layer-kind {kind}", comp(ratio), target, mask, bdb, secs))
        if given_source and kind == "surface":  # told the true source light (--from), as a user who knows it would
            ratio, secs = edit_layers(base.float(), "relight", labels, sources, layer_kind=kind)
            method = f"lasagna edit --layer relight --layer-kind {kind} --from (the true source light)"
            rows.append(gain_row(method, comp(ratio), target, mask, bdb, secs))
    return rows


def leak_row(args, split: str, size: int, albedo_net, lit_net, dome=None) -> dict:
    walls, labels = scenes(split, args.count, args.seed, size, walls=True)
    out = {"split": split, "size": size}
    for name, net, image in (("albedo", albedo_net, walls.albedo), ("lit", lit_net, None)):
        if net is None:
            continue
        if image is None:
            image = relighting(walls, relight_sources(walls.params)).base
        n, _ = net.estimate_at(image, dome, side=ESTIMATE_AT, symmetry=SYMMETRY)
        y = lambert(n, lights_of(labels)).double()
        flat = y.mean(dim=(1, 2, 3), keepdim=True).expand_as(y)
        out[f"leak_db_{name}"] = round(psnr(y, flat), 2)
    if args.edit_leak:  # the edits' own layers on the walls (shading: the albedo; relight: lit), every --edits kind
        lit = relighting(walls, relight_sources(walls.params)).base.float()
        for kind in args.edits:
            for preset, image in (("shading", walls.albedo.float()), ("relight", lit)):
                y = edit_layers(image, preset, labels, layer_kind=kind)[0].double()
                flat = y.mean(dim=(1, 2, 3), keepdim=True).expand_as(y)
                out[f"leak_db_{preset}_{kind}"] = round(psnr(y, flat), 2)
            if args.given_source and kind == "surface":  # the surface relight told the true source light (--from)
                y = edit_layers(lit, "relight", labels, relight_sources(walls.params), layer_kind=kind)[0].double()
                flat = y.mean(dim=(1, 2, 3), keepdim=True).expand_as(y)
                out[f"leak_db_relight_{kind}_given"] = round(psnr(y, flat), 2)
    return out


def photo_rows(lit_net, folder: Path, sheet: Path | None, dome=None) -> list[dict]:
    """Relight each photograph toward opposite lights; the swing of composite/input between the thirds nearest and
    farthest from the light, summed over the two edits of an axis (≥ 0.10 per photo and axis is the target)."""
    rows, tiles = [], []
    for file in sorted(folder.glob("*.jpg")):
        image = read_photo(file)
        t0 = time.perf_counter()
        n, source = lit_net.estimate_at(image, dome, side=ESTIMATE_AT, symmetry=SYMMETRY)
        seconds = time.perf_counter() - t0
        row = {"photo": file.stem, "size": list(image.shape[-2:]), "estimate_seconds": round(seconds, 3)}
        composites = {}
        for axis, pair in PHOTO_AXES.items():
            swing = 0.0
            for light in pair:
                ratio = lambert(n, lights_of([light])) / lambert(n, source)
                comp = (image * ratio).clamp(0, 1)
                swing += photo_swing(image, comp, light)
                composites[light] = comp
            row[f"swing_{axis}"] = round(swing, 4)
        rows.append(row)
        print(json.dumps({"photo": row}), flush=True)
        shading = lambert(n, lights_of(["top-left"])).expand(-1, 3, -1, -1)
        tiles.append(torch.cat([image, (n + 1) / 2, shading, composites["left"], composites["right"]], -1))
    if sheet is not None and tiles:
        save_sheet(tiles, sheet)
    return rows


def albedo_photo_sheet(albedo_net, folder: Path, sheet: Path, dome=None) -> None:
    """The shading preset's surface on each photograph (512²): input | normal map | the input shaded from the left |
    from the right — to look at: the shading should follow shape, not paint."""
    tiles = []
    for file in sorted(folder.glob("*.jpg")):
        image = read_photo(file)
        n, _ = albedo_net.estimate_at(image, dome, side=ESTIMATE_AT, symmetry=SYMMETRY)
        shaded = [image * lambert(n, lights_of([light])) for light in ("left", "right")]
        tiles.append(torch.cat([image, (n + 1) / 2, *shaded], -1))
    save_sheet(tiles, sheet)


def save_sheet(rows: list[torch.Tensor], sheet: Path) -> None:
    """Rows (1, 3, h, w) of tiles stacked top to bottom (narrower rows padded black), saved at half size: a sheet to
    look at, not a measurement."""
    from PIL import Image

    w = max(t.shape[-1] for t in rows)
    rows = [torch.nn.functional.pad(t, (0, w - t.shape[-1])) for t in rows]
    grid = torch.cat(rows, -2)[0].clamp(0, 1).permute(1, 2, 0).numpy()
    sheet.parent.mkdir(parents=True, exist_ok=True)
    im = Image.fromarray((grid * 255 + 0.5).astype("uint8"))
    im.resize((im.width // 2, im.height // 2), Image.LANCZOS).save(sheet)


def load(path: str | None) -> SurfaceEstimator | None:
    """A saved estimator folder, or a run's checkpoint.safetensors (its EMA weights: a run measured mid-way)."""
    if path is None:
        return None
    if str(path).endswith(".safetensors"):
        return estimator_from_checkpoint(path)[0]
    return SurfaceEstimator.from_pretrained(path)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--splits", nargs="+", default=["select", "heldout"])
    p.add_argument("--sizes", nargs="+", type=int, default=[64, 256])
    p.add_argument("--count", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--albedo", default=None, help="an albedo-input surface estimator folder")
    p.add_argument("--lit", default=None, help="a lit-input surface estimator folder")
    p.add_argument(
        "--dome",
        default=None,
        metavar="WEIGHT,HEIGHT",
        help="mix the dome prior into the estimators' normals (needs a silhouette head), e.g. 0.5,0.5",
    )
    p.add_argument("--json-out", type=Path, default=None)
    p.add_argument(
        "--edits",
        nargs="*",
        default=[],
        choices=("free", "surface"),
        help="also measure `lasagna edit` with these --layer-kind (the catalogue's presets: free is today's layer)",
    )
    p.add_argument(
        "--given-source",
        action="store_true",
        help="also measure the relight surface layer (--edits surface) told the scene's true source light (--from)",
    )
    p.add_argument(
        "--edit-leak",
        action="store_true",
        help="also measure the wall leak of `lasagna edit --layer shading` and `--layer relight`, each --edits kind",
    )
    p.add_argument("--photos", type=Path, default=ROOT / "examples" / "photos" / "large", help="512² photographs")
    p.add_argument("--sheet", type=Path, default=None, help="photo sheet: input | normals | shading | left | right")
    p.add_argument(
        "--albedo-sheet", type=Path, default=None, help="albedo estimator photo sheet: input | normals | left | right"
    )
    p.add_argument(
        "--estimate-at",
        type=int,
        default=None,
        metavar="SIDE",
        help="read the estimators' inputs at this working size instead of their own (a diagnostic)",
    )
    p.add_argument(
        "--symmetry",
        choices=SYMMETRIES,
        default="none",
        help="the estimators' symmetry ensemble (a preset's surface.symmetry)",
    )
    p.add_argument(
        "--stray",
        type=int,
        default=None,
        metavar="SEED",
        help="a diagnostic: every relight scene's input and truth times a stray illumination gain "
        "(lasagna.world.stray, drawn from SEED): a sky's gradient, a vignette or a pool that stays when relit",
    )
    args = p.parse_args(argv)
    global ESTIMATE_AT, SYMMETRY
    ESTIMATE_AT, SYMMETRY = args.estimate_at, args.symmetry
    albedo_net, lit_net = load(args.albedo), load(args.lit)
    dome = None
    if args.dome:
        weight, height = (float(v) for v in args.dome.split(","))
        dome = DomePrior(weight=weight, height=height)
    result = {"machine": machine_info(), "command": " ".join(sys.argv), "shading": [], "relight": [], "leak": []}
    if albedo_net is not None and args.albedo_sheet is not None and args.photos.is_dir():
        albedo_photo_sheet(albedo_net, args.photos, args.albedo_sheet, dome)
    if lit_net is not None and args.photos.is_dir():
        result["photos"] = photo_rows(lit_net, args.photos, args.sheet, dome)
    for split in args.splits:
        for size in args.sizes:
            scene, labels = scenes(split, args.count, args.seed, size)
            for task, rows in (
                ("shading", shading_rows(scene, labels, albedo_net, args.edits, dome)),
                ("relight", relight_rows(scene, labels, lit_net, args.edits, dome, args.stray, args.given_source)),
            ):
                for r in rows:
                    r.update(split=split, size=size)
                    print(json.dumps({task: r}), flush=True)
                    result[task].append(r)
            leak = leak_row(args, split, size, albedo_net, lit_net, dome)
            print(json.dumps({"leak": leak}), flush=True)
            result["leak"].append(leak)
    if args.json_out is not None:
        args.json_out.write_text(json.dumps(result, indent=1) + "\n", encoding="utf-8")

    def best(task: str, method: str, key: str):
        vals = [r[key] for r in result[task] if r["method"] == method and r["split"] == args.splits[0]]
        return min(vals) if vals else None

    print_json_line(
        {
            "split": args.splits[0],
            "shading_gain_obj_db": best("shading", f"surface estimator (albedo){dome_label(dome)}", "gain_obj_db"),
            "shading_oracle_obj_db": best("shading", "oracle: true outlines inflated", "gain_obj_db"),
            "relight_gain_obj_db": best(
                "relight", f"surface estimator (lit){dome_label(dome)}, its source light", "gain_obj_db"
            ),
            "relight_oracle_obj_db": best(
                "relight", "oracle: true outlines inflated, true source light", "gain_obj_db"
            ),
        }
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
