"""A run of adjustment layers baked into one 3D colour lattice, for the banded no-grad forward.

An unmasked, full-canvas adjustment layer of one opacity is a function of the pixel's own colour only:
Cb ↦ clamp(Cb + α(B(Cb, f(Cb)) − Cb)) (``step.py``'s ``_adjusted``, the blend table, the clamp). A run of them is
that function composed, one map [0, 1]³ → [0, 1]³, however many layers the run holds. ``run_lattice`` evaluates the
exact chain (the same torch functions, in float64) on a ``LATTICE``³ grid once (``segment_runs``, which also
checks it) and ``apply_lattice`` reads it
per pixel with trilinear interpolation — one ``grid_sample`` instead of 10–50 eager passes per adjustment.

A lattice is only used where it is accurate. Trilinear interpolation errs most at a cell's centre (for a smooth
map, h²/8 · |f''| per axis) and wherever the map bends sharply inside a cell (a levels gamma's infinite slope at
its black point, a clamp's kink, color balance's steep preserve-luminosity near white); posterize and threshold
are steps. So every lattice is checked when it is baked: the exact chain at every cell centre ((LATTICE − 1)³
points) and at ``CHECK_POINTS`` seeded random colours, against the lattice read there. A run grows one step at a
time while its lattice passes (errs by at most ``LUT_TOLERANCE`` at every check point); the step that fails
starts the next run, or, failing alone, is composited exactly. The check is a measurement, not a proof: a feature
narrower than a cell that no check point meets can still err more (the tests bound the error on random images of
every adjustment type). Everything else stays exact: masked, partial, dissolve, gradient-carrying and lone adjustments,
canvases under ``MIN_PIXELS`` (the bake would cost more than it saves), the output and no-clamp policies (their
canvas may leave [0, 1], the lattice's domain), half-precision canvases, and every autograd path.

Baked lattices are kept (``CACHE_SIZE`` runs, least recently used first out), keyed by what the map depends on:
each step's adjustment fingerprint, blend, opacity, clamps and decoding.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor

from lasagna.compose.blend import KERNELS
from lasagna.compose.plan import PlanStep, RenderPlan
from lasagna.compose.step import _adjusted, _clamp

# Nodes per axis. Trilinear error of a smooth map falls as h² (h = 1/(LATTICE − 1)): measured on the benchmark's ten
# adjustments (opacity 0.8, random colours), 33 nodes erred up to 1.9/255 on the channel mixer's clamp where 65 erred
# 0.95/255. 65³ × 3 float32 is 3.3 MB (the atlas 6.4 MB), baked and checked from 65³ + 64³ exact evaluations.
LATTICE = 65

# The largest difference, at a check point, between a lattice and the exact chain that a render accepts: one 8-bit
# code. Beyond it the run (or the step) is composited exactly.
LUT_TOLERANCE = 1.0 / 255.0

# Seeded random colours checked besides the cell centres (they meet features off the centres).
CHECK_POINTS = 4096

# A lattice is baked only for a render of at least this many canvas pixels (times batch entries). Baking and checking
# evaluate each step of a run twice on 65³ + 64³ + 4096 ≈ 0.54 M float64 colours: ~1.2 s for the benchmark's ten
# adjustments on this box (1 thread), about 2.5 exact renders of them at 2048². It pays from the third render with the
# same parameters (the cache: an editor, a batch) or on canvases several times larger; a smaller canvas renders
# exactly. Tests lower it.
MIN_PIXELS = 1 << 22

# The shortest run worth a lattice: one adjustment's exact pass costs about what a lattice read does.
MIN_RUN = 2

CACHE_SIZE = 16

_cache: OrderedDict[tuple, tuple[Any, Tensor | None]] = OrderedDict()


def fusable(step: PlanStep, plan: RenderPlan) -> bool:
    """Whether ``step`` is a function of the pixel's colour alone that a lattice may stand for (module docstring)."""
    spec = step.spec
    t = spec.tensors
    return (
        spec.adjust is not None
        and step.children is None
        and step.full
        and not spec.requires_grad
        and t.mask is None
        and t.alpha is None
        and spec.blend != "dissolve"
        and spec.opacity_value() is not None
        and plan.clamp == "layer"
        and step.clamp_lo
        and step.clamp_hi
    )


def _key(step: PlanStep) -> tuple:
    spec = step.spec
    return (spec.adjust.fingerprint(), spec.blend, spec.opacity_value(), step.clamp_lo, step.clamp_hi, step.decode)  # type: ignore[union-attr]


def chain(steps: Sequence[PlanStep], C: Tensor) -> Tensor:
    """The exact run on colours ``C (3, 1, n)``: each step's adjustment, blend at its opacity, and clamp."""
    for step in steps:
        op = step.spec.opacity_value()
        a = None if op == 1.0 else op
        C = _clamp(KERNELS[step.blend](C, _adjusted(step, C, C.dtype), a), step)
    return C


def _nodes(n: int) -> Tensor:
    """The lattice's colours as ``(3, 1, n³)``, red slowest, blue fastest (float64)."""
    t = torch.linspace(0.0, 1.0, n, dtype=torch.float64)
    r, g, b = torch.meshgrid(t, t, t, indexing="ij")
    return torch.stack([r, g, b]).reshape(3, 1, n**3)


