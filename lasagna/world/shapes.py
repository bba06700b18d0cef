"""Analytic shape families and their exact ray intersections, on flat lists of rays.

Shapes without a closed-form intersection are sphere-traced (`_trace`) to within 1e-5 of their size;
their normals are closed forms where simple and central differences of the distance otherwise.

Every family is defined in its own local frame (centred at the origin; the scene places it with a
rotation R and a centre c: p_camera = R·p_local + c) by three size parameters. Its ``intersect``
takes M rays in that local frame — origins ``o`` and directions ``d``, each a tuple of three (M,)
tensors — and returns the ray parameter t of the first surface point with t > ``t_min`` (``inf``
where the ray misses) and the unit outward normal there, in the local frame.

Flat lists keep the work proportional to the pixels an object can cover (the renderer culls each
object to its bounding circle first) and keep every ray independent of the others, so a scene
renders bit-identically alone or in any batch. Vectors are tuples of components rather than (M, 3)
tensors with matmuls for the same reason: elementwise arithmetic gives the same bits at any size.

Families (``SHAPES``; which split uses which is in ``lasagna.world.splits``):

============  =====================================  ===========================================
family        size parameters (s0, s1, s2)           intersection
============  =====================================  ===========================================
ellipsoid     semi-axes along x, y, z (s0=s1=s2:     quadratic
              a sphere)
box           half-extents along x, y, z             slab method (Kay & Kajiya 1986)
cylinder      radius s0, half-height s1 (axis y)     quadratic (side) + two cap planes
torus         major radius s0, minor s1 (ring in     sphere tracing (Hart 1996) of the exact
              the xz plane, around y)                signed distance, from the bounding sphere
capsule       radius s0, half-length s1 of the       cylinder side + two spheres
              axis segment (axis y)
cone          base radius s0, half-height s1: apex   quadratic (side) + base cap plane
              at y = +s1, base disc at y = −s1
roundbox      half-extents x, y, z; edges rounded    sphere tracing of the exact distance
              by r = min(s)/3
panel         a thin box (s2 ≤ 0.04), turned toward  slab method, as box
              the camera: a flat textured card
octahedron    vertex distance s0 (|x|+|y|+|z| = s0)  sphere tracing of a distance bound
hexprism      apothem s0 (flat edges at y = ±s0), half-      sphere tracing of the exact distance
              length s1 along z
triprism      inradius s0/2 (triangle in xy),        sphere tracing of a distance bound
              half-length s1 along z
pyramid       base half-width s0 (at y = −s1), apex   sphere tracing of the five planes' bound
              at y = +s1
bicone        rim radius s0 (y = 0), apexes y = ±s1   sphere tracing of a distance bound;
                                                     normals in closed form
lens          rim radius s0 in xy, half-thickness s1  sphere tracing of two spheres' bound;
              along z (two spherical caps)            radial normals
gem           bounding radius s0; codes s1, s2 fix    Cyrus–Beck clipping by the ten planes,
              a cube's six tilted, moved faces and
              four cut corners (a random crystal)     then the bounding sphere
blob          bounding radius s0; codes s1, s2 fix    sphere tracing of a smooth minimum of
              three spheres (centres and radii)       three spheres' distances
============  =====================================  ===========================================
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

Tensor = torch.Tensor
Vec = tuple[Tensor, Tensor, Tensor]

# Ray directions with a zero component make 1/d infinite in the slab test; a tiny substitute keeps
# the arithmetic finite (0·inf would give NaN) and changes no hit: the slab bounds become ±1e30.
_DIR_EPS = 1e-30
# Sphere tracing stops when the signed distance is below this fraction of the shape's size; a
# pixel of a 256² render is 7.8e-3 wide, so the silhouette error is far below a pixel.
_TRACE_TOL = 1e-5
_TRACE_STEPS = 96


def dot(a: Vec, b: Vec) -> Tensor:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def normalize(v: Vec) -> Vec:
    # The norm of a surface gradient is > 0 except at a cone's apex (a measure-zero set); the clamp
    # keeps that one point finite instead of NaN.
    inv = torch.rsqrt((v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).clamp_min(1e-30))
    return (v[0] * inv, v[1] * inv, v[2] * inv)


def _roots(a: Tensor, b_half: Tensor, c: Tensor) -> tuple[Tensor, Tensor]:
    """Both roots (t1 ≤ t2) of a·t² + 2·b_half·t + c = 0; NaN where there is no real root.

    The cancellation-free form q = −(b_half + sign(b_half)·√disc), t = q/a and c/q (Press et al.,
    Numerical Recipes §5.6), so a grazing ray far from the origin keeps its precision.
    """
    disc = b_half * b_half - a * c
    sq = torch.sqrt(disc)  # NaN where disc < 0: comparisons with NaN are False, i.e. "no hit"
    q = -(b_half + torch.where(b_half >= 0, sq, -sq))
    r1, r2 = q / a, c / q
    return torch.minimum(r1, r2), torch.maximum(r1, r2)


def _first(t_min: float, *candidates: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
    """Smallest valid t > t_min among (t, valid) candidates, and the index of the winning candidate."""
    best = None
    which = None
    for i, (t, ok) in enumerate(candidates):
        t = torch.where(ok & (t > t_min), t, torch.full_like(t, math.inf))
        if best is None:
            best, which = t, torch.zeros_like(t, dtype=torch.int64)
        else:
            closer = t < best
            best = torch.where(closer, t, best)
            which = torch.where(closer, torch.full_like(which, i), which)
    return best, which


def _at(o: Vec, d: Vec, t: Tensor) -> Vec:
    # Where t is inf the point is inf/NaN; callers only read points where t is finite.
    tt = torch.where(torch.isfinite(t), t, torch.zeros_like(t))
    return (o[0] + tt * d[0], o[1] + tt * d[1], o[2] + tt * d[2])


def _select(which: Tensor, *normals: Vec) -> Vec:
    out = list(normals[0])
    for i, n in enumerate(normals[1:], start=1):
        pick = which == i
        out = [torch.where(pick, n[j], out[j]) for j in range(3)]
    return (out[0], out[1], out[2])


def _sphere(o: Vec, d: Vec, cy: Tensor | float, r: Tensor) -> tuple[Tensor, Tensor]:
    """Roots of a ray with a sphere of radius r centred at (0, cy, 0)."""
    oy = o[1] - cy
    a = dot(d, d)
    b = o[0] * d[0] + oy * d[1] + o[2] * d[2]
    c = o[0] * o[0] + oy * oy + o[2] * o[2] - r * r
    return _roots(a, b, c)


def ellipsoid(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    # Scale to the unit sphere: |o/s + t·d/s|² = 1 has the same t.
    os_ = (o[0] / s[0], o[1] / s[1], o[2] / s[2])
    ds_ = (d[0] / s[0], d[1] / s[1], d[2] / s[2])
    t1, t2 = _roots(dot(ds_, ds_), dot(os_, ds_), dot(os_, os_) - 1.0)
    ok = torch.ones_like(t1, dtype=torch.bool)
    t, _ = _first(t_min, (t1, ok), (t2, ok))
    p = _at(o, d, t)
    # Gradient of x²/a² + y²/b² + z²/c².
    n = normalize((p[0] / (s[0] * s[0]), p[1] / (s[1] * s[1]), p[2] / (s[2] * s[2])))
    return t, n


def box(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    lo, hi = [], []
    for i in range(3):
        di = torch.where(d[i] == 0, torch.full_like(d[i], _DIR_EPS), d[i])
        ta, tb = (-s[i] - o[i]) / di, (s[i] - o[i]) / di
        lo.append(torch.minimum(ta, tb))
        hi.append(torch.maximum(ta, tb))
    t_near = torch.maximum(torch.maximum(lo[0], lo[1]), lo[2])
    t_far = torch.minimum(torch.minimum(hi[0], hi[1]), hi[2])
    hit = t_near <= t_far
    t, _ = _first(t_min, (t_near, hit), (t_far, hit))
    # The entry face is the axis whose slab was entered last; its normal points against the ray.
    zero = torch.zeros_like(t)
    n = []
    for i in range(3):
        n.append(torch.where(lo[i] == t_near, -torch.sign(d[i]), zero))
    n[1] = torch.where(n[0] != 0, zero, n[1])
    n[2] = torch.where((n[0] != 0) | (n[1] != 0), zero, n[2])
    return t, (n[0], n[1], n[2])


def _cylinder_side(o: Vec, d: Vec, r: Tensor, h: Tensor) -> tuple[tuple[Tensor, Tensor], tuple[Tensor, Tensor]]:
    a = d[0] * d[0] + d[2] * d[2]
    b = o[0] * d[0] + o[2] * d[2]
    c = o[0] * o[0] + o[2] * o[2] - r * r
    t1, t2 = _roots(a, b, c)
    y1, y2 = o[1] + t1 * d[1], o[1] + t2 * d[1]
    return (t1, y1.abs() <= h), (t2, y2.abs() <= h)


def _cap(o: Vec, d: Vec, y: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
    dy = torch.where(d[1] == 0, torch.full_like(d[1], _DIR_EPS), d[1])
    t = (y - o[1]) / dy
    x, z = o[0] + t * d[0], o[2] + t * d[2]
    return t, x * x + z * z <= r * r


def cylinder(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    r, h = s[0], s[1]
    side1, side2 = _cylinder_side(o, d, r, h)
    t, which = _first(t_min, side1, side2, _cap(o, d, h, r), _cap(o, d, -h, r))
    p = _at(o, d, t)
    zero, one = torch.zeros_like(t), torch.ones_like(t)
    side = (p[0] / r, zero, p[2] / r)
    n = _select(which, side, side, (zero, one, zero), (zero, -one, zero))
    return t, normalize(n)


def capsule(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    # The union of convex pieces: the first entry is the first entry of any piece; the side of the
    # finite cylinder suffices because its caps lie inside the end spheres.
    r, h = s[0], s[1]
    side1, side2 = _cylinder_side(o, d, r, h)
    ok = torch.ones_like(r, dtype=torch.bool)
    a1, a2 = _sphere(o, d, h, r)
    b1, b2 = _sphere(o, d, -h, r)
    t, which = _first(t_min, side1, side2, (a1, ok), (a2, ok), (b1, ok), (b2, ok))
    p = _at(o, d, t)
    zero = torch.zeros_like(t)
    side = (p[0], zero, p[2])
    top = (p[0], p[1] - h, p[2])
    bottom = (p[0], p[1] + h, p[2])
    return t, normalize(_select(which, side, side, top, top, bottom, bottom))


def cone(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    # Side: x² + z² = k²·(h − y)² with k = r / (2h), restricted to −h ≤ y ≤ h (which also drops the
    # mirrored nappe above the apex).
    r, h = s[0], s[1]
    k2 = (r / (2.0 * h)) ** 2
    u = h - o[1]
    a = d[0] * d[0] + d[2] * d[2] - k2 * d[1] * d[1]
    b = o[0] * d[0] + o[2] * d[2] + k2 * u * d[1]
    c = o[0] * o[0] + o[2] * o[2] - k2 * u * u
    t1, t2 = _roots(a, b, c)
    y1, y2 = o[1] + t1 * d[1], o[1] + t2 * d[1]
    t, which = _first(t_min, (t1, y1.abs() <= h), (t2, y2.abs() <= h), _cap(o, d, -h, r))
    p = _at(o, d, t)
    zero, one = torch.zeros_like(t), torch.ones_like(t)
    side = (p[0], k2 * (h - p[1]), p[2])  # half the gradient of x² + z² − k²(h − y)²
    return t, normalize(_select(which, side, side, (zero, -one, zero)))


def _trace(o: Vec, d: Vec, sdf: Callable[[Vec], Tensor], bound: Tensor, t_min: float) -> tuple[Tensor, Vec]:
    """Sphere tracing (Hart 1996, "Sphere tracing", eq. 1) of ``sdf`` inside the bounding sphere of
    radius ``bound``; returns t (inf on a miss) and the hit point.

    ``sdf`` must be a signed distance or a lower bound of one (then steps are shorter, never past
    the surface). Directions are unit in the camera frame and R is a rotation, so |d| = 1 here,
    which stepping by the distance needs.
    """
    t1, t2 = _sphere(o, d, 0.0, bound)
    inside = t2 > t_min  # False also where the bounding sphere is missed (t2 is NaN)
    zero = torch.zeros_like(t1)
    t = torch.where(inside, torch.clamp_min(t1, t_min), zero)
    t_end = torch.where(inside, t2, zero)
    tol = _TRACE_TOL * bound
    for _ in range(_TRACE_STEPS):
        dist = sdf(_at(o, d, t))
        t = t + torch.where(dist > tol, dist, torch.zeros_like(dist))
    dist = sdf(_at(o, d, t))
    hit = inside & (dist <= tol * 4) & (t <= t_end)
    t = torch.where(hit, t, torch.full_like(t, math.inf))
    return t, _at(o, d, t)


def _sdf_normal(sdf: Callable[[Vec], Tensor], p: Vec, d: Vec, h: Tensor) -> Vec:
    """The normalised gradient of ``sdf`` near the hit p by central differences of step h (where no closed form).

    Evaluated at p backed off 4h along the ray d, i.e. outside the shape: there the distance to a convex
    shape is smooth, so the differences never straddle an edge into the inside, where the gradient points
    to whichever face is nearest (a back face, near an edge). The normal's error is O(h) ≈ 1e-4 of the size.
    """
    p = (p[0] - 4.0 * h * d[0], p[1] - 4.0 * h * d[1], p[2] - 4.0 * h * d[2])
    g = []
    for i in range(3):
        hi = [c + h if j == i else c for j, c in enumerate(p)]
        lo = [c - h if j == i else c for j, c in enumerate(p)]
        g.append(sdf((hi[0], hi[1], hi[2])) - sdf((lo[0], lo[1], lo[2])))
    return normalize((g[0], g[1], g[2]))


def _torus_sdf(p: Vec, big_r: Tensor, small_r: Tensor) -> Tensor:
    q = torch.sqrt(p[0] * p[0] + p[2] * p[2]) - big_r
    return torch.sqrt(q * q + p[1] * p[1]) - small_r


def torus(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    big_r, small_r = s[0], s[1]
    t, p = _trace(o, d, lambda q: _torus_sdf(q, big_r, small_r), big_r + small_r, t_min)
    ring = torch.sqrt(p[0] * p[0] + p[2] * p[2]).clamp_min(1e-30)
    scale = 1.0 - big_r / ring
    return t, normalize((p[0] * scale, p[1], p[2] * scale))


def _roundbox_sdf(p: Vec, s: Vec) -> Tensor:
    # Quilez, "Distance functions": a box of half-extents s − r with its edges rounded by r = ⅓·min(s).
    r = torch.minimum(torch.minimum(s[0], s[1]), s[2]) / 3.0
    q = [p[i].abs() - (s[i] - r) for i in range(3)]
    outside = torch.sqrt(sum(c.clamp_min(0.0) ** 2 for c in q))
    inside = torch.maximum(torch.maximum(q[0], q[1]), q[2]).clamp_max(0.0)
    return outside + inside - r


def roundbox(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    bound = torch.sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2])
    t, p = _trace(o, d, lambda q: _roundbox_sdf(q, s), bound, t_min)
    return t, _sdf_normal(lambda q: _roundbox_sdf(q, s), p, d, 1e-4 * bound)


def _octahedron_sdf(p: Vec, s: Vec) -> Tensor:
    # A lower bound of the distance (Quilez): exact on the faces' normal lines, which suffices to trace.
    return (p[0].abs() + p[1].abs() + p[2].abs() - s[0]) * (1.0 / math.sqrt(3.0))


def octahedron(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    t, p = _trace(o, d, lambda q: _octahedron_sdf(q, s), s[0], t_min)
    # Each face's normal is (±1, ±1, ±1)/√3 with the signs of the point's coordinates.
    return t, normalize((torch.sign(p[0]), torch.sign(p[1]), torch.sign(p[2])))


_HEX_K = (-math.sqrt(3.0) / 2.0, 0.5, 1.0 / math.sqrt(3.0))


def _hexprism_sdf(p: Vec, s: Vec) -> Tensor:
    # Quilez's exact hexagonal prism: apothem s0 in the xy plane, half-length s1 along z.
    x, y, z = p[0].abs(), p[1].abs(), p[2].abs()
    k = 2.0 * torch.clamp_max(_HEX_K[0] * x + _HEX_K[1] * y, 0.0)
    x, y = x - k * _HEX_K[0], y - k * _HEX_K[1]
    cx = torch.maximum(torch.minimum(x, _HEX_K[2] * s[0]), -_HEX_K[2] * s[0])
    dx = torch.sqrt((x - cx) ** 2 + (y - s[0]) ** 2) * torch.sign(y - s[0])
    dz = z - s[1]
    return torch.clamp_max(torch.maximum(dx, dz), 0.0) + torch.sqrt(dx.clamp_min(0) ** 2 + dz.clamp_min(0) ** 2)


def hexprism(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    bound = torch.sqrt((s[0] * (2.0 / math.sqrt(3.0))) ** 2 + s[1] * s[1])
    t, p = _trace(o, d, lambda q: _hexprism_sdf(q, s), bound, t_min)
    return t, _sdf_normal(lambda q: _hexprism_sdf(q, s), p, d, 1e-4 * bound)


def _triprism_sdf(p: Vec, s: Vec) -> Tensor:
    # Quilez's triangular prism (a bound): an equilateral triangle of inradius s0/2 in xy, half-length s1 along z.
    return torch.maximum(
        p[2].abs() - s[1], torch.maximum(p[0].abs() * (math.sqrt(3.0) / 2.0) + p[1] * 0.5, -p[1]) - s[0] * 0.5
    )


def triprism(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    bound = torch.sqrt(s[0] * s[0] + s[1] * s[1])
    t, p = _trace(o, d, lambda q: _triprism_sdf(q, s), bound, t_min)
    return t, _sdf_normal(lambda q: _triprism_sdf(q, s), p, d, 1e-4 * bound)


def _pyramid_sdf(p: Vec, s: Vec) -> Tensor:
    # A square pyramid (base half-width s0 at y = −s1, apex at y = +s1) as the intersection of five
    # half-spaces: the largest signed plane distance is a lower bound of a convex polytope's distance,
    # exact on each face's normal line, which suffices to trace.
    base, half = s[0], s[1]
    norm = torch.rsqrt(4.0 * half * half + base * base)
    side_x = (2.0 * half * p[0].abs() + base * p[1] - base * half) * norm
    side_z = (2.0 * half * p[2].abs() + base * p[1] - base * half) * norm
    return torch.maximum(torch.maximum(side_x, side_z), -p[1] - half)


def pyramid(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    bound = torch.sqrt(2.0 * s[0] * s[0] + s[1] * s[1])
    t, p = _trace(o, d, lambda q: _pyramid_sdf(q, s), bound, t_min)
    return t, _sdf_normal(lambda q: _pyramid_sdf(q, s), p, d, 1e-4 * bound)


def _bicone_sdf(p: Vec, s: Vec) -> Tensor:
    # Two cones base to base (radius s0 at y = 0, apexes at y = ±s1): the distance to the side's line
    # in the (r, |y|) half-plane, a lower bound of the true distance near the apexes and the rim.
    r = torch.sqrt(p[0] * p[0] + p[2] * p[2])
    return (s[1] * r + s[0] * p[1].abs() - s[0] * s[1]) * torch.rsqrt(s[0] * s[0] + s[1] * s[1])


def bicone(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    bound = torch.maximum(s[0], s[1])
    t, p = _trace(o, d, lambda q: _bicone_sdf(q, s), bound, t_min)
    # The gradient of s1·r + s0·|y|: (s1·x/r, s0·sgn y, s1·z/r); the rim (y = 0) takes the side toward the ray.
    r = torch.sqrt(p[0] * p[0] + p[2] * p[2]).clamp_min(1e-30)
    sign_y = torch.where(p[1] == 0, -torch.sign(d[1]), torch.sign(p[1]))
    return t, normalize((s[1] * p[0] / r, s[0] * sign_y, s[1] * p[2] / r))


def _lens_sdf(p: Vec, s: Vec) -> Tensor:
    # A convex lens: the intersection of two spheres of radius R whose centres lie at z = ±(R − s1), so
    # the rim is a circle of radius s0 in the xy plane and the lens is 2·s1 thick (R = (s0² + s1²)/2s1).
    # The larger of two convex distances is a lower bound of the intersection's.
    big_r = (s[0] * s[0] + s[1] * s[1]) / (2.0 * s[1])
    off = big_r - s[1]
    xy = p[0] * p[0] + p[1] * p[1]
    front = torch.sqrt(xy + (p[2] + off) ** 2) - big_r
    back = torch.sqrt(xy + (p[2] - off) ** 2) - big_r
    return torch.maximum(front, back)


def lens(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    t, p = _trace(o, d, lambda q: _lens_sdf(q, s), s[0], t_min)
    big_r = (s[0] * s[0] + s[1] * s[1]) / (2.0 * s[1])
    off = big_r - s[1]
    # On the lens each point lies on the sphere whose distance is the larger: its normal is radial.
    xy = p[0] * p[0] + p[1] * p[1]
    use_front = torch.sqrt(xy + (p[2] + off) ** 2) >= torch.sqrt(xy + (p[2] - off) ** 2)
    cz = torch.where(use_front, -off * torch.ones_like(p[2]), off * torch.ones_like(p[2]))
    return t, normalize((p[0], p[1], p[2] - cz))


def _code(u: Tensor, a: float, b: float = 0.0) -> Tensor:
    """A number in [−1, 1) that a shape code u ∈ [0, 1) fixes: 2·frac(a·u + b) − 1.

    The generic families (gem, blob) draw their many free parameters from one or two such codes. Only
    multiplies, adds and floors: exactly rounded elementwise, so an object renders to the same bits alone or in
    any batch (a transcendental's vectorised and scalar paths may differ in the last bit). Distinct large
    multipliers make the numbers of one code look independent of each other.
    """
    x = u * a + b
    return 2.0 * (x - torch.floor(x)) - 1.0


# The gem: a cube's six face planes, each tilted and moved by the codes, with four alternate corners cut
# (the tetrahedral ones: all eight would make an octahedron's faces), inside the bounding sphere.
_GEM_TILT = 0.45  # largest tangent component of a face normal's tilt (≤ 32.5° per face)
_GEM_FACE = (0.38, 0.52)  # face plane distances, fractions of the bounding radius
_GEM_CUT = (0.6, 0.8)  # corner cut distances, fractions of the bounding radius
_CUBE_FACES = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0), (2, 1.0), (2, -1.0))
_TETRA_CORNERS = ((1.0, 1.0, 1.0), (1.0, -1.0, -1.0), (-1.0, 1.0, -1.0), (-1.0, -1.0, 1.0))


def _gem_planes(s: Vec) -> list[tuple[Vec, Tensor]]:
    """The gem's planes (unit normal n, distance d: n·p ≤ d inside) from its size (R, code u, code v)."""
    big_r, u, v = s
    planes: list[tuple[Vec, Tensor]] = []
    for k, (axis, sign) in enumerate(_CUBE_FACES):
        n = [torch.zeros_like(u), torch.zeros_like(u), torch.zeros_like(u)]
        n[axis] = torch.full_like(u, sign)
        n[(axis + 1) % 3] = _GEM_TILT * _code(u, 97.0 + 31.0 * k, 0.37 * k)
        n[(axis + 2) % 3] = _GEM_TILT * _code(v, 89.0 + 37.0 * k, 0.61 * k)
        frac = 0.5 * (_code(u + v, 53.0 + 17.0 * k, 0.13 * k) + 1.0)
        planes.append((normalize((n[0], n[1], n[2])), big_r * (_GEM_FACE[0] + (_GEM_FACE[1] - _GEM_FACE[0]) * frac)))
    for k, c in enumerate(_TETRA_CORNERS):
        jit = [0.25 * _code(v if j % 2 else u, 71.0 + 13.0 * (3 * k + j), 0.29 * j) for j in range(3)]
        n = normalize(tuple(c[j] + jit[j] for j in range(3)))  # type: ignore[arg-type]
        frac = 0.5 * (_code(u - v, 43.0 + 19.0 * k, 0.71 * k) + 1.0)
        planes.append((n, big_r * (_GEM_CUT[0] + (_GEM_CUT[1] - _GEM_CUT[0]) * frac)))
    return planes


def gem(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    """Cyrus–Beck clipping (Cyrus & Beck 1978): the ray enters the last of the planes it enters and leaves at the
    first it leaves, then the bounding sphere clips both; exact, no tracing (a polytope's plane bound makes sphere
    tracing crawl along grazing faces). The entry's normal is the entering plane's (or the sphere's)."""
    planes = _gem_planes(s)
    big_r = s[0]
    s1, s2 = _sphere(o, d, 0.0, big_r)  # NaN where the sphere is missed: every comparison below is then False
    t_near, t_far = s1, s2
    which = torch.full_like(s1, -1.0)  # −1: the sphere; k: plane k
    for k, (n, dist) in enumerate(planes):
        den = dot(n, d)
        den = torch.where(den == 0, torch.full_like(den, _DIR_EPS), den)
        tk = (dist - dot(n, o)) / den
        entering = den < 0
        later = entering & (tk > t_near)
        t_near = torch.where(later, tk, t_near)
        which = torch.where(later, torch.full_like(which, float(k)), which)
        t_far = torch.where(~entering & (tk < t_far), tk, t_far)
    hit = t_near <= t_far
    t, pick = _first(t_min, (t_near, hit), (t_far, hit))
    p = _at(o, d, t)
    sphere = normalize(p)
    out = [sphere[0], sphere[1], sphere[2]]
    for k, (n, _) in enumerate(planes):
        on = (which == k) & (pick == 0)
        out = [torch.where(on, n[j], out[j]) for j in range(3)]
    # Leaving from inside (t_min inside the gem): the exit's normal is not tracked; the sphere's radial direction
    # stands in for it (only a ray starting inside an object meets it; the renderer's rays start at the camera).
    return t, (out[0], out[1], out[2])


# The blob: three spheres inside the bounding sphere (one at the centre, two at directions the codes fix), joined
# by a smooth minimum: an organic, rounded, non-convex shape.
_BLOB_SMOOTH = 0.2  # the smooth minimum's width k, a fraction of the bounding radius
_BLOB_LIPSCHITZ = 0.9  # the step's safety factor: the blended field may be slightly steeper than 1 near the seam


def _blob_spheres(s: Vec) -> list[tuple[Vec, Tensor]]:
    big_r, u, v = s
    zero = torch.zeros_like(u)
    spheres: list[tuple[Vec, Tensor]] = [((zero, zero, zero), big_r * (0.38 + 0.12 * _code(u + v, 61.0)))]
    for k, w in enumerate((u, v)):
        direction = normalize(tuple(_code(w, 113.0 + 29.0 * (3 * k + j), 0.23 * j) for j in range(3)))  # type: ignore
        offset = big_r * (0.4 + 0.12 * _code(w, 47.0 + 11.0 * k))
        radius = big_r * (0.3 + 0.1 * _code(w, 83.0 + 7.0 * k, 0.5))
        spheres.append((tuple(offset * c for c in direction), radius))  # type: ignore[arg-type]
    return spheres  # every |centre| + radius ≤ 0.92 R; the blend adds at most k/4 = 0.05 R


def _blob_sdf(p: Vec, spheres: list[tuple[Vec, Tensor]], big_r: Tensor) -> Tensor:
    k = _BLOB_SMOOTH * big_r
    dist = None
    for c, r in spheres:
        q = (p[0] - c[0], p[1] - c[1], p[2] - c[2])
        di = torch.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]) - r
        if dist is None:
            dist = di
        else:  # Quilez's polynomial smooth minimum: min(a, b) − h²k/4, h = max(k − |a − b|, 0)/k
            h = torch.clamp_min(k - (dist - di).abs(), 0.0) / k
            dist = torch.minimum(dist, di) - h * h * k * 0.25
    assert dist is not None
    return dist * _BLOB_LIPSCHITZ


