"""The image input policy (lasagna.io.image): which formats are read and at what depth, against arrays
written by Pillow and tifffile; everything else (EPS, PDF, GIF, SVG) refused unopened, in one line."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
import tifffile
from PIL import Image

from lasagna.errors import ImageError, LasagnaError
from lasagna.io.image import read_image_file
from tests.support.bounded import cpu_seconds

RNG = np.random.default_rng(16)
BIG = 10**8


def _refused(path, **kw) -> str:
    with pytest.raises(ImageError) as info:
        read_image_file(path, max_pixels=kw.get("max_pixels", BIG))
    message = str(info.value)
    assert "\n" not in message and str(path) in message
    return message


EPS = b"%!PS-Adobe-3.0 EPSF-3.0\n%%BoundingBox: 0 0 10 10\n{ } loop\n"
PDF = b"%PDF-1.4\n1 0 obj << /Type /Catalog >> endobj\ntrailer << /Root 1 0 R >>\n%%EOF\n"
SVG = b'<svg xmlns="http://www.w3.org/2000/svg" width="10" height="10"><rect width="10" height="10"/></svg>\n'


@pytest.fixture
def no_subprocess(monkeypatch):
    """Fail the test if anything starts a process (Ghostscript is run through subprocess.Popen)."""

    def refuse(*args, **kwargs):
        raise AssertionError(f"a process was started: {args!r}")

    monkeypatch.setattr(subprocess, "Popen", refuse)
    monkeypatch.setattr(subprocess, "check_call", refuse)


@pytest.mark.parametrize("name, data", [("x.eps", EPS), ("x.ps", EPS), ("x.png", EPS), ("x.pdf", PDF), ("x.svg", SVG)])
def test_other_formats_are_refused_unopened(tmp_path, no_subprocess, name, data):
    path = tmp_path / name
    path.write_bytes(data)
    start = cpu_seconds()
    message = _refused(path)
    assert cpu_seconds() - start < 2  # CPU seconds (not wall: a loaded machine stretches that)
    assert "expected a PNG, JPEG, WebP, BMP or TIFF" in message


def test_eps_never_reaches_ghostscript(tmp_path, monkeypatch):
    from PIL import EpsImagePlugin

    calls = []
    monkeypatch.setattr(EpsImagePlugin, "Ghostscript", lambda *a, **k: calls.append(a))
    monkeypatch.setattr(EpsImagePlugin, "has_ghostscript", lambda: calls.append("probe") or True)
    path = tmp_path / "x.eps"
    path.write_bytes(EPS)
    _refused(path)
    assert calls == []


def test_gif_is_refused(tmp_path, no_subprocess):
    path = tmp_path / "x.gif"
    Image.new("P", (4, 4)).save(path)
    assert "not an image of a format lasagna reads" in _refused(path)


def test_16bit_gray_tiff(tmp_path):
    path = tmp_path / "i16.tif"
    Image.new("I;16", (64, 48), 30000).save(path)
    img = read_image_file(path, max_pixels=BIG)
    assert img.bit_depth == 16 and img.alpha is None and img.color.shape == (3, 48, 64)
    assert np.all(img.color == np.float32(30000) / np.float32(65535))


def test_float_tiff_in_range_and_out_of_range(tmp_path):
    path = tmp_path / "f.tif"
    Image.new("F", (8, 6), 0.4).save(path)
    img = read_image_file(path, max_pixels=BIG)
    assert img.bit_depth == 16 and np.allclose(img.color, 0.4, atol=1e-7)
    Image.new("F", (8, 6), 2.0).save(path)
    assert "span [2, 2]" in _refused(path) and "expected values in [0, 1]" in _refused(path)


@pytest.mark.parametrize("channels", [3, 4])
def test_16bit_rgb_and_rgba_tiff_keep_every_bit(tmp_path, channels):
    codes = RNG.integers(0, 65536, (9, 11, channels)).astype(np.uint16)
    codes[0, 0, 0] = 1  # a low byte only: Pillow would read it as 0
    path = tmp_path / "x.tif"
    tifffile.imwrite(path, codes, photometric="rgb", extrasamples=["unassalpha"] if channels == 4 else None)
    img = read_image_file(path, max_pixels=BIG)
    values = codes.astype(np.float32) / np.float32(65535)
    assert img.bit_depth == 16
    assert np.array_equal(img.color, values[:, :, :3].transpose(2, 0, 1))
    if channels == 4:
        assert np.array_equal(img.alpha[0], values[:, :, 3])
    else:
        assert img.alpha is None


def test_float_rgb_tiff_via_tifffile(tmp_path):
    values = RNG.random((5, 6, 3)).astype(np.float32)
    tifffile.imwrite(tmp_path / "x.tif", values, photometric="rgb")
    img = read_image_file(tmp_path / "x.tif", max_pixels=BIG)
    assert np.array_equal(img.color, values.transpose(2, 0, 1))
    tifffile.imwrite(tmp_path / "hdr.tif", values * 4, photometric="rgb")
    assert "expected values in [0, 1]" in _refused(tmp_path / "hdr.tif")


def test_8bit_lzw_tiff(tmp_path):
    codes = RNG.integers(0, 256, (7, 9, 3)).astype(np.uint8)
    Image.fromarray(codes).save(tmp_path / "x.tif", compression="tiff_lzw")
    img = read_image_file(tmp_path / "x.tif", max_pixels=BIG)
    assert img.bit_depth == 8 and np.array_equal(img.color, codes.transpose(2, 0, 1) / np.float32(255))


@pytest.mark.parametrize("fmt, exact", [("JPEG", False), ("WEBP", True), ("BMP", True)])
def test_jpeg_webp_bmp(tmp_path, fmt, exact):
    codes = np.full((8, 10, 3), 90, np.uint8)
    codes[:, 5:] = (200, 40, 10)
    path = tmp_path / f"x.{fmt.lower()}"
    Image.fromarray(codes).save(path, format=fmt, **({"lossless": True} if fmt == "WEBP" else {}))
    img = read_image_file(path, max_pixels=BIG)
    with Image.open(path) as im:
        ref = np.asarray(im.convert("RGB")).transpose(2, 0, 1) / np.float32(255)
    assert img.bit_depth == 8 and np.array_equal(img.color, ref)
    if exact:
        assert np.array_equal(img.color, codes.transpose(2, 0, 1) / np.float32(255))


def test_oversized_jpeg_is_refused_before_decoding(tmp_path, monkeypatch):
    path = tmp_path / "big.jpg"
    Image.new("RGB", (300, 200)).save(path)
    from PIL import ImageFile

    def no_load(self):
        raise AssertionError("decoded")

    monkeypatch.setattr(ImageFile.ImageFile, "load", no_load)
    assert "300x200 = 60000 pixels, over the limit of 1000" in _refused(path, max_pixels=1000)


def test_memory_budget_refuses_before_decoding(tmp_path):
    from lasagna.limits import BudgetError, memory_budget_scope

    Image.new("RGB", (300, 200)).save(tmp_path / "x.bmp")
    values = RNG.random((50, 40, 3)).astype(np.float32)
    tifffile.imwrite(tmp_path / "x.tif", values, photometric="rgb")
    for name, size in (("x.bmp", "300x200"), ("x.tif", "40x50")):
        with memory_budget_scope(10_000), pytest.raises(BudgetError) as info:
            read_image_file(tmp_path / name, max_pixels=BIG)
        # the refusal as it is, not wrapped in "cannot decode (BudgetError: …" and cut short (a bug once)
        assert f"decoding a {size} image needs" in str(info.value) and "cannot decode" not in str(info.value)


def test_missing_and_folder(tmp_path):
    with pytest.raises(LasagnaError, match="cannot read"):
        read_image_file(tmp_path / "nope.png", max_pixels=BIG)
    assert "is a folder" in _refused(tmp_path)


def test_a_jpeg_of_thousands_of_scans_is_refused_before_decoding(tmp_path, monkeypatch):
    """The progressive-JPEG DoS: decoding costs a pass per scan, so a file of 1000 scans is refused from its
    bytes; Pillow's load is never reached. A real progressive JPEG (10 scans) still reads."""
    import io

    from PIL import Image, ImageFile

    from lasagna.io.image import MAX_JPEG_SCANS, probe_image_file, read_image_file

    buf = io.BytesIO()
    Image.fromarray((np.random.default_rng(0).random((32, 32, 3)) * 255).astype(np.uint8)).save(
        buf, "JPEG", progressive=True
    )
    good = tmp_path / "good.jpg"
    good.write_bytes(buf.getvalue())
    assert read_image_file(good, max_pixels=10**6).color.shape == (3, 32, 32)
    data = buf.getvalue()
    last = data.rindex(b"\xff\xda")  # repeat the last scan segment until there are far too many
    bomb = tmp_path / "scans.jpg"
    bomb.write_bytes(data[:last] + data[last:-2] * 1000 + data[-2:])
    monkeypatch.setattr(ImageFile.ImageFile, "load", lambda self: pytest.fail("decoded"))
    for fn in (probe_image_file, read_image_file):
        with pytest.raises(ImageError, match=f"scans; expected at most {MAX_JPEG_SCANS}"):
            fn(bomb, max_pixels=10**6)


