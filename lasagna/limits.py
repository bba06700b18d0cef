"""The input policy's numbers and the memory budget, in one place (ground floor: every tier may import it).

A hostile file is refused *before* the work it would cause: its cost is estimated from what is cheap
to read (PNG headers, zip directories, JSON sizes) and compared with the limits here.

**Memory budget.** Every command that decodes, renders or encodes estimates its peak from the
document (``estimate_*`` below, bytes of float32 tensors plus the transient buffers of decoding and
encoding) and calls :func:`check_memory` before allocating. The budget is, in order: the innermost
:func:`memory_budget_scope` (the CLI's ``--memory-budget``), the environment variable
``LASAGNA_MEMORY_BUDGET``, else ``DEFAULT_MEMORY_BUDGET``. Sizes are written ``8G``, ``512M``, ``3.5GB``
or a number of bytes.

**JSON.** ``MAX_DOCUMENT_BYTES`` and ``MAX_JSON_DEPTH`` bound a document before and while it is parsed
(Python's parser recurses once per nested bracket; 10⁵ brackets exhaust the stack);
``MAX_INT_DIGITS`` bounds integer literals (CPython refuses > 4300 digits with a ValueError of its own).
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import re
from collections.abc import Iterator

from lasagna.errors import LasagnaError

MEMORY_BUDGET_ENV = "LASAGNA_MEMORY_BUDGET"

# A third of this project's 24 GB machine (docs/DESIGN.md): one command, the OS and a training job fit
# beside it. An 8192² stack of four RGBA layers (4 × 1 GiB of float32) plus its canvas fits; a 16384²
# layer (4 GiB as float32 RGBA, plus decoding) needs the budget raised on purpose.
DEFAULT_MEMORY_BUDGET = 8 * 2**30

# Bytes per value of the tensors layers are decoded into (float32).
FLOAT_BYTES = 4

# stack.json and preset.json are a few kB; a layer stack's JSON of 16 MiB is already ~100 000 layers.
MAX_DOCUMENT_BYTES = 16 * 2**20
# Documents nest ~5 deep (layers → layer → offset); 64 leaves room and stays far from the recursion limit.
MAX_JSON_DEPTH = 64
# Groups nest at most this deep (a top-level group is 1 deep): a layer inside 30 groups is a JSON object 2·30 + 3
# deep and its offset one deeper, 64, so every layer tree the document allows is a stack.json ``validate``
# reads. Paint programs' files nest a few levels.
MAX_GROUP_DEPTH = (MAX_JSON_DEPTH - 4) // 2
# No field of a document needs an integer of more than 12 digits (sides ≤ 32768, seeds < 2⁶³ fit in 19).
MAX_INT_DIGITS = 20

# Compute a document may ask ``lasagna render`` for: per-image steps (every measured run of docs/BENCHMARKS.md
# stops before 600; 10 000 is ~2 minutes at 64² on this CPU) and random crops per step.
MAX_DISTILL_STEPS = 10_000
MAX_CROPS_PER_STEP = 16
# Particles per image (``distill.particles``): each is one more copy of the image in every step's batch.
MAX_PARTICLES = 16
# A layer generator's shape as its config.json may state it: the catalogue's are 4 levels of at most 192
# channels; these bounds keep a hostile config's weights under ~1 GB before anything is allocated.
MAX_GENERATOR_WIDTH = 1024
MAX_GENERATOR_LEVELS = 6
MAX_GENERATOR_BLOCKS = 8
MAX_VOCABULARY = 1024
# Points of one curve of a curves adjustment: Photoshop's dialog takes at most 16 per channel; 64 leaves room for
# other writers while a hostile document's spline (a dense solve, n² values) stays a few kB.
MAX_CURVE_POINTS = 64
# Colour (and opacity) stops of one gradient (a gradient fill, a gradient map): Photoshop's editor holds a few dozen;
# each pixel of a fill searches them, so a hostile document's 10⁶ stops are refused, not searched.
MAX_GRADIENT_STOPS = 64
# Pixels of a pattern layer's tile, as stored and as resampled at its scale: Photoshop's patterns are at most a few
# thousand pixels a side; 4096² bounds the tile (and the float64 copy its resampling holds, 0.5 GB at RGBA) so that a
# hostile 1000 % scale of a large tile is refused from the PNG's header, not allocated.
MAX_PATTERN_PIXELS = 4096 * 4096
# A folder copied into the catalogue (``prior add --corrective``: b̂ is a config.json and a few MB of weights):
# links are never followed, and the copy stops at these, so a crafted folder cannot fill the disk.
MAX_COPY_BYTES = 2**30
MAX_COPY_FILES = 1000

_UNITS = {"": 1, "B": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}
_SIZE = re.compile(r"^\s*([0-9]+(?:\.[0-9]+)?)\s*([KMGT]?)(?:I?B)?\s*$", re.IGNORECASE)

_scoped_budget: contextvars.ContextVar[int | None] = contextvars.ContextVar("lasagna_memory_budget", default=None)


class BudgetError(LasagnaError):
    """A command would need more memory than the budget allows (refused before allocating)."""


def parse_size(text: str, where: str = "memory budget") -> int:
    """``"8G"``, ``"512M"``, ``"3.5GB"``, ``"1GiB"`` or ``"1048576"`` → bytes (binary units)."""
    m = _SIZE.match(str(text))
    if not m:
        raise LasagnaError(f"{text!r} is not a size; expected bytes or a number with K, M, G or T (e.g. 12G)", where)
    value = int(float(m.group(1)) * _UNITS[m.group(2).upper()])
    if value <= 0:
        raise LasagnaError(f"{text!r} is not positive; expected a size above 0 (e.g. 12G)", where)
    return value


def format_size(n: int | float) -> str:
    """Bytes as a short human size: ``12.9 GB`` (binary units, one decimal)."""
    for unit, scale in (("TB", 2**40), ("GB", 2**30), ("MB", 2**20), ("KB", 2**10)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{int(n)} B"


def memory_budget() -> int:
    """The budget in bytes now: the innermost scope, else ``LASAGNA_MEMORY_BUDGET``, else the default."""
    scoped = _scoped_budget.get()
    if scoped is not None:
        return scoped
    env = os.environ.get(MEMORY_BUDGET_ENV)
    if env:
        return parse_size(env, MEMORY_BUDGET_ENV)
    return DEFAULT_MEMORY_BUDGET


@contextlib.contextmanager
def memory_budget_scope(budget: int | str | None) -> Iterator[int]:
    """Run a block under ``budget`` (bytes or a size string; None: leave the budget as it is)."""
    if budget is None:
        yield memory_budget()
        return
    value = budget if isinstance(budget, int) else parse_size(budget)
    token = _scoped_budget.set(value)
    try:
        yield value
    finally:
        _scoped_budget.reset(token)


def check_memory(needed: int, what: str, where: str) -> None:
    """Refuse (``BudgetError``, one line) when ``needed`` bytes exceed the budget."""
    budget = memory_budget()
    if needed > budget:
        raise BudgetError(
            f"{what} needs ~{format_size(needed)}, over the memory budget of {format_size(budget)}; expected a "
            f"smaller input, or raise the budget with --memory-budget or {MEMORY_BUDGET_ENV}",
            where,
        )


def raster_bytes(width: int, height: int, channels: int) -> int:
    """Bytes of a decoded ``channels`` × ``height`` × ``width`` float32 tensor."""
    return int(width) * int(height) * int(channels) * FLOAT_BYTES


def out_of_memory(exc: BaseException, where: str) -> BudgetError:
    """The one line for an allocation that failed anyway (the estimate was short, or the machine is busy)."""
    detail = " ".join(str(exc).split())[:160]
    return BudgetError(
        f"out of memory ({type(exc).__name__}: {detail}); expected a smaller input or more free memory "
        f"(the budget is {format_size(memory_budget())}; see --memory-budget)",
        where,
    )


# What torch's CPU and CUDA allocators say when an allocation fails (a RuntimeError, or its subclass
# torch.OutOfMemoryError), matched here so this module needs no torch.
_OOM_MESSAGES = ("can't allocate memory", "out of memory", "not enough memory")


def is_out_of_memory(exc: BaseException) -> bool:
    """Whether ``exc`` is a failed allocation (``MemoryError``, or torch's allocator's RuntimeError)."""
    if isinstance(exc, MemoryError):
        return True
    return type(exc).__name__ == "OutOfMemoryError" or any(m in str(exc).lower() for m in _OOM_MESSAGES)


__all__ = [
    "DEFAULT_MEMORY_BUDGET",
    "FLOAT_BYTES",
    "MAX_COPY_BYTES",
    "MAX_COPY_FILES",
    "MAX_CROPS_PER_STEP",
    "MAX_DISTILL_STEPS",
    "MAX_DOCUMENT_BYTES",
    "MAX_GENERATOR_BLOCKS",
    "MAX_GENERATOR_LEVELS",
    "MAX_GENERATOR_WIDTH",
    "MAX_GROUP_DEPTH",
    "MAX_VOCABULARY",
    "MAX_INT_DIGITS",
    "MAX_JSON_DEPTH",
    "MEMORY_BUDGET_ENV",
    "BudgetError",
    "check_memory",
    "format_size",
    "is_out_of_memory",
    "memory_budget",
    "memory_budget_scope",
    "out_of_memory",
    "parse_size",
    "raster_bytes",
]
