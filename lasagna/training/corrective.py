"""Training the manifold corrective b̂_ψ on triplets (z, ẑ_t, t) with L_k (LMC-SDS, Sec. 4 and suppl.).

Triplets, as in the paper: z = ``prior.encode(images)`` of clean images from a data source,
t ~ U(t_min, t_max) (default 0.02–0.98, mapped to integer steps), z_t = √ᾱ_t z + √(1 − ᾱ_t) ε and
ẑ_t = the prior's x̂₀-prediction. The branch defaults to the **unconditional** one (null label,
conditioning image kept): the paper writes ẑ_t = z_φ(z_t, t) without y (eq. 7), and L_lmc replaces
the projection term L_proj, which uses the unconditional ε_φ(z_t, t) (eq. 6c). ``branch="cond"`` is
available for experiments. A ``sees_condition`` b̂ is given the sample's conditioning image and
label (whichever branch ẑ_t comes from), as LMC-SDS passes them at use time. L_k (eq. 10) is the
only loss; Adam, lr 1e-4 (the paper's; decay optional: 0.9 every 100 k steps in the paper).

Output folder::

    out_dir/
      train_config.json        the CorrectiveTrainConfig (a resumed run must match it)
      checkpoint.safetensors   ONE atomic file: model, EMA, Adam state, RNG state; step + config in metadata
      log.jsonl                {"step", "lk", "lr", "elapsed_s"} every log_every steps
      corrective/              the final b̂ (EMA weights when enabled): model.safetensors + config.json
      metrics.json             held-out L_k of the trained b̂ and of the trivial b̂ = z, and their ratio

Start again with the same ``out_dir`` after a kill and training continues from the last checkpoint
with the same random stream (every random draw — data, t, ε — comes from one ``rng`` whose state
is checkpointed), so a resumed run reproduces the uninterrupted one. ``max_minutes`` bounds one
invocation; the run then checkpoints and stops, and the next invocation continues.

The data source is a callable ``sample_batch(batch, rng) -> (images in [0, 1] (B, 3, H, W),
label_idx (B,) into the prior's vocabulary, cond_image (B, C, H, W) in [0, 1] or None)``: the world's
scenes (``lasagna.training.prior.world_source``), a folder of the user's images (``image_folder_source``),
or any callable. For a text-conditioned prior of one's own (a diffusers folder) ``unconditional_source``
puts every sample on the null prompt with the image itself as the ControlNet's conditioning image — the
branch L_lmc replaces, conditioned as an edit conditions it (on the base).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
from pydantic import ConfigDict, Field, model_validator

from lasagna.atomic import atomic_write_text
from lasagna.errors import LasagnaError
from lasagna.losses.corrective import Corrective, CorrectiveConfig, TrivialCorrective, lk_loss
from lasagna.priors.base import Condition, Prior
from lasagna.priors.nn import randn
from lasagna.training.loop import LoopConfig, train_loop

Source = Callable[[int, torch.Generator], tuple[torch.Tensor, torch.Tensor, "torch.Tensor | None"]]

CHECKPOINT_FORMAT = "lasagna.corrective_checkpoint"
_EVAL_SEED_OFFSET = 1_000_003  # the held-out batches come from their own rng, never the training one


class CorrectiveTrainConfig(LoopConfig):
    """How b̂ is trained (saved as train_config.json and inside every checkpoint); the loop's
    settings (steps, lr, EMA, checkpoints, time budget, seed) come from ``LoopConfig``."""

    model_config = ConfigDict(extra="forbid")

    corrective: CorrectiveConfig
    batch_size: int = Field(32, ge=1)
    t_min: float = Field(0.02, ge=0.0, le=1.0)
    t_max: float = Field(0.98, ge=0.0, le=1.0)
    branch: Literal["uncond", "cond"] = "uncond"
    eval_batches: int = Field(8, ge=1)

    @model_validator(mode="after")
    def _t_range(self) -> CorrectiveTrainConfig:
        if self.t_min > self.t_max:
            raise ValueError(f"t_min {self.t_min} must be <= t_max {self.t_max}")
        return self


def corrective_config_for(
    prior: Prior, filters: tuple[int, ...] = (32, 64, 128), sees_condition: bool = False, cond_channels: int = 0
) -> CorrectiveConfig:
    """A ``CorrectiveConfig`` matching ``prior`` (channels, resolution, T, vocabulary)."""
    c, h, _ = prior.sample_shape
    return CorrectiveConfig(
        channels=c,
        resolution=h,
        filters=filters,
        num_timesteps=prior.schedule.num_steps,
        sees_condition=sees_condition,
        cond_channels=cond_channels if sees_condition else 0,
        vocabulary=tuple(prior.vocabulary),
    )


@dataclass
class Triplet:
    """One batch of training triplets. ``label`` is the sample's label, which a ``sees_condition`` b̂ is
    given — whichever branch ẑ_t comes from — because that is what LMC-SDS passes it at use time."""

    z: torch.Tensor  # (B, C, h, w) clean, in the prior's space
    t: torch.Tensor  # (B,) integer timesteps
    z_hat: torch.Tensor  # (B, C, h, w) the prior's x̂₀-prediction, float32
    label: torch.Tensor  # (B,)
    image: torch.Tensor | None  # (B, C_cond, H, W) in [0, 1]


def make_triplets(
    prior: Prior,
    source: Source,
    batch: int,
    rng: torch.Generator,
    branch: str,
    t_min: float,
    t_max: float,
    device: torch.device,
    t_range: tuple[int, int] | None = None,
) -> Triplet:
    """Draw clean images, noise them at t ~ U(t_min, t_max), and take the prior's x̂₀ (one network pass).

    ``t_range`` (lo, hi) instead draws integer timesteps uniformly from [lo, hi) (a spectral fit's bucket).
    """
    images, label_idx, cond_image = source(batch, rng)
    if images.dim() != 4 or images.shape[0] != batch:
        raise LasagnaError(f"images have shape {tuple(images.shape)}; expected ({batch}, C, H, W)", "source")
    images, label_idx = images.to(device), label_idx.to(device=device, dtype=torch.long)
    cond_image = cond_image.to(device) if cond_image is not None else None
    sched = prior.schedule
    null = len(prior.vocabulary)
    with torch.no_grad():
        z = prior.encode(images).float()
    if t_range is None:
        u = t_min + (t_max - t_min) * torch.rand((batch,), generator=rng, device=rng.device)
        t = sched.continuous_to_index(u).to(device)
    else:
        t = torch.randint(t_range[0], t_range[1], (batch,), generator=rng, device=rng.device).to(device)
    z_t = sched.add_noise(z, randn(tuple(z.shape), rng, device, z.dtype), t)
    if int(label_idx.min()) < 0 or int(label_idx.max()) > null:
        raise LasagnaError(
            f"label_idx must lie in [0, {null}] (the null index is {null}); got {label_idx.tolist()}", "source"
        )
    labels = [prior.vocabulary[i] if i < null else "" for i in label_idx.tolist()]
    eps = prior.predict(z_t, t, Condition(labels, image=cond_image), branches=(branch,)).eps[branch]
    z_hat = sched.x0_from_eps(z_t, eps.float(), t)
    return Triplet(z=z, t=t, z_hat=z_hat, label=label_idx, image=cond_image)


@torch.no_grad()
def evaluate_lk(model: torch.nn.Module, triplets: list[Triplet]) -> float:
    """Mean L_k of ``model`` over the held-out triplets."""
    total = sum(float(lk_loss(model(tr.z, tr.t, cond_image=tr.image, label_idx=tr.label), tr.z_hat)) for tr in triplets)
    return total / len(triplets)


@dataclass
class TrainResult:
    corrective: (
        torch.nn.Module
    )  # the final b̂ (a Corrective with EMA weights when enabled, or a SpectralCorrective), eval mode
    step: int
    stopped: Literal["done", "time"]
    lk_trained: float
    lk_trivial: float

    @property
    def ratio(self) -> float:
        """L_k(trained) / L_k(b̂ = z) on held-out batches; the issue's target is ≤ 0.5."""
        return self.lk_trained / self.lk_trivial if self.lk_trivial > 0 else math.nan


# -- the loop -----------------------------------------------------------------------------------
def train_corrective(
    prior: Prior,
    source: Source,
    config: CorrectiveTrainConfig,
    out_dir: str | Path,
    device: str | torch.device | None = None,
) -> TrainResult:
    """Train b̂_ψ (or resume training it) in ``out_dir``; see the module docstring."""
    cfg = config
    cc = cfg.corrective
    if cc.channels != prior.sample_shape[0] or cc.num_timesteps != prior.schedule.num_steps:
        raise LasagnaError(
            f"corrective has channels={cc.channels}, num_timesteps={cc.num_timesteps}; expected the prior's "
            f"{prior.sample_shape[0]} and {prior.schedule.num_steps}",
            "config.corrective",
        )
    if cc.sees_condition and tuple(cc.vocabulary) != tuple(prior.vocabulary):
        raise LasagnaError(
            f"corrective vocabulary {list(cc.vocabulary)}; expected the prior's {list(prior.vocabulary)}",
            "config.corrective.vocabulary",
        )
    if device is None:
        p = next(iter(prior.parameters()), None)
        device = p.device if p is not None else torch.device("cpu")
    device = torch.device(device)
    out = Path(out_dir)

    with torch.random.fork_rng(devices=[]):  # a seeded initialisation without touching the global RNG
        torch.manual_seed(cfg.seed)
        model = Corrective(cc)

    # Held-out batches: their own rng, drawn before training, identical across resumes.
    eval_rng = torch.Generator().manual_seed(cfg.seed + _EVAL_SEED_OFFSET)
    held_out = [
        make_triplets(prior, source, cfg.batch_size, eval_rng, cfg.branch, cfg.t_min, cfg.t_max, device)
        for _ in range(cfg.eval_batches)
    ]

    def step_fn(net: torch.nn.Module, rng: torch.Generator, step: int) -> tuple[torch.Tensor, dict[str, float]]:
        tr = make_triplets(prior, source, cfg.batch_size, rng, cfg.branch, cfg.t_min, cfg.t_max, device)
        loss = lk_loss(net(tr.z, tr.t, cond_image=tr.image, label_idx=tr.label), tr.z_hat)
        return loss, {"lk": float(loss.detach())}

    done = train_loop(
        model, step_fn, cfg, cfg, out, checkpoint_format=CHECKPOINT_FORMAT, desc="corrective", device=device
    )
    final, step, stopped = done.model, done.step, done.stopped
    final.save_pretrained(out / "corrective")
    lk_trained = evaluate_lk(final, held_out)
    lk_trivial = evaluate_lk(TrivialCorrective(), held_out)
    result = TrainResult(corrective=final, step=step, stopped=stopped, lk_trained=lk_trained, lk_trivial=lk_trivial)
    ratio = result.ratio if math.isfinite(result.ratio) else None  # strict JSON has no NaN
    metrics = {
        "step": step,
        "stopped": stopped,
        "lk_trained": lk_trained,
        "lk_trivial": lk_trivial,
        "ratio": ratio,
        "held_out_samples": cfg.eval_batches * cfg.batch_size,
    }
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    return result


def fit_spectral(
    prior: Prior,
    source: Source,
    out_dir: str | Path,
    *,
    batch_size: int = 32,
    batches: int = 8,
    buckets: int = 50,
    branch: str = "uncond",
    eval_batches: int = 8,
    t_min: float = 0.02,
    t_max: float = 0.98,
    seed: int = 0,
    device: str | torch.device = "cpu",
) -> TrainResult:
    """Fit the spectral b̂ (``spectral.py``) in closed form and write ``out_dir/corrective`` + metrics.json.

    ``batches`` batches of ``batch_size`` clean images per timestep bucket; held-out L_k against
    b̂ = z on ``eval_batches`` batches from the same random stream as ``train_corrective``'s.
    """
    from lasagna.losses.spectral import SpectralCorrectiveConfig, fit_spectral_corrective

    for name, value in (("batches", batches), ("batch_size", batch_size), ("eval_batches", eval_batches)):
        if value < 1:  # zero batches would "fit" the identity gains and report it as a corrective
            raise LasagnaError(f"{name} is {value}; expected at least 1", f"train-corrective.{name}")
    device = torch.device(device)
    channels, h, w = prior.sample_shape
    T = prior.schedule.num_steps
    config = SpectralCorrectiveConfig(channels=channels, height=h, width=w, buckets=buckets, num_timesteps=T)
    eval_rng = torch.Generator().manual_seed(seed + _EVAL_SEED_OFFSET)
    held_out = [
        make_triplets(prior, source, batch_size, eval_rng, branch, t_min, t_max, device) for _ in range(eval_batches)
    ]
    rng = torch.Generator().manual_seed(seed)

    def draw(k: int):
        lo, hi = -(-k * T // buckets), -(-(k + 1) * T // buckets)  # ceil: exactly the t with t·buckets // T == k
        tr = make_triplets(prior, source, batch_size, rng, branch, t_min, t_max, device, t_range=(lo, hi))
        return tr.z, tr.t, tr.z_hat

    model = fit_spectral_corrective(config, draw, batches)
    out = Path(out_dir)
    model.save_pretrained(out / "corrective")
    result = TrainResult(
        corrective=model,
        step=batches * buckets,
        stopped="done",
        lk_trained=evaluate_lk(model, held_out),
        lk_trivial=evaluate_lk(TrivialCorrective(), held_out),
    )
    ratio = result.ratio if math.isfinite(result.ratio) else None
    metrics = {
        "kind": "spectral",
        "buckets": buckets,
        "fit_images_per_bucket": batches * batch_size,
        "lk_trained": result.lk_trained,
        "lk_trivial": result.lk_trivial,
        "ratio": ratio,
        "held_out_samples": eval_batches * batch_size,
    }
    atomic_write_text(out / "metrics.json", json.dumps(metrics, indent=2) + "\n")
    return result


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp", ".bmp", ".tif", ".tiff")


def image_folder_source(folder: str | Path, size: int, max_pixels: int = 4096 * 4096) -> Source:
    """``sample_batch`` drawing the images of ``folder`` (uniformly, from ``rng``), each centre-cropped to a
    square and resized to ``size``², labels 0 and no conditioning image (see ``unconditional_source``)."""
    import torch.nn.functional as F

    from lasagna.io.image import read_image_file

    files = sorted(f for f in Path(folder).iterdir() if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise LasagnaError(f"has no image ({', '.join(IMAGE_SUFFIXES)}); expected a folder of images", str(folder))
    cache: dict[int, torch.Tensor] = {}

    def image(i: int) -> torch.Tensor:
        if i not in cache:
            x = torch.from_numpy(read_image_file(files[i], max_pixels=max_pixels).color).float()
            x = x.expand(3, -1, -1) if x.shape[0] == 1 else x[:3]
            h, w = x.shape[-2:]
            side = min(h, w)
            top, left = (h - side) // 2, (w - side) // 2
            square = x[None, :, top : top + side, left : left + side]
            cache[i] = F.interpolate(square, size=(size, size), mode="area" if side >= size else "bilinear")[0]
        return cache[i]

    def sample_batch(batch: int, rng: torch.Generator):
        idx = torch.randint(0, len(files), (batch,), generator=rng).tolist()
        return torch.stack([image(i) for i in idx]).clamp(0, 1), torch.zeros(batch, dtype=torch.long), None

    return sample_batch


def unconditional_source(source: Source, null: int, control: bool) -> Source:
    """``source`` with every label the null index ``null`` and, with ``control``, the image itself as the
    conditioning image (else none)."""

    def sample_batch(batch: int, rng: torch.Generator):
        images, _, _ = source(batch, rng)
        return images, torch.full((batch,), null, dtype=torch.long), images if control else None

    return sample_batch
