"""The lighting vocabulary contract and the Lambertian shading formula."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lasagna.errors import ConditionError, LasagnaError
from lasagna.world import lighting
from lasagna.world.lighting import AMBIENT, LIGHTS, VOCABULARY, WALL_SHADING, lambert, light_vectors


class TestVocabulary:
    def test_names_and_order(self):
        assert VOCABULARY == ("left", "right", "top", "bottom", "top-left", "top-right", "bottom-left", "bottom-right")
        assert tuple(LIGHTS) == VOCABULARY

    def test_vectors_match_the_contract(self):
        # Independent closed form in float64: elevation 30° (60° from +z), azimuth per name.
        s, c = np.sin(np.pi / 3), np.cos(np.pi / 3)
        inplane = {
            "left": (-1, 0),
            "right": (1, 0),
            "top": (0, 1),
            "bottom": (0, -1),
            "top-left": (-1, 1),
            "top-right": (1, 1),
            "bottom-left": (-1, -1),
            "bottom-right": (1, -1),
        }
        for name, (ux, uy) in inplane.items():
            norm = math.hypot(ux, uy)
            expected = (s * ux / norm, s * uy / norm, c)
            np.testing.assert_allclose(LIGHTS[name], expected, rtol=0, atol=1e-15)
            assert math.isclose(np.linalg.norm(LIGHTS[name]), 1.0, abs_tol=1e-15)

    def test_contract_text_is_in_the_docstring(self):
        doc = lighting.__doc__
        for phrase in (
            "camera frame x right, y up, z toward the viewer",
            "image row 0\n  is the TOP",
            "`left` = (−sin 60°, 0, cos 60°)",
            "shading = a + (1 − a)·max(0, n·l)",
            "wall's shading is a + (1−a)·cos 60° = 0.625",
        ):
            assert phrase in doc, phrase

    def test_wall_shading_constant(self):
        assert WALL_SHADING == pytest.approx(0.625, abs=1e-15)

    def test_light_vectors_shape_and_values(self):
        t = light_vectors(["top", "bottom-right"], dtype=torch.float64)
        assert t.shape == (2, 3) and t.dtype == torch.float64
        assert t[0].tolist() == list(LIGHTS["top"])

    def test_unknown_label(self):
        with pytest.raises(ConditionError, match="unknown light label 'up'; expected one of left, right"):
            light_vectors(["up"])


class TestLambert:
    def test_reference_values(self):
        rng = np.random.default_rng(0)
        n = rng.normal(size=(2, 3, 4, 5))
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        light = np.array([LIGHTS["left"], LIGHTS["top-right"]])
        expected = AMBIENT + (1 - AMBIENT) * np.maximum(0.0, np.einsum("bchw,bc->bhw", n, light))[:, None]
        got = lambert(torch.from_numpy(n), torch.from_numpy(light))
        assert got.shape == (2, 1, 4, 5)
        np.testing.assert_allclose(got.numpy(), expected, rtol=0, atol=1e-14)

    def test_wall_normal_gives_0625_for_every_label(self):
        n = torch.zeros(8, 3, 2, 2)
        n[:, 2] = 1.0
        got = lambert(n, light_vectors(list(VOCABULARY)))
        assert torch.allclose(got, torch.full_like(got, 0.625), atol=1e-7, rtol=0)

    def test_range_is_ambient_to_one(self):
        n = torch.nn.functional.normalize(torch.randn(1, 3, 32, 32, generator=torch.Generator().manual_seed(1)), dim=1)
        s = lambert(n, light_vectors(["bottom-left"]), ambient=0.1)
        assert s.min() >= 0.1 and s.max() <= 1.0 + 1e-6

    def test_nan_normal_propagates(self):
        n = torch.zeros(1, 3, 1, 2)
        n[:, 2] = 1.0
        n[0, 0, 0, 1] = float("nan")
        s = lambert(n, light_vectors(["left"]))
        assert torch.isfinite(s[0, 0, 0, 0]) and torch.isnan(s[0, 0, 0, 1])

    @pytest.mark.parametrize("a", [-0.1, 1.0, float("nan")])
    def test_bad_ambient(self, a):
        with pytest.raises(LasagnaError, match="ambient: ambient must be in"):
            lambert(torch.zeros(1, 3, 1, 1), light_vectors(["left"]), ambient=a)

    def test_gradcheck(self):
        g = torch.Generator().manual_seed(0)
        n = torch.nn.functional.normalize(torch.randn(1, 3, 3, 3, dtype=torch.float64, generator=g), dim=1)
        n[:, 2] = n[:, 2].abs() + 0.2  # facing the light's side: no n·l at the kink max(0, ·)
        n.requires_grad_()
        light = light_vectors(["top"], dtype=torch.float64)
        assert torch.autograd.gradcheck(lambda x: lambert(x, light), (n,))
