"""Relight candidates against the shipped catalogue, in the same run (issue #24, rounds 16–17). Plain script; one
JSON row per (candidate, split, size, kind), then one JSON line.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/relight_candidates.py --estimator runs/g17/lit-relief-gpu/surface
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/relight_candidates.py --prior runs/g17/relit-big/prior --kinds free
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/relight_candidates.py --count 2 --sizes 64 --kinds surface given
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/relight_candidates.py --estimator @wall_relief=0.5 --kinds surface

A candidate is a lit surface estimator (``--estimator``: the ``relight`` preset with ``surface.estimator`` this one)
or a relit prior (``--prior``: put in place of the preset's ``prior``), each in a temporary catalogue put first
(``lasagna.edit(..., catalogue_dirs=...)``); an estimator may carry preset settings (``FOLDER@wall_relief=0.5``;
``@wall_relief=0.5`` alone: the shipped estimator so set; ``@told={...}`` replaces the whole told route, as JSON),
so every row runs the whole edit path a user runs. The shipped catalogue is measured in the same run as the
baseline. Each scene of ``--splits`` (world seed ``--seed``) is lit by its relight task's source light and relit
toward its named light (``benchmarks/relight.py``'s task); ``--kinds``:

* ``free`` — ``lasagna edit --layer relight`` (the default: the free layer started from the estimator's surface);
* ``surface`` — ``--layer-kind surface`` (the estimator's surface rendered S(target)/S(source), its light fitted);
* ``given`` — ``--layer-kind surface --from`` the true source light (the preset's ``surface.told`` estimator when it
  names one; a candidate folder is read here too).

Per row: dB over the unchanged input (all pixels / objects), seconds per image, and the composite's summed squared
error split by where it falls (objects, flat walls, relief walls: ``relief_walls.ratio_errors``) in units of a 64²
image's pixels; with ``--leak``, the layer's texture leak on the same scenes' bare painted walls (objects removed,
relief flat: the true ratio is one constant; the layer's PSNR against its own mean, ∞ for a flat layer). The headroom
row ("true at the working size": the true normals reduced to the preset's working size
and enlarged, rendered under the true lights) says how far any surface layer at that size can go. The last line
holds every row and, per candidate and kind, the mean over splits and sizes of the all-pixel and object gains
against the shipped catalogue's (``delta``). ``--sheet`` draws the first split and size's first four scenes: input |
the truth relit | the true ratio | each candidate and kind's ratio, to look at what the numbers say.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import machine_info, psnr, save_sheet  # noqa: E402
from relief_walls import ratio_errors  # noqa: E402
from surface import lights_of, scenes  # noqa: E402

from lasagna.catalogue import catalogues, load_preset  # noqa: E402
from lasagna.compose.resample import downsample  # noqa: E402
from lasagna.compose.surface import enlarge_surface, lambert, light_vector, surface_normals  # noqa: E402
from lasagna.document.condition import parse_direction  # noqa: E402
from lasagna.world.tasks import relight_sources, relighting  # noqa: E402

PRESET = "relight"
KINDS = ("free", "surface", "given")
SHIPPED = "shipped"


def candidate_catalogue(
    root: Path, estimator: str | None = None, prior: str | None = None, surface: dict | None = None
) -> Path:
    """A catalogue folder under ``root`` that, put first, makes ``PRESET`` use ``estimator`` (a lit estimator folder,
    read whether or not the light is told: the preset's ``surface.told`` dropped; "" keeps the preset's own
    estimators, catalogue names found in the catalogues after this one) with its ``surface`` settings updated by
    ``surface``, or ``prior`` (a prior folder, under the name the preset asks for)."""
    preset = json.loads((ROOT / "layers" / PRESET / "preset.json").read_text())
    if estimator is not None:
        if estimator:
            name = "candidate-estimator"
            shutil.copytree(estimator, root / name)
            preset["surface"]["estimator"] = name
            preset["surface"]["told"] = None  # a candidate estimator is read told the light as well as not
        preset["surface"].update(surface or {})
        (root / PRESET).mkdir(parents=True)
        (root / PRESET / "preset.json").write_text(json.dumps(preset, indent=2))
    if prior is not None:
        shutil.copytree(prior, root / preset["prior"])
    return root


def top_level_split(text: str, sep: str = ",") -> list[str]:
    """``text`` split at each ``sep`` outside brackets and braces, so a JSON value may hold commas:
    ``a=1,b={"x":1,"y":2}`` → ``['a=1', 'b={"x":1,"y":2}']``."""
    parts, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        depth += (ch in "[{") - (ch in "]}")
        if ch == sep and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    parts.append(text[start:])
    return parts


def estimator_spec(spec: str) -> tuple[str, dict]:
    """``FOLDER[@key=value,...]`` → (folder, the preset's ``surface`` settings it changes, values read as JSON); an
    empty folder keeps the preset's estimator: ``@wall_relief=0.5`` is the shipped estimator with that setting."""
    folder, _, rest = spec.partition("@")
    settings = {}
    for item in filter(None, top_level_split(rest)):
        key, eq, value = item.partition("=")
        if not eq:
            raise SystemExit(f"--estimator {spec}: {item!r} is not key=value")
        settings[key] = json.loads(value)
    return folder, settings


def kind_options(kind: str) -> dict:
    return {"free": {"layer_kind": "free"}, "surface": {"layer_kind": "surface"}, "given": {"layer_kind": "surface"}}[
        kind
    ]


TOLD_OFF_SEED = 11
"""Seed of ``--told-off``'s noise (docs/BENCHMARKS.md round 23, probes N and N2, and rule WI)."""


def off_by(sources: list[str], sigma: float) -> list[str]:
    """``sources`` (``az=…,el=…``) each off by Gaussian noise of ``sigma`` degrees on its azimuth and its elevation
    (the elevation kept in [1, 89]), drawn from a generator seeded ``TOLD_OFF_SEED``; ``sigma`` 0 returns them."""
    if sigma <= 0:
        return list(sources)
    g = torch.Generator().manual_seed(TOLD_OFF_SEED)
    out = []
    for text in sources:
        az, el = parse_direction(text)
        daz, de = (float(v) * sigma for v in torch.randn(2, generator=g, dtype=torch.float64))
        out.append(f"az={(az + daz) % 360.0:.2f},el={min(max(el + de, 1.0), 89.0):.2f}")
    return out


def edit_ratios(
    base, labels, sources, kind: str, dirs: list[str] | None, within: float | None = None
) -> tuple[torch.Tensor, float]:
    """The relight layer of every image through ``lasagna.edit`` (told ``sources`` for ``given``, with the uncertainty
    ``within`` where given), and seconds per image."""
    from lasagna import edit

    t0 = time.perf_counter()
    out = []
    for i in range(base.shape[0]):
        given = {"source_light": sources[i]} if kind == "given" else {}
        if given and within is not None:
            given["source_within"] = within
        out.append(edit(base[i], PRESET, labels[i], catalogue_dirs=dirs, **kind_options(kind), **given).layer[:1])
    return torch.stack(out), (time.perf_counter() - t0) / base.shape[0]


def ratio_tile(ratio: torch.Tensor) -> torch.Tensor:
    """A relight ratio (1, H, W) as a grey tile at half its value (1 → mid-grey), clamped."""
    return (ratio[:1].float() / 2).clamp(0, 1).expand(3, -1, -1)


def measure(name, scene, rel, ratio, seconds, size) -> dict:
    base, target, mask = rel.base.clamp(0, 1), rel.target.clamp(0, 1), scene.mask
    comp = (rel.base * ratio).clamp(0, 1)
    unit = (size / 64) ** 2  # errors in units of a 64² image's pixels, so sizes compare
    errors = {k: round(v / unit, 1) for k, v in ratio_errors(scene, rel, ratio).items()}
    return {
        "method": name,
        "db_all": round(psnr(comp, target) - psnr(base, target), 3),
        "db_objects": round(psnr(comp, target, mask) - psnr(base, target, mask), 3),
        "seconds": None if seconds is None else round(seconds, 3),
        **errors,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--estimator",
        nargs="*",
        default=[],
        help="lit surface estimator folders to measure, each FOLDER[@key=value,...] with the preset's surface settings "
        "it changes (an empty FOLDER: the shipped estimator)",
    )
    p.add_argument("--prior", nargs="*", default=[], help="relit prior folders to measure (in the preset's place)")
    p.add_argument("--splits", nargs="+", default=["select"])
    p.add_argument("--sizes", nargs="+", type=int, default=[64, 256])
    p.add_argument("--kinds", nargs="+", choices=KINDS, default=["free", "surface"])
    p.add_argument("--count", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--told-off",
        type=float,
        default=0.0,
        metavar="DEG",
        help="given: each told light off by Gaussian noise of DEG degrees on its azimuth and its elevation (seed "
        "TOLD_OFF_SEED), as a person's reading is (0: the true light)",
    )
    p.add_argument(
        "--within",
        type=float,
        default=None,
        metavar="DEG",
        help="given: told lights carry this uncertainty (`lasagna edit --within`: the elevation fused with the fit's)",
    )
    p.add_argument(
        "--shadows",
        action="store_true",
        help="the scenes with the world's cast shadows (under the source light and the target light alike: the true "
        "ratio then holds the shadows a relight removes and casts, which no surface ratio renders)",
    )
    p.add_argument(
        "--leak", action="store_true", help="also each layer's texture leak on the split's bare painted walls (dB)"
    )
    p.add_argument(
        "--sheet",
        type=Path,
        default=None,
        help="the first split and size's first four scenes: input | truth relit | the true ratio | each candidate and "
        "kind's ratio (ratios at half their value: 1 is mid-grey), one row per scene",
    )
    args = p.parse_args(argv)
    sd = load_preset(PRESET).surface
    rows: list[dict] = []
    sheet: list[list[torch.Tensor]] = []  # columns of --sheet's grid
    with tempfile.TemporaryDirectory() as tmp:
        # catalogue_dirs replaces the search path, so a candidate's folder goes before the default catalogues.
        rest = [str(c) for c in catalogues()]
        candidates: dict[str, list[str] | None] = {SHIPPED: None}
        for i, spec in enumerate(args.estimator):
            folder, settings = estimator_spec(spec)
            cat = candidate_catalogue(Path(tmp) / f"e{i}", estimator=folder, surface=settings)
            candidates[f"estimator:{spec}"] = [str(cat), *rest]
        for i, folder in enumerate(args.prior):
            candidates[f"prior:{folder}"] = [str(candidate_catalogue(Path(tmp) / f"p{i}", prior=folder)), *rest]
        for split in args.splits:
            for size in args.sizes:
                scene, labels = scenes(split, args.count, args.seed, size, shadows=args.shadows)
                sources = relight_sources(scene.params)
                rel = relighting(scene, sources)
                told = off_by(sources, args.told_off)
                src = torch.cat([light_vector(*parse_direction(s))[None] for s in sources]).float()
                full, ws = (size, size), (sd.working_size, sd.working_size)
                truth = surface_normals(enlarge_surface(downsample(scene.normals.float(), ws), full))
                head = lambert(truth, lights_of(labels).float()) / lambert(truth, src)
                found = [measure("true at the working size", scene, rel, head, None, size)]
                if args.leak:
                    walls, wall_labels = scenes(split, args.count, args.seed, size, walls=True, shadows=args.shadows)
                    wall_sources = relight_sources(walls.params)
                    wall_base = relighting(walls, wall_sources).base.float()
                first = args.sheet is not None and not sheet
                if first:
                    sheet += [list(rel.base[:4].clamp(0, 1)), list(rel.target[:4].clamp(0, 1))]
                    sheet.append([ratio_tile(r) for r in rel.layer[:4]])  # the true ratio S_target / S_source
                for name, dirs in candidates.items():
                    for kind in args.kinds:
                        ratio, sec = edit_ratios(rel.base.float(), labels, told, kind, dirs, args.within)
                        if first:
                            sheet.append([ratio_tile(r) for r in ratio[:4]])
                        row = {"candidate": name, "kind": kind, **measure(kind, scene, rel, ratio, sec, size)}
                        if args.leak:  # the layer on bare painted walls, whose true ratio is one constant
                            y = edit_ratios(wall_base, wall_labels, wall_sources, kind, dirs, args.within)[0].double()
                            row["leak_db"] = round(psnr(y, y.mean(dim=(1, 2, 3), keepdim=True).expand_as(y)), 2)
                        found.append(row)
                for r in found:
                    r.update(split=split, size=size)
                    print(json.dumps(r), flush=True)
                rows += found
    if sheet:
        save_sheet(sheet, args.sheet)
    delta: dict[str, dict] = {}
    for name in candidates:
        if name == SHIPPED:
            continue
        for kind in args.kinds:
            mine = [r for r in rows if r.get("candidate") == name and r["kind"] == kind]
            ref = [r for r in rows if r.get("candidate") == SHIPPED and r["kind"] == kind]
            delta.setdefault(name, {})[kind] = {
                key: round(sum(a[key] - b[key] for a, b in zip(mine, ref, strict=True)) / len(mine), 3)
                for key in ("db_all", "db_objects")
            }
    print(json.dumps({"machine": machine_info(), "command": " ".join(sys.argv), "rows": rows, "delta": delta}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
