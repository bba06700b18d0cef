"""Conditional diffusion priors behind one interface, and a registry users can plug their own into.

``Prior`` (base.py) is the interface the losses call; ``GaussianPrior`` / ``GaussianMixturePrior``
(gaussian.py) are closed-form references; ``UNetPrior`` (unet.py) and ``DiffusersPrior``
(diffusers.py, optional extra) are registered lazily — their modules are imported only when
``get_prior`` asks for them, so ``import lasagna.priors`` never pulls in diffusers.

    register_prior("mine")(MyPrior)      # or as a class decorator; a taken name raises
    get_prior("gaussian")                # -> the class
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import TypeVar

from lasagna.errors import LasagnaError
from lasagna.priors.base import Branch, Condition, NoiseSchedule, Prediction, Prior
from lasagna.priors.gaussian import ExpectedX0Corrective, GaussianMixturePrior, GaussianPrior

__all__ = [
    "Branch",
    "Condition",
    "ExpectedX0Corrective",
    "GaussianMixturePrior",
    "GaussianPrior",
    "NoiseSchedule",
    "Prediction",
    "Prior",
    "available_priors",
    "get_prior",
    "register_prior",
]

P = TypeVar("P", bound=type)

_REGISTRY: dict[str, type] = {}
# name -> "module:attribute", imported on first use (keeps optional dependencies optional).
_LAZY: dict[str, str] = {
    "unet": "lasagna.priors.unet:UNetPrior",
    "diffusers": "lasagna.priors.diffusers:DiffusersPrior",
}


def register_prior(name: str) -> Callable[[P], P]:
    """Class decorator registering a ``Prior`` subclass under ``name``; a name already taken raises."""

    def deco(cls: P) -> P:
        if not (isinstance(cls, type) and issubclass(cls, Prior)):
            raise LasagnaError(f"register_prior({name!r}): expected a Prior subclass, got {cls!r}", "priors")
        if name in _REGISTRY or name in _LAZY:
            taken = _REGISTRY.get(name) or _LAZY[name]
            raise LasagnaError(f"prior name {name!r} is already registered ({taken}); expected a new name", "priors")
        _REGISTRY[name] = cls
        return cls

    return deco


def get_prior(name: str) -> type[Prior]:
    """The ``Prior`` class registered under ``name``."""
    if name in _REGISTRY:
        return _REGISTRY[name]
    if name in _LAZY:
        module, attr = _LAZY[name].split(":")
        cls = getattr(importlib.import_module(module), attr)
        _REGISTRY[name] = cls
        del _LAZY[name]
        return cls
    raise LasagnaError(f"unknown prior {name!r}; expected one of {', '.join(available_priors())}", "priors")


def available_priors() -> list[str]:
    return sorted({*_REGISTRY, *_LAZY})


register_prior("gaussian")(GaussianPrior)
register_prior("gaussian-mixture")(GaussianMixturePrior)
