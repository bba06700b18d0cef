"""The one light that renders a multiplier from a normal map, read from the pixels (`lasagna.export.surface_import`).

A surface layer's rendered multiplier M over its normal map n (a file's pair, `lasagna.export.rasters`) is fitted:

* shading, M = a + (1 − a)·k·max(0, n·l): linear in (a, w = (1 − a)·k·l) over the lit pixels (n·w > 0), solved by
  least squares in float64 and the lit set updated until it stops changing (``FIT_ROUNDS``);
* a relight ratio, M = S(l)/S(l_s) with S = a + (1 − a)·max(0, n·l): where both lights light a pixel,
  a(M − 1) + M·n·u − n·v = 0 with u = (1 − a)·l_s, v = (1 − a)·l, homogeneous in (a, u, v) — the smallest right
  singular vector, scaled so |u| = 1 − a — with the lit sets updated likewise;
* a coloured light's shading (three channels), per channel, read as one light of a colour when the three fits agree
  on it (``COLOUR_AGREE_DEG``).

A fit is kept only if the layer it makes renders the multiplier back (`lasagna.compose.surface.surface_tensors`,
the compositor's own path) within ``MATCH_TOLERANCE`` at every pixel; a whole-degree direction, a named light, an
ambient of 0.25 and an intensity of 1 are preferred when they render as well (``SNAP_SLACK``).
"""

from __future__ import annotations

import math

import numpy as np

MATCH_TOLERANCE = 3.0 / 255.0
"""Largest difference at any pixel between the file's multiplier y and the fitted layer's render, over max(1, y)²:
three 8-bit codes — an 8-bit multiplier's rounding (half a code) and an 8-bit normal map's (up to about two codes of
shading where the map is steep), as a paint program that re-saves the file at 8 bits leaves them; above 1 the
multiply and colour-dodge pair that holds y, y = m/(1 − d), rounds in steps that grow as y². A stroke that changes
fewer codes than this is not seen."""
FIT_PIXELS = 65536
"""The fit reads about this many pixels of a larger layer (a regular subsample); the check reads all."""
FIT_ROUNDS = 8
"""Rounds of the lit set's update; the fit stops earlier when the set no longer changes."""
LIT_EPS = 1e-6
"""n·w above this counts as lit (a pixel on the terminator takes the ambient either way)."""
FACING_Z = (0.97, 0.9, 0.8)
"""The ratio fit's first round reads only normals this close to the view axis (within 14°, 26° or 37°: each a
start), which both lights light unless one grazes — the lit sets are not known before a first fit."""
MIN_FIT_PIXELS = 8
COLOUR_AGREE_DEG = 0.5
"""A coloured light's three channel fits must find one light within this many degrees of their mean."""
IDENTIFIABLE = 1e-4
"""A fit is made only when its system has one solution: the least singular value of the shading fit's design (the
second least of the ratio's, whose least is the solution's) above this share of the largest; a flat map, or a few
pixels, says nothing of the light, and a light that happens to render them is not read into the file."""
SNAP_SLACK = 1.0 / 255.0
"""A rounder light (whole degrees, a named light), ambient or intensity is kept when its largest error is no more
than this above the exact fit's."""