def _returns(fn, *args, **kw):
    """``fn(*args, **kw)`` in a daemon thread: (finished, its result or exception). A read that blocks forever
    (a FIFO no one writes) leaves the thread behind instead of the test."""
    import threading

    box: list = []

    def target():
        try:
            box.append(fn(*args, **kw))
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            box.append(exc)

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    thread.join(60)  # a hang guard, not a timing: the refusal takes milliseconds
    return (not thread.is_alive()), (box[0] if box else None)


@pytest.mark.parametrize("suffix", [".png", ".jpg", ".tif"])
def test_a_fifo_is_refused_without_blocking(tmp_path, suffix):
    """Issue #28 (3): a named pipe is not opened for reading (which would block until a writer came)."""
    import os

    from lasagna.io.image import probe_image_file

    fifo = tmp_path / f"pipe{suffix}"
    os.mkfifo(fifo)
    for read in (read_image_file, probe_image_file):
        finished, result = _returns(read, fifo, max_pixels=BIG)
        assert finished, f"{read.__name__} blocked on a FIFO"
        assert isinstance(result, LasagnaError), result
        expected = "expected an image file or a stack folder"
        assert str(result) == f"{fifo}: is not a regular file (a named pipe (FIFO)); {expected}"


def test_open_regular_refuses_devices_and_swaps(tmp_path, monkeypatch):
    """The type is checked before the open and again on the open descriptor (a name swapped in between)."""
    import os

    from lasagna import atomic
    from lasagna.atomic import open_regular
    from lasagna.errors import PathError

    with pytest.raises(PathError, match=r"^/dev/null: is not a regular file \(a character device\)"):
        open_regular("/dev/null")
    with pytest.raises(IsADirectoryError):
        open_regular(tmp_path)
    real, fifo = tmp_path / "real.png", tmp_path / "pipe"
    real.write_bytes(b"x")
    os.mkfifo(fifo)
    opened = os.open

    def swap(path, flags, *a):  # the stat saw a regular file; by the open the name is a FIFO
        return opened(fifo if os.fspath(path) == str(real) else path, flags, *a)

    monkeypatch.setattr(atomic.os, "open", swap)
    finished, result = _returns(open_regular, real)
    assert finished and isinstance(result, PathError) and "named pipe" in str(result)
    link = tmp_path / "link"
    link.symlink_to(real)
    monkeypatch.undo()
    with pytest.raises(PathError, match="symbolic link"):
        open_regular(link, follow_symlinks=False)
    with open_regular(link) as fh:
        assert fh.read() == b"x"


