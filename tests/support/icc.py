"""A Display P3 ICC profile written from its definition (no profile file needed), and the independent float64
conversion of Display P3 codes to sRGB codes that the colour-managed reader is compared with.

Display P3: the DCI-P3 primaries, the D65 white and the sRGB transfer curve (Apple's definition). An ICC v2
matrix/TRC display profile states its primaries in the D50 connection space (Bradford-adapted, ICC.1 Annex E),
its curve as a 4096-entry table of the sRGB EOTF.
"""

from __future__ import annotations

import struct

import numpy as np

D65 = (0.3127, 0.3290)
P3 = ((0.680, 0.320), (0.265, 0.690), (0.150, 0.060))
SRGB = ((0.640, 0.330), (0.300, 0.600), (0.150, 0.060))
D50_XYZ = np.array([0.9642, 1.0, 0.8249])
BRADFORD = np.array([[0.8951, 0.2664, -0.1614], [-0.7502, 1.7135, 0.0367], [0.0389, -0.0685, 1.0296]])


def _xyz(xy) -> np.ndarray:
    x, y = xy
    return np.array([x / y, 1.0, (1 - x - y) / y])


def rgb_to_xyz(primaries, white=D65) -> np.ndarray:
    """The 3×3 matrix of linear RGB → XYZ (Y of white = 1)."""
    m = np.stack([_xyz(p) for p in primaries], axis=1)
    return m * np.linalg.solve(m, _xyz(white))


def srgb_eotf(v: np.ndarray) -> np.ndarray:
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def srgb_oetf(v: np.ndarray) -> np.ndarray:
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(np.maximum(v, 0.0031308), 1 / 2.4) - 0.055)


def p3_to_srgb_codes(codes: np.ndarray) -> np.ndarray:
    """(…, 3) uint8 Display P3 codes → uint8 sRGB codes: linear P3 → XYZ → linear sRGB, clipped to the gamut."""
    lin = srgb_eotf(codes.astype(np.float64) / 255.0)
    m = np.linalg.solve(rgb_to_xyz(SRGB), rgb_to_xyz(P3))
    out = np.clip(lin @ m.T, 0.0, 1.0)
    return np.rint(srgb_oetf(out) * 255.0).astype(np.uint8)


def _s15(v: float) -> bytes:
    return struct.pack(">i", int(round(v * 65536)))


def _xyz_tag(xyz) -> bytes:
    return b"XYZ " + b"\0" * 4 + b"".join(_s15(v) for v in xyz)


def _desc_tag(text: str) -> bytes:
    a = text.encode("ascii") + b"\0"
    return b"desc" + b"\0" * 4 + struct.pack(">I", len(a)) + a + b"\0" * 4 + b"\0" * 4 + b"\0" * 3 + b"\0" * 67


def _curve_tag() -> bytes:
    table = np.rint(srgb_eotf(np.linspace(0.0, 1.0, 4096)) * 65535).astype(">u2").tobytes()
    return b"curv" + b"\0" * 4 + struct.pack(">I", 4096) + table


def display_p3_profile() -> bytes:
    """An ICC v2 display profile of Display P3 (module docstring)."""
    adapt = np.linalg.inv(BRADFORD) @ np.diag((BRADFORD @ D50_XYZ) / (BRADFORD @ _xyz(D65))) @ BRADFORD
    m = adapt @ rgb_to_xyz(P3)  # columns: the primaries in D50
    curve = _curve_tag()
    tags = [
        (b"desc", _desc_tag("Display P3 (test)")),
        (b"wtpt", _xyz_tag(D50_XYZ)),
        (b"rXYZ", _xyz_tag(m[:, 0])),
        (b"gXYZ", _xyz_tag(m[:, 1])),
        (b"bXYZ", _xyz_tag(m[:, 2])),
        (b"rTRC", curve),
        (b"gTRC", curve),
        (b"bTRC", curve),
        (b"cprt", b"text" + b"\0" * 4 + b"No copyright\0"),
    ]
    offset = 128 + 4 + 12 * len(tags)
    table, data = [], b""
    for sig, body in tags:
        while (offset + len(data)) % 4:
            data += b"\0"
        table.append(struct.pack(">4sII", sig, offset + len(data), len(body)))
        data += body
    body = struct.pack(">I", len(tags)) + b"".join(table) + data
    size = 128 + len(body)
    header = (
        struct.pack(">I", size)
        + b"none"
        + struct.pack(">I", 0x02100000)
        + b"mntrRGB XYZ "
        + struct.pack(">6H", 2026, 1, 1, 0, 0, 0)
        + b"acsp"
        + b"\0" * 24
        + struct.pack(">I", 0)  # perceptual
        + b"".join(_s15(v) for v in D50_XYZ)
        + b"\0" * 48
    )
    assert len(header) == 128
    return header + body