def fit_light(part, m: np.ndarray) -> tuple[str, dict | None]:
    """(why not, None) or ("", a surface layer's light fields: light, source_light, ambient, light_intensity and a
    colour's light_color) of the one light under which the normal map ``part`` (3, h, w, a tensor of codes in
    [0, 1]) renders the multiplier ``m`` ((C, h, w) float64, C 1 or 3), within ``MATCH_TOLERANCE`` at every pixel
    (module docstring)."""
    coloured = m.shape[0] == 3 and not (np.abs(m - m[:1]).max() <= MATCH_TOLERANCE)
    m = m if coloured else m.mean(0, keepdims=True)  # (C, h, w): three channels for a coloured light, else one
    from lasagna.compose.surface import decode_normal_map

    # The fit and the choice among rounder lights on a regular subsample (Lambert is per pixel, so the render of
    # a strided map is the strided render); the chosen layer is checked on every pixel.
    step = max(1, math.ceil(math.sqrt(m[0].size / FIT_PIXELS)))
    codes = part[:, ::step, ::step].contiguous()
    n = decode_normal_map(codes[None].double())[0].numpy()
    few = m[:, ::step, ::step]
    scored = []
    fits = [fit_coloured(n, few)] if coloured else [fit_shading(n, few[0]), fit_ratio(n, few[0])]
    for fit in fits:
        for candidate in [] if fit is None else _rounder(fit):
            err = _error(codes, candidate, few)
            if err is not None:
                scored.append((err, candidate))
    if not scored:
        return "no light fits (paint over it, cast shadows, a highlight, a point light or several lights)", None
    least = min(err for err, _ in scored)
    chosen = max(((_roundness(c), -err), i, c) for i, (err, c) in enumerate(scored) if err <= least + SNAP_SLACK)[2]
    err = _error(part.contiguous(), chosen, m)
    if err is None or err > MATCH_TOLERANCE:
        return (
            f"the best light's render is {(least if err is None else err) * 255:.1f} codes off (paint over it, cast "
            "shadows, a highlight, a point light or several lights)"
        ), None
    return "", {
        "light": _text(chosen["light"]),
        "source_light": None if chosen["source_light"] is None else _text(chosen["source_light"]),
        "ambient": float(chosen["ambient"]),
        "light_intensity": float(chosen["light_intensity"]),
        **({"light_color": list(chosen["light_color"])} if "light_color" in chosen else {}),
    }


def fit_shading(n: np.ndarray, m: np.ndarray) -> dict | None:
    """a, k, l of M = a + (1 − a)·k·max(0, n·l) by least squares over the lit set (module docstring)."""
    nf, mf = n.reshape(3, -1).T, m.reshape(-1)
    lit = mf > mf.min() + 1e-3
    for _ in range(FIT_ROUNDS):
        rows = np.concatenate([np.ones((mf.size, 1)), nf * lit[:, None]], 1)
        x, _, _, sv = np.linalg.lstsq(rows, mf, rcond=None)
        if sv[-1] <= IDENTIFIABLE * sv[0]:
            return None  # the lit normals do not span the light's three directions: many lights render it
        a, w = float(x[0]), x[1:]
        now = nf @ w > LIT_EPS
        if (now == lit).all():
            break
        lit = now
    norm = float(np.linalg.norm(w))
    if not (0.0 <= a < 1.0) or norm <= 1e-9 or w[2] <= 0.0:
        return None
    return {"light": _direction(w / norm), "ambient": a, "light_intensity": norm / (1.0 - a), "source_light": None}


def fit_coloured(n: np.ndarray, m: np.ndarray) -> dict | None:
    """a, k, c, l of a coloured light's shading M_c = a + (1 − a)·k·c_c·max(0, n·l) (``m`` (3, h, w)): each channel's
    shading fit, kept when the three agree on the light (within ``COLOUR_AGREE_DEG``) and the ambient (within 0.01);
    k the largest channel's gain, c the gains over it. A coloured relight ratio is not read (its source is white)."""
    fits = [fit_shading(n, channel) for channel in m]
    if any(f is None for f in fits):
        return None
    from lasagna.document.condition import unit_vector

    lights = [np.asarray(unit_vector(*f["light"])) for f in fits]
    mean = sum(lights) / np.linalg.norm(sum(lights))
    if min(float(v @ mean) for v in lights) < math.cos(math.radians(COLOUR_AGREE_DEG)):
        return None
    ambients = [f["ambient"] for f in fits]
    if max(ambients) - min(ambients) > 0.01:
        return None
    gains = [f["light_intensity"] for f in fits]
    k = max(gains)
    return {
        "light": _direction(mean),
        "source_light": None,
        "ambient": float(np.mean(ambients)),
        "light_intensity": k,
        "light_color": tuple(g / k for g in gains),
    }


