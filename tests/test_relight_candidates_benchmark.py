"""benchmarks/relight_candidates.py: a candidate catalogue holding the shipped estimator reproduces the shipped rows
(delta 0, the same wall leak), another estimator moves them, the headroom row (the true normals at the working size)
is measured once, and a row's gains are the composite's PSNR over the input's in numpy float64."""

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import relight_candidates  # noqa: E402


def test_candidates_are_measured_against_the_shipped_catalogue_in_the_same_run(capsys, tmp_path):
    shipped = "@"  # the preset's own estimators (told the light: its surface.told), its settings as they are
    other = ROOT / "layers" / "surface-lit-closeup-32"  # read told the light too: the shipped untold estimator
    argv = [
        "--estimator",
        shipped,
        str(other),
        "--count",
        "1",  # one scene: each candidate's edits (60 refinement steps each) are the test's whole cost
        "--sizes",
        "32",
        "--kinds",
        "given",
        "--leak",
        "--sheet",
        str(tmp_path / "sheet.png"),
    ]
    assert relight_candidates.main(argv) == 0
    out = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    same, moved = out["delta"][f"estimator:{shipped}"], out["delta"][f"estimator:{other}"]
    assert abs(same["given"]["db_all"]) < 1e-6 and abs(same["given"]["db_objects"]) < 1e-6
    assert abs(moved["given"]["db_all"]) > 1e-3  # another estimator, another layer
    rows = out["rows"]
    assert len([r for r in rows if r["method"] == "true at the working size"]) == 1
    assert {r["candidate"] for r in rows if "candidate" in r} == {"shipped", *out["delta"]}
    leak = {(r["candidate"], r["kind"]): r["leak_db"] for r in rows if "candidate" in r}
    # The same estimator leaks the same; a layer is never exactly flat here.
    assert abs(leak[(f"estimator:{shipped}", "given")] - leak[("shipped", "given")]) < 1e-6
    assert 10.0 < leak[("shipped", "given")] < 200.0
    # The sheet: input | truth relit | true ratio | one ratio per candidate (shipped, "@", the other), 32² tiles.
    from PIL import Image

    with Image.open(tmp_path / "sheet.png") as sheet:
        assert sheet.width == 6 * 32 + 5 * 2


def test_a_rows_gains_are_the_composites_psnr_over_the_inputs_in_numpy_float64():
    from types import SimpleNamespace

    import numpy as np
    import torch

    g = torch.Generator().manual_seed(0)
    base, target = torch.rand(2, 3, 8, 8, generator=g), torch.rand(2, 3, 8, 8, generator=g)
    mask = (torch.rand(2, 1, 8, 8, generator=g) > 0.5).float()
    ratio = 0.5 + torch.rand(2, 1, 8, 8, generator=g)
    layer = torch.ones(2, 1, 8, 8)
    row = relight_candidates.measure(
        "x", SimpleNamespace(mask=mask), SimpleNamespace(base=base, target=target, layer=layer), ratio, 1.0, 8
    )

    def db(a, b, m=None):
        d = (a - b) ** 2
        mse = d.mean() if m is None else (d * m).sum() / (m.sum() * 3)
        return -10 * np.log10(mse)

    b, t, m = base.double().numpy(), target.double().numpy(), mask.double().numpy()
    y = np.clip(b * ratio.double().numpy(), 0, 1)
    assert abs(row["db_all"] - (db(y, t) - db(b, t))) < 2e-3  # rounded to 0.001
    assert abs(row["db_objects"] - (db(y, t, m) - db(b, t, m))) < 2e-3


def test_an_estimator_spec_carries_preset_settings_and_an_empty_folder_keeps_the_shipped_estimator(tmp_path):
    import pytest

    from lasagna.catalogue import load_preset

    assert relight_candidates.estimator_spec("runs/x/surface") == ("runs/x/surface", {})
    assert relight_candidates.estimator_spec('@wall_relief=0.5,symmetry="none"') == (
        "",
        {"wall_relief": 0.5, "symmetry": "none"},
    )
    # A JSON object's commas are inside braces: one setting, not three.
    assert relight_candidates.estimator_spec('x@wall_relief=0.25,closer_walls={"size":64,"wall_relief":0.05}') == (
        "x",
        {"wall_relief": 0.25, "closer_walls": {"size": 64, "wall_relief": 0.05}},
    )
    with pytest.raises(SystemExit, match="not key=value"):
        relight_candidates.estimator_spec("a@wall_relief")
    root = relight_candidates.candidate_catalogue(tmp_path / "c", estimator="", surface={"wall_relief": 0.25})
    got = load_preset(relight_candidates.PRESET, catalogue_dirs=[root])
    shipped = load_preset(relight_candidates.PRESET)
    assert got.surface.wall_relief == 0.25 and shipped.surface.wall_relief == 1.0
    assert got.surface.model_copy(update={"wall_relief": 1.0}) == shipped.surface
    # A candidate folder is read whether the light is told or not: the preset's told estimator is dropped.
    folder = relight_candidates.candidate_catalogue(tmp_path / "f", estimator=str(ROOT / "layers" / "surface-lit-32"))
    candidate = load_preset(relight_candidates.PRESET, catalogue_dirs=[folder])
    assert shipped.surface.told is not None and candidate.surface.told is None
    assert candidate.surface.estimator == "candidate-estimator"


def test_shadows_render_the_scenes_with_the_worlds_cast_shadows():
    """``--shadows``: the benchmark's scenes are the world's render with cast shadows (only darker than without, and
    somewhere strictly so), their normals unchanged."""
    import torch
    from surface import scenes

    from lasagna.world.lighting import VOCABULARY
    from lasagna.world.params import sample_scenes
    from lasagna.world.scene import render

    cast, labels = scenes("select", 4, 0, 32, shadows=True)
    bare, _ = scenes("select", 4, 0, 32)
    assert labels == [VOCABULARY[i] for i in range(4)] and cast.shadows and not bare.shadows
    want = render(sample_scenes("select", 0, range(4)).with_labels(labels), 32, shadows=True)
    assert torch.equal(cast.image, want.image) and torch.equal(cast.normals, bare.normals)
    assert (cast.shading <= bare.shading).all() and (cast.shading < bare.shading).any()
