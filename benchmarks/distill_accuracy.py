"""Learned layers against the world's ground truth: every score loss × ω, baselines, run time against error.

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/distill_accuracy.py --markdown     (~15 min on 2 vCPUs)
    .venv/bin/python benchmarks/distill_accuracy.py --quick                           (~1 min smoke run)

On ``--count`` scenes of the world's ``heldout`` split (shape and texture families the priors never
saw; labels cycling through the vocabulary), base = albedo, the bundled shading preset's prior and
corrective, a free per-pixel shading layer distilled for ``--steps`` steps, all images batched:

* per method (SDS, LMC-SDS, DDS, NFSD, MS-SDS) × ω: shading PSNR against the true shading over all
  pixels and over object pixels, the scale-invariant error (per image, the shading rescaled by its
  least-squares factor first), composite PSNR against the true relit image, chromaticity drift and
  albedo error against the input, wall time — and the shading PSNR after every step with its time
  (the run-time-against-error curves; one run gives the whole curve);
* baselines in the same run: the best constant shading (per image, least squares), the prior sampled
  directly (DDIM-50 with the same condition: the Lasagna paper's "ControlNet alone"), and LMC-SDS
  with the network corrective b̂ (``relight-32-bhat``) beside the preset's corrective;
* the amortised generator (one forward pass) and its supervised ceiling (the same generator trained
  on the true shading), where their run folders or the catalogue hold them;
* the radially averaged power spectrum of the composite (the LMC-SDS paper's Fig. 6), per method;
* colourisation: the same methods against the true colours (composite PSNR; baseline: the gray input;
  DDS's source and NFSD's negative: the null label);
* light: the same methods against the true glow (the ``plus`` layer) of the world's coloured fill
  light, labels cycling through warm, cool, white: glow PSNR over all and object pixels, composite
  PSNR against the lit image, the glow's colour error (angle between its mean RGB and the truth's)
  and the darkening drift (how much an edit darkened the input: 0 for a ``plus`` layer by
  construction); baselines: no light, the best constant glow, the prior sampled directly. DDS's
  source is the null label, NFSD's negative the other colour (warm ↔ cool; white: the null label).

``--sections`` runs a subset (shading, color, light); the sections not run are carried over from
``--json-out``, so one table can be refreshed without re-running the others.

Writes ``docs/img/distill_pareto.png``, ``docs/img/distill_spectrum.png`` and the full results to
``--json-out``; ends by printing one JSON line of the headline numbers.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from _common import (  # noqa: E402
    add_labels,
    colourfulness,
    darkening,
    glow_colour_error,
    implied_shading,
    luma,
    machine_info,
    print_json_line,
    psnr,
)

from lasagna.catalogue import load_corrective, load_preset, load_prior, resolve  # noqa: E402
from lasagna.distill import distill_image  # noqa: E402
from lasagna.priors.base import Condition  # noqa: E402
from lasagna.priors.ddim import ddim_sample  # noqa: E402
from lasagna.world import GLOW_VOCABULARY, VOCABULARY, additive_light, colorization, generate  # noqa: E402

METHODS = ("sds", "lmc-sds", "dds", "nfsd", "ms-sds")
OPPOSITE = {
    "left": "right",
    "right": "left",
    "top": "bottom",
    "bottom": "top",
    "top-left": "bottom-right",
    "bottom-right": "top-left",
    "top-right": "bottom-left",
    "bottom-left": "top-right",
}
OPPOSITE_GLOW = {"warm": "cool", "cool": "warm", "white": ""}  # NFSD's negative for a light (white: the null label)
SECTIONS = ("shading", "color", "light")
CHROMA_EPS = 0.05  # pixels darker than this (sum of RGB) have no meaningful chromaticity: left out of the drift


# -- metrics ------------------------------------------------------------------------------------


def scale_invariant_mse(y: torch.Tensor, true: torch.Tensor) -> float:
    """mean over images of min_α mean((α·y − y*)²): the shading's error up to a global brightness."""
    y, true = y.double().flatten(1), true.double().flatten(1)
    alpha = (y * true).sum(1, keepdim=True) / (y * y).sum(1, keepdim=True).clamp_min(1e-12)
    return float(((alpha * y - true) ** 2).mean())


