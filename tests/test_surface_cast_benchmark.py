"""benchmarks/surface_cast.py: its relief casts shadows under the low light it times, and its rows come back."""

import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import surface_cast  # noqa: E402


def test_the_relief_casts_shadows_and_the_rows_come_back():
    stack = surface_cast.relief_stack(64)
    plain = stack.render().image
    stack.set_light("shape", surface_cast.LOW, shadows=surface_cast.SHADOWS)
    shadowed = stack.render().image
    assert (shadowed <= plain + 1e-6).all() and (shadowed < plain - 0.05).sum() > 50
    row = surface_cast.timings(32, 1)
    assert row["size"] == 32 and all(row[k] > 0 for k in ("render_ms", "shadowed_ms", "shadowed_point_ms"))
    assert torch.isfinite(torch.tensor([row[k] for k in row])).all()