def fit_ratio(n: np.ndarray, m: np.ndarray) -> dict | None:
    """a, l, l_s of M = S(l)/S(l_s): the homogeneous least squares of a(M − 1) + M·n·u − n·v = 0 (module
    docstring), the lit sets of u and v updated in turn; started from each of ``FACING_Z``'s sets of pixels facing
    the viewer, the start whose light renders M closest kept."""
    nf, mf = n.reshape(3, -1).T, m.reshape(-1)
    if mf.max() <= 1.0 + 1e-3 and mf.min() >= 1.0 - 1e-3:
        return None  # a flat ratio of one: no light to read
    best: tuple[float, tuple] | None = None
    for facing in FACING_Z:
        x = _ratio_from(nf, mf, nf[:, 2] > facing)
        if x is None:
            continue
        a, u, v = x
        model = (a + nf @ v * (nf @ v > 0)) / (a + nf @ u * (nf @ u > 0))
        err = float((np.abs(model - mf) / np.maximum(1.0, mf) ** 2).max())
        if best is None or err < best[0]:
            best = (err, x)
    if best is None:
        return None
    a, u, v = best[1]
    if min(u[2], v[2]) <= 0.0:
        return None  # a light from behind the surface is no layer's
    return {
        "light": _direction(v / np.linalg.norm(v)),
        "source_light": _direction(u / np.linalg.norm(u)),
        "ambient": a,
        "light_intensity": 1.0,
    }


def _ratio_from(nf: np.ndarray, mf: np.ndarray, use: np.ndarray) -> tuple[float, np.ndarray, np.ndarray] | None:
    """(a, u, v) of the ratio fit started from the pixels ``use`` (both lights taken to light them), or None when
    the start is too small or the fit leaves no valid ambient or light."""
    if use.sum() < MIN_FIT_PIXELS:
        return None
    lit_t = lit_s = use
    x = None
    for _ in range(FIT_ROUNDS):
        rows = np.concatenate([(mf - 1.0)[:, None], mf[:, None] * nf * lit_s[:, None], -nf * lit_t[:, None]], 1)
        _, sv, vt = np.linalg.svd(rows[use], full_matrices=False)
        if sv[-2] <= IDENTIFIABLE * sv[0]:
            break  # more than one solution: the normals do not tell both lights apart
        y = vt[-1]
        y = -y if y[0] < 0 else y  # the singular vector's sign is free; the ambient is positive
        scale = float(np.linalg.norm(y[1:4])) + float(y[0])
        if abs(scale) < 1e-12:
            break
        y = y / scale
        if not 0.0 < y[0] < 1.0:
            break
        x = y
        now_s, now_t = nf @ x[1:4] > LIT_EPS, nf @ x[4:7] > LIT_EPS
        if min(now_s.sum(), now_t.sum()) < MIN_FIT_PIXELS:
            break
        if use.all() and (now_s == lit_s).all() and (now_t == lit_t).all():
            break
        lit_s, lit_t, use = now_s, now_t, np.ones_like(use)
    if x is None or np.linalg.norm(x[1:4]) <= 1e-9 or np.linalg.norm(x[4:7]) <= 1e-9:
        return None
    return float(x[0]), x[1:4], x[4:7]


def _direction(vector: np.ndarray) -> tuple[float, float]:
    """(az, el) in degrees of a unit vector, as `lasagna.document.condition.unit_vector` writes them."""
    x, y, z = (float(c) for c in vector)
    return math.degrees(math.atan2(y, x)) % 360.0, math.degrees(math.acos(max(-1.0, min(1.0, z))))


def _text(direction: tuple[float, float] | str) -> str:
    if isinstance(direction, str):
        return direction
    az, el = direction
    return f"az={az:.6g},el={el:.6g}"


