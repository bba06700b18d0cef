"""benchmarks/surface_shadows.py: the ray march casts a raised plateau's shadow as long as trigonometry says and none
under a light on the view axis, Frankot–Chellappa integration returns the height field its normals came from, the
objects are moved to rest on the wall, and the script's rows come back."""

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import surface_shadows  # noqa: E402

from lasagna.compose.surface import light_vector  # noqa: E402


@pytest.mark.parametrize("el", [40.0, 60.0])
def test_a_plateau_casts_a_shadow_as_long_as_its_height_over_the_lights_slope(el):
    """A square plateau of height H on a flat floor, lit from the right (az 0) at ``el`` degrees from the view axis:
    floor pixels left of it are in shadow for H·tan(el) canvas units (float64 trigonometry), ±1 pixel of the march's
    step; nothing is shadowed above, below or right of it, nor under a light on the view axis."""
    w, height = 64, 0.3
    h = torch.zeros(1, 1, w, w, dtype=torch.float64)
    h[..., 24:40, 40:52] = height
    light = light_vector(0.0, el, dtype=torch.float64)[None]
    vis = surface_shadows.cast_shadows(h, light)[0, 0].numpy()
    pixel = 2.0 / w
    length = height * math.tan(math.radians(el)) / pixel  # pixels of floor shadow
    row = vis[32]
    shadowed = np.flatnonzero(row[:40] == 0)
    assert shadowed.size and shadowed.max() == 39
    assert abs(shadowed.size - length) <= 1.0, (shadowed.size, length)
    assert (
        (vis[:24] == 1).all() and (vis[40:] == 1).all() and (vis[:, 52:] == 1).all() and (vis[24:40, 40:52] == 1).all()
    )
    assert (surface_shadows.cast_shadows(h, torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)) == 1).all()


def test_the_script_prints_its_rows(capsys):
    assert surface_shadows.main(["--count", "1", "--size", "24", "--gains", "1"]) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    for key in ("no shadows", "shadows"):
        rows = out[key]
        assert len(rows["told layer"]) == 2 and "its normals, shadows cast from the true heights" in rows
    march = out["shadows"]["ray march of the true heights against the world's source shadows"]
    assert 0.5 < march["agree"] <= 1.0


def test_the_script_casts_from_an_estimators_heights(capsys, tmp_path):
    """``--heights``: an estimator's own height field casts both lights' shadows and the target's onto the walls (a
    row each); an estimator whose heights are flat casts nothing, so its rows equal the told layer's."""
    from lasagna.generators.surface import SurfaceConfig, SurfaceEstimator

    flat = SurfaceEstimator(SurfaceConfig(input="lit", silhouette=True, light_input=True, channels=(4, 8), blocks=1))
    flat.save_pretrained(tmp_path / "flat")  # a zero-initialised head: every height 0
    assert (
        surface_shadows.main(["--count", "1", "--size", "24", "--gains", "1", "--heights", str(tmp_path / "flat")]) == 0
    )
    rows = json.loads(capsys.readouterr().out.strip().splitlines()[-1])["shadows"]
    told = rows["told layer"]
    assert rows[f"its normals, shadows cast from {tmp_path / 'flat'}'s heights"] == told
    assert rows[f"its normals, the target's shadows cast onto the walls from {tmp_path / 'flat'}'s heights"] == told
