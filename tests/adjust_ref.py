"""Float64 numpy references of the adjustments (``lasagna.compose.adjust``), written from the formulas directly
(per pixel, no tables): psd-tools' ``composite/adjustments.py`` in continuous form, the natural cubic spline by its
textbook tridiagonal system, HSL by the standard hexcone cases; colour balance per pixel as GIMP's C code reads
(lightness and its restoration through Python's ``colorsys``), black & white by sorting each pixel's channels, the
gradient map by walking its stops."""

from __future__ import annotations

import numpy as np


def _spline(xs, ys, t):
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    n = len(xs)
    m = np.zeros(n)
    if n > 2:
        h = np.diff(xs)
        a = np.zeros((n - 2, n - 2))
        for i in range(n - 2):
            a[i, i] = 2 * (h[i] + h[i + 1])
            if i:
                a[i, i - 1] = h[i]
            if i < n - 3:
                a[i, i + 1] = h[i + 1]
        s = np.diff(ys) / h
        m[1:-1] = np.linalg.solve(a, 6 * np.diff(s))
    t = np.clip(t, xs[0], xs[-1])
    k = np.clip(np.searchsorted(xs, t, side="right") - 1, 0, n - 2)
    h = xs[k + 1] - xs[k]
    u, v = (xs[k + 1] - t) / h, (t - xs[k]) / h
    return u * ys[k] + v * ys[k + 1] + ((u**3 - u) * m[k] + (v**3 - v) * m[k + 1]) * h**2 / 6


def _levels(x, c):
    t = np.clip((x - c["in_black"]) / (c["in_white"] - c["in_black"]), 0, 1) ** (1 / c["gamma"])
    return np.clip(c["out_black"] + t * (c["out_white"] - c["out_black"]), 0, 1)


def _curve(x, pts):
    pts = np.asarray(pts, float)
    return np.clip(_spline(pts[:, 0], pts[:, 1], x), 0, 1)


def _per_channel(C, p, f):
    out = C.copy()
    for i, name in enumerate(("red", "green", "blue")):
        if p.get(name) is not None:
            out[i] = f(C[i], p[name])
    return f(out, p["rgb"]) if p.get("rgb") is not None else out


def _bc(x, p):
    b, c = p["brightness"], p["contrast"]
    if p.get("legacy"):
        k = 1 + c / 100 if c <= 0 else 1 / max(1 - c / 100, 1 / 255)
        return np.clip((x + b / 255 - 0.5) * k + 0.5, 0, 1)
    b, c = b / 150, c / 100
    t = np.linspace(0, 1, 65536)
    cx = np.array([0, 63 / 255, 191 / 255, 1])
    con = _spline(cx, [0, cx[1] - c * 25 / 255, cx[2] + c * 25 / 255, 1], t)
    a, r = (1.65, -1.0, 1.96, 1.0, 1.0), (0.35, 10.0, 0.4, 4.0, 1.25)
    pol = [a[i] * t ** r[i] for i in range(5)]
    h = 0.5 * (abs(b) * (pol[0] + pol[1]) + (1 - abs(b)) * (pol[2] + pol[3]) + pol[4])
    bs = b * t * (1 - t) * h
    return np.clip(np.interp(x, t, np.clip(np.interp(t, t - bs, con + bs), 0, 1)), 0, 1)


def _rgb_to_hsl(C):
    r, g, b = C
    mx, mn = C.max(0), C.min(0)
    d = mx - mn
    L = (mx + mn) / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        S = np.where(d > 1e-12, d / np.maximum(1 - np.abs(2 * L - 1), 1e-12), 0)
        h = np.where(mx == r, ((g - b) / d) % 6, np.where(mx == g, (b - r) / d + 2, (r - g) / d + 4))
    return np.where(d > 1e-12, h / 6, 0), S, L


def _hsl_to_rgb(H, S, L):
    c = (1 - np.abs(2 * L - 1)) * S
    h6 = (H % 1) * 6
    x = c * (1 - np.abs(h6 % 2 - 1))
    z = np.zeros_like(c)
    sector = np.floor(h6).astype(int) % 6
    table = [(c, x, z), (x, c, z), (z, c, x), (z, x, c), (x, z, c), (c, z, x)]
    out = np.zeros((3, *c.shape))
    for s, rgb in enumerate(table):
        for i in range(3):
            out[i] = np.where(sector == s, rgb[i], out[i])
    return out + (L - c / 2)


def _lighten(x, light):
    if light > 0:
        return np.clip(x * (1 - light) + light, 0, 1)
    return np.clip(x * (1 + light), 0, 1)


