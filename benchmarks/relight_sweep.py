"""The sweeps that chose the relight preset's per-image settings. Plain script; one JSON row per setting, then one
JSON line. Defaults are never chosen on far.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/relight_sweep.py            # issue #11's, heldout 64² (~20 min)
    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/relight_sweep.py --count 2 --only default "particles 4"
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/relight_sweep.py --split select --size 256   # issue #24's re-choice

``--split heldout`` (the default) runs issue #11's settings, which chose particles 4 and t_min 0.1 when heldout
was where choices were made. ``--split select`` runs issue #24's re-choice of every field on the selection split:
each row changes one field of the preset as shipped (``SELECT_SETTINGS``; a field edit cannot override — the working
size — is a variant of the preset in a temporary catalogue put first), so its rows are relative to the current
preset.

Each setting runs ``lasagna.editing.edit(image, "relight", label, **overrides)`` on the scenes of
``benchmarks/relight.py`` (each lit by its own source light A, relit to a named light B) and reports the
composite PSNR against the truth over all pixels and over object pixels (``_common.row``). "N seeds" rows
average the layers of N runs with seeds 0…N−1 after the runs; "particles K" rows are one run with K
particles (``distill.particles``: K layers per image in one batch, averaged). The overrides are given
explicitly, so the rows do not depend on the preset's current defaults (the preset now says particles 4,
t_min 0.1: the row "particles 4 + t_min 0.1").
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import machine_info, print_json_line, row, scenes  # noqa: E402

from lasagna.editing import edit  # noqa: E402

# The previous default, explicitly: one run, t ~ U(0.02, 0.98), SDS at ω = 1.
BASE = {"particles": 1, "t_min": 0.02, "t_max": 0.98, "guidance": 1.0, "loss": "sds"}


def seeds(n: int, **o) -> list[dict]:
    return [{**BASE, **o, "seed": s} for s in range(n)]


SETTINGS: dict[str, list[dict]] = {
    "default (1 run, t_min 0.02)": seeds(1),
    "4 seeds averaged": seeds(4),
    "8 seeds averaged": seeds(8),
    "300 steps": seeds(1, optimize=300),
    "lr 0.015": seeds(1, lr=0.015),
    "lr 0.06": seeds(1, lr=0.06),
    "t_max 0.6": seeds(1, t_max=0.6),
    "t_min 0.1": seeds(1, t_min=0.1),
    "ω 1.5": seeds(1, guidance=1.5),
    "ω 0.5": seeds(1, guidance=0.5),
    "ω 2, 4 seeds": seeds(4, guidance=2.0),
    "ω 3, 4 seeds": seeds(4, guidance=3.0),
    "LMC-SDS ω 3, 4 seeds": seeds(4, guidance=3.0, loss="lmc-sds"),
    "particles 4": seeds(1, particles=4),
    "particles 8": seeds(1, particles=8),
    "particles 4 + t_min 0.1": seeds(1, particles=4, t_min=0.1),
    "particles 8 + t_min 0.1": seeds(1, particles=8, t_min=0.1),
}


# Issue #24: every field of the relight preset re-chosen on select, one field at a time from the preset as shipped.
# A "preset" entry is written into a temporary catalogue's copy of the preset; the rest are edit() overrides.
SELECT_SETTINGS: dict[str, list[dict]] = {
    "default": [{}],
    "working size 32": [{"preset": {"working_size": 32}}],
    "working size 48": [{"preset": {"working_size": 48}}],
    "working size 96": [{"preset": {"working_size": 96}}],
    "60 steps": [{"optimize": 60}],
    "300 steps": [{"optimize": 300}],
    "ω 0.5": [{"guidance": 0.5}],
    "ω 2": [{"guidance": 2.0}],
    "particles 1": [{"particles": 1}],
    "particles 8": [{"particles": 8}],
    "lr 0.015": [{"lr": 0.015}],
    "lr 0.06": [{"lr": 0.06}],
    "t_min 0.02": [{"t_min": 0.02}],
    # The second pass (2026-11-26): the fields that qualified in the first (ω 2, lr 0.06, particles 8) combined, and
    # one step further along the best one.
    "ω 2 + lr 0.06": [{"guidance": 2.0, "lr": 0.06}],
    "ω 2 + particles 8": [{"guidance": 2.0, "particles": 8}],
    "ω 2 + lr 0.06 + particles 8": [{"guidance": 2.0, "lr": 0.06, "particles": 8}],
    "ω 3": [{"guidance": 3.0}],
    "ω 3 + lr 0.06": [{"guidance": 3.0, "lr": 0.06}],
    # The round of 2026-11-26 (4): the step between ω 1 and the vetoed ω 2, and the surface start estimated at 64
    # (the close-up estimator, trained at 32, read at 64: `surface.working_size`, which the start now honours).
    "ω 1.5": [{"guidance": 1.5}],
    "surface working size 64": [{"preset": {"surface": {"working_size": 64}}}],
    "surface working size 64 + ω 1.5": [{"preset": {"surface": {"working_size": 64}}, "guidance": 1.5}],
    # The dome prior's fields re-checked by the photograph selection set's rule (they shape the surface start).
    "domes 0.3 / 0.5": [{"preset": {"surface": {"dome_weight": 0.3, "dome_height": 0.5}}}],
    "domes 0.5 / 0.5": [{"preset": {"surface": {"dome_weight": 0.5, "dome_height": 0.5}}}],
    "domes 0.3 / 1": [{"preset": {"surface": {"dome_weight": 0.3, "dome_height": 1.0}}}],
    "domes 0.5 / 1": [{"preset": {"surface": {"dome_weight": 0.5, "dome_height": 1.0}}}],
    # The round of 2026-11-26 (5): the learned manifold corrective (the preset's `relit-32-spectral`), which removes
    # the part of the score the prior's denoiser cannot tell from its own error, at the ω that painted under SDS.
    "LMC-SDS ω 1": [{"loss": "lmc-sds"}],
    "LMC-SDS ω 2": [{"loss": "lmc-sds", "guidance": 2.0}],
    "LMC-SDS ω 3": [{"loss": "lmc-sds", "guidance": 3.0}],
    "LMC-SDS ω 4": [{"loss": "lmc-sds", "guidance": 4.0}],
    "LMC-SDS ω 6": [{"loss": "lmc-sds", "guidance": 6.0}],
    # The round of 2026-11-26 (6): the guided enlargement judged where it acts (above the working size), with the
    # deepened start.
    "guided enlargement": [{"preset": {"enlarge": "guided"}}],
    # The round of 2026-11-26 (7): the surface route (`--layer-kind surface`), and its surface refined by multi-light
    # score distillation (`surface.refine_steps`: every step renders the one surface under `lights_per_step` lights
    # and the prior scores them all; `lasagna.distill.surface`).
    "surface route": [{"layer_kind": "surface"}],
    **{
        f"surface refined {n}, anchor {a:g}, lr {lr:g}": [
            {"layer_kind": "surface", "preset": {"surface": {"refine_steps": n, "anchor": a, "lr": lr}}}
        ]
        for n in (60, 150)
        for a in (1.0, 0.1)
        for lr in (0.01, 0.03)
    },
    # The round of 2026-11-27 (14): the crop phase (`distill.whole_fraction`, the LMC-SDS paper's 0.4, never re-chosen
    # on select): a prior trained on whole 32² scenes may read a native-resolution crop as a whole scene.
    "whole fraction 0.7": [{"preset": {"distill": {"whole_fraction": 0.7}}}],
    "whole image only": [{"preset": {"distill": {"whole_fraction": 1.0}}}],
    "whole fraction 0.2": [{"preset": {"distill": {"whole_fraction": 0.2}}}],
    "crops only": [{"preset": {"distill": {"whole_fraction": 0.0}}}],
    # One step further along the axis that won (the anchor), at 60 steps.
    **{
        f"surface refined 60, anchor {a:g}, lr {lr:g}": [
            {"layer_kind": "surface", "preset": {"surface": {"refine_steps": 60, "anchor": a, "lr": lr}}}
        ]
        for a in (0.01, 0.0)
        for lr in (0.01, 0.03)
    },
    # The fitted source light refined with the surface (`surface.refine_light`).
    **{
        f"surface refined 60, anchor {a:g}, lr 0.03, light refined": [
            {
                "layer_kind": "surface",
                "preset": {"surface": {"refine_steps": 60, "anchor": a, "lr": 0.03, "refine_light": True}},
            }
        ]
        for a in (0.01, 0.0)
    },
    # The refinement's correction without its low frequencies (`surface.refine_lock`, σ a fraction of the side).
    **{
        f"surface refined 60, anchor 0.01, lr 0.03, lock {sigma:g}": [
            {
                "layer_kind": "surface",
                "preset": {"surface": {"refine_steps": 60, "anchor": 0.01, "lr": 0.03, "refine_lock": sigma}},
            }
        ]
        for sigma in (0.05, 0.1, 0.2, 0.4)
    },
    # The adopted refinement made at working size 64 (`surface.refine_size`): whole image, then native crops.
    **{
        f"surface refined {n} at 64, anchor 0.01, lr 0.03, lock 0.2": [
            {
                "layer_kind": "surface",
                "preset": {"surface": {"refine_steps": n, "refine_size": 64}},
            }
        ]
        for n in (60, 150)
    },
    # Round 8: the surface layer's fitted source light calibrated (round 7's line, fitted on train by
    # benchmarks/light_calibration.py), alone and refined on the objects only (C′, adopted: the shipped preset since);
    # then its correction kept as a band without the working size's finest relief (D, on top of C′).
    "surface refined, calibrated": [
        {"layer_kind": "surface", "preset": {"surface": {"light_calibration": [26.43, 0.590]}}},
    ],
    "surface refined, calibrated, objects": [
        {
            "layer_kind": "surface",
            "preset": {"surface": {"light_calibration": [26.43, 0.590], "refine_objects": True}},
        },
    ],
    # Round 8's E: the default's four particles as a mirror ensemble (`distill.particle_mirrors`).
    "mirror particles": [{"preset": {"distill": {"particle_mirrors": True}}}],
    # Round 8's H: the source elevation from the shading head's level on the walls, as it is (H1) and mapped by the
    # line fitted on train (H2); both replace C′'s calibration of the fit.
    "surface, walls' elevation": [
        {"layer_kind": "surface", "preset": {"surface": {"source_elevation": "walls", "light_calibration": None}}}
    ],
    "surface, walls' elevation calibrated": [
        {
            "layer_kind": "surface",
            "preset": {"surface": {"source_elevation": "walls", "light_calibration": [-7.17, 1.097]}},
        }
    ],
    "surface refined, guided": [{"layer_kind": "surface", "preset": {"surface": {"enlarge": "guided"}}}],
    **{
        f"surface refined, smooth {s:g}": [{"layer_kind": "surface", "preset": {"surface": {"refine_smooth": s}}}]
        for s in (0.5, 1.0)
    },
    # Round 9's K: the walls' large-scale tilt removed from the estimate (`surface.flat_walls`, σ a fraction of the
    # working size's long side), for the default's surface start and for the surface layer.
    **{f"flat walls {s:g}": [{"preset": {"surface": {"flat_walls": s}}}] for s in (0.125, 0.25)},
    **{
        f"surface, flat walls {s:g}": [{"layer_kind": "surface", "preset": {"surface": {"flat_walls": s}}}]
        for s in (0.125, 0.25)
    },
}


def preset_variant(fields: dict, folder: Path) -> list[Path]:
    """A catalogue at ``folder`` holding the shipped relight preset with ``fields`` changed (its other names still
    resolve through the usual catalogues): the ``catalogue_dirs`` of an edit that uses it."""
    from lasagna.catalogue import catalogues, load_preset
    from lasagna.document.preset import Preset

    shipped = load_preset("relight").model_dump(mode="json")
    # A nested field (``surface``) is merged into the shipped one, so a variant names only what it changes.
    merged = {
        k: {**shipped[k], **v} if isinstance(v, dict) and isinstance(shipped.get(k), dict) else v
        for k, v in fields.items()
    }
    variant = Preset.model_validate({**shipped, **merged})
    (folder / "relight").mkdir(parents=True, exist_ok=True)
    (folder / "relight" / "preset.json").write_text(variant.to_json(), encoding="utf-8")
    return catalogues([folder])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--count", type=int, default=16)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--seed", type=int, default=0, help="world seed")
    ap.add_argument("--only", nargs="*", default=None, help="settings to run (names as in the rows)")
    ap.add_argument("--split", choices=("heldout", "select"), default="heldout")
    args = ap.parse_args(argv)
    rel, labels = scenes(args.split, args.count, args.seed, args.size)
    images = rel.base.float()
    cache: dict[str, torch.Tensor] = {}
    rows = []
    settings = SETTINGS if args.split == "heldout" else SELECT_SETTINGS
    for name, runs in settings.items():
        if args.only is not None and name not in args.only:
            continue
        t0 = time.perf_counter()
        layers = []
        for o in runs:
            key = json.dumps(o, sort_keys=True)
            if key not in cache:
                with tempfile.TemporaryDirectory() as tmp:
                    o = dict(o)
                    dirs = preset_variant(o.pop("preset"), Path(tmp)) if "preset" in o else None
                    cache[key] = torch.stack(
                        [
                            edit(images[i], "relight", labels[i], catalogue_dirs=dirs, **o).layer
                            for i in range(images.shape[0])
                        ]
                    ).double()
            layers.append(cache[key])
        r = row(rel, name, torch.stack(layers).mean(0), time.perf_counter() - t0)
        r.update(split=args.split, size=args.size)
        rows.append(r)
        print(json.dumps(r), flush=True)
    print_json_line(
        {
            "benchmark": "relight_sweep",
            "split": args.split,
            "rows": rows,
            "count": args.count,
            "machine": machine_info(),
        }
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
