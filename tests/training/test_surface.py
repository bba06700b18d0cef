"""Training the surface estimator on toy world batches: the multi-light error falls, a killed run resumes to
the same weights, held-out splits at the benchmarks' seed are refused, and the estimate is made at the working
size."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.errors import LasagnaError
from lasagna.generators.surface import SurfaceConfig, SurfaceEstimator
from lasagna.training.loop import read_log
from lasagna.training.surface import (
    SurfaceTrainConfig,
    estimator_from_checkpoint,
    random_lights,
    surface_loss,
    train_surface,
)
from lasagna.world import generate


def toy(**kw) -> SurfaceTrainConfig:
    base = dict(
        net=SurfaceConfig(input="lit", channels=(8, 16), blocks=1, working_size=16),
        batch_size=8,
        steps=60,
        lr=1e-2,
        checkpoint_every=10,
        log_every=1,
        progress=False,
        seed=3,
    )
    return SurfaceTrainConfig(**{**base, **kw})


def test_one_batch_is_fitted_under_every_light():
    """The loss, the renderer and the light fit are wired so that Adam fits a fixed batch: the multi-light
    shading error and the source light's error both fall by half (learning across fresh batches takes
    thousands of steps: the committed run's card measures that)."""
    config = toy()
    torch.manual_seed(0)
    net = SurfaceEstimator(config.net)
    scene = generate("val", 4, 1, 16)
    rng = torch.Generator().manual_seed(0)
    source = random_lights(4, rng, (30.0, 75.0))
    lights = random_lights(4 * config.lights, rng, (0.0, 75.0))
    opt = torch.optim.Adam(net.parameters(), 3e-3)
    history = []
    for _ in range(300):
        loss, metrics = surface_loss(net, config, scene, source, lights)
        opt.zero_grad()
        loss.backward()
        opt.step()
        history.append(metrics)
    assert history[-1]["shading_mse"] < 0.5 * history[0]["shading_mse"]
    assert history[-1]["light_cos_err"] < 0.5 * history[0]["light_cos_err"]


def test_a_run_writes_its_estimator(tmp_path):
    net = train_surface(toy(steps=3), tmp_path / "run")
    assert [r["step"] for r in read_log(tmp_path / "run")] == [1, 2, 3]
    back = SurfaceEstimator.from_pretrained(tmp_path / "run" / "surface")
    snap, step = estimator_from_checkpoint(tmp_path / "run" / "checkpoint.safetensors")
    x = torch.rand(1, 3, 16, 16)
    assert torch.equal(back(x), net(x)) and torch.equal(snap(x), net(x)) and step == 3