def _hue_saturation(C, p):
    col = p.get("colorize")
    if col is not None:
        _, _, L = _rgb_to_hsl(C)
        L = _lighten(L, col["lightness"] / 100)
        return np.clip(
            _hsl_to_rgb(np.full_like(L, col["hue"] / 360 % 1), np.full_like(L, col["saturation"] / 100), L), 0, 1
        )
    C = _lighten(C, p["lightness"] / 100)
    ranges = [r for r in p.get("ranges") or () if (r["hue"], r["saturation"], r["lightness"]) != (0, 0, 0)]
    if ranges:
        return _hue_ranges(C, p, ranges)
    H, S, L = _rgb_to_hsl(C)
    s = p["saturation"] / 100
    if s:
        S = np.clip(S / (1 - s + 1e-2) if s > 0 else S * (1 + s), 0, 1)
    return np.clip(_hsl_to_rgb(H + p["hue"] / 360, S, L), 0, 1)


def _lum(C):
    return 0.3 * C[0] + 0.59 * C[1] + 0.11 * C[2]


def _set_lum(C, lum):
    """W3C Compositing Level 1, section 10.3: SetLum with ClipColor, per pixel."""
    C = C + (lum - _lum(C))
    L, n, x = _lum(C), C.min(0), C.max(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        C = np.where(n < 0, L + (C - L) * L / (L - n), C)
        C = np.where(x > 1, L + (C - L) * (1 - L) / (x - L), C)
    return C


def _channel_mixer(C, p):
    rows = [p["gray"]] * 3 if p.get("gray") is not None else [p["red"], p["green"], p["blue"]]
    return np.clip(np.stack([(r[0] * C[0] + r[1] * C[1] + r[2] * C[2] + r[3]) / 100 for r in rows]), 0, 1)


def _color_balance(C, p):
    # GIMP 2.10, gimp_operation_color_balance_map, one pixel at a time.
    out = np.empty_like(C)
    for i in np.ndindex(C.shape[1:]):
        px = C[(slice(None), *i)]
        light = (px.max() + px.min()) / 2
        ws = min(max((light - 0.333) / -0.25 + 0.5, 0), 1) * 0.7
        wm = min(max((light - 0.333) / 0.25 + 0.5, 0), 1) * min(max((light + 0.333 - 1) / -0.25 + 0.5, 0), 1) * 0.7
        wh = min(max((light + 0.333 - 1) / 0.25 + 0.5, 0), 1) * 0.7
        v = np.clip(
            px + (np.array(p["shadows"]) * ws + np.array(p["midtones"]) * wm + np.array(p["highlights"]) * wh) / 100,
            0,
            1,
        )
        if p["preserve_luminosity"]:
            import colorsys

            h, _, s = colorsys.rgb_to_hls(*v)
            v = np.array(colorsys.hls_to_rgb(h, light, s))
        out[(slice(None), *i)] = v
    return out


def _black_and_white(C, p):
    out = np.empty_like(C)
    primary = {0: p["reds"], 1: p["greens"], 2: p["blues"]}
    secondary = {frozenset((0, 1)): p["yellows"], frozenset((1, 2)): p["cyans"], frozenset((0, 2)): p["magentas"]}
    for i in np.ndindex(C.shape[1:]):
        px = C[(slice(None), *i)]
        order = np.argsort(-px, kind="stable")
        mx, mid, mn = px[order]
        gray = mn + (mx - mid) * primary[order[0]] / 100 + (mid - mn) * secondary[frozenset(order[:2])] / 100
        out[(slice(None), *i)] = min(max(gray, 0), 1)
    if p.get("tint") is None:
        return out
    tint = np.broadcast_to(np.array(p["tint"], float)[:, None, None], C.shape)
    return np.clip(_set_lum(tint, out[0]), 0, 1)


def _gradient_map(C, p):
    stops = p["stops"]
    t = _lum(C)
    if p["reverse"]:
        t = 1 - t
    out = np.empty_like(C)
    for i in np.ndindex(t.shape):
        x = t[i]
        if x <= stops[0]["location"]:
            out[(slice(None), *i)] = stops[0]["color"]
            continue
        if x >= stops[-1]["location"]:
            out[(slice(None), *i)] = stops[-1]["color"]
            continue
        for a, b in zip(stops, stops[1:]):
            if a["location"] <= x < b["location"]:
                u, m = (x - a["location"]) / (b["location"] - a["location"]), a["midpoint"]
                f = 0.5 * u / m if u <= m else 0.5 + 0.5 * (u - m) / (1 - m)
                out[(slice(None), *i)] = np.array(a["color"]) + f * (np.array(b["color"]) - np.array(a["color"]))
                break
    return out


def _photo_filter(C, p):
    F = np.array(p["color"], float)[:, None, None]
    out = C + p["density"] / 100 * (C * F - C)
    if p["preserve_luminosity"]:
        out = _set_lum(out, _lum(C))
    return np.clip(out, 0, 1)


def _vibrance(C, p):
    H, S, L = _rgb_to_hsl(C)
    s, v = p["saturation"] / 100, p["vibrance"] / 100
    if s:
        S = np.clip(S / (1 - s + 1e-2) if s > 0 else S * (1 + s), 0, 1)
    S = np.clip(S + v * S * (1 - S), 0, 1)
    return np.clip(_hsl_to_rgb(H, S, L), 0, 1)


def _trapezoid(h, corners):
    bl, tl, tr, br = (c / 360 for c in corners)
    x, left, center, right = (h - bl) % 1, (tl - bl) % 1, (tr - bl) % 1, (br - bl) % 1
    if left <= x <= center:
        return 1.0
    if x < left:
        return x / left if left > 1e-12 else 0.0
    if x <= right:
        return (right - x) / (right - center) if right - center > 1e-12 else 0.0
    return 0.0


def _hue_ranges(C, p, ranges):
    """psd-tools' _huesaturation with colour ranges, one pixel at a time through colorsys (HSV and HLS), saturation
    contributions added (Lasagna's stated combination where ranges overlap)."""
    import colorsys

    def sat(x, s):
        return min(max(x / (1 - s + 1e-2) if s > 0 else x * (1 + s), 0), 1)

    out = np.empty_like(C)
    for i in np.ndindex(C.shape[1:]):
        px = C[(slice(None), *i)]
        h, _, _ = colorsys.rgb_to_hls(*px)
        if px.max() - px.min() <= 1e-12:
            h = 0.0
        rh = rs = rl = 0.0
        for r in ranges:
            m = _trapezoid(h, r["range"])
            s_ = r["saturation"] / 100
            rh += r["hue"] / 360 * m
            rl = min(max(rl + r["lightness"] / 100 * m, -1), 1)
            if s_:
                rs += s_ * (1 - (1 - m) ** (1.5 / (1 - s_**4 + 0.05))) if s_ > 0 else s_ * m
                rs = min(max(rs, -1), 1)
        _, sv, v = colorsys.rgb_to_hsv(*px)
        if rl < 0:
            v = min(max(v * (1 + rl * sv), 0), 1)
            inv = 1 / (sv + 1e-3)
            sv = min(max(1 + (inv - 1) / (abs(rl) - inv + 1e-3), 0), 1)
        else:
            sv = min(max(sv * (1 - rl), 0), 1)
        light = v * (1 - sv / 2)
        den = min(light, 1 - light)
        s_l = (v - light) / den if den > 1e-12 else 0.0
        s_l = sat(sat(s_l, p["saturation"] / 100), rs)
        out[(slice(None), *i)] = colorsys.hls_to_rgb((h + rh + p["hue"] / 360) % 1, light, s_l)
    return np.clip(out, 0, 1)


def adjust_reference(adjustment: dict, C: np.ndarray) -> np.ndarray:
    """The adjusted colour of ``C`` (3, h, w) float64 in [0, 1]."""
    p, kind = adjustment, adjustment["type"]
    C = np.clip(np.asarray(C, dtype=np.float64), 0, 1)
    if kind == "levels":
        return _per_channel(C, p, _levels)
    if kind == "curves":
        return _per_channel(C, p, _curve)
    if kind == "brightness-contrast":
        return _bc(C, p)
    if kind == "exposure":
        x = np.clip(C**2.2 * 2.0 ** p["exposure"] + p["offset"], 0, 1)
        return x ** (1 / (p["gamma"] * 2.2))
    if kind == "invert":
        return 1 - C
    if kind == "posterize":
        n, codes = p["levels"], 2.0 ** p.get("bits", 8)
        return np.floor(C * n * (codes - 1) / codes) / (n - 1)
    if kind == "threshold":
        lum = 0.3 * C[0] + 0.59 * C[1] + 0.11 * C[2]
        return np.repeat((lum >= p["level"])[None].astype(float), 3, axis=0)
    if kind == "hue-saturation":
        return _hue_saturation(C, p)
    others = {
        "channel-mixer": _channel_mixer,
        "color-balance": _color_balance,
        "vibrance": _vibrance,
        "black-and-white": _black_and_white,
        "gradient-map": _gradient_map,
        "photo-filter": _photo_filter,
    }
    if kind in others:
        return others[kind](C, p)
    raise ValueError(f"unknown adjustment {kind!r}")
