"""Four probes of issue #24's gap, each a way to more relief or better shape without more training (round 5).

    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe gain-fit     # ~2 min
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe gain-fit --default   # ~4 min
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe srgb         # ~1 min
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe profile      # ~3 min
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe sirfs        # ~6 min
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe symmetric-particles   # ~10 min
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe wall-level   # ~2 min (round 8)
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe truth-start  # ~3 min (round 13)
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe t-anneal     # ~15 min (round 13)
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe posterior-mean   # ~2 min (round 14)
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe denoise --prior runs/relit-grown/prior
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe told-fit     # ~2 min (round 25)
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe profile-fit  # ~40 s (round 27)
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe profile-fit --tilt   # ~1 min
    OMP_NUM_THREADS=2 .venv/bin/python benchmarks/surface_probes.py --probe ensemble \
        --members layers/surface-lit-32 layers/surface-lit-closeup-32                   # ~1 min

* **gain-fit** — a relief gain chosen per image: the lit estimator's heights times g, g on a fixed grid, the g whose
  normals (dome prior applied) under their own fitted light best give the estimator's source shading Ŝ_src (least
  squares). A lit image says how deep its relief is only through its shading, so the depth is read from the head
  that estimates it. Rows: the relight surface route on `select` (16 scenes, 64², dB over the unchanged input, all /
  objects) at g = 1 and fitted, and the surface route's photograph swings (`examples/photos/select`, chosen on;
  `examples/photos/large`, reported). ``--default`` instead patches the estimator for the whole edit path and
  measures the default relight (`relight_sweep.py`'s "default" row at 64² and 256², `photo_swing.py` on the
  selection set): what the estimator rule judges.
* **srgb** — photographs read in linear light: a photograph's stored values are sRGB-encoded, so its shading is
  seen compressed (≈ S^(1/2.2)), while the world's images are defined on stored values. Here the photograph is
  decoded, the surface estimated and the ratio applied in linear light, and the result encoded again; the stored
  multiplier is then encode(decode(x)·r)/x. The world cannot choose this (it has no encoding to undo), so only
  the photograph selection set can. Rows: the surface route's swings on both photograph sets, stored and linear.
* **profile** — the outline-inflation profile for shading: round domes √(R² − (R − d)²), roofs d (the straight
  skeleton's facets, a pyramid's or a prism's from above) and parabolas d(2R − d)/R, each at several heights,
  as the oracle (true outlines) and as the albedo estimator's dome prior (weights 0.25 and 0.5), on `select`'s
  shading (16 scenes, 64², dB over the best constant).
* **sirfs** — a per-image shape-from-shading refinement with an albedo prior, after SIRFS (Barron & Malik 2015):
  the lit estimator's height h₀ + δ and its light refined by Adam so that the log-albedo log Y − log S(n, l) has
  sparse gradients (Charbonnier), with an anchor λ_a‖δ‖² and a smoothness λ_s‖∇²h‖² (both per canvas unit). Rows:
  the relight surface route on `select` (64²) for each (steps, λ_a, λ_s, Charbonnier ε).

* **told-fit** (round 25) — the told route told the light the untold surface layer fits (`lasagna.edit(...,
  layer_kind="surface")`'s stored ``source_light``), and blends of a told layer on the objects with the free default
  on the walls (weights: the told estimator's silhouette probability, or the true mask as the blend's best case),
  beside the free default, the untold layer and the told route told the true light: `select` (16 scenes, world
  seed ``--seed``, 64²), dB over the unchanged input (all / objects), and each scene's fitted against true light.
  Asks whether a default can borrow the told route's objects without a person's reading.

* **profile-fit** (round 27) — analysis by synthesis over a low-dimensional shape family for the relight's objects,
  a different design from a per-pixel estimate: each true silhouette inflated by one of five profiles of its
  distance to the outline d (t = d/R: dome √(1 − (1 − t)²), cone t, parabola 1 − (1 − t)², mesa min(1, 2t), √t) at
  seven heights (× R, as ``ORACLE_HEIGHTS``), with ``--tilt`` also a plane of 25 slopes added; per object the choice
  whose Lambert shading under the true source light best explains the lit input's log luminance up to the object's
  mean paint (least squares over its pixels), and, as the family's ceiling, the choice the truth prefers. Rows: the
  relight through those normals on `select` (16 scenes, seed ``--seed``, 64², dB over the unchanged input, all /
  objects), with the one-height dome (the issue's oracle) and the true normals. Best case throughout: the true
  silhouettes and the true source light.

* **ensemble** — the lit estimators of ``--members`` (each with the relight's dome prior) averaged: their normals
  (renormalised) and their source shadings, the light fitted to the averages. Rows: the relight surface route on
  `select` at 64² and 256² for each member alone and for the ensemble.

* **symmetric-particles** — the default relight's distillation, its four particles given the image's four mirror
  images (each toward the mirrored light: left ↔ right, top ↔ bottom) instead of four noise draws of the image, each
  layer mirrored back and averaged: four whole edits at one particle each (`lasagna.edit(..., particles=1)`). The
  relight prior is not mirror-equivariant either. Rows: `relight_sweep.py`'s composite PSNR on select at 64² and
  256², and the swings on the photograph selection set.

* **wall-level** (round 8) — where the relight surface layer loses to the free default on `select` (16 scenes, 64²):
  per scene, the composite PSNR of the surface layer as shipped, of the free default, and of the surface layer with
  its source elevation solved (bisection, the azimuth kept) so that its mean log ratio over the true walls equals a
  reference's: the truth's (an oracle of the level alone), the free default's, and a short free run's (40 steps,
  2 particles); and each route's wall-level error, the mean |log| of its walls' level against the truth's, on all
  scenes and on the flat-wall ones. Per-scene means, not the pooled PSNR of `relight_sweep.py`.

* **truth-start** (round 13) — what the default relight's score-distillation correction does to a perfect start: the
  default edit (`lasagna.edit(image, "relight", label)`) on `select`'s 16 scenes at 64² and 256², as shipped and with
  its surface start replaced by the true ratio S_B/S_A reduced to the working size (`lasagna.learned._surface_start`
  patched), beside the identity and the true ratio at the working size enlarged bilinearly (the headroom of any layer
  made at 64). If the correction kept a perfect start, a better start would carry the default toward the headroom;
  the distance from the truth's row to the headroom is what the prior's correction takes away. Composite PSNR, all /
  object pixels (`_common.row`).

* **t-anneal** (round 13) — the default relight with its timesteps annealed (DreamTime, Huang et al. 2023): t_max
  falls linearly from 0.98 to each ``--finals`` value over the 150 steps, so the run ends on fine corrections.
  Rows per setting (the shipped first): `relight_sweep.py`'s default row on select at 64² and 256², the default's
  bare-wall leak there, and `photo_swing.py` on the photograph selection set.

* **posterior-mean** (round 14) — the default relight's score-distillation correction replaced by the prior's
  posterior mean of its start (SDEdit's mean, Meng et al. 2022): the start's composite in the prior's view noised to
  t*, the conditional x̂₀ averaged over 8 noise draws, and the ratio of its luma to the start's luma the correction —
  of the whole view (32², enlarged bilinearly to the working size), of the four 32² tiles of the 64² working input at
  native resolution ("tiles"), or both in turn; then the default's planar lock and guided enlargement
  (`lasagna.learned._optimise` patched). 8–16 prior passes against the default's 600. Rows: composite PSNR on
  `select`'s 16 scenes at 64² for t* × mode (``--finals`` are the t* values, ``--modes`` the modes); ``--size 32``
  makes the scenes at the prior's own size, the working size 32 (no enlargement, no crops).

* **denoise** (round 14) — the capacity question: the MSE of the conditional x̂₀ per t (128 scenes, 4 noise draws)
  of `relit-32` and of ``--prior`` on `val` (training families, unseen scenes) and `select` (unseen families).

Ends with one JSON line. None of these changes a preset; they are diagnostics (BENCHMARKS, round of 2026-11-26 (5)).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import photo_swing  # noqa: E402
import relight_sweep  # noqa: E402
import surface  # noqa: E402
from _common import PHOTO_AXES, machine_info, print_json_line, psnr, read_photo  # noqa: E402
from _common import swing as photo_swing_of  # noqa: E402
from relief_gain import last_json  # noqa: E402

import lasagna.compose.surface as cs  # noqa: E402
from lasagna.compose.color import linear_to_srgb, luma, srgb_to_linear  # noqa: E402
from lasagna.compose.resample import downsample, working_size  # noqa: E402
from lasagna.generators.surface import DomePrior, SurfaceEstimator  # noqa: E402
from lasagna.world.tasks import relight_sources, relighting  # noqa: E402

LAYERS = ROOT / "layers"
LIT = LAYERS / "surface-lit-closeup-32"
LIT_DOME = DomePrior(weight=0.15, height=0.5)
GAINS = (0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0)
PHOTO_SETS = {"select": ROOT / "examples" / "photos" / "select", "large": ROOT / "examples" / "photos" / "large"}
COUNT = 16
SIDE = 64


def fitted_gain(net: SurfaceEstimator, out, dome: DomePrior) -> tuple[float, torch.Tensor, torch.Tensor]:
    """(g, normals, light) of the grid's gain whose normals under their fitted light best give Ŝ_src."""
    best = None
    for g in GAINS:
        n = dome.apply(net.normals(out.surface * g), out.silhouette)
        light = cs.fit_light(n, out.shading)
        err = float(((cs.lambert(n, light) - out.shading) ** 2).mean())
        if best is None or err < best[0]:
            best = (err, g, n, light)
    return best[1], best[2], best[3]


