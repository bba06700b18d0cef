"""Exact ray intersections of every shape family, against closed forms in float64."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from lasagna.world.shapes import MAX_BOUNDING_RADIUS, SHAPES

F64 = torch.float64


def rays(origins, directions):
    o = torch.tensor(origins, dtype=F64).reshape(-1, 3)
    d = torch.tensor(directions, dtype=F64).reshape(-1, 3)
    d = d / d.norm(dim=1, keepdim=True)
    return tuple(o.T), tuple(d.T)


def sizes(m, s):
    return tuple(torch.full((m,), float(v), dtype=F64) for v in s)


def cast(family, origins, directions, size, t_min=0.0):
    o, d = rays(origins, directions)
    t, n = SHAPES[family].intersect(o, d, sizes(o[0].shape[0], size), t_min)
    return t.numpy(), np.stack([c.numpy() for c in n], 1)


DOWN = (0.0, 0.0, -1.0)


class TestClosedForms:
    def test_sphere_front_point_and_normal(self):
        # Sphere of radius 0.5: a ray down −z at (x, y) meets z = √(r² − x² − y²), normal p/r.
        pts = [(0.1, -0.2), (0.0, 0.0), (0.3, 0.35)]
        t, n = cast("ellipsoid", [(x, y, 2.0) for x, y in pts], [DOWN] * 3, (0.5, 0.5, 0.5))
        for (x, y), ti, ni in zip(pts, t, n):
            z = math.sqrt(0.25 - x * x - y * y)
            assert ti == pytest.approx(2.0 - z, abs=1e-12)
            np.testing.assert_allclose(ni, np.array([x, y, z]) / 0.5, atol=1e-12)

    def test_ellipsoid_axes(self):
        t, n = cast(
            "ellipsoid", [(3.0, 0, 0), (0, 3.0, 0), (0, 0, 3.0)], [(-1, 0, 0), (0, -1, 0), (0, 0, -1)], (0.2, 0.3, 0.4)
        )
        np.testing.assert_allclose(t, [2.8, 2.7, 2.6], atol=1e-12)
        np.testing.assert_allclose(n, np.eye(3), atol=1e-12)

    def test_box_faces(self):
        t, n = cast(
            "box",
            [(0.05, -0.1, 2.0), (2.0, 0.1, 0.0), (0.0, -2.0, 0.1)],
            [DOWN, (-1, 0, 0), (0, 1, 0)],
            (0.2, 0.3, 0.4),
        )
        np.testing.assert_allclose(t, [1.6, 1.8, 1.7], atol=1e-12)
        np.testing.assert_allclose(n, [[0, 0, 1], [1, 0, 0], [0, -1, 0]], atol=0)

    def test_cylinder_cap_and_side(self):
        # Axis y, radius 0.3, half-height 0.4: down the axis meets the cap y = 0.4; along −z the side.
        t, n = cast("cylinder", [(0.1, 2.0, 0.0), (0.1, 0.2, 2.0)], [(0, -1, 0), DOWN], (0.3, 0.4, 0.0))
        z = math.sqrt(0.09 - 0.01)
        np.testing.assert_allclose(t, [1.6, 2.0 - z], atol=1e-12)
        np.testing.assert_allclose(n, [[0, 1, 0], [0.1 / 0.3, 0, z / 0.3]], atol=1e-12)

    def test_torus_ring_and_hole(self):
        # Ring in the xz plane (around y), R = 0.3, r = 0.1: down −y at x = R meets y = r; at x = 0 the hole.
        t, n = cast(
            "torus", [(0.3, 2.0, 0.0), (0.0, 2.0, 0.0), (0.0, 0.0, 2.0)], [(0, -1, 0)] * 2 + [DOWN], (0.3, 0.1, 0.0)
        )
        assert t[0] == pytest.approx(1.9, abs=1e-5)
        np.testing.assert_allclose(n[0], [0, 1, 0], atol=1e-4)
        assert np.isinf(t[1])
        assert t[2] == pytest.approx(2.0 - 0.4, abs=1e-5)  # along −z through the centre: outer equator
        np.testing.assert_allclose(n[2], [0, 0, 1], atol=1e-4)

    def test_capsule_tip_and_side(self):
        t, n = cast("capsule", [(0.0, 2.0, 0.0), (0.0, 0.05, 2.0)], [(0, -1, 0), DOWN], (0.15, 0.2, 0.0))
        np.testing.assert_allclose(t, [2.0 - 0.35, 2.0 - 0.15], atol=1e-12)
        np.testing.assert_allclose(n, [[0, 1, 0], [0, 0, 1]], atol=1e-12)

    def test_cone_apex_side_and_base(self):
        # Base radius 0.3 at y = −0.4, apex at y = 0.4: at height y the radius is 0.3·(0.4 − y)/0.8.
        t, n = cast("cone", [(0.0, 0.0, 2.0), (0.05, -2.0, 0.0)], [DOWN, (0, 1, 0)], (0.3, 0.4, 0.0))
        k = 0.3 / 0.8
        np.testing.assert_allclose(t, [2.0 - 0.4 * k, 1.6], atol=1e-12)
        side = np.array([0.0, k, 1.0]) / math.hypot(k, 1.0)  # outward normal of the side at (0, 0, 0.4k)
        np.testing.assert_allclose(n, [side, [0, -1, 0]], atol=1e-12)

    @pytest.mark.parametrize("family", sorted(SHAPES))
    def test_miss_is_inf(self, family):
        t, _ = cast(family, [(5.0, 5.0, 2.0)], [DOWN], (0.2, 0.2, 0.2))
        assert np.isinf(t).all()

    @pytest.mark.parametrize("family", sorted(SHAPES))
    def test_t_min_skips_hits_behind(self, family):
        # From the centre outward, only the exit point lies ahead; from beyond the shape, nothing.
        t, _ = cast(family, [(0.0, 0.0, 2.0)], [DOWN], (0.3, 0.1, 0.3), t_min=3.0)
        assert np.isinf(t).all()

    def test_zero_direction_component_box(self):
        # d has exact zeros in x and y: the slab test must neither NaN nor miss.
        t, n = cast("box", [(0.0, 0.0, 1.0)], [DOWN], (0.2, 0.2, 0.2))
        assert t[0] == pytest.approx(0.8) and n[0].tolist() == [0, 0, 1]


@pytest.mark.parametrize("family", sorted(SHAPES))
@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1))
def test_hits_lie_on_the_surface_with_unit_normals(family, seed):
    """Property: every hit is within the bounding sphere, its normal is unit and faces the ray."""
    rng = np.random.default_rng(seed)
    size = tuple(rng.uniform(0.1, 0.3, 3))
    m = 64
    d = rng.normal(size=(m, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    target = rng.uniform(-0.3, 0.3, size=(m, 3))
    o = target - 2.0 * d
    t, n = cast(family, o.tolist(), d.tolist(), size)
    hit = np.isfinite(t)
    p = o + t[:, None] * d
    radius = SHAPES[family].bounding_radius(np.asarray(size))
    assert radius <= MAX_BOUNDING_RADIUS
    assert (np.linalg.norm(p[hit], axis=1) <= radius * (1 + 1e-6) + 1e-5).all()
    np.testing.assert_allclose(np.linalg.norm(n[hit], axis=1), 1.0, atol=1e-9)
    assert ((n[hit] * d[hit]).sum(1) <= 1e-9).all()


class TestTracedFamilies:
    """The sphere-traced families against their closed forms (rays down −z, identity rotation)."""

    def test_octahedron_faces(self):
        # |x| + |y| + |z| = s: a ray down −z at (x, y) meets z = s − |x| − |y|, normal (sgn x, sgn y, 1)/√3.
        pts = [(0.1, 0.05), (-0.2, 0.1), (0.05, -0.3)]
        t, n = cast("octahedron", [(x, y, 2.0) for x, y in pts], [DOWN] * 3, (0.5, 0.0, 0.0))
        for (x, y), ti, ni in zip(pts, t, n):
            assert ti == pytest.approx(2.0 - (0.5 - abs(x) - abs(y)), abs=1e-5)
            np.testing.assert_allclose(ni, np.array([np.sign(x), np.sign(y), 1.0]) / math.sqrt(3.0), atol=1e-12)

    def test_hexprism_cap_and_silhouette(self):
        # Axis z: seen down −z, the cap z = s1 over the hexagon of apothem s0 (flat edges at y = ±s0, vertices on ±x).
        s0, s1 = 0.25, 0.2
        rng = np.random.default_rng(0)
        xy = rng.uniform(-0.35, 0.35, size=(400, 2))
        t, n = cast("hexprism", [(x, y, 2.0) for x, y in xy], [DOWN] * 400, (s0, s1, 0.0))
        ax, ay = np.abs(xy[:, 0]), np.abs(xy[:, 1])
        inside = (ay <= s0) & (0.5 * ay + (math.sqrt(3.0) / 2.0) * ax <= s0)
        margin = np.minimum(s0 - ay, s0 - (0.5 * ay + (math.sqrt(3.0) / 2.0) * ax))
        clear = np.abs(margin) > 1e-3  # leave rays that graze the rim to the tracer's tolerance
        assert np.array_equal(np.isfinite(t)[clear], inside[clear])
        hit = np.isfinite(t) & (margin > 1e-3)
        np.testing.assert_allclose(t[hit], 2.0 - s1, atol=1e-5)
        np.testing.assert_allclose(n[hit], np.tile([0.0, 0.0, 1.0], (int(hit.sum()), 1)), atol=1e-4)

    def test_triprism_cap_and_silhouette(self):
        # Axis z: the cap z = s1 over the triangle max(|x|·√3/2 + y/2, −y) ≤ s0/2.
        s0, s1 = 0.4, 0.2
        rng = np.random.default_rng(1)
        xy = rng.uniform(-0.45, 0.45, size=(400, 2))
        t, n = cast("triprism", [(x, y, 2.0) for x, y in xy], [DOWN] * 400, (s0, s1, 0.0))
        level = np.maximum(np.abs(xy[:, 0]) * math.sqrt(3.0) / 2.0 + xy[:, 1] / 2.0, -xy[:, 1]) - s0 / 2.0
        clear = np.abs(level) > 1e-3
        assert np.array_equal(np.isfinite(t)[clear], (level <= 0)[clear])
        hit = np.isfinite(t) & (level < -1e-3)
        np.testing.assert_allclose(t[hit], 2.0 - s1, atol=1e-5)
        np.testing.assert_allclose(n[hit], np.tile([0.0, 0.0, 1.0], (int(hit.sum()), 1)), atol=1e-4)

    def test_roundbox_face_corner_and_silhouette(self):
        # Half-extents s, rounding r = min(s)/3: flat face z = s2 in the middle; the silhouette is the
        # rectangle of half-extents (s0, s1) with corners rounded by r; a corner ray meets the sphere
        # of radius r about the inner box's corner.
        s = (0.3, 0.24, 0.18)
        r = min(s) / 3.0
        t, n = cast("roundbox", [(0.0, 0.0, 2.0), (0.0, 0.0, 2.0)], [DOWN, (0, 0, -1)], s)
        assert t[0] == pytest.approx(2.0 - s[2], abs=1e-5)
        np.testing.assert_allclose(n[0], [0, 0, 1], atol=1e-4)
        c = np.array(s) - r  # inner corner; along the diagonal direction from it, the surface is at distance r
        u = np.array([1.0, 1.0, 1.0]) / math.sqrt(3.0)
        target = c + r * u
        t, n = cast("roundbox", [tuple(target + 2.0 * u)], [tuple(-u)], s)
        assert t[0] == pytest.approx(2.0, abs=1e-5)
        np.testing.assert_allclose(n[0], u, atol=1e-3)
        xy = np.random.default_rng(2).uniform(-0.35, 0.35, size=(400, 2))
        q = np.abs(xy) - (np.array(s[:2]) - r)
        level = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0) - r
        t, _ = cast("roundbox", [(x, y, 2.0) for x, y in xy], [DOWN] * 400, s)
        clear = np.abs(level) > 1e-3
        assert np.array_equal(np.isfinite(t)[clear], (level <= 0)[clear])


def test_hexprism_normal_faces_the_ray_at_an_edge():
    # Hypothesis found this ray grazing a hexprism's edge: the normal once pointed along the ray
    # (central differences straddled the edge into the inside, where the nearest face is a back face).
    rng = np.random.default_rng(811375)
    size = tuple(rng.uniform(0.1, 0.3, 3))
    d = rng.normal(size=(64, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = rng.uniform(-0.3, 0.3, size=(64, 3)) - 2.0 * d
    t, n = cast("hexprism", o.tolist(), d.tolist(), size)
    hit = np.isfinite(t)
    assert hit.any() and ((n[hit] * d[hit]).sum(1) <= 1e-9).all()


class TestSelectFamilies:
    """The select split's families against closed forms (rays down −z, identity rotation)."""

    def test_pyramid_front_face(self):
        # Apex at y = s1, base half-width s0 at y = −s1: at height y the square section has half-width
        # w = s0·(s1 − y)/(2·s1); a ray down −z with |x| < w meets the +z face at z = w, normal ∝ (0, s0, 2·s1).
        s0, s1 = 0.3, 0.25
        pts = [(0.0, 0.0), (0.05, -0.1), (-0.08, 0.05), (0.1, -0.2)]
        t, n = cast("pyramid", [(x, y, 2.0) for x, y in pts], [DOWN] * len(pts), (s0, s1, 0.0))
        normal = np.array([0.0, s0, 2 * s1]) / math.hypot(s0, 2 * s1)
        for (x, y), ti, ni in zip(pts, t, n):
            w = s0 * (s1 - y) / (2 * s1)
            assert abs(x) < w
            assert ti == pytest.approx(2.0 - w, abs=1e-5)
            np.testing.assert_allclose(ni, normal, atol=1e-4)
        # Beside the base and above the apex: misses.
        t, _ = cast("pyramid", [(0.0, s1 + 0.02, 2.0), (s0 + 0.02, -s1 + 0.01, 2.0)], [DOWN] * 2, (s0, s1, 0.0))
        assert np.isinf(t).all()

    def test_bicone_side(self):
        # Radius ρ(y) = s0·(1 − |y|/s1): a ray down −z at (x, y) with |x| < ρ meets z = √(ρ² − x²), where the
        # normal is the gradient of s1·r + s0·|y|: (s1·x/r, s0·sgn y, s1·z/r), r = ρ.
        s0, s1 = 0.3, 0.35
        pts = [(0.0, 0.1), (0.1, -0.05), (-0.05, 0.2), (0.12, 0.12)]
        t, n = cast("bicone", [(x, y, 2.0) for x, y in pts], [DOWN] * len(pts), (s0, s1, 0.0))
        for (x, y), ti, ni in zip(pts, t, n):
            rho = s0 * (1 - abs(y) / s1)
            z = math.sqrt(rho * rho - x * x)
            assert ti == pytest.approx(2.0 - z, abs=1e-5)
            g = np.array([s1 * x / rho, s0 * np.sign(y), s1 * z / rho])
            np.testing.assert_allclose(ni, g / np.linalg.norm(g), atol=1e-4)

    def test_lens_front_cap_and_rim(self):
        # Rim radius s0 in xy, half-thickness s1: the front cap is the sphere of radius R = (s0² + s1²)/2s1
        # centred at z = −(R − s1).
        s0, s1 = 0.4, 0.12
        big_r = (s0 * s0 + s1 * s1) / (2 * s1)
        off = big_r - s1
        rng = np.random.default_rng(2)
        xy = rng.uniform(-0.45, 0.45, size=(300, 2))
        t, n = cast("lens", [(x, y, 2.0) for x, y in xy], [DOWN] * 300, (s0, s1, 0.0))
        r = np.hypot(xy[:, 0], xy[:, 1])
        clear = np.abs(r - s0) > 2e-3
        assert np.array_equal(np.isfinite(t)[clear], (r < s0)[clear])
        hit = np.isfinite(t) & (r < s0 - 2e-3)
        z = -off + np.sqrt(big_r**2 - r[hit] ** 2)
        np.testing.assert_allclose(t[hit], 2.0 - z, atol=1e-5)
        ref = np.stack([xy[hit, 0], xy[hit, 1], z + off], 1) / big_r
        np.testing.assert_allclose(n[hit], ref, atol=2e-5)  # the traced hit is within 1e-5·size of the sphere


