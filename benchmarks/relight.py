"""Relighting what is already lit (issue #11): the `relight` preset on `heldout` and `far`, 64² and 256².

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/relight.py                  (~10 min on 2 vCPUs)
    .venv/bin/python benchmarks/relight.py --quick                              (~1 min smoke run)

Each scene of the world is lit by its own random source light A (``lasagna.world.tasks.relight_sources``:
any azimuth, elevation in the relight range; the base is that lit image) and must be relit to a named light
B (labels cycling through the vocabulary); the truth is the scene under B and the ratio S_B / S_A. Rows,
against the truth, composite PSNR over all pixels and over object pixels, and the ratio layer's PSNR (in its
[0, 4] units divided by 4):

* **unchanged input** (ratio 1): the bar the issue's targets are measured from;
* **best constant multiplier** per image (least squares, in [0, 4]);
* **the prior sampled directly** (DDIM-50 at its size, conditioned on the lit input; the implied ratio
  target / input, enlarged, applied to the input);
* **the default edit** — exactly ``lasagna edit --layer relight`` (the API's ``edit``, one image at a time);
* ``--omegas`` × ``--losses``: per-image runs at other guidance weights and losses (the default is SDS at
  ω = 1; ``lmc-sds`` needs a preset with a corrective, e.g. a candidate catalogue through ``--catalogue``);
* ``--methods N …``: the preset's amortised generator (``lasagna edit --generator amortised``), then N
  refinement steps (0: the one forward pass);
* ``--supervised FOLDER``: the supervised ceiling, the same generator trained on the world's true ratio
  (``lasagna train-layer --preset relight --supervised``), run as the edit runs a generator.

**Directions between the named ones**: the
same scenes relit to az + 22.5° of each named light (rows "… between the named"), through the same edit with
``--condition az=…,el=…`` (the prior is conditioned on the direction's unit vector). **Texture leak**: walls with
no objects and no relief, whose true ratio is one constant: PSNR of the default layer (/4) against its own
mean. **Sheets** (``docs/img/relight_{heldout,far}.png``, the first ``--sheet`` scenes at the smallest size):
input | truth | composites of the default edit, the amortised generator and the supervised ceiling | their
ratio layers (ratio / 2 as grey: mid-grey is "unchanged"). Ends with one JSON line: ``far_gain_db``,
``far_gain_obj_db``, ``far256_gain_db`` (default edit over the unchanged input) and the rest of the headline.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import RANGE_HI, machine_info, print_json_line, psnr, row, save_sheet, scenes  # noqa: E402

from lasagna import catalogue as cat  # noqa: E402
from lasagna.compose.resample import downsample, upsample  # noqa: E402
from lasagna.compose.surface import inflated_normals, lambert  # noqa: E402
from lasagna.editing import edit  # noqa: E402
from lasagna.priors.base import Condition  # noqa: E402
from lasagna.priors.ddim import ddim_sample  # noqa: E402


def default_layers(images: torch.Tensor, labels, dirs, **options) -> tuple[torch.Tensor, float]:
    t0 = time.perf_counter()
    out = [edit(images[i], "relight", labels[i], catalogue_dirs=dirs, **options).layer for i in range(images.shape[0])]
    return torch.stack(out), time.perf_counter() - t0


def prior_ratio(rel, labels, prior, omega: float = 1.0) -> torch.Tensor:
    side = prior.sample_shape[-1]
    small = downsample(rel.base.float(), (side, side))
    cond = Condition(list(labels), image=small)
    x = ddim_sample(prior, cond, steps=50, omega=omega, rng=torch.Generator().manual_seed(0)).image
    x = x.clamp(0, 1).double()
    ratio = (x / small.double().clamp_min(1e-3)).mean(dim=1, keepdim=True).clamp(0, RANGE_HI)
    return upsample(ratio.float(), tuple(rel.base.shape[-2:])).double()


SHEET = {
    "default edit (`lasagna edit --layer relight`)": "default",
    "edit --generator amortised": "amortised",
    "supervised ceiling": "supervised",
}
"""Methods whose composites (and ratio layers) go into the sheet, in this order."""


def table(args, split: str, size: int, prior, sheets: dict | None = None) -> list[dict]:
    """The rows of one split and size; with ``sheets``, its first ``args.sheet`` scenes as sheet columns:
    input | truth | each of ``SHEET``'s composites, then each of their ratio layers (ratio / 2, grey)."""
    rel, labels = scenes(split, args.count, args.seed, size)
    base, target = rel.base.double(), rel.target.clamp(0, 1).double()
    c = ((base * target).sum(dim=(1, 2, 3)) / (base * base).sum(dim=(1, 2, 3)).clamp_min(1e-12)).clamp(0, RANGE_HI)
    rows: list[dict] = []
    kept: dict[str, torch.Tensor] = {}  # SHEET's ratio layers, by their sheet name

    def add(on, method: str, ratio: torch.Tensor, seconds: float | None = None) -> None:
        rows.append(row(on, method, ratio, seconds))
        if method in SHEET:
            kept[SHEET[method]] = ratio

    add(rel, "unchanged input", torch.ones_like(rel.layer))
    add(rel, "best constant multiplier", c.view(-1, 1, 1, 1))
    if prior is not None:
        t0 = time.perf_counter()
        ratio = prior_ratio(rel, labels, prior)
        add(rel, "prior sampled directly (DDIM-50, ω = 1)", ratio, time.perf_counter() - t0)
    y, seconds = default_layers(rel.base.float(), labels, args.catalogue)
    add(rel, "default edit (`lasagna edit --layer relight`)", y.double(), seconds)
    if args.between:
        mid, mid_labels = scenes(split, args.count, args.seed, size, between=True)
        y, seconds = default_layers(mid.base.float(), mid_labels, args.catalogue)
        add(mid, "default edit, directions between the named (az + 22.5°)", y.double(), seconds)
        add(mid, "unchanged input, directions between the named", torch.ones_like(mid.layer))
    for loss in args.losses:
        for omega in args.omegas:
            y, seconds = default_layers(rel.base.float(), labels, args.catalogue, loss=loss, guidance=omega)
            add(rel, f"per-image {loss.upper()} ω = {omega:g}", y.double(), seconds)
    for n in args.methods:  # the amortised generator, then N refinement steps: candidates for the default
        y, seconds = default_layers(rel.base.float(), labels, args.catalogue, generator="amortised", optimize=n)
        add(rel, "edit --generator amortised" + (f" --optimize {n}" if n else ""), y.double(), seconds)
    for kind in args.layer_kinds:  # issue #24: a surface's ratio S(l)/S(l_src), or today's per-pixel layer
        y, seconds = default_layers(rel.base.float(), labels, args.catalogue, layer_kind=kind)
        add(rel, f"edit --layer-kind {kind}", y.double(), seconds)
    add(rel, "oracle: true outlines inflated, true source light", inflated_ratio(rel))
    if args.supervised is not None:
        add(rel, "supervised ceiling", supervised_ratio(rel, labels, args.supervised))
    if sheets is not None:
        n = min(args.sheet, rel.base.shape[0])
        ratios = [kept[k][:n] for k in SHEET.values() if k in kept]
        cols = [list(rel.base[:n].float()), list(rel.target[:n].clamp(0, 1).float())]
        cols += [list((rel.base[:n] * r).clamp(0, 1).float()) for r in ratios]
        cols += [list(r.float()) for r in ratios]  # shown halved by save_sheet
        sheets[(split, size)] = cols
    for r in rows:
        r.update(split=split, size=size)
        print(json.dumps(r), flush=True)
    return rows


