"""The checkpoint formats: saved networks and training checkpoints, written atomically.

Every tier from the priors up saves and loads its networks here; nothing else reads or writes
safetensors. A saved network is a folder::

    mynet/
      config.json         {"format": "lasagna.unet_prior", "version": 1, "config": {...}}
      model.safetensors   the state dict (tensors only; no pickle, so loading runs no code)

``config`` is the pydantic model that rebuilds the network exactly (architecture, schedule,
vocabulary). Each file is written atomically (``lasagna.atomic``): a crash leaves the previous
file intact. The weights are written before the config, so a folder whose config.json exists was
complete when that config was written.

``save_tensors`` / ``load_tensors`` store a flat dict of tensors plus string metadata in ONE
safetensors file. A **training checkpoint** (``save_checkpoint`` / ``load_checkpoint``) is one such
file: ``model.*`` (the network), ``ema.*`` (its moving average, when kept), ``optim.<i>.<key>`` (Adam's
tensors) and ``rng.train`` (the run's random generator), with ``format``, ``step``, ``config`` (the run's
config as JSON) and Adam's scalars in the metadata: a checkpoint is a single atomic write, so a kill
leaves the previous one intact. A **run folder** records its config in ``train_config.json``
(``check_same_run``), so that resuming with another config is refused.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import ClassVar, TypeVar

import torch
from pydantic import BaseModel, ValidationError
from safetensors import safe_open
from safetensors.torch import save as _st_save
from torch import nn

from lasagna.atomic import atomic_write_bytes, atomic_write_text
from lasagna.errors import LasagnaError, describe_validation_error

WEIGHTS_NAME = "model.safetensors"
CONFIG_NAME = "config.json"
FORMAT_VERSION = 1
CHECKPOINT = "checkpoint.safetensors"  # a run folder's one training checkpoint
RUN_CONFIG = "train_config.json"  # a run folder's config, compared on resume
# Fields that may change between invocations on one run folder: they change neither the random stream
# nor the model (extending ``steps``, a new time budget, other logging cadences).
RESUMABLE = frozenset(
    {"steps", "max_minutes", "progress", "checkpoint_every", "checkpoint_minutes", "log_every", "eval_batches"}
)

C = TypeVar("C", bound=BaseModel)


def save_tensors(
    path: str | os.PathLike, tensors: Mapping[str, torch.Tensor], metadata: Mapping[str, str] | None = None
) -> None:
    """Write tensors (moved to CPU, made contiguous) and string metadata to one safetensors file, atomically."""
    flat = {k: v.detach().to("cpu").contiguous() for k, v in tensors.items()}
    atomic_write_bytes(path, _st_save(flat, metadata=dict(metadata or {})))


def load_tensors(
    path: str | os.PathLike, device: str | torch.device = "cpu"
) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Read a safetensors file: (tensors, metadata). A missing or corrupt file is a LasagnaError naming it."""
    p = Path(path)
    if not p.is_file():
        raise LasagnaError("file not found; expected a safetensors file", str(p))
    try:
        with safe_open(str(p), framework="pt", device=str(device)) as fh:
            meta = dict(fh.metadata() or {})
            tensors = {k: fh.get_tensor(k) for k in fh.keys()}
    except Exception as exc:  # safetensors raises its own error types for truncated/corrupt headers
        raise LasagnaError(
            f"cannot read safetensors ({type(exc).__name__}: {exc}); expected an intact file", str(p)
        ) from None
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
        raise LasagnaError(
            f"{CONFIG_NAME} not found; expected a folder written by save_pretrained", str(Path(directory))
        )
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
        raise describe_validation_error(exc, str(path), prefix="config") from None


