"""Training the surface estimator (`lasagna.generators.surface`) on the world's truth, under many lights.

The world knows every scene's normals, so the estimator is trained on the quantity a shading layer is made
from: its height field h is turned into normals and **rendered under K random lights per step** (multi-light
supervision: one geometry must shade right under all of them, as multi-view supervision makes one shape fit
every view), compared with the true shading under the same lights::

    L = mean_k ‖S(n̂, l_k) − S(n, l_k)‖²  +  λ_n‖n̂ − n‖²  (+ ‖Ŝ_src − S(n, l_src)‖² + λ_l (1 − l̂_src·l_src) lit)
        (+ λ_s BCE(ŝ, mask), an estimator with a silhouette head: where the objects are, for the dome prior)
        (+ λ_h ‖(h − h̄) − (d − d̄)‖², d the true heights above the wall: what a cast shadow needs, ``height_weight``)

An estimator with a light input (``SurfaceConfig.light_input``) is told its source light on a fraction of the
scenes (``light_given``), jittered (``light_jitter``) as a light fitted to its own first reading would be, and
nothing on the rest: at use it reads an image alone, fits the light, and reads it again with that light.

S = a + (1 − a)·max(0, n·l) (`lasagna.compose.surface.lambert`); lights l_k uniform in azimuth, elevation in
[0°, ``MAX_TRAIN_ELEVATION``]. A ``"lit"`` estimator reads each scene lit by its own random source light
(elevation in the relight range, `lasagna.world.tasks.RELIGHT_ELEVATION`) and also learns that light's shading
Ŝ_src; the light l̂_src fitted to it through the surface (`lasagna.compose.surface.fit_light`) is trained end
to end. With ``stray`` > 0 a lit input may also carry stray illumination (`lasagna.world.stray`: a sky's
gradient, a vignette, a spotlight's pool) that the truth does not: the estimator learns it as paint.

Scenes come from one world split (``train`` by default) and never from ``select``, ``heldout`` or ``far`` at
the benchmarks' seed; every random draw of a step comes from the loop's generator, so a run resumes bit for bit
(`lasagna.training.loop`). ``surface_metrics`` is the measurement the trainer logs and the benchmarks print.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Literal

import torch
from pydantic import ConfigDict, Field

from lasagna.compose.resample import downsample
from lasagna.compose.surface import fit_light, lambert
from lasagna.errors import LasagnaError
from lasagna.generators.surface import MIRRORS, SurfaceConfig, SurfaceEstimator, transpose_normals, view_light
from lasagna.training.loop import LoopConfig, network_from_checkpoint, train_loop
from lasagna.training.tasks import SCENE_RANGE
from lasagna.world.params import WALL_Z, SceneParams, sample_scenes
from lasagna.world.relief import RELIEF_DRAWS, RELIEF_NAMES, RELIEFS
from lasagna.world.scene import Scene, render, with_light
from lasagna.world.splits import SPLITS, check_training_scenes
from lasagna.world.stray import stray_gain
from lasagna.world.tasks import RELIGHT_ELEVATION

CHECKPOINT_FORMAT = "lasagna.surface_run"
REST_SINK = (0.25, 1.0)
"""Range of a resting scene's sink (its objects' centres this many bounding radii in front of the wall; ``rest``):
from a third sunk into the wall to just touching it."""
LOW_KEY_GAIN = (0.08, 0.5)
"""Range of a low-key surface's albedo gain (``low_key``): the world's paint (HSV value 0.55–0.95) times it reaches
0.04–0.48, a photograph's dark backdrop or coat."""
MAX_TRAIN_ELEVATION = 75.0
"""Highest elevation (degrees from the view axis) of the training lights: grazing lights beyond it shade
almost every surface at the ambient floor and say little about shape."""


