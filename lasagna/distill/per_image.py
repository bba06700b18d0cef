"""Per-image distillation: optimise an edit layer (free per-pixel, or a generator) for B base images.

    result = distill_image(albedo, preset, prior, corrective, condition="left", steps=150, seed=0)
    result.layer, result.composite, result.history, result.settings, result.stopped_reason

The loop (Adam; optional global-norm gradient clipping) minimises ``objective.ScoreObjective`` — the
score loss on the composite plus the scheduled L2 to the identity edit — for all B images at once
(one parameter tensor for B free layers: one batched prior pass per step).

**Images larger than the prior** (LMC-SDS Sec. 5 and supplementary): the first ``whole_fraction``
of the steps score the whole composite downsampled to the prior's size ("this ensures that the whole
image is affected by the loss, but the signal may be blurry"); the remaining steps score random crops
of the prior's size at native resolution ("to prevent the loss from producing fake detail … we lower
the learning rate during this phase through Cosine decay": ``cosine_lr`` over the run). A free layer
lives at native resolution; a generator is fully convolutional. Images whose sides are not both at
least the prior's size use the whole view only; an image of another aspect than the prior's is
letterboxed into its view (``settings.aspect``; ``"stretch"`` resizes it, as settings stored before
the option meant).
A preset sets ``whole_fraction`` (``distill.whole_fraction``): 1 keeps smooth layers off the crops
(the light layer lost 2.6 dB to them at 64²; docs/BENCHMARKS.md#learned-layers).

**Early stopping** (``settings.early_stop``), checked at every step of the last phase once
``min_steps`` steps have run and that phase has 2·``window`` steps of history: stop when both the
score's gradient norm (batch mean of ‖g‖) and the layer's change per unit learning rate (RMS of
y_k − y_{k−1}, over lr_{k−1}, so a decaying rate does not read as convergence) have stopped
decreasing — the mean over the last ``window`` steps is not below (1 − rtol) × the mean over the
``window`` steps before. Score gradients never vanish (they are noisy at every t), so a plateau, not a
zero, is what convergence looks like. The batch stops as a whole.

**Particles** (``settings.particles`` = k > 1, a preset's ``distill.particles``): each image is scored k
times per step in the same batch, each copy a free layer of its own with its own noise and timestep
draws, all starting at the identity edit (or at a given free layer, for a refinement); the result, the
history's layer change and the callback's layer are the mean of the k layers. The score of one noise draw
is a noisy estimate (SDS gradients never vanish), so the mean of k layers carries less of that noise: on
the relight task's heldout split, 4 particles gave +0.35 dB over one run, 8 gave +0.78, and 4 with
t_min 0.1 gave +0.76 (docs/BENCHMARKS.md#relighting-lit-images). One batched pass per step serves all k
copies; it costs about k single runs' time on a CPU.

**Reproducibility.** Every random draw (t, ε, patch positions) comes from one ``torch.Generator``
seeded with ``settings.seed``; the free layer starts at the identity edit (an alpha layer at the base's
own colour with α = 1, whose colour then gets the whole gradient; every other layer at its blend's
identity value) and a given generator is copied (the caller's is not modified), so the same inputs and
seed give the same result.

**Checkpoints** (``checkpoint_dir``): every ``checkpoint_every`` steps one atomic safetensors file
(the layer or generator, Adam's state, the run's ``rng`` state; ``lasagna.io.checkpoint``'s format) and
``history.json`` (written first); ``train_config.json`` records the settings and a hash of the image
and condition, and a folder holding another run is refused. Run again with the same folder after a
kill and the run continues where it was checkpointed, reproducing the uninterrupted run — except
for LMC-SDS with ``fixed_eps`` and no ``fixed_eps_seed``, whose fixed ε is drawn anew on resume.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch
from torch import Tensor, nn
from tqdm.auto import tqdm

from lasagna.atomic import atomic_write_text
from lasagna.distill.adam import Adam
from lasagna.distill.objective import ScoreObjective, build_loss, draw_patches, label_list, prior_image_size
from lasagna.distill.schedules import cosine_lr
from lasagna.distill.settings import DistillSettings, EarlyStop, PatchConfig
from lasagna.errors import LasagnaError
from lasagna.generators.free import FreeLayer, FreeLayerConfig
from lasagna.generators.layer import composite
from lasagna.generators.unet import LayerGenerator
from lasagna.io.checkpoint import (
    CHECKPOINT,
    check_same_run,
    load_checkpoint,
    load_tensors,
    save_checkpoint,
    save_tensors,
)
from lasagna.priors.base import Prior

CHECKPOINT_FORMAT = "lasagna.distill_checkpoint"
HISTORY_FILE = "history.json"
PREVIOUS_FILE = "previous_layer.safetensors"
StopReason = Literal["steps", "converged"]


@dataclass
class DistillResult:
    """What a per-image run produced.

    ``layer`` (B, C, H, W): the edit layer's values, in its range. ``composite`` (B, 3, H, W): the
    base with the layer blended, clamped to [0, 1] once (the document's ``clamp="output"``).
    ``history``: one record per step: step, phase, lr, total, score, reg, w_score, w_reg, grad_norm
    (batch mean of ‖g‖), t_mean, layer_change (RMS change per unit lr; None at the first step),
    time_s (cumulative wall seconds). ``settings``: the resolved settings. ``model``: the optimised
    free layer or generator (eval mode).
    """

    layer: Tensor
    composite: Tensor
    history: list[dict[str, Any]]
    settings: DistillSettings
    stopped_reason: StopReason
    steps: int
    seconds: float
    model: nn.Module


class _RunRecord(DistillSettings):
    """What a checkpoint folder must match to be resumed: the settings, the inputs and the model."""

    base_sha256: str
    labels: tuple[str, ...]
    negative: tuple[str, ...] | None = None
    model_kind: str


def resolve_settings(preset_or_settings, **overrides: Any) -> DistillSettings:
    """``DistillSettings`` from a ``Preset`` (its layer and distill defaults) or from settings, with overrides."""
    if isinstance(preset_or_settings, DistillSettings):
        return preset_or_settings.with_overrides(**overrides)
    if hasattr(preset_or_settings, "distill") and hasattr(preset_or_settings, "blend"):
        return DistillSettings.from_preset(preset_or_settings, **overrides)
    raise LasagnaError(
        f"got {type(preset_or_settings).__name__}; expected a Preset or DistillSettings", "preset_or_settings"
    )


def distill_image(
    base: Tensor,
    preset_or_settings,
    prior: Prior,
    corrective=None,
    *,
    condition: str | Sequence[str],
    negative: str | Sequence[str] | None = None,
    loss: str | None = None,
    guidance: float | None = None,
    steps: int | None = None,
    lr: float | None = None,
    seed: int | None = None,
    generator: Literal["free"] | LayerGenerator | FreeLayer = "free",
    patches: PatchConfig | None = None,
    early_stop: EarlyStop | bool | None = None,
    progress: bool = False,
    checkpoint_dir: str | Path | None = None,
    callback: Callable[[int, Tensor], None] | None = None,
    control: Tensor | None = None,
    **settings_overrides: Any,
) -> DistillResult:
    """Distil the edit layer of ``base`` (B, 3, H, W) or (3, H, W) in [0, 1] (see the module docstring).

    ``preset_or_settings``: a ``Preset`` (layer and distill defaults) or ``DistillSettings``; the
    keywords loss, guidance, steps, lr, seed, patches, early_stop (``False`` disables it, ``True`` the
    default rule) and any other ``DistillSettings`` field in ``settings_overrides`` override it
    (``None`` keeps it). ``condition``: one label, or one per image; ``negative``: the second label
    DDS (source) and NFSD (negative) need (DDS defaults to ``condition``). ``corrective``: b̂ for
    LMC-SDS. ``generator``: ``"free"`` (a per-pixel layer per image), or a ``LayerGenerator`` /
    ``FreeLayer`` to start from (copied, then fine-tuned). Runs on ``base``'s device.
    ``callback(step, layer)``, if given, sees the layer (detached, before that step's update) after
    every step's record is written — how benchmarks trace error against time without a second run.
    ``control`` (B or 1, C, H, W) in [0, 1], aligned with ``base``: the ControlNet's conditioning image
    instead of the base (a depth map, normals, edges), put in the prior's view like the base.
    """
    named = dict(loss=loss, guidance=guidance, steps=steps, lr=lr, seed=seed, patches=patches)
    if isinstance(early_stop, EarlyStop) or early_stop is True:
        named["early_stop"] = early_stop if isinstance(early_stop, EarlyStop) else EarlyStop()
    settings = resolve_settings(preset_or_settings, **settings_overrides, **named)
    if early_stop is False:
        settings = settings.model_copy(update={"early_stop": None})
    base = _check_base(base)
    image_sha = _sha256(base)
    labels = label_list(condition, base.shape[0])
    neg = None if negative is None else label_list(negative, base.shape[0], "negative")
    # Particles: each image k times in the batch (contiguous), each copy with its own noise draws; the layer
    # is their mean (``_mean_particles``), so the score's noise averages out over the copies.
    k = settings.particles
    images = base
    mirrors = settings.particle_mirrors and k > 1
    if k > 1:
        base = base.repeat_interleave(k, dim=0)
        labels = [label for label in labels for _ in range(k)]
        neg = None if neg is None else [label for label in neg for _ in range(k)]
        if control is not None:
            control = control.expand(images.shape[0], -1, -1, -1).repeat_interleave(k, dim=0)
    if mirrors:  # each particle sees the image, its control and its light mirrored (the module docstring)
        base = _mirror_particles(base, k)
        labels = _mirror_labels(labels, k)
        neg = None if neg is None else _mirror_labels(neg, k)
        control = None if control is None else _mirror_particles(control, k)
    b, _, h, w = base.shape
    model = _make_model(generator, settings, base)
    if k > 1 and isinstance(model, FreeLayer) and model.config.batch == b // k:
        model = _tile_free(model, k, mirrors)  # a given start (a refinement): every particle starts from it

    def mean_layer(layer: Tensor) -> Tensor:
        """The particles' layers, each mirrored back, averaged per image."""
        return _mean_particles(_mirror_particles(layer, k) if mirrors else layer, k)

    spec = settings.layer
    weights = settings.resolved_weights()
    objective = ScoreObjective(
        spec,
        prior,
        build_loss(settings.loss, corrective, settings.loss_options, settings.t_min, settings.t_max),
        settings.guidance,
        weights,
        settings.condition_image,
        settings.aspect,
        control=None if control is None else control.to(base.device).expand(b, -1, -1, -1),
    )
    size = prior_image_size(prior)
    patchable = h >= size[0] and w >= size[1] and (h, w) != tuple(size)
    whole_steps = round(settings.patches.whole_fraction * settings.steps) if patchable else settings.steps
    model_in = labels if isinstance(model, LayerGenerator) else None
    opt = Adam(model.parameters(), lr=settings.lr)
    rng = torch.Generator().manual_seed(settings.seed)

    run, save = _Progress(), None
    if checkpoint_dir is not None:
        ckpt_dir = Path(checkpoint_dir)
        record = _RunRecord(
            **settings.model_dump(),
            base_sha256=image_sha,
            labels=tuple(labels),
            negative=None if neg is None else tuple(neg),
            model_kind=_model_kind(model),
        )
        run = _resume(ckpt_dir, record, model, opt, rng, base.device)

        def save(run: _Progress) -> None:
            _write_history(ckpt_dir, run.history, run.stopped, run.prev_layer)
            save_checkpoint(ckpt_dir / CHECKPOINT, CHECKPOINT_FORMAT, run.step, record, model, None, opt, rng)

    def step_fn(step: int, lr: float, phase: str) -> tuple[Tensor, Any]:
        """One optimiser step at ``lr``: (the layer before the update, the objective's output)."""
        for group in opt.param_groups:
            group["lr"] = lr
        layer = model(base, model_in)
        rows = draw_patches(b, (h, w), size, settings.patches.per_step, rng) if phase == "patch" else None
        out = objective(base, layer, labels, rng=rng, step=step, patches=rows, negative=neg)
        opt.zero_grad(set_to_none=True)
        out.total.backward()
        if settings.grad_clip is not None:
            torch.nn.utils.clip_grad_norm_(model.parameters(), settings.grad_clip)
        opt.step()
        return mean_layer(layer.detach()), out

    model.train()
    _step_loop(run, settings, whole_steps, step_fn, save=save, progress=progress, callback=callback)

    model.eval()
    with torch.no_grad():
        final = mean_layer(model(base, model_in).detach())
        comp = composite(images, final, spec).clamp(0.0, 1.0)
    seconds = run.history[-1]["time_s"] if run.history else 0.0
    return DistillResult(
        layer=final,
        composite=comp,
        history=run.history,
        settings=settings,
        stopped_reason=run.stopped or "steps",
        steps=run.step,
        seconds=seconds,
        model=model,
    )


@dataclass
class _Progress:
    """Where a run stands: steps taken, their records, why it stopped (None: it has not), and the previous
    step's layer and lr (for ``layer_change``)."""

    step: int = 0
    history: list[dict[str, Any]] = field(default_factory=list)
    stopped: str | None = None
    prev_layer: Tensor | None = None
    prev_lr: float = 0.0


def _resume(ckpt_dir: Path, record: _RunRecord, model: nn.Module, opt, rng: torch.Generator, device) -> _Progress:
    """Open a checkpoint folder: refuse one holding another run, restore a killed run's model, Adam state,
    ``rng``, history and previous layer (a new folder: step 0)."""
    ckpt_dir.mkdir(parents=True, exist_ok=True)
    check_same_run(ckpt_dir, record)
    run = _Progress()
    if (ckpt_dir / CHECKPOINT).is_file():
        run.step = load_checkpoint(ckpt_dir / CHECKPOINT, CHECKPOINT_FORMAT, model, None, opt, rng, device)
        run.history, run.stopped = _read_history(ckpt_dir, run.step)
        run.prev_layer, run.prev_lr = _read_previous(ckpt_dir, run.history)
    return run


def _step_loop(
    run: _Progress,
    settings: DistillSettings,
    whole_steps: int,
    step_fn: Callable[[int, float, str], tuple[Tensor, Any]],
    *,
    save: Callable[[_Progress], None] | None,
    progress: bool,
    callback: Callable[[int, Tensor], None] | None,
) -> None:
    """Run ``step_fn(step, lr, phase)`` from ``run.step`` until ``settings.steps`` or early stopping, recording
    each step in ``run.history`` (cosine lr; the whole image for ``whole_steps`` steps, then patches) and
    calling ``save`` every ``checkpoint_every`` steps and at the end."""
    clock = time.monotonic() - (run.history[-1]["time_s"] if run.history else 0.0)
    bar = tqdm(total=settings.steps, initial=run.step, desc="distill", disable=not progress, dynamic_ncols=True)
    while run.stopped is None and run.step < settings.steps:
        step = run.step
        phase = "whole" if step < whole_steps else "patch"
        lr_k = cosine_lr(settings.lr, step, settings.steps, settings.lr_final)
        now, out = step_fn(step, lr_k, phase)
        change = None
        if run.prev_layer is not None:
            change = float((now - run.prev_layer).pow(2).mean().sqrt()) / run.prev_lr
        run.prev_layer, run.prev_lr = now, lr_k
        run.history.append(
            {
                "step": step,
                "phase": phase,
                "lr": lr_k,
                **out.summary(),
                "layer_change": change,
                "time_s": round(time.monotonic() - clock, 4),
            }
        )
        if callback is not None:
            callback(step, now)
        run.step += 1
        bar.update(1)
        bar.set_postfix(grad_norm=f"{run.history[-1]['grad_norm']:.3g}")
        if (
            settings.early_stop is not None
            and run.step < settings.steps
            and converged(run.history, settings.early_stop, phase)
        ):
            run.stopped = "converged"
        if save is not None and (
            run.step % settings.checkpoint_every == 0 or run.stopped or run.step == settings.steps
        ):
            save(run)
    bar.close()


def converged(history: list[dict[str, Any]], rule: EarlyStop, phase: str) -> bool:
    """The early-stopping test of the module docstring on ``history`` (records of ``phase`` only)."""
    if len(history) < rule.min_steps:
        return False
    recs = [r for r in history if r["phase"] == phase and r["layer_change"] is not None]
    w = rule.window
    if len(recs) < 2 * w:
        return False
    recent, before = recs[-w:], recs[-2 * w : -w]
    for key in ("grad_norm", "layer_change"):
        now = sum(r[key] for r in recent) / w
        then = sum(r[key] for r in before) / w
        if not (math.isfinite(now) and math.isfinite(then)) or now < (1.0 - rule.rtol) * then:
            return False  # still decreasing (or not a number: keep going, the caller sees it in history)
    return True


# -- helpers ---------------------------------------------------------------------------------------
def _check_base(base: Tensor) -> Tensor:
    if not isinstance(base, Tensor):
        raise LasagnaError(f"base is a {type(base).__name__}; expected a tensor (B, 3, H, W) in [0, 1]", "base")
    if base.dim() == 3:
        base = base.unsqueeze(0)
    if base.dim() != 4 or base.shape[1] != 3 or not base.is_floating_point():
        raise LasagnaError(
            f"base has shape {tuple(base.shape)} and dtype {base.dtype}; expected a float (B, 3, H, W) tensor", "base"
        )
    if not bool(torch.isfinite(base).all()):
        raise LasagnaError("base has NaN or infinite values; expected finite values in [0, 1]", "base")
    lo, hi = float(base.min()), float(base.max())
    if lo < 0.0 or hi > 1.0:
        raise LasagnaError(f"base has values in [{lo:.4g}, {hi:.4g}]; expected [0, 1]", "base")
    return base.detach()


def _make_model(generator, settings: DistillSettings, base: Tensor) -> nn.Module:
    b, _, h, w = base.shape
    if isinstance(generator, str):
        if generator != "free":
            raise LasagnaError(
                f"generator is {generator!r}; expected 'free', a LayerGenerator or a FreeLayer", "generator"
            )
        spec = settings.layer
        if spec.channels == 4 and base.shape[1] == 3:
            # An alpha layer starts as the base's own colour, opaque: the composite is the input exactly, as at
            # α = 0, but the colour gets the whole gradient (at α = 0 it gets α·g = 0, and α only grows where the
            # mid-gray start colour happens to help: the colour preset's α averaged 0.04 after 150 steps and its
            # composites were nearly gray; docs/BENCHMARKS.md#learned-layers).
            start = torch.cat([base, torch.ones_like(base[:, :1])], dim=1)
            return FreeLayer.from_layer(spec, start).to(base.device)
        return FreeLayer(FreeLayerConfig(layer=spec, batch=b, height=h, width=w)).to(base.device)
    if not isinstance(generator, (LayerGenerator, FreeLayer)):
        raise LasagnaError(
            f"generator is a {type(generator).__name__}; expected 'free', a LayerGenerator or a FreeLayer", "generator"
        )
    if generator.spec != settings.layer:
        raise LasagnaError(
            f"the generator makes {generator.spec.model_dump()}; expected the settings' layer "
            f"{settings.layer.model_dump()}",
            "generator",
        )
    return copy.deepcopy(generator).to(base.device)


def _tile_free(model: FreeLayer, k: int, mirrors: bool = False) -> FreeLayer:
    """A free layer of k× the batch whose particles (each image's k contiguous entries) all start at ``model``'s
    (``mirrors``: each mirrored as its particle's image is)."""
    tiled = FreeLayer(model.config.model_copy(update={"batch": model.config.batch * k})).to(model.u.device)
    with torch.no_grad():
        u = model.u.repeat_interleave(k, dim=0)
        tiled.u.copy_(_mirror_particles(u, k) if mirrors else u)
    return tiled


PARTICLE_MIRRORS: tuple[tuple[bool, bool], ...] = ((False, False), (True, False), (False, True), (True, True))
"""(left-right, top-bottom) mirror of particle j (``j % 4``) of a mirror ensemble (``settings.particle_mirrors``)."""


def _mirror_particles(x: Tensor, k: int) -> Tensor:
    """(B·k, C, H, W) with each image's k particles contiguous: particle j mirrored by ``PARTICLE_MIRRORS[j % 4]``
    (an involution, so the same call maps a particle's layer back to its image)."""
    out = []
    for i in range(x.shape[0]):
        lr, tb = PARTICLE_MIRRORS[(i % k) % len(PARTICLE_MIRRORS)]
        dims = [d for d, on in ((-1, lr), (-2, tb)) if on]
        out.append(x[i].flip(dims) if dims else x[i])
    return torch.stack(out)


def _mirror_labels(labels: list[str], k: int) -> list[str]:
    """Each particle's light condition mirrored as its image is (`lasagna.document.condition.mirror_direction`)."""
    from lasagna.document.condition import mirror_direction

    out = []
    for i, label in enumerate(labels):
        lr, tb = PARTICLE_MIRRORS[(i % k) % len(PARTICLE_MIRRORS)]
        try:
            out.append(mirror_direction(label, lr, tb) if lr or tb else label)
        except LasagnaError as e:
            raise LasagnaError(
                f"particle_mirrors needs light conditions; {label!r} is not one", where="particle_mirrors"
            ) from e
    return out


def _mean_particles(layer: Tensor, k: int) -> Tensor:
    """(B·k, C, H, W) layers, each image's k particles contiguous → their mean per image, (B, C, H, W)."""
    if k == 1:
        return layer
    return layer.view(layer.shape[0] // k, k, *layer.shape[1:]).mean(dim=1)


def _model_kind(model: nn.Module) -> str:
    if isinstance(model, FreeLayer):
        return f"free:{_sha256(model.u)}"
    digest = hashlib.sha256()
    for k, v in model.state_dict().items():
        digest.update(k.encode())
        digest.update(_sha256(v).encode())
    return f"generator:{digest.hexdigest()}"


def _sha256(t: Tensor) -> str:
    return hashlib.sha256(t.detach().to("cpu").contiguous().numpy().tobytes()).hexdigest()


def _write_history(folder: Path, history: list[dict[str, Any]], stopped: str | None, prev_layer: Tensor | None) -> None:
    """The history and the last step's layer (for the next step's layer_change), both before the checkpoint."""
    if prev_layer is not None:
        save_tensors(folder / PREVIOUS_FILE, {"layer": prev_layer}, {"step": str(len(history))})
    atomic_write_text(folder / HISTORY_FILE, json.dumps({"stopped": stopped, "history": history}) + "\n")


def _read_previous(folder: Path, history: list[dict[str, Any]]) -> tuple[Tensor | None, float]:
    """The layer of the checkpointed run's last step and its learning rate (None before any step)."""
    if not history:
        return None, 0.0
    tensors, meta = load_tensors(folder / PREVIOUS_FILE)
    if meta.get("step") is None or int(meta["step"]) < len(history):
        raise LasagnaError(f"{PREVIOUS_FILE} is older than the checkpoint; expected it written with it", str(folder))
    # A later file (a kill between it and the checkpoint) holds a later layer: the first change after
    # the resume is then left unmeasured (None), as at a run's first step.
    return (tensors["layer"] if int(meta["step"]) == len(history) else None), history[-1]["lr"]


def _read_history(folder: Path, step: int) -> tuple[list[dict[str, Any]], str | None]:
    """The history up to the checkpointed ``step`` (written before the checkpoint, so never shorter)."""
    path = folder / HISTORY_FILE
    if not path.is_file():
        raise LasagnaError(
            f"{HISTORY_FILE} is missing beside the checkpoint; expected both (delete the folder to start over)",
            str(folder),
        )
    doc = json.loads(path.read_text(encoding="utf-8"))
    history = [r for r in doc["history"] if r["step"] < step]
    if len(history) != step:
        raise LasagnaError(f"{HISTORY_FILE} has {len(history)} steps before step {step}; expected {step}", str(path))
    stopped = doc.get("stopped") if len(doc["history"]) == step else None
    return history, stopped