def blob(o: Vec, d: Vec, s: Vec, t_min: float) -> tuple[Tensor, Vec]:
    spheres = _blob_spheres(s)
    t, p = _trace(o, d, lambda q: _blob_sdf(q, spheres, s[0]), s[0], t_min)
    return t, _sdf_normal(lambda q: _blob_sdf(q, spheres, s[0]), p, d, 1e-4 * s[0])


@dataclass(frozen=True)
class ShapeFamily:
    """One analytic family: its exact intersection, bounding radius and size distribution."""

    name: str
    intersect: Callable[[Vec, Vec, Vec, float], tuple[Tensor, Vec]]
    bounding_radius: Callable[[np.ndarray], float]
    sample_size: Callable[[np.ndarray], tuple[float, float, float]]
    facing: bool = False
    """Turned toward the camera (tilted at most ``FACING_TILT``) instead of uniformly: a panel seen edge-on
    is a line."""


def _lerp(u: float, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(u)


def _ellipsoid_size(u: np.ndarray) -> tuple[float, float, float]:
    # One scene in three gets a sphere (the family includes spheres; they are also the easiest
    # shape to check against a closed form).
    if u[3] < 1.0 / 3.0:
        r = _lerp(u[0], 0.24, 0.45)
        return (r, r, r)
    return (_lerp(u[0], 0.18, 0.5), _lerp(u[1], 0.18, 0.5), _lerp(u[2], 0.18, 0.5))


SHAPES: dict[str, ShapeFamily] = {
    f.name: f
    for f in (
        ShapeFamily("ellipsoid", ellipsoid, lambda s: float(max(s)), _ellipsoid_size),
        ShapeFamily(
            "box",
            box,
            lambda s: float(np.linalg.norm(s)),
            lambda u: (_lerp(u[0], 0.14, 0.34), _lerp(u[1], 0.14, 0.34), _lerp(u[2], 0.14, 0.34)),
        ),
        ShapeFamily(
            "cylinder",
            cylinder,
            lambda s: float(math.hypot(s[0], s[1])),
            lambda u: (_lerp(u[0], 0.14, 0.33), _lerp(u[1], 0.14, 0.4), 0.0),
        ),
        ShapeFamily(
            "torus",
            torus,
            lambda s: float(s[0] + s[1]),
            lambda u: (_lerp(u[0], 0.24, 0.4), _lerp(u[1], 0.07, 0.16), 0.0),
        ),
        ShapeFamily(
            "capsule",
            capsule,
            lambda s: float(s[0] + s[1]),
            lambda u: (_lerp(u[0], 0.12, 0.25), _lerp(u[1], 0.1, 0.3), 0.0),
        ),
        ShapeFamily(
            "cone",
            cone,
            lambda s: float(math.hypot(s[0], s[1])),
            lambda u: (_lerp(u[0], 0.2, 0.36), _lerp(u[1], 0.2, 0.4), 0.0),
        ),
        ShapeFamily(
            "roundbox",
            roundbox,
            lambda s: float(np.linalg.norm(s)),
            lambda u: (_lerp(u[0], 0.14, 0.34), _lerp(u[1], 0.14, 0.34), _lerp(u[2], 0.14, 0.34)),
        ),
        ShapeFamily(
            "panel",
            box,
            lambda s: float(np.linalg.norm(s)),
            lambda u: (_lerp(u[0], 0.2, 0.4), _lerp(u[1], 0.2, 0.4), _lerp(u[2], 0.015, 0.04)),
            facing=True,
        ),
        ShapeFamily("octahedron", octahedron, lambda s: float(s[0]), lambda u: (_lerp(u[0], 0.25, 0.5), 0.0, 0.0)),
        ShapeFamily(
            "hexprism",
            hexprism,
            lambda s: float(math.hypot(s[0] * 2.0 / math.sqrt(3.0), s[1])),
            lambda u: (_lerp(u[0], 0.15, 0.3), _lerp(u[1], 0.12, 0.35), 0.0),
        ),
        ShapeFamily(
            "triprism",
            triprism,
            lambda s: float(math.hypot(s[0], s[1])),
            lambda u: (_lerp(u[0], 0.25, 0.45), _lerp(u[1], 0.12, 0.35), 0.0),
        ),
        # The select split's families (lasagna.world.splits): appended, so every earlier index is unchanged.
        ShapeFamily(
            "pyramid",
            pyramid,
            lambda s: float(math.hypot(s[0] * math.sqrt(2.0), s[1])),
            lambda u: (_lerp(u[0], 0.18, 0.32), _lerp(u[1], 0.18, 0.38), 0.0),
        ),
        ShapeFamily(
            "bicone",
            bicone,
            lambda s: float(max(s[0], s[1])),
            lambda u: (_lerp(u[0], 0.2, 0.4), _lerp(u[1], 0.2, 0.45), 0.0),
        ),
        ShapeFamily(
            "lens",
            lens,
            lambda s: float(s[0]),
            lambda u: (_lerp(u[0], 0.25, 0.5), _lerp(u[1], 0.08, 0.2), 0.0),
        ),
        # The generic families of the training-only ``wide`` split (lasagna.world.splits): size (bounding radius R,
        # code u, code v); the codes fix every other parameter (``_code``).
        ShapeFamily("gem", gem, lambda s: float(s[0]), lambda u: (_lerp(u[0], 0.3, 0.5), float(u[1]), float(u[2]))),
        ShapeFamily("blob", blob, lambda s: float(s[0]), lambda u: (_lerp(u[0], 0.3, 0.5), float(u[1]), float(u[2]))),
    )
}
SHAPE_NAMES: tuple[str, ...] = tuple(SHAPES)
MAX_BOUNDING_RADIUS = 0.6
FACING_TILT = math.radians(45.0)
"""How far from facing the camera a ``facing`` family (the panel) may turn."""
"""Largest bounding radius any family samples (box: √3·0.34 = 0.589); the scene keeps objects in front of
the wall with it."""
