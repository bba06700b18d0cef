"""The distillation objective shared by per-image and amortised distillation.

For a base layer x (B, 3, H, W) and the generator's layer y, the composite f(x, y) (the Lasagna
paper's fixed composition function; ``generators.composite``, i.e. the compositor's blend) is
scored by the conditional prior through a score loss (SDS, LMC-SDS, …; ``lasagna.losses``), and an
L2 term keeps the composite near the input:

    L = w_score(step) · S(view(f(x, y)))  +  w_reg(step) · mean((f(x, y) − x)²)

* **Clamp policy: none inside the graph.** f is computed unclamped (``clamp=None``): a clamp would
  give every saturated pixel a zero gradient, so an overshooting multiplier could not be pulled back.
  The prior sees out-of-range values as they are; its score points back towards the image manifold.
* **The view.** The prior works at one resolution (``prior_image_size``). The whole image is
  resized to it ("downsample the optimization state to 128×128 px", LMC-SDS Sec. 5) with area
  averaging (antialiased; bilinear where a side must grow) — an image of another aspect is
  letterboxed (``aspect="letterbox"``: scaled to fit, centred, the rest filled with mid-gray
  ``LETTERBOX_FILL``, which carries no gradient) or stretched (``"stretch"``) — or — the LMC-SDS patch strategy — the
  loss sees random crops of the prior's size at native resolution (``patches``: rows (sample, top,
  left)). Only the crops are composed then (blending is per pixel, so a crop of the composite is
  the composite of the crops).
* **The conditioning image** is the base in the same view (ControlNet-style: what the prior was
  trained to be conditioned on): RGB, or its Rec. 709 luma for a prior with one conditioning channel
  (the colourisation prior), or none for a prior without one (``condition_image="auto"``); or a
  user's ``control`` image (depth, normals, edges: (B, C, H, W) aligned with the base, put in the
  same view — letterboxed or cropped exactly like the base). For DDS the
  source image is the base's view too: the composite of the identity edit.
* **Scales.** S is the loss's surrogate divided by the number of its elements, and the L2 is a mean
  over the same pixels the loss sees (the whole image, or the crops at native resolution), so per
  pixel the two gradients compare as w_score·g (g: the method's gradient, in ε units) against
  w_reg·(f − x), at any image size. The surrogate's value is ½‖g‖², not a quality; report
  ``grad_norm``.
* **Weights** follow ``schedules.Weights`` (the LMC-SDS network recipe: score 0.1 → 1, L2 1 → 0.1).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal

import torch
import torch.nn.functional as F
from torch import Tensor

from lasagna.compose.color import luma
from lasagna.distill.schedules import Weights
from lasagna.errors import ConditionError, LasagnaError
from lasagna.generators.layer import LayerSpec, composite
from lasagna.losses import DDS, LMCSDS, Diagnostics, ScoreLoss, get_loss
from lasagna.priors.base import Condition, Prior

ConditionImage = Literal["auto", "base", "luma", "none"]
# The letterbox bars: mid-gray, the value farthest from both ends of [0, 1], so the prior reads them as a
# flat neutral border rather than as black or white content. They are constants: no gradient reaches them.
LETTERBOX_FILL = 0.5


# -- views -----------------------------------------------------------------------------------------
def prior_image_size(prior: Prior) -> tuple[int, int]:
    """(H, W) of the images the prior scores: its sample shape × the VAE factor of a latent prior."""
    _, h, w = prior.sample_shape
    f = int(getattr(prior, "vae_scale_factor", 1))
    return h * f, w * f


def resize(image: Tensor, size: tuple[int, int]) -> Tensor:
    """(B, C, H, W) → (B, C, *size): area averaging when both sides shrink, else antialiased bilinear."""
    if tuple(image.shape[-2:]) == tuple(size):
        return image
    if image.shape[-2] >= size[0] and image.shape[-1] >= size[1]:
        return F.interpolate(image, size=size, mode="area")
    return F.interpolate(image, size=size, mode="bilinear", align_corners=False, antialias=True)


def letterbox(image: Tensor, size: tuple[int, int]) -> Tensor:
    """(B, C, H, W) → (B, C, *size): scaled to fit inside ``size`` with its aspect kept (``resize``),
    centred, the rest ``LETTERBOX_FILL``."""
    h, w = image.shape[-2:]
    scale = min(size[0] / h, size[1] / w)
    inner = (max(1, min(size[0], round(h * scale))), max(1, min(size[1], round(w * scale))))
    fitted = resize(image, inner)
    top, left = (size[0] - inner[0]) // 2, (size[1] - inner[1]) // 2
    pad = (left, size[1] - inner[1] - left, top, size[0] - inner[0] - top)
    return F.pad(fitted, pad, value=LETTERBOX_FILL) if any(pad) else fitted


def view_of(image: Tensor, size: tuple[int, int], aspect: str = "stretch") -> Tensor:
    """The whole image in the prior's view: ``letterbox`` (aspect kept) or ``stretch`` (``resize``)."""
    return letterbox(image, size) if aspect == "letterbox" else resize(image, size)


