"""Any light direction (az, el) and the relight task: lit image A → lit image B through the ratio S_B / S_A."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lasagna.errors import ConditionError, LasagnaError
from lasagna.world import lighting
from lasagna.world.lighting import (
    AMBIENT,
    LIGHTS,
    VOCABULARY,
    condition_direction,
    direction_vector,
    lambert,
    named_direction,
    parse_direction,
    vector_condition,
)
from lasagna.world.params import sample_scenes
from lasagna.world.scene import generate, render, with_light
from lasagna.world.splits import STREAM_VERSION, scene_rng
from lasagna.world.tasks import RELIGHT_ELEVATION, relight_sources, relighting
from tests.support.reference import read_png64

EL = st.floats(0.0, 90.0, exclude_max=True)
AZ = st.floats(-720.0, 720.0, allow_nan=False)


def closed_form(az: float, el: float) -> np.ndarray:
    a, e = np.radians(az), np.radians(el)
    return np.array([np.sin(e) * np.cos(a), np.sin(e) * np.sin(a), np.cos(e)])


class TestDirections:
    def test_named_directions_are_the_lights(self):
        for label in VOCABULARY:
            az, el = named_direction(label)
            assert el == 60.0
            np.testing.assert_allclose(closed_form(az, el), LIGHTS[label], rtol=0, atol=1e-12)
            assert direction_vector(az, el) == LIGHTS[label] == condition_direction(label)
            assert vector_condition(LIGHTS[label]) == label

    def test_convention(self):
        # right = 0°, top = 90°, left = 180°, bottom = 270°; el from +z
        np.testing.assert_allclose(direction_vector(90.0, 40.0), closed_form(90.0, 40.0), atol=1e-15)
        x, y, z = condition_direction("az=135,el=40")
        assert x < 0 < y and x == pytest.approx(-y) and z == pytest.approx(math.cos(math.radians(40)))
        assert direction_vector(0.0, 0.0) == (0.0, 0.0, 1.0)

    def test_contract_text_is_in_the_docstring(self):
        doc = " ".join(lighting.__doc__.split())
        for phrase in (
            "azimuth in the image plane measured from +x (right) counter-clockwise toward +y (up)",
            "right = 0°, top = 90°, left = 180°, bottom = 270°",
            "elevation = the angle from the view axis +z, in [0, 90)",
            "l = (sin el·cos az, sin el·sin az, cos el)",
        ):
            assert phrase in doc, phrase

    @settings(max_examples=200, deadline=None)
    @given(az=AZ, el=EL)
    def test_vector_is_unit_and_matches_the_closed_form(self, az, el):
        v = np.array(direction_vector(az, el))
        assert abs(np.linalg.norm(v) - 1.0) <= 1e-15
        np.testing.assert_allclose(v, closed_form(az, el), rtol=0, atol=1e-12)
        assert v[2] > 0  # every condition lights the wall

    @settings(max_examples=100, deadline=None)
    @given(az=st.floats(0.0, 360.0, exclude_max=True), el=st.floats(0.5, 89.5))
    def test_vector_condition_inverts(self, az, el):
        back = parse_direction(vector_condition(direction_vector(az, el)))
        np.testing.assert_allclose(direction_vector(*back), direction_vector(az, el), atol=1e-7)

    def test_bad_vectors(self):
        scene = generate("train", 2, resolution=4)
        with pytest.raises(ConditionError, match="light: expected unit light vectors with z > 0"):
            with_light(scene, torch.tensor([0.0, 0.0, 2.0]))
        with pytest.raises(ConditionError, match="light: expected unit light vectors with z > 0"):
            with_light(scene, torch.tensor([0.0, 0.0, -1.0]))
        with pytest.raises(ConditionError, match=r"expected light vectors of shape \(3,\) or \(2, 3\)"):
            with_light(scene, torch.zeros(3, 3))
        with pytest.raises(ConditionError, match="expected 1 or 2 light conditions, got 3"):
            with_light(scene, ["top"] * 3)
        with pytest.raises(ConditionError, match="condition: expected one of left"):
            with_light(scene, "az=10")
        with pytest.raises(LasagnaError, match="light: expected labels or light, got both"):
            render(scene.params, 4, labels="top", light="top")


@pytest.fixture(scope="module")
def scene():
    return generate("val", 4, seed=3, resolution=16, dtype=torch.float64)


class TestAnyDirection:
    def test_named_light_renders_the_same_bits_as_its_label(self):
        p = sample_scenes("train", 1, range(3))
        for shadows in (False, True):
            by_label = render(p, 12, labels="top-left", shadows=shadows)
            by_angles = render(p, 12, light="az=135,el=60", shadows=shadows)
            assert torch.equal(by_label.image, by_angles.image) and by_angles.label == ["top-left"] * 3
            assert by_angles.label_index.tolist() == [VOCABULARY.index("top-left")] * 3

    def test_with_light_equals_render(self, scene):
        conds = ["az=10,el=20", "el=80,az=200", "bottom", "az=300.5,el=45"]
        a = with_light(scene, conds)
        b = render(scene.params, 16, light=conds, dtype=torch.float64)
        assert torch.equal(a.image, b.image) and torch.equal(a.light, b.light)
        assert a.label == b.label == ["az=10,el=20", "az=200,el=80", "bottom", "az=300.5,el=45"]
        assert a.label_index.tolist() == [-1, -1, VOCABULARY.index("bottom"), -1]
        assert torch.equal(a.params.label, scene.params.label)  # the scenes as sampled

    def test_vectors_as_light(self, scene):
        v = torch.tensor(direction_vector(33.0, 25.0), dtype=torch.float64)
        a = with_light(scene, v)
        assert torch.equal(a.image, with_light(scene, "az=33,el=25").image)
        assert a.label == ["az=33,el=25"] * 4

    def test_shading_reference(self, scene):
        lit = with_light(scene, "az=160,el=35")
        n = scene.normals.numpy()
        ref = AMBIENT + (1 - AMBIENT) * np.maximum(0.0, np.einsum("bchw,c->bhw", n, closed_form(160, 35)))
        np.testing.assert_allclose(lit.shading[:, 0].numpy(), ref, rtol=0, atol=1e-14)

    @pytest.mark.parametrize("el", [0.0, 25.0, 60.0, 85.0])
    def test_wall_shading_is_a_plus_cos_el_for_every_azimuth(self, el):
        p = sample_scenes("train", 0, range(2)).walls_only()
        for az in (0.0, 22.5, 100.0, 359.0):
            s = render(p, 8, light=f"az={az},el={el}", dtype=torch.float64)
            expected = AMBIENT + (1 - AMBIENT) * math.cos(math.radians(el))
            assert torch.allclose(s.shading, torch.full_like(s.shading, expected), rtol=0, atol=1e-15)

    def test_in_between_directions_shade_smoothly(self, scene):
        # Sweeping az from right to top-right, the shading moves continuously: for unit normals
        # |ΔS| ≤ (1 − a)·|n·Δl| ≤ (1 − a)·|Δl| (max(0, ·) is 1-Lipschitz), and the sweep's ends are the
        # named lights' shadings exactly.
        prev = None
        for az in np.linspace(0.0, 45.0, 10):
            cur = with_light(scene, f"az={az},el=60")
            if prev is not None:
                dl = float((cur.light[0] - prev.light[0]).norm())
                assert (cur.shading - prev.shading).abs().max() <= (1 - AMBIENT) * dl + 1e-12
            prev = cur
        ends = [with_light(scene, name).shading for name in ("right", "top-right")]
        assert torch.equal(with_light(scene, "az=0,el=60").shading, ends[0])
        assert torch.equal(prev.shading, ends[1])


class TestRelighting:
    @pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
    def test_ratio_closed_form_and_identity(self, dtype):
        s = generate("heldout", 4, seed=5, resolution=16, dtype=dtype)
        d = relighting(s, "az=250,el=30", "top-right")
        n = s.normals.double().numpy()

        def shade(v):
            return AMBIENT + (1 - AMBIENT) * np.maximum(0.0, np.einsum("bchw,c->bhw", n, np.asarray(v)))

        ratio = shade(LIGHTS["top-right"]) / shade(closed_form(250, 30))
        tol = 1e-13 if dtype == torch.float64 else 3e-6
        np.testing.assert_allclose(d.layer[:, 0].double().numpy(), ratio, rtol=tol, atol=0)
        np.testing.assert_allclose(d.base * d.layer, d.target, rtol=4 * torch.finfo(dtype).eps, atol=0)
        assert d.layer.min() >= AMBIENT - 1e-7 and d.layer.max() <= 1 / AMBIENT + 1e-6
        assert d.scene.label == ["top-right"] * 4 and d.source.label == ["az=250,el=30"] * 4

    def test_default_target_is_the_scene_itself(self, scene):
        d = relighting(scene, relight_sources(scene.params))
        assert torch.equal(d.target, scene.image) and d.scene is scene
        assert torch.equal(d.layer, scene.shading / d.source.shading)

    @pytest.mark.parametrize("shadows", [False, True])
    def test_range_and_identity_with_and_without_shadows(self, shadows):
        s = generate("train", 6, seed=2, resolution=24, shadows=shadows, dtype=torch.float64)
        d = relighting(s, relight_sources(s.params))
        assert d.layer.min() >= 0.25 and d.layer.max() <= 4.0
        torch.testing.assert_close(d.base * d.layer, d.target, rtol=1e-15, atol=1e-16)
        if shadows:  # A's shadows are lifted and B's cast: the ratio reaches past the unshadowed one
            free = relighting(dataclasses.replace(s, shadows=False), relight_sources(s.params))
            assert not torch.equal(d.layer, free.layer)

    def test_ambient_zero_is_refused(self):
        s = generate("train", 1, resolution=4, ambient=0.0)
        with pytest.raises(LasagnaError, match="ambient: the relight ratio S_B / S_A needs ambient > 0"):
            relighting(s, "top")


class TestSources:
    def test_drawn_in_range_rounded_and_reproducible(self):
        p = sample_scenes("train", 0, range(200))
        conds = relight_sources(p)
        assert conds == relight_sources(p) and conds[5:7] == relight_sources(p.select([5, 6]))
        angles = np.array([parse_direction(c) for c in conds])
        assert angles[:, 0].min() >= 0 and angles[:, 0].max() < 360
        assert RELIGHT_ELEVATION[0] <= angles[:, 1].min() and angles[:, 1].max() <= RELIGHT_ELEVATION[1]
        assert np.allclose(angles * 100, np.rint(angles * 100), atol=1e-6)  # 0.01° steps
        assert len({c for c in conds}) == 200
        assert np.histogram(angles[:, 0], bins=4, range=(0, 360))[0].min() > 30  # spread over all azimuths

    def test_existing_streams_are_untouched(self):
        # The scene's own stream is still keyed exactly as before the relight stream existed …
        import hashlib as h

        tag = f"lasagna.world/v{STREAM_VERSION}/train/3/9".encode()
        key = int.from_bytes(h.blake2b(tag, digest_size=16).digest(), "little")
        old = np.random.Generator(np.random.Philox(key=key)).random(8)
        assert np.array_equal(scene_rng("train", 3, 9).random(8), old)
        assert not np.array_equal(scene_rng("train", 3, 9, stream="relight").random(8), old)
        # … and every split's scene parameters are the very bits they were (digest taken before #11, over the
        # splits that existed then; ``select``, added later, appended its families to the registries).
        digest = hashlib.sha256()
        for split in ("train", "val", "heldout", "far"):
            p = sample_scenes(split, 7, [0, 1, 1000])
            for f in dataclasses.fields(p):
                v = getattr(p, f.name)
                if isinstance(v, torch.Tensor):
                    digest.update(v.numpy().tobytes())
        assert digest.hexdigest() == "093ba162b208b66f83627b770a1bd88bf18fd3caf6284ff0b9a0d279df7f2b67"


def test_cli_writes_valid_relight_stacks(tmp_path, capsys):
    from lasagna.cli import main

    out = tmp_path / "w"
    assert main(["world", "--task", "relight", "-o", str(out), "--split", "heldout", "--count", "2"]) == 0
    assert "wrote 2 relight stacks (heldout, seed 0, 64x64)" in capsys.readouterr().out
    manifest = json.loads((out / "world.json").read_text())
    scene = generate("heldout", 2, 0, 64)
    sources = relight_sources(scene.params)
    for i, entry in enumerate(manifest["scenes"]):
        folder = out / entry["folder"]
        assert main(["validate", str(folder)]) == 0
        doc = json.loads((folder / "stack.json").read_text())
        assert [(x["id"], x["blend"], x["range"]) for x in doc["layers"]] == [
            ("image", "normal", [0.0, 1.0]),
            ("relight", "multiply", [0.0, 4.0]),
        ]
        meta = doc["metadata"]["lasagna.world"]
        assert meta["task"] == "relight" and entry["condition"] == meta["condition"] == scene.label[i]
        assert meta["light"] == list(LIGHTS[scene.label[i]])
        assert meta["source_condition"] == sources[i]
        assert meta["source_light"] == list(condition_direction(sources[i]))
        base, _ = read_png64(folder / "layers" / "image.png")
        ratio, _ = read_png64(folder / "layers" / "relight.png")
        target, _ = read_png64(folder / "composite.png")
        composed = base * (4.0 * ratio)
        assert np.abs(composed - target).max() <= 0.5 / 255 + 4 * 0.5 / 65535 + 1e-12
        # the target is the scene under its own named light: the shading task's composite
        np.testing.assert_array_equal(
            np.rint(target * 255), np.rint(np.clip(scene.image[i].double().numpy(), 0, 1) * 255)
        )
    assert capsys.readouterr().out.count("ok:") == 2


def test_export_refuses_an_ambient_whose_ratio_overflows_the_range(tmp_path):
    from lasagna.world.export import write_world_stacks

    with pytest.raises(LasagnaError, match="ambient: the relight ratio lies in \\[a, 1/a\\]"):
        write_world_stacks(tmp_path / "x", "train", 1, task="relight", ambient=0.2)
    assert not (tmp_path / "x").exists()


def test_lambert_accepts_any_direction():
    n = torch.nn.functional.normalize(torch.randn(1, 3, 5, 5, generator=torch.Generator().manual_seed(0)), dim=1)
    light = torch.tensor([direction_vector(123.0, 17.0)], dtype=torch.float32)
    ref = AMBIENT + (1 - AMBIENT) * (n * light[0].view(1, 3, 1, 1)).sum(1, keepdim=True).clamp_min(0)
    torch.testing.assert_close(lambert(n, light), ref)