def inflated_ratio(rel) -> torch.Tensor:
    """The outline-inflation oracle's ratio S(target)/S(source) with the true source light (the true outlines
    inflated into domes, the wall flat: `lasagna.compose.surface.inflated_normals`)."""
    n = inflated_normals(rel.scene.object_index).double()
    return lambert(n, rel.scene.light.double()) / lambert(n, rel.source.light.double())


def supervised_ratio(rel, labels, folder: Path) -> torch.Tensor:
    """A generator trained on the world's true ratio (``train-layer --preset relight --supervised``), at the
    preset's working size and enlarged, as the edit does."""
    from lasagna.compose.resample import working_size
    from lasagna.generators.unet import LayerGenerator

    gen = LayerGenerator.from_pretrained(folder)
    full = tuple(rel.base.shape[-2:])
    side = cat.resolve("relight").preset.working_size
    with torch.no_grad():
        small = downsample(rel.base.float(), working_size(*full, side))
        return upsample(gen(small, list(labels))[:, :1], full).double()


def leak(args, split: str, size: int) -> dict:
    rel, labels = scenes(split, args.count, args.seed, size, walls=True)
    y, _ = default_layers(rel.base.float(), labels, args.catalogue)
    y = y.double() / RANGE_HI
    flat = y.mean(dim=(1, 2, 3), keepdim=True).expand_as(y)
    out = {"split": split, "size": size, "leak_db": round(psnr(y, flat), 2), "sigma": round(float((y - flat).std()), 4)}
    print(json.dumps({"leak": out}), flush=True)
    return out


def headline(rows: dict, leaks: list[dict]) -> dict:
    def gain(key: str, field: str) -> float | None:
        if key not in rows:
            return None
        by = {r["method"]: r for r in rows[key]}
        d = next(r for m, r in by.items() if m.startswith("default edit"))
        return round(d[field] - by["unchanged input"][field], 2)

    return {
        "far_gain_db": gain("far@64", "composite_psnr"),
        "far_gain_obj_db": gain("far@64", "object_psnr"),
        "far256_gain_db": gain("far@256", "composite_psnr"),
        "far256_gain_obj_db": gain("far@256", "object_psnr"),
        "heldout_gain_db": gain("heldout@64", "composite_psnr"),
        "heldout_gain_obj_db": gain("heldout@64", "object_psnr"),
        "leak_db": min((x["leak_db"] for x in leaks), default=None),
        "far_between_minus_named_db": between_gap(rows.get("far@64")),
    }


