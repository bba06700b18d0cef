"""The surface renderer (lasagna.compose.surface) against closed forms in numpy float64."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lasagna.compose.surface import (
    decode_normal_map,
    encode_normal_map,
    lambert,
    light_vector,
    normals_from_height,
    relight_ratio,
)
from lasagna.errors import LasagnaError

F64 = torch.float64


def np_light(az: float, el: float) -> np.ndarray:
    a, e = math.radians(az), math.radians(el)
    return np.array([math.sin(e) * math.cos(a), math.sin(e) * math.sin(a), math.cos(e)])


def random_normals(rng, b=2, h=5, w=7) -> np.ndarray:
    n = rng.normal(size=(b, 3, h, w))
    n[:, 2] = np.abs(n[:, 2]) + 0.1  # facing the viewer, as a visible surface does
    return n / np.linalg.norm(n, axis=1, keepdims=True)


class TestLambert:
    def test_reference(self):
        rng = np.random.default_rng(0)
        n = random_normals(rng)
        for az, el, a in ((0, 60, 0.25), (123.4, 17.0, 0.0), (270, 89, 0.5)):
            ref = a + (1 - a) * np.maximum(0, np.einsum("bchw,c->bhw", n, np_light(az, el)))[:, None]
            got = lambert(torch.from_numpy(n), light_vector(az, el, dtype=F64), a)
            np.testing.assert_allclose(got.numpy(), ref, atol=1e-14)

    def test_named_light_is_the_worlds(self):
        from lasagna.world.lighting import LIGHTS

        np.testing.assert_allclose(light_vector(180, 60, dtype=F64).numpy(), LIGHTS["left"], atol=1e-15)

    def test_batch_independent(self):
        rng = np.random.default_rng(1)
        n = torch.from_numpy(random_normals(rng, b=3)).float()
        lights = torch.stack([light_vector(a, 40) for a in (0, 90, 200)])
        whole = lambert(n, lights)
        for i in range(3):
            assert torch.equal(lambert(n[i : i + 1], lights[i : i + 1]), whole[i : i + 1])

    def test_bad_ambient(self):
        with pytest.raises(LasagnaError, match="ambient must be in"):
            lambert(torch.zeros(1, 3, 2, 2), light_vector(0, 10), 1.0)


class TestHeight:
    def test_plane_is_exact(self):
        # h = αx + βy in canvas units (2 units wide): n = (−α, −β, 1)/‖·‖ everywhere, borders included.
        h_, w_ = 9, 12
        x = (np.arange(w_) + 0.5) * 2 / w_ - 1
        y = 1 - (np.arange(h_) + 0.5) * 2 / w_  # rows run down; pixels are square
        alpha, beta = 0.7, -0.4
        height = alpha * x[None, :] + beta * y[:, None]
        n = normals_from_height(torch.from_numpy(height)[None, None])
        ref = np.array([-alpha, -beta, 1.0]) / math.sqrt(alpha**2 + beta**2 + 1)
        np.testing.assert_allclose(n[0].numpy(), np.broadcast_to(ref[:, None, None], (3, h_, w_)), atol=1e-12)

    def test_rising_toward_the_top_faces_down(self):
        # A ramp that rises toward row 0 (the top) tilts its normal toward −y: lit from the bottom, it is brighter.
        height = torch.linspace(1, 0, 8, dtype=F64)[:, None].expand(8, 8)[None, None]
        n = normals_from_height(height)
        assert (n[:, 1] < 0).all()
        assert (lambert(n, light_vector(270, 60, dtype=F64)) > lambert(n, light_vector(90, 60, dtype=F64))).all()

    def test_hemisphere(self):
        # h = √(r² − x² − y²) has n = (x, y, h)/r; central differences are second-order accurate inside.
        w_ = 128
        c = (np.arange(w_) + 0.5) * 2 / w_ - 1
        x, y = c[None, :], -c[:, None]
        r = 0.8
        inside = x**2 + y**2 < (0.9 * r) ** 2
        h = np.sqrt(np.clip(r * r - x * x - y * y, 0, None))
        n = normals_from_height(torch.from_numpy(h)[None, None])[0].numpy()
        ref = np.stack(np.broadcast_arrays(x / r, y / r, h / r))
        assert np.abs(n - ref)[:, inside].max() < 2e-3

    def test_shape(self):
        with pytest.raises(LasagnaError, match=r"height: got shape \(2, 3, 4\); expected \(B, 1, H, W\)"):
            normals_from_height(torch.zeros(2, 3, 4))

    def test_gradcheck(self):
        torch.manual_seed(0)
        h = (0.1 * torch.randn(1, 1, 5, 6, dtype=F64)).requires_grad_()
        light = light_vector(30, 50, dtype=F64)
        # n·l > 0 everywhere for this gentle field, so the clamp's kink is not on the path.
        assert (normals_from_height(h) * light[:, None, None]).sum(1).min() > 0
        assert torch.autograd.gradcheck(lambda t: lambert(normals_from_height(t), light), (h,))


class TestRatio:
    def test_relights_exactly(self):
        rng = np.random.default_rng(3)
        n = torch.from_numpy(random_normals(rng))
        src, tgt = light_vector(180, 60, dtype=F64), light_vector(0, 60, dtype=F64)
        ratio = relight_ratio(n, tgt, src)
        torch.testing.assert_close(ratio * lambert(n, src), lambert(n, tgt), atol=1e-15, rtol=0)
        assert ratio.max() <= 1 / 0.25 + 1e-12

    def test_needs_ambient(self):
        with pytest.raises(LasagnaError, match="needs an ambient term a > 0"):
            relight_ratio(torch.zeros(1, 3, 1, 1), light_vector(0, 0), light_vector(0, 0), 0.0)


class TestNormalMap:
    def test_opengl_convention(self):
        # +Y up: a normal tilted toward the top of the image has green above 0.5 (Blender, Krita, Godot).
        up = torch.tensor([0.0, math.sin(0.5), math.cos(0.5)], dtype=F64)[None, :, None, None]
        rgb = encode_normal_map(up)
        assert rgb[0, 1, 0, 0] > 0.5 and rgb[0, 0, 0, 0] == 0.5
        np.testing.assert_allclose(decode_normal_map(rgb).numpy(), up.numpy(), atol=1e-15)
        flipped = decode_normal_map(rgb, convention="directx")
        np.testing.assert_allclose(flipped[0, 1].numpy(), -up[0, 1].numpy(), atol=1e-15)

    @settings(max_examples=40, deadline=None)
    @given(seed=st.integers(0, 2**31 - 1), az=st.floats(0, 359.99), el=st.floats(0, 89.9))
    def test_sixteen_bit_round_trip_bound(self, seed, az, el):
        """Property: shading from a 16-bit map is within 3e-5 of shading from the exact normals."""
        n = torch.from_numpy(random_normals(np.random.default_rng(seed)))
        stored = torch.round(encode_normal_map(n) * 65535) / 65535
        light = light_vector(az, el, dtype=F64)
        err = (lambert(decode_normal_map(stored), light) - lambert(n, light)).abs().max()
        assert err < 3e-5

    def test_zero_vector_is_flat(self):
        n = decode_normal_map(torch.full((1, 3, 1, 1), 0.5, dtype=F64))
        assert n.flatten().tolist() == [0.0, 0.0, 1.0]

    def test_unknown_convention(self):
        with pytest.raises(LasagnaError, match="unknown normal-map convention 'vulkan'"):
            decode_normal_map(torch.zeros(1, 3, 1, 1), convention="vulkan")


class TestInflate:
    def test_disc_inflates_to_a_hemisphere(self):
        # A disc of radius r (pixels) → h = √(R² − (R − d)²) with d = r − ρ: the hemisphere √(R² − ρ²) when
        # R = r; the normals match (x, y, h)/R inside, away from the rim's pixel steps.
        from lasagna.compose.surface import inflate_regions

        w_, r = 96, 30.0
        c = np.arange(w_) + 0.5 - w_ / 2
        x, y = c[None, :], -c[:, None]
        rho = np.hypot(x, y)
        index = torch.from_numpy(np.where(rho < r, 3, -1))[None, None]
        h = inflate_regions(index)
        assert float(h[0, 0][torch.from_numpy(rho >= r)].abs().max()) == 0.0  # the wall stays flat
        n = normals_from_height(h)[0].numpy()
        big_r = float(h.max()) * w_ / 2  # the dome's height in pixels is its radius
        assert abs(big_r - r) < 1.0
        # Heights within a pixel and a half of the hemisphere (d is measured between pixel centres of a
        # jagged, pixelated outline); normals within 0.03 on average inside 0.8 r.
        hp = np.sqrt(np.clip(big_r**2 - rho**2, 0, None))
        disc = rho < 0.9 * r  # at the rim dh/dd is unbounded: half a pixel of d is many of h
        assert np.abs(h[0, 0].numpy() * w_ / 2 - hp)[disc].max() < 1.5
        inside = rho < 0.8 * r
        ref = np.stack(np.broadcast_arrays(x / big_r, y / big_r, hp / big_r))
        assert np.abs(n - ref)[:, inside].mean() < 0.03


class TestFitLight:
    def test_recovers_the_light_of_exact_shading(self):
        from lasagna.compose.surface import fit_light

        rng = np.random.default_rng(5)
        n = torch.from_numpy(random_normals(rng, b=3, h=16, w=16))
        lights = torch.stack([light_vector(a, e, dtype=F64) for a, e in ((10, 30), (200, 55), (300, 75))])
        got = fit_light(n, lambert(n, lights))
        # The ridge (1e-3 of the lit pixels' second moment) biases the solution by about that much.
        torch.testing.assert_close(got, lights, atol=5e-3, rtol=0)

    def test_flat_surface_keeps_a_valid_light(self):
        from lasagna.compose.surface import MAX_FIT_ELEVATION, fit_light

        flat = torch.zeros(1, 3, 4, 4, dtype=F64)
        flat[:, 2] = 1
        got = fit_light(flat, lambert(flat, light_vector(90, 40, dtype=F64)[None]))
        assert torch.isfinite(got).all() and abs(float(got.norm()) - 1) < 1e-12
        assert float(got[0, 2]) >= math.cos(math.radians(MAX_FIT_ELEVATION)) - 1e-12

    def test_differentiable(self):
        from lasagna.compose.surface import fit_light

        rng = np.random.default_rng(6)
        n = torch.from_numpy(random_normals(rng, b=1, h=4, w=4))
        s = lambert(n, light_vector(30, 40, dtype=F64)[None]).requires_grad_()
        assert torch.autograd.gradcheck(lambda t: fit_light(n, t), (s,))


class TestTurnToAzimuth:
    """``turn_to_azimuth``: a given source light adopted by turning the estimate about the view axis."""

    @settings(max_examples=25, deadline=None)
    @given(st.floats(0, 360), st.floats(5, 80), st.floats(0, 360), st.floats(5, 80), st.integers(0, 2**31 - 1))
    def test_keeps_the_source_shading_in_the_given_frame_and_walls_flat(self, az_f, el_f, az_g, el_g, seed):
        from lasagna.compose.surface import turn_to_azimuth

        rng = np.random.default_rng(seed)
        n = random_normals(rng, b=1, h=6, w=5)
        n[0, :, 0, 0] = (0.0, 0.0, 1.0)  # a flat wall's pixel
        fit, give = light_vector(az_f, el_f, dtype=F64)[None], light_vector(az_g, el_g, dtype=F64)[None]
        got = turn_to_azimuth(torch.from_numpy(n), fit, give)
        # The reference: the rotation by the azimuth difference about z, in numpy float64.
        a = math.radians(az_g - az_f)
        rot = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
        want = np.einsum("ij,bjhw->bihw", rot, n)
        np.testing.assert_allclose(got.numpy(), want, atol=1e-12)
        # n·l_fit is kept when the light is turned alike: the fitted light at the given azimuth.
        turned_light = torch.from_numpy(np_light(az_g, el_f))[None]
        torch.testing.assert_close(lambert(got, turned_light), lambert(torch.from_numpy(n), fit), atol=1e-12, rtol=0)
        np.testing.assert_allclose(got[0, :, 0, 0].numpy(), (0.0, 0.0, 1.0), atol=1e-15)
        np.testing.assert_allclose(np.linalg.norm(got.numpy(), axis=1), 1.0, atol=1e-12)

    def test_a_light_on_the_view_axis_turns_nothing(self):
        from lasagna.compose.surface import turn_to_azimuth

        n = torch.from_numpy(random_normals(np.random.default_rng(3), b=2))
        axis = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], dtype=F64)
        side = torch.stack([light_vector(90, 40, dtype=F64), light_vector(200, 30, dtype=F64)])
        assert torch.equal(turn_to_azimuth(n, axis, side), n) and torch.equal(turn_to_azimuth(n, side, axis), n)
        assert turn_to_azimuth(n.float(), side, side.flip(0)).dtype == torch.float32


def bfs_regions(mask: np.ndarray) -> list[set]:
    """The 8-connected regions of a 2-D boolean array, by breadth-first flood fill (the reference)."""
    seen, regions = np.zeros_like(mask, dtype=bool), []
    h, w = mask.shape
    for r0 in range(h):
        for c0 in range(w):
            if not mask[r0, c0] or seen[r0, c0]:
                continue
            region, queue = set(), [(r0, c0)]
            seen[r0, c0] = True
            while queue:
                r, c = queue.pop()
                region.add((r, c))
                for dr in (-1, 0, 1):
                    for dc in (-1, 0, 1):
                        rr, cc = r + dr, c + dc
                        if 0 <= rr < h and 0 <= cc < w and mask[rr, cc] and not seen[rr, cc]:
                            seen[rr, cc] = True
                            queue.append((rr, cc))
            regions.append(region)
    return regions


class TestDomePrior:
    @settings(max_examples=40, deadline=None)
    @given(st.integers(0, 2**31 - 1), st.floats(0.2, 0.8))
    def test_regions_are_the_flood_fill_regions(self, seed, density):
        from lasagna.compose.surface import label_regions

        mask = np.random.default_rng(seed).random((2, 1, 9, 11)) < density
        index = label_regions(torch.from_numpy(mask)).numpy()
        for b in range(2):
            want = bfs_regions(mask[b, 0])
            got = [set(zip(*np.nonzero(index[b, 0] == k), strict=True)) for k in range(index[b, 0].max() + 1)]
            assert sorted(map(sorted, got)) == sorted(map(sorted, want))
            assert (index[b, 0][~mask[b, 0]] == -1).all()

    def test_a_spiral_is_one_region(self):
        from lasagna.compose.surface import label_regions

        mask = np.zeros((9, 9), dtype=bool)
        mask[0, :] = mask[:, 8] = mask[8, :] = mask[2:, 0] = mask[2, :7] = mask[2:7, 6] = mask[6, 2:7] = True
        index = label_regions(torch.from_numpy(mask)[None, None])
        assert index.max() == 0 and (index[0, 0][torch.from_numpy(mask)] == 0).all()

    def test_domes_scale_the_height_and_stay_flat_outside(self):
        from lasagna.compose.surface import dome_normals, inflate_regions, inflated_normals

        yy, xx = np.mgrid[:21, :21]
        index = torch.from_numpy(np.where((yy - 10) ** 2 + (xx - 10) ** 2 <= 49, 0, -1))[None, None]
        torch.testing.assert_close(dome_normals(index, 1.0), inflated_normals(index), atol=0, rtol=0)
        half = dome_normals(index, 0.5)
        inside = index[0, 0] >= 0
        want = normals_from_height(inflate_regions(index) * 0.5)
        torch.testing.assert_close(half[..., inside], want[..., inside], atol=1e-12, rtol=0)
        assert (half[0, 2][~inside] == 1).all()

    def test_deepening_normals_scales_a_height_fields_slopes(self):
        """``deepen_normals(n(h), g)`` is n(g·h): checked on a random quadratic surface, whose normals are known in
        closed form (float64 numpy: n ∝ (−∂h/∂x, −∂h/∂y, 1))."""
        from lasagna.compose.surface import deepen_normals

        rng = np.random.default_rng(9)
        a, b, c, d = rng.normal(size=4)
        y, x = np.mgrid[-1:1:17j, -1:1:23j]
        hx, hy = 2 * a * x + c * y + d, 2 * b * y + c * x  # h = a x² + b y² + c x y + d x

        def closed(g):
            v = np.stack([-g * hx, -g * hy, np.ones_like(x)])[None]
            return v / np.linalg.norm(v, axis=1, keepdims=True)

        n = torch.from_numpy(closed(1.0))
        for g in (0.5, 2.0, 3.0):
            torch.testing.assert_close(deepen_normals(n, g).numpy(), closed(g), atol=1e-12, rtol=0)
        assert deepen_normals(n, 1.0) is n
        flat = torch.zeros(1, 3, 2, 2, dtype=torch.float64)
        flat[:, 2] = 1
        torch.testing.assert_close(deepen_normals(flat, 4.0), flat)  # the flat wall stays flat

    def test_mixing_normals(self):
        from lasagna.compose.surface import mix_normals

        rng = np.random.default_rng(5)
        a, b = (torch.from_numpy(random_normals(rng)) for _ in range(2))
        torch.testing.assert_close(mix_normals(a, b, 0.0), a, atol=1e-12, rtol=0)
        torch.testing.assert_close(mix_normals(a, b, 1.0), b, atol=1e-12, rtol=0)
        half = (a + b).numpy()
        torch.testing.assert_close(mix_normals(a, b, 0.5).numpy(), half / np.linalg.norm(half, axis=1, keepdims=True))


class TestFlatWalls:
    """``flatten_walls``: the walls' large-scale tilt removed, their relief and the objects kept (closed forms in
    float64 numpy)."""

    @staticmethod
    def normals(hx: np.ndarray, hy: np.ndarray) -> torch.Tensor:
        v = np.stack([-hx, -hy, np.ones_like(hx)])[None]
        return torch.from_numpy(v / np.linalg.norm(v, axis=1, keepdims=True))

    def test_a_tilted_wall_becomes_flat_and_a_ripple_keeps_its_closed_form_share(self):
        from lasagna.compose.surface import flatten_walls

        rng = np.random.default_rng(4)
        p, q = rng.normal(size=2) * 0.3
        y, x = np.mgrid[0:48, 0:48].astype(np.float64)
        walls = torch.ones(1, 1, 48, 48, dtype=F64)
        tilted = self.normals(np.full_like(x, p), np.full_like(x, q))  # a plane: constant slopes
        flat = flatten_walls(tilted, walls, 6.0)
        torch.testing.assert_close(flat[:, :2], torch.zeros_like(flat[:, :2]), atol=1e-12, rtol=0)
        # A ripple of wavelength λ on the tilt: its slope 2πA/λ·cos(2πx/λ) keeps 1 − exp(−2π²σ²/λ²) of itself
        # (the Gaussian's response to a cosine), away from the mirrored borders.
        lam, amp, sigma = 12.0, 0.4, 3.0
        ripple = 2 * math.pi * amp / lam * np.cos(2 * math.pi * x / lam)
        got = flatten_walls(self.normals(p + ripple, np.full_like(x, q)), walls, sigma)
        slope = (got[0, 0] / got[0, 2]).numpy()
        keep = 1 - math.exp(-2 * math.pi**2 * sigma**2 / lam**2)
        inner = (slice(12, 36), slice(12, 36))
        np.testing.assert_allclose(-slope[inner], keep * ripple[inner], atol=2e-3)
        assert flatten_walls(tilted, walls, 0.0) is tilted

    def test_the_objects_keep_their_slopes_and_the_wall_around_them_is_flattened(self):
        from lasagna.compose.surface import flatten_walls

        y, x = np.mgrid[0:32, 0:32].astype(np.float64)
        inside = (y - 16) ** 2 + (x - 16) ** 2 < 36
        hx = np.where(inside, (x - 16) / 6, 0.2)  # an object on a wall tilted by 0.2
        n = self.normals(hx, np.zeros_like(x))
        walls = torch.from_numpy(np.where(inside, 0.0, 1.0))[None, None]
        got = flatten_walls(n, walls, 8.0)
        torch.testing.assert_close(got[..., torch.from_numpy(inside)], n[..., torch.from_numpy(inside)])
        # the wall's mean is taken over the walls alone, so the object's slopes do not leak into it
        torch.testing.assert_close(got[0, 0][~torch.from_numpy(inside)], torch.zeros(int((~inside).sum()), dtype=F64))
        torch.testing.assert_close(got.norm(dim=1), torch.ones(1, 32, 32, dtype=F64))

    @settings(max_examples=30, deadline=None)
    @given(gain=st.floats(0.0, 1.0, allow_nan=False), seed=st.integers(0, 2**16), margin=st.sampled_from([0, 1, 2]))
    def test_calm_walls_scale_each_pixels_slopes_by_its_eroded_wall_weight(self, gain, seed, margin):
        """``calm_walls``: slopes p = n_xy/n_z times 1 − w + g·w per pixel, w the walls eroded by ``margin`` pixels
        (the least in each window, numpy float64), the objects (w = 0) and their rims within the margin untouched, a
        wall (w = 1) of gain 0 flat beyond the margin."""
        from lasagna.compose.surface import calm_walls

        rng = np.random.default_rng(seed)
        hx, hy = rng.normal(size=(2, 12, 10)) * 0.4
        w = rng.uniform(size=(12, 10))
        w[:3] = 0.0  # objects
        w[-5:] = 1.0  # walls
        padded = np.pad(w, margin, constant_values=np.inf)
        eroded = np.min(
            [padded[i : i + 12, j : j + 10] for i in range(2 * margin + 1) for j in range(2 * margin + 1)], axis=0
        )
        got = calm_walls(self.normals(hx, hy), torch.from_numpy(w)[None, None], gain, margin=margin)
        k = 1 - eroded + gain * eroded
        torch.testing.assert_close(got, self.normals(hx * k, hy * k), atol=1e-12, rtol=0)
        n = self.normals(hx, hy)
        rim = 3 + margin  # the objects' rows and the rows the erosion reaches from them
        torch.testing.assert_close(got[..., :rim, :], n[..., :rim, :], atol=1e-12, rtol=0)
        if gain == 0.0:
            flat = got[0, :2, -(5 - margin) :]
            torch.testing.assert_close(flat, torch.zeros_like(flat), atol=1e-12, rtol=0)
        assert calm_walls(n, torch.from_numpy(w)[None, None], 1.0) is n

    def test_a_calmed_walls_ratio_leaks_twenty_log_gain_less(self):
        from lasagna.compose.surface import calm_walls

        rng = np.random.default_rng(3)
        hx, hy = rng.normal(size=(2, 32, 32)) * 0.01  # paint read as faint relief
        n, walls = self.normals(hx, hy), torch.ones(1, 1, 32, 32, dtype=F64)
        src = torch.tensor([[0.5, 0.0, math.sqrt(0.75)]], dtype=F64)
        tgt = torch.tensor([[-0.5, 0.3, math.sqrt(0.66)]], dtype=F64)

        def leak(m):
            r = lambert(m, tgt) / lambert(m, src)
            return 10 * math.log10(1.0 / float(((r - r.mean()) ** 2).mean()))

        for gain in (0.5, 0.25):
            assert leak(calm_walls(n, walls, gain)) - leak(n) == pytest.approx(-20 * math.log10(gain), abs=0.05)


@settings(max_examples=40, deadline=None)
@given(
    g1=st.floats(0.1, 8.0, allow_nan=False),
    g2=st.floats(0.1, 8.0, allow_nan=False),
    seed=st.integers(0, 2**16),
)
def test_relief_gains_compose_and_a_relieved_map_round_trips(g1, g2, seed):
    """The relief gain is the normals of g·h, so gains compose: deepen(deepen(n, g1), g2) = deepen(n, g1·g2)
    (float64), and a map deepened by ``relieved_map`` decodes to the deepened normals within its quantisation."""
    from lasagna.compose.surface import deepen_normals, relieved_map

    rng = np.random.default_rng(seed)
    n = torch.from_numpy(random_normals(rng))
    torch.testing.assert_close(
        deepen_normals(deepen_normals(n, g1), g2), deepen_normals(n, g1 * g2), atol=1e-12, rtol=0
    )
    codes = encode_normal_map(n)
    back = decode_normal_map(relieved_map(codes, g1))
    torch.testing.assert_close(back, deepen_normals(decode_normal_map(codes), g1), atol=1e-9, rtol=0)
    assert relieved_map(codes, 1.0) is codes


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(-16.0, 17.0),
    y=st.floats(-16.0, 17.0),
    z=st.floats(1e-3, 64.0),
    h=st.integers(1, 9),
    w=st.integers(1, 9),
    seed=st.integers(0, 2**16),
)
def test_a_point_light_is_finite_bounded_and_its_closed_form(x, y, z, h, w, seed):
    """Anywhere a point light may stand (`parse_point`'s ranges) and over any unit normals, `point_lambert` is
    finite, in [a, 1] (its falloff is at most 1), and equals numpy float64 of the closed form — each pixel's own unit
    vector to the light, (z/|d|)² falloff."""
    from lasagna.compose.surface import point_lambert

    n = random_normals(np.random.default_rng(seed), b=1, h=h, w=w)
    got = point_lambert(torch.from_numpy(n), (x, y, z)).numpy()
    side = max(h, w)
    jj, ii = np.meshgrid(np.arange(w), np.arange(h))
    d = np.stack([(x - (jj + 0.5) / w) * w / side, ((ii + 0.5) / h - y) * h / side, np.full((h, w), z)])
    r = np.linalg.norm(d, axis=0)
    ref = 0.25 + 0.75 * (z / r) ** 2 * np.maximum(0.0, (n[0] * d / r).sum(0))
    assert np.isfinite(got).all() and got.min() >= 0.25 - 1e-12 and got.max() <= 1.0 + 1e-12
    np.testing.assert_allclose(got[0, 0], ref, rtol=1e-12, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(-2.0, 3.0),
    y=st.floats(-2.0, 3.0),
    z=st.floats(1e-2, 8.0),
    cone=st.floats(0.5, 90.0),
    ax=st.floats(-2.0, 3.0),
    ay=st.floats(-2.0, 3.0),
    blend=st.sampled_from([0.0, 0.15, 1.0]) | st.floats(0.01, 1.0),
    seed=st.integers(0, 2**16),
)
def test_a_spot_light_is_the_point_light_times_blenders_spot_mask(x, y, z, cone, ax, ay, blend, seed):
    """Any spot `parse_point` accepts renders numpy float64 of its closed form (`spot_reference`), finite and in
    [a, 1]; no brighter anywhere than the same point light without a cone."""
    from lasagna.compose.surface import point_lambert
    from lasagna.document.condition import PointLight
    from tests.support.lights import spot_reference

    n = random_normals(np.random.default_rng(seed), b=1, h=7, w=5)
    spot = PointLight(x, y, z, cone, ax, ay, blend)
    got = point_lambert(torch.from_numpy(n), spot).numpy()
    ref = spot_reference(n[0], x, y, z, cone, ax, ay, blend)
    if blend == 0:  # a hard edge: a ray on the cone's edge to the last bits may fall either side
        close = np.isclose(got[0, 0], ref, rtol=0, atol=1e-12)
        assert close.mean() > 0.9
    else:
        np.testing.assert_allclose(got[0, 0], ref, rtol=1e-9, atol=1e-12)
    assert np.isfinite(got).all() and got.min() >= 0.25 - 1e-12 and got.max() <= 1.0 + 1e-12
    assert (got <= point_lambert(torch.from_numpy(n), (x, y, z)).numpy() + 1e-12).all()


def test_a_spot_aimed_straight_down_lights_a_disc_of_its_cone():
    """A hard-edged spot (blend 0) straight down over a flat map lights exactly the pixels within z·tan C of the
    point beneath it, as a point light does there, and leaves the rest at the ambient; an aim to one side moves the
    lit patch that way."""
    from lasagna.compose.surface import point_lambert
    from lasagna.document.condition import PointLight

    flat = torch.zeros(1, 3, 41, 41, dtype=torch.float64)
    flat[:, 2] = 1
    got = point_lambert(flat, PointLight(0.5, 0.5, 0.25, 30.0, 0.5, 0.5, 0.0))[0, 0].numpy()
    jj, ii = np.meshgrid(np.arange(41), np.arange(41))
    rho = np.hypot((jj + 0.5) / 41 - 0.5, (ii + 0.5) / 41 - 0.5)
    inside = rho < 0.25 * np.tan(np.radians(30.0)) - 1e-9
    outside = rho > 0.25 * np.tan(np.radians(30.0)) + 1e-9
    point = point_lambert(flat, (0.5, 0.5, 0.25))[0, 0].numpy()
    np.testing.assert_allclose(got[inside], point[inside], rtol=0, atol=1e-12)
    assert (got[outside] == 0.25).all() and inside.sum() > 50
    right = point_lambert(flat, PointLight(0.5, 0.5, 0.25, 30.0, 0.8, 0.5, 0.0))[0, 0].numpy()
    lit = np.argwhere(right > 0.25)
    assert lit[:, 1].mean() > 25 and np.isclose(lit[:, 0].mean(), 20, atol=0.5)


@pytest.mark.parametrize("shape", [(48, 48), (36, 60)])
def test_integrating_a_height_fields_normals_returns_it(shape):
    """``integrate_normals`` inverts ``normals_from_height`` up to a constant (least value 0): two Gaussian bumps on a
    square and on a wide canvas come back within 2 % of their peak; a flat map integrates to zeros."""
    from lasagna.compose.surface import integrate_normals

    h, w = shape
    y, x = torch.meshgrid(
        torch.linspace(-h / w, h / w, h, dtype=torch.float64),
        torch.linspace(-1, 1, w, dtype=torch.float64),
        indexing="ij",
    )
    bump = (0.3 * torch.exp(-(x**2 + y**2) / 0.15) + 0.1 * torch.exp(-((x - 0.5) ** 2 + (y + 0.2) ** 2) / 0.05))[
        None, None
    ]
    got = integrate_normals(normals_from_height(bump))
    want = bump - bump.min()
    assert float((got - want).abs().max()) < 0.02 * float(want.max())
    flat = torch.zeros(1, 3, h, w, dtype=torch.float64)
    flat[:, 2] = 1.0
    assert float(integrate_normals(flat).abs().max()) < 1e-12


@pytest.mark.parametrize("blend", [0.0, 0.3])
def test_a_spot_lights_highlight_carries_its_falloff_and_cone(blend):
    """``highlight`` of a spot light: the Blinn–Phong term per pixel along its own vector to the light, times the
    light's falloff and cone (numpy float64 of their closed forms, tests/support/lights.py), zero outside the cone."""
    from lasagna.compose.surface import highlight
    from tests.support.lights import blinn_phong, spot_field

    torch.manual_seed(3)
    n = normals_from_height(0.1 * torch.randn(1, 1, 20, 28, dtype=torch.float64))
    text = f"x=0.3,y=0.4,z=0.5,cone=30,ax=0.6,ay=0.5,blend={blend}"
    got = highlight(n, text, 12.0)[0, 0].numpy()
    l_vec, weight = spot_field(n.shape, 0.3, 0.4, 0.5, 30.0, 0.6, 0.5, blend)
    want = blinn_phong(n[0].numpy(), l_vec, 12.0) * weight
    np.testing.assert_allclose(got, want, atol=1e-9)
    assert (want == 0).any() and (want > 0.05).any()  # the cone's outside dark, a highlight inside
