"""One resumable training loop for every network Lasagna trains (prior, corrective b̂, layer generator).

A run lives in one folder::

    out_dir/
      train_config.json        the run's full config (a resumed run must match it, up to RESUMABLE fields)
      checkpoint.safetensors   ONE atomic file: model, EMA, Adam state, RNG state; step + config in metadata
      log.jsonl                {"step", "loss", ..., "lr", "elapsed_s"} every ``log_every`` steps

Start again with the same ``out_dir`` after a kill and training continues from the last checkpoint
with the same random stream: every random draw of a step (data, t, ε, dropout) must come from the one
``torch.Generator`` the loop passes to ``step_fn``, whose state is checkpointed, so a resumed run
reproduces the uninterrupted one bit for bit. ``max_minutes`` bounds one invocation; the run then
checkpoints and stops, and the next invocation continues. A checkpoint is written every
``checkpoint_every`` steps or ``checkpoint_minutes`` minutes, whichever comes first. The checkpoint's
format and the run folder's config check are ``lasagna.io.checkpoint``'s.
"""

from __future__ import annotations

import copy
import json
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
import torch.distributed as dist
from pydantic import BaseModel, ConfigDict, Field
from tqdm.auto import tqdm

from lasagna.atomic import atomic_write_text, sweep_stale
from lasagna.distill.schedules import cosine_interp
from lasagna.errors import LasagnaError
from lasagna.io.checkpoint import CHECKPOINT, check_same_run, load_checkpoint, save_checkpoint

LOG_FILE = "log.jsonl"

StepFn = Callable[[torch.nn.Module, torch.Generator, int], "tuple[torch.Tensor, dict[str, float]]"]


class LoopConfig(BaseModel):
    """The loop's own settings; embedded (flattened) in each trainer's config."""

    model_config = ConfigDict(extra="forbid")

    steps: int = Field(20_000, ge=1)
    lr: float = Field(1e-4, gt=0.0)
    lr_decay: float = Field(1.0, gt=0.0, le=1.0, description="lr multiplied by this every lr_decay_every steps")
    lr_decay_every: int = Field(100_000, ge=1)
    lr_schedule: Literal["step", "cosine"] = Field(
        "step",
        description="step: × lr_decay every lr_decay_every steps; cosine: from lr to lr·lr_min_ratio over `steps`",
    )
    lr_min_ratio: float = Field(0.0, ge=0.0, le=1.0, description="the cosine schedule's final lr as a fraction of lr")
    warmup_steps: int = Field(0, ge=0, description="linear lr warm-up from 0 over this many steps")
    grad_clip: float | None = Field(None, gt=0.0, description="clip the global gradient norm to this")
    ema_decay: float | None = Field(None, ge=0.0, lt=1.0)
    ema_warmup: bool = Field(
        False,
        description="decay min(ema_decay, (1 + step)/(10 + step)): the average forgets "
        "the initial weights within the run (without it, 0.999^steps of them remain: 22 % after 1 500 steps)",
    )
    checkpoint_every: int = Field(500, ge=1)
    checkpoint_minutes: float | None = Field(
        5.0,
        gt=0.0,
        description="also checkpoint when this many minutes passed since the last one (whichever of this and "
        "checkpoint_every comes first): a kill loses at most this much work however slow the steps",
    )
    log_every: int = Field(10, ge=1)
    max_minutes: float | None = Field(None, gt=0.0)
    seed: int = 0
    progress: bool = True

    def lr_at(self, step: int) -> float:
        warm = min(1.0, (step + 1) / self.warmup_steps) if self.warmup_steps else 1.0
        if self.lr_schedule == "cosine":
            # Anneal to lr·lr_min_ratio at the last step: a diffusion model still gaining at a constant lr
            # (relight-32 at 65 min) gains most from letting the weights settle (SGDR, Loshchilov & Hutter 2017).
            return warm * cosine_interp(self.lr, self.lr * self.lr_min_ratio, step / max(1, self.steps - 1))
        return self.lr * warm * self.lr_decay ** (step // self.lr_decay_every)

    def ema_at(self, step: int) -> float:
        """The EMA decay after optimiser step ``step`` (0-based); TensorFlow's ExponentialMovingAverage
        ``num_updates`` ramp when ``ema_warmup``. A short run needs it: a light prior trained 1 500 steps from
        random weights sampled at 18.5 dB (held-out DDIM-50, ω = 1) with the plain 0.999 average, at 25.2 dB
        with its raw weights — the average still held 22 % of the random start."""
        assert self.ema_decay is not None
        return min(self.ema_decay, (1 + step) / (10 + step)) if self.ema_warmup else self.ema_decay


@dataclass
class LoopResult:
    model: torch.nn.Module  # the final network (EMA weights when enabled), in eval mode
    step: int
    stopped: Literal["done", "time"]


def expected_stop(steps: int, first: int, step: int, elapsed_s: float, max_minutes: float | None) -> int:
    """The step a run is expected to stop at: ``steps``, or sooner where ``max_minutes`` runs out first at the
    rate so far (``step - first`` steps in ``elapsed_s``). The progress bar's total, so that its ETA is the
    budget's: with the total at ``steps`` a 40-minute run of 20 000 slow steps showed an ETA of 158 hours."""
    if max_minutes is None or step <= first or elapsed_s <= 0:
        return steps
    remaining_s = max(0.0, max_minutes * 60 - elapsed_s)
    # The loop starts a step while time is left, so the step in progress when the budget ends is the last one.
    return min(steps, step + math.ceil(remaining_s * (step - first) / elapsed_s))


def trim_log(path: Path, step: int) -> None:
    """Keep only log lines up to the checkpointed step (a killed run may have logged past it; a
    half-written last line is dropped)."""
    if not path.is_file():
        return
    kept = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict) and rec.get("step", math.inf) <= step:
            kept.append(line)
    atomic_write_text(path, "".join(f"{line}\n" for line in kept))