@torch.no_grad()
def lit_estimate(net: SurfaceEstimator, image: torch.Tensor, gain: str) -> tuple[torch.Tensor, torch.Tensor, float]:
    """(normals at the image's size, source light, g) of the close-up estimator at its working size; ``gain`` 'fit'
    chooses g per image, else g = 1 (the shipped estimate)."""
    full = tuple(image.shape[-2:])
    small = downsample(image, working_size(*full, net.config.working_size))
    if gain == "fit":
        g, n, light = fitted_gain(net, net.outputs(small), LIT_DOME)
    else:
        (n, light), g = net.estimate(small, LIT_DOME), 1.0
    return net.normals(cs.enlarge_surface(n, full)), light, g


def world_relight(estimate) -> dict:
    """The relight surface route on select's 16 scenes at 64² with ``estimate(image) -> (normals, light)``."""
    scene, labels = surface.scenes("select", COUNT, 0, SIDE)
    rel = relighting(scene, relight_sources(scene.params))
    base, target, mask = rel.base, rel.target.clamp(0, 1), scene.mask
    targets = surface.lights_of(labels)
    comps = []
    for i in range(COUNT):
        n, light = estimate(base[i : i + 1])[:2]
        comps.append((base[i : i + 1] * cs.lambert(n, targets[i : i + 1]) / cs.lambert(n, light)).clamp(0, 1))
    c = torch.cat(comps)
    b_all, b_obj = psnr(base.clamp(0, 1), target), psnr(base.clamp(0, 1), target, mask)
    return {"gain_db": round(psnr(c, target) - b_all, 2), "gain_obj_db": round(psnr(c, target, mask) - b_obj, 2)}