class SurfaceTrainConfig(LoopConfig):
    """How a surface estimator is trained (saved as train_config.json and inside every checkpoint)."""

    model_config = ConfigDict(extra="forbid")

    net: SurfaceConfig
    batch_size: int = Field(32, ge=1)
    lights: int = Field(3, ge=1, le=16, description="random lights per scene and step (multi-light supervision)")
    normal_weight: float = Field(0.5, ge=0.0, description="λ_n: weight of the normals' own squared error")
    light_weight: float = Field(0.1, ge=0.0, description="λ_l: weight of the source light's cosine error (lit)")
    silhouette_weight: float = Field(
        0.1, ge=0.0, description="λ_s: weight of the silhouette head's cross-entropy against the objects' mask"
    )
    split: str = Field("train", description="world split the training scenes come from")
    init_from: str | None = Field(
        None,
        description="a saved surface estimator (folder) of this run's architecture (at any working size: heights are "
        "in canvas units) whose weights start this run: a second stage, e.g. the shipped estimator continued on the "
        "``wide`` split's generic shapes, or at a larger working size",
    )
    world_seed: int = Field(7, description="seed of the world split (scenes are (split, seed, index))")
    zoom: float = Field(
        1.0,
        ge=1.0,
        le=4.0,
        description="close-ups: each scene is rendered at zoom × the working size and a square window of 1 to zoom "
        "working sizes around one of its object pixels is reduced to the working size, so objects may fill the frame "
        "as in photographs (1: the whole scene, as rendered)",
    )
    stray: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="lit input: the probability that a scene's input carries stray illumination "
        "(lasagna.world.stray: a sky's gradient, a vignette, a spotlight's pool), taught as paint — the truth stays "
        "the scene's own (0: off)",
    )
    light_given: float = Field(
        0.75,
        ge=0.0,
        le=1.0,
        description="an estimator with a light input: the probability that a scene's source light is given to it "
        "(else a zero row, 'not known': the first of its two readings)",
    )
    light_jitter: float = Field(
        10.0,
        ge=0.0,
        le=45.0,
        description="an estimator with a light input: the given light is the true one plus Gaussian noise of this "
        "many degrees per component, renormalised — so it learns to use a light fitted to its own first reading "
        "(median 13° off on select) without trusting it more than such a light deserves",
    )
    relief: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="the probability that a scene whose wall the split drew flat is given relief of one of the "
        "split's relief families instead (`with_relief`): more relief walls than the split draws (0: as drawn)",
    )
    walls_only: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="the probability that a scene is its wall alone (objects removed, relief flat before `relief` "
        "applies: `bare_walls`); 1: every scene (with `relief` 1: every scene a painted wall with relief), the part "
        "of the relight no estimator had learned (docs/BENCHMARKS.md, rounds 16–17)",
    )
    shadows: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="lit input: the probability that a scene's input carries the world's cast shadows under its "
        "source light (`lasagna.world.scene.render`'s exact shadow rays), taught as paint — the truth (normals, the "
        "source light's shading) stays the shadowless contract's; photographs' shade is read as a face turned away "
        "by an estimator that never saw a shadow (docs/BENCHMARKS.md, round 22's P1) (0: off)",
    )
    rest: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="the probability that a scene's objects rest on the wall (`SceneParams.resting`, each scene's "
        "sink drawn uniformly in ``REST_SINK``) instead of floating in front of it as the world samples them: "
        "attached shadows, and a height field above the wall that describes the scene (0: as sampled)",
    )
    low_key: float = Field(
        0.0,
        ge=0.0,
        le=1.0,
        description="the probability that each surface (the wall, each object) is painted dark: its albedo times a "
        "gain drawn uniformly in ``LOW_KEY_GAIN`` (`SceneParams.darkened`) — photographs' low-key backdrops, which "
        "an estimator that saw only the world's light paint reads as relief turned from the light (docs/BENCHMARKS.md"
        ", round 25's probe A) (0: as sampled)",
    )
    height_weight: float = Field(
        0.0,
        ge=0.0,
        description="λ_h: weight of the height field's squared error against the true heights above the wall "
        "(depth − WALL_Z, in the close-up's canvas units), each scene's mean removed from both — the heights a "
        "cast shadow needs, which normals alone leave free across an object's outline (0: off; a height-output "
        "estimator only)",
    )
    scene_bank: int = Field(
        0,
        ge=0,
        description="render this many of the split's scenes once, at the start (at zoom × the working size, where "
        "`render_on` says), and draw every step's batch from them, each turned by a random symmetry of the square "
        "and lit anew (`SceneBank`); 0: fresh scenes every step. The renderer is 90–98 % of a step "
        "(benchmarks/train_throughput.py), so a bank buys steps where rendering bounds them, at the price of fewer "
        "distinct scenes",
    )
    render_on: Literal["device", "cpu"] = Field(
        "device",
        description="where the scenes are rendered: the training device (a GPU renders a batch faster than the "
        "CPU feeds it) or the CPU (the same bits as a CPU run's, whatever the device)",
    )