def draw_patches(
    batch: int, image_size: tuple[int, int], patch_size: tuple[int, int], per_sample: int, rng: torch.Generator | None
) -> Tensor:
    """(batch·per_sample, 3) long rows (sample, top, left) of uniformly placed crops, sample-major."""
    (h, w), (ph, pw) = image_size, patch_size
    if ph > h or pw > w:
        raise LasagnaError(
            f"patches of {ph}x{pw} do not fit an image of {h}x{w}; expected an image at least the prior's size",
            "patches",
        )
    n = batch * per_sample
    sample = torch.arange(batch).repeat_interleave(per_sample)
    top = torch.randint(0, h - ph + 1, (n,), generator=rng)
    left = torch.randint(0, w - pw + 1, (n,), generator=rng)
    return torch.stack([sample, top, left], dim=1)


def crop(x: Tensor, patches: Tensor, size: tuple[int, int]) -> Tensor:
    """The crops (N, C, *size) of x (B, C, H, W) at ``patches`` rows (sample, top, left)."""
    ph, pw = size
    return torch.stack([x[s, :, t : t + ph, left : left + pw] for s, t, left in patches.tolist()])


def conditioning_image(
    prior: Prior, base_view: Tensor, mode: ConditionImage = "auto", control_view: Tensor | None = None
) -> Tensor | None:
    """The ControlNet-style conditioning image for ``prior`` from the base in the prior's view (or the
    user's control image in that view, when there is one)."""
    if control_view is not None:
        return control_view.detach()
    if mode == "auto":
        channels = getattr(getattr(prior, "config", None), "cond_channels", None)
        if channels is None and hasattr(prior, "control_channels"):  # a diffusers prior: its ControlNets' (0: none)
            channels = sum(prior.control_channels)
        mode = {0: "none", 1: "luma"}.get(channels, "base") if channels is not None else "base"
    if mode == "none":
        return None
    if mode == "luma":
        return luma(base_view).detach()
    return base_view.detach()


def label_list(labels: str | Sequence[str], batch: int, where: str = "condition") -> list[str]:
    """One label per sample from one label or a list of 1 or ``batch`` labels."""
    names = [labels] * batch if isinstance(labels, str) else list(labels)
    if len(names) == 1:
        names = names * batch
    if len(names) != batch:
        raise ConditionError(f"got {len(names)} labels for a batch of {batch}; expected 1 or {batch}", where)
    return names


def build_loss(
    name: str, corrective=None, options: dict[str, Any] | None = None, t_min: float = 0.02, t_max: float = 0.98
) -> ScoreLoss:
    """The score loss ``name`` with t ~ U(t_min, t_max) and extra ``options`` of its Options model.

    ``corrective`` (b̂) is required by ``lmc-sds`` and unused by the other losses. The timestep
    interval is set by ``t_min``/``t_max`` only; ``options["timesteps"]`` may add annealing.
    """
    opts = dict(options or {})
    ts = dict(opts.pop("timesteps", {}) or {})
    if {"t_min", "t_max"} & set(ts):
        raise LasagnaError(
            "set the timestep interval with t_min/t_max, not inside loss_options.timesteps", "loss_options.timesteps"
        )
    opts["timesteps"] = {"t_min": t_min, "t_max": t_max, **ts}
    cls = get_loss(name)
    if cls is LMCSDS:
        return cls(corrective=corrective, options=opts)
    return cls(options=opts)


