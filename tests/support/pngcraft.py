"""Hand-built PNG files for tests: raw chunks, so a test can make a file lie about itself.

Independent of ``lasagna.io.png``: chunks are assembled with ``struct`` and ``zlib`` only.
"""

from __future__ import annotations

import struct
import zlib


def chunk(kind: bytes, body: bytes, *, bad_crc: bool = False) -> bytes:
    crc = zlib.crc32(kind + body) ^ (1 if bad_crc else 0)
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)


def png_bytes(
    width: int, height: int, idat: bytes, *, depth: int = 8, color_type: int = 0, interlace: int = 0, extra: bytes = b""
) -> bytes:
    ihdr = struct.pack(">IIBBBBB", width, height, depth, color_type, 0, 0, interlace)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + extra + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def header_bomb(width: int = 100_000, height: int = 100_000) -> bytes:
    """A valid-looking RGBA PNG that claims ``width``×``height`` pixels with a few bytes of data."""
    return png_bytes(width, height, zlib.compress(b"\x00" * 64), color_type=6)


def idat_bomb(width: int = 16, height: int = 16, expands_to: int = 64 * 2**20) -> bytes:
    """A 16×16 gray PNG whose image data inflates to ``expands_to`` bytes (a zip bomb)."""
    return png_bytes(width, height, zlib.compress(b"\x00" * expands_to, 9))


def gray8(width: int, height: int, value: int = 128) -> bytes:
    """A correct 8-bit gray PNG of one value."""
    raw = (b"\x00" + bytes([value]) * width) * height
    return png_bytes(width, height, zlib.compress(raw))