def photo_swings(relit) -> dict:
    """The surface route's swings per photograph set with ``relit(image, light) -> composite``."""
    out = {}
    for name, folder in PHOTO_SETS.items():
        values, rows = [], {}
        for file in sorted(folder.glob("*.jpg")):
            image = read_photo(file)
            row = []
            for pair in PHOTO_AXES.values():
                row.append(round(sum(photo_swing_of(image[0], relit(image, light)[0], light) for light in pair), 4))
            rows[file.stem] = row
            values += row
        out[name] = {
            "photos": rows,
            "mean": round(sum(values) / len(values), 4),
            "at_least_0.10": sum(v >= 0.10 for v in values),
            "wrong_signs": sum(v < 0 for v in values),
        }
    return out


def probe_gain_fit(default: bool) -> dict:
    if default:
        return gain_fit_default()
    net = SurfaceEstimator.from_pretrained(LIT)
    out = {}
    for gain in ("1", "fit"):
        gains = []

        def estimate(image, gain=gain, gains=gains):
            n, light, g = lit_estimate(net, image, gain)
            gains.append(g)
            return n, light

        row = world_relight(estimate)
        row["gains"] = list(gains)

        def relit(image, light, gain=gain):
            n, source, _ = lit_estimate(net, image, gain)
            return (image * cs.lambert(n, surface.lights_of([light])) / cs.lambert(n, source)).clamp(0, 1)

        out[f"g {gain}"] = {"select_64": row, **photo_swings(relit)}
    return out


@contextlib.contextmanager
def gain_fitted_estimators():
    """Every lit height estimator's ``estimate`` chooses its gain per image inside the block."""
    shipped = SurfaceEstimator.estimate

    def estimate(self, image, dome=None):
        out = self.outputs(image)
        if out.shading is None or self.config.output != "height":
            return shipped(self, image, dome)
        _, n, light = fitted_gain(self, out, dome or DomePrior())
        return n, light

    SurfaceEstimator.estimate = estimate
    try:
        yield
    finally:
        SurfaceEstimator.estimate = shipped


def gain_fit_default() -> dict:
    out = {}
    with gain_fitted_estimators():
        for size in (64, 256):
            run = last_json(relight_sweep.main, ["--split", "select", "--size", str(size), "--only", "default"])
            row = run["last"]["rows"][0]
            out[f"default_select_{size}"] = [row["composite_psnr"], row["object_psnr"]]
        swing = last_json(photo_swing.main, ["--label", "gain fit"])["last"]
        out["photo_select"] = {k: swing[k] for k in ("swing_mean", "wrong_signs", "below_0.10", "photos")}
    return out


def probe_srgb() -> dict:
    net = SurfaceEstimator.from_pretrained(LIT)
    out = {}
    for space in ("stored", "linear"):

        def relit(image, light, space=space):
            x = srgb_to_linear(image) if space == "linear" else image
            n, source, _ = lit_estimate(net, x, "1")
            y = x * cs.lambert(n, surface.lights_of([light])) / cs.lambert(n, source)
            return linear_to_srgb(y.clamp(0, 1)) if space == "linear" else y.clamp(0, 1)

        out[space] = photo_swings(relit)
    return out


PROFILES = {
    "dome": lambda d, r: (r**2 - (r - d) ** 2).clamp_min(0).sqrt(),
    "roof": lambda d, r: d,
    "parabola": lambda d, r: d * (2 * r - d) / r,
}


@contextlib.contextmanager
def inflation_profile(profile):
    """``inflate_regions`` with its round profile replaced by ``profile(d, R)`` inside the block."""
    shipped = cs.inflate_regions

    def inflate(index):
        dome = shipped(index) * (index.shape[-1] / 2.0)  # back to pixels: √(R² − (R − d)²)
        out = torch.zeros_like(dome)
        for b in range(index.shape[0]):
            for k in index[b, 0].unique().tolist():
                if k < 0:
                    continue
                inside = index[b, 0] == k
                h = dome[b, 0][inside]
                r = (h.max() ** 2 + 0.25).sqrt()  # R = max d + ½, so the top is √(R² − ¼)
                d = r - (r * r - h * h).clamp_min(0).sqrt()  # inverted: the distance to the outline
                out[b, 0][inside] = profile(d, r)
        return out * (2.0 / index.shape[-1])

    cs.inflate_regions = inflate
    try:
        yield
    finally:
        cs.inflate_regions = shipped


def probe_profile() -> dict:
    scene, labels = surface.scenes("select", COUNT, 0, SIDE)
    truth, mask = scene.shading, scene.mask
    const = truth.mean(dim=(1, 2, 3), keepdim=True).expand_as(truth)
    c_all, c_obj = psnr(const, truth), psnr(const, truth, mask)
    light = surface.lights_of(labels)
    net = SurfaceEstimator.from_pretrained(LAYERS / "surface-albedo-32")

    def gain(y):
        return [round(psnr(y, truth) - c_all, 2), round(psnr(y, truth, mask) - c_obj, 2)]

    out = {}
    for name, profile in PROFILES.items():
        with inflation_profile(profile):
            for height in (0.25, 0.5, 1.0):
                row = {"oracle": gain(cs.lambert(cs.dome_normals(scene.object_index, height), light))}
                for weight in (0.25, 0.5):
                    n, _ = net.estimate_at(scene.albedo, DomePrior(weight=weight, height=height))
                    row[f"estimator + prior {weight:g}"] = gain(cs.lambert(n, light))
                out[f"{name} {height:g}"] = row
    return out


def charbonnier(x: torch.Tensor, eps: float) -> torch.Tensor:
    return (x * x + eps * eps).sqrt() - eps