def _rounder(fields: dict) -> list[dict]:
    """The exact fit and the rounder versions of it worth trying (whole degrees, a named light, ambient 0.25,
    intensity 1), the exact one first."""
    from lasagna.document.condition import NAMED_DIRECTIONS, unit_vector

    def named_or_whole(direction):
        if direction is None:
            return [None]
        az, el = direction
        out = [(round(az, 2) % 360.0, round(el, 2)), (float(round(az)) % 360.0, float(round(el)))]
        near = unit_vector(az, el)
        for name, d in NAMED_DIRECTIONS.items():
            if float(np.dot(unit_vector(*d), near)) > math.cos(math.radians(0.5)):
                out.append(name)
        return out

    ambients = [fields["ambient"], round(fields["ambient"], 2), round(fields["ambient"], 3)]
    gains = [fields["light_intensity"], round(fields["light_intensity"], 2), round(fields["light_intensity"], 3)]
    colours = [None] if "light_color" not in fields else [fields["light_color"]]
    if "light_color" in fields:
        colours += [
            tuple(round(c, 2) for c in fields["light_color"]),
            tuple(round(c, 3) for c in fields["light_color"]),
        ]
    out = [fields]
    for light in named_or_whole(fields["light"]):
        for source in named_or_whole(fields["source_light"]):
            for a in ambients:
                for k in gains:
                    for colour in colours:
                        rounder = {"light": light, "source_light": source, "ambient": a, "light_intensity": k}
                        out.append(rounder if colour is None else {**rounder, "light_color": colour})
    return out


def _roundness(fields: dict) -> int:
    """How round a fit's values are: a shading rather than a ratio, named lights (two) or whole degrees (one), an
    ambient and an intensity of two decimals each count."""
    lights = [fields["light"]] + ([] if fields["source_light"] is None else [fields["source_light"]])
    score = int(fields["source_light"] is None)
    score += int(round(fields["ambient"], 2) == fields["ambient"]) + int(
        round(fields["light_intensity"], 2) == fields["light_intensity"]
    )
    score += int(all(round(c, 2) == c for c in fields.get("light_color", ())))
    for light in lights:
        score += 2 if isinstance(light, str) else int(all(float(v).is_integer() for v in light))
    return score


def _error(codes, fields: dict, m: np.ndarray) -> float | None:
    """The largest difference between ``m`` and the surface layer of ``fields`` rendered from the map ``codes``
    (3, h, w) by the compositor's own path; None when the fields are no valid layer."""
    from lasagna.compose.layer import LayerTensors
    from lasagna.compose.surface import surface_tensors
    from lasagna.document.condition import parse_direction
    from lasagna.errors import LasagnaError

    try:
        light = _text(fields["light"])
        source = None if fields["source_light"] is None else _text(fields["source_light"])
        parse_direction(light)
        if source is not None:
            parse_direction(source)
        colour = tuple(float(c) for c in fields.get("light_color", (1.0, 1.0, 1.0)))
        if not 0.0 <= fields["ambient"] < 1.0 or not 0.0 < fields["light_intensity"] <= 16.0:
            return None
        if not all(0.0 <= c <= 1.0 for c in colour):
            return None
        rendered = surface_tensors(
            LayerTensors(codes, None, None),
            light,
            source,
            float(fields["ambient"]),
            1.0,
            colour,
            float(fields["light_intensity"]),
        ).color
    except (LasagnaError, ValueError):
        return None
    # Above 1 a multiplier is a multiply and colour-dodge pair in the file, y = m/(1 − d), whose rounding grows
    # as y²: the difference is measured in the pair's own steps.
    # ``m`` is (C, h, w); a white light renders one channel, a coloured one three (broadcast against each other).
    return float((np.abs(rendered.double().numpy() - m) / np.maximum(1.0, m) ** 2).max())


__all__ = ["MATCH_TOLERANCE", "fit_coloured", "fit_light", "fit_ratio", "fit_shading"]