def between_gap(rows) -> float | None:
    """The default edit's gain over the unchanged input for in-between directions minus that for named ones."""
    if not rows:
        return None
    by = {r["method"]: r for r in rows}
    mid = by.get("default edit, directions between the named (az + 22.5°)")
    if mid is None:
        return None
    named = next(r for m, r in by.items() if m.startswith("default edit (`"))
    gain_mid = mid["composite_psnr"] - by["unchanged input, directions between the named"]["composite_psnr"]
    gain_named = named["composite_psnr"] - by["unchanged input"]["composite_psnr"]
    return round(gain_mid - gain_named, 2)


def markdown(result: dict) -> str:
    lines = [
        "| split | size | method | composite PSNR (dB) | object pixels (dB) | ratio PSNR (dB) | s per image |",
        "|---|---|---|---|---|---|---|",
    ]
    for rows in result["relight"].values():
        for r in rows:
            lines.append(
                f"| {r['split']} | {r['size']}² | {r['method']} | {r['composite_psnr']} | {r['object_psnr']} | "
                f"{r['ratio_psnr']} | {r.get('seconds_per_image', '')} |"
            )
    lines += ["", "| split | size | texture leak (dB) | σ of the ratio / 4 |", "|---|---|---|---|"]
    lines += [f"| {x['split']} | {x['size']}² | {x['leak_db']} | {x['sigma']} |" for x in result["leak"]]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--splits", nargs="+", default=["heldout", "far"])
    ap.add_argument("--sizes", nargs="+", type=int, default=[64, 256])
    ap.add_argument("--count", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--omegas", nargs="*", type=float, default=[3.0])
    ap.add_argument(
        "--losses",
        nargs="*",
        default=["sds"],
        help="per-image losses run at each --omegas (lmc-sds needs a corrective in the preset: --catalogue)",
    )
    ap.add_argument("--catalogue", type=Path, nargs="*", default=None, help="catalogue folders searched first")
    ap.add_argument(
        "--layer-kinds",
        nargs="*",
        default=[],
        choices=("free", "surface"),
        help="also `lasagna edit --layer-kind K` (surface: the estimated surface's ratio)",
    )
    ap.add_argument(
        "--methods",
        type=int,
        nargs="*",
        default=[],
        help="N: the amortised generator then N refinement steps (0: one pass); needs a generator",
    )
    ap.add_argument("--supervised", type=Path, default=None, help="a supervised generator folder: the ceiling row")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--no-between", dest="between", action="store_false", help="skip the in-between directions")
    ap.add_argument("--quick", action="store_true", help="4 scenes, 64² only, no extra ω")
    ap.add_argument("--markdown", action="store_true")
    ap.add_argument("--json-out", type=Path, default=ROOT / "docs" / "relight.json")
    ap.add_argument("--sheet", type=int, default=8, help="scenes per sheet (0: none)")
    ap.add_argument("--img", type=Path, default=ROOT / "docs" / "img", help="folder of the sheets")
    args = ap.parse_args(argv)
    if args.quick:
        args.count, args.sizes, args.omegas, args.json_out = 4, [64], [], Path("/tmp/relight_quick.json")
        args.img = Path("/tmp/relight_quick")
        args.methods = args.methods[:1]
    torch.set_num_threads(args.threads)
    t0 = time.perf_counter()
    status = cat.preset_status("relight", args.catalogue)
    if not status["usable"]:
        print(f"relight preset not usable: {status['why']}", file=sys.stderr)
        return 2
    parts = cat.resolve("relight", catalogue_dirs=args.catalogue)
    prior = cat.load_prior(parts.prior)
    result: dict = {"machine": machine_info(), "count": args.count, "seed": args.seed, "relight": {}, "leak": []}
    result["preset"] = parts.preset.model_dump(mode="json")
    sheets: dict = {}
    for split in args.splits:
        for size in args.sizes:
            keep = sheets if args.sheet > 0 and size == min(args.sizes) else None
            result["relight"][f"{split}@{size}"] = table(args, split, size, prior, keep)
            result["leak"].append(leak(args, split, size))
    for (split, _), cols in sheets.items():  # input | truth | composites | ratio layers, one row per scene
        save_sheet(cols, args.img / f"relight_{split}.png")
    result["headline"] = headline(result["relight"], result["leak"])
    result["wall_seconds"] = round(time.perf_counter() - t0, 1)
    args.json_out.parent.mkdir(parents=True, exist_ok=True)
    args.json_out.write_text(json.dumps(result, indent=1) + "\n")
    if args.markdown:
        print(markdown(result))
    print_json_line({"benchmark": "relight", **result["headline"], "wall_seconds": result["wall_seconds"]})
    return 0


if __name__ == "__main__":
    sys.exit(main())