def sirfs(net: SurfaceEstimator, image: torch.Tensor, steps: int, anchor: float, smooth: float, eps: float):
    """(normals, light) of the close-up estimate refined by the albedo-sparsity objective (module docstring)."""
    full = tuple(image.shape[-2:])
    small = downsample(image, working_size(*full, net.config.working_size))
    with torch.no_grad():
        out = net.outputs(small)
        n0 = LIT_DOME.apply(net.normals(out.surface), out.silhouette)
        l0 = cs.fit_light(n0, out.shading)
    h0 = out.surface
    delta = torch.zeros_like(h0, requires_grad=True)
    lp = l0.clone().requires_grad_(True)
    log_y = torch.log(luma(small).clamp_min(1e-3))
    opt = torch.optim.Adam([delta, lp], lr=0.01)
    unit = h0.shape[-1] / 2.0  # pixels per canvas unit
    for _ in range(steps):
        h = h0 + delta
        n = LIT_DOME.apply(cs.normals_from_height(h), out.silhouette)
        r = log_y - torch.log(cs.lambert(n, lp / lp.norm(dim=1, keepdim=True)))
        lap = h[..., 1:-1, 2:] + h[..., 1:-1, :-2] + h[..., 2:, 1:-1] + h[..., :-2, 1:-1] - 4 * h[..., 1:-1, 1:-1]
        loss = (
            charbonnier(r[..., :, 1:] - r[..., :, :-1], eps).mean()
            + charbonnier(r[..., 1:, :] - r[..., :-1, :], eps).mean()
            + anchor * (delta * delta).mean() * unit**2
            + smooth * (lap * lap).mean() * unit**4
        )
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        n = LIT_DOME.apply(cs.normals_from_height(h0 + delta), out.silhouette)
        return net.normals(cs.enlarge_surface(n, full)), lp / lp.norm(dim=1, keepdim=True)


SIRFS_SETTINGS = ((0, 0.0, 0.0, 0.01), (100, 0.1, 0.1, 0.01), (100, 1.0, 0.1, 0.01), (100, 10.0, 1.0, 0.01),
                  (100, 100.0, 1.0, 0.01), (50, 30.0, 10.0, 0.05))  # fmt: skip


def probe_sirfs() -> dict:
    net = SurfaceEstimator.from_pretrained(LIT)
    return {
        f"steps {s}, anchor {a:g}, smooth {m:g}, eps {e:g}": world_relight(
            lambda image, s=s, a=a, m=m, e=e: sirfs(net, image, s, a, m, e)
        )
        for s, a, m, e in SIRFS_SETTINGS
    }