def test_a_killed_run_resumes_to_the_same_weights(tmp_path):
    whole = train_surface(toy(steps=20), tmp_path / "a")
    train_surface(toy(steps=20, max_minutes=1e-9), tmp_path / "b")  # stops at once, checkpointed at step 0/1
    train_surface(toy(steps=10), tmp_path / "b")
    resumed = train_surface(toy(steps=20), tmp_path / "b")
    for (k, v), w in zip(whole.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(v, w), k


@pytest.mark.parametrize("split", ["select", "heldout", "far"])
def test_held_out_splits_at_the_benchmarks_seed_are_refused(tmp_path, split):
    with pytest.raises(LasagnaError, match="world_seed: training on .* would train on the benchmarks' own scenes"):
        train_surface(toy(split=split, world_seed=0), tmp_path / "x")


def test_estimate_at_the_working_size():
    net = SurfaceEstimator(SurfaceConfig(input="albedo", channels=(4,), blocks=1, working_size=8))
    torch.nn.init.normal_(net.head.weight)
    torch.nn.init.normal_(net.head.bias)
    normals, light = net.estimate_at(torch.rand(2, 3, 32, 48))
    assert normals.shape == (2, 3, 32, 48) and light is None
    assert torch.allclose(normals.norm(dim=1), torch.ones(2, 32, 48), atol=1e-5)
    # Made at 6×8 (the aspect kept, long side 8): enlarged bilinearly, so it is smooth at full size.
    small = net(torch.nn.functional.interpolate(torch.rand(2, 3, 32, 48), size=(5, 8), mode="bilinear"))
    assert small.shape[-2:] == (5, 8)


def test_a_silhouette_head_learns_where_the_objects_are():
    """With ``silhouette=True`` the loss adds the head's cross-entropy against the objects' mask: on a fixed batch
    Adam halves it, and the head's probabilities separate object pixels from wall pixels."""
    config = toy(net=SurfaceConfig(input="albedo", silhouette=True, channels=(8, 16), blocks=1, working_size=16))
    torch.manual_seed(0)
    net = SurfaceEstimator(config.net)
    scene = generate("val", 4, 1, 16)
    rng = torch.Generator().manual_seed(0)
    lights = random_lights(4 * config.lights, rng, (0.0, 75.0))
    opt = torch.optim.Adam(net.parameters(), 3e-3)
    first = None
    for _ in range(200):
        loss, metrics = surface_loss(net, config, scene, None, lights)
        first = first or metrics["silhouette_bce"]
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert metrics["silhouette_bce"] < 0.5 * first
    with torch.no_grad():
        p = torch.sigmoid(net.outputs(scene.albedo).silhouette)
    on, off = scene.mask > 0.5, scene.mask < 0.5
    assert float(p[on].mean()) > float(p[off].mean()) + 0.3


def test_init_from_starts_at_the_saved_estimator(tmp_path):
    """A run started from a saved estimator (``init_from``) begins at its weights (step 0 would reproduce it) and
    trains from there on another split; an estimator of another architecture is refused."""
    first = train_surface(toy(steps=3), tmp_path / "a")
    config = toy(steps=1, lr=1e-12, warmup_steps=0, split="wide", init_from=str(tmp_path / "a" / "surface"))
    second = train_surface(config, tmp_path / "b")
    x = torch.rand(1, 3, 16, 16)
    torch.testing.assert_close(second(x), first(x), atol=1e-6, rtol=0)  # one step of lr 1e-12 moves nothing visible
    fresh = train_surface(toy(steps=1, lr=1e-12, warmup_steps=0, split="wide"), tmp_path / "c")
    assert not torch.allclose(fresh(x), first(x), atol=1e-4)
    larger = toy(steps=1, lr=1e-12, warmup_steps=0, init_from=str(tmp_path / "a" / "surface"))
    larger = larger.model_copy(update={"net": larger.net.model_copy(update={"working_size": 24})})
    third = train_surface(larger, tmp_path / "e")  # another working size: the same weights, continued there
    assert third.config.working_size == 24
    torch.testing.assert_close(third(x), first(x), atol=1e-6, rtol=0)
    other = toy(net=SurfaceConfig(input="lit", channels=(8, 8), blocks=1, working_size=16))
    with pytest.raises(LasagnaError, match="its estimator config differs from this run's"):
        train_surface(other.model_copy(update={"init_from": str(tmp_path / "a" / "surface")}), tmp_path / "d")


def test_close_ups_are_windows_of_the_larger_render():
    """``close_ups``: every scene becomes a window of the render reduced to the working size — a window of the whole
    render is the render reduced (the same numbers as reducing it directly), normals stay unit, the mask stays
    binary, and the same generator state gives the same windows."""
    from lasagna.compose.resample import downsample
    from lasagna.training.surface import close_ups

    scene = generate("wide", 6, 2, 48)
    a = close_ups(scene, 16, torch.Generator().manual_seed(4))
    b = close_ups(scene, 16, torch.Generator().manual_seed(4))
    assert a.image.shape == (6, 3, 16, 16) and a.object_index.dtype == torch.int64
    assert torch.equal(a.normals, b.normals) and torch.equal(a.albedo, b.albedo)
    torch.testing.assert_close(a.normals.norm(dim=1), torch.ones(6, 16, 16), atol=1e-5, rtol=0)
    assert set(a.mask.unique().tolist()) <= {0.0, 1.0}
    # Windows differ in size: some scenes are zoomed in (more object pixels than the whole render reduced).
    whole = downsample(scene.mask, (16, 16))
    assert (a.mask.mean(dim=(1, 2, 3)) > whole.mean(dim=(1, 2, 3)) + 0.05).any()
    # A window as large as the render is the render reduced.
    one = scene.select([0])
    for seed in range(200):
        win = int(torch.randint(16, 49, (1,), generator=torch.Generator().manual_seed(seed)))
        if win == 48:
            full = close_ups(one, 16, torch.Generator().manual_seed(seed))
            torch.testing.assert_close(full.albedo, downsample(one.albedo, (16, 16)))
            break
    else:
        pytest.fail("no seed drew the whole render")


def test_a_run_with_close_ups_trains(tmp_path):
    net = train_surface(toy(steps=2, zoom=2.0, split="wide"), tmp_path / "run")
    assert [r["step"] for r in read_log(tmp_path / "run")] == [1, 2]
    assert net(torch.rand(1, 3, 16, 16)).shape == (1, 1, 16, 16)


def test_stray_illumination_changes_the_input_not_the_truth():
    """With a gain the estimator reads the lit image times it, clipped to [0, 1]; the loss's truth is the scene's
    own, so the same estimate costs the same shading error with and without it."""
    from lasagna.training.surface import estimator_input
    from lasagna.world.scene import with_light

    config = toy(stray=1.0)
    scene = generate("val", 2, 1, 16)
    source = random_lights(2, torch.Generator().manual_seed(0), (30.0, 75.0))
    gain = torch.full((2, 1, 16, 16), 3.0)
    lit = with_light(scene, source).image
    assert torch.equal(estimator_input(config.net, scene, source, gain), (lit * 3).clamp(0, 1))
    assert torch.equal(estimator_input(config.net, scene, source), lit)


def test_a_run_with_stray_illumination_trains_and_resumes(tmp_path):
    whole = train_surface(toy(steps=4, stray=0.5), tmp_path / "a")
    train_surface(toy(steps=2, stray=0.5), tmp_path / "b")
    resumed = train_surface(toy(steps=4, stray=0.5), tmp_path / "b")
    for (k, v), w in zip(whole.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(v, w), k


def test_shadowed_scenes_carry_the_worlds_cast_shadows_in_the_input_and_not_in_the_truth():
    """``shadowed_scenes``: the source lights are drawn first and the scenes rendered under them with the world's cast
    shadows; a shadowed scene's input is that render's image (shadows only darken, and some pixels are darkened), an
    unshadowed one's the shadowless Lambert image, and the truth — the normals — is the shadowless render's."""
    from lasagna.training.surface import estimator_input, shadowed_scenes, training_scenes
    from lasagna.world.scene import render, with_light
    from lasagna.world.tasks import RELIGHT_ELEVATION

    config = toy(shadows=0.5, batch_size=6, split="val")
    scene, source, shadowed = shadowed_scenes(config, torch.Generator().manual_seed(5), "cpu")
    rng = torch.Generator().manual_seed(5)  # the same draws, in the order the docstring gives
    assert torch.equal(source, random_lights(6, rng, RELIGHT_ELEVATION))
    assert torch.equal(shadowed, torch.rand(6, generator=rng, dtype=torch.float64) < 0.5)
    params = training_scenes(config, rng)
    cast = render(params, 16, light=source, shadows=True)
    bare = render(params, 16, light=source, shadows=False)
    assert not scene.shadows and torch.equal(scene.normals, bare.normals)
    image = estimator_input(config.net, scene, source, shadowed=torch.ones(6, dtype=torch.bool))
    torch.testing.assert_close(image, cast.image)
    torch.testing.assert_close(estimator_input(config.net, scene, source), with_light(bare, source).image)
    assert (cast.image <= bare.image + 1e-6).all() and (cast.image < bare.image - 0.05).any()
    mixed = estimator_input(config.net, scene, source, shadowed=shadowed)
    for i, keep in enumerate(shadowed.tolist()):
        torch.testing.assert_close(mixed[i], (cast if keep else bare).image[i])


def test_a_run_with_cast_shadows_trains_and_resumes_and_needs_a_lit_input_and_fresh_scenes(tmp_path):
    whole = train_surface(toy(steps=3, shadows=0.5, zoom=2.0), tmp_path / "a")
    train_surface(toy(steps=1, shadows=0.5, zoom=2.0), tmp_path / "b")
    resumed = train_surface(toy(steps=3, shadows=0.5, zoom=2.0), tmp_path / "b")
    for (k, v), w in zip(whole.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(v, w), k
    albedo = SurfaceConfig(input="albedo", channels=(8, 16), blocks=1, working_size=16)
    for bad in (toy(steps=1, shadows=0.5, net=albedo), toy(steps=1, shadows=0.5, scene_bank=8)):
        with pytest.raises(LasagnaError, match="cast shadows"):
            train_surface(bad, tmp_path / "c")


def test_given_lights_are_jittered_unit_lights_or_zero_rows():
    from lasagna.training.surface import given_lights

    rng = torch.Generator().manual_seed(0)
    source = random_lights(400, rng, (10.0, 60.0))
    exact = given_lights(source, rng, 1.0, 0.0)
    torch.testing.assert_close(exact, source, atol=1e-6, rtol=0)
    assert torch.equal(given_lights(source, rng, 0.0, 10.0), torch.zeros_like(source))
    some = given_lights(source, rng, 0.5, 10.0)
    kept = some.norm(dim=1) > 0.5
    assert 150 < int(kept.sum()) < 250  # about half given
    torch.testing.assert_close(some[kept].norm(dim=1), torch.ones(int(kept.sum())), atol=1e-5, rtol=0)
    angle = torch.rad2deg(torch.arccos((some[kept] * source[kept]).sum(1).clamp(-1, 1)))
    assert 5.0 < float(angle.median()) < 25.0  # 10° per component: about 10·√2·0.83 ≈ 12° off


def test_a_light_input_run_starts_at_the_estimator_it_widens(tmp_path):
    """``init_from`` an estimator without a light input into one with it: the new channels start at zero, so the
    widened estimator answers as the saved one whatever light it is told, then learns; the reverse is refused."""
    first = train_surface(toy(steps=3), tmp_path / "a")
    wide_net = toy().net.model_copy(update={"light_input": True})
    config = toy(net=wide_net, steps=1, lr=1e-12, warmup_steps=0, init_from=str(tmp_path / "a" / "surface"))
    wide = train_surface(config, tmp_path / "b")
    x = torch.rand(2, 3, 16, 16)
    told = torch.tensor([[0.6, 0.0, 0.8], [0.0, 0.0, 0.0]])
    torch.testing.assert_close(wide.outputs(x, told).surface, first(x), atol=1e-6, rtol=0)
    learnt = train_surface(toy(net=wide_net, steps=20, init_from=str(tmp_path / "a" / "surface")), tmp_path / "c")
    assert not torch.allclose(learnt.outputs(x, told).surface, learnt.outputs(x).surface, atol=1e-5)
    back = toy(steps=1, init_from=str(tmp_path / "b" / "surface"))
    with pytest.raises(LasagnaError, match="its estimator config differs from this run's"):
        train_surface(back, tmp_path / "d")


def test_with_relief_gives_flat_walls_relief_of_the_splits_families():
    """``relief``: a flat wall gets relief of one of the split's families with the given probability (all at 1,
    none at 0); a wall the split gave relief keeps it; the rendered wall's normals then leave +z."""
    from lasagna.training.surface import with_relief
    from lasagna.world.params import sample_scenes
    from lasagna.world.relief import RELIEF_NAMES
    from lasagna.world.scene import render
    from lasagna.world.splits import SPLITS

    params = sample_scenes("train", 5, range(24))
    families = SPLITS["train"].reliefs
    drawn = params.relief >= 0
    assert 0 < int(drawn.sum()) < 24  # the split draws some reliefs, not all
    every = with_relief(params, torch.Generator().manual_seed(1), 1.0, families)
    assert bool((every.relief >= 0).all())
    assert torch.equal(every.relief[drawn], params.relief[drawn])
    assert torch.equal(every.relief_params[drawn], params.relief_params[drawn])
    assert {RELIEF_NAMES[int(r)] for r in every.relief[~drawn]} <= set(families)
    none = with_relief(params, torch.Generator().manual_seed(1), 0.0, families)
    assert torch.equal(none.relief, params.relief) and torch.equal(none.relief_params, params.relief_params)
    flat = int((~drawn).nonzero()[0])
    before, after = render(params, 32), render(every, 32)
    wall = ~before.mask[flat, 0].bool()
    assert float(before.normals[flat, 2][wall].min()) > 0.999  # drawn flat
    assert float(after.normals[flat, 2][wall].min()) < 0.99  # the new relief bends the wall's normals
    with pytest.raises(LasagnaError, match="draws no relief"):
        with_relief(params, torch.Generator(), 0.5, ())


def test_training_scenes_walls_only_with_relief_are_bare_walls_with_relief():
    """``walls_only`` 1: a step's scenes have no objects (an empty mask); with ``relief`` 1 every wall has relief of the
    split's families; the draws are the run generator's (the same seed, the same scenes), and without either flag
    the scenes are the split's as drawn."""
    from lasagna.training.surface import training_scenes
    from lasagna.world.relief import RELIEF_NAMES
    from lasagna.world.scene import render
    from lasagna.world.splits import SPLITS

    base = toy(steps=1)
    plain = training_scenes(base, torch.Generator().manual_seed(3))
    assert bool(plain.present.any())  # the split's scenes have objects
    walls = base.model_copy(update={"walls_only": 1.0, "relief": 1.0})
    a = training_scenes(walls, torch.Generator().manual_seed(3))
    b = training_scenes(walls, torch.Generator().manual_seed(3))
    assert not bool(a.present.any()) and torch.equal(a.relief, b.relief)
    assert bool((a.relief >= 0).all()) and {RELIEF_NAMES[int(r)] for r in a.relief} <= set(SPLITS["train"].reliefs)
    scene = render(a, 32)
    assert float(scene.mask.max()) == 0.0
    assert bool((scene.normals[:, 2].flatten(1).min(1).values < 0.99).all())  # every wall bent somewhere
    bare = training_scenes(base.model_copy(update={"walls_only": 1.0}), torch.Generator().manual_seed(3))
    assert bool((bare.relief < 0).all())  # walls alone, no relief asked: flat
    # A fraction: the picked scenes are bare flat walls, the others the split's scenes as drawn.
    some = training_scenes(toy(steps=1, batch_size=64, walls_only=0.5), torch.Generator().manual_seed(3))
    drawn = training_scenes(toy(steps=1, batch_size=64), torch.Generator().manual_seed(3))
    picked = ~some.present.any(1) & drawn.present.any(1)
    assert 16 < int(picked.sum()) < 48
    assert bool((some.relief[picked] < 0).all())
    kept = some.present.any(1)
    assert torch.equal(some.present[kept], drawn.present[kept]) and torch.equal(some.relief[kept], drawn.relief[kept])


def _depth_normals(scene) -> np.ndarray:
    """Unit normals from the scene's depth (camera z, toward the viewer) by central differences in numpy float64:
    x along columns, y up (against rows), canvas units [−1, 1] — the world's truth, independent of its normals."""
    z = scene.depth[:, 0].double().numpy()
    step = 2.0 / z.shape[-1]
    dzdx, dzdy = np.gradient(z, step, axis=2), -np.gradient(z, step, axis=1)
    n = np.stack([-dzdx, -dzdy, np.ones_like(z)], 1)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _inside(scene) -> np.ndarray:
    m = scene.mask[:, 0].numpy() > 0.5
    inner = np.zeros_like(m)
    inner[:, 1:-1, 1:-1] = m[:, 1:-1, 1:-1] & m[:, :-2, 1:-1] & m[:, 2:, 1:-1] & m[:, 1:-1, :-2] & m[:, 1:-1, 2:]
    return inner


def test_a_turned_scene_is_a_scene_its_normals_agree_with_its_turned_depth_and_light():
    """``turned``: each of the eight symmetries of the square moves every map as pixels and turns the normals and the
    light with them: the normals agree with central differences of the turned depth (numpy float64) and the shading
    is Lambert's of the turned normals under the turned light; moving the normals as pixels alone does not agree."""
    from lasagna.compose.surface import lambert
    from lasagna.generators.surface import MIRRORS
    from lasagna.training.surface import turned
    from lasagna.world.params import sample_scenes
    from lasagna.world.scene import render

    scene = render(sample_scenes("train", 5, range(8)), 48)
    for k in range(8):
        t = turned(scene, k)
        inner = _inside(t)
        assert inner.sum() > 500
        cos = (_depth_normals(t) * t.normals.double().numpy()).sum(1)[inner]
        assert float(np.median(cos)) > 0.999, k
        assert torch.allclose(lambert(t.normals, t.light, scene.ambient), t.shading, atol=1e-5), k
        if k:  # the pixels moved but the normals not turned: the depth disagrees
            dims = MIRRORS[k % 4][0]
            naive = scene.normals.transpose(-1, -2) if k >= 4 else scene.normals
            pixels_only = naive.flip(dims) if dims else naive
            bad = (_depth_normals(t) * pixels_only.double().numpy()).sum(1)[inner]
            assert float(np.median(bad)) < 0.99, k


def test_a_scene_bank_is_rendered_once_drawn_turned_and_resumes_to_the_same_weights(tmp_path):
    """``scene_bank``: the bank is the same for the same seed (a resumed run renders it again), each step's scenes
    are bank scenes turned by one symmetry, and a killed run with a bank resumes to the same weights."""
    from lasagna.training.surface import SceneBank, turned

    config = toy(steps=20, scene_bank=12)
    a, b = SceneBank(config, "cpu"), SceneBank(config, "cpu")
    assert len(a) == 12 and torch.equal(a.scenes.albedo, b.scenes.albedo)
    drawn = a.draw(5, torch.Generator().manual_seed(2))
    g = torch.Generator().manual_seed(2)
    idx = torch.randint(0, 12, (5,), generator=g)
    k = int(torch.randint(0, 8, (1,), generator=g))
    assert torch.equal(drawn.albedo, turned(a.scenes.select(idx.tolist()), k).albedo)
    whole = train_surface(config, tmp_path / "a")
    train_surface(toy(steps=10, scene_bank=12), tmp_path / "b")
    resumed = train_surface(config, tmp_path / "b")
    for (name, v), w in zip(whole.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(v, w), name


def test_the_light_weight_scales_the_fitted_lights_cosine_error_in_the_loss_and_the_cli_sets_it(tmp_path):
    """λ_l (``light_weight``, ``train-surface --light-weight``): the loss moves by exactly Δλ_l times the logged cosine
    error of the fitted light, all else equal; the CLI writes it into the run's config."""
    import json

    from lasagna.cli import main

    scene = generate("val", 2, 1, 16)
    rng = torch.Generator().manual_seed(1)
    source, lights = random_lights(2, rng, (30.0, 75.0)), random_lights(6, rng, (0.0, 75.0))
    torch.manual_seed(0)
    net = SurfaceEstimator(toy().net)
    low, metrics = surface_loss(net, toy(light_weight=0.1), scene, source, lights)
    high, _ = surface_loss(net, toy(light_weight=1.0), scene, source, lights)
    assert metrics["light_cos_err"] > 1e-4
    assert float((high - low).detach()) == pytest.approx(0.9 * metrics["light_cos_err"], rel=1e-4)
    argv = ["train-surface", "--input", "lit", "--out", str(tmp_path / "run"), "--working-size", "16"]
    argv += ["--channels", "8,16", "--blocks", "1", "--batch-size", "2", "--steps", "1", "--light-weight", "0.7"]
    assert main([*argv, "--no-progress"]) == 0
    assert json.loads((tmp_path / "run" / "train_config.json").read_text())["light_weight"] == 0.7


def test_a_close_ups_heights_are_in_its_own_canvas_units():
    """``close_ups`` scales the heights above the wall by the window's zoom (big / win), as its normals are the
    geometry's, unchanged: central differences of a close-up's depth (numpy float64) agree with its normals, where the
    render's depth, cut and reduced alone, disagrees for every zoomed window."""
    from lasagna.training.surface import close_ups
    from lasagna.world.params import WALL_Z, sample_scenes
    from lasagna.world.scene import render

    scene = render(sample_scenes("train", 5, range(8)).resting(0.5), 96)
    cut = close_ups(scene, 32, torch.Generator().manual_seed(2))
    inner = _inside(cut)
    cos = (_depth_normals(cut) * cut.normals.double().numpy()).sum(1)
    unscaled = []
    for i in range(8):
        if inner[i].sum() < 30:
            continue
        assert float(np.median(cos[i][inner[i]])) > 0.99, i
        peak = float((cut.depth[i] - WALL_Z).max())
        unscaled.append(peak)
    assert len(unscaled) >= 4
    # The heights grew with the zoom: some window's peak exceeds the whole render's tallest object.
    assert max(unscaled) > float((scene.depth - WALL_Z).max()) * 1.2


def test_resting_scenes_and_the_height_loss(tmp_path):
    """``rest``: the drawn scenes' objects sit REST_SINK radii in front of the wall (some scenes, at 0.5); the height
    loss is zero for the true heights plus any constant and positive for a flat field; a run with both trains, logs
    the height error, and a normals-output estimator is refused a height loss."""
    from lasagna.training.surface import REST_SINK, centred, training_scenes
    from lasagna.world.params import WALL_Z

    config = toy(rest=0.5, batch_size=64)
    params = training_scenes(config, torch.Generator().manual_seed(1))
    sink = (params.center[..., 2] - WALL_Z) / params.radius.to(params.center.dtype)
    rests = ((sink >= REST_SINK[0] - 1e-9) & (sink <= REST_SINK[1] + 1e-9)).all(1)
    assert 16 < int(rests.sum()) < 48
    assert bool((params.center[~rests][..., 2] >= -0.2 - 1e-9).all())  # the others float, as sampled
    truth = torch.rand(2, 1, 8, 8, dtype=torch.float64)
    assert float(centred(truth + 3.0).sub(centred(truth)).abs().max()) < 1e-12
    assert float(centred(truth).abs().mean()) > 0.1
    train_surface(toy(steps=2, zoom=2.0, rest=1.0, height_weight=1.0), tmp_path / "run")
    assert all(r["height_mse"] > 0 for r in read_log(tmp_path / "run"))
    with pytest.raises(LasagnaError, match="height field"):
        normals = SurfaceConfig(input="lit", output="normals", channels=(8, 16), blocks=1, working_size=16)
        train_surface(toy(steps=1, height_weight=1.0, net=normals), tmp_path / "refused")


def test_low_key_paints_some_surfaces_dark_within_its_gains():
    """``low_key``: about that share of surfaces (wall and objects) painted dark by a gain in ``LOW_KEY_GAIN``, the
    others and the geometry as drawn; 0 draws nothing (the same scenes, the rng untouched)."""
    from lasagna.training.surface import LOW_KEY_GAIN, training_scenes

    rng0, rng1 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    plain = training_scenes(toy(batch_size=64), rng0)
    dark = training_scenes(toy(batch_size=64, low_key=0.3), rng1)
    assert torch.equal(plain.center, dark.center) and torch.equal(plain.shape, dark.shape)
    gains = torch.cat(
        [dark.color[..., 0] / plain.color[..., 0], (dark.wall_color[:, 0] / plain.wall_color[:, 0])[:, None]], 1
    )
    darkened = gains < 1 - 1e-9
    assert 0.2 < float(darkened.double().mean()) < 0.4
    assert (
        float(gains[darkened].min()) >= LOW_KEY_GAIN[0] - 1e-9
        and float(gains[darkened].max()) <= LOW_KEY_GAIN[1] + 1e-9
    )
    assert torch.allclose(gains[~darkened], torch.ones_like(gains[~darkened]))
    torch.testing.assert_close(dark.wall_color_delta, plain.wall_color_delta * gains[:, -1:])
    assert torch.equal(training_scenes(toy(batch_size=64), torch.Generator().manual_seed(3)).color, plain.color)