def chroma(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    s = x.double().sum(1, keepdim=True)
    return x.double() / s.clamp_min(1e-6), (s > CHROMA_EPS).double()


def chromaticity_drift(out: torch.Tensor, base: torch.Tensor) -> float:
    """Mean L1 difference of rgb/(r+g+b) between an edit and its input (pixels bright enough in both)."""
    co, mo = chroma(out)
    cb, mb = chroma(base)
    m = mo * mb
    return float(((co - cb).abs().sum(1, keepdim=True) * m).sum() / m.sum().clamp_min(1))


def albedo_error(out: torch.Tensor, base: torch.Tensor) -> float:
    """Mean |out / y − base| with y = implied_shading: what the edit changed besides luminosity."""
    y = implied_shading(out, base).clamp_min(1e-3)
    return float((out.double() / y.double() - base.double()).abs().mean())


def radial_spectrum(x: torch.Tensor) -> torch.Tensor:
    """Radially averaged power spectrum of the luma, mean over images: (H//2,) from DC outwards."""
    lum = luma(x.double())[:, 0]
    lum = lum - lum.mean(dim=(-2, -1), keepdim=True)
    p = torch.fft.fftshift(torch.fft.fft2(lum).abs() ** 2, dim=(-2, -1)).mean(0)
    h, w = p.shape
    yy, xx = torch.meshgrid(torch.arange(h) - h // 2, torch.arange(w) - w // 2, indexing="ij")
    r = (yy.double() ** 2 + xx.double() ** 2).sqrt().round().long()
    n = min(h, w) // 2
    return torch.stack([p[r == k].mean() for k in range(n)])


# -- runs ---------------------------------------------------------------------------------------
def shading_row(method: str, omega: float | None, y: torch.Tensor, comp: torch.Tensor, scene, seconds: float) -> dict:
    """The metrics of one shading result y (B, 1, H, W) with its composite, against the scene's truth."""
    n = len(scene.label)
    return {
        "method": method,
        "omega": omega,
        "shading_psnr": round(psnr(y, scene.shading), 2),
        "object_psnr": round(psnr(y, scene.shading, scene.mask), 2),
        "si_mse": round(scale_invariant_mse(y, scene.shading), 5),
        "composite_psnr": round(psnr(comp, scene.image), 2),
        "chroma_drift": round(chromaticity_drift(comp, scene.albedo), 5),
        "albedo_error": round(albedo_error(comp, scene.albedo), 5),
        "seconds": round(seconds, 4),
        "seconds_per_image": round(seconds / n, 5),
        "spectrum": radial_spectrum(comp).tolist(),
    }


def shading_run(method: str, omega: float, scene, preset, prior, corrective, steps: int, seed: int, every: int) -> dict:
    """One per-image distillation of every scene at once; metrics at the end and the curve on the way."""
    true = scene.shading
    curve: list[dict] = []
    negative = None
    if method == "dds":
        negative = ""  # DDS's source condition: the unlit input has no light label, so the null label
    elif method == "nfsd":
        negative = [OPPOSITE[lab] for lab in scene.label]  # away from the opposite light

    def trace(step: int, layer: torch.Tensor) -> None:
        if step % every == 0 or step == steps - 1:
            curve.append(
                {
                    "step": step + 1,
                    "time_s": time.perf_counter() - t0,
                    "shading_psnr": round(psnr(layer[:, :1], true), 3),
                }
            )

    t0 = time.perf_counter()
    res = distill_image(
        scene.albedo,
        preset,
        prior,
        corrective if method == "lmc-sds" else None,
        condition=scene.label,
        negative=negative,
        loss=method,
        guidance=omega,
        steps=steps,
        seed=seed,
        early_stop=False,
        callback=trace,
    )
    seconds = time.perf_counter() - t0
    n = true.shape[0]
    for c in curve:
        c["time_s_per_image"] = round(c.pop("time_s") / n, 5)
    return {**shading_row(method, omega, res.layer[:, :1], res.composite, scene, seconds), "curve": curve}


def direct_samples(scene, prior, omega: float, seed: int) -> dict:
    """The prior sampled with the same condition (DDIM-50): the "ControlNet alone" baseline."""
    t0 = time.perf_counter()
    out = ddim_sample(
        prior,
        Condition(list(scene.label), image=scene.albedo),
        steps=50,
        omega=omega,
        rng=torch.Generator().manual_seed(seed),
    ).image
    seconds = time.perf_counter() - t0
    return shading_row("prior-direct", omega, implied_shading(out, scene.albedo), out, scene, seconds)


def amortised(scene, preset, folder: Path | None, name: str) -> dict | None:
    """One forward pass of a trained shading generator over every scene (None if there is none)."""
    if folder is None or not (folder / "config.json").is_file():
        return None
    from lasagna.generators.layer import composite
    from lasagna.generators.unet import LayerGenerator

    gen = LayerGenerator.from_pretrained(folder)
    with torch.no_grad():
        gen(scene.albedo[:1], list(scene.label[:1]))  # warm-up: first-call allocations are not the steady cost
        t0 = time.perf_counter()
        y = gen(scene.albedo, list(scene.label))
        seconds = time.perf_counter() - t0
        comp = composite(scene.albedo, y, gen.spec).clamp(0, 1)
    return shading_row(name, None, y[:, :1], comp, scene, seconds)


def refined(scene, preset, prior, corrective, folder: Path | None, steps: int) -> dict | None:
    """The amortised pass, then ``steps`` per-image steps of the preset's loss from it (``lasagna edit --optimize``)."""
    if folder is None or not (folder / "config.json").is_file():
        return None
    from lasagna.distill import DistillSettings
    from lasagna.generators.free import FreeLayer
    from lasagna.generators.unet import LayerGenerator
    from lasagna.recipe import refining  # exactly the settings `lasagna edit --optimize` refines with

    t0 = time.perf_counter()
    with torch.no_grad():
        start = LayerGenerator.from_pretrained(folder)(scene.albedo, list(scene.label))
    settings = refining(DistillSettings.from_preset(preset, steps=steps))
    res = distill_image(
        scene.albedo,
        settings,
        prior,
        corrective,
        condition=scene.label,
        early_stop=False,
        generator=FreeLayer.from_layer(settings.layer, start),
    )
    seconds = time.perf_counter() - t0
    return shading_row(
        f"amortised + {steps} steps ({preset.distill.loss})",
        preset.distill.guidance,
        res.layer[:, :1],
        res.composite,
        scene,
        seconds,
    )


def color_run(method: str, omega: float, col, preset, prior, corrective, steps: int, seed: int) -> dict:
    t0 = time.perf_counter()
    res = distill_image(
        col.base,
        preset,
        prior,
        corrective if method == "lmc-sds" else None,
        condition="natural",
        negative="" if method in ("dds", "nfsd") else None,
        loss=method,
        guidance=omega,
        steps=steps,
        seed=seed,
        early_stop=False,
    )
    seconds = time.perf_counter() - t0
    return {
        "method": method,
        "omega": omega,
        "composite_psnr": round(psnr(res.composite, col.target), 2),
        "colourfulness": round(colourfulness(res.composite), 2),
        "seconds": round(seconds, 2),
    }


def light_row(method: str, omega: float | None, glow: torch.Tensor, comp: torch.Tensor, add, seconds: float) -> dict:
    """The metrics of one glow result (B, 3, H, W) with its composite, against the true glow and lit image."""
    mask = add.scene.mask
    return {
        "method": method,
        "omega": omega,
        "glow_psnr": round(psnr(glow, add.glow), 2),
        "object_psnr": round(psnr(glow, add.glow, mask), 2),
        "composite_psnr": round(psnr(comp, add.lit), 2),
        "colour_error_deg": round(glow_colour_error(glow, add.glow), 2),
        "darkening": round(darkening(comp, add.base), 5),
        "seconds": round(seconds, 3),
        "seconds_per_image": round(seconds / glow.shape[0], 5),
    }


def light_baselines(add, prior, omegas, seed: int) -> list[dict]:
    """No light, the best constant glow (per image and channel, least squares) and the prior sampled directly."""
    zero = torch.zeros_like(add.glow)
    const = add.glow.mean(dim=(2, 3), keepdim=True).expand_as(add.glow)
    rows = [
        light_row("no light (identity edit)", None, zero, add.base, add, 0.0),
        light_row("best-constant", None, const, (add.base + const).clamp(0, 1), add, 0.0),
    ]
    for w in omegas:
        t0 = time.perf_counter()
        out = ddim_sample(
            prior,
            Condition(list(add_labels(add)), image=add.base),
            steps=50,
            omega=w,
            rng=torch.Generator().manual_seed(seed),
        ).image
        rows.append(light_row("prior-direct", w, (out - add.base).clamp_min(0.0), out, add, time.perf_counter() - t0))
    return rows


def light_amortised(add, folder: Path | None) -> dict | None:
    """One forward pass of a trained light generator over every scene (None if there is none)."""
    if folder is None or not (folder / "config.json").is_file():
        return None
    from lasagna.generators.layer import composite
    from lasagna.generators.unet import LayerGenerator

    gen = LayerGenerator.from_pretrained(folder)
    labels = add_labels(add)
    with torch.no_grad():
        gen(add.base[:1], labels[:1])  # warm-up: first-call allocations are not the steady cost
        t0 = time.perf_counter()
        glow = gen(add.base, labels)
        seconds = time.perf_counter() - t0
        comp = composite(add.base, glow, gen.spec).clamp(0, 1)
    return light_row("amortised (distilled)", None, glow, comp, add, seconds)


def light_run(method: str, omega: float, add, preset, prior, corrective, steps: int, seed: int) -> dict:
    labels = add_labels(add)
    negative = None
    if method == "dds":
        negative = ""  # the source: the unlit input under no label
    elif method == "nfsd":
        negative = [OPPOSITE_GLOW[lab] for lab in labels]  # away from the other colour
    t0 = time.perf_counter()
    res = distill_image(
        add.base,
        preset,
        prior,
        corrective if method == "lmc-sds" else None,
        condition=labels,
        negative=negative,
        loss=method,
        guidance=omega,
        steps=steps,
        seed=seed,
        early_stop=False,
    )
    return light_row(method, omega, res.layer, res.composite, add, time.perf_counter() - t0)


# -- summaries and plots ------------------------------------------------------------------------
def best_by_method(rows: list[dict]) -> dict[str, dict]:
    best: dict[str, dict] = {}
    for r in rows:
        if r["method"] in METHODS and (
            r["method"] not in best or r["shading_psnr"] > best[r["method"]]["shading_psnr"]
        ):
            best[r["method"]] = r
    return best


def time_to_reach(curve: list[dict], target: float) -> float | None:
    """Seconds per image at the first traced step whose shading PSNR reaches ``target`` (None: never)."""
    for c in curve:
        if c["shading_psnr"] >= target:
            return c["time_s_per_image"]
    return None


def pareto(points: list[tuple[float, float]]) -> list[tuple[float, float]]:
    """The points no other point beats in both time (lower) and PSNR (higher), by time."""
    front, best = [], -math.inf
    for t, p in sorted(points):
        if p > best:
            front.append((t, p))
            best = p
    return front


def plot_pareto(rows: list[dict], extra: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4.8), dpi=110)
    best = best_by_method(rows)
    points = []
    for r in rows:
        points += [(c["time_s_per_image"], c["shading_psnr"]) for c in r.get("curve", [])]
    for m, r in best.items():
        ax.plot(
            [c["time_s_per_image"] for c in r["curve"]],
            [c["shading_psnr"] for c in r["curve"]],
            lw=1.4,
            label=f"{m} (best ω = {r['omega']:g})",
        )
    front = pareto(points)
    ax.plot([p[0] for p in front], [p[1] for p in front], "k--", lw=1, label="Pareto front (all methods × ω × steps)")
    curves = [r for r in extra if r.get("curve")]  # e.g. LMC-SDS with the network b̂: its best ω as a dotted curve
    if curves:
        r = max(curves, key=lambda r: r["shading_psnr"])
        ax.plot(
            [c["time_s_per_image"] for c in r["curve"]],
            [c["shading_psnr"] for c in r["curve"]],
            lw=1.2,
            ls=":",
            color="gray",
            label=f"{r['method']} (best ω = {r['omega']:g})",
        )
    for r in extra:
        if r.get("seconds_per_image") and r["method"] != "best-constant" and not r.get("curve"):
            ax.scatter(
                [r["seconds_per_image"]],
                [r["shading_psnr"]],
                marker="*",
                s=90,
                zorder=3,
                label=f"{r['method']}" + (f" ω = {r['omega']:g}" if r.get("omega") else ""),
            )
    const = next((r for r in extra if r["method"] == "best-constant"), None)
    if const:
        ax.axhline(const["shading_psnr"], color="gray", lw=0.8, ls=":", label="best constant")
    ax.set_xscale("log")
    ax.set_xlabel("wall time per image (s, batched, log scale)")
    ax.set_ylabel("shading PSNR vs truth (dB)")
    ax.set_title("Learned shading on held-out scenes: error against run time")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    plt.close(fig)


def plot_spectrum(curves: dict[str, list[float]], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4), dpi=110)
    for name, spec in curves.items():
        style = (
            {"lw": 2.2, "color": "k"}
            if name == "truth"
            else ({"lw": 1.5, "ls": "--", "color": "gray"} if name == "input (albedo)" else {"lw": 1.1})
        )
        ax.plot(range(1, len(spec)), spec[1:], label=name, **style)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("spatial frequency (cycles per image)")
    ax.set_ylabel("power of the luma (mean over images)")
    ax.set_title("Radially averaged power spectrum of the composite")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _cell(r: dict, key: str, spec: str, scale: float = 1.0) -> str:
    """One table cell: ``r[key]`` × scale formatted with ``spec``, or a dash when it was not measured."""
    v = r.get(key)
    return "—" if v is None else format(scale * v, spec)


