"""Colourisation and additive-light data: exact layer identities and a numpy reference for the glow."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from lasagna.world.scene import generate
from lasagna.world.tasks import additive_light, colorization, glow
from tests.world.helpers import pixel_centres


@pytest.fixture(scope="module")
def scene():
    return generate("val", 6, seed=2, resolution=24, dtype=torch.float64)


class TestColorization:
    def test_base_is_rec709_luma(self, scene):
        c = colorization(scene)
        img = scene.image.numpy()
        ref = 0.2126 * img[:, 0] + 0.7152 * img[:, 1] + 0.0722 * img[:, 2]
        for ch in range(3):
            np.testing.assert_allclose(c.base[:, ch].numpy(), ref, atol=1e-15, rtol=0)
        assert torch.equal(c.target, scene.image)

    def test_normal_layer_with_alpha_one_reproduces_the_target(self, scene):
        c = colorization(scene)
        assert c.layer.shape == (6, 4, 24, 24) and (c.layer[:, 3] == 1).all()
        a = c.layer[:, 3:]
        composed = c.base + a * (c.layer[:, :3] - c.base)  # W3C normal: Cb + α(Cs − Cb)
        torch.testing.assert_close(composed, c.target, atol=1e-15, rtol=0)  # one rounding of Cb + (Cs − Cb)


class TestAdditiveLight:
    def test_identities(self, scene):
        d = additive_light(scene)
        assert d.glow.shape == (6, 3, 24, 24)
        assert d.glow.min() >= 0 and d.lit.max() <= 1
        assert torch.equal(d.lit, d.base + d.glow) and torch.equal(d.base, scene.image)
        assert (d.glow > 0.01).float().mean() > 0.05  # a visible light in the scenes

    def test_glow_reference(self, scene):
        p = scene.params
        x, y = pixel_centres(24)
        for b in range(len(scene)):
            q, c = p.glow_position[b].numpy(), p.glow_color[b].numpy()
            n, rho, z = scene.normals[b].numpy(), scene.albedo[b].numpy(), scene.depth[b, 0].numpy()
            v = np.stack([q[0] - x, q[1] - y, q[2] - z])
            dist = np.linalg.norm(v, axis=0)
            cos = np.maximum(0, (n * v).sum(0) / dist)
            refl = rho * c[:, None, None] * float(p.glow_intensity[b]) * cos / (1 + dist**2)  # d₀ = 1
            sigma = float(p.halo_radius[b])
            halo = (
                c[:, None, None]
                * float(p.halo_intensity[b])
                * np.exp(-((x - q[0]) ** 2 + (y - q[1]) ** 2) / (2 * sigma**2))
            )
            np.testing.assert_allclose(glow(scene.select(b))[0].numpy(), refl + halo, atol=1e-12, rtol=1e-12)
            clipped = np.minimum(refl + halo, 1 - scene.image[b].numpy())
            np.testing.assert_allclose(additive_light(scene.select(b)).glow[0].numpy(), clipped, atol=1e-12)


@pytest.fixture(scope="module")
def many():
    return generate("train", 300, seed=0, resolution=8, dtype=torch.float64)


class TestGlowLabels:
    """The light preset's contract: the glow's colour comes from its label, its light sits near the view axis."""

    def test_colour_lies_in_its_labels_hsv_ranges(self, many):
        import colorsys

        from lasagna.world.lighting import GLOW_TONES, GLOW_VOCABULARY

        p = many.params
        for b in range(len(many)):
            label = GLOW_VOCABULARY[int(p.glow_label[b])]
            h, s, v = colorsys.rgb_to_hsv(*p.glow_color[b].tolist())
            (h0, h1), (s0, s1) = GLOW_TONES[label]
            assert v == pytest.approx(1.0, abs=1e-12)
            assert s0 - 1e-9 <= s <= s1 + 1e-9, (label, s)
            if label != "white":  # white's hue is free (and ill-defined at saturation 0)
                assert h0 - 1e-9 <= h <= h1 + 1e-9, (label, h)

    def test_labels_are_drawn_evenly(self, many):
        counts = torch.bincount(many.params.glow_label, minlength=3)
        assert counts.min() > 300 / 3 - 35  # ±3.5σ of a binomial(300, 1/3) (σ ≈ 8.2)

    def test_light_sits_in_front_of_every_object_near_the_axis(self, many):
        p = many.params
        front = (p.center[..., 2] + p.radius).max()
        assert (p.glow_position[:, 2] > front).all()
        assert p.glow_position[:, :2].abs().max() <= 0.35

    def test_relabelling_keeps_the_tone_and_changes_the_colour(self, scene):
        import colorsys

        from lasagna.world.lighting import GLOW_TONES

        d = additive_light(scene, "cool")
        p = scene.params.with_glow_labels("cool")
        (h0, h1), (s0, s1) = GLOW_TONES["cool"]
        for b in range(len(scene)):
            u_hue, u_sat = scene.params.glow_tone[b].tolist()
            ref = colorsys.hsv_to_rgb(h0 + (h1 - h0) * u_hue, s0 + (s1 - s0) * u_sat, 1.0)
            np.testing.assert_allclose(p.glow_color[b].numpy(), ref, atol=1e-12)
        assert (p.glow_label == 1).all()
        # Only the colour changed: the glow is the unlabelled one rescaled per channel by the colour ratio
        # wherever the head-room clip is inactive.
        raw = glow(scene)
        ratio = (p.glow_color / scene.params.glow_color)[:, :, None, None]
        free = (d.glow < 1 - scene.image - 1e-9) & (raw * ratio < 1 - scene.image - 1e-9)
        np.testing.assert_allclose(d.glow[free].numpy(), (raw * ratio)[free].numpy(), rtol=1e-12, atol=1e-14)

    def test_unknown_glow_label_is_one_clear_error(self, scene):
        from lasagna.errors import ConditionError

        with pytest.raises(ConditionError, match="unknown glow label 'red'; expected one of warm, cool, white"):
            additive_light(scene, "red")
