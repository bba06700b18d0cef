"""Saving and loading networks as ``model.safetensors`` + ``config.json``, atomically.

A saved network is a folder::

    mynet/
      config.json         {"format": "lasagna.unet_prior", "version": 1, "config": {...}}
      model.safetensors   the state dict (tensors only; no pickle, so loading runs no code)

``config`` is the pydantic model that rebuilds the network exactly (architecture, schedule,
vocabulary). Each file is written atomically (``lasagna.io.atomic``): a crash leaves the previous
file intact. The weights are written before the config, so a folder whose config.json exists was
complete when that config was written.

``save_tensors`` / ``load_tensors`` store a flat dict of tensors plus string metadata in ONE
safetensors file; training checkpoints use them so that a checkpoint is a single atomic write.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import ClassVar, Mapping, TypeVar

import torch
from pydantic import BaseModel, ValidationError
from safetensors import safe_open
from safetensors.torch import save as _st_save
from torch import nn

from lasagna.errors import LasagnaError
from lasagna.io.atomic import atomic_write_bytes, atomic_write_text

WEIGHTS_NAME = "model.safetensors"
CONFIG_NAME = "config.json"
FORMAT_VERSION = 1

C = TypeVar("C", bound=BaseModel)


def save_tensors(path: str | os.PathLike, tensors: Mapping[str, torch.Tensor], metadata: Mapping[str, str] | None = None) -> None:
    """Write tensors (moved to CPU, made contiguous) and string metadata to one safetensors file, atomically."""
    flat = {k: v.detach().to("cpu").contiguous() for k, v in tensors.items()}
    atomic_write_bytes(path, _st_save(flat, metadata=dict(metadata or {})))


def load_tensors(path: str | os.PathLike, device: str | torch.device = "cpu") -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Read a safetensors file: (tensors, metadata). A missing or corrupt file is a LasagnaError naming it."""
    p = Path(path)
    if not p.is_file():
        raise LasagnaError("file not found; expected a safetensors file", str(p))
    try:
        with safe_open(str(p), framework="pt", device=str(device)) as fh:
            meta = dict(fh.metadata() or {})
            tensors = {k: fh.get_tensor(k) for k in fh.keys()}
    except Exception as exc:  # safetensors raises its own error types for truncated/corrupt headers
        raise LasagnaError(f"cannot read safetensors ({type(exc).__name__}: {exc}); expected an intact file", str(p)) from None
    return tensors, meta


def save_pretrained(directory: str | os.PathLike, module: nn.Module, config: BaseModel, kind: str) -> Path:
    """Write ``module``'s state dict and ``config`` to ``directory`` (created if needed)."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    save_tensors(d / WEIGHTS_NAME, module.state_dict(), {"format": kind, "version": str(FORMAT_VERSION)})
    doc = {"format": kind, "version": FORMAT_VERSION, "config": config.model_dump(mode="json")}
    atomic_write_text(d / CONFIG_NAME, json.dumps(doc, indent=2, ensure_ascii=False) + "\n")
    return d


def read_config(directory: str | os.PathLike, kind: str, model: type[C]) -> C:
    """Parse ``directory/config.json`` into ``model``, checking the format name and version."""
    path = Path(directory) / CONFIG_NAME
    if not path.is_file():
        raise LasagnaError(f"{CONFIG_NAME} not found; expected a folder written by save_pretrained", str(Path(directory)))
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise LasagnaError(f"not valid JSON ({exc})", str(path)) from None
    if not isinstance(doc, dict) or doc.get("format") != kind:
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise LasagnaError(f"format is {got!r}; expected {kind!r}", str(path))
    if doc.get("version") != FORMAT_VERSION:
        raise LasagnaError(f"version is {doc.get('version')!r}; expected {FORMAT_VERSION}", str(path))
    try:
        return model.model_validate(doc.get("config"))
    except ValidationError as exc:
        raise LasagnaError(*describe_validation_error(exc, f"{path}: config")) from None


def describe_validation_error(exc: ValidationError, where: str) -> tuple[str, str]:
    """(message, where) of a pydantic error's first problem, for a one-line LasagnaError."""
    err = exc.errors()[0]
    loc = ".".join(str(x) for x in err["loc"])
    more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
    return err["msg"] + more, f"{where}.{loc}" if loc else where


def load_weights(directory: str | os.PathLike, module: nn.Module, kind: str, device: str | torch.device = "cpu") -> None:
    """Load ``directory/model.safetensors`` into ``module`` strictly (names and shapes must match)."""
    path = Path(directory) / WEIGHTS_NAME
    tensors, meta = load_tensors(path, device)
    if meta.get("format") not in (None, kind):
        raise LasagnaError(f"weights have format {meta.get('format')!r}; expected {kind!r}", str(path))
    load_state_strict(module, tensors, str(path))


def load_state_strict(module: nn.Module, tensors: Mapping[str, torch.Tensor], where: str) -> None:
    """``load_state_dict(strict=True)`` with a one-line error naming missing/unexpected/mis-shaped tensors."""
    own = module.state_dict()
    missing = sorted(set(own) - set(tensors))
    unexpected = sorted(set(tensors) - set(own))
    if missing or unexpected:
        raise LasagnaError(
            f"weights do not match the config: missing {missing[:4]}{'…' if len(missing) > 4 else ''}, "
            f"unexpected {unexpected[:4]}{'…' if len(unexpected) > 4 else ''}; expected exactly the model's {len(own)} tensors",
            where,
        )
    for name, value in own.items():
        if tuple(tensors[name].shape) != tuple(value.shape):
            raise LasagnaError(f"tensor {name} has shape {tuple(tensors[name].shape)}; expected {tuple(value.shape)}", where)
    module.load_state_dict(dict(tensors), strict=True)


class Pretrained:
    """``save_pretrained`` / ``from_pretrained`` for an ``nn.Module`` rebuilt from a pydantic config.

    A subclass sets ``FORMAT`` (the name written into config.json and the weights) and ``CONFIG``
    (its config model) and keeps its config in ``self.config``.
    """

    FORMAT: ClassVar[str]
    CONFIG: ClassVar[type[BaseModel]]

    def save_pretrained(self, directory: str | os.PathLike) -> Path:
        """Write ``model.safetensors`` + ``config.json`` (atomically) to ``directory``."""
        return save_pretrained(directory, self, self.config, self.FORMAT)  # type: ignore[arg-type, attr-defined]

    @classmethod
    def from_pretrained(cls, directory: str | os.PathLike, device: str | torch.device = "cpu", dtype: torch.dtype | None = None):
        """Rebuild the network from its config and load its weights; returned in eval mode."""
        model = cls(read_config(directory, cls.FORMAT, cls.CONFIG))  # type: ignore[call-arg]
        load_weights(directory, model, cls.FORMAT)
        model = model.to(device=device) if dtype is None else model.to(device=device, dtype=dtype)
        return model.eval()