def random_lights(count: int, rng: torch.Generator, el_range: tuple[float, float]) -> torch.Tensor:
    """(count, 3) unit lights: azimuth uniform in [0, 360°), elevation uniform in ``el_range`` (degrees)."""
    az = torch.rand(count, generator=rng, dtype=torch.float64) * (2 * math.pi)
    lo, hi = (math.radians(e) for e in el_range)
    el = lo + (hi - lo) * torch.rand(count, generator=rng, dtype=torch.float64)
    return torch.stack([el.sin() * az.cos(), el.sin() * az.sin(), el.cos()], 1).float()


def given_lights(source: torch.Tensor, rng: torch.Generator, given: float, jitter: float) -> torch.Tensor:
    """(B, 3): what an estimator with a light input is told of the source lights ``source`` (B, 3) — each, with
    probability ``given``, the light plus Gaussian noise of ``jitter`` degrees (radians of the unit vector's
    components) renormalised, else a zero row ("not known")."""
    noisy = source.double() + math.radians(jitter) * torch.randn(source.shape, generator=rng, dtype=torch.float64)
    noisy = torch.nn.functional.normalize(noisy, dim=1)
    keep = torch.rand(len(source), generator=rng, dtype=torch.float64) < given
    return (noisy * keep[:, None]).to(source.dtype)


def with_relief(params: SceneParams, rng: torch.Generator, probability: float, families: tuple[str, ...]):
    """``params`` with each flat wall given, with ``probability``, relief of one of ``families`` (drawn uniformly,
    its parameters from ``RELIEF_DRAWS`` uniforms of ``rng``, as the split's own sampler draws them); walls the
    split gave relief keep it. Every draw comes from ``rng`` (a resumed run sees the same walls)."""
    if not families:
        raise LasagnaError("this split draws no relief; expected a split with relief families", "relief")
    b = len(params.relief)
    pick = torch.rand(b, generator=rng, dtype=torch.float64)
    family = torch.randint(0, len(families), (b,), generator=rng)
    uniforms = torch.rand(b, RELIEF_DRAWS, generator=rng, dtype=torch.float64).numpy()
    relief, prm = params.relief.clone(), params.relief_params.clone()
    for i in range(b):
        if int(relief[i]) < 0 and float(pick[i]) < probability:
            name = families[int(family[i])]
            relief[i] = RELIEF_NAMES.index(name)
            prm[i] = torch.as_tensor(RELIEFS[name].sample(uniforms[i]), dtype=prm.dtype)
    return replace(params, relief=relief, relief_params=prm)


