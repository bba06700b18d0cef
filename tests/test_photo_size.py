"""Photographs as they come off a phone (issue 27): the memory budget refuses an edit, not a pixel cap; every
phase of a long edit reports on stderr when asked."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from lasagna.cli import main
from lasagna.io.image import DEFAULT_EDIT_MAX_PIXELS, check_edit_memory, edit_bytes
from lasagna.limits import DEFAULT_MEMORY_BUDGET, BudgetError, memory_budget_scope


def test_24_megapixels_fit_the_default_budget():
    assert DEFAULT_EDIT_MAX_PIXELS >= 6000 * 4000  # no pixel cap below a 24 MP photo
    assert edit_bytes(6000, 4000) <= DEFAULT_MEMORY_BUDGET
    check_edit_memory(6000, 4000, "photo.jpg")  # passes under the default budget


def test_the_budget_refuses_a_larger_photo():
    with pytest.raises(BudgetError, match=r"editing a 9000x6000 image needs ~.*over the memory budget of 8.0 GB"):
        check_edit_memory(9000, 6000, "photo.jpg")
    with memory_budget_scope("1G"), pytest.raises(BudgetError, match="over the memory budget of 1.0 GB"):
        check_edit_memory(4000, 3000, "photo.jpg")


def _png_header(width: int, height: int) -> bytes:
    """A PNG of ``width`` × ``height`` RGB by its header, with no pixels: refused before decoding, or invalid."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"")) + chunk(b"IEND", b"")


def test_cli_refuses_by_the_budget_before_decoding(tmp_path, capsys):
    big = tmp_path / "big.png"
    big.write_bytes(_png_header(12_000, 8_000))  # 96 MP by its header: decoded it would be ~27 GB
    code = main(["edit", str(big), "--condition", "left", "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1
    assert "over the memory budget" in err and "over the limit" not in err
    assert not (tmp_path / "out").exists()


def test_cli_reports_each_long_phase_with_progress(tmp_path, capsys, monkeypatch):
    import lasagna.cli.common as common

    monkeypatch.setattr(common, "PHASE_QUIET_SECONDS", 0.0)  # every phase counts as long
    photo = tmp_path / "photo.jpg"
    Image.fromarray(np.random.default_rng(0).integers(0, 256, (40, 56, 3), dtype=np.uint8)).save(photo)
    out = tmp_path / "out"
    code = main(["edit", str(photo), "--condition", "left", "--steps", "2", "-o", str(out), "--progress"])
    err = capsys.readouterr().err
    assert code == 0, err
    for what in ("reading photo.jpg", "making the layer", "encoding composite.png", "encoding stack.ora"):
        assert any(line.startswith(f"lasagna: {what}") and " done in " in line for line in err.splitlines()), what


def test_no_progress_into_a_file_without_the_flag(tmp_path, capsys, monkeypatch):
    import lasagna.cli.common as common

    monkeypatch.setattr(common, "PHASE_QUIET_SECONDS", 0.0)
    photo = tmp_path / "photo.jpg"
    Image.fromarray(np.full((24, 32, 3), 128, np.uint8)).save(photo)
    code = main(["edit", str(photo), "--condition", "left", "--steps", "2", "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 0 and err == ""