def markdown(result: dict) -> str:
    rows = result.get("shading", [])
    out = [
        "| method | ω | shading PSNR | object PSNR | si-MSE ×10³ | composite PSNR | chroma drift | s / image |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in result.get("baselines", []) + rows:
        out.append(
            f"| {r['method']} | {_cell(r, 'omega', 'g')} | {r['shading_psnr']:.2f} | {r['object_psnr']:.2f} | "
            f"{_cell(r, 'si_mse', '.2f', 1e3)} | {_cell(r, 'composite_psnr', '.2f')} | "
            f"{_cell(r, 'chroma_drift', '.4f')} | "
            f"{_cell(r, 'seconds_per_image', '.3g')} |"
        )
    if result.get("color"):
        out += [
            "",
            "| colourisation method | ω | composite PSNR vs true colours | colourfulness M | s (all images) |",
            "|---|---|---|---|---|",
        ]
        for r in result["color"]:
            out.append(
                f"| {r['method']} | {_cell(r, 'omega', 'g')} | {r['composite_psnr']:.2f} | "
                f"{_cell(r, 'colourfulness', '.1f')} | "
                f"{r.get('seconds', '—')} |"
            )
    if result.get("light"):
        out += [
            "",
            "| light method | ω | glow PSNR | object PSNR | composite PSNR | colour error (°) | darkening ×10³ | s "
            "/ image |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for r in result["light"]:
            out.append(
                f"| {r['method']} | {_cell(r, 'omega', 'g')} | {r['glow_psnr']:.2f} | {r['object_psnr']:.2f} | "
                f"{r['composite_psnr']:.2f} | "
                f"{r['colour_error_deg']:.1f} | {1e3 * r['darkening']:.2f} | {r['seconds_per_image']:.3g} |"
            )
    return "\n".join(out)


def run_shading(args) -> dict:
    """The shading section: baselines, every method × ω, headline numbers against the targets, plots."""
    preset = load_preset("shading")
    parts = resolve("shading")
    prior = load_prior(parts.prior)
    corrective = load_corrective(parts.corrective) if parts.corrective else None
    labels = [VOCABULARY[i % len(VOCABULARY)] for i in range(args.count)]
    scene = generate(args.split, args.count, args.seed, prior.sample_shape[-1], labels=labels)
    # Warm-up: the first distillation of a process pays one-off allocations that are not the method's cost.
    distill_image(scene.albedo, preset, prior, corrective, condition=scene.label, steps=3, seed=0, early_stop=False)

    const = scene.shading.mean(dim=(1, 2, 3), keepdim=True).expand_as(scene.shading)
    baselines = [
        {
            "method": "best-constant",
            "omega": None,
            "shading_psnr": round(psnr(const, scene.shading), 2),
            "object_psnr": round(psnr(const, scene.shading, scene.mask), 2),
            "si_mse": round(scale_invariant_mse(const, scene.shading), 5),
            "composite_psnr": round(psnr((scene.albedo * const).clamp(0, 1), scene.image), 2),
        }
    ]
    print(json.dumps(baselines[-1]), flush=True)
    for w in sorted({1.0, 3.0, 7.5} & set(args.omegas) or {1.0}):
        baselines.append(direct_samples(scene, prior, w, args.seed))
        print(json.dumps({k: v for k, v in baselines[-1].items() if k != "spectrum"}), flush=True)
    gen_folder = args.generator or parts.generator
    for folder, name in ((gen_folder, "amortised (distilled)"), (args.supervised, "amortised (supervised ceiling)")):
        row = amortised(scene, preset, folder, name)
        if row is not None:
            baselines.append(row)
            print(json.dumps({k: v for k, v in row.items() if k != "spectrum"}), flush=True)

    row = refined(scene, preset, prior, corrective, gen_folder, args.refine_steps) if args.refine_steps else None
    if row is not None:
        baselines.append(row)
        print(json.dumps({k: v for k, v in row.items() if k != "spectrum"}), flush=True)

    rows = []
    for method in args.methods:
        for w in args.omegas:
            rows.append(shading_run(method, w, scene, preset, prior, corrective, args.steps, 0, args.trace_every))
            print(json.dumps({k: v for k, v in rows[-1].items() if k not in ("curve", "spectrum")}), flush=True)
    if args.network_corrective and "lmc-sds" in args.methods:
        net = load_corrective(args.network_corrective)
        for w in args.omegas:
            r = shading_run("lmc-sds", w, scene, preset, prior, net, args.steps, 0, args.trace_every)
            r["method"] = f"lmc-sds, b̂ = {args.network_corrective}"
            baselines.append(r)
            print(json.dumps({k: v for k, v in r.items() if k not in ("curve", "spectrum")}), flush=True)

    # Headline numbers against the issue's targets.
    best = best_by_method(rows)
    by = {(r["method"], r["omega"]): r for r in rows}
    sds_best, lmc_best = best.get("sds"), best.get("lmc-sds")
    direct = [b for b in baselines if b["method"] == "prior-direct"]
    lmc_default = by.get(("lmc-sds", preset.distill.guidance)) or lmc_best
    head = {
        "best_constant": baselines[0]["shading_psnr"],
        "best_constant_objects": baselines[0]["object_psnr"],
        "best": {
            m: {"omega": r["omega"], "shading_psnr": r["shading_psnr"], "object_psnr": r["object_psnr"]}
            for m, r in best.items()
        },
    }
    if sds_best and lmc_best:
        t_sds = sds_best["curve"][-1]["time_s_per_image"]
        t_lmc = time_to_reach(lmc_best["curve"], sds_best["shading_psnr"])
        head["lmc_time_to_sds_final_vs_sds"] = None if t_lmc is None else round(t_lmc / t_sds, 3)
        for w in (7.5, 15.0):
            if ("sds", w) in by and ("lmc-sds", w) in by:
                head[f"lmc_minus_sds_at_{w:g}"] = round(
                    by[("lmc-sds", w)]["shading_psnr"] - by[("sds", w)]["shading_psnr"], 2
                )
    if lmc_default and direct:
        head["drift_lasagna_vs_direct"] = round(
            lmc_default["chroma_drift"] / max(min(d["chroma_drift"] for d in direct), 1e-12), 4
        )
    ceiling = next((b for b in baselines if b["method"] == "amortised (supervised ceiling)"), None)
    distilled = next((b for b in baselines if b["method"] == "amortised (distilled)"), None)
    if ceiling:
        head["supervised_ceiling"] = ceiling["shading_psnr"]
    if distilled and lmc_default:
        head["amortised_minus_per_image"] = round(distilled["shading_psnr"] - lmc_default["shading_psnr"], 2)
        head["amortised_time_vs_per_image"] = round(
            distilled["seconds_per_image"] / lmc_default["seconds_per_image"], 5
        )

    spectra = {"input (albedo)": radial_spectrum(scene.albedo).tolist(), "truth": radial_spectrum(scene.image).tolist()}
    for m, r in best.items():
        spectra[f"{m} ω = {r['omega']:g}"] = r["spectrum"]
    for d in direct[:1]:
        spectra[f"prior sampled directly ω = {d['omega']:g}"] = d["spectrum"]
    args.img.mkdir(parents=True, exist_ok=True)
    plot_pareto(rows, baselines, args.img / "distill_pareto.png")
    plot_spectrum(spectra, args.img / "distill_spectrum.png")

    return {
        "prior": str(parts.prior),
        "corrective": str(parts.corrective),
        "headline": head,
        "baselines": baselines,
        "shading": rows,
    }


def run_color(args) -> list[dict]:
    """The colourisation section: the gray input, SDS and LMC-SDS × ω against the true colours."""
    color = []
    cpreset = load_preset("color")
    cparts = resolve("color")
    cprior = load_prior(cparts.prior)
    ccorr = load_corrective(cparts.corrective) if cparts.corrective else None
    col = colorization(generate(args.split, args.count, args.seed, cprior.sample_shape[-1]))
    color.append(
        {
            "method": "gray input (identity edit)",
            "omega": None,
            "composite_psnr": round(psnr(col.base, col.target), 2),
            "colourfulness": round(colourfulness(col.base), 2),
        }
    )
    color.append(
        {
            "method": "the true colours",
            "omega": None,
            "composite_psnr": 100.0,
            "colourfulness": round(colourfulness(col.target), 2),
        }
    )
    t0 = time.perf_counter()
    out = ddim_sample(
        cprior,
        Condition(["natural"] * args.count, image=col.base[:, :1]),
        steps=50,
        omega=1.0,
        rng=torch.Generator().manual_seed(args.seed),
    ).image
    color.append(
        {
            "method": "prior-direct",
            "omega": 1.0,
            "composite_psnr": round(psnr(out, col.target), 2),
            "colourfulness": round(colourfulness(out), 2),
            "seconds": round(time.perf_counter() - t0, 2),
        }
    )
    for m in [m for m in args.methods if m != "lmc-sds" or ccorr is not None]:
        for w in args.color_omegas:
            color.append(color_run(m, w, col, cpreset, cprior, ccorr, args.steps, 0))
            print(json.dumps(color[-1]), flush=True)
    return color


def run_light(args) -> list[dict]:
    """The light section: baselines, SDS and LMC-SDS × ω against the true glow (labels warm, cool, white in turn)."""
    from lasagna.catalogue import preset_status

    status = preset_status("light")
    if not status["usable"]:
        print(json.dumps({"light": "skipped", "why": status["why"]}), flush=True)
        return []
    lpreset = load_preset("light")
    lparts = resolve("light")
    lprior = load_prior(lparts.prior)
    lcorr = load_corrective(lparts.corrective) if lparts.corrective else None
    labels = [GLOW_VOCABULARY[i % len(GLOW_VOCABULARY)] for i in range(args.count)]
    add = additive_light(generate(args.split, args.count, args.seed, lprior.sample_shape[-1]), labels)
    light = light_baselines(
        add, lprior, [w for w in args.light_omegas if w in (1.0, 3.0)] or args.light_omegas[:1], args.seed
    )
    row = light_amortised(add, args.light_generator or lparts.generator)
    if row is not None:
        light.append(row)
    for r in light:
        print(json.dumps(r), flush=True)
    for m in [m for m in args.methods if m != "lmc-sds" or lcorr is not None]:
        for w in args.light_omegas:
            light.append(light_run(m, w, add, lpreset, lprior, lcorr, args.steps, 0))
            print(json.dumps(light[-1]), flush=True)
    return light


# -- main ---------------------------------------------------------------------------------------
def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=16)
    ap.add_argument("--seed", type=int, default=7, help="world seed of the held-out scenes")
    ap.add_argument(
        "--split", default="heldout", help="world split (heldout: families the priors never saw; val: seen families)"
    )
    ap.add_argument("--steps", type=int, default=150)
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    ap.add_argument("--omegas", nargs="+", type=float, default=[1.0, 3.0, 7.5, 15.0, 30.0])
    ap.add_argument(
        "--network-corrective", default="relight-32-bhat", help="the network b̂ compared with the preset's ('' to skip)"
    )
    ap.add_argument(
        "--generator", type=Path, default=None, help="amortised generator folder (default: the shading preset's)"
    )
    ap.add_argument(
        "--supervised",
        type=Path,
        default=ROOT / "runs" / "shading-supervised" / "generator",
        help="the supervised-ceiling generator folder",
    )
    ap.add_argument("--refine-steps", type=int, default=50, help="per-image steps after the amortised pass (0: skip)")
    ap.add_argument("--color-omegas", nargs="*", type=float, default=[1.0, 3.0, 7.5])
    ap.add_argument("--light-omegas", nargs="*", type=float, default=[1.0, 3.0, 7.5])
    ap.add_argument(
        "--light-generator",
        type=Path,
        default=None,
        help="amortised light generator folder (default: the light preset's)",
    )
    ap.add_argument(
        "--sections",
        nargs="+",
        default=list(SECTIONS),
        choices=SECTIONS,
        help="which tables to run; the others are carried over from --json-out",
    )
    ap.add_argument("--trace-every", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--quick", action="store_true", help="2 images, 10 steps, SDS and LMC-SDS at ω 1 and 7.5")
    ap.add_argument("--markdown", action="store_true")
    ap.add_argument("--json-out", type=Path, default=ROOT / "docs" / "distill_accuracy.json")
    ap.add_argument("--img", type=Path, default=ROOT / "docs" / "img")
    ap.add_argument("--replot", action="store_true", help="redraw the plots from --json-out without running anything")
    args = ap.parse_args(argv)
    if args.replot:
        saved = json.loads(args.json_out.read_text())
        plot_pareto(saved["shading"], saved["baselines"], args.img / "distill_pareto.png")
        print(markdown(saved))
        return 0
    if args.quick:
        args.count, args.steps, args.methods, args.omegas, args.color_omegas, args.light_omegas = (
            2,
            10,
            ["sds", "lmc-sds"],
            [1.0, 7.5],
            [1.0],
            [1.0],
        )
        args.json_out, args.img = Path("/tmp/distill_accuracy_quick.json"), Path("/tmp/distill_accuracy_quick")
    torch.set_num_threads(args.threads)
    t_start = time.perf_counter()
    result = {}
    if args.json_out.is_file() and set(args.sections) != set(SECTIONS):
        result = json.loads(args.json_out.read_text())  # the sections not run are carried over
    result.update(
        {"machine": machine_info(), "split": args.split, "count": args.count, "steps": args.steps, "seed": args.seed}
    )
    if "shading" in args.sections:
        result.update(run_shading(args))
    if "color" in args.sections:
        result["color"] = run_color(args) if args.color_omegas else []
    if "light" in args.sections:
        result["light"] = run_light(args) if args.light_omegas else []
    result["wall_seconds"] = round(time.perf_counter() - t_start, 1)
    args.json_out.parent.mkdir(parents=True, exist_ok=True)
    args.json_out.write_text(json.dumps(result, indent=1) + "\n")
    if args.markdown:
        print(markdown(result))
    print_json_line(
        {
            "benchmark": "distill_accuracy",
            "sections": args.sections,
            **result.get("headline", {}),
            "wall_seconds": result["wall_seconds"],
        }
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