# -- the objective ---------------------------------------------------------------------------------
@dataclass
class ObjectiveOutput:
    """``total``: the scalar to backpropagate; the parts as floats; per-sample grad norm and t."""

    total: Tensor
    score: float  # S: the surrogate per element (½ mean g²), not a quality
    reg: float  # mean (f(x, y) − x)² over the pixels the loss saw
    w_score: float
    w_reg: float
    grad_norm: Tensor  # (N,) ‖g‖ per view sample (N = B, or B·patches)
    t: Tensor | None  # (N,) integer timesteps
    diagnostics: Diagnostics

    def summary(self) -> dict[str, float]:
        out = {
            "total": float(self.total.detach()),
            "score": self.score,
            "reg": self.reg,
            "w_score": self.w_score,
            "w_reg": self.w_reg,
            "grad_norm": float(self.grad_norm.mean()),
        }
        if self.t is not None:
            out["t_mean"] = float(self.t.double().mean())
        return out


class ScoreObjective:
    """L = w_score·S(view(f(x, y))) + w_reg·L2 (see the module docstring)."""

    def __init__(
        self,
        spec: LayerSpec,
        prior: Prior,
        loss: ScoreLoss,
        guidance: float,
        weights: Weights,
        condition_image: ConditionImage = "auto",
        aspect: str = "stretch",
        control: Tensor | None = None,
    ):
        self.spec, self.prior, self.loss, self.guidance = spec, prior, loss, float(guidance)
        self.weights, self.condition_image, self.aspect = weights, condition_image, aspect
        self.size = prior_image_size(prior)
        self.control = None if control is None else control.detach()  # (B, C, H, W), aligned with the base

    def __call__(
        self,
        base: Tensor,
        layer: Tensor,
        labels: str | Sequence[str],
        *,
        rng: torch.Generator | None,
        step: int,
        patches: Tensor | None = None,
        negative: str | Sequence[str] | None = None,
    ) -> ObjectiveOutput:
        """The objective at ``step`` for base (B, 3, H, W), layer (B, C, H, W) and one label per sample;
        ``patches`` (rows (sample, top, left), ``draw_patches``) selects the patch view."""
        b = base.shape[0]
        if base.dim() != 4 or base.shape[1] != 3:
            raise LasagnaError(f"base has shape {tuple(base.shape)}; expected (B, 3, H, W)", "base")
        if layer.shape[0] != b or tuple(layer.shape[-2:]) != tuple(base.shape[-2:]):
            raise LasagnaError(
                f"layer has shape {tuple(layer.shape)}; expected ({b}, {self.spec.channels}, {base.shape[-2]}, "
                f"{base.shape[-1]})",
                "layer",
            )
        if self.control is not None and (
            self.control.shape[0] != b or tuple(self.control.shape[-2:]) != tuple(base.shape[-2:])
        ):
            raise LasagnaError(
                f"the control image has shape {tuple(self.control.shape)}; expected ({b}, C, {base.shape[-2]}, "
                f"{base.shape[-1]}), aligned with the base",
                "control_image",
            )
        labels = label_list(labels, b)
        negative = None if negative is None else label_list(negative, b, "negative")
        if patches is None:
            comp = composite(base, layer, self.spec)  # (B, 3, H, W), unclamped
            reg = (comp - base).pow(2).mean()
            view, base_view = view_of(comp, self.size, self.aspect), view_of(base, self.size, self.aspect)
            control = None if self.control is None else view_of(self.control, self.size, self.aspect)
        else:
            rows = patches[:, 0].tolist()
            base_p = crop(base, patches, self.size)
            comp = composite(base_p, crop(layer, patches, self.size), self.spec)
            reg = (comp - base_p).pow(2).mean()
            view, base_view = comp, base_p
            control = None if self.control is None else crop(self.control, patches, self.size)
            labels = [labels[i] for i in rows]
            negative = None if negative is None else [negative[i] for i in rows]
        if isinstance(self.loss, DDS):
            self.loss.source_image = base_view.detach()  # the source is the identity edit's composite
            negative = labels if negative is None else negative
        image = conditioning_image(self.prior, base_view, self.condition_image, control)
        cond = Condition(labels, image=image, negative=negative)
        out = self.loss(view, self.prior, cond, self.guidance, rng=rng, step=step)
        score = out.loss / out.diagnostics.grad.numel()
        w_score, w_reg = self.weights.at(step)
        total = w_score * score + w_reg * reg
        return ObjectiveOutput(
            total=total,
            score=float(score.detach()),
            reg=float(reg.detach()),
            w_score=w_score,
            w_reg=w_reg,
            grad_norm=out.diagnostics.grad_norm,
            t=out.diagnostics.t,
            diagnostics=out.diagnostics,
        )