def _check_colours(n: int) -> Tensor:
    """Every cell centre of an ``n``-node lattice and ``CHECK_POINTS`` seeded random colours, ``(3, 1, m)``."""
    t = (torch.arange(n - 1, dtype=torch.float64) + 0.5) / (n - 1)
    r, g, b = torch.meshgrid(t, t, t, indexing="ij")
    centres = torch.stack([r, g, b]).reshape(3, 1, (n - 1) ** 3)
    rand = torch.rand(3, 1, CHECK_POINTS, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    return torch.cat([centres, rand], dim=-1)


def _atlas(values: Tensor, n: int) -> Tensor:
    """Lattice values ``(3, n, n, n)`` (c, r, g, b) as ``grid_sample``'s 2D image ``(1, 6, n, (n − 1)·n)``: blue
    slice k's (r, g) plane in columns k·n … k·n + n − 1 (x = r, y = g), channels 0–2 slice k and 3–5 slice k + 1,
    so one bilinear read gives both blue neighbours and a lerp finishes the trilinear interpolation."""
    lo = values[..., :-1].permute(0, 2, 3, 1).reshape(3, n, (n - 1) * n)
    hi = values[..., 1:].permute(0, 2, 3, 1).reshape(3, n, (n - 1) * n)
    return torch.cat([lo, hi]).unsqueeze(0)


def apply_lattice(atlas: Tensor, C: Tensor) -> Tensor:
    """Colours ``C (3, h, w)`` in [0, 1] read from ``atlas`` (``_atlas``) with trilinear interpolation."""
    n = atlas.shape[-2]
    C = C.clamp(0.0, 1.0)
    z = C[2] * (n - 1)
    k = z.floor().clamp_max_(n - 2)
    fz = z.sub_(k)  # (h, w)
    grid = torch.empty((1, *C.shape[-2:], 2), dtype=C.dtype, device=C.device)
    # align_corners=True: a pixel coordinate p maps to 2p/(size − 1) − 1. x = k·n + r(n − 1): r = 1 lands on the
    # slice's last column, whose right neighbour (the next slice's first) then has weight 0.
    width = n * (n - 1)
    torch.add(k.mul_(n), C[0], alpha=n - 1, out=grid[0, ..., 0]).mul_(2.0 / (width - 1)).sub_(1.0)
    torch.mul(C[1], 2.0, out=grid[0, ..., 1]).sub_(1.0)
    both = F.grid_sample(atlas, grid, mode="bilinear", padding_mode="border", align_corners=True)[0]  # (6, h, w)
    return torch.lerp(both[:3], both[3:], fz)


def _error(atlas: Tensor, probe: Tensor, exact: Tensor) -> float:
    """The largest difference between the lattice read at the check colours and the exact chain there."""
    return float((apply_lattice(atlas, probe[:, 0].unsqueeze(-1))[..., 0] - exact[:, 0]).abs().max())


def _split(steps: Sequence[PlanStep]) -> list[tuple[int, int, Tensor]]:
    """Greedy runs of ``steps`` (all ``fusable``): each grows while its lattice passes the check, one exact
    evaluation of each step on the nodes and check colours; a step that fails even alone stays exact. Returns
    ``(first, after, float64 atlas)`` for runs of ``MIN_RUN`` or more steps."""
    n = LATTICE
    nodes, probe = _nodes(n), _check_colours(n)
    runs: list[tuple[int, int, Tensor]] = []
    i = 0
    with torch.no_grad():
        while i < len(steps):
            values, exact, atlas, k = nodes, probe, None, i
            while k < len(steps):
                v, e = chain(steps[k : k + 1], values), chain(steps[k : k + 1], exact)
                a = _atlas(v.reshape(3, n, n, n), n)
                if _error(a, probe, e) > LUT_TOLERANCE:
                    break
                values, exact, atlas, k = v, e, a, k + 1
            if k - i >= MIN_RUN and atlas is not None:
                runs.append((i, k, atlas))
            i = max(k, i + 1)
    return runs


def segment_runs(steps: Sequence[PlanStep], dtype: torch.dtype, device: torch.device) -> list[tuple[int, int, Tensor]]:
    """``_split``'s runs of the fusable segment ``steps`` with their atlases in ``dtype`` on ``device`` (cached)."""
    key = (tuple(_key(s) for s in steps), dtype, device)
    hit = _cache.get(key)
    if hit is None:
        # The entry holds the adjustments: a tensor parameter's id in the key stays its own while it lives.
        runs = [(i, k, a.to(dtype=dtype, device=device)) for i, k, a in _split(steps)]
        hit = (tuple(s.spec.adjust for s in steps), runs)
        _cache[key] = hit
        while len(_cache) > CACHE_SIZE:
            _cache.popitem(last=False)
    _cache.move_to_end(key)
    return hit[1]


def lattice_runs(
    plan: RenderPlan, begin: int, end: int, dtype: torch.dtype, switch_at: Sequence[int] = ()
) -> dict[int, tuple[int, Tensor]]:
    """The runs of ``plan.steps[begin:end]`` a lattice stands for: first step → (step after the run, atlas).

    Runs lie within segments of consecutive ``fusable`` steps that no prefix-cache snapshot (``switch_at``) cuts;
    none for canvases under ``MIN_PIXELS`` or dtypes other than float32 and float64."""
    pixels = plan.canvas[0] * plan.canvas[1]
    for d in plan.batch_shape:
        pixels *= d
    if pixels < MIN_PIXELS or dtype not in (torch.float32, torch.float64):
        return {}
    cuts = set(switch_at)
    runs: dict[int, tuple[int, Tensor]] = {}
    j = begin
    while j < end:
        m = j
        while m < end and (m == j or m not in cuts) and fusable(plan.steps[m], plan):
            m += 1
        if m - j >= MIN_RUN:
            for i, k, atlas in segment_runs(plan.steps[j:m], dtype, plan.device):
                runs[j + i] = (j + k, atlas)
        j = max(m, j + 1)
    return runs


__all__ = [
    "LATTICE",
    "LUT_TOLERANCE",
    "MIN_PIXELS",
    "apply_lattice",
    "chain",
    "fusable",
    "lattice_runs",
    "segment_runs",
]
