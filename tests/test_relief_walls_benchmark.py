"""benchmarks/relief_walls.py's split of the error: the true normals score zero everywhere, a flat wall scores only
where the wall has relief, and the split sums to the composite's whole squared error (numpy float64)."""

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from relief_walls import split_errors  # noqa: E402
from surface import lights_of, scenes  # noqa: E402

from lasagna.compose.surface import light_vector  # noqa: E402
from lasagna.document.condition import parse_direction  # noqa: E402
from lasagna.world.tasks import relight_sources, relighting  # noqa: E402


def test_the_split_is_zero_for_the_truth_and_puts_a_flat_walls_error_on_relief_walls():
    scene, labels = scenes("select", 8, 0, 24)
    sources = relight_sources(scene.params)
    rel = relighting(scene, sources)
    src = torch.cat([light_vector(*parse_direction(s))[None] for s in sources]).double()
    tgt = lights_of(labels).double()
    normals = scene.normals.double()
    assert max(split_errors(scene, rel, normals, src, tgt).values()) < 0.05
    flat = torch.zeros_like(normals)
    flat[:, 2] = 1.0
    walls_flat = torch.where((scene.mask < 0.5).expand_as(normals), flat, normals)
    got = split_errors(scene, rel, walls_flat, src, tgt)
    assert got["objects"] < 0.05 and got["flat_walls"] < 0.05 and got["relief_walls"] > 1.0
    # By hand in numpy float64: the whole composite's summed squared error (RGB mean per pixel).

    def ratio(n, light):  # the world's contract: 0.25 + 0.75·max(0, n·l)
        return 0.25 + 0.75 * np.clip(np.einsum("bchw,bc->bhw", n, light), 0, None)

    n, ls, lt = walls_flat.numpy(), src.numpy(), tgt.numpy()
    y = np.clip(rel.base.double().numpy() * (ratio(n, lt) / ratio(n, ls))[:, None], 0, 1)
    whole = ((y - np.clip(rel.target.double().numpy(), 0, 1)) ** 2).mean(1).sum()
    assert abs(sum(got.values()) - whole) < 0.2  # the rows are rounded to 0.1