@torch.no_grad()
def ensemble_estimate(nets: list[SurfaceEstimator], image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    full = tuple(image.shape[-2:])
    small = downsample(image, working_size(*full, nets[0].config.working_size))
    normals, shadings = [], []
    for net in nets:
        out = net.outputs(small)
        normals.append(LIT_DOME.apply(net.normals(out.surface), out.silhouette))
        shadings.append(out.shading)
    n = cs.facing_normals(torch.stack(normals).mean(0))
    light = cs.fit_light(n, torch.stack(shadings).mean(0))
    return cs.facing_normals(cs.enlarge_surface(n, full)), light


def probe_ensemble(members: list[Path]) -> dict:
    nets = {str(m): SurfaceEstimator.from_pretrained(m) for m in members}
    groups = {name: [net] for name, net in nets.items()}
    groups["ensemble of all"] = list(nets.values())
    out = {}
    for size in (64, 256):
        global SIDE
        SIDE, shipped = size, SIDE
        try:
            for name, group in groups.items():
                out.setdefault(name, {})[f"select_{size}"] = world_relight(
                    lambda image, group=group: ensemble_estimate(group, image)
                )
        finally:
            SIDE = shipped
    return out


# Each mirror of the image, and what it does to a named light (the vocabulary's eight).
_LEFT_RIGHT = {
    "left": "right",
    "right": "left",
    "top-left": "top-right",
    "top-right": "top-left",
    "bottom-left": "bottom-right",
    "bottom-right": "bottom-left",
    "top": "top",
    "bottom": "bottom",
}
_TOP_BOTTOM = {
    "top": "bottom",
    "bottom": "top",
    "top-left": "bottom-left",
    "bottom-left": "top-left",
    "top-right": "bottom-right",
    "bottom-right": "top-right",
    "left": "left",
    "right": "right",
}
LIGHT_MIRRORS = (
    ((), lambda light: light),
    ((-1,), lambda light: _LEFT_RIGHT[light]),
    ((-2,), lambda light: _TOP_BOTTOM[light]),
    ((-2, -1), lambda light: _TOP_BOTTOM[_LEFT_RIGHT[light]]),
)


def symmetric_layer(image: torch.Tensor, light: str) -> torch.Tensor:
    """The default relight of ``image`` (3, H, W) toward ``light`` from its four mirror images, one particle each."""
    from lasagna.editing import edit

    layers = []
    for dims, mirror in LIGHT_MIRRORS:
        layer = edit(image.flip(dims) if dims else image, "relight", mirror(light), particles=1).layer
        layers.append(layer.flip(dims) if dims else layer)
    return torch.stack(layers).mean(0)


def probe_symmetric_particles() -> dict:
    from _common import row, scenes

    out = {}
    for size in (64, 256):
        rel, labels = scenes("select", COUNT, 0, size)
        images = rel.base.float()
        layers = torch.stack([symmetric_layer(images[i], labels[i]) for i in range(COUNT)]).double()
        r = row(rel, "symmetric particles", layers)
        out[f"select_{size}"] = [r["composite_psnr"], r["object_psnr"]]
    values, photos = [], {}
    for file in sorted(PHOTO_SETS["select"].glob("*.jpg")):
        image = read_photo(file)[0]
        axes = []
        for pair in PHOTO_AXES.values():
            total = 0.0
            for light in pair:
                total += photo_swing_of(image, (image * symmetric_layer(image, light)).clamp(0, 1), light)
            axes.append(round(total, 4))
        photos[file.stem] = axes
        values += axes
    out["photo_select"] = {
        "photos": photos,
        "mean": round(sum(values) / len(values), 4),
        "at_least_0.10": sum(v >= 0.10 for v in values),
        "wrong_signs": sum(v < 0 for v in values),
    }
    return out


def wall_level(y: torch.Tensor, walls: torch.Tensor) -> float:
    """The mean log of a ratio ``y`` (1, 1, H, W) over the wall pixels ``walls`` (bool, same shape)."""
    return float(y.double().clamp_min(1e-4).log()[walls].mean())


def level_matched(normals, target, light, walls, level: float) -> torch.Tensor:
    """The ratio S(target)/S(source) of ``normals`` with the source light's elevation solved (bisection over
    [0, MAX_FIT_ELEVATION], its azimuth kept) so that its wall level (``wall_level``) is ``level``: a higher source
    elevation darkens a flat wall's S(source), so the level rises with it."""
    lo, hi = 0.0, cs.MAX_FIT_ELEVATION
    for _ in range(40):
        mid = (lo + hi) / 2
        source = cs._with_elevation(light, torch.tensor([mid], dtype=light.dtype))
        if wall_level(cs.relight_ratio(normals, target, source), walls) < level:
            lo = mid
        else:
            hi = mid
    return cs.relight_ratio(
        normals, target, cs._with_elevation(light, torch.tensor([(lo + hi) / 2], dtype=light.dtype))
    )


def probe_wall_level() -> dict:
    from lasagna import edit
    from lasagna.document.condition import parse_direction

    scene, labels = surface.scenes("select", COUNT, 0, SIDE)
    rel = relighting(scene, relight_sources(scene.params))
    base, target, truth = rel.base, rel.target.clamp(0, 1), rel.layer.double()
    flat = (scene.params.relief < 0).tolist()
    psnrs: dict[str, list[float]] = {}
    errors: dict[str, list[float]] = {}
    for i in range(COUNT):
        x, walls = base[i].float(), scene.mask[i : i + 1] < 0.5
        made = edit(x, "relight", labels[i], layer_kind="surface")
        layer = made.stack.document.layer(made.layer_id)
        normals = cs.decode_normal_map(made.stack.tensors[made.layer_id].color[None].double())
        source = cs.light_vector(*parse_direction(layer.source_light), dtype=torch.float64)[None]
        tgt = cs.light_vector(*parse_direction(labels[i]), dtype=torch.float64)[None]
        ratios = {
            "surface layer": made.layer[:1][None].double(),
            "free default": edit(x, "relight", labels[i], layer_kind="free").layer[:1][None].double(),
            "short free run": edit(x, "relight", labels[i], layer_kind="free", optimize=40, particles=2)
            .layer[:1][None]
            .double(),
            "amortised generator": edit(x, "relight", labels[i], layer_kind="free", generator="amortised")
            .layer[:1][None]
            .double(),
        }
        refs = {
            "truth": truth[i : i + 1],
            "free default": ratios["free default"],
            "short free run": ratios["short free run"],
        }
        for name, ref in refs.items():
            ratios[f"surface layer, level of the {name}"] = level_matched(
                normals, tgt, source, walls, wall_level(ref, walls)
            )
        true_level = wall_level(truth[i : i + 1], walls)
        for name, y in ratios.items():
            psnrs.setdefault(name, []).append(psnr((base[i : i + 1] * y).clamp(0, 1), target[i : i + 1]))
            errors.setdefault(name, []).append(abs(wall_level(y, walls) - true_level))

    def mean(v: list[float], pick=None) -> float:
        v = [x for k, x in enumerate(v) if pick is None or pick[k]]
        return round(sum(v) / len(v), 3)

    return {
        name: {
            "psnr_mean": mean(psnrs[name], None),
            "psnr_mean_flat_walls": mean(psnrs[name], flat),
            "wall_level_abs_log_err": mean(errors[name], None),
            "wall_level_abs_log_err_flat": mean(errors[name], flat),
        }
        for name in psnrs
    }


@contextlib.contextmanager
def start_relief(gain: float):
    """Every ``SurfaceEstimator.estimate_at`` inside the block deepens its estimate by ``gain`` (``relief``): in the
    default relight's path that is only the free ratio's surface start."""
    shipped = SurfaceEstimator.estimate_at

    def estimate_at(self, image, dome=None, side=None, symmetry="none", relief=1.0):
        return shipped(self, image, dome, side, symmetry, relief * gain)

    SurfaceEstimator.estimate_at = estimate_at
    try:
        yield
    finally:
        SurfaceEstimator.estimate_at = shipped


def probe_start_relief(gains: list[float]) -> dict:
    out = {}
    for gain in gains:
        row = {}
        with start_relief(gain):
            for size in (64, 256):
                run = last_json(relight_sweep.main, ["--split", "select", "--size", str(size), "--only", "default"])
                r = run["last"]["rows"][0]
                row[f"default_select_{size}"] = [r["composite_psnr"], r["object_psnr"]]
            swing = last_json(photo_swing.main, ["--label", f"start relief {gain:g}"])["last"]
            row["photo_select"] = {k: swing[k] for k in ("swing_mean", "wrong_signs", "below_0.10", "photos")}
        out[f"g {gain:g}"] = row
    return out


def probe_truth_start() -> dict:
    from _common import row, scenes

    import lasagna.learned as learned
    from lasagna.compose.resample import upsample
    from lasagna.editing import edit

    shipped, out = learned._surface_start, {}
    for size in (64, 256):
        rel, labels = scenes("select", COUNT, 0, size)
        ws = working_size(size, size, SIDE)
        truth = [downsample(rel.layer[i][None].float(), ws) for i in range(COUNT)]
        rows = [
            row(rel, "identity", torch.ones_like(rel.layer).double()),
            row(rel, "truth at 64, bilinear", torch.cat([upsample(t, (size, size)) for t in truth]).double()),
        ]
        for name, start in (("default", None), ("default from the true ratio", truth)):
            layers = []
            for i in range(COUNT):
                if start is not None:
                    learned._surface_start = lambda recipe, x, device, t=start[i]: t.clamp(*recipe.distill.layer.range)
                try:
                    layers.append(edit(rel.base[i].float(), "relight", labels[i]).layer)
                finally:
                    learned._surface_start = shipped
            rows.append(row(rel, name, torch.stack(layers).double()))
        out[f"select_{size}"] = rows
    return out


@contextlib.contextmanager
def t_anneal(final: float | None):
    """Every per-image distillation inside the block draws t ~ U(t_min, t_max(step)) with t_max annealed linearly from
    the preset's t_max to ``final`` over the run's steps (``losses.core.TimestepOptions``; None: as shipped)."""
    import lasagna.distill.per_image as per_image

    shipped = per_image.build_loss

    def build_loss(name, corrective=None, options=None, t_min=0.02, t_max=0.98):
        timesteps = {"anneal": "linear", "t_max_final": final, "anneal_steps": ANNEAL_STEPS}
        return shipped(name, corrective, {**(options or {}), "timesteps": timesteps}, t_min, t_max)

    if final is not None:
        per_image.build_loss = build_loss
    try:
        yield
    finally:
        per_image.build_loss = shipped


ANNEAL_STEPS = 150  # the relight preset's steps: t_max reaches its final value at the last step


def relight_leak(size: int) -> float:
    """The default relight's layer on select's bare walls (every object removed, lit by their own source light, relit
    toward the named lights): its PSNR against its own mean, pooled over the 16 scenes (∞ for a flat layer)."""
    from _common import scenes as relight_scenes

    from lasagna.editing import edit

    rel, labels = relight_scenes("select", COUNT, 0, size, walls=True)
    y = torch.stack([edit(rel.base[i].float(), "relight", labels[i]).layer for i in range(COUNT)]).double()
    return round(psnr(y, y.mean(dim=(1, 2, 3), keepdim=True).expand_as(y)), 2)


def probe_t_anneal(finals: list[float]) -> dict:
    out = {}
    for final in [None, *finals]:
        row = {}
        with t_anneal(final):
            for size in (64, 256):
                run = last_json(relight_sweep.main, ["--split", "select", "--size", str(size), "--only", "default"])
                r = run["last"]["rows"][0]
                row[f"default_select_{size}"] = [r["composite_psnr"], r["object_psnr"]]
                row[f"leak_{size}"] = relight_leak(size)
            swing = last_json(photo_swing.main, ["--label", f"t_max final {final}"])["last"]
            row["photo_select"] = {k: swing[k] for k in ("swing_mean", "wrong_signs", "below_0.10", "photos")}
        name = "shipped" if final is None else f"t_max 0.98 → {final:g}"
        out[name] = row
        print(json.dumps({name: row}), flush=True)
    return out


def _posterior_ratio(prior, comp: torch.Tensor, base: torch.Tensor, label: str, t_star: float, seed: int):
    """luma(E[x̂₀ | z_t]) / luma(comp): the prior's mean over ``POSTERIOR_DRAWS`` noise draws of ``comp`` (1, 3, s, s)
    noised to ``t_star``, conditioned on ``base`` (the lit input in the same view) and the target light."""
    from lasagna.priors.base import Condition

    k = POSTERIOR_DRAWS
    g = torch.Generator().manual_seed(seed)
    z0 = prior.encode(comp.clamp(0, 1)).expand(k, -1, -1, -1)
    eps = torch.randn(z0.shape, generator=g)
    t = prior.schedule.continuous_to_index(torch.full((k,), float(t_star)))
    z_t = prior.schedule.add_noise(z0, eps, t)
    cond = Condition([label] * k, image=base.expand(k, -1, -1, -1))
    eps_hat = prior.predict(z_t, t, cond, branches=("cond",)).eps["cond"]
    x0 = prior.decode(prior.schedule.x0_from_eps(z_t, eps_hat, t)).clamp(0, 1).mean(0, keepdim=True)
    return luma(x0).clamp_min(POSTERIOR_EPS) / luma(comp).clamp_min(POSTERIOR_EPS)


POSTERIOR_DRAWS = 8
POSTERIOR_EPS = 1e-3  # a black pixel's ratio stays finite (the layer is clamped to its range after)


def probe_posterior_mean(t_stars: list[float], modes: list[str], size: int = 64) -> dict:
    import tempfile
    import types

    import torch.nn.functional as F
    from _common import row, scenes

    import lasagna.learned as learned
    from lasagna.components import load_prior
    from lasagna.distill.objective import resize
    from lasagna.editing import edit
    from lasagna.recipe import LayerSettings

    cfg: dict = {}

    @torch.no_grad()
    def posterior_mean(recipe, x, initial, layer_id, files, device, progress, callback):
        prior = load_prior(recipe.prior, preset=recipe.preset, device=device)
        side = prior.config.resolution
        lo, hi = recipe.distill.layer.range
        r, (h, w) = initial.float(), x.shape[-2:]
        if cfg["mode"] in ("whole", "both"):
            view = (side, side)
            c = _posterior_ratio(prior, resize(x * r, view), resize(x, view), recipe.label, cfg["t"], 0)
            r = (r * F.interpolate(c, size=(h, w), mode="bilinear", align_corners=False)).clamp(lo, hi)
        if cfg["mode"] in ("tiles", "both"):
            out = r.clone()
            for i in range(0, h - side + 1, side):
                for j in range(0, w - side + 1, side):
                    tile = (..., slice(i, i + side), slice(j, j + side))
                    c = _posterior_ratio(prior, (x * r)[tile], x[tile], recipe.label, cfg["t"], 1 + i + j)
                    out[tile] = (r[tile] * c).clamp(lo, hi)
            r = out
        settings = LayerSettings(method=recipe.method, optimize=recipe.steps, working_size=recipe.working_size)
        return types.SimpleNamespace(layer=r, history=[], stopped_reason="steps"), settings

    shipped, rows = learned._optimise, []
    rel, labels = scenes("select", COUNT, 0, size)
    learned._optimise = posterior_mean
    tmp = tempfile.TemporaryDirectory()
    try:
        # Below the preset's working size (64), the scenes are made at their own size: at 32, the prior's own view.
        dirs = relight_sweep.preset_variant({"working_size": size}, Path(tmp.name)) if size < 64 else None
        for mode in modes:
            for t_star in t_stars:
                cfg.update(t=t_star, mode=mode)
                layers = [edit(rel.base[i].float(), "relight", labels[i], catalogue_dirs=dirs) for i in range(COUNT)]
                rows.append(
                    row(rel, f"posterior mean, t* {t_star:g}, {mode}", torch.stack([e.layer for e in layers]).double())
                )
                print(json.dumps(rows[-1]), flush=True)
    finally:
        learned._optimise = shipped
        tmp.cleanup()
    return {f"select_{size}": rows}


def probe_denoise(candidate: Path) -> dict:
    from prior_quality import heldout

    from lasagna.priors.evaluate import denoising_error
    from lasagna.priors.unet import UNetPrior

    ts, out = (0.1, 0.25, 0.5, 0.75, 0.9, 0.98), {}
    for split in ("val", "select"):
        x0, labels, cond = heldout("relit", 128, 32, 1, split=split)
        for name, path in (("relit-32", LAYERS / "relit-32"), ("candidate", candidate)):
            prior = UNetPrior.from_pretrained(path).eval()
            with torch.no_grad():
                runs = [denoising_error(prior, x0, labels, cond, ts, seed=s) for s in range(4)]
            out[f"{split}/{name}"] = {str(t): round(sum(r[t] for r in runs) / 4, 6) for t in ts}
            print(json.dumps({f"{split}/{name}": out[f"{split}/{name}"]}), flush=True)
    return out


def probe_told_fit(seed: int) -> dict:
    from relight_candidates import measure
    from surface import scenes as world_scenes

    import lasagna.catalogue as cat
    from lasagna.catalogue import load_preset
    from lasagna.compose.resample import upsample
    from lasagna.editing import edit
    from lasagna.world.tasks import relight_sources, relighting

    sd = load_preset("relight").surface
    net = SurfaceEstimator.from_pretrained(cat.find(sd.told.estimator, "estimator"))
    scene, labels = world_scenes("select", COUNT, seed, 64)
    sources = relight_sources(scene.params)
    rel = relighting(scene, sources)
    names = ("free default", "untold surface layer", "told the fitted light", "told the true light")
    names += ("fitted-told objects, free walls (silhouette)", "fitted-told objects, free walls (true mask)")
    names += ("true-told objects, free walls (silhouette)", "mean of the free default and fitted-told")
    names += ("told the fitted light, unrefined", "mean of the free default and fitted-told, unrefined")
    layers: dict[str, list] = {n: [] for n in names}
    fits = []
    for i in range(COUNT):
        b, label = rel.base[i].float(), labels[i]
        free = edit(b, "relight", label, layer_kind="free").layer[:1]
        untold = edit(b, "relight", label, layer_kind="surface")
        fitted = next(x for x in untold.stack.document.layers if x.id == untold.layer_id).source_light
        fits.append({"true": sources[i], "fitted": fitted})
        told_fit = edit(b, "relight", label, layer_kind="surface", source_light=fitted).layer[:1]
        told_true = edit(b, "relight", label, layer_kind="surface", source_light=sources[i]).layer[:1]
        quick = edit(b, "relight", label, layer_kind="surface", source_light=fitted, optimize=0).layer[:1]
        small = downsample(b[None], working_size(*b.shape[-2:], sd.working_size))
        p = upsample(net.silhouette(small, sd.symmetry), tuple(b.shape[-2:])).clamp(0, 1)[0]
        m = scene.mask[i].float()
        for name, y in zip(
            names,
            (
                free,
                untold.layer[:1],
                told_fit,
                told_true,
                p * told_fit + (1 - p) * free,
                m * told_fit + (1 - m) * free,
                p * told_true + (1 - p) * free,
                (free + told_fit) / 2,
                quick,
                (free + quick) / 2,
            ),
            strict=True,
        ):
            layers[name].append(y)
    rows = [measure(n, scene, rel, torch.stack(v), None, 64) for n, v in layers.items()]
    return {f"select_seed{seed}_64": rows, "lights": fits}


FIT_PROFILES = {
    "dome": lambda t: (1 - (1 - t) ** 2).clamp_min(0).sqrt(),
    "cone": lambda t: t,
    "parabola": lambda t: 1 - (1 - t) ** 2,
    "mesa": lambda t: (2 * t).clamp_max(1.0),
    "sqrt": lambda t: t.sqrt(),
}
"""profile-fit's shape family: a height over an object's silhouette as a function of t = d/R (d the distance to the
outline, R its largest value + ½)."""
FIT_TILTS = tuple((a, b) for a in (-0.8, -0.4, 0.0, 0.4, 0.8) for b in (-0.8, -0.4, 0.0, 0.4, 0.8))


def probe_profile_fit(seed: int, tilt: bool) -> dict:
    """Rows for ``--probe profile-fit`` (the module docstring)."""
    scene, labels = surface.scenes("select", COUNT, seed, SIDE)
    sources = relight_sources(scene.params)
    rel = relighting(scene, sources)
    base, target, mask = rel.base.double(), rel.target.clamp(0, 1).double(), scene.mask
    src, tgt = surface.lights_of(sources).double(), surface.lights_of(labels).double()
    before = (psnr(base.clamp(0, 1), target), psnr(base.clamp(0, 1), target, mask))
    b_, _, h_, w_ = base.shape
    # d from the shipped dome, inverted (h = √(R² − (R − d)²), in pixels), as `inflation_profile` reads it
    dome = cs.inflate_regions(scene.object_index).double() * (w_ / 2.0)
    yy, xx = torch.stack(torch.meshgrid(torch.arange(h_), torch.arange(w_), indexing="ij")).double() * 2.0 / w_
    luma = base.mean(1).clamp_min(1e-3).log()
    chosen = {"fitted": torch.zeros(b_, 1, h_, w_, dtype=torch.float64)}
    chosen["ceiling"] = chosen["fitted"].clone()
    chosen["dome"] = chosen["fitted"].clone()
    for b in range(b_):
        for k in scene.object_index[b, 0].unique().tolist():
            if k < 0:
                continue
            inside = scene.object_index[b, 0] == k
            top = dome[b, 0][inside]
            r = (top.max() ** 2 + 0.25).sqrt()
            t = (r - (r * r - top * top).clamp_min(0).sqrt()) / r
            scored = []
            for name, profile in FIT_PROFILES.items():
                for height in surface.ORACLE_HEIGHTS:
                    for slope in FIT_TILTS if tilt else ((0.0, 0.0),):
                        field = torch.zeros(1, 1, h_, w_, dtype=torch.float64)
                        field[0, 0][inside] = profile(t) * height * r * (2.0 / w_)
                        field[0, 0][inside] += slope[0] * xx[inside] + slope[1] * yy[inside]
                        n = cs.normals_from_height(field)
                        shade = cs.lambert(n, src[b : b + 1])
                        residual = luma[b][inside] - shade[0, 0][inside].clamp_min(1e-6).log()
                        composite = (base[b : b + 1] * cs.lambert(n, tgt[b : b + 1]) / shade).clamp(0, 1)
                        wrong = (composite - target[b : b + 1]).pow(2).mean(1)[0][inside].mean()
                        scored.append((float(residual.var(unbiased=False)), float(wrong), name, height, slope, field))
            dome_one = next(c for c in scored if c[2] == "dome" and c[3] == 1.0 and c[4] == (0.0, 0.0))
            for key, pick in (
                ("fitted", min(scored, key=lambda c: c[0])),
                ("ceiling", min(scored, key=lambda c: c[1])),
                ("dome", dome_one),
            ):
                chosen[key][b, 0][inside] = pick[5][0, 0][inside]
    flat = torch.zeros(b_, 3, h_, w_, dtype=torch.float64)
    flat[:, 2] = 1.0

    def gain(normals) -> list[float]:
        composite = (base * cs.lambert(normals, tgt) / cs.lambert(normals, src)).clamp(0, 1)
        return [round(psnr(composite, target) - before[0], 2), round(psnr(composite, target, mask) - before[1], 2)]

    def field_normals(field):
        return torch.where(scene.object_index >= 0, cs.normals_from_height(field), flat)

    return {
        "one-height dome (the issue's oracle)": gain(field_normals(chosen["dome"])),
        "profile fitted per object (analysis by synthesis)": gain(field_normals(chosen["fitted"])),
        "profile chosen per object by the truth (the family's ceiling)": gain(field_normals(chosen["ceiling"])),
        "true normals": gain(scene.normals.double()),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument(
        "--probe",
        choices=(
            "gain-fit",
            "srgb",
            "profile",
            "sirfs",
            "ensemble",
            "symmetric-particles",
            "start-relief",
            "wall-level",
            "truth-start",
            "t-anneal",
            "posterior-mean",
            "denoise",
            "told-fit",
            "profile-fit",
        ),
        required=True,
    )
    p.add_argument("--tilt", action="store_true", help="profile-fit: also a plane of 25 slopes per object")
    p.add_argument("--modes", nargs="+", default=["whole", "tiles", "both"], help="posterior-mean: the corrections")
    p.add_argument("--prior", type=Path, default=None, help="denoise: the candidate prior (a folder)")
    p.add_argument("--size", type=int, default=64, help="posterior-mean: the scenes' size (32: the prior's own)")
    p.add_argument(
        "--finals",
        nargs="+",
        type=float,
        default=None,
        help="t-anneal: t_max's final values (0.5 0.3); posterior-mean: t* (0.2 … 0.9)",
    )
    p.add_argument("--gains", nargs="+", type=float, default=[1.0, 1.5, 2.0, 3.0], help="start-relief")
    p.add_argument("--members", nargs="+", type=Path, default=[LAYERS / "surface-lit-32", LIT], help="ensemble")
    p.add_argument("--seed", type=int, default=0, help="told-fit: the world seed of select's scenes")
    p.add_argument("--default", action="store_true", help="gain-fit: measure the default relight instead")
    args = p.parse_args(argv)
    torch.manual_seed(0)
    if args.probe == "gain-fit":
        rows = probe_gain_fit(args.default)
    elif args.probe == "ensemble":
        rows = probe_ensemble(args.members)
    elif args.probe == "start-relief":
        rows = probe_start_relief(args.gains)
    elif args.probe == "t-anneal":
        rows = probe_t_anneal(args.finals or [0.5, 0.3])
    elif args.probe == "posterior-mean":
        rows = probe_posterior_mean(args.finals or [0.2, 0.4, 0.6, 0.75, 0.9], args.modes, args.size)
    elif args.probe == "denoise":
        if args.prior is None:
            p.error("--probe denoise needs --prior FOLDER")
        rows = probe_denoise(args.prior)
    else:
        probes = {"srgb": probe_srgb, "profile": probe_profile, "sirfs": probe_sirfs}
        probes.update({"symmetric-particles": probe_symmetric_particles, "wall-level": probe_wall_level})
        probes["truth-start"] = probe_truth_start
        probes["told-fit"] = lambda: probe_told_fit(args.seed)
        probes["profile-fit"] = lambda: probe_profile_fit(args.seed, args.tilt)
        rows = probes[args.probe]()
    record = {"benchmark": "surface_probes", "probe": args.probe, "default": args.default, "rows": rows}
    print_json_line({**record, "machine": machine_info()})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