def load_weights(
    directory: str | os.PathLike, module: nn.Module, kind: str, device: str | torch.device = "cpu"
) -> None:
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
            f"unexpected {unexpected[:4]}{'…' if len(unexpected) > 4 else ''}; expected exactly the model's "
            f"{len(own)} tensors",
            where,
        )
    for name, value in own.items():
        if tuple(tensors[name].shape) != tuple(value.shape):
            raise LasagnaError(
                f"tensor {name} has shape {tuple(tensors[name].shape)}; expected {tuple(value.shape)}", where
            )
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
    def from_pretrained(
        cls, directory: str | os.PathLike, device: str | torch.device = "cpu", dtype: torch.dtype | None = None
    ):
        """Rebuild the network from its config and load its weights; returned in eval mode."""
        model = cls(read_config(directory, cls.FORMAT, cls.CONFIG))  # type: ignore[call-arg]
        load_weights(directory, model, cls.FORMAT)
        model = model.to(device=device) if dtype is None else model.to(device=device, dtype=dtype)
        return model.eval()


# -- training checkpoints -------------------------------------------------------------------------
def save_checkpoint(
    path: Path, fmt: str, step: int, config: BaseModel, model: nn.Module, ema, opt, rng: torch.Generator
) -> None:
    """Write a training checkpoint (module docstring) to ``path`` atomically."""
    tensors = {f"model.{k}": v for k, v in model.state_dict().items()}
    if ema is not None:
        tensors.update({f"ema.{k}": v for k, v in ema.items()})
    osd = opt.state_dict()
    scalars: dict[str, dict[str, object]] = {}
    for idx, state in osd["state"].items():
        for key, val in state.items():
            if torch.is_tensor(val):
                tensors[f"optim.{idx}.{key}"] = val
            else:
                scalars.setdefault(str(idx), {})[key] = val
    tensors["rng.train"] = rng.get_state()
    meta = {
        "format": fmt,
        "step": str(step),
        "config": config.model_dump_json(),
        "optim.param_groups": json.dumps(osd["param_groups"]),
        "optim.scalars": json.dumps(scalars),
    }
    save_tensors(path, tensors, meta)


def load_checkpoint(path: Path, fmt: str, model: nn.Module, ema, opt, rng: torch.Generator, device) -> int:
    """Restore ``model``, ``ema`` (a state dict updated in place), ``opt`` and ``rng`` from a training
    checkpoint of format ``fmt``; returns its step."""
    tensors, meta = load_tensors(path)
    if meta.get("format") != fmt:
        raise LasagnaError(f"format is {meta.get('format')!r}; expected {fmt!r}", str(path))
    load_state_strict(model, {k[6:]: v for k, v in tensors.items() if k.startswith("model.")}, str(path))
    if ema is not None:
        for k in ema:
            if f"ema.{k}" not in tensors:
                raise LasagnaError(f"checkpoint has no EMA tensor {k}; expected one (ema_decay is set)", str(path))
            ema[k] = tensors[f"ema.{k}"].to(device)
    state: dict[int, dict[str, object]] = {}
    for k, v in tensors.items():
        if k.startswith("optim."):
            _, idx, key = k.split(".", 2)
            state.setdefault(int(idx), {})[key] = v.to(device) if key != "step" else v
    for idx, vals in json.loads(meta.get("optim.scalars", "{}")).items():
        state.setdefault(int(idx), {}).update(vals)
    opt.load_state_dict({"state": state, "param_groups": json.loads(meta["optim.param_groups"])})
    rng.set_state(tensors["rng.train"])
    return int(meta["step"])


def check_same_run(out: Path, config: C) -> None:
    """Record ``config`` in ``out``; refuse to resume a folder trained with a different config
    (fields in ``RESUMABLE`` may differ). Without a checkpoint nothing was trained (a run killed before its
    first one): there is nothing to protect, so any config is accepted and replaces the recorded one."""
    path = out / RUN_CONFIG
    if path.is_file() and (out / CHECKPOINT).is_file():
        try:
            old = type(config).model_validate_json(path.read_text(encoding="utf-8"))
        except ValidationError as exc:
            raise describe_validation_error(exc, str(path)) from None
        a, b = old.model_dump(exclude=set(RESUMABLE)), config.model_dump(exclude=set(RESUMABLE))
        diff = sorted(k for k in a if a[k] != b[k])
        if diff:
            raise LasagnaError(
                f"this folder holds a run with different {', '.join(diff)}; expected the same config to resume "
                "(or a new folder)",
                str(out),
            )
    atomic_write_text(path, config.model_dump_json(indent=2) + "\n")