def _many_samples_tiff(path, side: int, samples: int):
    """A ``side``² uint8 TIFF of ``samples`` per pixel, zlib tiles of zeros, written tile by tile (never whole):
    2048² × 128 is 0.5 MB on disk and 512 MiB of samples (2.9 GB peak when decoded before the refusal)."""
    tile = np.zeros((256, 256, samples), np.uint8)
    tiles = (tile for _ in range((side // 256) ** 2))
    tifffile.imwrite(
        path, tiles, shape=(side, side, samples), dtype=np.uint8, tile=(256, 256), photometric="minisblack",
        planarconfig="contig", compression="zlib",
    )  # fmt: skip
    return path


@pytest.mark.parametrize("samples", [5, 128])
def test_many_samples_per_pixel_are_refused_from_the_header(tmp_path, samples):
    from lasagna.io.image import probe_image_file

    path = _many_samples_tiff(tmp_path / "wide.tif", 512, samples)
    for read in (read_image_file, probe_image_file):
        with pytest.raises(ImageError) as info:
            read(path, max_pixels=BIG)
        assert str(info.value) == (
            f"{path}: image has {samples} samples per pixel (from its header); expected 1 to 4 "
            "(gray, gray and alpha, RGB or RGBA)"
        )


def test_the_estimate_counts_every_sample(tmp_path):
    """The budget is checked with the samples the header states, not 4 (a 3-sample 16-bit TIFF costs more
    than an 8-bit one of the same size)."""
    from lasagna.io.image import decode_bytes
    from lasagna.limits import BudgetError, memory_budget_scope

    assert decode_bytes(100, 100, 4, 2) > decode_bytes(100, 100, 4, 1)
    assert decode_bytes(100, 100, 3, 4) > decode_bytes(100, 100, 3, 2)
    path = tmp_path / "rgb16.tif"
    tifffile.imwrite(path, np.zeros((64, 64, 3), np.uint16), photometric="rgb")
    with memory_budget_scope(decode_bytes(64, 64, 3, 2) - 1), pytest.raises(BudgetError):
        read_image_file(path, max_pixels=BIG)
    with memory_budget_scope(decode_bytes(64, 64, 3, 2)):
        assert read_image_file(path, max_pixels=BIG).color.shape == (3, 64, 64)


def test_a_2048_tiff_of_128_samples_is_refused_in_little_memory(tmp_path):
    """Issue #28 (6): refused from the header: the refusing process's peak stays far below the 512 MiB of samples
    (2.9 GB when it was decoded first)."""
    from tests.support.peak import run_python

    path = _many_samples_tiff(tmp_path / "wide.tif", 2048, 128)
    code, out, err, peak = run_python(
        "from lasagna.io.image import read_image_file\n"
        "try:\n"
        f"    read_image_file({str(path)!r}, max_pixels=2048 * 2048)\n"
        "except Exception as exc:\n"
        "    print(type(exc).__name__, exc)\n"
    )
    assert code == 0 and out.startswith("ImageError ") and "128 samples per pixel" in out, (out, err)
    assert peak < 500, f"peak {peak:.0f} MB"