def close_ups(scene: Scene, side: int, rng: torch.Generator) -> Scene:
    """``scene`` (rendered at a side Z·``side``) as close-ups at ``side``: per scene a square window of a side drawn
    uniformly in [``side``, Z·``side``] pixels, centred on one of its object pixels drawn uniformly (any pixel where
    it has none) and kept inside the image, reduced to ``side`` (antialiased; the normals renormalised; the object
    index by nearest pixel; the depth's heights above the wall in the close-up's canvas units, big / win times the
    scene's, as its normals are unchanged). Every draw comes from ``rng``, so a resumed run sees the same windows."""
    big = int(scene.image.shape[-1])
    out: dict[str, list[torch.Tensor]] = {k: [] for k in _CROPPED}
    for i in range(len(scene)):
        win = int(torch.randint(side, big + 1, (1,), generator=rng))
        pixels = scene.mask[i, 0].flatten().nonzero()[:, 0]
        pick = int(torch.randint(0, max(1, pixels.numel()), (1,), generator=rng))
        at = int(pixels[pick]) if pixels.numel() else int(torch.randint(0, big * big, (1,), generator=rng))
        top = min(max(at // big - win // 2, 0), big - win)
        left = min(max(at % big - win // 2, 0), big - win)
        for name in _CROPPED:
            x = getattr(scene, name)[i : i + 1, :, top : top + win, left : left + win]
            if name == "object_index":
                x = torch.nn.functional.interpolate(x.double(), size=(side, side), mode="nearest").long()
            else:
                x = downsample(x, (side, side))
            if name == "depth":  # the window is the close-up's canvas: heights above the wall scale by big / win
                x = WALL_Z + (x - WALL_Z) * (big / win)
            out[name].append(x)
    cropped = {k: torch.cat(v) for k, v in out.items()}
    cropped["normals"] = torch.nn.functional.normalize(cropped["normals"], dim=1)
    cropped["mask"] = (cropped["mask"] > 0.5).to(cropped["mask"].dtype)
    return replace(scene, **cropped)


_CROPPED = ("albedo", "normals", "shading", "image", "mask", "depth", "object_index")


def estimator_input(
    net: SurfaceConfig,
    scene,
    source: torch.Tensor | None,
    gain: torch.Tensor | None = None,
    shadowed: torch.Tensor | None = None,
) -> torch.Tensor:
    """What the estimator reads of ``scene``: its albedo, or the scene lit by ``source`` (B, 3), times the stray
    illumination ``gain`` (B, 1, H, W; `lasagna.world.stray`) where given, clipped to [0, 1]. Where ``shadowed``
    (B,) is true the input is ``scene.image`` as rendered — under ``source`` with its cast shadows (`shadowed_scenes`)
    — instead of the shadowless Lambert image."""
    if net.input == "albedo":
        return scene.albedo
    if source is None:
        raise LasagnaError("a lit-input estimator needs the source lights", "source")
    image = with_light(scene, source).image
    if shadowed is not None:
        image = torch.where(shadowed.to(image.device).view(-1, 1, 1, 1), scene.image.to(image.dtype), image)
    return image if gain is None else (image * gain).clamp(0.0, 1.0)


def surface_loss(
    net: SurfaceEstimator,
    config: SurfaceTrainConfig,
    scene,
    source: torch.Tensor | None,
    lights: torch.Tensor,
    device: str | torch.device = "cpu",
    gain: torch.Tensor | None = None,
    given: torch.Tensor | None = None,
    shadowed: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """The module docstring's L on one batch: ``scene`` (B scenes), ``source`` (B, 3) their source lights (lit
    input), ``lights`` (K·B, 3) the lights their estimate and truth are compared under (K per scene), ``gain`` the
    stray illumination on the input (lit; the truth is unchanged by it), ``given`` (B, 3) the source lights an
    estimator with a light input reads (zero rows: not known; `given_lights`), ``shadowed`` (B,) the scenes whose input
    carries its cast shadows (`shadowed_scenes`; the truth stays shadowless)."""
    b = len(scene)
    image = estimator_input(config.net, scene, source, gain, shadowed).to(device)
    out = net.outputs(image, None if given is None else given.to(device))
    surface, source_shading = out.surface, out.shading
    normals, truth = net.normals(surface), scene.normals.to(device)
    groups = lights.to(device).split(b)
    shading = sum(torch.nn.functional.mse_loss(lambert(normals, lk), lambert(truth, lk)) for lk in groups)
    shading = shading / len(groups)
    loss = shading + config.normal_weight * torch.nn.functional.mse_loss(normals, truth)
    metrics = {"shading_mse": float(shading.detach())}
    if config.height_weight > 0:
        height_mse = torch.nn.functional.mse_loss(centred(surface), centred(scene.depth.to(device) - WALL_Z))
        loss = loss + config.height_weight * height_mse
        metrics["height_mse"] = float(height_mse.detach())
    if out.silhouette is not None:
        bce = torch.nn.functional.binary_cross_entropy_with_logits(out.silhouette, scene.mask.to(device))
        loss = loss + config.silhouette_weight * bce
        metrics["silhouette_bce"] = float(bce.detach())
    if source_shading is not None and source is not None:
        src = source.to(device)
        source_mse = torch.nn.functional.mse_loss(source_shading, lambert(truth, src))
        cos_err = (1.0 - (fit_light(normals, source_shading) * src).sum(1)).mean()
        loss = loss + source_mse + config.light_weight * cos_err
        metrics.update(source_shading_mse=float(source_mse.detach()), light_cos_err=float(cos_err.detach()))
    return loss, metrics


def centred(height: torch.Tensor) -> torch.Tensor:
    """``height`` (B, 1, H, W) with each scene's mean removed: a height field is known up to a constant."""
    return height - height.mean(dim=(-2, -1), keepdim=True)


def training_scenes(config: SurfaceTrainConfig, rng: torch.Generator) -> SceneParams:
    """One step's scenes: ``batch_size`` consecutive scenes of the split from a random start, some or all made bare
    walls (``walls_only``), flat walls given relief (``relief``), objects moved to rest on the wall (``rest``) and
    surfaces painted dark (``low_key``), every draw from ``rng``."""
    start = int(torch.randint(0, SCENE_RANGE, (1,), generator=rng))
    params = sample_scenes(config.split, config.world_seed, range(start, start + config.batch_size))
    if config.walls_only >= 1.0:
        params = params.walls_only()
    elif config.walls_only > 0.0:
        params = bare_walls(params, torch.rand(len(params), generator=rng) < config.walls_only)
    if config.relief > 0:
        params = with_relief(params, rng, config.relief, SPLITS[config.split].reliefs)
    if config.rest > 0:
        rests = torch.rand(len(params), generator=rng, dtype=torch.float64) < config.rest
        sink = REST_SINK[0] + (REST_SINK[1] - REST_SINK[0]) * torch.rand(
            len(params), generator=rng, dtype=torch.float64
        )
        moved = params.resting(sink)
        params = replace(params, center=torch.where(rests[:, None, None], moved.center, params.center))
    if config.low_key > 0:
        k = params.color.shape[1]
        dark = torch.rand(len(params), k + 1, generator=rng, dtype=torch.float64) < config.low_key
        gain = LOW_KEY_GAIN[0] + (LOW_KEY_GAIN[1] - LOW_KEY_GAIN[0]) * torch.rand(
            len(params), k + 1, generator=rng, dtype=torch.float64
        )
        gain = torch.where(dark, gain, torch.ones_like(gain))
        params = params.darkened(gain[:, k], gain[:, :k])
    return params


def step_scenes(
    config: SurfaceTrainConfig, rng: torch.Generator, device: str | torch.device, bank: SceneBank | None = None
) -> Scene:
    """One training step's scenes, rendered (on ``device``, or the CPU by ``render_on``) at the working size — or at
    ``zoom`` times it and cut to close-ups — or drawn from ``bank``; every draw from ``rng``."""
    side = config.net.working_size
    big = int(round(side * config.zoom))
    if bank is not None:
        scene = bank.draw(config.batch_size, rng)
    else:
        scene = render(training_scenes(config, rng), big, device=render_device(config, device))
    return close_ups(scene, side, rng) if big != side else scene


def shadowed_scenes(
    config: SurfaceTrainConfig, rng: torch.Generator, device: str | torch.device
) -> tuple[Scene, torch.Tensor, torch.Tensor]:
    """One step's scenes for ``config.shadows`` > 0: (scenes, source lights (B, 3), shadowed (B,) bool). The source
    lights are drawn first (elevation in the relight range), the scenes rendered under them with the world's cast
    shadows — at zoom × the working size, then cut to close-ups, so a window's shadows are the whole scene's — and
    each scene's input keeps its shadows with probability ``shadows`` (`estimator_input`); the returned scenes are
    marked shadowless, so `with_light` relights their normals pointwise as for any other scene."""
    source = random_lights(config.batch_size, rng, RELIGHT_ELEVATION)
    shadowed = torch.rand(config.batch_size, generator=rng, dtype=torch.float64) < config.shadows
    side = config.net.working_size
    big = int(round(side * config.zoom))
    where = render_device(config, device)
    scene = render(training_scenes(config, rng), big, light=source.to(where), shadows=True, device=where)
    scene = close_ups(scene, side, rng) if big != side else scene
    return replace(scene, shadows=False), source, shadowed


def render_device(config: SurfaceTrainConfig, device: str | torch.device) -> str | torch.device:
    return device if config.render_on == "device" else "cpu"


def turned(scene: Scene, k: int) -> Scene:
    """``scene`` seen through the ``k``-th symmetry of the square (0–7: ``k`` ≥ 4 transposed, then mirrored as
    ``MIRRORS[k % 4]``, the estimator's own symmetry ensemble): every map moved as pixels, the normals and the light
    turned with them (`transpose_normals`, `view_light`), so the shading stays Lambert's of the turned normals."""
    dims, sign = MIRRORS[k % 4]
    transpose = k >= 4

    def pixels(x: torch.Tensor) -> torch.Tensor:
        x = x.transpose(-1, -2) if transpose else x
        return x.flip(dims) if dims else x

    normals = transpose_normals(scene.normals) if transpose else scene.normals
    normals = normals.flip(dims) * normals.new_tensor(sign).view(1, 3, 1, 1) if dims else normals
    maps = {name: pixels(getattr(scene, name)) for name in _CROPPED if name != "normals"}
    return replace(scene, **maps, normals=normals.contiguous(), light=view_light(scene.light, dims, sign, transpose))


class SceneBank:
    """``config.scene_bank`` scenes of the split rendered once (in chunks of ``batch_size``, at zoom × the working
    size) from a generator of their own (seeded by the run's ``seed``: a resumed run renders the same bank), from
    which each step draws its batch with replacement, turned by one random symmetry of the square (`turned`); the
    step then lights it anew (`surface_loss`), so the light, the supervising lights and the close-up window are
    fresh every step while the geometry and the paint repeat."""

    def __init__(self, config: SurfaceTrainConfig, device: str | torch.device):
        rng = torch.Generator().manual_seed(BANK_SEED + config.seed)
        params = training_scenes(config.model_copy(update={"batch_size": config.scene_bank}), rng)
        big = int(round(config.net.working_size * config.zoom))
        where = render_device(config, device)
        chunk = max(config.batch_size, 1)
        parts = [render(params.select(slice(i, i + chunk)), big, device=where) for i in range(0, len(params), chunk)]
        tensors = {name: torch.cat([getattr(p, name) for p in parts]) for name in (*_CROPPED, "light", "label_index")}
        labels = [label for p in parts for label in p.label]
        self.scenes = replace(parts[0], **tensors, label=labels, params=params)

    def __len__(self) -> int:
        return len(self.scenes)

    def draw(self, count: int, rng: torch.Generator) -> Scene:
        """``count`` scenes drawn uniformly with replacement, turned by one symmetry drawn uniformly."""
        idx = torch.randint(0, len(self), (count,), generator=rng)
        k = int(torch.randint(0, 8, (1,), generator=rng))
        return turned(self.scenes.select(idx.tolist()), k)


BANK_SEED = 7919
"""Offset of a scene bank's generator from the run's seed (a prime, so a bank's draws are not the run's)."""


def step_loss(
    net: SurfaceEstimator,
    config: SurfaceTrainConfig,
    scene: Scene,
    rng: torch.Generator,
    device,
    source: torch.Tensor | None = None,
    shadowed: torch.Tensor | None = None,
):
    """(loss, metrics) of one step on ``scene``: its source lights (lit input; drawn here unless given, as
    `shadowed_scenes` draws them before rendering), the K supervising lights, stray illumination and the lights
    told to a light-reading estimator drawn from ``rng`` (`surface_loss`)."""
    if source is None and config.net.input == "lit":
        source = random_lights(config.batch_size, rng, RELIGHT_ELEVATION)
    lights = random_lights(config.batch_size * config.lights, rng, (0.0, MAX_TRAIN_ELEVATION))
    gain = stray_gain(scene.mask, rng, config.stray) if config.stray > 0 and source is not None else None
    given = None
    if config.net.light_input and source is not None:
        given = given_lights(source, rng, config.light_given, config.light_jitter)
    return surface_loss(net, config, scene, source, lights, device, gain, given, shadowed)


def bare_walls(params: SceneParams, pick: torch.Tensor) -> SceneParams:
    """``params`` with the scenes where ``pick`` (B,) is true made their walls alone: no objects, a flat wall (as
    `SceneParams.walls_only`, per scene)."""
    present, relief = params.present.clone(), params.relief.clone()
    present[pick] = False
    relief[pick] = -1
    return replace(params, present=present, relief=relief)


def train_surface(config: SurfaceTrainConfig, out_dir: str | Path, device: str | torch.device | None = "cpu"):
    """Train (or resume) the estimator in ``out_dir`` on ``device`` (None: CUDA where there is one); the final EMA
    weights go to ``out_dir/surface``."""
    if device is None:
        device = "cuda" if torch.cuda.is_available() else "cpu"
    check_training_scenes(config.split, config.world_seed, "world_seed")
    if config.height_weight > 0 and config.net.output != "height":
        raise LasagnaError(
            f"a height loss needs an estimator that outputs a height field; expected --output height, got "
            f"{config.net.output!r}",
            "height_weight",
        )
    if config.shadows > 0 and (config.net.input != "lit" or config.scene_bank):
        raise LasagnaError(
            f"cast shadows are rendered under each scene's source light: expected a lit-input estimator trained on "
            f"fresh scenes (no --scene-bank), got input {config.net.input!r}, scene bank {config.scene_bank}",
            "shadows",
        )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        estimator = SurfaceEstimator(config.net)
    if config.init_from is not None:
        start = SurfaceEstimator.from_pretrained(config.init_from)
        # The working size is not the architecture: heights are in canvas units, so an estimator trained at one
        # size may be continued at another (a fully convolutional net, the same weights).
        same = {"working_size": config.net.working_size, "light_input": config.net.light_input}
        narrower = start.config.light_input and not config.net.light_input
        if start.config.model_copy(update=same) != config.net or narrower:
            raise LasagnaError(
                f"its estimator config differs from this run's ({start.config} vs {config.net})", config.init_from
            )
        estimator.load_state_dict(widened_state(start, estimator))

    bank = SceneBank(config, device) if config.scene_bank else None

    def step_fn(net: SurfaceEstimator, rng: torch.Generator, step: int):
        if config.shadows > 0:
            scene, source, shadowed = shadowed_scenes(config, rng, device)
            return step_loss(net, config, scene, rng, device, source, shadowed)
        return step_loss(net, config, step_scenes(config, rng, device, bank), rng, device)

    done = train_loop(
        estimator,
        step_fn,
        config,
        config,
        out_dir,
        checkpoint_format=CHECKPOINT_FORMAT,
        desc=f"surface:{config.net.input}",
        device=device,
    )
    final: SurfaceEstimator = done.model  # type: ignore[assignment]
    final.save_pretrained(Path(out_dir) / "surface")
    return final


def widened_state(start: SurfaceEstimator, target: SurfaceEstimator) -> dict[str, torch.Tensor]:
    """``start``'s weights for ``target``, which may read a light besides (``light_input``): the first
    convolution's new input channels start at zero, so the widened estimator answers exactly as ``start`` until
    training teaches it to use the light."""
    state = start.state_dict()
    own = target.state_dict()
    for name, value in state.items():
        if value.shape != own[name].shape:  # only the first convolution's input width may differ
            wide = torch.zeros_like(own[name])
            wide[:, : value.shape[1]] = value
            state[name] = wide
    return state


def estimator_from_checkpoint(path: str | Path, ema: bool = True) -> tuple[SurfaceEstimator, int]:
    """(estimator, step) from a training checkpoint: its EMA weights (or the raw ones), in eval mode — so a
    run can be measured while it trains."""
    net, step, _ = network_from_checkpoint(
        path, CHECKPOINT_FORMAT, SurfaceTrainConfig, lambda c: SurfaceEstimator(c.net), ema
    )
    return net, step
