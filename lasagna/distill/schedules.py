"""Step schedules of distillation: the cosine ramps of the loss weights and the cosine learning-rate decay.

LMC-SDS supplementary ("Image-to-image translation network"): "In the first 20K steps, we use Cosine
scheduling to increase the weight of L_LMC-SDS from 0.1 to 1.0 and decrease the weight of L2
regularization w.r.t. the original image from 1.0 to 0.1" — ``Ramp`` is one such weight and
``Weights`` the pair, ``Weights.lmc_network(steps)`` that recipe over ``steps`` steps. Image editing
("learning rate of 0.02 with Cosine decay of 0.8 over all steps") is ``cosine_lr`` with
``final=0.8``: the rate falls from lr to 0.8·lr along half a cosine (optax's ``alpha``).
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


def cosine_interp(start: float, end: float, frac: float) -> float:
    """start at frac ≤ 0, end at frac ≥ 1, along half a cosine (slow at both ends); the one half-cosine,
    shared by these ramps and the training loop's lr schedule."""
    f = min(max(frac, 0.0), 1.0)
    return end + (start - end) * 0.5 * (1.0 + math.cos(math.pi * f))


class Ramp(BaseModel):
    """A weight that moves from ``start`` to ``end`` over the first ``steps`` steps, then stays at ``end``."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    start: float = Field(ge=0.0)
    end: float = Field(ge=0.0)
    steps: int = Field(0, ge=0, description="Length of the ramp; 0 = the end value from the first step.")
    shape: Literal["cosine", "linear"] = "cosine"

    @classmethod
    def constant(cls, value: float) -> Ramp:
        return cls(start=value, end=value, steps=0)

    def at(self, step: int) -> float:
        if self.steps == 0:
            return float(self.end)
        frac = step / self.steps
        if self.shape == "linear":
            f = min(max(frac, 0.0), 1.0)
            return float(self.start + (self.end - self.start) * f)
        return cosine_interp(self.start, self.end, frac)


class Weights(BaseModel):
    """The weights of the two terms of the distillation objective: the score loss and the L2 to the
    identity edit (``objective.py``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    score: Ramp = Ramp.constant(1.0)
    reg: Ramp = Ramp.constant(0.0)

    @classmethod
    def lmc_network(cls, steps: int, reg_end: float = 0.1) -> Weights:
        """LMC-SDS's network recipe: score 0.1 → 1.0 and L2 1.0 → ``reg_end`` (the paper: 0.1), cosine,
        over ``steps`` steps. ``reg_end=0`` releases the edit fully once the ramp is over (what
        ``lasagna train-layer`` uses: a layer's blend already keeps the content, and a lasting pull to
        the identity edit biased the distilled shading towards 1 — docs/BENCHMARKS.md#learned-layers)."""
        return cls(score=Ramp(start=0.1, end=1.0, steps=steps), reg=Ramp(start=1.0, end=reg_end, steps=steps))

    def at(self, step: int) -> tuple[float, float]:
        """(score weight, regulariser weight) at ``step``."""
        return self.score.at(step), self.reg.at(step)


def cosine_lr(lr: float, step: int, total: int, final: float) -> float:
    """lr · cosine_interp(1, final, step / (total − 1)): lr at the first step, final·lr at the last."""
    return lr * cosine_interp(1.0, final, step / max(total - 1, 1))
