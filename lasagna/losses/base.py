"""The ``ScoreLoss`` interface and its registry: every distillation loss is called the same way.

    out = loss(image, prior, cond, guidance, rng=g, step=i)
    out.loss.backward()            # d(out.loss)/d(image) = Jᵀ_encode · the method's gradient
    out.diagnostics.grad_norm      # what to watch: the surrogate's value is ½‖g‖², not a quality

``image`` is the differentiable composite in [0, 1], (B, 3, H, W) — one sample per row, each with
its own timestep, noise and label (a batch may mix conditions). The loss encodes it with
``prior.encode`` (the gradient flows through the encoder, e.g. a VAE), computes the method's
gradient g in the prior's space with the prior in inference mode (nothing reaches the prior's
parameters), applies w(t) and the optional 1/ω scale, and injects g with ``core.inject``.

A subclass implements one method, ``terms(z, t, prior, cond, omega, rng)``, returning the
method's named terms (unweighted) and the noise it drew; the gradient is their sum, times w(t),
times 1/ω when ``scale="inv_guidance"``. Subclasses register under a name:

    @register_loss("mine")
    class Mine(ScoreLoss): ...
    get_loss("sds")(weighting="uniform")      # the class; options as keywords or an Options model
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar, Literal, TypeVar

import torch
from pydantic import BaseModel, ConfigDict, Field

from lasagna.errors import ConditionError, LasagnaError
from lasagna.losses.core import Diagnostics, TimestepOptions, TimestepSampler, Weighting, expand, inject, weight
from lasagna.priors.base import Condition, Prior


class LossOptions(BaseModel):
    """Options shared by every loss (subclasses add their own and change defaults).

    ``weighting``: w(t), see ``core.weight``. ``scale``: ``"inv_guidance"`` multiplies the gradient
    by 1/ω (LMC-SDS Sec. 5, "to be able to ablate ω without changing the gradient magnitude"); it
    needs ω > 0. ``clamp``: optional elementwise clamp of the injected gradient.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    timesteps: TimestepOptions = TimestepOptions()
    weighting: Weighting = "uniform"
    scale: Literal["none", "inv_guidance"] = "none"
    clamp: float | None = Field(None, gt=0.0)


@dataclass
class LossOutput:
    """``loss``: the scalar surrogate to backpropagate; ``diagnostics``: see ``core.Diagnostics``."""

    loss: torch.Tensor
    diagnostics: Diagnostics


@dataclass
class Terms:
    """What ``ScoreLoss.terms`` returns: named gradient terms in the prior's space (B, C, h, w),
    unweighted, whose sum is the method's gradient, and the noise draws by name."""

    components: dict[str, torch.Tensor]
    noise: dict[str, torch.Tensor]


