"""A 12 MP photograph through ``lasagna edit`` with no flags (issue 27): peak memory within 3 GB, and what it wrote
reads back (composite.png, the layer PNGs, stack.ora). Marked slow (~15 s and ~2 GB); no clock is asserted — the
time is measured by benchmarks/photos.py (docs/BENCHMARKS.md, "Photographs")."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from PIL import Image

from tests.support.tinylayers import ROOT

PEAK_LIMIT_BYTES = 3 * 10**9


@pytest.mark.slow
@pytest.mark.skipif(not Path("/usr/bin/time").exists(), reason="needs /usr/bin/time (GNU time) for the peak RSS")
def test_a_12_megapixel_edit_peaks_under_3_gb(tmp_path):
    photo = tmp_path / "photo-12mp.jpg"
    with Image.open(ROOT / "examples" / "photos" / "large" / "chelsea.jpg") as im:
        im.convert("RGB").resize((4000, 3000), Image.Resampling.LANCZOS).save(photo, quality=90)
    lasagna = shutil.which("lasagna", path=str(Path(sys.executable).parent)) or "lasagna"
    out = tmp_path / "out"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    env.pop("LASAGNA_LAYERS", None)  # the shipped catalogue, as a user has it
    cmd = ["/usr/bin/time", "-v", lasagna, "edit", str(photo), "--layer", "shading", "--condition", "left"]
    proc = subprocess.run([*cmd, "-o", str(out)], env=env, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    peak = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr).group(1)) * 1024
    print(f"\n12 MP edit: peak {peak / 1e9:.2f} GB")
    assert peak <= PEAK_LIMIT_BYTES
    with Image.open(out / "composite.png") as im:
        assert im.size == (4000, 3000) and im.mode == "RGB"
        im.load()
    with zipfile.ZipFile(out / "stack.ora") as zf:
        assert zf.testzip() is None
        with Image.open(zf.open("mergedimage.png")) as im:
            assert im.size == (4000, 3000)