def read_log(out_dir: str | Path) -> list[dict]:
    """The run's log records (for loss curves)."""
    path = Path(out_dir) / LOG_FILE
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def cumulative_seconds(log: list[dict]) -> list[float]:
    """Training wall time at each record, summed over invocations (each resume restarts ``elapsed_s``)."""
    out, offset, last = [], 0.0, 0.0
    for r in log:
        if r["elapsed_s"] < last:  # a new invocation began
            offset += last
        last = r["elapsed_s"]
        out.append(offset + last)
    return out


# -- distributed data parallel -----------------------------------------------------------------
@dataclass(frozen=True)
class DistInfo:
    """Where this process stands: ``rank`` of ``world_size`` (0 of 1 without a process group)."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    initialised_here: bool = False

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def _grouped() -> bool:
    return dist.is_available() and dist.is_initialized()


def dist_info() -> DistInfo:
    """Rank and world size of the initialised process group (0 of 1 when there is none)."""
    if not _grouped():
        return DistInfo()
    return DistInfo(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", dist.get_rank())))


def init_distributed(device: torch.device | str | None = None) -> DistInfo:
    """Join the process group ``torchrun`` describes (``WORLD_SIZE`` > 1 in the environment).

    The backend is nccl for CUDA devices and gloo otherwise. Without torchrun's variables, or with a
    group already initialised, nothing is done. ``initialised_here`` says whether the caller should
    call ``shutdown_distributed`` when done.
    """
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1 or not dist.is_available() or _grouped():
        return dist_info()
    kind = torch.device(device).type if device is not None else ("cuda" if torch.cuda.is_available() else "cpu")
    if kind == "cuda":
        torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
    dist.init_process_group(backend="nccl" if kind == "cuda" else "gloo")
    info = dist_info()
    return DistInfo(info.rank, info.world_size, info.local_rank, initialised_here=True)


def shutdown_distributed(info: DistInfo) -> None:
    """Leave the process group if ``init_distributed`` joined it."""
    if info.initialised_here and _grouped():
        dist.destroy_process_group()


def _all_agree(flag: bool, device: torch.device) -> bool:
    """True on every process iff ``flag`` is true on every process (a no-op without a group)."""
    if not _grouped():
        return flag
    t = torch.tensor([1 if flag else 0], dtype=torch.int32, device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MIN)
    return bool(t.item())


def _mean_over_processes(values: dict[str, float], device: torch.device) -> dict[str, float]:
    """Average logged scalars over the processes (every process logs the same keys)."""
    if not _grouped() or not values:
        return values
    keys = sorted(values)
    t = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64, device=device)
    dist.all_reduce(t)
    t /= dist.get_world_size()
    return dict(zip(keys, t.tolist()))


# -- the loop -----------------------------------------------------------------------------------
def train_loop(
    model: torch.nn.Module,
    step_fn: StepFn,
    loop: LoopConfig,
    run_config: BaseModel,
    out_dir: str | Path,
    *,
    checkpoint_format: str,
    desc: str = "train",
    device: torch.device | str = "cpu",
) -> LoopResult:
    """Train ``model`` with Adam on ``step_fn(model, rng, step) -> (loss, metrics)`` (or resume).

    ``model`` must arrive freshly initialised (seeded by the caller); on resume its weights are replaced
    by the checkpoint's. ``run_config`` is the trainer's whole config: saved beside the checkpoint and
    compared on resume. Under an initialised process group ``step_fn`` receives the
    ``DistributedDataParallel`` wrapper (see the module docstring); checkpoints hold the bare module's
    state, so a run may resume with another number of processes.
    """
    device = torch.device(device)
    info = dist_info()
    out = Path(out_dir)
    error: LasagnaError | None = None
    if info.is_main:
        out.mkdir(parents=True, exist_ok=True)
        try:
            check_same_run(out, run_config)
        except LasagnaError as exc:
            error = exc
        else:
            sweep_stale(out)  # temporaries of a write killed half-way
    if not _all_agree(error is None, device):  # every process stops, not only the one that saw the error
        raise error or LasagnaError("rank 0 refused to resume this run; see its error", str(out))

    model.to(device).train()
    net: torch.nn.Module = model
    if info.world_size > 1:
        from torch.nn.parallel import DistributedDataParallel

        net = DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None)
    opt = torch.optim.Adam(model.parameters(), lr=loop.lr)
    ema = {k: v.detach().clone() for k, v in model.state_dict().items()} if loop.ema_decay is not None else None
    rng = torch.Generator().manual_seed(loop.seed)
    ckpt, log_path = out / CHECKPOINT, out / LOG_FILE
    step = 0
    if ckpt.is_file():
        step = load_checkpoint(ckpt, checkpoint_format, model, ema, opt, rng, device)
        if info.is_main:
            trim_log(log_path, step)
    elif info.is_main and log_path.exists():
        log_path.unlink()

    start, saved_at, stopped, first = time.monotonic(), step, "done", step
    postfix: dict[str, str] = {}
    saved_time = start
    bar = tqdm(
        total=loop.steps, initial=step, desc=desc, disable=not (loop.progress and info.is_main), dynamic_ncols=True
    )
    log = open(log_path, "a", encoding="utf-8") if info.is_main else None
    try:
        while step < loop.steps:
            over = loop.max_minutes is not None and time.monotonic() - start > loop.max_minutes * 60
            if info.world_size > 1:
                over = not _all_agree(not over, device)  # clocks differ: one process out of time stops all
            if over:
                stopped = "time"
                break
            lr = loop.lr_at(step)
            for group in opt.param_groups:
                group["lr"] = lr
            loss, metrics = step_fn(net, rng, step)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            if loop.grad_clip is not None:
                torch.nn.utils.clip_grad_norm_(model.parameters(), loop.grad_clip)
            opt.step()
            if ema is not None:
                decay = loop.ema_at(step)
                with torch.no_grad():
                    for k, v in model.state_dict().items():
                        ema[k].mul_(decay).add_(v.detach(), alpha=1 - decay)
            step += 1
            if loop.max_minutes is not None:  # the budget may stop the run first: the bar's total and ETA follow it
                total = expected_stop(loop.steps, first, step, time.monotonic() - start, loop.max_minutes)
                if total != bar.total:
                    bar.total = total
                    postfix["stops"] = f"{loop.max_minutes:g} min" if total < loop.steps else f"step {loop.steps}"
                    bar.set_postfix(postfix, refresh=False)
            bar.update(1)
            if step % loop.log_every == 0:
                values = _mean_over_processes({"loss": float(loss.detach()), **metrics}, device)
                rec = {
                    "step": step,
                    "loss": values.pop("loss"),
                    **values,
                    "lr": lr,
                    "elapsed_s": round(time.monotonic() - start, 3),
                }
                postfix["loss"] = f"{rec['loss']:.4f}"
                bar.set_postfix(postfix)
                if log is not None:
                    log.write(json.dumps(rec) + "\n")
                    log.flush()
            due = loop.checkpoint_minutes is not None and time.monotonic() - saved_time > loop.checkpoint_minutes * 60
            if step % loop.checkpoint_every == 0 or due:  # only rank 0 writes: the clocks need not agree
                if info.is_main:
                    save_checkpoint(ckpt, checkpoint_format, step, run_config, model, ema, opt, rng)
                saved_at, saved_time = step, time.monotonic()
    finally:
        bar.close()
        if log is not None:
            log.close()
    if info.is_main and (saved_at != step or not ckpt.is_file()):
        save_checkpoint(ckpt, checkpoint_format, step, run_config, model, ema, opt, rng)
    if info.world_size > 1:
        dist.barrier()  # the checkpoint exists for every process once any of them returns

    final = copy.deepcopy(model).eval()
    if ema is not None:
        final.load_state_dict(ema)
    return LoopResult(model=final, step=step, stopped=stopped)


def network_from_checkpoint(path: str | Path, fmt: str, config_model: type[BaseModel], build, ema: bool = True):
    """(network, step, run config) from a training checkpoint of format ``fmt``: ``build(config)`` made from the
    run's config (``config_model``), loaded with the EMA weights (or the raw ones), in eval mode. Lets a run be
    measured while it trains, and snapshots of a run be measured afterwards."""
    from lasagna.io.checkpoint import load_state_strict, load_tensors

    tensors, meta = load_tensors(path)
    if meta.get("format") != fmt:
        raise LasagnaError(f"format is {meta.get('format')!r}; expected {fmt!r}", str(path))
    config = config_model.model_validate_json(meta["config"])
    prefix = "ema." if ema and any(k.startswith("ema.") for k in tensors) else "model."
    net = build(config)
    load_state_strict(net, {k[len(prefix) :]: v for k, v in tensors.items() if k.startswith(prefix)}, str(path))
    return net.eval(), int(meta["step"]), config