class ScoreLoss(abc.ABC):
    """A score-distillation loss (see the module docstring)."""

    name: ClassVar[str] = "loss"  # set by register_loss
    Options: ClassVar[type[LossOptions]] = LossOptions

    def __init__(self, options: LossOptions | dict | None = None, **overrides):
        if options is None:
            options = self.Options(**overrides)
        elif isinstance(options, dict):
            options = self.Options(**{**options, **overrides})
        else:
            if not isinstance(options, self.Options):
                raise LasagnaError(f"options must be {self.Options.__name__}, got {type(options).__name__}", self.name)
            if overrides:  # re-validate (model_copy(update=) would not)
                options = self.Options(**{**options.model_dump(), **overrides})
        self.options = options
        self.sampler = TimestepSampler(options.timesteps)

    @abc.abstractmethod
    def terms(
        self, z: torch.Tensor, t: torch.Tensor, prior: Prior, cond: Condition, omega: float, rng: torch.Generator | None
    ) -> Terms:
        """The method's named gradient terms for the detached clean z (B, C, h, w) at timesteps t (B,)."""

    def __call__(
        self,
        image: torch.Tensor,
        prior: Prior,
        cond: Condition,
        guidance: float,
        *,
        rng: torch.Generator | None,
        step: int | None = None,
    ) -> LossOutput:
        omega = self._check_guidance(guidance)
        z = self._encode(image, prior)
        b = z.shape[0]
        cond.label_list(b)  # a wrong number of labels fails here, naming the field
        t = self.sampler.sample(b, prior.schedule, rng, device=z.device, step=step)
        terms = self.terms(z.detach(), t, prior, cond, omega, rng)
        factor = weight(prior.schedule, t, self.options.weighting, z.dtype)
        if self.options.scale == "inv_guidance":
            factor = factor / omega
        factor = expand(factor, z)
        components = {k: factor * v.to(z.dtype) for k, v in terms.components.items()}
        grad = sum(components.values())
        loss, diag = inject(z, grad, self.options.clamp, t=t, components=components, noise=terms.noise)
        return LossOutput(loss=loss, diagnostics=diag)

    # -- checks shared by every loss -----------------------------------------------------------
    def _check_guidance(self, guidance: float) -> float:
        try:
            omega = float(guidance)
        except (TypeError, ValueError):
            raise LasagnaError(f"guidance must be a number, got {guidance!r}", f"{self.name}.guidance") from None
        if not math.isfinite(omega):
            raise LasagnaError(f"guidance must be finite, got {omega}", f"{self.name}.guidance")
        if self.options.scale == "inv_guidance" and omega <= 0:
            raise LasagnaError(
                f"scale='inv_guidance' divides by ω, so ω must be > 0; got {omega} (use scale='none' for ω <= 0)",
                f"{self.name}.guidance",
            )
        return omega

    def _encode(self, image: torch.Tensor, prior: Prior) -> torch.Tensor:
        if not isinstance(image, torch.Tensor) or image.dim() != 4:
            shape = tuple(image.shape) if isinstance(image, torch.Tensor) else type(image).__name__
            raise ConditionError(f"expected the composite as a (B, C, H, W) tensor, got {shape}", f"{self.name}.image")
        if not image.is_floating_point():
            raise ConditionError(f"expected a floating-point image in [0, 1], got {image.dtype}", f"{self.name}.image")
        z = prior.encode(image)
        if tuple(z.shape[1:]) != tuple(prior.sample_shape):
            raise ConditionError(
                f"image {tuple(image.shape)} encodes to {tuple(z.shape[1:])} but the prior works at "
                f"{tuple(prior.sample_shape)}; resize or crop patches first",
                f"{self.name}.image",
            )
        return z


# -- registry ---------------------------------------------------------------------------------
L = TypeVar("L", bound=type)
_REGISTRY: dict[str, type[ScoreLoss]] = {}


def register_loss(name: str) -> Callable[[L], L]:
    """Class decorator registering a ``ScoreLoss`` subclass under ``name``; a name already taken raises."""

    def deco(cls: L) -> L:
        if not (isinstance(cls, type) and issubclass(cls, ScoreLoss)):
            raise LasagnaError(f"register_loss({name!r}): expected a ScoreLoss subclass, got {cls!r}", "losses")
        if name in _REGISTRY:
            raise LasagnaError(
                f"loss name {name!r} is already registered ({_REGISTRY[name].__qualname__}); expected a new name",
                "losses",
            )
        cls.name = name
        _REGISTRY[name] = cls
        return cls

    return deco


def get_loss(name: str) -> type[ScoreLoss]:
    """The ``ScoreLoss`` class registered under ``name``. The built-ins (``lasagna.document.preset.LOSS_NAMES``)
    are registered by the package ``lasagna.losses``, which Python imports before this module."""
    if name not in _REGISTRY:
        raise LasagnaError(f"unknown loss {name!r}; expected one of {', '.join(available_losses())}", "losses")
    return _REGISTRY[name]


def available_losses() -> list[str]:
    return sorted(_REGISTRY)