class TestWideFamilies:
    """The training-only generic families against independent float64 references (random rays)."""

    @staticmethod
    def _rays(n, seed):
        rng = np.random.default_rng(seed)
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = rng.uniform(-0.3, 0.3, size=(n, 3)) - 2.0 * d
        return o, d

    @pytest.mark.parametrize("codes", [(0.0, 0.0), (0.13, 0.71), (0.5, 0.25), (0.93, 0.4)])
    def test_gem_is_the_clipped_polytope(self, codes):
        # Cyrus–Beck clipping of each ray by the gem's half-spaces (n·p ≤ d), then the bounding sphere, in float64:
        # the entry point and the entering plane's normal (or the sphere's) are the hit and its normal.
        from lasagna.world.shapes import _gem_planes

        big_r = 0.4
        o, d = self._rays(400, 3)
        t, n = cast("gem", o.tolist(), d.tolist(), (big_r, *codes))
        s = sizes(1, (big_r, *codes))
        planes = [(np.array([float(c[0]) for c in pn]), float(pd[0])) for pn, pd in _gem_planes(s)]
        checked = 0
        for i in range(len(o)):
            lo, hi, normal = -np.inf, np.inf, None
            for pn, pd in planes:
                den, num = pn @ d[i], pd - pn @ o[i]
                if abs(den) < 1e-12:
                    if num < 0:
                        lo, hi = np.inf, -np.inf
                    continue
                ti = num / den
                if den < 0 and ti > lo:
                    lo, normal = ti, pn
                elif den > 0:
                    hi = min(hi, ti)
            b = o[i] @ d[i]
            disc = b * b - (o[i] @ o[i] - big_r * big_r)
            if disc <= 0:
                lo, hi = np.inf, -np.inf
            else:
                s1, s2 = -b - math.sqrt(disc), -b + math.sqrt(disc)
                if s1 > lo:
                    lo, normal = s1, (o[i] + s1 * d[i]) / big_r
                hi = min(hi, s2)
            margin = hi - lo
            if lo < hi and margin > 1e-3:  # a clear hit, not grazing an edge
                assert t[i] == pytest.approx(lo, abs=1e-4)
                np.testing.assert_allclose(n[i], normal, atol=2e-3)
                checked += 1
            elif lo > hi + 1e-3 or not np.isfinite(lo):
                assert np.isinf(t[i])
        assert checked > 50

    def test_gem_faces_are_tilted_but_bounded(self):
        # The codes move the cube's faces: different codes, different normals; every plane keeps the origin inside.
        from lasagna.world.shapes import _gem_planes

        a = _gem_planes(sizes(1, (0.4, 0.1, 0.2)))
        b = _gem_planes(sizes(1, (0.4, 0.6, 0.9)))
        assert any(abs(float(pa[0][0][0]) - float(pb[0][0][0])) > 1e-3 for pa, pb in zip(a, b))
        for _, dist in a + b:
            assert 0.38 * 0.4 - 1e-12 <= float(dist[0]) <= 0.8 * 0.4 + 1e-12

    @pytest.mark.parametrize("codes", [(0.2, 0.8), (0.55, 0.05)])
    def test_blob_hits_lie_on_its_smooth_union(self, codes):
        # Reference in float64 with numpy: the smooth minimum of the three spheres' distances (Quilez) is zero at
        # each hit, and the normal is its gradient by central differences.
        from lasagna.world.shapes import _BLOB_SMOOTH, _blob_spheres

        big_r = 0.45
        spheres = [
            (np.array([float(c[0]) for c in centre]), float(radius[0]))
            for centre, radius in _blob_spheres(sizes(1, (big_r, *codes)))
        ]
        assert all(np.linalg.norm(c) + r <= 0.921 * big_r for c, r in spheres)

        def field(p):
            k = _BLOB_SMOOTH * big_r
            dist = None
            for c, r in spheres:
                di = np.linalg.norm(p - c, axis=-1) - r
                if dist is None:
                    dist = di
                else:
                    h = np.maximum(k - np.abs(dist - di), 0.0) / k
                    dist = np.minimum(dist, di) - h * h * k / 4
            return dist

        o, d = self._rays(300, 5)
        t, n = cast("blob", o.tolist(), d.tolist(), (big_r, *codes))
        hit = np.isfinite(t)
        assert hit.sum() > 30
        p = o[hit] + t[hit, None] * d[hit]
        assert np.abs(field(p)).max() < 1e-4
        eps = 1e-6
        grad = np.stack([field(p + eps * e) - field(p - eps * e) for e in np.eye(3)], 1)
        grad /= np.linalg.norm(grad, axis=1, keepdims=True)
        assert np.median(np.abs(n[hit] - grad).max(1)) < 1e-3
